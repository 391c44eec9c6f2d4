"""The two records made most often (every output epoch's NavState, every fusion attempt's
AidStatus) have a one-call __init__ instead of the frozen dataclass's own: it must set every
field the dataclass declares, under its name, with the declared defaults, and stay frozen."""
import dataclasses
import pickle

import pytest

from adaptnav.fusion.state import NavState
from adaptnav.fusion.status import AidStatus


@pytest.mark.parametrize("cls", [NavState, AidStatus])
def test_the_init_sets_every_declared_field_and_stays_frozen(cls):
    fields = dataclasses.fields(cls)
    values = {f.name: ("value", i) for i, f in enumerate(fields)}  # distinct sentinels
    for rec in (cls(**values), cls(*values.values())):
        assert vars(rec) == values
        assert dataclasses.asdict(rec) == values
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(rec, fields[0].name, None)
        assert pickle.loads(pickle.dumps(rec)) == rec
        assert dataclasses.replace(rec, **{fields[0].name: "other"}) != rec
    defaulted = [f for f in fields if f.default is not dataclasses.MISSING]
    if defaulted:
        rec = cls(**{f.name: values[f.name] for f in fields if f.default is dataclasses.MISSING})
        assert all(getattr(rec, f.name) == f.default for f in defaulted)
    with pytest.raises(TypeError):
        cls(**values, unknown_field=1)  # a misspelt field is refused, as by the dataclass's own
