"""CalibratorSonar's per-ping float path (AnchoredDeadReckoning.push_floats →
ObjectFrontEnd.push_floats) against the array path it replaced (push with a position array and
an isotropic covariance matrix), sighting for sighting, bit for bit."""
from __future__ import annotations

import math

import numpy as np
import pytest

from adaptnav.calibration.sidescan import CalibratorSonar
from adaptnav.sim.seabed import Seabed
from adaptnav.sim.sidescan import SidescanRenderer
from adaptnav.sonar.dead_reckoning import AnchoredDeadReckoning
from adaptnav.sonar.objects import ObjectFrontEnd

DS_M = 0.375  # along-track metres per ping (1.5 m/s, 4 Hz)


@pytest.fixture(scope="module")
def survey_pings():
    sb = Seabed.survey((100.0, 200.0), np.random.default_rng(31), n_objects=80, wreck=False)
    ren = SidescanRenderer(sb, 40.0, 512)
    k = np.arange(460)
    pos = np.column_stack([5.0 + k * DS_M, np.full(k.size, 50.0)])
    pings = ren.render_track(k * DS_M / 1.5, pos, 0.0, 10.0, np.random.default_rng(32), 1.5)
    return pings, pos


def _fields(o):
    return (o.t_s, o.side, o.ground_range_m, o.height_m, o.shadow_length_m, o.length_along_m, o.width_across_m,
            o.contrast, o.altitude_m, o.row, o.heading_rad, o.weak, o.pos_n_m.tobytes(), o.nav_cov.tobytes(),
            o.det_cov.tobytes(), None if o.jump_n_m is None else o.jump_n_m.tobytes(),
            None if o.vel_cov is None else o.vel_cov.tobytes())


def test_calibrator_sonar_float_path_is_the_array_path(survey_pings):
    pings, pos = survey_pings
    # a ping out of order (rejected by both), fixes before and during the pass (σ NaN → 1 km
    # before the first), one far off (a jump)
    pings = list(pings)
    pings.insert(300, pings[120])
    fixes = {0: (pings[0].t_s + 40.0, pos[100] + [3.0, -2.0], 2.5), 250: (pings[250].t_s, pos[250] - 40.0, 1.0)}
    new = CalibratorSonar()
    ref_dr, ref_fe = AnchoredDeadReckoning(), ObjectFrontEnd()
    got, want = [], []
    for k, ping in enumerate(pings):
        if k in fixes:
            new.dead_reckoning.fix(*fixes[k])
            ref_dr.fix(*fixes[k])
        batch = new.push(ping)
        if batch is not None:
            got += batch.sightings
        p, sigma = ref_dr.push(ping)
        s = sigma if math.isfinite(sigma) else 1e3
        want += ref_fe.push(ping, p, np.eye(2) * (s * s), float(ping.heading_rad))
    assert new.front_end.rejected == ref_fe.rejected == {"out of order": 1}
    assert len(want) > 5
    assert [_fields(o) for o in got] == [_fields(o) for o in want]
    # the dead reckonings agree too (push returns the float path's position as an array)
    assert ref_dr._P.tobytes() == new.dead_reckoning._P.tobytes()


def test_push_floats_with_velocity_is_push(survey_pings):
    # the jump-free track (vel_n_m_s given): the position array rebuilt from the floats
    pings, pos = survey_pings
    rng = np.random.default_rng(33)
    a, b = ObjectFrontEnd(), ObjectFrontEnd()
    got, want = [], []
    jump, jumps, last = np.zeros(2), set(), None  # the jumps at every ping, computed here
    for ping, q in zip(pings, pos):
        p = q + rng.normal(0.0, 0.3, 2)
        cov = np.array([[0.5, 0.1], [0.1, 0.7]])
        vel = np.array([1.5, 0.0]) + rng.normal(0.0, 0.01, 2)
        vcov = np.eye(2) * 1e-4
        if last is not None:
            jump = jump + (p - (last[1] + 0.5 * (last[2] + vel) * (ping.t_s - last[0])))
        last = (ping.t_s, p, vel)
        jumps.add(jump.tobytes())
        want += a.push(ping, p, cov, 0.0, vel, vcov)
        pn, pe = p.tolist()
        got += b.push_floats(ping, pn, pe, cov.reshape(4).tolist(), 0.0, vel, vcov)
    assert len(want) > 5
    assert [_fields(o) for o in got] == [_fields(o) for o in want]
    assert all(o.jump_n_m.tobytes() in jumps for o in got)
    # a non-finite covariance entry is rejected as by push
    assert b.push_floats(pings[-1], 0.0, 0.0, [1.0, math.nan, 0.0, 1.0], 0.0) == []
    assert b.rejected.get("non-finite") == 1
