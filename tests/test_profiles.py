"""Vehicle profiles: byte-exact frames per profile, opendbc cross-checks for the ZE1, the
gateway fitted to each vehicle, and the closed-loop s-curve through every profile.

Worked examples are derived by hand from the layouts in the issue (and the DBC comments):

* leafgate-dbw DBW_STEER_CMD, 0.1 rad at 0.5 rad/s, enabled: angle 0.1 / 1e-4 = 1000 =
  0x03E8 little-endian → ``E8 03``; rate 0.5 / 1e-3 = 500 = 0x01F4 → ``F4 01``; ENABLE is
  bit 32 → byte 4 = ``01``; byte 5 ``00``; alive counter 0 in byte 6; byte 7 the CRC-8 J1850
  over the data ID 0xA0 and bytes 0–6.
* sze-hlc HLC_AUTONOMOUS, tire angle +5.5°, 12 km/h: byte 0 = ``01``; byte 1 = 12 = ``0C``;
  −5.5 × 100 = −550 = 0xFDDA as a big-endian int16 → ``FD DA``. HLC_SPEED_REF_KMPH 12 km/h →
  ``00 0C``.
* leaf-ze1-lkas LKAS, steering wheel +10.00°: raw = (10 − 1310) / −0.01 = 130000 = 0x1FBD0 in
  18 big-endian bits from bit 7 → bytes 0–2 ``7E F4 00`` (the top 18 bits of 0x7EF400);
  byte 3 ``80``; MAX_TORQUE 1 N·m / 0.01 = 100 → ``64``; byte 5 ``80``; LKA_ACTIVE at bit 52
  and counter 5 in bits 51..48 → ``15``; byte 7 the checksum ``C4`` (opendbc agrees).
"""

from __future__ import annotations

import hashlib
import hmac
import math
import subprocess
import sys
from pathlib import Path

import cantools
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from leafgate.can import e2e
from leafgate.can.codec import CanCodec
from leafgate.can.profile import PROFILE_NAMES, load_profile
from leafgate.config import VehicleConfig
from leafgate.errors import CanCodecError, ConfigError, LeafgateError
from leafgate.gateway.safety import SafetyLimits, angle_rate_bounds
from leafgate.messages import (
    Commands,
    GatewayState,
    LongCommand,
    LongMode,
    SteerCommand,
    SystemCommand,
)
from leafgate.settings import LeafgateConfig, load_config, with_profile
from leafgate.sim.runner import run
from leafgate.sim.scenarios import get_scenario
from tests.test_vehicle_dbc import (
    OPENDBC_MISSING,
    opendbc_leaf_2018_dbc_text,
    opendbc_nissan_angle_rate_tables,
)

ROOT = Path(__file__).resolve().parent.parent
RATIO = VehicleConfig().steering_ratio
DEG = math.pi / 180.0


def tick(steer: SteerCommand, long: LongCommand | None = None) -> Commands:
    return Commands(steer=steer, long=long or LongCommand(), system=None)


# --- byte-exact frames and decode back ----------------------------------------------------------


def test_leafgate_dbw_steer_frame_is_byte_exact_and_decodes_back() -> None:
    gw, ecu = CanCodec(profile="leafgate-dbw"), CanCodec(profile="leafgate-dbw")
    cmd = SteerCommand(angle=0.1, rate_limit=0.5, enable=True)
    frame = gw.encode(cmd)
    body = bytes.fromhex("E8 03 F4 01 01 00 00")
    assert bytes(frame.data) == body + bytes((e2e.crc8_j1850(bytes((0xA0,)) + body),))
    assert frame.arbitration_id == 0x0A0
    assert ecu.decode(frame).value == cmd


def test_leafgate_dbw_auth_steer_frame_is_byte_exact_and_decodes_back() -> None:
    # 0.1 rad → E8 03; 0.5 rad/s → 500 in 13 bits from bit 16 → F4 01; ENABLE at bit 29 → byte 3
    # 0x01 | 0x20 = 21; byte 4 the freshness value's low byte; bytes 5-7 the first 3 bytes of
    # HMAC-SHA256(key, 00 A0 ‖ bytes 0-3 ‖ freshness as 8 bytes big-endian)
    key, t = bytes(range(32)), 1_790_000_000.0
    gw = CanCodec(profile="leafgate-dbw-auth", key=key, clock=lambda: t)
    ecu = CanCodec(profile="leafgate-dbw-auth", key=key, clock=lambda: t)
    cmd = SteerCommand(angle=0.1, rate_limit=0.5, enable=True)
    frame = gw.encode(cmd)
    body = bytes.fromhex("E8 03 F4 21")
    freshness = round(t * 200)  # 5 ms steps of Unix time
    tag = hmac.digest(key, b"\x00\xa0" + body + freshness.to_bytes(8, "big"), hashlib.sha256)
    assert bytes(frame.data) == body + bytes((freshness & 0xFF,)) + tag[:3]
    assert frame.arbitration_id == 0x0A0
    assert ecu.decode(frame).value == cmd


def test_the_authenticated_dbc_keeps_the_reports_of_the_plain_one() -> None:
    """One truth for the report layouts: leafgate_dbw_auth.dbc changes the commands only."""
    plain = cantools.database.load_file(ROOT / "dbc" / "leafgate_dbw.dbc")
    auth = cantools.database.load_file(ROOT / "dbc" / "leafgate_dbw_auth.dbc")

    def layout(db: object, name: str) -> list[tuple[object, ...]]:
        message = db.get_message_by_name(name)  # type: ignore[attr-defined]
        return [
            (s.name, s.start, s.length, s.byte_order, s.is_signed, s.scale, s.offset)
            for s in message.signals
        ] + [message.frame_id, message.length]

    for name in ("DBW_STEER_RPT", "DBW_LONG_RPT", "DBW_SYSTEM_RPT"):
        assert layout(auth, name) == layout(plain, name)
    for name in ("DBW_STEER_CMD", "DBW_LONG_CMD", "DBW_SYSTEM_CMD"):
        assert auth.get_message_by_name(name).frame_id == plain.get_message_by_name(name).frame_id


def test_sze_hlc_frames_are_byte_exact_and_decode_back() -> None:
    gw, ecu = CanCodec(profile="sze-hlc"), CanCodec(profile="sze-hlc")
    steer = SteerCommand(angle=5.5 * DEG, enable=True)
    long = LongCommand(mode=LongMode.SPEED, speed=12.0 / 3.6, enable=True)
    frames = gw.encode_commands(tick(steer, long))
    assert [(f.arbitration_id, bytes(f.data).hex(" ")) for f in frames] == [
        (0x01, "01 0c fd da 00 00 00 00"),
        (0x05, "00 0c"),
    ]
    decoded = ecu.decode(frames[0])
    assert decoded.valid
    got_steer, got_long = decoded.values
    assert isinstance(got_steer, SteerCommand) and isinstance(got_long, LongCommand)
    assert got_steer.angle == pytest.approx(5.5 * DEG) and got_steer.enable
    assert got_long.speed == pytest.approx(12.0 / 3.6) and got_long.enable
    assert got_long.mode == LongMode.SPEED  # the profile's only mode
    speed_ref = ecu.decode(frames[1]).value
    assert isinstance(speed_ref, LongCommand) and speed_ref.speed == pytest.approx(12.0 / 3.6)
    assert speed_ref.enable  # folded in from HLC_AUTONOMOUS


def test_sze_hlc_speed_goes_out_in_whole_km_per_h() -> None:
    frames = CanCodec(profile="sze-hlc").encode_commands(
        tick(SteerCommand(angle=0.0, enable=True), LongCommand(speed=1.5, enable=True))
    )
    assert frames[0].data[1] == round(1.5 * 3.6)  # 5.4 km/h → 5


def test_leaf_ze1_lkas_frame_is_byte_exact_and_decodes_back() -> None:
    gw, ecu = CanCodec(profile="leaf-ze1-lkas"), CanCodec(profile="leaf-ze1-lkas")
    steer = SteerCommand(angle=10.0 / RATIO * DEG, enable=True)
    for _ in range(5):  # counters 0..4
        ecu.decode(gw.encode_commands(tick(steer))[0])
    (frame,) = gw.encode_commands(tick(steer))  # lateral only: no longitudinal frame
    assert frame.arbitration_id == 0x169
    assert bytes(frame.data).hex(" ") == "7e f4 00 80 64 80 15 c4"
    decoded = ecu.decode(frame)
    assert decoded.valid, decoded.error
    assert decoded.value.angle == pytest.approx(steer.angle, abs=0.01 / RATIO * DEG)
    assert decoded.value.enable


def test_leaf_ze1_lkas_receiver_rejects_a_bad_checksum_and_a_stuck_counter() -> None:
    gw, ecu = CanCodec(profile="leaf-ze1-lkas"), CanCodec(profile="leaf-ze1-lkas")
    first = gw.encode_commands(tick(SteerCommand(angle=0.0, enable=True)))[0]
    assert ecu.decode(first).valid
    assert ecu.decode(first).error == "bad_counter"  # the same counter again
    broken = gw.encode_commands(tick(SteerCommand(angle=0.0, enable=True)))[0]
    broken.data[0] ^= 0x01
    assert ecu.decode(broken).error == "bad_crc"
    stats = ecu.stats[0x169]
    assert (stats.bad_counter, stats.bad_crc) == (1, 1)


def test_profiles_without_protection_accept_any_frame_and_count_nothing_bad() -> None:
    gw, ecu = CanCodec(profile="sze-hlc"), CanCodec(profile="sze-hlc")
    frame = gw.encode_commands(tick(SteerCommand(angle=0.0)))[0]
    assert ecu.decode(frame).valid and ecu.decode(frame).valid  # no counter to repeat
    assert ecu.stats[0x01].errors == 0


# --- opendbc, the independent database of the 2018 Leaf ------------------------------------------


@settings(max_examples=60, deadline=None)
@given(
    wheel_deg=st.floats(-500.0, 500.0),
    enable=st.booleans(),
    frames=st.integers(0, 20),
)
def test_ze1_frames_decode_with_opendbc_and_its_checksum(
    wheel_deg: float, enable: bool, frames: int
) -> None:
    pytest.importorskip("opendbc", reason=OPENDBC_MISSING)
    from opendbc.car.nissan.nissancan import nissan_checksum

    theirs = cantools.database.load_string(opendbc_leaf_2018_dbc_text(), database_format="dbc")
    gw = CanCodec(profile="leaf-ze1-lkas")
    steer = SteerCommand(angle=wheel_deg / RATIO * DEG, enable=enable)
    for _ in range(frames):
        gw.encode_commands(tick(steer))
    (frame,) = gw.encode_commands(tick(steer))
    values = theirs.decode_message(0x169, bytes(frame.data), decode_choices=False)
    assert values["DESIRED_ANGLE"] == pytest.approx(wheel_deg, abs=0.0051)
    assert values["LKA_ACTIVE"] == int(enable)
    assert values["COUNTER"] == frames % 16
    assert frame.data[7] == nissan_checksum(bytes(frame.data[:7]))


def test_ze1_gate_rate_limits_match_the_cars_safety_model_at_its_breakpoints() -> None:
    tables = opendbc_nissan_angle_rate_tables()
    assert tables.windup.speeds_mps == tables.unwind.speeds_mps
    cfg = with_profile(LeafgateConfig(), "leaf-ze1-lkas")
    period = cfg.gateway.period
    assert period == pytest.approx(0.01)  # one LKAS frame per tick, as the safety model counts
    limits = SafetyLimits.from_config(cfg.gateway.safety, cfg.vehicle, period)
    last = 0.1  # rad, left of centre: up = away from centre (wind-up), down = unwind
    for speed, up_deg, down_deg in zip(
        tables.windup.speeds_mps,
        tables.windup.deg_per_frame,
        tables.unwind.deg_per_frame,
        strict=True,
    ):
        lo, hi = angle_rate_bounds(last, speed, limits)
        # deg of steering wheel per 10 ms frame → rad of road wheel per tick
        assert hi - last == pytest.approx(up_deg / RATIO * DEG, rel=1e-9)
        assert last - lo == pytest.approx(down_deg / RATIO * DEG, rel=1e-9)


def test_bounded_rate_tables_never_exceed_either_table() -> None:
    cfg = LeafgateConfig()
    own = cfg.gateway.safety
    ze1 = with_profile(cfg, "leaf-ze1-lkas").gateway.safety
    table = load_profile("leaf-ze1-lkas").steer_rate
    assert table is not None
    for speed in [x * 0.25 for x in range(0, 81)]:
        mine_up = _interp(speed, own.rate_speeds, own.rate_up)
        car_up = _interp(speed, table.speeds, table.windup)
        got = _interp(speed, ze1.rate_speeds, ze1.rate_up)
        assert got == pytest.approx(min(mine_up, car_up), rel=1e-9, abs=1e-12)


def _interp(x: float, xp: tuple[float, ...], fp: tuple[float, ...]) -> float:
    import numpy as np

    return float(np.interp(x, xp, fp))


# --- the gateway fitted to the vehicle -----------------------------------------------------------


def test_profiles_set_loop_rate_report_watchdogs_and_mode() -> None:
    base = LeafgateConfig()
    sze = with_profile(base, "sze-hlc")
    assert sze.gateway.watchdog.system_report_period is None  # no ECU state report
    assert sze.gateway.watchdog.steer_report_period == pytest.approx(0.01)  # 0x002
    assert sze.controller.mpc.mode == "velocity"  # a target speed only
    assert not sze.gateway.engage.allow_reverse
    ze1 = with_profile(base, "leaf-ze1-lkas")
    assert ze1.gateway.rate_hz == pytest.approx(100.0)
    dbw = with_profile(base, "leafgate-dbw")
    assert dbw.gateway == base.gateway and dbw.controller == base.controller


def test_system_frames_only_when_the_tick_has_one() -> None:
    codec = CanCodec(profile="leafgate-dbw")
    cmds = Commands(SteerCommand(angle=0.0), LongCommand(), SystemCommand(GatewayState.STANDBY))
    assert [f.arbitration_id for f in codec.encode_commands(cmds)] == [0x0A0, 0x0A1, 0x0A2]
    assert [f.arbitration_id for f in codec.encode_commands(tick(SteerCommand(0.0)))] == [
        0x0A0,
        0x0A1,
    ]


@pytest.mark.slow
@pytest.mark.parametrize("profile", PROFILE_NAMES)
def test_s_curve_closed_loop_through_each_profile(profile: str) -> None:
    cfg = with_profile(LeafgateConfig(), profile)
    result = run(cfg, get_scenario("s-curve"))
    m = result.metrics
    assert m["finished"], result.timeline
    assert m["final_state"] == "STANDBY"
    # the controller-core thresholds (tests/test_mpc_closed_loop.py)
    assert m["lateral_error_max_m"] <= 0.05
    assert m["lateral_error_rms_m"] <= 0.02
    assert m["final_position_error_m"] <= 0.10
    assert m["solver_not_converged"] == 0
    assert m["can_frames_rejected"] == 0 and m["ecu_frames_rejected"] == 0
    per_second = m["can_frames_sent"] / m["duration_s"]
    expected = {
        "leafgate-dbw": 50 * 2 + 10,
        "leafgate-dbw-auth": 50 * 2 + 10,
        "sze-hlc": 50 * 2,
        "leaf-ze1-lkas": 100,
    }[profile]
    assert per_second == pytest.approx(expected, rel=0.05)


@pytest.mark.slow
@pytest.mark.parametrize("profile", PROFILE_NAMES)
def test_replay_check_passes_a_recorded_drive_of_each_profile(
    profile: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`replay check` on `sim --profile P --record DIR`; an authenticated profile's MACs are
    said to be unverified without the key, and verified with it."""
    from leafgate import cli

    rec = tmp_path / "rec"
    argv = ["sim", "--profile", profile, "--record", str(rec), "--no-plots"]
    assert cli.main([*argv, "--out", str(tmp_path / "out")]) == 0
    (log,) = rec.glob("*.blf")
    (session,) = rec.glob("*.mcap")
    capsys.readouterr()
    assert cli.main(["replay", "check", str(log), "--profile", profile]) == 0
    verdict = capsys.readouterr().out.splitlines()[-1]
    assert verdict.startswith("OK: ")
    if profile == "sze-hlc":  # read with another profile, its command stream is not checked
        assert cli.main(["replay", "check", str(log), "--profile", "leafgate-dbw"]) == 1
        out = capsys.readouterr().out  # (it said "OK: 0 engaged command frames checked")
        assert "no frame on the command IDs of profile leafgate-dbw" in out
        assert out.splitlines()[-1].startswith("FAILED: ")
    authenticated = load_profile(profile).authenticated
    assert ("MAC not verified" in verdict) == authenticated
    assert "MAC verified" not in verdict
    if authenticated:  # the throwaway key the sim wrote next to the recording
        from leafgate.record.logs import FrameSource

        # sealed on the recording's own clock: each command frame's freshness byte is its
        # recorded time in 5 ms steps (however long the sim took to start)
        for msg in FrameSource(log):
            if msg.arbitration_id in (0x0A0, 0x0A1, 0x0A2) and not msg.is_extended_id:
                assert msg.data[4] == math.floor(msg.timestamp * 200) & 0xFF, msg
        key = rec / "auth.key"
        assert key.stat().st_mode & 0o777 == 0o600
        assert cli.main(["replay", "check", str(session), "--key-file", str(key)]) == 0
        verdict = capsys.readouterr().out.splitlines()[-1]
        assert verdict.startswith("OK: ") and "0 bad MAC, 0 stale freshness" in verdict
        other = tmp_path / "other.key"  # another key: every MAC fails, and says so
        cli.main(["keygen", str(other)])
        assert cli.main(["replay", "check", str(session), "--key-file", str(other)]) == 1
        verdict = capsys.readouterr().out.splitlines()[-1]
        assert verdict.startswith("FAILED: ") and " 0 bad MAC" not in verdict


@pytest.mark.slow
def test_a_vehicle_without_gear_requests_refuses_a_reverse_maneuver() -> None:
    result = run(with_profile(LeafgateConfig(), "sze-hlc"), get_scenario("parallel-park"))
    events = " ".join(event for _, event in result.timeline)
    assert "reverse segments" in events
    assert not result.metrics["finished"]


# --- profile files: errors name the file and the key ---------------------------------------------


def write_profile(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "car.yaml"
    source = (ROOT / "leafgate" / "data" / "profiles" / "sze-hlc.yaml").read_text()
    path.write_text(source.replace("dbc: [sze_hlc.dbc]", "dbc: [sze_hlc.dbc]\n" + text))
    return path


def test_a_profile_file_is_a_dbc_and_data_only(tmp_path: Path) -> None:
    # A new vehicle: a copy of a profile next to its DBC, loaded by path.
    (tmp_path / "sze_hlc.dbc").write_text((ROOT / "dbc" / "sze_hlc.dbc").read_text())
    path = write_profile(tmp_path, "")
    codec = CanCodec(profile=str(path))
    assert codec.profile.dbc == (str(tmp_path / "sze_hlc.dbc"),)
    assert codec.encode_commands(tick(SteerCommand(0.0)))[0].arbitration_id == 0x01


@pytest.mark.parametrize(
    ("replace", "by", "expected"),
    [
        ("TIRE_ANGLE: {field", "TIRE_ANGEL: {field", "TIRE_ANGEL is missing from the DBC"),
        ("field: steer.angle, unit: deg}", "field: steer.angel, unit: deg}", "no field 'angel'"),
        (
            "TARGET_SPEED: {field: long.speed, unit: km/h}",
            "TARGET_SPEED: {field: long.speed, unit: mph}",
            "unit: expected one of",
        ),
        (
            "period: 0.02\n    signals:\n      AUTONOMOUS",
            "period: -1\n    signals:\n      AUTONOMOUS",
            "HLC_AUTONOMOUS.period",
        ),
        ("lateral: true", "lateral: yes please", "capabilities.lateral"),
    ],
)
def test_profile_errors_name_the_file_and_key(
    tmp_path: Path, replace: str, by: str, expected: str
) -> None:
    (tmp_path / "sze_hlc.dbc").write_text((ROOT / "dbc" / "sze_hlc.dbc").read_text())
    path = write_profile(tmp_path, "")
    text = path.read_text()
    assert replace in text
    path.write_text(text.replace(replace, by, 1))
    with pytest.raises((ConfigError, CanCodecError)) as info:
        CanCodec(profile=str(path))
    assert isinstance(info.value, LeafgateError)
    assert expected in str(info.value)
    assert str(path) in str(info.value)


def test_check_config_says_the_profile_has_no_frame_protection(tmp_path: Path) -> None:
    cfg = tmp_path / "sze.yaml"
    cfg.write_text("vehicle:\n  profile: sze-hlc\n")
    result = subprocess.run(
        [sys.executable, "-m", "leafgate.cli", "check-config", str(cfg)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    assert "vehicle profile sze-hlc" in result.stdout
    assert "frame protection: NONE" in result.stdout


def test_unknown_profile_is_one_config_error(tmp_path: Path) -> None:
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("vehicle:\n  profile: leaf-2030\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: vehicle\.profile: 'leaf-2030'"):
        load_config(cfg)


@settings(max_examples=300, deadline=None)
@given(
    profile=st.sampled_from(PROFILE_NAMES),
    frames=st.lists(
        st.tuples(
            st.sampled_from([0x01, 0x05, 0x002, 0x169, 0x176, 0x185, 0x284, 0x285, 0x421])
            | st.integers(0, 0x7FF),
            st.binary(min_size=0, max_size=8),
        ),
        max_size=20,
    ),
)
def test_every_profile_decodes_random_frames_without_raising(
    profile: str, frames: list[tuple[int, bytes]]
) -> None:
    import can

    codec = CanCodec(profile=profile)
    for frame_id, data in frames:
        decoded = codec.decode(
            can.Message(arbitration_id=frame_id, data=data, is_extended_id=False)
        )
        assert decoded.valid == (decoded.error is None)
        assert decoded.valid or not decoded.values or decoded.error in ("bad_crc", "bad_counter")
    assert sum(s.frames for s in codec.stats.values()) == len(frames)


@pytest.mark.slow
def test_ze1_driver_steering_is_an_override_not_a_fault() -> None:
    from leafgate.sim.runner import Injection

    cfg = with_profile(LeafgateConfig(), "leaf-ze1-lkas")
    result = run(cfg, get_scenario("s-curve"), injections=(Injection.parse("override@8"),))
    events = [event for _, event in result.timeline]
    assert any("ENGAGED → STANDBY: driver override" in e for e in events), events
    assert not any("FAULT" in e for e in events), events
