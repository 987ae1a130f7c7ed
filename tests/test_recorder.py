"""Recorders: formats, rotation, crash safety, faults instead of exceptions, session content."""

from __future__ import annotations

import itertools
import os
import time
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import Any

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from leafgate.config import from_mapping
from leafgate.config.recording import RecordingConfig
from leafgate.control import make_controller
from leafgate.errors import ConfigError
from leafgate.gateway.core import Gateway, GatewayInputs, StepResult
from leafgate.messages import LongMode, Pose, Stamped, Trajectory
from leafgate.record.logs import FrameSource
from leafgate.record.recorder import CanLogRecorder, SessionRecorder, open_recording
from leafgate.record.session import TOPIC_CAN, TOPIC_TICK, SessionReader
from leafgate.settings import LeafgateConfig
from leafgate.transport import cdr
from leafgate.transport.payloads import odometry_to_pose, pose_to_odometry
from tests.conftest import Disk, wait_for

FORMATS = (".blf", ".log", ".asc")


def tolerance(suffix: str) -> float:
    """s: BLF keeps ns from a ms start, candump µs, ASC its start in ms."""
    return 1.1e-3 if suffix == ".asc" else 2e-6


def frame(
    t: float, frame_id: int = 0x123, data: bytes = b"\x01\x02", rx: bool = True
) -> can.Message:
    return can.Message(
        timestamp=t,
        arbitration_id=frame_id,
        data=data,
        is_extended_id=False,
        is_rx=rx,
        channel="can0",
    )


def ticks(n: int, start: float = 0.0) -> Iterator[tuple[float, GatewayInputs, StepResult]]:
    """``n`` gateway ticks in STANDBY (the gateway really steps; no ECU is needed)."""
    config = LeafgateConfig()
    controller = make_controller(config.controller, config.vehicle, config.gateway.period)
    gateway = Gateway(config.gateway, config.vehicle, controller, LongMode.ACCELERATION)
    trajectory = Trajectory(
        x=[0.0, 0.5, 1.0], y=[0.0, 0.0, 0.0], heading=[0.0] * 3, speed=[1.0] * 3
    )
    for k in range(n):
        now = start + 0.02 * k
        inputs = GatewayInputs(
            pose=Stamped(Pose(0.01 * k, 0.0, 0.0, 0.0, stamp=now), now),
            trajectory=Stamped(trajectory, 0.0),
            steer_report=None,
            long_report=None,
            system_report=None,
        )
        yield now, inputs, gateway.step(now, inputs)


def record_ticks(rec: SessionRecorder, n: int, start: float = 0.0) -> None:
    for now, inputs, result in ticks(n, start):
        rec.on_can_frame(frame(now), "rx")
        rec.on_tick(now, inputs, result, [])


def read_ticks(path: Path) -> tuple[list[float], SessionReader]:
    with SessionReader(path) as reader:
        times = [r.json()["now"] for r in reader.records(frozenset({TOPIC_TICK}))]
    return times, reader


# --- CAN logs ----------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", FORMATS)
def test_sent_frames_are_restamped_and_marked_tx(tmp_path: Path, suffix: str) -> None:
    with CanLogRecorder(tmp_path / f"c{suffix}", tx_clock=lambda: 1_700_000_000.5) as rec:
        rec.on_can_frame(frame(1_700_000_000.25), "rx")
        rec.on_can_frame(frame(0.02, 0x0A0, bytes(8)), "tx")  # the gateway's own clock
    rx, tx = list(FrameSource(rec.files[0]))
    assert rx.is_rx and not tx.is_rx
    assert tx.timestamp == pytest.approx(1_700_000_000.5, abs=tolerance(suffix))
    assert rx.timestamp == pytest.approx(1_700_000_000.25, abs=tolerance(suffix))


@settings(
    max_examples=10, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    st.lists(
        st.tuples(
            st.integers(0, 0x7FF),
            st.binary(min_size=0, max_size=8),
            st.floats(0.0, 0.05),
            st.booleans(),
        ),
        min_size=1,
        max_size=40,
    ),
    st.sampled_from(FORMATS),
)
def test_frames_round_trip_through_each_format(
    tmp_path_factory: pytest.TempPathFactory,
    rows: list[tuple[int, bytes, float, bool]],
    suffix: str,
) -> None:
    path = tmp_path_factory.mktemp("rt") / f"c{suffix}"
    t = 1_700_000_000.0
    frames = []
    for frame_id, data, dt, rx in rows:
        t += dt
        frames.append(frame(t, frame_id, data, rx))
    with CanLogRecorder(path) as rec:
        for f in frames:
            rec.on_can_frame(f, "rx" if f.is_rx else "tx")
    back = list(FrameSource(rec.files[0]))
    assert [(f.arbitration_id, bytes(f.data), f.is_rx) for f in back] == [
        (f.arbitration_id, bytes(f.data), f.is_rx) for f in frames
    ]
    tol = tolerance(suffix)
    assert all(abs(a.timestamp - b.timestamp) < tol for a, b in zip(back, frames, strict=True))


def _channels(path: Path) -> list[object]:
    return [m.channel for m in FrameSource(path)]


@pytest.mark.parametrize("suffix", [*FORMATS, ".mcap"])
def test_every_format_names_a_frames_bus_by_one_rule(tmp_path: Path, suffix: str) -> None:
    """One rule (README, "Recording and replay"): a name format (candump, MCAP) writes the
    configured channel name of the frame's bus, a numbered one (BLF, ASC) the bus's number,
    CAN 1 for the drive-by-wire bus and CAN 2 for CAR-CAN (python-can reads them 0-based).
    Old code: BLF and ASC numbered a channel by the digits its name ends in: the multicast
    group 239.74.163.1 read back as 1, and the buses vcan0 and can0 were one channel, 0."""
    path = tmp_path / f"c{suffix}"
    one = {"channel": "239.74.163.1", "one_bus": True}
    two = {"channel": "vcan0", "car_channel": "can0"}
    frames = [
        frame(T0, 0x0B0),  # received on the dbw bus (its interface's own name for it)
        can.Message(timestamp=T0 + 0.01, arbitration_id=0x0A0, channel=None, is_rx=False),
    ]
    car = frame(T0 + 0.02, 0x284)
    if suffix == ".mcap":
        one_rec: Any = SessionRecorder(path, LeafgateConfig(), **one)
        # a session stores names: a received frame keeps its bus's
        two_rec: Any = SessionRecorder(tmp_path / "two.mcap", LeafgateConfig(), channel="vcan0")
    else:
        one_rec = CanLogRecorder(path, **one)
        two_rec = CanLogRecorder(tmp_path / f"two{suffix}", **two)
    with one_rec, two_rec:
        for msg in [*frames, car]:
            one_rec.on_can_frame(msg, "rx" if msg.is_rx else "tx")
        frames[0].channel = "vcan0"
        car.channel = "can0"
        for msg in [*frames, car]:
            two_rec.on_can_frame(msg, "rx" if msg.is_rx else "tx")
    one_path = one_rec.files[0]
    two_path = two_rec.files[0]
    if suffix in (".blf", ".asc"):
        assert _channels(one_path) == [0, 0, 0]
        assert _channels(two_path) == [0, 0, 1]
    else:
        assert _channels(one_path) == ["239.74.163.1"] * 3
        assert _channels(two_path) == ["vcan0", "vcan0", "can0"]


@pytest.mark.parametrize("suffix", FORMATS)
def test_log_rotates_by_size_and_keeps_every_frame_in_order(tmp_path: Path, suffix: str) -> None:
    frames = [frame(1.0 + 0.001 * i, 0x100 + i % 7, bytes([i % 256] * 8)) for i in range(3000)]
    with CanLogRecorder(tmp_path / f"c{suffix}", max_bytes=20_000) as rec:
        for f in frames:
            rec.on_can_frame(f, "rx")
    assert len(rec.files) > 2
    assert [p.name for p in rec.files][:2] == [f"c_000{suffix}", f"c_001{suffix}"]
    back = [f for path in rec.files for f in FrameSource(path)]
    assert [bytes(f.data) for f in back] == [bytes(f.data) for f in frames]


@pytest.mark.parametrize("suffix", FORMATS)
def test_flushed_log_survives_a_crash(tmp_path: Path, suffix: str) -> None:
    """A copy of the file taken after a flush, writer never closed, reads back every frame."""
    rec = CanLogRecorder(tmp_path / f"c{suffix}")
    frames = [frame(1_700_000_000.0 + 0.01 * i, 0x0B0, bytes([i % 256] * 8)) for i in range(200)]
    for f in frames:
        rec.on_can_frame(f, "rx")
    assert rec.flush()
    crashed = tmp_path / f"crashed{suffix}"
    crashed.write_bytes(rec.files[0].read_bytes())
    rec.close()
    back = list(FrameSource(crashed))
    assert [bytes(f.data) for f in back] == [bytes(f.data) for f in frames]
    assert back[0].timestamp == pytest.approx(frames[0].timestamp, abs=tolerance(suffix))


def test_unwritable_directory_is_a_fault_not_an_exception(tmp_path: Path) -> None:
    blocker = tmp_path / "not-a-directory"
    blocker.write_text("")
    can_log = CanLogRecorder(blocker / "sub" / "can.blf")
    session = SessionRecorder(blocker / "sub" / "session.mcap", LeafgateConfig())
    for rec in (can_log, session):
        assert "not-a-directory" in rec.fault
        rec.on_can_frame(frame(1.0), "rx")  # does not raise
        rec.close()
    assert can_log.diagnostics()["dropped"] == 1


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
def test_disk_full_is_a_fault_and_the_caller_keeps_running(tmp_path: Path) -> None:
    (tmp_path / "can_000.log").symlink_to("/dev/full")
    rec = CanLogRecorder(tmp_path / "can.log")
    for i in range(100):
        rec.on_can_frame(frame(float(i)), "rx")
    rec.flush()
    assert "No space left" in rec.fault
    rec.on_can_frame(frame(200.0), "rx")  # still accepted, counted as dropped
    rec.close()
    d = rec.diagnostics()
    assert d["errors"] >= 1 and d["dropped"] >= 1

    (tmp_path / "session.mcap").symlink_to("/dev/full")
    session = SessionRecorder(tmp_path / "session.mcap", LeafgateConfig())
    record_ticks(session, 3)
    session.close()
    assert "No space left" in session.fault


# --- sessions ----------------------------------------------------------------------------------


def test_closed_session_is_a_complete_indexed_mcap(tmp_path: Path) -> None:
    path = tmp_path / "s.mcap"
    with SessionRecorder(path, LeafgateConfig()) as rec:
        record_ticks(rec, 20)
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        counts = {
            summary.channels[c].topic: n
            for c, n in summary.statistics.channel_message_counts.items()
        }
        assert counts[TOPIC_TICK] == 20 and counts[TOPIC_CAN] == 20 + 1  # + the end marker
        assert {m.name for m in reader.iter_metadata()} >= {"leafgate.config", "leafgate.session"}
    times, reader_ = read_ticks(path)
    assert len(times) == 20 and not reader_.truncated


def test_session_cut_mid_write_yields_every_record_up_to_the_last_flush(tmp_path: Path) -> None:
    path = tmp_path / "s.mcap"
    rec = SessionRecorder(path, LeafgateConfig())
    record_ticks(rec, 30)
    assert rec.flush()
    flushed = path.stat().st_size
    record_ticks(rec, 30, start=10.0)
    assert rec.flush()
    data = path.read_bytes()  # the process "crashes" here: no summary, no footer
    rec.close()
    assert len(data) > flushed
    expected, _ = read_ticks(path)
    for cut in (flushed + 1, flushed + 40, flushed + 400):  # inside the second chunk
        crashed = tmp_path / f"crash-{cut}.mcap"
        crashed.write_bytes(data[:cut])
        times, reader = read_ticks(crashed)
        assert reader.truncated and reader.error
        assert times == expected[:30], cut  # everything of the first flush
        assert reader.config().gateway.period == LeafgateConfig().gateway.period
    crashed = tmp_path / "crash-at-flush.mcap"
    crashed.write_bytes(data)
    times, reader = read_ticks(crashed)
    assert len(times) == 60 and reader.truncated


def test_zenoh_cdr_input_is_recorded_raw_with_its_ros2msg_schema(tmp_path: Path) -> None:
    payload = cdr.serialize(pose_to_odometry(Pose(1.5, -2.0, 0.3, 1.0, stamp=12.0)), cdr.ODOMETRY)
    path = tmp_path / "s.mcap"
    with SessionRecorder(path, LeafgateConfig()) as rec:
        rec.on_zenoh_input("leaf/localization/kinematic_state", payload, 3.25, cdr.ODOMETRY)
        rec.on_zenoh_input("leaf/planning/trajectory", b'{"x": []}', 3.5, None)
    with path.open("rb") as f:
        reader = make_reader(f)
        messages = {ch.topic: (schema, ch, msg) for schema, ch, msg in reader.iter_messages()}
        start = next(m for m in reader.iter_metadata() if m.name == "leafgate.session")
    schema, channel, msg = messages["/leaf/localization/kinematic_state"]
    assert channel.message_encoding == "cdr"
    assert schema is not None and schema.encoding == "ros2msg" and schema.name == cdr.ODOMETRY
    assert schema.data.decode() == cdr.msg_definition(cdr.ODOMETRY)
    assert msg.data == payload
    # Unix-epoch log time: the simulated 3.25 s after the recording's wall-clock start.
    assert msg.log_time - int(start.metadata["epoch_offset_ns"]) == 3_250_000_000
    assert odometry_to_pose(cdr.deserialize(msg.data, cdr.ODOMETRY)).x == 1.5
    assert messages["/leaf/planning/trajectory"][1].message_encoding == "json"


def test_one_trajectory_object_is_stored_once(tmp_path: Path) -> None:
    path = tmp_path / "s.mcap"
    with SessionRecorder(path, LeafgateConfig()) as rec:
        record_ticks(rec, 25)
    with SessionReader(path) as reader:
        topics = [r.topic for r in reader.records()]
    assert topics.count("/leafgate/trajectory") == 1


# --- configuration ------------------------------------------------------------------------------


def test_recording_config_rejects_unknown_formats_and_slow_flushes() -> None:
    with pytest.raises(ConfigError, match="recording: can_log"):
        from_mapping(RecordingConfig, {"can_log": "x.txt"}, "f.yaml", "recording")
    with pytest.raises(ConfigError, match="flush_period"):
        from_mapping(RecordingConfig, {"flush_period": 2.0}, "f.yaml", "recording")
    assert from_mapping(RecordingConfig, {"can_log": "c.asc"}, "f.yaml").can_log == "c.asc"


def test_open_recording_names_files_by_start_time(tmp_path: Path) -> None:
    assert open_recording(RecordingConfig(), LeafgateConfig()).recorders == ()
    cfg = RecordingConfig(enabled=True, directory=str(tmp_path / "rec"), can_log="can-{start}.log")
    with open_recording(cfg, LeafgateConfig(), start=datetime(2025, 1, 31, 14, 15)) as recording:
        recording.on_can_frame(frame(1.0), "rx")
        assert recording.fault == ""
    names = sorted(p.name for p in (tmp_path / "rec").iterdir())
    assert names == ["can-20250131T141500_000.log", "session-20250131T141500.mcap"]
    assert set(recording.diagnostics()) == {"fault", "can_log", "session"}


# --- recording that fails loudly (issue 17, finding 6) ------------------------------------------


def test_session_queue_is_bounded_in_bytes(tmp_path: Path) -> None:
    # 120 junk payloads of 10 MB raised the daemon from 140 MB to 1.29 GB
    rec = SessionRecorder(tmp_path / "s.mcap", LeafgateConfig(), queue_bytes=25_000_000)
    junk = bytes(10_000_000)
    for _ in range(20):
        rec.on_zenoh_input("leaf/localization/kinematic_state", junk, 1.0)
    counters = rec.diagnostics()
    assert counters["queued_bytes"] <= 25_000_000
    rec.close()
    assert rec._bg.dropped_bytes > 0  # the writer cannot keep up with 200 MB at once


def test_recording_failure_is_logged_as_a_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    blocked = tmp_path / "not-a-directory"
    blocked.write_text("")
    with CanLogRecorder(blocked / "c.blf") as rec:
        assert rec.fault
    assert any(r.levelname == "WARNING" and "recording" in r.getMessage() for r in caplog.records)


def test_check_reports_a_log_without_its_end_marker_as_incomplete(tmp_path: Path) -> None:
    from leafgate.replay.check import check_log

    closed = tmp_path / "closed.log"
    with CanLogRecorder(closed) as rec:
        for k in range(5):
            rec.on_can_frame(frame(1_700_000_000.0 + 0.01 * k), "rx")
    report = check_log(rec.files[0], profile="leafgate-dbw")
    assert report.count("incomplete") == 0
    cut = tmp_path / "cut.log"
    with can.Logger(cut) as writer:
        for msg in list(FrameSource(rec.files[0]))[:3]:  # a log that stops early
            writer.on_message_received(msg)
    report = check_log(cut, profile="leafgate-dbw")
    (finding,) = [f for f in report.findings if f.kind == "incomplete"]
    assert "stops after frame 3" in finding.detail
    assert finding.time == pytest.approx(1_700_000_000.02)
    # the verdict says why it failed: it read "FAILED: … 0 E2E errors, 0 gaps, …" and no more
    verdict = report.format()[-1]
    assert verdict.startswith("FAILED:") and verdict.endswith(", 1 incomplete finding"), verdict


def test_engage_refused_while_a_required_recording_fails() -> None:
    from leafgate.runtime.daemon import recording_refusal

    cfg = from_mapping(
        LeafgateConfig, {"recording": {"enabled": True, "required": True}}, "test.yaml"
    )
    assert recording_refusal(cfg, "") is None
    reason = recording_refusal(cfg, "session s.mcap: write: No space left on device")
    assert reason is not None and "No space left on device" in reason
    off = from_mapping(LeafgateConfig, {"recording": {"required": True}}, "test.yaml")
    assert recording_refusal(off, "") is not None
    assert recording_refusal(LeafgateConfig(), "any fault") is None  # not required


# --- a full disk is a fault while it lasts ---------------------------------------------------------


def test_a_full_disk_is_a_session_fault_while_it_lasts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """Old code: the file was given up for good; the fault (and a required recording's engage
    refusal) lasted until the daemon restarted, long after the space was freed."""
    disk = Disk(tmp_path)
    disk.install(monkeypatch)
    path = tmp_path / "s.mcap"
    rec = SessionRecorder(path, LeafgateConfig(), flush_period=0.05, retry_period=0.2)
    record_ticks(rec, 20)
    assert rec.flush() and rec.fault == ""
    disk.free = 0
    record_ticks(rec, 20, start=1.0)
    rec.flush()
    assert "No space left" in rec.fault
    time.sleep(0.5)  # attempts at a new file while the disk is full fail, and leave none
    record_ticks(rec, 5, start=2.0)
    assert "No space left" in rec.fault
    assert not (tmp_path / "s.3.mcap").exists()  # no trail of empty files
    disk.free = 10**9  # space freed
    assert wait_for(lambda: record_ticks(rec, 1, start=5.0) or rec.fault == ""), rec.fault
    record_ticks(rec, 20, start=10.0)
    rec.close()
    d = rec.diagnostics()
    assert d["recoveries"] == 1 and d["lost"] >= 50 and "No space left" in d["last_fault"]
    assert [p.name for p in rec.files] == ["s.mcap", "s.2.mcap"]
    assert any("resumed" in r.getMessage() and "dropped" in r.getMessage() for r in caplog.records)
    # the broken file ends without footer or end marker; the new one is a whole session
    broken = FrameSource(path, markers=True)
    frames = list(broken)
    assert broken.truncated and not broken.ended and len(frames) == 20
    times, reader = read_ticks(tmp_path / "s.2.mcap")
    assert not reader.truncated and times[-20:] == [10.0 + 0.02 * k for k in range(20)]
    assert reader.metadata["leafgate.session"]["resumes"] == "s.mcap"
    resumed = FrameSource(tmp_path / "s.2.mcap", markers=True)
    list(resumed)
    assert resumed.ended


T0 = 1_700_000_000.0  # s, Unix time (BLF and ASC store a calendar start)


@pytest.mark.parametrize("suffix", FORMATS)
def test_a_full_disk_is_a_can_log_fault_while_it_lasts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, suffix: str
) -> None:
    disk = Disk(tmp_path)
    disk.install(monkeypatch)
    rec = CanLogRecorder(tmp_path / f"can{suffix}", flush_period=0.05, retry_period=0.2)
    for k in range(50):
        rec.on_can_frame(frame(T0 + 0.01 * k), "rx")
    assert rec.flush() and rec.fault == ""
    disk.free = 0
    for k in range(50):
        rec.on_can_frame(frame(T0 + 1.0 + 0.01 * k), "rx")
    rec.flush()
    assert "No space left" in rec.fault
    time.sleep(0.5)
    assert "No space left" in rec.fault and len(rec.files) <= 2  # no trail of empty parts
    disk.free = 10**9
    assert wait_for(lambda: rec.on_can_frame(frame(T0 + 5.0), "rx") or rec.fault == "")
    for k in range(50):
        rec.on_can_frame(frame(T0 + 10.0 + 0.01 * k), "rx")
    rec.close()
    assert [p.name for p in rec.files] == [f"can_000{suffix}", f"can_001{suffix}"]
    assert rec.diagnostics()["recoveries"] == 1 and rec.diagnostics()["lost"] >= 1
    first = FrameSource(rec.files[0], markers=True)
    assert len(list(first)) >= 50 and not first.ended  # given up as it was: no end marker
    second = FrameSource(rec.files[1], markers=True)
    frames = list(second)
    # the next part starts with the first frame after the outage: one hole, between the parts
    assert second.ended and frames[0].timestamp == pytest.approx(T0 + 5.0, abs=2e-3)
    assert all(a.timestamp <= b.timestamp + 2e-3 for a, b in itertools.pairwise(frames))
    assert frames[-2].timestamp == pytest.approx(T0 + 10.49, abs=2e-3)


def test_a_session_fed_from_two_threads_is_written_in_time_order(tmp_path: Path) -> None:
    """Old code wrote items as they arrived: a frame received during a tick (bus thread,
    stamped then) came before the tick and the frames it sent (control thread, stamped at
    the tick's start), so every daemon session went backwards by up to a tick."""
    now = [0.0]
    path = tmp_path / "s.mcap"
    rec = SessionRecorder(path, LeafgateConfig(), clock=lambda: now[0], epoch=T0)
    for t, inputs, result in ticks(100):
        now[0] = t + 0.012  # the tick took 12 ms; a frame arrived meanwhile
        rec.on_can_frame(frame(t + 0.012), "rx")
        rec.on_tick(t, inputs, result, [frame(t, 0x0A0, rx=False)])
        rec.on_zenoh_input("/localization/kinematic_state", b"{}", t + 0.001)
    # a tick beyond the reorder window: logged at the last time written, and counted
    rec.on_tick(0.505, *next(iter(ticks(1)))[1:], [])
    rec.close()
    with SessionReader(path) as reader:
        records = list(reader.records())
    times = [r.log_time for r in records]
    assert times == sorted(times)
    source = FrameSource(path)
    stamps = [m.timestamp for m in source]
    assert len(stamps) == 200 and stamps == sorted(stamps)
    (late_tick,) = [r for r in records if r.topic == TOPIC_TICK and r.json()["now"] == 0.505]
    assert late_tick.log_time > (T0 + 1.7) * 1e9  # logged late; its own time kept exact
    assert rec.diagnostics()["late"] == 1
