"""The sensor table (adaptnav.fusion.samples.SENSORS) is the one list of sample kinds:
every consumer covers every kind it must (the aid sources against it:
tests/fusion/test_aiding_contract.py)."""
from __future__ import annotations

import dataclasses
import inspect

import pytest

from adaptnav.fusion import samples as fs
from adaptnav.fusion.samples import ROLES, SENSOR_BY_KIND, SENSORS, kinds


def test_rows_are_unique_and_well_formed():
    assert len(SENSOR_BY_KIND) == len(SENSORS)
    assert len({s.priority for s in SENSORS}) == len(SENSORS), "equal priorities make the replay order ambiguous"
    for s in SENSORS:
        assert s.role in ROLES, s
        if s.sample_type is not None:
            assert s.sample_type.KIND == s.kind
        if s.role == "aid":
            assert s.aid_source == s.kind, s  # its status carries the aid source's name
    assert SENSOR_BY_KIND["truth"].priority == max(s.priority for s in SENSORS)  # metrics see every update


def test_every_sample_class_has_a_row():
    declared = {cls.KIND for _, cls in inspect.getmembers(fs, inspect.isclass)
                if dataclasses.is_dataclass(cls) and isinstance(getattr(cls, "KIND", None), str)}
    assert declared - {"imu_batch"} == {s.kind for s in SENSORS if s.sample_type is not None}


def test_the_sonar_row_is_the_sonar_ping():
    from adaptnav.sonar.ping import SonarPing

    assert SENSOR_BY_KIND[SonarPing.KIND].sample_type is None  # declared in the sonar leaf package


def test_every_kind_has_a_codec_and_a_schema():
    from adaptnav.service.transport import codec

    for kind in kinds():
        assert kind in codec.kinds(), kind
        assert codec.schema_for(kind)["type"] == "object"


def test_the_estimator_handles_or_ignores_every_kind():
    from adaptnav.fusion.eskf import AID_KINDS, IGNORED_KINDS

    handled = set(kinds(role="propagate")) | set(kinds(role="control")) | AID_KINDS
    assert not handled & IGNORED_KINDS
    # calibration-only kinds pass the estimator without effect; everything else is named
    assert handled | IGNORED_KINDS | set(kinds(role="calibration")) == set(kinds())


def test_the_calibrator_takes_what_the_table_says():
    from adaptnav.calibration.online import UNUSED_KINDS
    from adaptnav.service.runtime import runner

    assert UNUSED_KINDS == set(kinds(calibrator_uses=False))
    assert runner._CALIBRATOR_UNUSED == UNUSED_KINDS


def test_the_service_lists_derive_from_the_table():
    from adaptnav.service.daemon import SENSOR_AID_SOURCE
    from adaptnav.service.runtime.sources import NAV_STREAMS

    assert set(NAV_STREAMS) <= set(kinds())
    assert set(SENSOR_AID_SOURCE) == {s.kind for s in SENSORS if s.role in ("aid", "control")}


@pytest.mark.slow
def test_the_simulator_makes_only_kinds_of_the_table():
    from adaptnav.sim.scenario import load_scenario
    from adaptnav.sim.simulator import simulate

    result = simulate(load_scenario("short", ["duration_s=30"]))
    assert set(result.samples) <= set(kinds()), set(result.samples) - set(kinds())
