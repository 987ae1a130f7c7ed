"""How the replay tools print their reports: text lines, or one JSON object (``--json``)."""

from __future__ import annotations

import json
from typing import Any, Protocol, TextIO


class Report(Protocol):
    def to_dict(self) -> dict[str, Any]: ...

    def format(self) -> list[str]: ...


def write_report(report: Report, as_json: bool, out: TextIO) -> None:
    """``report`` on ``out``: its ``format()`` lines, or its ``to_dict()`` as indented JSON."""
    if as_json:
        json.dump(report.to_dict(), out, indent=2)
        out.write("\n")
    else:
        for line in report.format():
            out.write(line + "\n")
