"""leafgate: drive-by-wire gateway for automated low-speed driving of a Nissan Leaf."""

__version__ = "0.1.0"
