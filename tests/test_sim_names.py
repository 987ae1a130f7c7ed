"""The fault names of ``leafgate sim`` and ``leafgate sim-ecu``: what each ``--help`` says the
other command takes is what the other command's parser takes."""

from __future__ import annotations

import pytest

from leafgate.errors import ConfigError
from leafgate.sim.names import TO_SIM, TO_SIM_ECU, only_here
from leafgate.sim.realtime import SIM_ECU_INJECTIONS, EngagedInjection
from leafgate.sim.runner import INJECTION_KINDS, Injection

SIM_ONLY = only_here(INJECTION_KINDS, SIM_ECU_INJECTIONS, TO_SIM).split(", ")
SIM_ECU_ONLY = only_here(SIM_ECU_INJECTIONS, INJECTION_KINDS, TO_SIM_ECU).split(", ")


@pytest.mark.parametrize("kind", sorted(INJECTION_KINDS))
def test_sim_ecu_takes_every_sim_fault_its_help_does_not_exclude(kind: str) -> None:
    text = f"{kind}@3"
    if kind in SIM_ONLY:
        with pytest.raises(ConfigError, match="unknown kind"):
            EngagedInjection.parse(text)
    else:
        assert EngagedInjection.parse(text).kind == TO_SIM_ECU.get(kind, kind)


@pytest.mark.parametrize("kind", sorted(SIM_ECU_INJECTIONS))
def test_sim_takes_every_sim_ecu_fault_its_help_does_not_exclude(kind: str) -> None:
    text = f"{kind}@3"
    if kind in SIM_ECU_ONLY:
        with pytest.raises(ConfigError, match="unknown kind"):
            Injection.parse(text)
    else:
        assert Injection.parse(text).kind == TO_SIM.get(kind, kind)


def test_each_command_has_faults_the_other_lacks() -> None:
    """The gateway-side faults exist only in the one-process simulation, a late localization
    only in the ECU process: both help texts name them (not "-")."""
    assert "command-dropout" in SIM_ONLY and "foreign-command" in SIM_ONLY
    assert SIM_ECU_ONLY == ["localization-delay"]


def test_only_here_maps_the_other_spelling() -> None:
    assert only_here(["a", "b"], ["c"], {"c": "a"}) == "b"
    assert only_here(["a"], ["c"], {"c": "a"}) == "-"
