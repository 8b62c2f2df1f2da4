"""The seed-001 case files (demos/pseudo2d) hold Table 1-3 of the paper, and the study files load."""

from pathlib import Path

import pytest

from febed.case import load_case
from febed.study import load_study

DEMO = Path(__file__).parents[2] / "demos" / "pseudo2d"

# seed 001 Table 3: bed mass (kg), U_f (m/s), mu_p, mu_w, mesh
TABLE3 = {
    "C1": (0.075, 1.20, 0.2, 0.2, "coarse"),
    "C2": (0.075, 1.20, 0.2, 0.2, "intermediate"),
    "C3": (0.075, 1.20, 0.2, 0.2, "fine"),
    "C4": (0.075, 1.20, 0.1, 0.1, "intermediate"),
    "C5": (0.075, 1.20, 0.1, 0.1, "intermediate"),
    "C6": (0.075, 1.71, 0.1, 0.1, "intermediate"),
    "C7": (0.125, 1.54, 0.1, 0.1, "intermediate"),
}


@pytest.mark.parametrize("name", TABLE3)
def test_case_matches_table3(name):
    c = load_case(DEMO / f"{name}.toml")
    mass, uf, mu_p, mu_w, level = TABLE3[name]
    assert (c.particles.bed_mass, c.boundary["inlet"].velocity) == (mass, uf)
    assert (c.contact.friction_pp, c.contact.friction_pw, c.mesh.level) == (mu_p, mu_w, level)
    # Table 1 and sec 3.2
    assert (c.particles.diameter, c.particles.density, c.gas.density, c.gas.viscosity) == (1e-3, 2500.0, 1.165, 2e-5)
    assert c.contact.restitution_pp == c.contact.restitution_pw == 0.97
    assert c.gas.les == "smagorinsky" and c.boundary["inlet"].cross_section_tags == ["bottom_wall"]
    assert c.mesh.builtin == "pseudo2d" and c.particles.bed_file == f"pseudo2d-{round(mass * 1000)}g.npz"


def test_c1_slip_front_back_is_c1_with_slipping_front_and_back_walls():
    c, v = load_case(DEMO / "C1.toml"), load_case(DEMO / "C1-slip-front-back.toml")
    assert v.boundary["walls"].slip and v.boundary["walls"].slip_normals == ["y"]
    assert not c.boundary["walls"].slip and c.boundary["walls"].slip_normals == []
    for sec in ("particles", "contact", "mesh", "gas", "coupling"):
        assert getattr(v, sec).as_dict() == getattr(c, sec).as_dict(), sec


def test_c1_partial_slip_front_back_is_the_slip_variant_with_a_slip_length():
    v, p = load_case(DEMO / "C1-slip-front-back.toml"), load_case(DEMO / "C1-partial-slip-front-back.toml")
    assert v.boundary["walls"].slip_length is None and p.boundary["walls"].slip_length == 1e-3
    assert p.boundary["walls"].slip and p.boundary["walls"].slip_normals == ["y"]
    members = {m.name: m for m in load_study(DEMO / "study-walls.toml").members}
    assert "gas.boundary.walls.slip_length=0.001" in members["C1-partial-slip-front-back"].overrides
    for sec in ("particles", "contact", "mesh", "coupling"):
        assert getattr(v, sec).as_dict() == getattr(p, sec).as_dict(), sec


def test_c1_partial_slip_edges_lets_every_wall_slip_and_the_inlet_take_the_patch_edges():
    p, e = load_case(DEMO / "C1-partial-slip-front-back.toml"), load_case(DEMO / "C1-partial-slip-edges.toml")
    assert e.boundary["walls"].slip and e.boundary["walls"].slip_normals == ["x", "y"]
    assert e.boundary["walls"].slip_length == 1e-3 and e.boundary["inlet"].wins_over == ["bottom_wall"]
    assert p.boundary["inlet"].wins_over == []
    members = {m.name: m for m in load_study(DEMO / "study-walls.toml").members}
    assert 'gas.boundary.inlet.wins_over=["bottom_wall"]' in members["C1-partial-slip-edges"].overrides
    # the case keeps the projected pressure-gradient reaction its documented runs used, and so does the study
    assert p.coupling.pressure_gradient_reaction == "nodal" and e.coupling.pressure_gradient_reaction == "projected"
    assert "coupling.pressure_gradient_reaction=projected" in members["C1-partial-slip-edges"].overrides
    for sec in ("particles", "contact", "mesh"):
        assert getattr(p, sec).as_dict() == getattr(e, sec).as_dict(), sec
    other = {k: v for k, v in e.coupling.as_dict().items() if k != "pressure_gradient_reaction"}
    assert other == {k: v for k, v in p.coupling.as_dict().items() if k != "pressure_gradient_reaction"}


def test_c3_is_c2_on_the_fine_mesh_with_four_convective_substeps():
    """C3.toml, and C3 in the studies, take four explicit sub-steps per gas step; C1 and C2 one."""
    c2, c3 = load_case(DEMO / "C2.toml"), load_case(DEMO / "C3.toml")
    assert (c2.gas.convection_substeps, c3.gas.convection_substeps) == (1, 4)
    assert load_case(DEMO / "C1.toml").gas.convection_substeps == 1
    g2, g3 = c2.gas.as_dict(), c3.gas.as_dict()
    assert {k: v for k, v in g3.items() if k != "convection_substeps"} == {
        k: v for k, v in g2.items() if k != "convection_substeps"
    }
    for sec in ("particles", "contact", "coupling"):
        assert getattr(c2, sec).as_dict() == getattr(c3, sec).as_dict(), sec
    t3 = {m.name: m for m in load_study(DEMO / "study-table3.toml").members}
    assert "gas.convection_substeps=4" in t3["C3"].overrides
    assert not any("convection_substeps" in o for o in t3["C2"].overrides)
    assert "gas.convection_substeps = 4" in load_study(DEMO / "study-mesh.toml").common


def test_studies_load():
    sizes = {"mesh": 3, "friction-wall": 4, "friction-particle": 4, "table3": 13, "walls": 9}
    for name, n in sizes.items():
        s = load_study(DEMO / f"study-{name}.toml")
        assert len(s.members) == n
    t3 = {m.name: m for m in load_study(DEMO / "study-table3.toml").members}
    assert "gas.boundary.inlet.velocity=1.71" in t3["C6"].overrides
    assert "particles.bed_mass=0.125" in t3["C7"].overrides
    assert "gas.boundary.inlet.ramp_time=1.0" in t3["C7"].overrides  # as C7.toml


def test_c7_ramps_its_inlet_over_a_second_with_the_outlet_open():
    """Ramped over base.toml's 0.05 s, C7's packed bed rises to the outlet as a slug; over 1 s it does not.

    Every case keeps the outlet open to the particles; the 75 g cases keep the short ramp.
    """
    c7, c2 = load_case(DEMO / "C7.toml"), load_case(DEMO / "C2.toml")
    assert c7.boundary["inlet"].ramp_time == 1.0 and c2.boundary["inlet"].ramp_time == 0.05
    assert c7.boundary["outlet"].particles is True and c2.boundary["outlet"].particles is True
