"""The simulated drive-by-wire ECU, in simulated time, through the real codec."""

from __future__ import annotations

import math
import threading
from collections import Counter
from collections.abc import Callable
from dataclasses import replace
from typing import TypeVar

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from leafgate.can.codec import CanCodec
from leafgate.config import VehicleConfig
from leafgate.config.can import BusConfig, CanConfig
from leafgate.config.sim import EcuConfig, PlantConfig, SimConfig
from leafgate.errors import LeafgateError
from leafgate.messages import (
    EcuState,
    GatewayState,
    Gear,
    GearPosition,
    LongCommand,
    LongMode,
    LongReport,
    MotorSpeed,
    Pose,
    SteerCommand,
    SteeringWheelAngle,
    SteerReport,
    SystemCommand,
    SystemReport,
    WheelSpeeds,
)
from leafgate.settings import LeafgateConfig
from leafgate.sim.ecu import InjectionError, RealtimeStats, SimulatedEcu, run_ecu_realtime
from leafgate.sim.plant import make_plant

DT = 0.001  # s, ECU step in these tests
CMD_TICKS = 20  # ticks between two command frames (20 ms, the gateway's loop)
VEHICLE = VehicleConfig()
T = TypeVar("T")


class Rig:
    """A gateway-side codec pair and an ECU stepped on integer ticks of DT."""

    def __init__(
        self,
        start: Pose | None = None,
        plant: PlantConfig | None = None,
        ecu: EcuConfig | None = None,
    ) -> None:
        plant_cfg = plant or PlantConfig(kind="kinematic", input_delay=0.0)
        self.plant = make_plant(plant_cfg, VEHICLE, start or Pose(0.0, 0.0, 0.0, 0.0))
        self.ecu = SimulatedEcu(ecu or EcuConfig(), self.plant, VEHICLE)
        self.tx = CanCodec(profile="leafgate-dbw")  # the gateway's codec: encodes commands
        self.rx = CanCodec(profile="leafgate-dbw")  # … and decodes reports
        self.tick = 0
        self.frames: list[tuple[float, can.Message]] = []

    @property
    def now(self) -> float:
        return self.tick * DT

    def send(self, value: SteerCommand | LongCommand | SystemCommand) -> can.Message:
        msg = self.tx.encode(value, timestamp=self.now)
        self.ecu.receive_frame(self.now, msg)
        return msg

    def run(
        self,
        duration: float,
        steer: SteerCommand | None = None,
        long: LongCommand | None = None,
        until: Callable[[], bool] | None = None,
    ) -> None:
        """Step for ``duration`` s, sending the commands every 20 ms (none when None)."""
        for _ in range(round(duration / DT)):
            if self.tick % CMD_TICKS == 0:
                if steer is not None:
                    self.send(steer)
                if long is not None:
                    self.send(long)
            self.frames.extend((self.now, m) for m in self.ecu.reports(self.now))
            self.ecu.step(self.now, DT)
            self.tick += 1
            if until is not None and until():
                return

    def engage(self, accel: float = 0.0, angle: float = 0.0) -> None:
        """ENABLE=0 for 100 ms, then ENABLE=1: an edge."""
        self.run(0.1, SteerCommand(angle), LongCommand(accel=accel))
        self.run(0.04, SteerCommand(angle, enable=True), LongCommand(accel=accel, enable=True))
        assert self.ecu.state == EcuState.ENGAGED

    def decoded(self, frame_type: type[T], since: float = -math.inf) -> list[T]:
        """The valid report frames of one type received since ``since``, decoded (by a fresh
        codec each time: the car's frames carry counters, each frame is decoded once)."""
        out = []
        rx = CanCodec(profile="leafgate-dbw")
        for t, msg in self.frames:
            if t < since:
                continue
            d = rx.decode(msg)
            if d.valid and isinstance(d.value, frame_type):
                out.append(d.value)
        return out


def on(
    angle: float = 0.0,
    accel: float = 0.0,
    mode: LongMode = LongMode.ACCELERATION,
    speed: float = 0.0,
    gear: Gear = Gear.NONE,
) -> tuple[SteerCommand, LongCommand]:
    """Commands with ENABLE=1."""
    long = LongCommand(mode=mode, accel=accel, speed=speed, gear=gear, enable=True)
    return SteerCommand(angle, enable=True), long


# --- engagement ----------------------------------------------------------------------------


def test_enable_held_at_one_from_the_start_does_not_engage() -> None:
    rig = Rig()
    rig.run(0.5, *on())
    assert rig.ecu.state == EcuState.READY
    assert not rig.ecu.engaged


def test_enable_edge_engages() -> None:
    rig = Rig()
    rig.run(0.1, SteerCommand(0.0), LongCommand())
    assert rig.ecu.state == EcuState.READY
    rig.run(0.05, *on())
    assert rig.ecu.state == EcuState.ENGAGED
    assert rig.ecu.counters.engagements == 1


def test_enable_edge_on_steer_alone_does_not_engage() -> None:
    rig = Rig()
    rig.run(0.1, SteerCommand(0.0), LongCommand())
    rig.run(0.2, SteerCommand(0.0, enable=True), LongCommand())
    assert not rig.ecu.engaged


def test_enable_zero_disengages_and_driver_holds_steering_and_brakes() -> None:
    rig = Rig(start=Pose(0.0, 0.0, 0.0, 2.0))
    rig.engage(angle=0.1)
    rig.run(0.5, *on(angle=0.1))
    held = rig.plant.steer_angle
    assert held == pytest.approx(0.1)
    rig.run(0.3, SteerCommand(-0.3), LongCommand(accel=1.0))  # ENABLE=0: commands ignored
    assert rig.ecu.state == EcuState.READY
    assert rig.plant.steer_angle == pytest.approx(held)
    assert rig.plant.accel == pytest.approx(-EcuConfig().driver_decel)


def test_engage_without_commands_is_not_ready() -> None:
    rig = Rig()
    rig.run(0.2)
    assert rig.ecu.state == EcuState.NOT_READY
    assert not rig.ecu.cmd_timeout  # nothing was ever received: not a timeout


# --- command timeout -----------------------------------------------------------------------


def test_timeout_after_100ms_then_brake_at_3_mps2_to_a_stop() -> None:
    rig = Rig(start=Pose(0.0, 0.0, 0.0, 2.0))
    rig.engage()
    last_cmd = (rig.tick - 1) // CMD_TICKS * CMD_TICKS * DT  # s, the last command frame sent
    rig.run(1.0, until=lambda: rig.ecu.cmd_timeout)
    t_timeout = rig.now
    assert EcuConfig().cmd_timeout <= t_timeout - last_cmd <= EcuConfig().cmd_timeout + 2 * DT
    assert not rig.ecu.engaged
    speeds = []
    for _ in range(200):
        rig.run(DT)
        speeds.append(rig.plant.speed)
    decel = (speeds[-1] - speeds[0]) / ((len(speeds) - 1) * DT)  # m/s²
    assert decel == pytest.approx(-EcuConfig().timeout_decel, rel=1e-6)
    rig.run(1.0)
    assert rig.plant.speed == 0.0
    assert rig.ecu.counters.timeouts == 1
    steer = rig.decoded(SteerReport, since=t_timeout + 0.011)
    system = rig.decoded(SystemReport, since=t_timeout + 0.101)
    assert steer and all(r.cmd_timeout and not r.enabled for r in steer)
    assert system and all(r.fault_cmd_timeout for r in system)


def test_commands_back_after_timeout_need_a_new_edge() -> None:
    rig = Rig()
    rig.engage()
    rig.run(0.3)  # silence: timeout
    rig.run(0.2, *on())  # ENABLE=1 on the first frames after the timeout
    assert rig.ecu.state == EcuState.READY
    rig.run(0.1, SteerCommand(0.0), LongCommand())
    rig.run(0.05, *on())
    assert rig.ecu.state == EcuState.ENGAGED


# --- driver override -----------------------------------------------------------------------


def test_torque_above_threshold_for_100ms_latches_override() -> None:
    rig = Rig()
    rig.engage()
    t0 = rig.now
    rig.ecu.inject("override-torque", at=t0, duration=0.5, torque=2.6)
    rig.run(0.1 - 2 * DT, *on())
    assert rig.ecu.engaged  # not yet 100 ms
    rig.run(3 * DT, *on())
    assert rig.ecu.state == EcuState.OVERRIDE
    rig.run(1.0, *on())  # torque gone, ENABLE still 1: stays latched
    assert rig.ecu.state == EcuState.OVERRIDE
    assert rig.decoded(SteerReport, since=t0 + 0.2)[0].override


@pytest.mark.parametrize(("torque", "duration"), [(2.5, 1.0), (-2.5, 1.0), (3.0, 0.09)])
def test_torque_at_threshold_or_too_short_does_not_override(torque: float, duration: float) -> None:
    rig = Rig()
    rig.engage()
    rig.ecu.inject("override-torque", at=rig.now, duration=duration, torque=torque)
    rig.run(1.2, *on())
    assert rig.ecu.state == EcuState.ENGAGED
    assert rig.decoded(SteerReport)[-1].driver_torque == 0.0


def test_brake_pedal_overrides_at_once() -> None:
    rig = Rig(start=Pose(0.0, 0.0, 0.0, 1.0))
    rig.engage()
    rig.ecu.inject("brake-pedal", at=rig.now, duration=0.3, pedal_pct=20.0)
    rig.run(2 * DT, *on())
    assert rig.ecu.state == EcuState.OVERRIDE
    rig.run(0.05, *on())
    assert rig.decoded(LongReport)[-1].brake_pedal_pct == pytest.approx(20.0)


def test_clear_override_then_new_edge_engages_again() -> None:
    rig = Rig()
    rig.engage()
    rig.ecu.inject("override-torque", at=rig.now, duration=0.2, torque=-4.0)
    rig.run(0.5, *on())
    assert rig.ecu.state == EcuState.OVERRIDE
    steer, long = SteerCommand(0.0, clear_override=True), LongCommand()
    rig.run(0.1, steer, long)
    assert rig.ecu.state == EcuState.READY
    rig.run(0.05, *on())
    assert rig.ecu.state == EcuState.ENGAGED


def test_clear_override_refused_while_driver_still_brakes() -> None:
    rig = Rig()
    rig.engage()
    rig.ecu.inject("brake-pedal", at=rig.now, duration=1.0)
    rig.run(0.2, *on())
    rig.run(0.2, SteerCommand(0.0, clear_override=True), LongCommand(clear_override=True))
    assert rig.ecu.state == EcuState.OVERRIDE


# --- invalid command frames ----------------------------------------------------------------


def test_bad_crc_command_dropped_and_counted() -> None:
    rig = Rig()
    rig.engage()
    msg = rig.tx.encode(SteerCommand(0.3, enable=True), timestamp=rig.now)
    msg.data[7] ^= 0x01
    rig.ecu.receive_frame(rig.now, msg)
    rig.run(0.1)  # no valid steer command since: the 0.3 rad target must not be applied
    assert rig.plant.steer_angle == pytest.approx(0.0)
    assert rig.ecu.counters.bad_crc == 1
    system = rig.decoded(SystemReport)[-1]
    assert system.fault_bad_crc and system.rx_error_count == 1


def test_repeated_counter_command_dropped_and_counted() -> None:
    rig = Rig()
    rig.engage()
    rig.send(SteerCommand(0.1, enable=True))
    stale = rig.tx.encode(SteerCommand(0.1, enable=True))
    rig.ecu.receive_frame(rig.now, stale)
    rig.ecu.receive_frame(rig.now, stale)  # the same counter again
    assert rig.ecu.counters.bad_counter == 1
    assert rig.ecu.counters.rx_errors == rig.ecu.rejected_frames == 1


def test_wrong_length_command_dropped_and_counted() -> None:
    rig = Rig()
    msg = rig.tx.encode(LongCommand())
    short = can.Message(arbitration_id=msg.arbitration_id, is_extended_id=False, data=msg.data[:6])
    rig.ecu.receive_frame(0.0, short)
    assert rig.ecu.counters.wrong_length == 1
    assert rig.ecu.state == EcuState.NOT_READY


def test_frames_that_are_not_commands_are_ignored() -> None:
    rig = Rig()
    report = rig.tx.encode(SteerReport(0.0, 0.0, 0.0, False, False, False, False))
    rig.ecu.receive_frame(0.0, report)
    rig.ecu.receive_frame(0.0, can.Message(arbitration_id=0x7FF, is_extended_id=False))
    assert rig.ecu.counters.rx_errors == 0


# --- a second sender on the command IDs (issue 17, finding 2) ------------------------------


class Replayer:
    """Replays a recorded command stream byte for byte, each frame just after the genuine one
    whose counter precedes it: the race the attack won."""

    def __init__(self, rig: Rig, recorded: list[can.Message]) -> None:
        self.rig = rig
        self.frames = {(m.arbitration_id, m.data[6] & 0x0F): m for m in recorded}

    def after(self, genuine: can.Message) -> None:
        counter = (genuine.data[6] + 1) & 0x0F
        forged = self.frames.get((genuine.arbitration_id, counter))
        if forged is not None:
            self.rig.ecu.receive_frame(self.rig.now, forged)


def _engage_sequence() -> list[can.Message]:
    """The gateway's frames of an engagement (ENABLE=0, then ENABLE=1), as recorded."""
    codec = CanCodec(profile="leafgate-dbw")
    out = [codec.encode(v) for _ in range(8) for v in (SteerCommand(0.0), LongCommand())]
    out += [codec.encode(v) for _ in range(8) for v in on(accel=1.5)]
    return out


def _race(rig: Rig, duration: float, replayer: Replayer, *commands: SteerCommand | LongCommand):
    for _ in range(round(duration / DT)):
        if rig.tick % CMD_TICKS == 0:
            for value in commands:
                replayer.after(rig.send(value))
        rig.frames.extend((rig.now, m) for m in rig.ecu.reports(rig.now))
        rig.ecu.step(rig.now, DT)
        rig.tick += 1


def test_replayed_stream_racing_the_gateway_faults_and_never_drives() -> None:
    rig = Rig()
    replayer = Replayer(rig, _engage_sequence()[16:])  # the ENABLE=1 frames of the recording
    rig.run(0.1, SteerCommand(0.0), LongCommand())  # the gateway in STANDBY: ENABLE=0
    _race(rig, 2.0, replayer, SteerCommand(0.0), LongCommand())
    assert rig.ecu.state == EcuState.FAULT
    assert rig.ecu.counters.counter_races == 1
    assert rig.plant.speed == 0.0 and abs(rig.plant.x) < 0.01  # at most a first-tick twitch


def test_counter_race_while_engaged_brakes_to_rest_and_clears_once_quiet() -> None:
    rig = Rig(start=Pose(0.0, 0.0, 0.0, 2.0))
    rig.engage()
    replayer = Replayer(rig, _engage_sequence()[16:])
    _race(rig, 0.2, replayer, *on())
    assert rig.ecu.state == EcuState.FAULT and not rig.ecu.engaged
    _race(rig, 1.0, replayer, *on())
    assert rig.plant.speed == 0.0  # braked to rest at timeout_decel
    rig.send(SystemCommand(GatewayState.FAULT, clear_faults=True))  # the race is still on
    _race(rig, 0.1, replayer, SteerCommand(0.0), LongCommand())
    assert rig.ecu.state == EcuState.FAULT
    rig.run(0.6, SteerCommand(0.0), LongCommand())  # the second sender has gone quiet
    rig.send(SystemCommand(GatewayState.STANDBY, clear_faults=True))
    rig.run(0.05, SteerCommand(0.0), LongCommand())
    assert rig.ecu.state == EcuState.READY


def test_a_few_counter_drops_are_not_a_race() -> None:
    rig = Rig()
    rig.engage()
    for _ in range(EcuConfig().race_drops):
        stale = rig.tx.encode(SteerCommand(0.0, enable=True))
        rig.ecu.receive_frame(rig.now, stale)
        rig.ecu.receive_frame(rig.now, stale)  # the same counter again
        rig.run(0.2, *on())
    assert rig.ecu.counters.bad_counter == EcuConfig().race_drops
    assert rig.ecu.engaged and rig.ecu.counters.counter_races == 0


# --- gears ---------------------------------------------------------------------------------


def test_gear_change_refused_while_moving_accepted_at_standstill() -> None:
    rig = Rig(start=Pose(0.0, 0.0, 0.0, 1.0))
    rig.engage()
    rig.run(0.3, *on(accel=-1.0, gear=Gear.R))
    assert rig.plant.gear == Gear.D
    assert rig.ecu.counters.gear_refused == 1  # once per request, not per frame
    rig.run(1.0, *on(accel=-1.0, gear=Gear.R))  # stops after 1 s of braking, then shifts
    assert rig.plant.gear == Gear.R
    assert rig.ecu.counters.gear_changes == 1
    rig.run(1.0, *on(accel=0.5, gear=Gear.R))
    assert rig.plant.speed < -0.3  # reversing
    assert rig.decoded(LongReport)[-1].gear == Gear.R
    assert rig.decoded(GearPosition)[-1].gear == Gear.R


# --- longitudinal modes --------------------------------------------------------------------


def test_speed_mode_reaches_target_speed() -> None:
    rig = Rig()
    rig.engage()
    rig.run(8.0, *on(mode=LongMode.SPEED, speed=1.5))
    assert rig.plant.speed == pytest.approx(1.5, abs=0.02)


@pytest.mark.parametrize("kind", ["kinematic", "steer-lag", "dynamic"])
def test_ecu_drives_every_plant_kind_in_speed_mode(kind: str) -> None:
    rig = Rig(plant=PlantConfig(kind=kind))  # type: ignore[arg-type]
    rig.engage()
    rig.run(6.0, *on(angle=0.1, mode=LongMode.SPEED, speed=2.0))
    assert rig.plant.speed == pytest.approx(2.0, abs=0.05)
    assert rig.plant.steer_angle == pytest.approx(0.1, abs=1e-3)
    assert all(rig.rx.decode(m).valid for _, m in rig.frames)


def test_acceleration_mode_clamps_to_vehicle_limits() -> None:
    rig = Rig()
    rig.engage()
    rig.run(0.5, *on(accel=8.0))
    assert rig.plant.accel == pytest.approx(VEHICLE.max_accel)


def test_steering_rate_limit_from_command_reaches_plant() -> None:
    plant = PlantConfig(kind="steer-lag", input_delay=0.0, steer_dead_time=0.0, steer_tau=0.01)
    rig = Rig(plant=plant, start=Pose(0.0, 0.0, 0.0, 1.0))
    rig.engage()
    steer = SteerCommand(0.4, rate_limit=0.1, enable=True)
    rig.run(0.5, steer, LongCommand(enable=True))
    assert 0.04 <= rig.plant.steer_angle <= 0.051  # 0.1 rad/s for ≤ 0.5 s


# --- reports -------------------------------------------------------------------------------


def test_report_periods_over_one_second() -> None:
    rig = Rig()
    rig.run(1.0)
    counts = Counter(msg.arbitration_id for _, msg in rig.frames)
    assert counts == {
        0x0B0: 100,  # 10 ms
        0x0B1: 50,  # 20 ms
        0x0B2: 10,  # 100 ms
        0x002: 100,  # 10 ms
        0x284: 50,  # 20 ms
        0x285: 50,  # 20 ms
        0x421: 17,  # 60 ms: 0, 60, …, 960 ms (no gear change, no event frame)
        0x176: 100,  # 10 ms
    }


def test_reports_from_a_late_caller_are_not_sent_in_bursts() -> None:
    ecu = Rig().ecu
    ecu.reports(0.0)
    ids = Counter(m.arbitration_id for m in ecu.reports(0.35))  # 350 ms late
    assert set(ids.values()) == {1}


def test_car_frames_decode_to_plant_values() -> None:
    rig = Rig(start=Pose(0.0, 0.0, 0.0, 1.5))
    rig.engage(angle=0.2)
    rig.run(0.5, *on(angle=0.2))
    t = rig.now
    rig.frames.clear()
    rig.run(0.0201, *on(angle=0.2))  # steady: values at t equal the plant's now
    speed, angle = rig.plant.speed, rig.plant.steer_angle
    assert angle == pytest.approx(0.2)
    wheel = rig.decoded(SteeringWheelAngle, since=t)[0]
    assert wheel.angle == pytest.approx(angle * VEHICLE.steering_ratio, abs=math.radians(0.1))
    speeds = {w.axle: w for w in rig.decoded(WheelSpeeds, since=t)}
    kmh = 0.005 / 3.6  # m/s, one bit of 0x284/0x285
    assert speeds["rear"].left == pytest.approx(speed, abs=kmh)
    assert speeds["rear"].right == pytest.approx(speed, abs=kmh)
    assert speeds["front"].left == pytest.approx(speed / math.cos(angle), abs=kmh)
    motor = rig.decoded(MotorSpeed, since=t)[0]
    assert motor.speed == pytest.approx(speed, abs=0.02)
    steer = rig.decoded(SteerReport, since=t)[0]
    assert steer.angle == pytest.approx(angle, abs=1e-4)
    assert steer.enabled


def test_long_report_speed_is_signed_when_reversing() -> None:
    rig = Rig(start=Pose(0.0, 0.0, 0.0, -1.0))
    rig.run(0.05)  # not engaged: the driver brakes from −1 m/s
    t_last = max(t for t, m in rig.frames if m.arbitration_id == 0x0B1)
    report = rig.decoded(LongReport)[-1]
    expected = -1.0 + EcuConfig().driver_decel * t_last  # m/s
    assert report.speed == pytest.approx(expected, abs=0.002)
    assert report.accel == pytest.approx(EcuConfig().driver_decel, abs=0.01)


# --- injections ----------------------------------------------------------------------------


def test_report_dropout_sends_nothing_for_its_duration() -> None:
    rig = Rig()
    rig.ecu.inject("report-dropout", at=0.1, duration=0.2)
    rig.run(0.5)
    times = sorted({t for t, _ in rig.frames})
    assert not [t for t in times if 0.1 <= t < 0.3]
    assert [t for t in times if t >= 0.3]
    assert all(rig.rx.decode(m).valid for _, m in rig.frames)  # counters resume in sequence


def test_corrupt_crc_reports_rejected_by_the_gateway_codec() -> None:
    rig = Rig()
    rig.ecu.inject("corrupt-crc", at=0.1, duration=0.1)
    rig.run(0.3)
    for _, msg in rig.frames:
        rig.rx.decode(msg)
    stats = rig.rx.stats
    assert stats[0x0B0].bad_crc == 10
    assert stats[0x0B1].bad_crc == 5
    assert stats[0x0B2].bad_crc == 1
    assert stats[0x002].bad_crc == 0  # CAR-CAN frames carry no leafgate E2E


def test_stuck_counter_reports_rejected_by_the_gateway_codec() -> None:
    rig = Rig()
    rig.ecu.inject("stuck-counter", at=0.1, duration=0.1)
    rig.run(0.3)
    errors = [rig.rx.decode(m).error for t, m in rig.frames if m.arbitration_id == 0x0B0]
    assert errors.count("bad_counter") >= 10  # every frame in the window (and one at its end)
    assert all(e in (None, "bad_counter") for e in errors)


def test_actuator_fault_latches_until_clear_faults() -> None:
    rig = Rig(start=Pose(0.0, 0.0, 0.0, 1.0))
    rig.engage()
    rig.ecu.inject("actuator-fault", at=rig.now, duration=0.2)
    rig.run(0.1, *on(accel=1.0))
    assert rig.ecu.state == EcuState.FAULT
    assert rig.plant.accel < 0.0  # the driver brakes
    rig.send(SystemCommand(GatewayState.STANDBY, clear_faults=True))  # too early: still faulty
    rig.run(0.3, SteerCommand(0.0), LongCommand())
    assert rig.ecu.state == EcuState.FAULT
    rig.send(SystemCommand(GatewayState.STANDBY, clear_faults=True))
    rig.run(0.05, SteerCommand(0.0), LongCommand())
    assert rig.ecu.state == EcuState.READY


@pytest.mark.parametrize(
    ("kind", "kw"),
    [
        ("no-such-fault", {}),
        ("override-torque", {"torgue": 3.0}),
        ("brake-pedal", {"pedal_pct": math.nan}),
    ],
)
def test_bad_injection_raises_a_leafgate_error(kind: str, kw: dict[str, float]) -> None:
    with pytest.raises(InjectionError) as info:
        Rig().ecu.inject(kind, at=0.0, **kw)
    assert isinstance(info.value, LeafgateError)


# --- properties ----------------------------------------------------------------------------


@settings(max_examples=15, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.floats(-0.8, 0.8),  # rad, the DBC's full range
            st.floats(-10.0, 10.0),  # m/s²
            st.sampled_from(list(Gear)),
            st.booleans(),
        ),
        min_size=1,
        max_size=15,
    )
)
def test_any_command_sequence_keeps_plant_in_limits_and_reports_valid(
    commands: list[tuple[float, float, Gear, bool]],
) -> None:
    rig = Rig(start=Pose(0.0, 0.0, 0.0, 3.0))
    for angle, accel, gear, enable in commands:
        steer = SteerCommand(angle, enable=enable)
        rig.run(0.06, steer, LongCommand(accel=accel, gear=gear, enable=enable))
        assert abs(rig.plant.steer_angle) <= VEHICLE.max_steer_angle + 1e-12
        assert VEHICLE.min_accel - 1e-9 <= rig.plant.accel <= VEHICLE.max_accel + 1e-9
    assert rig.ecu.counters.encode_errors == 0
    assert all(rig.rx.decode(m).valid for _, m in rig.frames)


# --- real time -----------------------------------------------------------------------------


@pytest.mark.parametrize("separate_car_bus", [False, True])
def test_realtime_ecu_reports_on_virtual_buses_and_stops_cleanly(separate_car_bus: bool) -> None:
    channel = f"ecu-rt-{id(object())}"
    car_cfg = BusConfig(interface="virtual", channel=channel + "-car") if separate_car_bus else None
    can_cfg = CanConfig(dbw=BusConfig(interface="virtual", channel=channel), car=car_cfg)
    config = LeafgateConfig(can=can_cfg, sim=replace(SimConfig(), ecu=EcuConfig()))
    car_ids = CanCodec(profile="leafgate-dbw").receive_ids("car")
    stop = threading.Event()
    result: list[RealtimeStats] = []
    gateway = can.Bus(interface="virtual", channel=channel)
    car = can.Bus(interface="virtual", channel=channel + "-car") if separate_car_bus else None
    try:
        thread = threading.Thread(
            target=lambda: result.append(run_ecu_realtime(config, stop)), daemon=True
        )
        thread.start()
        codec = CanCodec(profile="leafgate-dbw")
        seen: Counter[int] = Counter()
        for _ in range(2000):
            msg = gateway.recv(timeout=1.0)
            assert msg is not None, "the ECU sent nothing"
            decoded = codec.decode(msg)
            assert decoded.valid, decoded.error
            seen[msg.arbitration_id] += 1
            if seen[0x0B2] >= 2:
                break
        gateway.send(CanCodec(profile="leafgate-dbw").encode(SteerCommand(0.0)))
        car_frame = car.recv(timeout=1.0) if car is not None else None
        stop.set()
        thread.join(timeout=5.0)
        assert not thread.is_alive()
    finally:
        stop.set()
        gateway.shutdown()
        if car is not None:
            car.shutdown()
    assert seen[0x0B0] >= 5 and seen[0x0B1] >= 2
    if separate_car_bus:
        assert not car_ids & set(seen)
        assert car_frame is not None and car_frame.arbitration_id in car_ids
    else:
        assert car_ids <= set(seen)
    (stats,) = result
    assert stats.ticks > 0 and stats.frames_sent >= sum(seen.values())
