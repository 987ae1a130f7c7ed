"""README.md's ``sh`` blocks work when pasted as written, in order (issue 19, item 1).

``tools/readme_check.py`` runs them in a fresh copy of the repository; the slow test here runs
it once (``python tools/readme_check.py --repeat 10`` for the ten runs in a row).
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import readme_check  # noqa: E402


def test_blocks_markers_and_headings() -> None:
    text = """# Top
<!-- readme-check: skip (needs can0) -->
```sh
ip link set can0 up
```
## Two
```text
not a shell block
```
<!-- readme-check: expect ENGAGED -->
<!-- readme-check: slow (minutes) -->
```sh
leafgate engage --config x
```
```sh
echo plain
```
"""
    blocks = readme_check.blocks(text)
    assert [(b.line, b.heading) for b in blocks] == [(3, "Top"), (12, "Two"), (15, "Two")]
    assert blocks[0].skip == "needs can0" and not blocks[0].slow
    assert blocks[1].expect == ["ENGAGED"] and blocks[1].slow == "minutes"
    assert not blocks[2].skip and not blocks[2].slow and not blocks[2].expect


def test_install_lines_keep_what_follows_them() -> None:
    block = readme_check.Block(
        1,
        "x",
        "python3 -m venv .venv && .venv/bin/pip install . && .venv/bin/leafgate sim\n"
        "python3 -m venv .venv && .venv/bin/pip install -e '.[dev]'\n"
        "leafgate decode a.log | head\n",
    )
    script, notes = readme_check.script(block, install=False)
    assert ".venv/bin/leafgate sim\n" in script and "pip install" not in script
    assert "leafgate decode a.log | head" in script and script.startswith("set -e\n")
    assert notes == ["install step left out (--install runs it)"] * 2
    script, notes = readme_check.script(block, install=True)
    assert "pip install ." in script and not notes


def test_every_readme_block_runs_or_says_why_not() -> None:
    blocks = readme_check.blocks((ROOT / "README.md").read_text(encoding="utf-8"))
    for block in blocks:
        needs_car = "can0" in block.text or "config/leafgate.yaml" in block.text
        assert not needs_car or block.skip, f"README.md:{block.line} needs the car: mark it"
        assert not block.skip or block.skip.strip(), block.line
    hil = [b for b in blocks if "leafgate run" in b.text and "config/sim.yaml" in b.text]
    assert hil and hil[0].expect == ["ENGAGED"] and not hil[0].skip


README_CHECK_TIMEOUT = 1800  # s: every block as written, `leafgate compare` alone takes minutes


@pytest.mark.slow
@pytest.mark.timeout(README_CHECK_TIMEOUT + 60)  # the suite's 300 s is per ordinary test
def test_readme_blocks_pass_as_written() -> None:
    done = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "readme_check.py")],
        capture_output=True,
        text=True,
        timeout=README_CHECK_TIMEOUT,
    )
    report = json.loads(done.stdout)
    print(done.stderr)  # which blocks ran, were skipped (and why) or failed
    assert done.returncode == 0 and report["runs_passed"] == 1, json.dumps(
        report["failures"], indent=1
    )
    assert report["blocks_run"] >= 6


def _sim_parser() -> argparse.ArgumentParser:
    from leafgate import cli

    parser = cli.build_parser()
    subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return subparsers.choices["sim"]


def test_the_sim_synopsis_is_the_sim_command_line() -> None:
    """Old README: the ``leafgate sim`` synopsis left out --profile, --seed, --no-plots and
    --record. Every option of ``leafgate sim --help`` is in it, with its choices as the
    command takes them, and nothing else."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    section = readme[readme.index("## The simulator") :]
    synopsis = re.search(r"```text\n(leafgate sim .*?)```", section, re.S)
    assert synopsis is not None, "README.md: no ```text block of `leafgate sim` usage"
    written = dict(re.findall(r"(--[a-z][a-z-]*)(?: ([^\s\]]+))?", synopsis.group(1)))
    options = {
        action.option_strings[-1]: action
        for action in _sim_parser()._actions
        if action.option_strings and action.option_strings[-1] != "--help"
    }
    assert set(written) == set(options), "README.md's sim synopsis differs from sim --help"
    for name, action in options.items():
        if action.choices is not None:
            assert written[name] == "|".join(action.choices), name
