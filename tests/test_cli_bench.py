"""One bench per port: config/sim.yaml's ``bench: N`` gives the multicast and Zenoh ports, so
two benches on one host stay apart (issue 19, item 7)."""

from __future__ import annotations

from pathlib import Path

import pytest

from leafgate.cli import main
from leafgate.errors import ConfigError
from leafgate.settings import BENCH_ENV, load_config

ROOT = Path(__file__).resolve().parents[1]
SIM = ROOT / "config" / "sim.yaml"


def _ports(monkeypatch: pytest.MonkeyPatch, bench: str | None) -> tuple[int, tuple[str, ...]]:
    if bench is None:
        monkeypatch.delenv(BENCH_ENV, raising=False)
    else:
        monkeypatch.setenv(BENCH_ENV, bench)
    cfg = load_config(SIM)
    return cfg.can.dbw.kwargs["port"], cfg.zenoh.listen


def test_two_benches_get_different_ports(monkeypatch: pytest.MonkeyPatch) -> None:
    assert _ports(monkeypatch, None) == (43113, ("tcp/127.0.0.1:17447",))
    one = _ports(monkeypatch, "1")
    assert one == (43114, ("tcp/127.0.0.1:17448",))
    assert _ports(monkeypatch, "250") == (43363, ("tcp/127.0.0.1:17697",))


def test_bad_bench_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    for value in ("x", "-1", "1000"):
        monkeypatch.setenv(BENCH_ENV, value)
        with pytest.raises(ConfigError, match=f"{BENCH_ENV}='{value}'.*not a bench number"):
            load_config(SIM)


def test_file_ports_win_and_the_car_config_is_untouched(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(BENCH_ENV, "7")
    path = tmp_path / "sim.yaml"
    cfg = load_config(ROOT / "config" / "leafgate.yaml")  # no bench: key
    assert cfg.zenoh.listen == ("tcp/127.0.0.1:7450",)
    path.write_text(
        "bench: 3\ncan: {dbw: {interface: udp_multicast, channel: 239.74.163.1,"
        " kwargs: {port: 50000}}}\nzenoh: {listen: ['tcp/127.0.0.1:50001']}\n"
    )
    cfg = load_config(path)
    assert cfg.can.dbw.kwargs["port"] == 50000 and cfg.zenoh.listen == ("tcp/127.0.0.1:50001",)


def test_bench_option_sets_it_for_the_process(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv(BENCH_ENV, "0")  # main() sets it; monkeypatch restores it afterwards
    assert main(["--bench", "2", "check-config", str(SIM)]) == 0
    out = capsys.readouterr().out
    assert "port 43115" in out and "tcp/127.0.0.1:17449" in out
