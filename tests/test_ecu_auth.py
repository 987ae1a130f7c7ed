"""The simulated ECU with authenticated command frames (profile leafgate-dbw-auth, issue 17).

A replayed or forged frame is rejected and counted (``stale_freshness``, ``bad_mac``), shown on
DBW_SYSTEM_RPT like the other rejects, and more than ``race_drops`` of them within
``race_window`` brake the car to rest: the counter race's rule, one rule.
"""

from __future__ import annotations

import can
import pytest

from leafgate.can.codec import CanCodec
from leafgate.config import VehicleConfig
from leafgate.config.sim import EcuConfig, PlantConfig
from leafgate.errors import ConfigError
from leafgate.messages import (
    EcuState,
    GatewayState,
    LongCommand,
    Pose,
    SteerCommand,
    SystemCommand,
    SystemReport,
)
from leafgate.sim.ecu import SimulatedEcu
from leafgate.sim.plant import make_plant

PROFILE = "leafgate-dbw-auth"
KEY = bytes(range(32))
VEHICLE = VehicleConfig(profile=PROFILE)
DT = 0.001  # s
CMD_TICKS = 20  # ticks between command frames
EPOCH = 1_790_000_000.0  # s, Unix time of the rig's t = 0


class AuthRig:
    """Gateway codec and ECU of the authenticated profile on one simulated Unix clock."""

    def __init__(self, start: Pose | None = None, epoch: float = EPOCH) -> None:
        self.tick = 0
        self.epoch = epoch
        self.plant = make_plant(
            PlantConfig(kind="kinematic", input_delay=0.0),
            VEHICLE,
            start or Pose(0.0, 0.0, 0.0, 0.0),
        )
        ecu_codec = CanCodec(profile=PROFILE, key=KEY, clock=self.unix)
        self.ecu = SimulatedEcu(EcuConfig(), self.plant, VEHICLE, ecu_codec)
        self.tx = CanCodec(profile=PROFILE, key=KEY, clock=self.unix)
        self.sent: list[can.Message] = []
        self.reports: list[can.Message] = []
        self.accepted_foreign = 0

    @property
    def now(self) -> float:
        return self.tick * DT

    def unix(self) -> float:
        return self.epoch + self.now

    def send(self, value: SteerCommand | LongCommand | SystemCommand) -> can.Message:
        msg = self.tx.encode(value, timestamp=self.now)
        self.sent.append(msg)
        self.ecu.receive_frame(self.now, msg)
        return msg

    def inject(self, msg: can.Message) -> None:
        """A foreign frame on the bus; counts it when the ECU accepted it."""
        if self.ecu.receive_frame(self.now, msg).valid:
            self.accepted_foreign += 1

    def run(self, duration: float, *commands: SteerCommand | LongCommand, foreign=None) -> None:
        """Step ``duration`` s; each command period sends ``commands``, then ``foreign(msg)``
        for each genuine frame (a racer answering it)."""
        for _ in range(round(duration / DT)):
            if self.tick % CMD_TICKS == 0:
                for value in commands:
                    msg = self.send(value)
                    if foreign is not None:
                        foreign(msg)
            self.reports.extend(self.ecu.reports(self.now))
            self.ecu.step(self.now, DT)
            self.tick += 1

    def engage(self) -> None:
        self.run(0.1, SteerCommand(0.0), LongCommand())
        self.run(0.04, SteerCommand(0.0, enable=True), LongCommand(accel=1.0, enable=True))
        assert self.ecu.state == EcuState.ENGAGED

    def system_reports(self) -> list[SystemReport]:
        rx = CanCodec(profile=PROFILE)
        out = []
        for msg in self.reports:
            d = rx.decode(msg)
            if d.valid and isinstance(d.value, SystemReport):
                out.append(d.value)
        return out


def recorded_engagement(epoch: float) -> list[can.Message]:
    """A drive's engagement as recorded: ENABLE=0, then ENABLE=1 with acceleration."""
    rig = AuthRig(epoch=epoch)
    rig.run(0.2, SteerCommand(0.0), LongCommand())
    rig.run(1.0, SteerCommand(0.1, enable=True), LongCommand(accel=1.5, enable=True))
    return rig.sent


def test_an_authenticated_stream_engages_and_drives() -> None:
    rig = AuthRig()
    rig.engage()
    rig.run(1.0, SteerCommand(0.0, enable=True), LongCommand(accel=1.0, enable=True))
    assert rig.plant.speed > 0.5
    assert rig.ecu.counters.rx_errors == 0


def test_an_ecu_without_the_key_refuses_to_start() -> None:
    plant = make_plant(PlantConfig(kind="kinematic"), VEHICLE, Pose(0.0, 0.0, 0.0, 0.0))
    with pytest.raises(ConfigError, match="needs the key"):
        SimulatedEcu(EcuConfig(), plant, VEHICLE)


def test_an_old_recording_replayed_after_a_restart_never_drives_the_car() -> None:
    old = recorded_engagement(EPOCH - 3600.0)  # an hour ago, before both ends restarted
    replay = iter(old)
    rig = AuthRig()

    def racer(genuine: can.Message) -> None:
        msg = next(replay, None)
        if msg is not None:
            rig.inject(msg)

    rig.run(2.0, SteerCommand(0.0), LongCommand(), foreign=racer)  # the gateway in STANDBY
    c = rig.ecu.counters
    assert rig.accepted_foreign == 0
    assert c.bad_mac + c.stale_freshness > 0 and c.counter_races == 1
    assert rig.ecu.state == EcuState.FAULT
    assert rig.plant.speed == 0.0 and abs(rig.plant.x) < 1e-9


def test_the_stream_replayed_byte_for_byte_right_after_each_frame_is_stale() -> None:
    """The attack of issue 17: the gateway's own frames sent again at once (within the window)."""
    rig = AuthRig()
    rig.run(0.2, SteerCommand(0.0), LongCommand())
    # the engagement sequence of *this* run, replayed while the gateway is in STANDBY again
    rig.run(0.5, SteerCommand(0.1, enable=True), LongCommand(accel=1.5, enable=True))
    rig.run(0.5, SteerCommand(0.0), LongCommand())  # the gateway disengaged
    recorded = iter(list(rig.sent))
    start = rig.plant.x

    def racer(genuine: can.Message) -> None:
        rig.inject(genuine)  # the genuine frame again, byte for byte
        msg = next(recorded, None)
        if msg is not None:
            rig.inject(msg)

    rig.run(2.0, SteerCommand(0.0), LongCommand(), foreign=racer)
    c = rig.ecu.counters
    assert rig.accepted_foreign == 0
    assert c.stale_freshness > 0 and c.counter_races >= 1
    assert rig.ecu.state == EcuState.FAULT and not rig.ecu.engaged
    assert rig.plant.speed == 0.0 and rig.plant.x - start < 0.5  # braked from its roll-out


def test_forged_frames_are_bad_macs_and_brake_the_car_to_rest() -> None:
    rig = AuthRig(start=Pose(0.0, 0.0, 0.0, 2.0))
    rig.engage()
    forger = CanCodec(profile=PROFILE, key=bytes(32), clock=rig.unix)  # not the car's key

    def racer(genuine: can.Message) -> None:
        rig.inject(forger.encode(SteerCommand(0.5, enable=True), timestamp=rig.now))

    rig.run(0.2, SteerCommand(0.0, enable=True), LongCommand(accel=0.5, enable=True), foreign=racer)
    assert rig.ecu.counters.bad_mac > EcuConfig().race_drops
    assert rig.ecu.state == EcuState.FAULT and not rig.ecu.engaged
    rig.run(2.0, SteerCommand(0.0, enable=True), LongCommand(accel=0.5, enable=True))
    assert rig.plant.speed == 0.0  # braked to rest at timeout_decel
    assert abs(rig.plant.steer_angle) < 0.01  # no forged angle reached the wheel
    # the rejects are on DBW_SYSTEM_RPT like the others: integrity bit and the count
    last = rig.system_reports()[-1]
    assert last.fault_bad_crc and last.rx_error_count == rig.ecu.counters.rx_errors


def test_a_few_rejected_frames_are_not_a_race() -> None:
    rig = AuthRig()
    rig.engage()
    for _ in range(EcuConfig().race_drops):
        stale = rig.sent[-1]
        rig.inject(stale)  # the last genuine frame again
        rig.run(0.6, SteerCommand(0.0, enable=True), LongCommand(accel=1.0, enable=True))
    assert rig.ecu.counters.stale_freshness == EcuConfig().race_drops
    assert rig.ecu.engaged and rig.ecu.counters.counter_races == 0


def test_clear_faults_after_a_quiet_window_makes_the_ecu_ready_again() -> None:
    rig = AuthRig()
    forger = CanCodec(profile=PROFILE, key=bytes(32), clock=rig.unix)
    rig.run(
        0.2,
        SteerCommand(0.0),
        LongCommand(),
        foreign=lambda m: rig.inject(forger.encode(SteerCommand(0.0), timestamp=rig.now)),
    )
    assert rig.ecu.state == EcuState.FAULT
    rig.run(0.6, SteerCommand(0.0), LongCommand())
    rig.send(SystemCommand(GatewayState.STANDBY, clear_faults=True))
    rig.run(0.05, SteerCommand(0.0), LongCommand())
    assert rig.ecu.state == EcuState.READY
