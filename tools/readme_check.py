#!/usr/bin/env python3
"""Run every ``sh`` block of README.md as written, in order, in a fresh copy of the repository.

    python tools/readme_check.py                 # once; JSON on stdout, exit 1 on any failure
    python tools/readme_check.py --repeat 10     # ten fresh runs in a row
    python tools/readme_check.py --list          # the blocks and what would happen to each

How a block runs:

- in one ``bash`` per block, from a temporary copy of the repository's tracked files, with
  ``set -e``: a command that fails fails the block (a pipeline's status is its last command's,
  as in an interactive shell);
- with ``.venv`` pointing at the running interpreter's venv and its ``bin`` first on ``PATH``,
  as after ``. .venv/bin/activate``, and the copy's own ``leafgate`` package first on
  ``PYTHONPATH`` (a checkout edited meanwhile does not change a run). A line ``python3 -m venv .venv && .venv/bin/pip install
  … && REST`` runs only ``REST`` (installing is what ``--install`` adds: a real venv, from the
  network); a line that only installs is left out, and the report says so;
- with ``LEAFGATE_BENCH`` set to a bench whose ports are free, so the hardware-in-the-loop
  block gets its own multicast and Zenoh ports (``config/sim.yaml``'s ``bench:``);
- where it can (root, ``unshare`` and ``ip``; not with ``--install``), in a private network
  namespace of its own, so a block's fixed ports (the Dask cluster's 8786) are its own too;
  the JSON's ``isolation`` says whether it could (``netns``) or not (``none``);
- background jobs (``cmd &``) still running when the block ends are killed, and waited for.

An HTML comment right before a block steers the check; each is printed with its reason:

- ``<!-- readme-check: skip (REASON) -->``: never run here (the car, SocketCAN);
- ``<!-- readme-check: slow (REASON) -->``: run only with ``--all``;
- ``<!-- readme-check: expect TEXT -->``: the block's output must contain TEXT.

The JSON says, per run, each block's line, heading, verdict (``passed``, ``failed``,
``skipped``), the reason, the seconds it took, and for a failure the end of its output.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
INSTALL = re.compile(
    r"^\s*python3 -m venv \.venv && \.venv/bin/pip install (?:-e )?\S+(?: && (?P<rest>.*))?$"
)
MARKER = re.compile(r"<!--\s*readme-check:\s*(?P<kind>skip|slow|expect)\s*(?P<arg>.*?)\s*-->")
BLOCK_TIMEOUT = 600.0  # s, one block (compare takes minutes on a loaded machine)
BENCH_CAN_PORT, BENCH_ZENOH_PORT = 43113, 17447  # bench 0's ports (leafgate.settings)


@dataclass
class Block:
    line: int  # 1-based line of the opening fence
    heading: str
    text: str
    skip: str = ""
    slow: str = ""
    expect: list[str] = field(default_factory=list)


def blocks(readme: str) -> list[Block]:
    """The ``sh`` blocks of a README, with their heading and markers."""
    found: list[Block] = []
    heading = ""
    pending: dict[str, Any] = {"skip": "", "slow": "", "expect": []}
    lines = readme.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("#"):
            heading = line.lstrip("#").strip()
        marker = MARKER.search(line)
        if marker:
            kind, arg = marker["kind"], marker["arg"].strip().strip("()")
            if kind == "expect":
                pending["expect"].append(arg)
            else:
                pending[kind] = arg or kind
        if line.strip().startswith("```"):
            lang = line.strip()[3:].strip()
            end = i + 1
            while end < len(lines) and not lines[end].strip().startswith("```"):
                end += 1
            if lang == "sh":
                found.append(
                    Block(
                        i + 1,
                        heading,
                        "\n".join(lines[i + 1 : end]) + "\n",
                        pending["skip"],
                        pending["slow"],
                        list(pending["expect"]),
                    )
                )
            pending = {"skip": "", "slow": "", "expect": []}
            i = end + 1
            continue
        i += 1
    return found


def script(block: Block, install: bool) -> tuple[str, list[str]]:
    """The bash script of a block, and notes on what was left out."""
    notes: list[str] = []
    out = []
    for line in block.text.splitlines():
        match = INSTALL.match(line)
        if match and not install:
            rest = match["rest"]
            notes.append("install step left out (--install runs it)")
            if rest:
                out.append(rest)
            continue
        out.append(line)
    body = "\n".join(out)
    return (
        "set -e\n"
        # a job still running at the end is stopped (the daemon disengages on SIGTERM); set +e:
        # a job that ends between `jobs` and `kill` must not fail the block (kill → xargs 123)
        "trap 'set +e; jobs -p | xargs -r kill 2>/dev/null; wait' EXIT\n" + body + "\n",
        notes,
    )


def _free(port: int, kind: int) -> bool:
    with socket.socket(socket.AF_INET, kind) as sock:
        try:
            sock.bind(("127.0.0.1" if kind == socket.SOCK_STREAM else "", port))
        except OSError:
            return False
    return True


def free_bench() -> int:
    """A bench number whose multicast (UDP) and Zenoh (TCP) ports are free on this host."""
    start = 100 + os.getpid() % 800
    for n in [*range(start, 999), *range(100, start)]:
        if _free(BENCH_CAN_PORT + n, socket.SOCK_DGRAM) and _free(
            BENCH_ZENOH_PORT + n, socket.SOCK_STREAM
        ):
            return n
    raise SystemExit("readme_check: no free bench in 100–998")


def copy_repo(dest: Path) -> None:
    """The repository's tracked files (or, outside git, the whole tree without caches)."""
    try:
        names = subprocess.run(
            ["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True
        ).stdout.split(b"\0")
    except (OSError, subprocess.CalledProcessError):
        shutil.copytree(ROOT, dest, dirs_exist_ok=True, ignore=shutil.ignore_patterns(".*"))
        return
    for raw in names:
        if not raw:
            continue
        rel = Path(os.fsdecode(raw))
        source = ROOT / rel
        (dest / rel).parent.mkdir(parents=True, exist_ok=True)
        if source.is_symlink():  # e.g. leafgate/data/dbc → ../../dbc: kept a link
            (dest / rel).symlink_to(os.readlink(source))
        elif source.is_file():
            shutil.copy2(source, dest / rel)


# A private network namespace with its loopback up and multicast routed to it: the blocks' fixed
# ports (the cluster's 8786) and multicast groups are then the block's own, whoever else runs on
# this host (another check, a test session, a real cluster).
_NETNS_SETUP = (
    "ip link set lo up && ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo"
    ' && exec bash -c "$1"'
)


def isolation(install: bool) -> str:
    """``netns`` when each block can run in a private network namespace (root, ``unshare`` and
    ``ip`` present, and the install steps, which need the network, not run); else ``none``,
    and the blocks share this host's ports."""
    if install or os.geteuid() != 0 or not (shutil.which("unshare") and shutil.which("ip")):
        return "none"
    probe = subprocess.run(
        ["unshare", "-n", "bash", "-c", _NETNS_SETUP, "_", "true"], capture_output=True
    )
    return "netns" if probe.returncode == 0 else "none"


def run_block(
    block: Block, cwd: Path, env: dict[str, str], install: bool, netns: bool = False
) -> dict[str, Any]:
    text, notes = script(block, install)
    t0 = time.monotonic()
    argv = ["bash", "-c", text]
    if netns:
        argv = ["unshare", "-n", "bash", "-c", _NETNS_SETUP, "_", text]
    process = subprocess.Popen(
        argv,
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,  # its own process group: a timeout kills every job
    )
    try:
        output, _ = process.communicate(timeout=BLOCK_TIMEOUT)
        status = process.returncode
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        output, _ = process.communicate()
        status = None
    seconds = time.monotonic() - t0
    missing = [text for text in block.expect if text not in output]
    passed = status == 0 and not missing
    reason = "; ".join(notes)
    if status is None:
        reason = f"timed out after {BLOCK_TIMEOUT:g} s"
    elif status != 0:
        reason = f"exit status {status}"
    elif missing:
        reason = "output lacks " + ", ".join(repr(m) for m in missing)
    record: dict[str, Any] = {
        "line": block.line,
        "heading": block.heading,
        "verdict": "passed" if passed else "failed",
        "reason": reason,
        "seconds": round(seconds, 1),
    }
    if not passed:
        record["output_tail"] = output[-3000:]
    return record


def check_once(
    install: bool, run_slow: bool, log: Any, netns: bool = False
) -> list[dict[str, Any]]:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    results = []
    with tempfile.TemporaryDirectory(prefix="readme-check-") as tmp:
        cwd = Path(tmp)
        copy_repo(cwd)
        env = dict(os.environ)
        venv = Path(sys.prefix)
        if not install:
            (cwd / ".venv").symlink_to(venv)
        env["PATH"] = f"{cwd / '.venv' / 'bin'}{os.pathsep}{env.get('PATH', '')}"
        env["VIRTUAL_ENV"] = str(cwd / ".venv")
        env["LEAFGATE_BENCH"] = str(free_bench())
        # the copy's code, not the checkout's: what a fresh clone would run (the venv's
        # editable install finds the checkout only after PYTHONPATH)
        env["PYTHONPATH"] = str(cwd)
        for block in blocks(readme):
            if block.skip or (block.slow and not run_slow):
                reason = block.skip or f"{block.slow}; --all runs it"
                results.append(
                    {
                        "line": block.line,
                        "heading": block.heading,
                        "verdict": "skipped",
                        "reason": reason,
                        "seconds": 0.0,
                    }
                )
            else:
                results.append(run_block(block, cwd, env, install, netns))
            r = results[-1]
            print(
                f"README.md:{r['line']} ({r['heading']}): {r['verdict']}"
                + (f" — {r['reason']}" if r["reason"] else "")
                + (f" [{r['seconds']:.0f} s]" if r["seconds"] else ""),
                file=log,
                flush=True,
            )
    return results


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=1, help="fresh runs in a row")
    parser.add_argument("--all", action="store_true", help="run the blocks marked slow too")
    parser.add_argument(
        "--install", action="store_true", help="run the install steps (a new venv, network)"
    )
    parser.add_argument("--list", action="store_true", help="list the blocks and exit")
    args = parser.parse_args(argv)
    if args.list:
        for block in blocks((ROOT / "README.md").read_text(encoding="utf-8")):
            what = (
                f"skip: {block.skip}"
                if block.skip
                else f"slow: {block.slow}"
                if block.slow
                else "run"
            )
            print(f"README.md:{block.line} ({block.heading}): {what}")
        return 0
    runs = []
    isolated = isolation(args.install)
    for k in range(args.repeat):
        print(f"run {k + 1}/{args.repeat}", file=sys.stderr, flush=True)
        runs.append(check_once(args.install, args.all, sys.stderr, isolated == "netns"))
    failed_runs = sum(any(r["verdict"] == "failed" for r in run) for run in runs)
    print(
        json.dumps(
            {
                "runs": args.repeat,
                "runs_passed": args.repeat - failed_runs,
                # netns: each block in a private network namespace; none: on this host's ports
                "isolation": isolated,
                "blocks_run": sum(r["verdict"] != "skipped" for r in runs[0]) if runs else 0,
                "blocks_skipped": [
                    {"line": r["line"], "reason": r["reason"]}
                    for r in (runs[0] if runs else [])
                    if r["verdict"] == "skipped"
                ],
                "failures": [
                    {"run": k + 1, **r}
                    for k, run in enumerate(runs)
                    for r in run
                    if r["verdict"] == "failed"
                ],
            },
            indent=2,
        )
    )
    return 1 if failed_runs else 0


if __name__ == "__main__":
    sys.exit(main())
