"""Case files: defaults, round trip, overrides, extends, and clear messages for bad input."""

import math

import pytest

from febed.case import CaseError, dumps_toml, load_case, parse_override
from febed.schema import BOUNDARY, SCHEMA

BASE = """
[run]
mode = "cfd-dem"
end_time = 0.5
[mesh]
builtin = "wang2d"
[gas]
density = 1.28
viscosity = 1.7e-5
[gas.boundary.inlet]
type = "inlet"
velocity = 0.9
[gas.boundary.outlet]
type = "outlet"
[gas.boundary.walls]
type = "wall"
[particles]
diameter = 1.5e-3
density = 1150.0
count = 4080
"""


def write(tmp_path, text, name="case.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def problems(tmp_path, text, overrides=()):
    with pytest.raises(CaseError) as e:
        load_case(write(tmp_path, text), list(overrides))
    return e.value.problems


def test_defaults_filled(tmp_path):
    case = load_case(write(tmp_path, BASE))
    assert case.gas.density == 1.28
    assert case.contact.stiffness == SCHEMA["contact"]["stiffness"].default
    assert case.coupling.filter_passes == 1
    assert case.boundary["inlet"].velocity == 0.9
    assert case.boundary["walls"].slip is False
    assert case.name == "case"
    assert case.output_dir().name == "case"


def test_every_declared_parameter_has_unit_help_and_valid_default():
    for sec, params in [*SCHEMA.items(), ("gas.boundary", BOUNDARY)]:
        for key, par in params.items():
            assert par.help and par.unit is not None, f"{sec}.{key}"
            if par.default is not None:
                value, err = par.check(par.default)
                assert err is None, f"default of {sec}.{key} fails its own check: {err}"


def test_round_trip(tmp_path):
    case = load_case(write(tmp_path, BASE), ["contact.friction_pp=0.1"])
    again = load_case(write(tmp_path, case.to_toml(), "resolved.toml"))
    assert again.to_dict() == case.to_dict()
    assert math.isinf(again.output.checkpoint_interval)


def test_overrides_and_types(tmp_path):
    case = load_case(write(tmp_path, BASE), ["gas.density=1.165", "mesh.builtin=pseudo2d", "particles.count=10"])
    assert case.gas.density == 1.165 and case.mesh.builtin == "pseudo2d" and case.particles.count == 10
    assert isinstance(load_case(write(tmp_path, BASE), ["gas.density=2"]).gas.density, float)
    assert parse_override("run.name=my run") == {"run": {"name": "my run"}}


def test_extends(tmp_path):
    write(tmp_path, BASE, "base.toml")
    child = write(tmp_path, 'extends = "base.toml"\n[gas.boundary.inlet]\nvelocity = 1.9\n', "child.toml")
    case = load_case(child)
    assert case.boundary["inlet"].velocity == 1.9
    assert case.boundary["inlet"].type == "inlet"  # kept from the base
    assert case.particles.count == 4080
    assert case.name == "child"


def test_dumps_toml_escapes():
    assert dumps_toml({"run": {"name": 'a "b"'}}) == '[run]\nname = "a \\"b\\""\n\n'


# Each bad input and (a fragment of) the message it must give.
BAD = [
    ("[gas]\ndensty = 1.2\n", "unknown key 'densty': did you mean 'density'?"),
    ("[gaz]\ndensity = 1.2\n", "unknown section [gaz]: did you mean 'gas'?"),
    ('[gas]\ndensity = "heavy"\n', "[gas] density = 'heavy': expected a number > 0"),
    ("[gas]\ndensity = -1.0\n", "[gas] density = -1.0: expected a number > 0"),
    ("[particles]\ncount = 2.5\n", "[particles] count = 2.5: expected an integer >= 0"),
    ('[contact]\nmodel = "hertz"\n', "[contact] model = 'hertz': expected one of 'linear', 'linear-history'"),
    ("[contact]\nrestitution_pp = 1.5\n", "restitution_pp = 1.5: expected a number > 0 and <= 1"),
    ("[contact]\nrotation = 1\n", "unknown key 'rotation'"),
    ("[particles]\nrotation = 1\n", "[particles] rotation = 1: expected true or false"),
    ("[particles]\nregion = [0, 0, 1]\n", "region = [0, 0, 1]: expected a list of 6 numbers"),
    ("[particles]\nregion = [0, 0, 0, 1, -1, 1]\n", "needs xmin <= xmax"),
    ('[mesh]\nfile = "nowhere.msh"\nbuiltin = ""\n', "mesh file not found"),
    ('[mesh]\nbuiltin = "pseudo3d"\n', "[mesh] builtin = 'pseudo3d': expected one of"),
    ("[gas.boundary.inlet2]\ntype = 'inlet'\n", "type = 'inlet' needs velocity"),
    ("[gas.boundary.inlet]\ntype = 'intake'\n", "[gas.boundary.inlet] type = 'intake': expected one of 'inlet'"),
    ("[gas.boundary.inlet]\nvelocty = 1.0\n", "unknown key 'velocty': did you mean 'velocity'?"),
    ("[particles]\ncount = 10\nbed_mass = 0.1\n", "give count or bed_mass, not both"),
    ("density = 1.2\n", "'density' at the top level"),
    ("[run]\nend_time = 0\n", "[run] end_time = 0: expected a number > 0"),
    ("[output]\nfield_interval = nan\n", "field_interval = nan"),
]


@pytest.mark.parametrize("extra,message", BAD)
def test_bad_input_gives_clear_message(tmp_path, extra, message):
    # A valid base case, extended by a file that breaks one thing.
    write(tmp_path, BASE, "base.toml")
    got = problems(tmp_path, 'extends = "base.toml"\n' + extra)
    assert any(message in p for p in got), got


def test_all_problems_reported_together(tmp_path):
    got = problems(tmp_path, BASE, ["gas.densty=1", "particles.diameter=-1", "contact.model=x"])
    assert len(got) == 3


def test_bad_override_syntax(tmp_path):
    assert "expected section.key=value" in problems(tmp_path, BASE, ["gas.density"])[0]
    assert "must be section.key" in problems(tmp_path, BASE, ["density=1"])[0]


def test_not_toml_and_missing_file(tmp_path):
    assert "not valid TOML" in problems(tmp_path, "[gas\n")[0]
    with pytest.raises(CaseError, match="case file not found"):
        load_case(tmp_path / "absent.toml")
    write(tmp_path, 'extends = "loop.toml"\n', "loop.toml")
    with pytest.raises(CaseError, match="loops back"):
        load_case(tmp_path / "loop.toml")


def test_mode_needs_boundaries(tmp_path):
    text = '[run]\nmode = "gas"\n[mesh]\nbuiltin = "wang2d"\n'
    assert "needs gas boundary conditions" in problems(tmp_path, text)[0]
    assert load_case(write(tmp_path, text.replace('"gas"', '"dem"'))).run.mode == "dem"


def test_slip_normals_axes_and_their_wall(tmp_path):
    """slip_normals: axes from x, y, z (schema choices), and only on a slipping wall (cross-check)."""
    got = problems(tmp_path, BASE, ['gas.boundary.walls.slip_normals=["y", "w"]'])
    assert got == ["[gas.boundary.walls] slip_normals = ['y', 'w']: expected a list of strings from 'x', 'y', 'z'"]
    got = problems(tmp_path, BASE, ['gas.boundary.walls.slip_normals=["y"]'])
    assert got == ["[gas.boundary.walls] slip_normals needs type = 'wall' and slip = true"]
    case = load_case(write(tmp_path, BASE), ["gas.boundary.walls.slip=true", 'gas.boundary.walls.slip_normals=["x"]'])
    assert case.boundary["walls"].slip_normals == ["x"]


def test_slip_length_positive_and_on_a_slipping_wall(tmp_path):
    """slip_length: > 0 m (schema bound), and only on a slipping wall (cross-check)."""
    got = problems(tmp_path, BASE, ["gas.boundary.walls.slip=true", "gas.boundary.walls.slip_length=0"])
    assert len(got) == 1 and got[0].startswith("[gas.boundary.walls] slip_length = 0"), got
    got = problems(tmp_path, BASE, ["gas.boundary.walls.slip_length=1e-3"])
    assert got == ["[gas.boundary.walls] slip_length needs type = 'wall' and slip = true"]
    case = load_case(write(tmp_path, BASE), ["gas.boundary.walls.slip=true", "gas.boundary.walls.slip_length=1e-3"])
    assert case.boundary["walls"].slip_length == 1e-3


def test_wall_law_choices_and_its_wall(tmp_path):
    """wall_law: 'brinkman' (default) or 'no_slip', and 'no_slip' only on a wall without slip (cross-check)."""
    got = problems(tmp_path, BASE, ['gas.boundary.walls.wall_law="log"'])
    assert got == ["[gas.boundary.walls] wall_law = 'log': expected one of 'brinkman', 'no_slip'"]
    got = problems(tmp_path, BASE, ['gas.boundary.walls.wall_law="no_slip"', "gas.boundary.walls.slip=true"])
    assert got == ["[gas.boundary.walls] wall_law is for a wall without slip (type = 'wall', slip = false)"]
    case = load_case(write(tmp_path, BASE), ['gas.boundary.walls.wall_law="no_slip"'])
    assert case.boundary["walls"].wall_law == "no_slip"
    assert load_case(write(tmp_path, BASE)).boundary["walls"].wall_law == "brinkman"


def test_wins_over_on_an_inlet_over_a_no_slip_wall(tmp_path):
    """wins_over: only an inlet's key, and the walls it names must be no-slip (cross-checks)."""
    got = problems(tmp_path, BASE, ['gas.boundary.walls.wins_over=["inlet"]'])
    assert got == ["[gas.boundary.walls] wins_over is for an inlet (type = 'inlet')"]
    got = problems(tmp_path, BASE, ['gas.boundary.inlet.wins_over=["walls"]', "gas.boundary.walls.slip=true"])
    assert got == [
        "[gas.boundary.inlet] wins_over = 'walls': [gas.boundary.walls] must be a no-slip wall "
        "(type = 'wall', slip = false)"
    ]
    got = problems(tmp_path, BASE, ['gas.boundary.inlet.wins_over=["walls"]'])
    assert got == [
        "[gas.boundary.inlet] wins_over = 'walls': [gas.boundary.walls] must set wall_law = 'no_slip' "
        "(an inlet already shares its nodes with a wall of the porous wall law by facet)"
    ]
    case = load_case(
        write(tmp_path, BASE), ['gas.boundary.inlet.wins_over=["walls"]', 'gas.boundary.walls.wall_law="no_slip"']
    )
    assert case.boundary["inlet"].wins_over == ["walls"]
