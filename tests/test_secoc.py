"""Authenticated command frames (issue 17, finding 2): leafgate.can.secoc and the codec's use.

Seal/verify: a tampered byte, a wrong key, a replayed freshness value, the freshness rebuilt
across the wrap of its transmitted low byte, and a recording replayed after a restart. The key
file: refused with one line (file, reason) when missing, short, not hex, or open to others;
the key never appears in a message.
"""

from __future__ import annotations

import itertools
import os
import subprocess
import sys
from pathlib import Path

import pytest

from leafgate.can import secoc
from leafgate.can.codec import CanCodec, EncodeError
from leafgate.errors import ConfigError
from leafgate.messages import GatewayState, LongCommand, SteerCommand, SystemCommand
from leafgate.settings import load_config

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
T0 = 1_790_000_000.0  # s, a Unix time
STEP = secoc.FRESHNESS_UNIT
PERIOD = 0.02  # s, the command period


def stream(sealer: secoc.Sealer, start: float, n: int, frame_id: int = 0x0A0) -> list[bytes]:
    """``n`` sealed frames of ``frame_id``, one per command period from ``start``."""
    return [sealer.seal(frame_id, bytes((i & 0xFF, 1, 2, 3)), start + i * PERIOD) for i in range(n)]


# --- seal and verify -------------------------------------------------------------------------


def test_a_sealed_stream_verifies_frame_by_frame() -> None:
    frames = stream(secoc.Sealer(KEY), T0, 50)
    rx = secoc.Verifier(KEY)
    assert [rx.verify(0x0A0, f, T0 + i * PERIOD + 0.002) for i, f in enumerate(frames)] == [
        "ok"
    ] * 50


@pytest.mark.parametrize("byte", range(8))
def test_a_tampered_byte_is_rejected(byte: int) -> None:
    frame = bytearray(secoc.Sealer(KEY).seal(0x0A0, bytes(4), T0))
    frame[byte] ^= 0x01
    assert secoc.Verifier(KEY).verify(0x0A0, frame, T0) != "ok"


def test_the_mac_covers_the_can_id() -> None:
    frame = secoc.Sealer(KEY).seal(0x0A0, bytes(4), T0)
    assert secoc.Verifier(KEY).verify(0x0A1, frame, T0) == "bad_mac"


def test_a_frame_sealed_with_another_key_is_a_bad_mac() -> None:
    frame = secoc.Sealer(OTHER_KEY).seal(0x0A0, bytes(4), T0)
    assert secoc.Verifier(KEY).verify(0x0A0, frame, T0) == "bad_mac"


def test_a_replayed_freshness_value_is_stale() -> None:
    sealer, rx = secoc.Sealer(KEY), secoc.Verifier(KEY)
    first, second = stream(sealer, T0, 2)
    assert rx.verify(0x0A0, first, T0) == "ok"
    assert rx.verify(0x0A0, second, T0 + PERIOD) == "ok"
    # byte for byte, right after: within the window, but not above the last accepted value
    assert rx.verify(0x0A0, first, T0 + PERIOD) == "stale"
    assert rx.verify(0x0A0, second, T0 + PERIOD) == "stale"
    # a rejected frame does not move the receiver: the next genuine frame is accepted
    assert rx.verify(0x0A0, sealer.seal(0x0A0, bytes(4), T0 + 2 * PERIOD), T0 + 2 * PERIOD) == "ok"


def test_two_frames_in_one_freshness_step_still_rise() -> None:
    sealer, rx = secoc.Sealer(KEY), secoc.Verifier(KEY)
    a = sealer.seal(0x0A2, bytes(4), T0)
    b = sealer.seal(0x0A2, bytes(4), T0 + STEP / 10)  # a reset's system frame at once
    assert a[secoc.FRESHNESS_BYTE] != b[secoc.FRESHNESS_BYTE]
    assert rx.verify(0x0A2, a, T0) == "ok" and rx.verify(0x0A2, b, T0) == "ok"


def test_freshness_is_rebuilt_across_the_wrap_of_its_low_byte() -> None:
    # a start just below a multiple of 256 steps: the transmitted byte wraps 0xFF → 0x00
    start = (secoc.freshness_at(T0) // 256 + 1) * 256 * STEP - 10 * STEP
    sealer, rx = secoc.Sealer(KEY), secoc.Verifier(KEY)
    frames = stream(sealer, start, 20)
    lows = [f[secoc.FRESHNESS_BYTE] for f in frames]
    assert any(a > b for a, b in itertools.pairwise(lows))  # it did wrap
    # received 30 ms late, with the receiver's clock 0.2 s ahead: within the window
    verdicts = [rx.verify(0x0A0, f, start + i * PERIOD + 0.23) for i, f in enumerate(frames)]
    assert verdicts == ["ok"] * 20
    assert secoc.reconstruct(0x02, 0x1FE) == 0x202 and secoc.reconstruct(0xFE, 0x202) == 0x1FE


def test_a_clock_offset_beyond_the_window_is_stale() -> None:
    frame = secoc.Sealer(KEY).seal(0x0A0, bytes(4), T0)
    assert secoc.Verifier(KEY).verify(0x0A0, frame, T0 + secoc.FRESHNESS_WINDOW * 0.9) == "ok"
    for offset in (secoc.FRESHNESS_WINDOW * 1.1, -secoc.FRESHNESS_WINDOW * 1.1):
        assert secoc.Verifier(KEY).verify(0x0A0, frame, T0 + offset) != "ok"


def test_an_old_recording_replayed_after_a_restart_is_refused() -> None:
    recorded = stream(secoc.Sealer(KEY), T0, 500)  # 10 s of a drive
    # hours later both ends restart: the receiver keeps no state, the sender neither
    later = T0 + 3 * 3600
    rx = secoc.Verifier(KEY)
    replayed = [rx.verify(0x0A0, f, later + i * PERIOD) for i, f in enumerate(recorded)]
    assert "ok" not in replayed
    # … and a minute later, racing a restarted sender: its frames pass, the old ones never
    rx = secoc.Verifier(KEY)
    genuine = stream(secoc.Sealer(KEY), T0 + 60, 500)
    for i, (old, new) in enumerate(zip(recorded, genuine, strict=True)):
        now = T0 + 60 + i * PERIOD
        assert rx.verify(0x0A0, old, now) != "ok"
        assert rx.verify(0x0A0, new, now) == "ok"


def test_a_restarted_sender_is_accepted_by_a_running_receiver() -> None:
    rx = secoc.Verifier(KEY)
    for i, f in enumerate(stream(secoc.Sealer(KEY), T0, 10)):
        assert rx.verify(0x0A0, f, T0 + i * PERIOD) == "ok"
    restarted = secoc.Sealer(KEY)  # the gateway restarted 1 s later: its clock went on
    assert rx.verify(0x0A0, restarted.seal(0x0A0, bytes(4), T0 + 1.2), T0 + 1.2) == "ok"


def test_nothing_prints_the_key() -> None:
    assert KEY.hex() not in repr(secoc.Sealer(KEY)) + repr(secoc.Verifier(KEY))


# --- the codec ---------------------------------------------------------------------------------


def codecs(t: list[float]) -> tuple[CanCodec, CanCodec]:
    """A gateway and an ECU codec of the authenticated profile on the clock ``t[0]``."""
    gw = CanCodec(profile="leafgate-dbw-auth", key=KEY, clock=lambda: t[0])
    ecu = CanCodec(profile="leafgate-dbw-auth", key=KEY, clock=lambda: t[0])
    return gw, ecu


def test_the_codec_seals_and_verifies_every_command_frame() -> None:
    t = [T0]
    gw, ecu = codecs(t)
    values = (
        SteerCommand(angle=-0.3, rate_limit=0.25, enable=True),
        LongCommand(accel=-2.5, speed=3.2, enable=True),
        SystemCommand(GatewayState.STANDBY),
    )
    for value in values:
        msg = gw.encode(value)
        d = ecu.decode(msg)
        assert d.valid, d
        assert type(d.value) is type(value)
        assert ecu.decode(msg).error == "stale_freshness"  # the same frame again
    steer = ecu.decode(gw.encode(values[0])).value
    assert isinstance(steer, SteerCommand) and steer.angle == pytest.approx(-0.3)
    long = ecu.decode(gw.encode(values[1])).value
    assert isinstance(long, LongCommand) and long.accel == pytest.approx(-2.5, abs=0.003)
    stats = ecu.stats[0x0A0]
    assert (stats.stale_freshness, stats.bad_mac, stats.errors) == (1, 0, 1)


def test_a_tampered_frame_is_a_bad_mac_in_the_codec() -> None:
    t = [T0]
    gw, ecu = codecs(t)
    msg = gw.encode(SteerCommand(angle=0.1, enable=True))
    msg.data[0] ^= 0x10  # the angle changed in flight
    assert ecu.decode(msg).error == "bad_mac"
    assert ecu.stats[0x0A0].bad_mac == 1


def test_without_the_key_frames_decode_unverified_and_cannot_be_sent() -> None:
    t = [T0]
    gw, _ = codecs(t)
    reader = CanCodec(profile="leafgate-dbw-auth", clock=None)
    msg = gw.encode(SteerCommand(angle=0.1))
    d = reader.decode(msg)
    assert d.valid and not reader.verifies
    assert reader.stats[0x0A0].mac_unverified == 1
    with pytest.raises(EncodeError, match="no key"):
        reader.encode(SteerCommand(angle=0.1))


def test_a_plain_leafgate_dbw_stream_is_refused_by_an_authenticated_ecu() -> None:
    plain = CanCodec(profile="leafgate-dbw")
    _, ecu = codecs([T0])
    errors = {ecu.decode(plain.encode(SteerCommand(0.1, enable=True))).error for _ in range(20)}
    assert errors <= {"bad_mac", "stale_freshness"} and None not in errors


# --- the key file ------------------------------------------------------------------------------


def key_file(tmp_path: Path, text: str = KEY.hex(), mode: int = 0o600) -> Path:
    path = tmp_path / "leafgate.key"
    path.write_text(text + "\n", encoding="ascii")
    path.chmod(mode)
    return path


def test_keygen_writes_a_private_key_and_never_overwrites(tmp_path: Path) -> None:
    path = secoc.write_key(tmp_path / "k")
    assert path.stat().st_mode & 0o777 == 0o600
    assert len(secoc.load_key(path)) == secoc.KEY_BYTES
    before = path.read_text()
    with pytest.raises(ConfigError, match="never overwritten"):
        secoc.write_key(path)
    assert path.read_text() == before


def test_a_good_key_file_loads(tmp_path: Path) -> None:
    assert secoc.load_key(key_file(tmp_path)) == KEY
    assert secoc.load_key(key_file(tmp_path, mode=0o400)) == KEY


@pytest.mark.parametrize(
    ("text", "mode", "reason"),
    [
        (KEY.hex(), 0o640, "accessible by group or others (mode 0640)"),
        (KEY.hex(), 0o604, "accessible by group or others (mode 0604)"),
        (KEY.hex(), 0o660, "chmod 600"),
        (KEY[:8].hex(), 0o600, "the key is 64 bits long, at least 128"),
        (KEY.hex()[:-1] + "z", 0o600, "the key file holds 'z', not a hex digit (0-9, a-f)"),
        # old code: "does not hold hex digits" of a file of nothing else
        ("abc", 0o600, "holds 3 hex digits, an odd number: a key is whole bytes"),
    ],
)
def test_a_bad_key_file_is_one_line_naming_file_and_reason(
    tmp_path: Path, text: str, mode: int, reason: str
) -> None:
    path = key_file(tmp_path, text, mode)
    with pytest.raises(ConfigError) as info:
        secoc.load_key(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and reason in message
    assert "\n" not in message
    assert KEY.hex()[:16] not in message and KEY[:8].hex() not in message


def test_a_missing_key_file_says_how_to_make_one(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"no such key file \(make one with `leafgate keygen"):
        secoc.load_key(tmp_path / "nope.key")


def test_a_key_file_of_another_user_is_refused(tmp_path: Path) -> None:
    path = key_file(tmp_path)
    if os.geteuid() != 0:
        pytest.skip("giving the file to another user needs root")
    os.chown(path, 4242, -1)
    with pytest.raises(ConfigError, match="belongs to uid 4242, not to the user running"):
        secoc.load_key(path)


def auth_config(tmp_path: Path) -> Path:
    """A config of the authenticated profile naming ``leafgate.key`` next to it."""
    path = tmp_path / "car.yaml"
    path.write_text("vehicle: {profile: leafgate-dbw-auth}\ncan: {auth_key_file: leafgate.key}\n")
    return path


def leafgate(*args: str) -> subprocess.CompletedProcess[str]:
    """``leafgate ARGS`` in a process of its own (its exit status and stderr as a user sees)."""
    return subprocess.run(
        [sys.executable, "-m", "leafgate.cli", *args], capture_output=True, text=True, timeout=120
    )


def check_config(path: Path) -> subprocess.CompletedProcess[str]:
    return leafgate("check-config", str(path))


def test_the_key_file_is_found_next_to_the_config(tmp_path: Path) -> None:
    key_file(tmp_path)
    cfg_path = auth_config(tmp_path)
    cfg = load_config(cfg_path)
    assert cfg.can.auth_key_file == str(tmp_path / "leafgate.key")
    assert CanCodec.for_config(cfg).verifies
    # given on the command line, a relative path is the caller's (not moved)
    cfg = load_config(cfg_path, {"can.auth_key_file": "other.key"})
    assert cfg.can.auth_key_file == "other.key"


def test_the_authenticated_profile_without_a_key_file_is_refused(tmp_path: Path) -> None:
    cfg_path = tmp_path / "car.yaml"
    cfg_path.write_text("vehicle: {profile: leafgate-dbw-auth}\n")
    with pytest.raises(ConfigError, match=r"set can\.auth_key_file"):
        CanCodec.for_config(load_config(cfg_path))


@pytest.mark.parametrize("mode", [0o644, None])
def test_check_config_refuses_a_bad_key_file_in_one_line(tmp_path: Path, mode: int | None) -> None:
    if mode is not None:
        key_file(tmp_path, mode=mode)
    result = check_config(auth_config(tmp_path))
    assert result.returncode != 0
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert str(tmp_path / "leafgate.key") in lines[0]
    assert "Traceback" not in result.stderr and KEY.hex()[:16] not in result.stderr


def test_check_config_names_the_key_it_checked(tmp_path: Path) -> None:
    key_file(tmp_path)
    result = check_config(auth_config(tmp_path))
    assert result.returncode == 0, result.stderr
    assert f"authentication key: {tmp_path / 'leafgate.key'}" in result.stdout
    assert KEY.hex()[:16] not in result.stdout


def test_the_daemon_refuses_an_open_key_file_before_recording(tmp_path: Path) -> None:
    key_file(tmp_path, mode=0o644)
    cfg_path = auth_config(tmp_path)
    rec = tmp_path / "rec"
    cfg_path.write_text(cfg_path.read_text() + f"recording: {{enabled: true, directory: {rec}}}\n")
    result = leafgate("run", "--config", str(cfg_path))
    assert result.returncode != 0
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert lines == [lines[-1]] and "accessible by group or others (mode 0644)" in lines[-1]
    assert not rec.exists()  # refused before any recording file was created
    assert KEY.hex()[:16] not in result.stderr + result.stdout


def test_sim_drives_the_authenticated_profile_with_a_configured_key(tmp_path: Path) -> None:
    from leafgate import cli

    key = key_file(tmp_path)
    argv = ["sim", "--profile", "leafgate-dbw-auth", "--scenario", "straight", "--no-plots"]
    argv += ["--out", str(tmp_path / "out"), "--set", f"can.auth_key_file={key}"]
    assert cli.main(argv) == 0
    assert not (tmp_path / "out" / "auth.key").exists()  # no throwaway key: the configured one


def test_replay_check_finds_a_replayed_frame_only_with_the_key() -> None:
    from leafgate.gateway.safety import SafetyLimits
    from leafgate.replay.check import check_frames
    from leafgate.settings import LeafgateConfig

    t = [T0]
    gw, _ = codecs(t)
    frames = []
    for i in range(100):  # 2 s of STANDBY commands, as recorded
        t[0] = T0 + i * PERIOD
        for value in (SteerCommand(0.0), LongCommand()):
            msg = gw.encode(value, timestamp=t[0])
            msg.timestamp = t[0]
            frames.append(msg)
    replayed = frames[10].__copy__()  # a frame of 1.8 s before, sent again at the end
    replayed.timestamp = t[0] + 0.001
    frames.append(replayed)
    cfg = LeafgateConfig()
    limits = SafetyLimits.from_config(cfg.gateway.safety, cfg.vehicle, cfg.gateway.period)
    with_key = check_frames(frames, limits, "leafgate-dbw-auth", key=KEY)
    e2e = [f for f in with_key.findings if f.kind == "e2e"]
    assert [(f.name, f.detail) for f in e2e] in (
        [("DBW_STEER_CMD", "bad_mac")],
        [("DBW_STEER_CMD", "stale_freshness")],
    )
    assert "MAC verified with the key on 201 authenticated frames" in with_key.authentication
    without = check_frames(frames, limits, "leafgate-dbw-auth")
    assert not [f for f in without.findings if f.kind == "e2e"]
    assert without.authentication.startswith("MAC not verified")
    assert "MAC not verified" in without.format()[-1]
