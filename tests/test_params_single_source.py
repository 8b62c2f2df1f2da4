"""The Python API's parameter objects take their defaults and ranges from `febed/schema.py`.

`DEMParams`, `VANSParameters` and `OneWayCase` declare each case parameter with `schema_field("section.key")`:
its default must be the schema's, and `validate()` must refuse what the case validation refuses, naming the
field and the key. Every other field must be listed, with the reason, in the class's `NOT_IN_CASE`.
"""

from __future__ import annotations

import dataclasses
import math

import pytest

from febed.case import load_case
from febed.coarse.oneway import OneWay, OneWayCase, case_settings
from febed.dem.solver import DEM, DEMParams
from febed.gas.vans import VANSParameters
from febed.schema import SCHEMA, param, schema_key

CLASSES = (DEMParams, VANSParameters, OneWayCase)


def _make(cls, **kw):
    """An instance with `kw` set; OneWayCase checks itself when made, the others in `validate()`."""
    obj = cls(**kw)
    obj.validate()
    return obj


def _mapped(cls) -> list[tuple[str, str]]:
    return [(f.name, schema_key(f)) for f in dataclasses.fields(cls) if schema_key(f) is not None]


MAPPED = [(cls, name, key) for cls in CLASSES for name, key in _mapped(cls)]
IDS = [f"{cls.__name__}.{name}" for cls, name, _ in MAPPED]


def _refused(par) -> list:
    """Values of the declared type that the schema refuses (each checked to be refused by the schema itself)."""
    bad = []
    if par.type in (float, int):
        if par.lo is not None:
            bad.append(par.lo if par.lo_open else par.lo - 1)
        if par.hi is not None:
            bad.append(par.hi + 1)
        if par.type is float and par.finite:
            bad.append(math.nan)
        bad.append("1")  # a string where a number is declared
    elif par.type is bool:
        bad.append("yes")
    elif par.type is str and par.choices is not None:
        bad.append("no-such-choice")
    for value in bad:
        assert par.check(value)[1] is not None, f"the schema accepts {value!r}: not a refused value"
    return bad


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.__name__)
def test_every_field_is_a_case_key_or_listed_as_not_one(cls):
    """A new field must be made with `schema_field` or be listed, with a reason, in NOT_IN_CASE."""
    names = {f.name for f in dataclasses.fields(cls)}
    mapped = {name for name, _ in _mapped(cls)}
    internal = set(cls.NOT_IN_CASE)
    assert not (names - mapped - internal), f"{cls.__name__}: fields neither schema_field nor in NOT_IN_CASE"
    assert not (internal - names), f"{cls.__name__}.NOT_IN_CASE names fields that do not exist"
    assert not (internal & mapped), f"{cls.__name__}: fields both schema_field and in NOT_IN_CASE"
    assert all(reason for reason in cls.NOT_IN_CASE.values())


@pytest.mark.parametrize(("cls", "name", "key"), MAPPED, ids=IDS)
def test_default_is_the_schema_default(cls, name, key):
    section, _, k = key.partition(".")
    assert k in SCHEMA[section], f"{cls.__name__}.{name}: {key} is not declared"
    assert getattr(cls(), name) == SCHEMA[section][k].default


@pytest.mark.parametrize(("cls", "name", "key"), MAPPED, ids=IDS)
def test_validate_refuses_what_the_schema_refuses(cls, name, key):
    bad = _refused(param(key))
    for value in bad:
        with pytest.raises(ValueError) as err:
            _make(cls, **{name: value})
        msg = str(err.value)
        assert f"{cls.__name__}.{name} = " in msg and key in msg and "expected" in msg, msg


@pytest.mark.parametrize(("cls", "name", "key"), MAPPED, ids=IDS)
def test_validate_accepts_the_schema_bounds(cls, name, key):
    par = param(key)
    for value in (par.lo if not par.lo_open else None, par.hi):
        if value is not None and par.type in (float, int):
            _make(cls, **{name: par.type(value)})


def test_the_case_name_reaches_the_api_object():
    """One name from case file to DEMParams: contact.stiffness -> DEMParams.stiffness, and so on."""
    case = load_case(
        data={
            "mesh": {"builtin": "box", "extent": [0.01, 0.01, 0.01]},
            "run": {"mode": "dem", "gravity": 3.0},
            "contact": {"stiffness": 1234.0, "stiffness_wall": 567.0, "skin": 0.3, "model": "linear"},
        }
    )
    p = DEM.from_case(case).params
    assert (p.stiffness, p.stiffness_wall, p.skin, p.contact_model, p.gravity) == (1234.0, 567.0, 0.3, "linear", 3.0)
    for name, key in _mapped(DEMParams):
        section, _, k = key.partition(".")
        assert getattr(p, name) == getattr(getattr(case, section), k), name


def test_one_way_settings_are_the_case_keys():
    case = load_case(
        data={
            "mesh": {"builtin": "box", "extent": [0.01, 0.01, 0.01]},
            "run": {"mode": "one-way", "end_time": 0.5},
            "prescribed_gas": {"drag_factor": 7.0, "integration": "explicit", "window": 1e-4},
            "coupling": {"drag": "stokes"},
        }
    )
    s = case_settings(case)
    for name, key in _mapped(OneWayCase):
        section, _, k = key.partition(".")
        assert getattr(s, name) == getattr(getattr(case, section), k), name


def test_one_way_driver_checks_its_arguments_as_the_case_keys():
    with pytest.raises(ValueError, match=r"integration = 'rk4' \(prescribed_gas.integration\): expected one of"):
        OneWay(None, None, "stokes", "rk4")
    with pytest.raises(ValueError, match=r"drag_factor = 0 \(prescribed_gas.drag_factor\): expected a number > 0"):
        OneWay(None, None, "stokes", drag_factor=0)


def test_cross_checks_remain():
    with pytest.raises(ValueError, match=r"dt_min \(0.1\) must not exceed dt_max"):
        VANSParameters(dt_min=0.1, dt_max=0.01).validate()
    with pytest.raises(ValueError, match="DEMParams.dim must be 2 or 3"):
        DEMParams(dim=4).validate()
    with pytest.raises(ValueError, match="DEMParams.sort_every must be an integer >= 1"):
        DEMParams(sort_every=0).validate()
