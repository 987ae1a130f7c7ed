"""The fault-injection results as a Markdown table.

Run the fault suite with ``LEAFGATE_FAULT_REPORT=faults.jsonl`` set (each test appends one JSON
line: fault, detected, state, reason, reaction_s, safe_state_s, frames_missing, and the
gateway's ENABLE=1 command frames judged against the safety limits at the plant's true speed
and wheel angle from the simulated ECU's trace: commands_outside_limits of commands_checked),
then::

    python tools/fault_table.py faults.jsonl

A fault run more than once (the file is appended to) shows its last line.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

COLUMNS = (
    ("fault", "fault"),
    ("detected", "detected"),
    ("state", "final state"),
    ("reason", "reason"),
    ("reaction_s", "reaction [s]"),
    ("safe_state_s", "to rest [s]"),
    ("frames_missing", "frames missing (CAN log / session)"),
    ("commands_outside_limits", "commands outside limits (true state) / judged"),
)


def load(path: Path) -> list[dict[str, Any]]:
    """The outcomes in file order, the last line per fault kept.

    :raises SystemExit: a line is not a JSON object (names the line)
    """
    rows: dict[str, dict[str, Any]] = {}
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError as exc:
            raise SystemExit(f"{path}:{number}: not JSON: {exc.msg}") from None
        if not isinstance(row, dict) or "fault" not in row:
            raise SystemExit(f"{path}:{number}: expected an object with a 'fault' key")
        rows.pop(str(row["fault"]), None)  # a re-run moves the fault to its latest place
        rows[str(row["fault"])] = row
    return list(rows.values())


def cell(key: str, row: dict[str, Any]) -> str:
    value = row.get(key)
    if key == "detected":
        return "yes" if value else "no"
    if key == "frames_missing":
        session = row.get("frames_missing_session")
        log = "–" if value is None else str(value)
        return log if session is None else f"{log} / {session}"
    if key == "commands_outside_limits":
        judged = row.get("commands_checked")
        return "–" if value is None else f"{value} / {judged}"
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.3f}"
    return str(value).replace("|", "\\|")


def table(rows: list[dict[str, Any]]) -> str:
    head = "| " + " | ".join(title for _, title in COLUMNS) + " |"
    rule = "|" + "|".join("---" for _ in COLUMNS) + "|"
    body = ["| " + " | ".join(cell(key, row) for key, _ in COLUMNS) + " |" for row in rows]
    return "\n".join([head, rule, *body])


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: python tools/fault_table.py RESULTS.jsonl", file=sys.stderr)
        return 2
    path = Path(argv[0])
    if not path.is_file():
        print(f"fault_table: {path}: no such file", file=sys.stderr)
        return 2
    print(table(load(path)))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
