"""``leafgate batch``: sweep files, seeded disturbances, the Dask engine, results and reports."""

from __future__ import annotations

import errno
import json
import os
import shlex
import signal
import time
from pathlib import Path
from typing import Any

import pytest

from leafgate.batch.engine import INTERRUPTED, NOT_RUN, EngineRun, run_tasks
from leafgate.batch.results import read_table
from leafgate.batch.sweep import expand, load_sweep
from leafgate.cli import main
from leafgate.errors import ConfigError
from leafgate.sim.runner import WALL_CLOCK_METRICS
from tests.conftest import process_cluster

#: A small sweep on the shortest route: 2 controllers × 2 seeded samples, with noise.
SMALL_SWEEP = """\
name: small
seed: 11
samples: 2
routes: [straight]
plants: [kinematic]
controllers: [mpc, stanley]
disturbances:
  sim.localization.position_noise: [0.01, 0.03]
  sim.localization.latency: [0.0, 0.04]
  sim.plant.wheelbase_error: [-0.05, 0.05]
  sim.start_lateral_offset: [-0.2, 0.2]
thresholds:
  lateral_error_max_m: 0.0001
"""


def write(tmp_path: Path, text: str, name: str = "sweep.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def same_numbers(a: dict[str, Any], b: dict[str, Any]) -> dict[str, tuple[Any, Any]]:
    """The keys both have whose values differ, wall-clock metrics aside."""
    skip = WALL_CLOCK_METRICS | {"case_wall_s"}
    return {k: (a[k], b[k]) for k in a.keys() & b.keys() if k not in skip and a[k] != b[k]}


def sim_alone(command: str, out: Path) -> dict[str, Any]:
    """Run a results row's command line (in this process) and read its metrics.json."""
    argv = shlex.split(command)
    assert argv[:2] == ["leafgate", "sim"]
    i = argv.index("--out")
    argv[i + 1] = str(out)
    main([*argv[1:], "--no-plots"])
    return json.loads((out / "metrics.json").read_text())


# --- sweep files --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("routes: [straight]\nbogus: 1\n", "bogus: unknown key"),
        ("routes: [nowhere]\n", "routes: 'nowhere' is neither a scenario"),
        ("routes: [missing.csv]\n", "routes: 'missing.csv': no such file"),
        ("routes: [straight]\nplants: [wobbly]\n", "plants: unknown 'wobbly'"),
        ("routes: [straight]\nsamples: 0\n", "samples: expected an integer >= 1"),
        (
            "routes: [straight, s-curve]\nsamples: 1000000000\n",
            "samples: 1000000000 makes 2000000000 cases (2 routes × 1 plants × 1 controllers × "
            "1000000000 samples), above the bound of 100000 (max_cases: raise it in the sweep file)",
        ),
        (
            "routes: [straight]\nsamples: 3\nmax_cases: 2\n",
            "samples: 3 makes 3 cases (1 routes × 1 plants × 1 controllers × 3 samples), above the "
            "bound of 2",
        ),
        ("routes: [straight]\nmax_cases: 0\n", "max_cases: expected an integer >= 1"),
        (
            "routes: [straight]\ndisturbances:\n  sim.plant.nope: [0, 1]\n",
            "sim.plant.nope: unknown key",
        ),
        (
            "routes: [straight]\ndisturbances:\n  sim.plant.steer_tau: [0.5, 0.1]\n",
            "disturbances.sim.plant.steer_tau: low 0.5 is above high 0.1",
        ),
        (
            "routes: [straight]\ndisturbances:\n  sim.plant.steer_tau: [-1, 0.1]\n",
            "steer_tau must be a positive number",
        ),
        (
            "routes: [straight]\ndisturbances:\n  sim.start_lateral_offset: [-2, 2]\n",
            "disturbances.sim.start_lateral_offset: [-2, 2] m leaves the engage envelope",
        ),
        ("routes: [straight]\nset:\n  controller.mpc.solver: fast\n", "controller.mpc.solver"),
        ("routes: [straight]\nthresholds:\n  finished: maybe\n", "thresholds.finished"),
        (
            "routes: [straight]\nthresholds:\n  lateral_eror_max_m: 0.6\n",
            "thresholds.lateral_eror_max_m: no such metric",
        ),
        ("routes: [straight\n", "sweep.yaml"),
    ],
)
def test_bad_sweep_file_names_file_and_key(tmp_path: Path, text: str, expected: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_sweep(path)
    message = str(info.value)
    assert str(path) in message and expected in message
    assert "\n" not in message


def test_bad_sweep_file_on_the_command_line_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write(tmp_path, "routes: [straight]\ndisturbances:\n  sim.plant.nope: [0, 1]\n")
    assert main(["batch", "sim", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err
    assert str(path) in err and "sim.plant.nope" in err


def test_threshold_typo_is_refused_before_any_case_runs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import leafgate.batch.cli as batch_cli

    ran: list[object] = []
    monkeypatch.setattr(batch_cli, "run_tasks", lambda *a, **k: ran.append(a))
    path = write(tmp_path, "routes: [straight]\nthresholds:\n  lateral_eror_max_m: 0.6\n")
    assert main(["batch", "sim", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err
    assert f"{path}: thresholds.lateral_eror_max_m: no such metric" in err
    assert not ran


def test_threshold_names_are_what_a_case_writes(tmp_path: Path) -> None:
    """SIM_METRICS is the list the thresholds are checked against before the run: every
    number and flag a real case's row holds is in it (a new metric must be added there)."""
    from leafgate.batch.results import SIM_METRICS
    from leafgate.batch.tasks import sim_case

    sweep = load_sweep(write(tmp_path, SMALL_SWEEP))
    row = sim_case(expand(sweep)[0].argv)
    assert row["status"] == "ok", row["error"]
    numbers = {k for k, v in row.items() if isinstance(v, (bool, int, float))}
    assert numbers - set(SIM_METRICS) == set()
    assert {"lateral_error_max_m", "finished", "exit_status"} <= numbers


def test_output_folder_that_cannot_be_created_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    sweep = write(tmp_path, "routes: [straight]\n")
    assert main(["batch", "sim", str(sweep), "--out", str(blocker / "out")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err
    assert "cannot create the output folder" in err and str(blocker / "out") in err


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux /proc")
def test_an_output_folder_nothing_can_be_written_in_is_refused_before_the_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Old code: every case ran, then "cannot write the results" (found by an outside look with
    a read-only mount; /proc/self is a folder no one can create a file in, root included)."""
    sweep = write(tmp_path, "routes: [straight]\n")
    assert main(["batch", "sim", str(sweep), "--out", "/proc/self"]) == 1
    out, err = capsys.readouterr()
    assert err.strip() == (
        "leafgate: error: --out /proc/self: cannot write in the output folder: "
        "No such file or directory"
    )
    assert "case" not in out  # nothing ran


def test_cases_are_seeded_and_reproducible(tmp_path: Path) -> None:
    sweep = load_sweep(write(tmp_path, SMALL_SWEEP))
    cases = expand(sweep)
    assert [c.case_id for c in cases] == ["0000", "0001", "0002", "0003"]
    assert [c.seed for c in cases] == [11, 12, 13, 14]
    assert [(c.controller, c.plant, c.route) for c in cases[:2]] == [
        ("mpc", "kinematic", "straight")
    ] * 2
    assert expand(load_sweep(write(tmp_path, SMALL_SWEEP, "again.yaml"))) == cases
    draws = []
    for case in cases:
        settings = dict(a.split("=", 1) for a in case.argv if "=" in a)
        noise = float(settings["sim.localization.position_noise"])
        offset = float(settings["sim.start_lateral_offset"])
        assert 0.01 <= noise <= 0.03 and -0.2 <= offset <= 0.2
        draws.append(noise)
        assert f"--seed {case.seed}" in case.command
    assert len(set(draws)) == len(draws)  # each seed draws its own values


def test_the_example_sweep_file_loads() -> None:
    sweep = load_sweep(Path(__file__).parents[1] / "config" / "sweep.yaml")
    assert 16 <= sweep.size <= 30
    assert sweep.thresholds


def test_batch_sim_help_describes_the_sweep_format(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["batch", "sim", "--help"])
    text = capsys.readouterr().out
    for key in ("routes:", "plants:", "controllers:", "disturbances:", "thresholds:", "seed:"):
        assert key in text


# --- seeded disturbances in `leafgate sim` ----------------------------------------------------


@pytest.mark.slow
def test_sim_seed_and_noise_change_the_drive_and_repeat(tmp_path: Path) -> None:
    """Localization noise acts in the simulated loop (it was ignored there), follows --seed,
    and the same seed gives the same numbers."""
    base = ["sim", "--scenario", "straight", "--no-plots"]
    noise = ["--set", "sim.localization.position_noise=0.05"]

    def metrics(name: str, *extra: str) -> dict[str, Any]:
        assert main([*base, "--out", str(tmp_path / name), *extra]) in (0, 1)
        return json.loads((tmp_path / name / "metrics.json").read_text())

    clean = metrics("clean")
    a = metrics("a", *noise, "--seed", "1")
    a_again = metrics("a2", *noise, "--seed", "1")
    b = metrics("b", *noise, "--seed", "2")
    assert clean["lateral_error_max_m"] == 0.0  # a straight line, driven exactly
    assert a["lateral_error_max_m"] > 0.0
    assert same_numbers(a, a_again) == {}
    assert a["lateral_error_rms_m"] != b["lateral_error_rms_m"]


@pytest.mark.slow
def test_start_offset_and_wheelbase_error_reach_the_plant(tmp_path: Path) -> None:
    def metrics(name: str, *extra: str) -> dict[str, Any]:
        main(["sim", "--scenario", "straight", "--no-plots", "--out", str(tmp_path / name), *extra])
        return json.loads((tmp_path / name / "metrics.json").read_text())

    offset = metrics("offset", "--set", "sim.start_lateral_offset=0.4")
    assert offset["lateral_error_max_m"] == pytest.approx(0.4, abs=1e-6)
    assert offset["finished"] is True
    s_curve = ["--scenario", "s-curve"]
    plain = metrics("plain", *s_curve)
    longer = metrics("longer", *s_curve, "--set", "sim.plant.wheelbase_error=0.3")
    assert longer["lateral_error_max_m"] != plain["lateral_error_max_m"]


# --- the engine ---------------------------------------------------------------------------------


def _task(kind: str) -> dict[str, Any]:
    if kind == "raise":
        raise RuntimeError("this case breaks")
    if kind == "hang":
        time.sleep(120.0)
    if kind == "die":  # the worker process dies (as when killed, or out of memory)
        os.kill(os.getpid(), signal.SIGKILL)
    if kind.startswith("die-once:"):
        marker = Path(kind.removeprefix("die-once:"))
        if not marker.exists():
            marker.touch()
            os.kill(os.getpid(), signal.SIGKILL)
    return {"status": "ok", "error": None, "kind": kind}


def test_a_sweep_may_raise_its_bound_of_cases(tmp_path: Path) -> None:
    sweep = load_sweep(write(tmp_path, "routes: [straight]\nsamples: 3\nmax_cases: 3\n"))
    assert len(expand(sweep)) == 3


@pytest.mark.slow
def test_a_case_whose_worker_dies_is_rerun_and_says_so(tmp_path: Path) -> None:
    """Dask's scheduler gives the task of a worker that died to another worker (up to
    distributed.scheduler.allowed-failures = 3 times), then fails it with KilledWorker. Before,
    a re-run was silent: the row looked like that of a case that ran once."""
    import cloudpickle

    cloudpickle.register_pickle_by_value(__import__(__name__))
    run = run_tasks(_task, {"once": (f"die-once:{tmp_path / 'died'}",), "ok": ("ok",)}, workers=2)
    assert [run.rows[k]["status"] for k in ("once", "ok")] == ["ok", "ok"]
    assert run.rows["once"]["attempts"] == 2  # one worker died, once
    # "ok" may have been queued on the worker that died: then it was re-run as well
    assert run.rows["ok"]["attempts"] in (1, 2)
    assert run.rerun == 1 + (run.rows["ok"]["attempts"] == 2)
    # alone: a task that kills every worker would take the tasks queued beside it along
    run = run_tasks(_task, {"always": ("die",)}, workers=1)
    (row,) = run.rows.values()
    assert (row["status"], row["attempts"]) == ("failed", 4)
    assert row["error"].startswith("KilledWorker: 4 workers died while holding it (3 re-runs")


@pytest.mark.slow
def test_local_cluster_records_failures_and_timeouts_and_goes_on() -> None:
    import cloudpickle

    cloudpickle.register_pickle_by_value(__import__(__name__))  # workers need not import tests
    t0 = time.monotonic()
    run = run_tasks(
        _task,
        {"a": ("ok",), "b": ("raise",), "c": ("hang",), "d": ("ok",), "e": ("ok",)},
        workers=2,
        timeout=3.0,
    )
    assert time.monotonic() - t0 < 100.0  # did not wait for the hanging case to end
    assert run.workers == 2 and "local cluster" in run.scheduler
    rows = run.rows
    assert {k: r["status"] for k, r in rows.items()} == {
        "a": "ok",
        "b": "failed",
        "c": "failed",
        "d": "ok",
        "e": "ok",
    }
    assert "RuntimeError: this case breaks" in rows["b"]["error"]
    assert "timed out after 3 s" in rows["c"]["error"]


@pytest.fixture(scope="module")
def local_sweep(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[dict[str, Any]]]:
    """The small sweep on a local cluster of two workers."""
    tmp = tmp_path_factory.mktemp("batch")
    sweep = write(tmp, SMALL_SWEEP)
    status = main(["batch", "sim", str(sweep), "--workers", "2", "--out", str(tmp / "local")])
    assert status == 1  # the threshold (1e-4 m) is crossed: the batch says so
    return sweep, read_table(tmp / "local" / "results.parquet")


@pytest.mark.slow
def test_local_cluster_results_are_those_of_single_runs(
    local_sweep: tuple[Path, list[dict[str, Any]]], tmp_path: Path
) -> None:
    sweep, rows = local_sweep
    cases = expand(load_sweep(sweep))
    assert [r["case_id"] for r in rows] == [c.case_id for c in cases]
    for row, case in zip(rows, cases, strict=True):
        assert row["status"] == "ok", row["error"]
        assert (row["route"], row["plant"], row["controller"], row["seed"]) == (
            case.route,
            case.plant,
            case.controller,
            case.seed,
        )
        assert row["command"] == case.command
        alone = sim_alone(row["command"], tmp_path / case.case_id)
        for key in alone.keys() - {"controller", "plant"}:  # every metrics.json key is a column
            assert key in row
        flat_alone = {
            k: json.dumps(v) if isinstance(v, (list, dict)) else v for k, v in alone.items()
        }
        flat_alone.pop("controller")  # the kind; the row has the sweep's controller name
        assert same_numbers(flat_alone, row) == {}
    # the seeds make the noisy drives differ from one another
    assert len({r["lateral_error_rms_m"] for r in rows}) == len(rows)


@pytest.mark.slow
def test_report_lists_worst_cases_with_their_command_lines(
    local_sweep: tuple[Path, list[dict[str, Any]]],
) -> None:
    sweep, rows = local_sweep
    out = sweep.parent / "local"
    report = (out / "report.md").read_text()
    worst = max(rows, key=lambda r: r["lateral_error_max_m"])
    assert "worst cases by lateral_error_max_m" in report
    assert worst["command"] in report
    assert (out / "errors.png").stat().st_size > 1000
    assert "lateral_error_max_m =" in report  # the thresholds crossed are listed
    info = json.loads((out / "batch.json").read_text())
    assert info["workers"] == 2 and info["cases"] == len(rows)


# --- batch check and batch rerun ---------------------------------------------------------------


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two recorded drives in a folder tree, and one unreadable log."""
    root = tmp_path_factory.mktemp("drives")
    for i, scenario in enumerate(("straight", "s-curve")):
        out = root / f"day{i}" / scenario
        assert (
            main(
                [
                    "sim",
                    "--scenario",
                    scenario,
                    "--no-plots",
                    "--out",
                    str(root.parent / f"{root.name}-sim{i}"),  # trace.csv: not in the tree
                    "--record",
                    str(out / "rec"),
                ]
            )
            == 0
        )
    (root / "broken.log").write_text("this is not a CAN log\n")
    return root


@pytest.mark.slow
def test_batch_check_checks_every_log_and_records_the_unreadable(
    recordings: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # the CAN logs name no profile (the sessions do)
    args = ["check", str(recordings), "--workers", "2", "--profile", "leafgate-dbw"]
    status = main(["batch", *args, "--out", str(tmp_path)])
    out = capsys.readouterr().out
    rows = read_table(tmp_path / "results.parquet")
    recorded = sorted(p for p in recordings.rglob("rec/*") if p.is_file())
    assert len(recorded) >= 2
    assert {r["path"] for r in rows} == {str(p) for p in [*recorded, recordings / "broken.log"]}
    by_path = {r["path"]: r for r in rows}
    for path in recorded:
        assert by_path[str(path)]["status"] == "ok"
        assert by_path[str(path)]["ok"] is True, by_path[str(path)]
    broken = by_path[str(recordings / "broken.log")]
    assert broken["status"] == "failed" or broken["ok"] is False
    assert status == 1
    assert f"{recordings / 'broken.log'}:" in out


@pytest.mark.slow
def test_batch_rerun_reproduces_and_shows_where_a_change_diverges(
    recordings: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    same = main(["batch", "rerun", str(recordings), "--workers", "2", "--out", str(tmp_path / "a")])
    out = capsys.readouterr().out
    sessions = sorted(recordings.rglob("*.mcap"))
    assert len(sessions) == 2
    assert same == 0
    assert out.count("IDENTICAL") == 2
    changed = main(
        [
            "batch",
            "rerun",
            str(recordings),
            "--workers",
            "2",
            "--out",
            str(tmp_path / "b"),
            "--set",
            "controller.mpc.weight_lateral=100",
        ]
    )
    out = capsys.readouterr().out
    assert changed == 1
    rows = read_table(tmp_path / "b" / "results.parquet")
    curved = next(r for r in rows if "s-curve" in r["path"])
    assert curved["identical"] is False
    assert curved["first_divergence_s"] > 0.0
    assert "steer.angle" in curved["diverging_signals"]
    assert "DIVERGED at" in out


@pytest.mark.slow
def test_batch_rerun_shows_a_truncated_session_was_checked_only_up_to_the_cut(
    recordings: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A session cut short (a crash before its footer) re-runs up to the cut: IDENTICAL there
    says nothing of the rest of the drive. Before, its line read as a whole drive's."""
    session = next(recordings.rglob("*.mcap"))
    data = session.read_bytes()
    cut = tmp_path / "in" / "cut.mcap"
    cut.parent.mkdir()
    cut.write_bytes(data[: len(data) * 6 // 10])
    args = ["batch", "rerun", str(cut.parent), "--workers", "1"]
    assert main([*args, "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert f"{cut}: IDENTICAL up to the cut (truncated session): " in out
    assert "1 session, 0 not reproduced, 1 reproduced only up to a cut (truncated)" in out
    (row,) = read_table(tmp_path / "out" / "results.parquet")
    assert row["truncated"] is True and row["identical"] is True


# --- results ------------------------------------------------------------------------------------


def test_results_are_csv_without_pyarrow(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from leafgate.batch.results import write_table

    rows = [
        {"case_id": "0000", "status": "ok", "lateral_error_max_m": 0.25, "transitions": [{"t": 1}]},
        {"case_id": "0001", "status": "failed", "error": "boom"},
    ]
    monkeypatch.setitem(__import__("sys").modules, "pyarrow", None)  # import pyarrow fails
    path = write_table(rows, tmp_path)
    assert path.name == "results.csv"
    back = read_table(path)
    assert [r["case_id"] for r in back] == ["0000", "0001"]
    assert back[0]["lateral_error_max_m"] == "0.25" and back[1]["error"] == "boom"
    assert json.loads(back[0]["transitions"]) == [{"t": 1}]


def test_thresholds_bound_numbers_require_flags_and_count_failures() -> None:
    from leafgate.batch.engine import BatchError
    from leafgate.batch.results import crossings

    rows = [
        {"case_id": "a", "status": "ok", "lateral_error_max_m": 0.2, "finished": True},
        {"case_id": "b", "status": "ok", "lateral_error_max_m": 0.7, "finished": True},
        {"case_id": "c", "status": "ok", "lateral_error_max_m": 0.1, "finished": False},
        {"case_id": "d", "status": "failed", "error": "timed out after 3 s"},
        {"case_id": "e", "status": "ok", "lateral_error_max_m": float("nan"), "finished": True},
    ]
    lines = crossings(rows, {"lateral_error_max_m": 0.5, "finished": True}, "s.yaml")
    assert [line.split(":")[0] for line in lines] == ["case b", "case c", "case d", "case e"]
    assert "timed out" in lines[2]
    with pytest.raises(BatchError, match=r"s.yaml: thresholds.lateral_eror: no such metric"):
        crossings(rows, {"lateral_eror": 0.5}, "s.yaml")


def test_progress_bar_only_on_a_terminal() -> None:
    import io

    from leafgate.batch.engine import Progress

    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    tty, pipe = Tty(), io.StringIO()
    for stream in (tty, pipe):
        bar = Progress(stream, 4, "cases")
        bar.add({"status": "ok"})
        bar.add({"status": "failed"})
        bar.close()
    assert "2/4 cases, 1 failed" in tty.getvalue()
    assert pipe.getvalue() == ""


def _spawned_workers(pid: int) -> list[int]:
    """The multiprocessing-spawned children of ``pid`` (any thread may have started them)."""
    found = []
    for children in Path(f"/proc/{pid}/task").glob("*/children"):
        for child in children.read_text().split():
            cmdline = Path(f"/proc/{child}/cmdline")
            if cmdline.exists() and b"spawn_main" in cmdline.read_bytes():
                found.append(int(child))
    return found


def _ignores_sigint(pid: int) -> bool:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("SigIgn:"):
            return bool(int(line.split()[1], 16) & (1 << (2 - 1)))  # SIGINT is signal 2
    return False


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, IndexError):
        return False
    return state != "Z"


@pytest.mark.slow
def test_ctrl_c_at_the_terminal_stops_the_batch_and_its_workers_in_one_line(
    tmp_path: Path,
) -> None:
    """Ctrl-C reaches the batch and its worker processes (one process group): one line, 130,
    and the results of the cases that finished, the others listed as not run.

    Before, each worker printed a KeyboardInterrupt traceback, or a heartbeat to a closed
    scheduler, or Dask's exit handler its own; a Ctrl-C during the cluster's start could end
    in a silent exit 1.
    """
    import signal
    import subprocess
    import sys

    sweep = write(tmp_path, SMALL_SWEEP.replace("samples: 2", "samples: 40"))
    argv = [sys.executable, "-m", "leafgate", "batch", "sim", str(sweep), "--workers", "2"]
    with (tmp_path / "err").open("w+") as err:
        process = subprocess.Popen(
            [*argv, "--out", str(tmp_path / "out")],
            stdout=subprocess.DEVNULL,
            stderr=err,
            cwd=tmp_path,
            start_new_session=True,  # its own process group, as a shell job has
        )
        deadline = time.monotonic() + 120
        workers: list[int] = []
        while time.monotonic() < deadline and process.poll() is None:
            try:  # up: both workers have started and run their set-up
                workers = _spawned_workers(process.pid)
                if len(workers) == 2 and all(_ignores_sigint(p) for p in workers):
                    break
            except (FileNotFoundError, ProcessLookupError):  # a process came or went
                pass
            time.sleep(0.2)
        assert process.poll() is None, "the batch ended before its workers were up"
        assert len(workers) == 2 and all(_ignores_sigint(p) for p in workers), (
            "the workers did not set Ctrl-C aside for the batch process"
        )
        os.killpg(process.pid, signal.SIGINT)  # what the terminal does on Ctrl-C
        try:
            status = process.wait(timeout=120)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            raise
        err.seek(0)
        text = err.read()
    lines = [line for line in text.replace("\r", "\n").splitlines() if line.strip()]
    lines = [line for line in lines if not line.startswith("[")]  # the progress bar
    assert status == 130, text
    assert lines == ["leafgate: interrupted"], text
    # what finished is kept, and what did not run is listed as such (before: no --out at all)
    rows = read_table(tmp_path / "out" / "results.parquet")
    assert len(rows) == 80
    assert {r["status"] for r in rows} <= {"ok", "not run"}
    assert any(r["status"] == "not run" for r in rows)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and any(_alive(p) for p in workers):
        time.sleep(0.2)
    assert not any(_alive(p) for p in workers), "worker processes outlived the batch"


def test_batch_rerun_refuses_an_override_a_rerun_cannot_honour(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Refused up front (exit 2, one line naming the key), before any session is re-run."""
    (tmp_path / "in").mkdir()
    args = ["batch", "rerun", str(tmp_path / "in"), "--out", str(tmp_path / "out")]
    assert main([*args, "--set", "sim.plant.kind=dynamic"]) == 2
    err = capsys.readouterr().err
    assert "--set sim.plant.kind:" in err and "vehicle, controller, gateway" in err


def test_batch_check_line_names_the_kinds_of_findings(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A log whose findings are neither limits, E2E errors nor gaps says what they are."""
    logs = tmp_path / "in"
    logs.mkdir()
    (logs / "foreign.log").write_text(
        "(1700000000.000000) vcan0 123#0011223344556677\n"
        "(1700000000.010000) vcan0 123#0011223344556677\n"
    )
    args = ["batch", "check", str(logs), "--profile", "leafgate-dbw", "--workers", "1"]
    assert main([*args, "--out", str(tmp_path / "out")]) == 1
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.startswith(f"{logs / 'foreign.log'}:"))
    assert "FINDINGS: coverage 1, incomplete 1; 2 frames" in line, line
    assert "first: coverage: profile: no frame of profile leafgate-dbw" in line
    row = read_table(tmp_path / "out" / "results.parquet")[0]
    assert row["finding_kinds"] == "coverage 1, incomplete 1"
    assert "; local cluster (1 worker process), 1 worker, " in out  # not "1 worker processes"
    assert row["status"] == "ok"  # the check ran; its verdict (findings) is `ok`, False


# --- a batch that stops early, or cannot write ---------------------------------------------------


def _fake_engine(
    monkeypatch: pytest.MonkeyPatch, rows: dict[str, dict[str, Any]], stopped: str | None = None
) -> None:
    """``run_tasks`` answering ``rows`` (by task key) at once, as the engine would have."""

    def run_tasks(fn: Any, tasks: dict[str, Any], **_: Any) -> EngineRun:
        assert set(tasks) == set(rows)
        return EngineRun(rows=rows, wall_s=1.0, workers=2, scheduler="fake", stopped=stopped)

    monkeypatch.setattr("leafgate.batch.cli.run_tasks", run_tasks)


def _sim_row(error_m: float, attempts: int = 1) -> dict[str, Any]:
    return {
        "status": "ok",
        "error": None,
        "exit_status": 0,
        "lateral_error_max_m": error_m,
        "finished": True,
        "attempts": attempts,
    }


def test_batch_sim_summary_names_the_cases_rerun_after_a_worker_died(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    sweep = write(tmp_path, "routes: [straight]\nsamples: 2\nthresholds:\n  finished: true\n")
    _fake_engine(monkeypatch, {"0000": _sim_row(0.1, attempts=2), "0001": _sim_row(0.1)})
    assert main(["batch", "sim", str(sweep), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert "2 cases, 0 failed, 1 re-run after a worker holding it died; fake, 2 workers" in out
    assert "PASSED: every case ran (1 re-run after a worker died)" in out
    info = json.loads((tmp_path / "out" / "batch.json").read_text())
    assert info["rerun"] == 1
    rows = read_table(tmp_path / "out" / "results.parquet")
    assert [r["attempts"] for r in rows] == [2, 1]
    report = (tmp_path / "out" / "report.md").read_text()
    assert "- case 0000: 2 attempts" in report


def test_interrupted_batch_sim_keeps_what_finished_and_lists_the_rest(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    sweep = write(tmp_path, "routes: [straight]\nsamples: 3\nthresholds:\n  finished: true\n")
    not_run = {"status": NOT_RUN, "error": f"not run: {INTERRUPTED}"}
    rows = {"0000": _sim_row(0.1), "0001": not_run, "0002": dict(not_run)}
    _fake_engine(monkeypatch, rows, stopped=INTERRUPTED)
    assert main(["batch", "sim", str(sweep), "--out", str(tmp_path / "out")]) == 130
    captured = capsys.readouterr()
    assert captured.err.strip() == "leafgate: interrupted"
    assert "3 cases, 0 failed, 2 not run (interrupted (Ctrl-C))" in captured.out
    table = read_table(tmp_path / "out" / "results.parquet")
    assert [r["status"] for r in table] == ["ok", NOT_RUN, NOT_RUN]
    info = json.loads((tmp_path / "out" / "batch.json").read_text())
    assert (info["not_run"], info["stopped"]) == (2, INTERRUPTED)
    assert "## Cases not run (interrupted (Ctrl-C))" in (tmp_path / "out" / "report.md").read_text()


def test_batch_sim_on_a_full_disk_prints_the_summary_before_failing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The cases ran: their verdict is printed before the files that cannot be written."""
    sweep = write(
        tmp_path, "routes: [straight]\nsamples: 25\nthresholds:\n  lateral_error_max_m: 0.5\n"
    )
    _fake_engine(monkeypatch, {f"{i:04d}": _sim_row(1.0) for i in range(25)})

    def full(*_: Any, **__: Any) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("leafgate.batch.cli.write_table", full)
    assert main(["batch", "sim", str(sweep), "--out", str(tmp_path / "out")]) == 1
    captured = capsys.readouterr()
    assert "25 cases, 0 failed; fake, 2 workers" in captured.out
    for i in range(25):  # all of them, not only the 20 shown when the report holds the rest
        assert f"case {i:04d}: lateral_error_max_m = 1.0 above 0.5" in captured.out
    err = captured.err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err
    assert "cannot write the results: No space left on device" in err


def test_refused_inputs_leave_no_empty_output_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "empty").mkdir()
    for job in ("check", "rerun"):
        out = tmp_path / f"out-{job}"
        assert main(["batch", job, str(tmp_path / "empty"), "--out", str(out)]) == 1
        assert "files in it" in capsys.readouterr().err
        assert not out.exists()


def test_a_glob_that_matches_no_log_says_so_not_that_nothing_matched(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Old code: "no *.txt files in it" for a folder holding notes.txt."""
    (tmp_path / "misc").mkdir()
    (tmp_path / "misc" / "notes.txt").write_text("not a log\n")
    assert main(["batch", "check", str(tmp_path / "misc"), "--glob", "*.txt"]) == 1
    err = capsys.readouterr().err
    assert f"{tmp_path / 'misc'}: no *.txt file in it is a log (.log, " in err


@pytest.mark.slow
def test_relative_paths_reach_workers_started_in_another_folder(
    recordings: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``batch check drives/`` and ``batch rerun drives/`` on a cluster whose workers were
    started in another folder (as a cluster's are). Before, the tasks got the relative paths
    and each worker looked for them in its own folder: every log failed, 'no such file' (or a
    file of the same name there was checked instead)."""
    elsewhere = tmp_path / "workers-start-here"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)  # the workers' working folder
    with process_cluster() as cluster:
        monkeypatch.chdir(recordings.parent)  # the batch's, where `drives/` is
        relative = recordings.name
        args = ["--scheduler", cluster.scheduler_address]
        rerun = main(["batch", "rerun", relative, *args, "--out", str(tmp_path / "r")])
        only_sessions = ["--profile", "leafgate-dbw", "--glob", "*.mcap"]
        check = main(
            ["batch", "check", relative, *args, *only_sessions, "--out", str(tmp_path / "c")]
        )
    out = capsys.readouterr().out
    assert "no such file" not in out
    assert rerun == 0, out
    rows = read_table(tmp_path / "r" / "results.parquet")
    assert len(rows) == 2 and all(r["identical"] for r in rows)
    assert {r["path"] for r in rows} == {
        str(p.relative_to(recordings.parent)) for p in recordings.rglob("*.mcap")
    }
    assert check == 0, out
    rows = read_table(tmp_path / "c" / "results.parquet")
    assert len(rows) == 2 and all(r["ok"] for r in rows)


@pytest.mark.slow
def test_a_case_whose_drive_fails_alone_does_not_pass_a_sweep_without_thresholds(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """`leafgate sim` exits 1 when the drive did not finish (tight-hairpin, R = 3 m): its case
    ran, but it is no pass. Before, a sweep without thresholds printed 'PASSED: every case ran
    and stayed within the thresholds' and exited 0 for it."""
    sweep = write(tmp_path, "routes: [tight-hairpin, straight]\ncontrollers: [stanley]\n")
    assert main(["batch", "sim", str(sweep), "--workers", "1", "--out", str(tmp_path / "o")]) == 1
    out = capsys.readouterr().out
    assert "PASSED" not in out
    assert "case 0000: leafgate sim exited 1 (the drive did not finish" in out
    assert "case 0001" not in out
    assert "FAILED: 1 threshold crossing or failed case" in out
    rows = read_table(tmp_path / "o" / "results.parquet")
    assert [(r["status"], r["exit_status"], r["finished"]) for r in rows] == [
        ("ok", 1, False),
        ("ok", 0, True),
    ]
    assert load_sweep(sweep).thresholds == {"exit_status": 0.0}
    # a sweep that means to keep such cases says so
    accepting = write(tmp_path, "routes: [straight]\nthresholds:\n  exit_status: 1\n", "b.yaml")
    assert load_sweep(accepting).thresholds == {"exit_status": 1.0}
