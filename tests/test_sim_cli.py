"""``leafgate sim`` as a user drives it: their own trajectory file, ``--set`` overrides,
``trace.csv``, and an exit status that says whether the maneuver finished (issue 13)."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from leafgate import cli
from leafgate.config import parse_overrides
from leafgate.replay import rerun
from leafgate.sim.scenarios import OBSTACLES, SCENARIOS, Box

pytestmark = pytest.mark.slow


def _write_route(path: Path) -> list[tuple[float, float, float, float]]:
    """A 12 m drive with a gentle left bend, 0.5 m apart, as a planner sends it."""
    s = np.arange(0.0, 12.01, 0.5)
    heading = 0.3 * np.clip((s - 4.0) / 4.0, 0.0, 1.0)
    x = np.concatenate(([0.0], np.cumsum(0.5 * np.cos(0.5 * (heading[1:] + heading[:-1])))))
    y = np.concatenate(([0.0], np.cumsum(0.5 * np.sin(0.5 * (heading[1:] + heading[:-1])))))
    speed = np.minimum(np.minimum(np.sqrt(0.09 + 0.8 * s), np.sqrt(0.8 * (s[-1] - s))), 1.0)
    rows = list(zip(x + 3.0, y - 2.0, heading, speed, strict=True))
    if path.suffix == ".csv":
        lines = ["x,y,heading,speed"] + [",".join(f"{v:.6f}" for v in r) for r in rows]
        path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    else:
        path.write_text(
            "".join(
                f"- {{x: {a:.6f}, y: {b:.6f}, heading: {c:.6f}, speed: {d:.6f}}}\n"
                for a, b, c, d in rows
            ),
            encoding="utf-8",
        )
    return [tuple(map(float, r)) for r in rows]


def _sim(*args: str) -> int:
    return cli.main(["sim", "--no-plots", *args])


def test_sim_drives_a_csv_trajectory_file_and_writes_trace_csv(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    route = _write_route(tmp_path / "route.csv")
    out = tmp_path / "out"
    assert _sim("--trajectory", str(tmp_path / "route.csv"), "--out", str(out)) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["finished"] is True
    assert metrics["route_length_m"] == pytest.approx(12.0, abs=0.01)
    assert metrics["start_progress_m"] == pytest.approx(0.0, abs=1e-9)
    assert metrics["progress_m"] == pytest.approx(metrics["route_length_m"], abs=0.2)
    assert metrics["final_position_error_m"] < 0.1
    with (out / "trace.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == [
        "t_s",
        "x_m",
        "y_m",
        "heading_deg",
        "speed_mps",
        "steer_cmd_deg",
        "steer_deg",
        "accel_cmd_mps2",
        "state",
    ]
    # one row per control tick (20 ms), from the start on the first waypoint to the end
    t = np.array([float(r["t_s"]) for r in rows])
    np.testing.assert_allclose(np.diff(t), 0.02, atol=1e-6)
    assert t[-1] == pytest.approx(metrics["duration_s"], abs=0.03)
    assert (float(rows[0]["x_m"]), float(rows[0]["y_m"])) == pytest.approx(route[0][:2], abs=1e-6)
    states = [r["state"] for r in rows]
    assert states[0] == "STANDBY" and "ENGAGED" in states and states[-1] == "STANDBY"
    assert max(float(r["accel_cmd_mps2"]) for r in rows) > 0.1
    end = rows[-1]
    assert math.hypot(float(end["x_m"]) - route[-1][0], float(end["y_m"]) - route[-1][1]) < 0.1
    out_text, err = capsys.readouterr()
    assert "trace.csv" in out_text
    assert "chords" not in err  # 0.5 m apart on a gentle bend: the chords are the curve


def test_sim_warns_when_sparse_waypoints_make_the_lateral_error_coarse(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A 90° arc of 10 m radius with waypoints 3.1 m apart: the car follows a curve through
    them, the lateral error is measured from chords that cut it by R (1 − cos(Δθ/2)), and the
    sim says so instead of reporting the cut as the car's error without a word."""
    radius, n = 10.0, 6
    angle = np.linspace(0.0, math.pi / 2, n)
    lines = ["x,y,heading,speed"] + [
        f"{radius * math.sin(a):.6f},{radius * (1 - math.cos(a)):.6f},{a:.6f},{1.0 if k < n - 1 else 0.0}"
        for k, a in enumerate(angle)
    ]
    (tmp_path / "sparse.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    assert _sim("--trajectory", str(tmp_path / "sparse.csv"), "--out", str(tmp_path / "o")) == 0
    err = capsys.readouterr().err
    cut = radius * (1.0 - math.cos(0.5 * angle[1]))  # m, the sagitta of one chord
    assert f"cut it by up to {cut * 100:.1f} cm" in err, err
    assert f"{2 * radius * math.sin(0.5 * angle[1]):.2f} m apart" in err


@pytest.mark.parametrize(
    "name, spacing, goal_speed",
    [("2 m apart", 2.0, 0.0), ("0.1 m apart", 0.1, 0.0), ("a goal at 0.5 m/s", 0.5, 0.5)],
)
def test_sim_drives_what_the_format_allows_beyond_what_a_planner_sends(
    name: str, spacing: float, goal_speed: float, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The help says what a file needs and what a planner sends: waypoints farther apart or
    closer than 0.5-1.0 m drive (the controller follows a curve through them), and the car
    stops on the last waypoint whatever its speed, so neither is refused nor warned about on
    a straight."""
    n = round(10.0 / spacing) + 1
    speeds = [0.8] * (n - 1) + [goal_speed]
    rows = [f"{spacing * i:.3f},0,0,{v}" for i, v in enumerate(speeds)]
    route = tmp_path / "route.csv"
    route.write_text("\n".join(["x,y,heading,speed", *rows]) + "\n", encoding="utf-8")
    assert _sim("--trajectory", str(route), "--out", str(tmp_path / "o")) == 0, name
    assert capsys.readouterr().err == ""
    metrics = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert metrics["finished"] is True and metrics["final_position_error_m"] < 0.1


def test_sim_help_tells_required_from_recommended(capsys: pytest.CaptureFixture[str]) -> None:
    """Old help: "0.5-1.0 m apart as a planner sends them … the last waypoint is the goal
    (speed 0)" among the requirements, neither checked, and the rule that did refuse files
    (speeds at 0 before a leg's end) not said."""
    with pytest.raises(SystemExit):
        cli.main(["sim", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "Any spacing drives" in text and "a planner sends them 0.5-1.0 m apart" in text
    assert "the car stops on it whatever its speed" in text
    assert "speeds above 0 up to each cusp and the last waypoint" in text


def test_sim_drives_a_yaml_trajectory_from_a_given_start(tmp_path: Path) -> None:
    route = _write_route(tmp_path / "route.yaml")
    out = tmp_path / "out"
    start = f"{route[0][0]:.3f},{route[0][1] + 0.5:.3f},10"  # 0.5 m to the left, turned 10°
    rc = _sim("--trajectory", str(tmp_path / "route.yaml"), "--start", start, "--out", str(out))
    assert rc == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["finished"] is True
    with (out / "trace.csv").open() as f:
        first = next(csv.DictReader(f))
    assert float(first["y_m"]) == pytest.approx(route[0][1] + 0.5, abs=1e-3)
    assert float(first["heading_deg"]) == pytest.approx(10.0, abs=1e-3)


def test_sim_takes_a_start_pose_with_a_negative_x_as_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Old code: `--start -3,0.3,-5` was argparse's "argument --start: expected one argument"
    (Python 3.11 reads a value starting with "-" as an option unless it is a plain number)."""
    route = tmp_path / "route.csv"
    rows = [f"{x:.1f},0,0,{0.0 if x == 5 else 1.0}" for x in range(-3, 6)]
    route.write_text("\n".join(["x,y,heading,speed", *rows]) + "\n", encoding="utf-8")
    out = tmp_path / "out"
    rc = _sim("--trajectory", str(route), "--start", "-3,0.3,-5", "--out", str(out))
    assert rc == 0, capsys.readouterr().err
    with (out / "trace.csv").open() as f:
        first = next(csv.DictReader(f))
    assert float(first["x_m"]) == pytest.approx(-3.0, abs=1e-3)
    assert float(first["y_m"]) == pytest.approx(0.3, abs=1e-3)
    assert float(first["heading_deg"]) == pytest.approx(-5.0, abs=1e-3)


def test_sim_exits_non_zero_with_the_reason_when_the_maneuver_does_not_finish(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Old code: exit 0 whatever happened. A localization dropout ends the drive in FAULT.
    rc = _sim("--inject", "localization-dropout@3s", "--out", str(tmp_path))
    err = capsys.readouterr().err
    assert rc == 1
    assert "not finished" in err and "STOPPING at t = 3.1" in err and "localization" in err
    assert json.loads((tmp_path / "metrics.json").read_text())["finished"] is False


def test_sim_exits_non_zero_when_the_car_drove_through_an_obstacle(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # A route driven to its end is not a maneuver done when the car's body went into something
    # on the way: a box 0.5 m left of the straight's centre line, 10–12 m along it (the Leaf is
    # 0.885 m wide each side of it, so its body passes 0.385 m deep into the box).
    box = Box(10.0, 12.0, 0.5, 2.0, "a test wall")
    monkeypatch.setitem(OBSTACLES, "straight", (box,))
    rc = _sim("--scenario", "straight", "--out", str(tmp_path))
    err = capsys.readouterr().err
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["finished"] is True  # the route itself was driven
    assert metrics["clearance_min_m"] == pytest.approx(-0.385, abs=0.02)
    assert rc == 1
    assert "collision: the car's body went 0.3" in err and "into a test wall at t =" in err


def test_sim_set_applies_dotted_overrides(tmp_path: Path) -> None:
    out = tmp_path / "out"
    args = ["--set", "sim.plant.kind=steer-lag", "--set", "controller.mpc.weight_lateral=30"]
    assert _sim("--scenario", "straight", *args, "--out", str(out)) == 0
    assert json.loads((out / "metrics.json").read_text())["plant"] == "steer-lag"


def test_sim_set_and_replay_rerun_set_are_one_mechanism() -> None:
    assert rerun.parse_overrides is parse_overrides
    assert parse_overrides(["a.b=1", "c=[1, 2]"]) == {"a.b": 1, "c": [1, 2]}


@pytest.mark.parametrize(
    "args, words",
    [
        (["--set", "controller.mpc.no_such_key=1"], ["controller.mpc.no_such_key"]),
        (["--set", "controller.mpc.solver"], ["--set", "KEY=VALUE"]),
        (["--set", "controller.mpc.solver=gurobi"], ["solver", "gurobi"]),
        (["--trajectory", "x.csv", "--start", "1,2"], ["--start", "X,Y,HEADING_DEG"]),
        (["--trajectory", "x.csv", "--start", "1,2,nan"], ["--start", "finite"]),
        (["--start", "1,2,3"], ["--start", "--trajectory"]),
        (["--scenario", "u-turn", "--trajectory", "x.csv"], ["--scenario", "--trajectory"]),
        (["--trajectory", "/nonexistent/route.csv"], ["/nonexistent/route.csv", "no such file"]),
        (["--scenario", "hairpin"], ["hairpin", "tight-hairpin"]),
    ],
)
def test_sim_bad_arguments_give_one_line(
    args: list[str], words: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rc = _sim(*args, "--out", str(tmp_path))
    err = capsys.readouterr().err.strip()
    assert rc in (1, 2)
    assert len(err.splitlines()) == 1 and err.startswith("leafgate: error:")
    for word in words:
        assert word in err


def test_sim_help_lists_the_scenarios_and_the_trajectory_format(
    capsys: pytest.CaptureFixture[str],
) -> None:
    with pytest.raises(SystemExit):
        cli.main(["sim", "--help"])
    text = capsys.readouterr().out
    for name in SCENARIOS:
        assert name in text
    for words in ("x,y,heading,speed", "--trajectory", "--start", "--set", "negative = reverse"):
        assert words in text


@pytest.mark.parametrize(
    "args, model",
    [
        (["--plant", "steer-lag"], "kinematic_steer_lag"),
        (["--plant", "dynamic"], "kinematic_steer_lag"),
        ([], "kinematic"),
        (["--plant", "steer-lag", "--set", "controller.mpc.model=kinematic"], "kinematic"),
    ],
)
def test_sim_uses_the_steering_aware_model_where_the_wheel_lags(
    args: list[str], model: str, tmp_path: Path
) -> None:
    assert _sim("--scenario", "straight", *args, "--out", str(tmp_path)) == 0
    assert json.loads((tmp_path / "metrics.json").read_text())["model"] == model


def test_window_options_without_a_rolling_window_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert _sim("--window-resample", "--out", str(tmp_path)) == 2
    err = capsys.readouterr().err
    assert (
        err.strip()
        .splitlines()[-1]
        .endswith("--window-behind and --window-resample need --rolling-window")
    )
