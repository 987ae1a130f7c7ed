"""One exception tree for start-up and tooling errors.

In the control loop faults become state (watchdogs, safety gate); these exceptions belong to
start-up, configuration, file parsing and command-line tools.
"""


class LeafgateError(Exception):
    """Base of every error leafgate raises on purpose."""


class ConfigError(LeafgateError):
    """A configuration file is missing, unreadable or holds a bad key or value."""


class UsageError(ConfigError):
    """The command line asks for what cannot be: options that do not go together, a bad value
    of one. Its message names the options, never the config file (which is not at fault)."""


class TrajectoryError(LeafgateError):
    """A trajectory file or message is malformed (the message names the row)."""


class CanCodecError(LeafgateError):
    """A CAN database could not be loaded or a frame could not be encoded."""


class BusError(LeafgateError):
    """A CAN bus could not be opened."""


class TransportError(LeafgateError):
    """The Zenoh session could not be opened or a payload codec is misconfigured."""


class ReplayError(LeafgateError):
    """A recorded log or session could not be read."""


class PayloadError(TransportError):
    """A payload could not be decoded (truncated, malformed, wrong type or bad values).

    Raised inside the codecs only; subscribers catch it, count it per key and drop the sample.
    """


class InjectionError(LeafgateError, ValueError):
    """An injected driver action or fault (simulator) is unknown or has bad parameters."""


# leafgate.can.codec.EncodeError(CanCodecError, cantools.database.EncodeError) stays beside the
# codec: it also derives from cantools' class, and this module imports nothing.
