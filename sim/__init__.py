"""Vehicle, environment and sensor simulator with ground truth (DESIGN.md "Layout").

Entry points: :func:`adaptnav.sim.scenario.load_scenario` and :func:`adaptnav.sim.simulator.simulate`
(also importable from here, lazily, so ``import sim.seabed`` stays light).
"""
from __future__ import annotations

__all__ = ["load_scenario", "simulate", "Scenario", "SimResult"]


def __getattr__(name: str):
    if name in ("load_scenario", "Scenario"):
        from adaptnav.sim import scenario

        return getattr(scenario, name)
    if name in ("simulate", "SimResult"):
        from adaptnav.sim import simulator

        return getattr(simulator, name)
    raise AttributeError(f"module 'sim' has no attribute {name!r}")
