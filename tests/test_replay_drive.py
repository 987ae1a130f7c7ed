"""A recorded closed-loop simulated drive: check, re-run, plot, and the formats it is kept in.

One s-curve drive is recorded once per module, through
the simulator's recorder hook, into every CAN log format and an MCAP session.
"""

from __future__ import annotations

import dataclasses
import io
import math
import subprocess
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import can
import pytest

from leafgate.can import e2e
from leafgate.can.codec import CanCodec
from leafgate.gateway.safety import CLAMP_KINDS
from leafgate.messages import SteerCommand
from leafgate.record.logs import FrameSource
from leafgate.record.recorder import CanLogRecorder, Recording, SessionRecorder
from leafgate.replay.check import LONG_KINDS, STEER_KINDS, check_log, main_check
from leafgate.replay.plot import main_plot
from leafgate.replay.rerun import main_rerun, rerun_session
from leafgate.settings import LeafgateConfig
from leafgate.sim.runner import ENGAGE_AT, SimResult, run
from leafgate.sim.scenarios import get_scenario

FORMATS = (".blf", ".log", ".asc")


@dataclass(frozen=True)
class Drive:
    result: SimResult
    logs: dict[str, Path]  # suffix → CAN log
    session: Path
    config: LeafgateConfig


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> Drive:
    directory = tmp_path_factory.mktemp("drive")
    config = LeafgateConfig()
    epoch = 1.8e9  # s: simulated time from 0 → Unix time, the same offset for every file
    can_logs = [CanLogRecorder(directory / f"can{suffix}", time_offset=epoch) for suffix in FORMATS]
    session = SessionRecorder(directory / "session.mcap", config, epoch=epoch)
    with Recording([*can_logs, session]) as recording:
        result = run(config, get_scenario("s-curve"), recorder=recording)
    assert recording.fault == ""
    logs = {suffix: rec.files[0] for suffix, rec in zip(FORMATS, can_logs, strict=True)}
    return Drive(result, logs, session.path, config)


def frames_of(path: Path) -> list[can.Message]:
    return list(FrameSource(path))


# --- recording ---------------------------------------------------------------------------------


def test_every_frame_in_and_out_is_recorded_in_each_format(drive: Drive) -> None:
    m = drive.result.metrics
    expected = m["can_frames_sent"] + m["can_frames_received"]
    for path in [*drive.logs.values(), drive.session]:
        frames = frames_of(path)
        assert len(frames) == expected, path.name
        assert sum(1 for f in frames if not f.is_rx) == m["can_frames_sent"], path.name


def test_formats_hold_the_same_frames_in_the_same_order(drive: Drive) -> None:
    reference = frames_of(drive.session)
    for path in drive.logs.values():
        frames = frames_of(path)
        assert [(f.arbitration_id, bytes(f.data)) for f in frames] == [
            (f.arbitration_id, bytes(f.data)) for f in reference
        ], path.name
        # BLF stores ns offsets from a ms-truncated start, text formats µs
        assert all(
            abs(a.timestamp - b.timestamp) < 2e-6 for a, b in zip(frames, reference, strict=True)
        ), path.name


def test_candump_log_is_read_by_cantools_decode(drive: Drive) -> None:
    dbc = Path(__file__).parents[1] / "dbc" / "leafgate_dbw.dbc"
    text = drive.logs[".log"].read_text()
    proc = subprocess.run(
        [sys.executable, "-m", "cantools", "decode", "--single-line", str(dbc)],
        input=text,
        capture_output=True,
        text=True,
        check=True,
    )
    decoded = [line for line in proc.stdout.splitlines() if ":: DBW_STEER_CMD(" in line]
    assert len(decoded) == text.count(" 0A0#")
    assert "ENABLE: 1" in "".join(decoded)


# --- check -------------------------------------------------------------------------------------


def test_check_of_recorded_drive_finds_nothing_and_counts_frames(drive: Drive) -> None:
    report = check_log(drive.logs[".blf"], profile="leafgate-dbw")
    assert report.findings == []
    assert (
        report.frames
        == drive.result.metrics["can_frames_sent"] + drive.result.metrics["can_frames_received"]
    )
    counts = Counter(f.arbitration_id for f in frames_of(drive.logs[".blf"]))
    assert {s.frame_id: s.frames for s in report.ids} == dict(counts)
    assert report.engaged_frames > 1000  # the drive was checked, not skipped


def test_check_of_session_agrees_with_check_of_log(drive: Drive) -> None:
    a = check_log(drive.session).to_dict()
    b = check_log(drive.logs[".log"], profile="leafgate-dbw").to_dict()
    for key in ("frames", "engaged_command_frames", "violations", "e2e_errors", "gaps"):
        assert a[key] == b[key], key


def test_check_exit_status_and_json(drive: Drive) -> None:
    out = io.StringIO()
    assert (
        main_check(
            drive.logs[".log"], profile="leafgate-dbw", as_json=True, out=out, err=io.StringIO()
        )
        == 0
    )
    assert '"ok": true' in out.getvalue()


def test_every_clamp_kind_of_the_gate_is_rechecked() -> None:
    assert set(CLAMP_KINDS) <= STEER_KINDS | LONG_KINDS


def _edited(frames: list[can.Message]) -> tuple[list[can.Message], float, float, float]:
    """The drive with an over-limit steering frame, a bad CRC and a 300 ms gap, far apart."""
    codec = CanCodec(profile="leafgate-dbw")
    engaged = [
        i
        for i, f in enumerate(frames)
        if f.arbitration_id == 0x0A0 and not f.is_rx and f.data[4] & 0x01
    ]
    assert engaged, "no engaged steering frame in the drive"
    t0 = frames[engaged[0]].timestamp
    # 1. an engaged steering command beyond the 31° road-wheel limit, with a valid CRC
    over = next(i for i in engaged if frames[i].timestamp >= t0 + 6.0)
    value = codec.decode(frames[over]).value
    assert isinstance(value, SteerCommand)
    edited = CanCodec(profile="leafgate-dbw").encode(
        SteerCommand(0.6, value.rate_limit, True, value.clear_override)
    )
    data = e2e.apply(0x0A0, edited.data, e2e.counter_of(frames[over].data))
    frames[over] = can.Message(
        timestamp=frames[over].timestamp,
        arbitration_id=0x0A0,
        data=data,
        is_extended_id=False,
        is_rx=False,
        channel=frames[over].channel,
    )
    # 2. a long report with one bit flipped
    bad = next(
        i for i, f in enumerate(frames) if f.arbitration_id == 0x0B1 and f.timestamp >= t0 + 10.0
    )
    flipped = bytearray(frames[bad].data)
    flipped[2] ^= 0x10
    frames[bad] = can.Message(
        timestamp=frames[bad].timestamp,
        arbitration_id=0x0B1,
        data=bytes(flipped),
        is_extended_id=False,
        channel=frames[bad].channel,
    )
    # 3. 300 ms without any frame while engaged
    gap_start = t0 + 3.0
    kept = [f for f in frames if not gap_start < f.timestamp < gap_start + 0.3]
    return kept, frames[over].timestamp, frames[bad].timestamp, gap_start


def test_edited_log_reports_exactly_the_three_edits_with_their_times(
    drive: Drive, tmp_path: Path
) -> None:
    frames, t_over, t_crc, t_gap = _edited(frames_of(drive.logs[".log"]))
    path = tmp_path / "edited.log"
    with can.Logger(path) as writer:
        for f in frames:
            writer.on_message_received(f)
    report = check_log(path, profile="leafgate-dbw")
    assert [(f.kind, f.detail) for f in report.findings] == [
        ("silence", report.findings[0].detail),  # the whole bus, once
        ("limit", "angle"),
        ("e2e", "bad_crc"),
        ("incomplete", report.findings[3].detail),  # written here, not by the recorder
    ]
    gap, limit, crc, _ = report.findings
    assert gap.time == pytest.approx(t_gap, abs=0.011)  # the last frame before the gap
    assert gap.value == pytest.approx(0.3, abs=0.02)
    assert limit.time == pytest.approx(t_over, abs=1e-6) and limit.frame_id == 0x0A0
    assert limit.value == pytest.approx(0.6) and limit.bound == pytest.approx(math.radians(31))
    assert crc.time == pytest.approx(t_crc, abs=1e-6) and crc.frame_id == 0x0B1
    assert main_check(path, profile="leafgate-dbw", out=io.StringIO(), err=io.StringIO()) == 1


def test_check_finds_a_forged_speed_report_by_the_wheel_speeds(
    drive: Drive, tmp_path: Path
) -> None:
    # issue 17, finding 4: `replay check` passed a log whose long reports said 20 m/s at 2 m/s
    frames = frames_of(drive.logs[".log"])
    codec = CanCodec(profile="leafgate-dbw")
    t0 = frames[0].timestamp
    forged_at = [f.timestamp for f in frames if f.arbitration_id == 0x0B1 and f.timestamp > t0 + 8]
    out = []
    for f in frames:
        if f.arbitration_id == 0x0B1 and t0 + 8.0 < f.timestamp < t0 + 8.5:
            decoded = codec.decode(f)  # the recorded counter follows on
            assert decoded.valid
            forged = dataclasses.replace(decoded.value, speed=20.0)
            data = e2e.apply(
                0x0B1, CanCodec(profile="leafgate-dbw").encode(forged).data, e2e.counter_of(f.data)
            )
            f = can.Message(
                timestamp=f.timestamp,
                arbitration_id=0x0B1,
                data=data,
                is_extended_id=False,
                channel=f.channel,
            )
        out.append(f)
    path = tmp_path / "forged.log"
    with can.Logger(path) as writer:
        for f in out:
            writer.on_message_received(f)
    report = check_log(path, profile="leafgate-dbw")
    reports = [f for f in report.findings if f.kind == "report"]
    assert reports, report.findings
    assert "disagrees with the" in reports[0].detail and "wheel speeds" in reports[0].detail
    assert reports[0].time == pytest.approx(forged_at[0], abs=0.05)
    assert len(reports) <= 2  # one per stretch, not one per frame
    assert not [f for f in report.findings if f.kind == "e2e"]  # CRC and counter were valid


# --- rerun -------------------------------------------------------------------------------------


def test_rerun_reproduces_every_command_bit_for_bit(drive: Drive) -> None:
    report = rerun_session(drive.session)
    assert report.identical, report.format()
    assert report.ticks == len(
        [f for f in frames_of(drive.session) if f.arbitration_id == 0x0A0 and not f.is_rx]
    )
    assert main_rerun(drive.session, out=io.StringIO()) == 0


def test_rerun_of_a_truncated_session_says_what_it_did_not_rerun(
    drive: Drive, tmp_path: Path
) -> None:
    """A session cut at half its size (a crash): the ticks it holds reproduce, and the verdict
    says they are all it checked. Old code: "every command reproduced bit for bit"."""
    data = drive.session.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    report = rerun_session(cut)
    assert report.truncated and report.identical and report.ticks > 0
    out = io.StringIO()
    assert main_rerun(cut, out=out) == 0
    verdict = out.getvalue().strip().splitlines()[-1]
    assert verdict.startswith(f"IDENTICAL up to the cut: the {report.ticks} ticks"), verdict
    assert "not re-run" in verdict and "every command" not in verdict


def test_rerun_with_changed_weight_reports_divergence(drive: Drive) -> None:
    report = rerun_session(drive.session, {"controller.mpc.weight_lateral": 10.0})
    assert not report.identical
    steer = next(s for s in report.signals if s.name == "steer.angle")
    assert steer.differing > 0 and steer.max_abs > 1e-4 and steer.rms > 0.0
    assert report.first_divergence is not None and report.first_divergence >= ENGAGE_AT - 1e-9
    out = io.StringIO()
    assert main_rerun(drive.session, overrides=["controller.mpc.weight_lateral=10"], out=out) == 1
    assert "DIVERGED" in out.getvalue()


@pytest.mark.parametrize(
    "override", ["sim.plant.kind=dynamic", "can.dbw.channel=vcan9", "recording.directory=/tmp/x"]
)
def test_rerun_refuses_an_override_it_cannot_honour(
    drive: Drive, override: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """A re-run feeds recorded inputs to the controller and gateway: a sim/can/recording key
    changes nothing, so an IDENTICAL verdict would be about a change never tested."""
    from leafgate.cli import main
    from leafgate.errors import ConfigError

    key = override.partition("=")[0]
    with pytest.raises(ConfigError, match=rf"--set {key}: .*vehicle, controller, gateway"):
        rerun_session(drive.session, {key: override.partition("=")[2]})
    assert main(["replay", "rerun", str(drive.session), "--set", override]) == 2
    captured = capsys.readouterr()
    assert "IDENTICAL" not in captured.out and f"--set {key}:" in captured.err
    # the sections a re-run builds from are still accepted
    ok = ["gateway.safety.max_steer_angle_deg=31", "vehicle.profile=leafgate-dbw"]
    assert main_rerun(drive.session, overrides=ok, out=io.StringIO()) in (0, 1)


# --- plot --------------------------------------------------------------------------------------


@pytest.mark.parametrize("source", ["session", ".blf"])
def test_plot_writes_path_steering_and_speed(drive: Drive, tmp_path: Path, source: str) -> None:
    path = drive.session if source == "session" else drive.logs[source]
    assert main_plot(path, out=tmp_path, profile="leafgate-dbw", stdout=io.StringIO()) == 0
    for name in ("path", "steering", "speed"):
        png = tmp_path / f"{name}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
