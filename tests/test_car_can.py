"""Leaf CAR-CAN as the car sends it (issue 15): every row of the table, by hand-derived bytes.

Worked examples (the facts: 2016 AZE0 Leaf and e-NV200 recordings, issue 15):

* 0x002 STEER_ANGLE_SENSOR, +10.0° at the steering wheel, counter 3: raw 10 / −0.1 = −100 =
  0xFF9C little-endian → ``9C FF``; rate ``00``; byte 3 always ``07``; byte 4 low nibble the
  counter 3, high nibble the XOR of the nibbles 9, C, F, F, 0, 0, 0, 7 and the counter 3:
  9^C = 5, ^F = A, ^F = 5, ^7 = 2, ^3 = 1 → byte 4 = ``13``.
  −5.0°, counter 0: raw +50 = 0x0032 → ``32 00 00 07``; 3^2^7^0 = 6 → byte 4 = ``60``.
* 0x176 OUTPUT_SPEED, 50 km/h: 50 × 8.570637 = 428.53 → 429 rpm = ``01 AD``; byte 6 the 4-bit
  counter (5 → ``05``): ``01 AD 00 00 00 00 05``.
* 0x284 WHEEL_SPEEDS_FRONT, 3.6 km/h both wheels: 3.6 / 0.005 = 720 = ``02 D0``; counter 0x10
  in byte 6, byte 7 = 0x10 + 0x86 = ``96``. 0x285 with counter 0xFF: 0xFF + 0x87 = 0x186 →
  ``86``.
* 0x421 GEAR_POSITION: 3 bytes; D = 4 in bits 7..3 of byte 0 → ``20 00 00``; P ``08 00 00``.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import can
import cantools
import pytest
from cantools.database.can import Database

from leafgate.can import e2e
from leafgate.can.codec import CanCodec
from leafgate.can.profile import Profile
from leafgate.config import VehicleConfig
from leafgate.config.sim import EcuConfig
from leafgate.gateway.safety import SafetyLimits
from leafgate.messages import (
    Gear,
    GearPosition,
    LongCommand,
    LongReport,
    MotorSpeed,
    Pose,
    SteerCommand,
    SteeringWheelAngle,
    SteerReport,
    WheelSpeeds,
)
from leafgate.record.logs import FrameSource
from leafgate.record.recorder import CanLogRecorder, Recording, SessionRecorder
from leafgate.replay.check import CheckReport, check_frames, check_log
from leafgate.replay.plot import main_plot
from leafgate.settings import LeafgateConfig, with_profile
from leafgate.sim.ecu import SimulatedEcu
from leafgate.sim.plant import make_plant
from leafgate.sim.runner import run
from leafgate.sim.scenarios import get_scenario

ROOT = Path(__file__).resolve().parent.parent
DBC = ROOT / "leafgate" / "data" / "dbc"
DEG = math.pi / 180.0
PROFILES = ("leafgate-dbw", "sze-hlc", "leaf-ze1-lkas")


def frame(frame_id: int, hex_bytes: str, t: float = 0.0) -> can.Message:
    return can.Message(
        timestamp=t, arbitration_id=frame_id, data=bytes.fromhex(hex_bytes), is_extended_id=False
    )


def replaced(msg: can.Message, **changes: object) -> can.Message:
    """A copy of a recorded frame with its timestamp or data changed."""
    fields: dict[str, object] = {
        "timestamp": msg.timestamp,
        "arbitration_id": msg.arbitration_id,
        "data": bytes(msg.data),
        "is_extended_id": False,
        "channel": msg.channel,
        **changes,
    }
    return can.Message(**fields)  # type: ignore[arg-type]


# --- the table, byte by byte ---------------------------------------------------------------------


def test_0x002_byte_3_is_0x07_and_byte_4_carries_counter_and_nibble_checksum() -> None:
    codec = CanCodec(profile="leafgate-dbw")
    frames = [codec.encode(SteeringWheelAngle(angle=10.0 * DEG)) for _ in range(4)]
    assert bytes(frames[3].data).hex(" ") == "9c ff 00 07 13"  # counter 3
    other = CanCodec(profile="sze-hlc")  # the same frame, read into the steering report
    assert other.decode(frame(0x002, "9C FF 00 07 13")).valid
    assert e2e.nissan_nibble_checksum(bytes.fromhex("32 00 00 07 00")) == 0x6
    assert CanCodec(profile="leafgate-dbw").decode(frame(0x002, "32 00 00 07 60")).valid


def test_0x176_is_output_shaft_rpm_with_a_4_bit_counter_in_byte_6() -> None:
    codec = CanCodec(profile="leafgate-dbw")
    frames = [codec.encode(MotorSpeed(speed=50 / 3.6)) for _ in range(6)]
    assert bytes(frames[5].data).hex(" ") == "01 ad 00 00 00 00 05"
    decoded = CanCodec(profile="leafgate-dbw").decode(frame(0x176, "01 AD 00 00 00 00 05"))
    assert decoded.valid
    assert decoded.value == MotorSpeed(speed=429 / 8.570637 / 3.6)


def test_0x284_0x285_byte_7_is_the_8_bit_counter_plus_0x86_or_0x87() -> None:
    codec = CanCodec(profile="leafgate-dbw")
    for _ in range(0x10):
        codec.encode(WheelSpeeds(left=1.0, right=1.0, axle="front"))
    front = codec.encode(WheelSpeeds(left=1.0, right=1.0, axle="front"))
    assert bytes(front.data).hex(" ") == "02 d0 02 d0 00 00 10 96"
    rx = CanCodec(profile="leafgate-dbw")
    assert rx.decode(frame(0x285, "02 D0 02 D0 00 00 FF 86")).valid
    assert rx.decode(frame(0x285, "02 D0 02 D0 00 00 00 87")).valid  # 0xFF → 0x00 wraps


def test_0x421_is_3_bytes_every_60_ms() -> None:
    codec = CanCodec(profile="leafgate-dbw")
    assert bytes(codec.encode(GearPosition(Gear.D)).data).hex(" ") == "20 00 00"
    assert bytes(codec.encode(GearPosition(Gear.P)).data).hex(" ") == "08 00 00"
    for profile in ("leafgate-dbw", "sze-hlc"):
        spec = CanCodec(profile=profile).profile.frame("GEAR_POSITION")
        assert spec.period == 0.06 and spec.on_change
    assert CanCodec(profile="leaf-ze1-lkas").profile.frame("GEARBOX").period == 0.04  # 25 Hz


@pytest.mark.parametrize(
    ("frame_id", "good", "bad", "error"),
    [
        (0x002, "9C FF 00 07 13", "9C FF 00 07 23", "bad_crc"),  # one checksum nibble
        (0x284, "02 D0 02 D0 00 00 10 96", "02 D0 02 D0 00 00 10 97", "bad_crc"),
        (0x285, "02 D0 02 D0 00 00 10 97", "02 D0 02 D0 00 00 10 96", "bad_crc"),
    ],
)
def test_a_wrong_checksum_of_a_car_frame_is_rejected(
    frame_id: int, good: str, bad: str, error: str
) -> None:
    codec = CanCodec(profile="leafgate-dbw")
    assert codec.decode(frame(frame_id, good)).valid
    decoded = codec.decode(frame(frame_id, bad))
    assert decoded.error == error and decoded.counts_for_reports
    assert codec.stats[frame_id].bad_crc == 1  # per ID, as diagnostics show it


@pytest.mark.parametrize(
    ("frame_id", "first", "repeat"),
    [
        (0x002, "9C FF 00 07 13", "9C FF 00 07 13"),
        (0x176, "01 AD 00 00 00 00 05", "01 AD 00 00 00 00 05"),
        (0x284, "02 D0 02 D0 00 00 10 96", "02 D0 02 D0 00 00 10 96"),
    ],
)
def test_a_repeated_counter_of_a_car_frame_is_rejected(
    frame_id: int, first: str, repeat: str
) -> None:
    codec = CanCodec(profile="leafgate-dbw")
    assert codec.decode(frame(frame_id, first)).valid
    decoded = codec.decode(frame(frame_id, repeat))
    assert decoded.error == "bad_counter" and decoded.counts_for_reports
    assert codec.stats[frame_id].bad_counter == 1


def test_sze_hlc_says_the_feedback_check_is_its_only_e2e_check() -> None:
    protection = CanCodec(profile="sze-hlc").profile.protection
    assert "only end-to-end check" in protection


def test_the_ze1_reads_its_measured_angle_from_0x185_not_0x002() -> None:
    # 0x185, +10.00 deg at the wheel: raw (1310 - 10) / 0.01 = 130000 = data[2] << 10 |
    # data[3] << 2 | data[4] >> 6 → 7E F4 00 in bytes 2-4; driver torque 0 → raw 2047 = 7F F.
    # 0x002 says −5.0 deg (32 00): the coarse sensor, kept apart as the steering-wheel angle.
    codec = CanCodec(profile="leaf-ze1-lkas")
    ratio = VehicleConfig().steering_ratio
    coarse = codec.decode(frame(0x002, "32 00 00 07 00"))
    assert coarse.valid and coarse.values == (SteeringWheelAngle(angle=-5.0 * DEG),)
    fine = codec.decode(frame(0x185, "7F F0 7E F4 00 00 00 00"))
    assert fine.valid
    steer = fine.values[0]
    assert isinstance(steer, SteerReport)
    assert steer.angle == pytest.approx(10.0 * DEG / ratio, abs=1e-12)
    assert steer.driver_torque == pytest.approx(0.0, abs=1e-9)


# --- cantools reads the shipped DBCs on real-shaped frames --------------------------------------


REAL_SHAPED = {  # frames as the recordings show them
    0x002: "9C FF 00 07 13",
    0x176: "01 AD 00 00 00 00 05",
    0x284: "02 D0 02 D0 00 00 10 96",
    0x285: "02 D0 02 D0 00 00 10 97",
    0x421: "20 00 40",  # byte 2 bit 6 set, as on one of the cars
}


@pytest.mark.parametrize("dbc", ["leaf_aze0_car.dbc", "sze_hlc.dbc"])
def test_cantools_decodes_real_shaped_frames_with_the_shipped_dbcs(dbc: str) -> None:
    db = cantools.database.load_file(DBC / dbc, strict=True)
    assert isinstance(db, Database)
    known = {m.frame_id for m in db.messages}
    for frame_id, data in REAL_SHAPED.items():
        if frame_id in known:
            db.decode_message(frame_id, bytes.fromhex(data))  # raises on a wrong length


def test_cantools_decode_command_reads_a_real_shaped_candump(tmp_path: Path) -> None:
    lines = "".join(
        f"(0.{i:06d}) can0 {fid:03X}#{data.replace(' ', '')}\n"
        for i, (fid, data) in enumerate(REAL_SHAPED.items())
    )
    result = subprocess.run(
        [sys.executable, "-m", "cantools", "decode", str(DBC / "leaf_aze0_car.dbc")],
        input=lines,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    assert "Wrong data size" not in result.stdout and "Unknown" not in result.stdout
    assert "GEAR_POSITION" in result.stdout and "OUTPUT_SPEED" in result.stdout


# --- unknown stays unknown -------------------------------------------------------------------------


@pytest.mark.parametrize("profile", ["sze-hlc", "leaf-ze1-lkas"])
def test_gear_is_unknown_until_the_first_gear_frame(profile: str) -> None:
    ecu = CanCodec(profile=profile)
    rx = CanCodec(profile=profile)
    speed_frame = "OUTPUT_SPEED" if profile == "sze-hlc" else "WHEEL_SPEEDS_REAR"
    values = {
        "long": LongReport(0.0, 0.0, Gear.P, 0.0, 0.0, False, False, False, False),
        "wheels_rear": WheelSpeeds(left=0.0, right=0.0, axle="rear"),
    }
    before = rx.decode(ecu.encode_frame(speed_frame, values))
    reports = [v for v in before.values if isinstance(v, LongReport)]
    assert reports and reports[0].gear == Gear.NONE  # not the profile's old default D
    gear_name = "GEAR_POSITION" if profile == "sze-hlc" else "GEARBOX"
    rx.decode(ecu.encode_frame(gear_name, values))
    after = rx.decode(ecu.encode_frame(speed_frame, values))
    assert next(v for v in after.values if isinstance(v, LongReport)).gear == Gear.P


# Engage is refused while the gear is unknown: tests/test_state_machine.py, row gear_unknown.


# --- the simulated ECU sends the frames as the car does -------------------------------------------


def test_simulated_ecu_sends_an_event_gear_frame_soon_after_a_gear_change() -> None:
    vehicle = VehicleConfig()
    plant = make_plant(LeafgateConfig().sim.plant, vehicle, Pose(0.0, 0.0, 0.0, 0.0))
    ecu = SimulatedEcu(EcuConfig(), plant, vehicle, CanCodec(profile="leafgate-dbw"))
    gear_frames: list[tuple[float, bytes]] = []
    for tick in range(20):  # 10 ms ticks
        now = tick * 0.01
        if tick == 8:
            assert plant.set_gear(Gear.R)  # at rest: accepted
        gear_frames += [(now, bytes(m.data)) for m in ecu.reports(now) if m.arbitration_id == 0x421]
    times = [round(t, 3) for t, _ in gear_frames]
    assert times == [0.0, 0.06, 0.08, 0.12, 0.18]  # cyclic 60 ms + the event frame at 80 ms
    assert [d for _, d in gear_frames] == [bytes.fromhex(x) for x in ("200000",) * 2] + [
        bytes.fromhex("100000")
    ] * 3


# --- simulated recordings through replay check ---------------------------------------------------


@dataclass(frozen=True)
class Recorded:
    profile: str
    log: Path  # candump .log
    session: Path
    frames: list[can.Message]


@pytest.fixture(scope="module", params=PROFILES)
def recorded(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Recorded:
    profile = request.param
    directory = tmp_path_factory.mktemp(profile)
    config = with_profile(LeafgateConfig(), profile)
    can_log = CanLogRecorder(directory / "can.log", channel="can0", one_bus=True)
    session = SessionRecorder(directory / "session.mcap", config)
    with Recording([can_log, session]) as recording:
        run(config, get_scenario("s-curve"), recorder=recording)
    assert recording.fault == ""
    log = can_log.files[0]
    return Recorded(profile, log, session.path, list(FrameSource(log)))


@functools.cache
def _limits_of(profile: str) -> tuple[SafetyLimits, Profile]:
    cfg = with_profile(LeafgateConfig(), profile)
    limits = SafetyLimits.from_config(cfg.gateway.safety, cfg.vehicle, cfg.gateway.period)
    return limits, cfg.profile


def _check(rec: Recorded, frames: list[can.Message]) -> CheckReport:
    limits, profile = _limits_of(rec.profile)
    return check_frames(frames, limits, profile)


def test_a_simulated_recording_checks_ok_with_its_engaged_frames_checked(rec: Recorded) -> None:
    for report in (
        check_log(rec.log, profile=rec.profile),
        check_log(rec.session),  # the profile from the session's recorded configuration
    ):
        assert report.profile == rec.profile
        assert report.engaged_frames > 0
        assert report.ok, report.format()
        assert not any(f.kind in ("period", "e2e", "silence", "gap") for f in report.findings)
        assert report.backwards == 0


@pytest.fixture
def rec(recorded: Recorded) -> Recorded:
    return recorded


def _engaged_command(rec: Recorded) -> int:
    """The index of an engaged steering command frame in the middle of the drive."""
    codec = CanCodec(profile=rec.profile)
    steer_id = codec.frame_id(codec.profile.frames_of("command")[0].name)
    found = []
    for i, msg in enumerate(rec.frames):
        decoded = codec.decode(msg)
        engaged = any(getattr(v, "enable", False) for v in decoded.values)
        if msg.arbitration_id == steer_id and decoded.valid and engaged:
            found.append(i)
    return found[len(found) // 2]


def test_one_planted_over_limit_frame_fails_the_check_naming_it(rec: Recorded) -> None:
    index = _engaged_command(rec)
    target = rec.frames[index]
    codec = CanCodec(profile=rec.profile)
    name = codec.profile.frames_of("command")[0].name
    decoded = CanCodec(profile=rec.profile).decode(target)  # a first frame: valid
    values = _sources(decoded.values)
    steer = values["steer"]
    assert isinstance(steer, SteerCommand) and steer.enable
    values["steer"] = dataclasses.replace(steer, angle=steer.angle + 0.05)  # a 0.05 rad jump
    data = bytearray(codec.encode_frame(name, values).data)
    scheme = codec.profile.frame(name).e2e
    if scheme == "leafgate":  # keep the recorded alive counter, with a CRC that fits
        data = bytearray(e2e.apply(target.arbitration_id, data, e2e.counter_of(target.data)))
    elif scheme == "nissan-lkas":  # the counter is the low nibble of byte 6
        data[6] = (data[6] & 0xF0) | (target.data[6] & 0x0F)
        data[7] = e2e.crc8_nissan_lkas(data)
    planted = list(rec.frames)
    planted[index] = replaced(target, data=bytes(data))
    report = _check(rec, planted)
    limits = [f for f in report.findings if f.kind == "limit"]
    assert not report.ok
    assert limits[0].time == target.timestamp and limits[0].frame_id == target.arbitration_id
    # nothing else: at most the return from the gate's value to the next recorded frame
    assert all(f.kind == "limit" for f in report.findings), "\n".join(report.format()[-4:])
    assert all(0 <= f.time - target.timestamp <= 0.021 for f in report.findings)


def _sources(values: tuple[object, ...]) -> dict[str, object]:
    out: dict[str, object] = {}
    for v in values:
        if isinstance(v, SteerCommand):
            out["steer"] = v
        elif isinstance(v, LongCommand):
            out["long"] = v
    return out


def _only_finding(report: CheckReport) -> tuple[str, int | None]:
    assert len(report.findings) == 1, report.format()
    return report.findings[0].kind, report.findings[0].frame_id


def test_one_corrupt_0x002_checksum_nibble_is_exactly_one_finding(rec: Recorded) -> None:
    if rec.profile == "leaf-ze1-lkas":
        pytest.skip("the ZE1's 0x002 checksum is not known; its counter is not checked")
    frames = list(rec.frames)
    i = [k for k, m in enumerate(frames) if m.arbitration_id == 0x002][500]
    data = bytearray(frames[i].data)
    data[4] ^= 0x10  # one bit of the checksum nibble
    frames[i] = replaced(frames[i], data=bytes(data))
    assert _only_finding(_check(rec, frames)) == ("e2e", 0x002)


def test_one_repeated_counter_is_exactly_one_finding(rec: Recorded) -> None:
    # the ZE1 profile checks the counter of its own command frame only
    frame_id = 0x169 if rec.profile == "leaf-ze1-lkas" else 0x176
    frames = list(rec.frames)
    i = [k for k, m in enumerate(frames) if m.arbitration_id == frame_id][300]
    repeat = frames[i]
    frames.insert(i + 1, replaced(repeat, timestamp=repeat.timestamp + 0.0002))
    assert _only_finding(_check(rec, frames)) == ("e2e", frame_id)


def test_gear_frames_delayed_to_100_ms_are_exactly_one_period_finding(rec: Recorded) -> None:
    gears = [m for m in rec.frames if m.arbitration_id == 0x421]
    others = [m for m in rec.frames if m.arbitration_id != 0x421]
    t0, t1 = gears[0].timestamp, rec.frames[-1].timestamp
    delayed = []
    for k in range(int((t1 - t0) / 0.1) + 1):  # every 100 ms, the payload the car had then
        t = t0 + k * 0.1
        latest = [g for g in gears if g.timestamp <= t + 1e-9][-1]
        delayed.append(replaced(latest, timestamp=t))
    frames = sorted(others + delayed, key=lambda m: m.timestamp)
    report = _check(rec, frames)
    assert _only_finding(report) == ("period", 0x421)
    assert "median period 100.0 ms" in report.findings[0].detail


def test_a_drive_cut_at_every_frame_checks_without_a_false_violation(rec: Recorded) -> None:
    """Every cut point of the engaged part of the drive: the check of the cut log only differs
    from the check of the whole log until its state is known again (a long report with a gear
    and one command of each kind: under 0.2 s), so a window after each cut stands for the
    rest of the log, which the whole-log check found clean."""
    report = _check(rec, rec.frames)
    assert report.ok
    start = _engaged_command(rec) - 600
    cuts = range(max(start, 0), min(start + 1200, len(rec.frames)))
    times = [m.timestamp for m in rec.frames]
    violations = 0
    not_checkable = 0
    for cut in cuts:
        end = cut
        while end < len(times) and times[end] - times[cut] < 0.3:
            end += 1
        cut_report = _check(rec, rec.frames[cut:end])
        violations += cut_report.count("limit")
        not_checkable += sum(cut_report.not_checkable.values())
    assert violations == 0
    assert not_checkable > 0  # the first command after a cut is not rate-checked


# --- the tools around it --------------------------------------------------------------------------


def test_a_log_of_another_vehicle_or_an_empty_log_is_not_ok(tmp_path: Path) -> None:
    empty = tmp_path / "empty.log"
    empty.write_text("")
    report = check_log(empty, profile="leafgate-dbw")
    assert not report.ok and report.findings[0].kind == "coverage"
    sze = [frame(0x001, "01 0C FD DA 00 00 00 00", t * 0.02) for t in range(20)]
    other = check_frames(sze, _limits_of("leafgate-dbw")[0], "leafgate-dbw")
    assert not other.ok and "another vehicle" in other.findings[-1].detail


def test_a_log_without_a_profile_is_an_error_naming_the_option(tmp_path: Path) -> None:
    path = tmp_path / "x.log"
    path.write_text("(0.000000) can0 002#9CFF000713\n")
    result = subprocess.run(
        [sys.executable, "-m", "leafgate.cli", "replay", "check", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode != 0
    assert "--profile" in result.stderr and "Traceback" not in result.stderr


def test_plot_with_nothing_to_plot_fails_with_a_message(tmp_path: Path) -> None:
    path = tmp_path / "cars.log"
    path.write_text("".join(f"(0.{i:06d}) can0 002#9CFF000713\n" for i in range(3)))
    from leafgate.errors import ReplayError

    with pytest.raises(ReplayError, match="nothing to plot"):
        main_plot(path, out=tmp_path / "plots", profile="leafgate-dbw")


def test_decode_into_a_closed_pipe_ends_quietly(recorded: Recorded) -> None:
    command = (
        f"{sys.executable} -m leafgate.cli decode {recorded.log} --profile {recorded.profile} "
        "| head -n 1"
    )
    result = subprocess.run(
        ["bash", "-c", command], capture_output=True, text=True, timeout=120, cwd=ROOT
    )
    assert result.stdout.count("\n") == 1
    assert "Traceback" not in result.stderr and "BrokenPipe" not in result.stderr


# --- recordings in time order ---------------------------------------------------------------------


def _disordered(n: int) -> Iterator[can.Message]:
    """Frames as the daemon hands them to the recorder: the received ones in time, the sent
    ones stamped before they arrive, up to 0.12 s late (the worst measured under load)."""
    for k in range(n):
        t = 1_700_000_000.0 + k * 0.005
        yield can.Message(timestamp=t, arbitration_id=0x0B0, data=bytes(8), channel="can0")
        if k % 4 == 3:
            late = t - 0.12 * ((k // 4) % 3) / 2
            yield can.Message(timestamp=late, arbitration_id=0x0A0, data=bytes(8), is_rx=False)


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_rotated_logs_are_monotonic_with_true_times_in_every_format(
    tmp_path: Path, suffix: str
) -> None:
    sent = list(_disordered(4000))
    with CanLogRecorder(tmp_path / f"can{suffix}", max_bytes=30_000) as rec:
        for msg in sent:
            rec.on_can_frame(msg, "rx" if msg.is_rx else "tx")
    assert len(rec.files) > 2 and rec.late == 0
    got = [m for f in rec.files for m in FrameSource(f)]
    stamps = [m.timestamp for m in got]
    assert all(b >= a for a, b in itertools.pairwise(stamps))  # across files too
    tolerance = 1.1e-3 if suffix == ".asc" else 1e-5
    assert stamps == pytest.approx(sorted(m.timestamp for m in sent), abs=tolerance)
    for f in rec.files:  # each file starts with its own earliest frame
        first = next(iter(FrameSource(f)))
        assert first.timestamp == pytest.approx(min(m.timestamp for m in FrameSource(f)))
    assert {m.channel for m in got if suffix == ".log"} <= {"can0"}


def test_a_shared_bus_is_written_under_one_channel_name(tmp_path: Path) -> None:
    with CanLogRecorder(tmp_path / "can.log", channel="can0", one_bus=True) as rec:
        rec.on_can_frame(can.Message(timestamp=1.0, arbitration_id=0x0B0, channel="sim-7"), "rx")
        rec.on_can_frame(can.Message(timestamp=1.001, arbitration_id=0x0A0), "tx")
    assert {m.channel for m in FrameSource(rec.files[0])} == {"can0"}


def test_a_session_names_a_shared_bus_once_too(tmp_path: Path) -> None:
    path = tmp_path / "s.mcap"
    with SessionRecorder(path, LeafgateConfig(), channel="can0", one_bus=True) as rec:
        rec.on_can_frame(can.Message(timestamp=1.0, arbitration_id=0x0B0, channel="sim-7"), "rx")
        rec.on_can_frame(can.Message(timestamp=1.001, arbitration_id=0x0A0), "tx")
    assert {m.channel for m in FrameSource(path)} == {"can0"}


def test_session_frames_are_read_on_the_gateway_clock(tmp_path: Path) -> None:
    # a daemon session: received frames carry the kernel's epoch time, sent ones the gateway's
    path = tmp_path / "s.mcap"
    ticks = iter([100.0, 100.01, 100.02])  # the last read stamps the end-of-recording marker
    with SessionRecorder(path, LeafgateConfig(), clock=lambda: next(ticks), epoch=1e9) as rec:
        rec.on_can_frame(can.Message(timestamp=1.7e9, arbitration_id=0x0B0), "rx")
        rec.on_can_frame(can.Message(timestamp=100.009, arbitration_id=0x0A0), "tx")
    # read back in Unix time: the gateway clock plus the session's epoch offset
    stamps = [m.timestamp - 1e9 for m in FrameSource(path)]
    assert stamps == pytest.approx([100.0, 100.01], abs=1e-6)


def test_decode_and_check_warn_about_a_log_that_goes_backwards(tmp_path: Path) -> None:
    path = tmp_path / "back.log"
    path.write_text(
        "(1.000000) can0 002#9CFF000702\n(1.010000) can0 002#9CFF000713\n"
        "(0.990000) can0 002#9CFF000720\n"
    )
    import io

    from leafgate.replay.decode import decode_log

    out, err = io.StringIO(), io.StringIO()
    decode_log(path, out, profile="leafgate-dbw", err=err)
    assert "backwards" in err.getvalue() and "(timestamp goes backwards)" in out.getvalue()
    report = check_log(path, profile="leafgate-dbw")
    assert report.backwards == 1 and "backwards" in report.format()[1]
