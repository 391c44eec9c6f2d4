"""What replay only logged is in summary.json's ``warnings`` too: a first fix passed over
or an unconfirmed one taken for the map origin, and a jump of the input's time base."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from adaptnav.fusion.samples import ImuBatch
from adaptnav.service.cli import main
from adaptnav.service.transport.logs import write_mcap


@pytest.fixture(scope="module")
def mission():
    from adaptnav.service.runtime.sources import simulate
    from adaptnav.sim.scenario import load_scenario

    items = list(simulate(load_scenario("short", ["duration_s=60"])).iter_blocks())
    return [i for i in items if getattr(i, "KIND", "") != "truth"]


def _replay(tmp_path, items) -> dict:
    write_mcap(tmp_path / "m.mcap", items)  # no scenario metadata: the origin comes from the fixes
    assert main(["replay", str(tmp_path / "m.mcap"), "--out", str(tmp_path / "out"), "--no-plots",
                 "--no-progress"]) == 0
    return json.loads((tmp_path / "out" / "summary.json").read_text())


def test_a_first_fix_passed_over_for_the_origin_is_a_summary_warning(tmp_path, mission):
    fixes = [i for i in mission if getattr(i, "KIND", "") in ("gnss", "usbl")]
    bad = replace(fixes[0], lat_rad=fixes[0].lat_rad + 4.755e6 / 6.371e6)  # 4,755 km north
    summary = _replay(tmp_path, [bad if i is fixes[0] else i for i in mission])
    origin = [w for w in summary["warnings"] if w.startswith("origin:")]
    assert len(origin) == 1 and f"t={bad.t_s:.3f} s is not confirmed" in origin[0], summary["warnings"]


def test_a_jump_of_the_time_base_is_a_summary_warning(tmp_path, mission):
    t_jump, jump_s = 30.0, -500.0  # from 30 s on, the input's clock reads 500 s earlier

    def shifted(item):
        if isinstance(item, ImuBatch):
            t = np.asarray(item.t_s, dtype=float)
            return ImuBatch(np.where(t >= t_jump, t + jump_s, t), item.specific_force_b_m_s2, item.omega_b_rad_s)
        return replace(item, t_s=item.t_s + jump_s) if item.t_s >= t_jump else item

    summary = _replay(tmp_path, [shifted(i) for i in mission])
    # the log is read in time order: the shifted part first, then a jump forward to the rest
    assert summary["clock_jumps_s"], "the replay saw no jump"
    assert all(400.0 < abs(j) < 600.0 for j in summary["clock_jumps_s"]), summary["clock_jumps_s"]
    jumps = [w for w in summary["warnings"] if "time base jumped" in w]
    assert len(jumps) == 1, summary["warnings"]
    assert all(f"{j:+.3f} s" in jumps[0] for j in summary["clock_jumps_s"])
    # navigation went on through the re-basing (the filter's held thrust moved with it)
    assert summary["errors"] == {} and summary["nav_states"] > 0


def test_a_depth_sensor_noisier_than_the_bound_is_a_summary_warning(tmp_path, mission):
    from adaptnav.fusion.frames import GRAVITY_M_S2
    from adaptnav.fusion.samples import DepthSample

    # the mission's pressure sensor with 1 m of white noise (the bound: filter.depth.adaptive_max_sigma_m 0.5)
    rng = np.random.default_rng(4)
    noisy = [replace(i, pressure_pa=i.pressure_pa + 1025.0 * GRAVITY_M_S2 * rng.standard_normal())
             if isinstance(i, DepthSample) else i for i in mission]
    summary = _replay(tmp_path, noisy)
    depth = summary["filter"]["depth_noise"]
    assert depth["sigma_m"] == depth["max_sigma_m"] == 0.5 and depth["fraction_at_bound"] > 0.5, depth
    assert any(w.startswith("the depth sensor was noisier than the bound of 0.5 m") for w in summary["warnings"])
    (tmp_path / "clean").mkdir()
    assert not any("depth sensor" in w for w in _replay(tmp_path / "clean", mission)["warnings"])
