"""``leafgate compare``: the report of every controller × plant × scenario (a small subset)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from leafgate.errors import ConfigError
from leafgate.settings import LeafgateConfig
from leafgate.sim.compare import (
    CONTROLLERS,
    TIE,
    add_arguments,
    cmd_compare,
    drive_config,
    run_compare,
)
from leafgate.sim.scenarios import OBSTACLES, SCENARIOS, Box, get_scenario

pytestmark = pytest.mark.slow

FEASIBLE = [name for name in SCENARIOS if get_scenario(name).feasible]


def test_report_holds_the_table_the_numbers_and_the_plots(tmp_path: Path) -> None:
    report = run_compare(
        LeafgateConfig(),
        tmp_path,
        scenarios=["s-curve"],
        plants=["dynamic"],
        controllers=["mpc", "mpc-steer", "stanley"],
        direct=True,
        workers=1,
    )
    saved = json.loads((tmp_path / "report.json").read_text(encoding="utf-8"))
    assert saved["runs"] == json.loads(json.dumps(report["runs"]))
    assert {r["controller"] for r in saved["runs"]} == {"mpc", "mpc-steer", "stanley"}
    for run in saved["runs"]:
        for key in (
            "lateral_error_rms_m",
            "lateral_error_max_m",
            "heading_error_max_rad",
            "final_position_error_m",
            "steer_rate_rms_radps",
            "steer_rate_max_radps",
            "steer_rate_sign_changes",
            "solve_time_median_s",
            "solve_time_p99_s",
        ):
            assert key in run["metrics"]
    errors = {r["controller"]: r["metrics"]["lateral_error_max_m"] for r in saved["runs"]}
    assert saved["best_lateral_max"]["s-curve"]["dynamic"] == min(errors, key=errors.get)
    text = (tmp_path / "report.md").read_text(encoding="utf-8")
    assert "## s-curve" in text and "| dynamic | stanley |" in text and "lat. max [m]" in text
    for name in ("path", "steering", "speed"):
        assert (tmp_path / "plots" / "s-curve" / "dynamic" / f"{name}.png").stat().st_size > 0
        # the paper's Figs. 2-4 pair: plain vs steering-aware MPC on the full vehicle plant
        assert (tmp_path / "paper-fig2-4" / "s-curve" / f"{name}.png").stat().st_size > 0
    assert "paper-fig2-4/s-curve/steering.png" in text


def test_report_says_when_a_drive_went_into_an_obstacle(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # a wall across the straight's left half, 0.5 m from its centre line: every car passes it
    # with its body 0.385 m deep in it (the Leaf is 0.885 m wide each side)
    monkeypatch.setitem(OBSTACLES, "straight", (Box(10.0, 12.0, 0.5, 2.0, "a test wall"),))
    kw = {"scenarios": ["straight"], "plants": ["kinematic"], "direct": True, "workers": 1}
    report = run_compare(LeafgateConfig(), tmp_path, controllers=["mpc"], **kw)
    assert report["runs"][0]["metrics"]["clearance_min_m"] < 0.0
    text = (tmp_path / "report.md").read_text(encoding="utf-8")
    assert "| yes; 0.38 m into a test wall |" in text or "| yes; 0.39 m into a test wall |" in text


def test_unknown_names_are_config_errors_listing_the_known_ones(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"known: .*stanley"):
        run_compare(LeafgateConfig(), tmp_path, controllers=["lqr"])
    with pytest.raises(ConfigError, match="unknown plant 'lgsvl'"):
        run_compare(LeafgateConfig(), tmp_path, plants=["kinematic,lgsvl"])
    with pytest.raises(ConfigError, match="scenario"):
        run_compare(LeafgateConfig(), tmp_path, scenarios=["hairpin"])


def test_drive_config_sets_controller_model_and_plant() -> None:
    cfg = drive_config(LeafgateConfig(), "mpc-steer", "steer-lag")
    assert cfg.controller.kind == "mpc" and cfg.controller.mpc.model == "kinematic_steer_lag"
    assert cfg.sim.plant.kind == "steer-lag"
    assert (
        drive_config(LeafgateConfig(), "pure-pursuit", "dynamic").controller.kind
        == (CONTROLLERS["pure-pursuit"][0])
    )


def test_command_line_entry_writes_the_report(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(
        [
            "--out",
            str(tmp_path),
            "--scenario",
            "straight",
            "--plant",
            "kinematic",
            "--controller",
            "pure-pursuit,stanley",
            "--direct",
            "--workers",
            "1",
            "--no-plots",
        ]
    )
    assert cmd_compare(args) == 0
    assert (tmp_path / "report.md").exists() and not (tmp_path / "plots").exists()
    assert "report.md" in capsys.readouterr().out


#: The MPC for each plant: the paper's kinematic model where the wheel follows the command at
#: once, the steering-aware model where it lags (the plain model oscillates there, see
#: tests/test_steer_aware_mpc.py).
MATCHED_MPC = {"kinematic": "mpc", "steer-lag": "mpc-steer", "dynamic": "mpc-steer"}


#: How far Pure Pursuit's max lateral error may be below the steering-aware MPC's on the
#: steer-lag plant (m). Measured 7.7 mm at most (switch-back, u-turn: 3.2 against 3.9 cm), once
#: the baselines stopped on the end instead of 0.3 m past it, which had counted as their error.
STEER_LAG_MARGIN = 0.01
#: How far Stanley's max lateral error may be below the MPC's on the kinematic plant (m).
#: Stanley feeds the plan's curvature forward on the front axle's path; on a plant that is
#: exactly its model that tracks tighter than the MPC on most scenarios, by up to 1.8 cm
#: (perpendicular park: 0.8 against 2.6 cm). Where the wheel lags, it is far behind.
KINEMATIC_MARGIN = 0.025


def test_mpc_lateral_error_against_the_baselines_on_every_scenario_and_plant(
    tmp_path: Path,
) -> None:
    """The matched MPC is the most accurate on every feasible scenario of the dynamic plant; on
    the steer-lag plant it is within STEER_LAG_MARGIN of the best baseline everywhere, and
    below it where the README says it is; on the kinematic plant within KINEMATIC_MARGIN."""
    for plant, mpc in MATCHED_MPC.items():
        report = run_compare(
            LeafgateConfig(),
            tmp_path / plant,
            scenarios=FEASIBLE,  # the infeasible hairpin has no accuracy to rank
            plants=[plant],
            controllers=[mpc, "pure-pursuit", "stanley"],
            direct=True,
            workers=2,
            plots=False,
        )
        errors: dict[tuple[str, str], float] = {
            (r["scenario"], r["controller"]): r["metrics"]["lateral_error_max_m"]
            for r in report["runs"]
        }
        for scenario in report["scenarios"]:
            mine = errors[(scenario, mpc)]
            best_baseline = min(errors[(scenario, b)] for b in ("pure-pursuit", "stanley"))
            if best_baseline <= TIE:  # a straight line: everyone on it, nothing to beat
                assert mine <= TIE, (scenario, plant)
            elif plant == "kinematic":
                assert mine < best_baseline + KINEMATIC_MARGIN, (scenario, mine, best_baseline)
            elif plant == "steer-lag" and scenario in (
                "s-curve",
                "switch-back",
                "closed-loop",
                "u-turn",
            ):
                assert mine < best_baseline + STEER_LAG_MARGIN, (scenario, mine, best_baseline)
            else:
                assert mine < best_baseline, (scenario, plant, mine, best_baseline)
            if plant != "kinematic":  # where the wheel lags, Stanley is no match for the MPC
                assert errors[(scenario, "stanley")] >= mine, (scenario, plant)


def test_compare_drives_the_route_library(tmp_path: Path) -> None:
    report = run_compare(
        LeafgateConfig(),
        tmp_path,
        plants=["kinematic"],
        controllers=["mpc"],
        direct=True,
        workers=1,
        plots=False,
    )
    library = {"switch-back", "figure-eight", "closed-loop", "u-turn", "corner", "cusp-retrace"}
    assert library | {"tight-hairpin"} <= set(report["scenarios"])
    finished = {r["scenario"]: r["metrics"]["finished"] for r in report["runs"]}
    assert all(finished[name] for name in library), finished
    text = (tmp_path / "report.md").read_text()
    assert "## tight-hairpin" in text and "Infeasible by design" in text


def test_command_line_lists_unfinished_drives_and_fails_on_a_feasible_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A drive on a feasible scenario that did not finish is a failed comparison (exit 1, named
    on stderr with its reason); one on an infeasible scenario is listed as expected (exit 0).

    Every feasible drive finishes with the default config, so the failure is made: a goal
    tolerance of 1 mm, which Pure Pursuit cannot stop within, keeps the U-turn from ending."""
    config = tmp_path / "tight.yaml"
    config.write_text("controller:\n  pure_pursuit:\n    goal_tolerance: 0.001\n", encoding="utf-8")
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    common = [
        "--plant",
        "steer-lag",
        "--controller",
        "pure-pursuit",
        "--workers",
        "1",
        "--no-plots",
    ]
    tight = ["--config", str(config)]
    args = parser.parse_args(
        ["--out", str(tmp_path / "a"), "--scenario", "u-turn,tight-hairpin", *tight, *common]
    )
    assert cmd_compare(args) == 1
    captured = capsys.readouterr()
    assert "u-turn:" in captured.err and "pure-pursuit × steer-lag plant: " in captured.err
    assert "tight-hairpin" not in captured.err
    assert "did not finish, as expected" in captured.out and "tight-hairpin:" in captured.out
    assert "1 feasible drives did not finish" in captured.out
    saved = json.loads((tmp_path / "a" / "report.json").read_text(encoding="utf-8"))
    assert {(d["scenario"], d["feasible"]) for d in saved["not_finished"]} == {
        ("u-turn", True),
        ("tight-hairpin", False),
    }
    (u_turn,) = [d for d in saved["not_finished"] if d["scenario"] == "u-turn"]
    assert u_turn["reason"] in captured.err  # the reason, as the report has it
    text = (tmp_path / "a" / "report.md").read_text(encoding="utf-8")
    assert "## Drives that did not finish" in text and "Not compared" in text

    args = parser.parse_args(["--out", str(tmp_path / "b"), "--scenario", "tight-hairpin", *common])
    assert cmd_compare(args) == 0  # the infeasible hairpin is expected not to finish
    captured = capsys.readouterr()
    assert captured.err == "" and "tight-hairpin:" in captured.out
    assert "0 feasible drives did not finish" in captured.out
    assert "Exit status" in (parser.epilog or "")
