"""Words in the tools' output: a count with its noun in the right number."""

from __future__ import annotations

__all__ = ["plural"]


def plural(n: int, noun: str, nouns: str | None = None) -> str:
    """``n`` and its noun: ``1 log``, ``2 logs``, ``0 logs`` (``nouns``: an irregular plural).

    >>> plural(1, "session"), plural(3, "bus silence"), plural(2, "entry", "entries")
    ('1 session', '3 bus silences', '2 entries')
    """
    return f"{n} {noun if n == 1 else (nouns or noun + 's')}"
