"""The daemon's log: state transitions with their reason, inputs lost and regained, at syslog
priorities the journal understands (``<N>`` prefixes, ``priority`` in JSON lines)."""

from __future__ import annotations

import io
import json
import logging
import os
import signal
import time
from typing import Any

import pytest

from leafgate.journal import JsonFormatter, TextFormatter, priority_of, under_journal
from leafgate.runtime.daemon import StateLog, SystemdWatchdog, set_rt_priority
from leafgate.settings import load_config
from leafgate.sim.runner import Injection, run
from leafgate.sim.scenarios import get_scenario


class _LogOnly:
    """A recorder stand-in for the simulator that only feeds the daemon's state log."""

    def __init__(self, state_log: StateLog) -> None:
        self.state_log = state_log

    def wrap_controller(self, controller: Any) -> Any:
        return controller

    def on_can_frame(self, *_: Any) -> None:
        pass

    def on_zenoh_input(self, *_: Any) -> None:
        pass

    def on_tick(self, *args: Any) -> None:
        self.state_log.on_tick(*args)


def _drive_with_log(formatter: logging.Formatter, *injections: str) -> list[str]:
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(formatter)
    logger = logging.getLogger("test.daemon.statelog")
    logger.handlers[:] = [handler]
    logger.setLevel(logging.DEBUG)
    logger.propagate = False
    recorder: Any = _LogOnly(StateLog(logger))
    run(
        load_config(None),
        get_scenario("s-curve"),
        injections=tuple(Injection.parse(t) for t in injections),
        recorder=recorder,
    )
    return stream.getvalue().splitlines()


def test_json_lines_carry_transitions_reasons_and_priorities() -> None:
    lines = _drive_with_log(JsonFormatter(journal=True), "localization-dropout@8s")
    assert lines and all(line.startswith("<") for line in lines)
    records = []
    for line in lines:
        prefix, _, body = line.partition(">")
        record = json.loads(body)
        assert int(prefix[1:]) == record["priority"]
        records.append(record)
    transitions = [r for r in records if r.get("event") == "transition"]
    path = [(r["from"], r["to"]) for r in transitions]
    assert path == [("STANDBY", "ENGAGED"), ("ENGAGED", "STOPPING"), ("STOPPING", "FAULT")]
    engaged, stopping, fault = transitions
    assert engaged["priority"] == 5 and engaged["reason"]
    assert stopping["priority"] == 4
    assert fault["priority"] == 3 and "localization" in fault["reason"]
    assert fault["msg"].startswith("state STOPPING → FAULT: ")
    changes = [r for r in records if r.get("event") == "input" and r["input"] == "localization"]
    assert changes[0]["msg"] == "input localization received" and changes[0]["priority"] == 6
    lost = changes[1]
    assert lost["priority"] == 4 and lost["msg"].startswith("input localization lost: ")
    assert lost["status"] == "stale"


def test_text_lines_name_the_input_lost_and_back() -> None:
    lines = _drive_with_log(TextFormatter(journal=True), "report-dropout@6+0.2")
    text = "\n".join(lines)
    assert "<4>WARNING" in text and "input steer_report lost" in text
    assert "input steer_report back after" in text
    assert any(line.startswith("<3>ERROR") and "→ FAULT" in line for line in lines)


def test_state_log_quiet_without_changes() -> None:
    lines = _drive_with_log(TextFormatter(journal=False))
    # One engagement, one arrival at the goal; each input arrives once. (The simulator
    # publishes its plan once, so the trajectory ages out near the end of the drive.)
    states = [line for line in lines if "state " in line and "→" in line]
    assert states[0].endswith("state STANDBY → ENGAGED: operator engage")
    assert states[1].endswith("state ENGAGED → STANDBY: trajectory end reached")
    assert len(states) == 2, lines
    received = [line for line in lines if line.endswith(" received")]
    assert len(received) == 5, lines  # the five inputs, not the error counter or overruns
    assert not any(line.startswith("<") for line in lines)


def test_priority_of_levels_and_override() -> None:
    record = logging.LogRecord("x", logging.WARNING, __file__, 1, "m", None, None)
    assert priority_of(record) == 4
    record.priority = 5
    assert priority_of(record) == 5
    record = logging.LogRecord("x", logging.DEBUG, __file__, 1, "m", None, None)
    assert priority_of(record) == 7


def test_under_journal_compares_device_and_inode(
    tmp_path: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    with open(tmp_path / "out", "w") as stream:
        st = os.fstat(stream.fileno())
        monkeypatch.setenv("JOURNAL_STREAM", f"{st.st_dev}:{st.st_ino}")
        assert under_journal(stream)
        monkeypatch.setenv("JOURNAL_STREAM", f"{st.st_dev}:{st.st_ino + 1}")
        assert not under_journal(stream)
        monkeypatch.delenv("JOURNAL_STREAM")
        assert not under_journal(stream)


def test_systemd_watchdog_kicks_at_half_the_interval(monkeypatch: pytest.MonkeyPatch) -> None:
    sent: list[str] = []
    monkeypatch.setattr(
        "leafgate.runtime.daemon.sd_notify", lambda state: sent.append(state) or True
    )
    monkeypatch.setenv("WATCHDOG_USEC", "2000000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    dog = SystemdWatchdog.from_environment()
    assert dog.interval == pytest.approx(1.0)
    dog.kick(0.0)  # the first tick, before READY=1: no ping yet
    assert sent == []
    dog.start(0.0)  # READY=1 has gone out
    for k in range(151):  # 3 s of 20 ms ticks
        dog.kick(k * 0.02)
    assert sent == ["WATCHDOG=1"] * 4  # at 0, 1, 2 and 3 s
    monkeypatch.setenv("WATCHDOG_PID", "1")  # meant for another process
    assert SystemdWatchdog.from_environment().interval is None
    monkeypatch.delenv("WATCHDOG_USEC")
    assert SystemdWatchdog.from_environment().interval is None


def test_rt_priority_applies_to_the_calling_thread_only(caplog: pytest.LogCaptureFixture) -> None:
    import threading

    other = os.sched_getscheduler(0)
    result: list[bool] = []

    def loop_thread() -> None:
        result.append(set_rt_priority(10))
        if result[0]:
            assert os.sched_getscheduler(0) == os.SCHED_FIFO

    with caplog.at_level(logging.INFO):
        t = threading.Thread(target=loop_thread)
        t.start()
        t.join()
    assert os.sched_getscheduler(0) == other  # this (main) thread is unchanged
    if not result[0]:
        assert "SCHED_FIFO 10 refused" in caplog.text
    assert set_rt_priority(0) is False


def test_a_closed_log_stream_goes_quiet_without_a_traceback(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from leafgate.journal import setup_logging

    stream = io.StringIO()
    handler = setup_logging("text", stream=stream, queued=False)
    try:
        stream.close()  # the reader went away (`leafgate run | head`, a closed journal)
        logging.getLogger("test.closed").warning("still running")
        logging.getLogger("test.closed").warning("and again")
        assert "Logging error" not in capsys.readouterr().err
    finally:
        logging.getLogger().removeHandler(handler)


class _SlowReader(io.StringIO):
    """A stdout that Ctrl-C interrupts while the last queued lines are written at exit."""

    def write(self, text: str) -> int:
        signal.raise_signal(signal.SIGINT)  # noted now, raised on the main thread (its join)
        time.sleep(0.05)
        return super().write(text)


def test_a_ctrl_c_while_the_queued_log_is_written_at_exit_is_no_traceback() -> None:
    """``leafgate run`` writes its queued log lines at exit (atexit); a Ctrl-C then (the
    daemon's third, once stopped: 1 in 30 trials) ended in "Exception ignored in atexit
    callback" and KeyboardInterrupt's traceback. The lines still queued are dropped instead."""
    from leafgate.journal import _stop_listener, setup_logging

    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        setup_logging("text", stream=_SlowReader(), queued=True)
        logging.getLogger("leafgate.test").info("the last line")
        try:
            _stop_listener()
            time.sleep(0.2)  # a KeyboardInterrupt still pending is raised here
        except KeyboardInterrupt:
            pytest.fail("Ctrl-C while the log was written escaped the atexit callback")
    finally:
        signal.signal(signal.SIGINT, previous)
        root.handlers[:], root.level = handlers, level
