"""Post-processing on synthetic particle data whose fields are known exactly (febed.post)."""

import math

import numpy as np
import pytest

from febed.io.particles import vtp_bytes
from febed.post import Grid, TimeAverage, average_fields, bin_sums, list_snapshots, post_run, read_snapshot

L, D, H = 0.08, 0.015, 0.25  # the pseudo2d box (built-in), x, y (depth), z
DP = 1e-3
RHO_P, RHO_G, UF = 2500.0, 1.165, 1.2
VP = math.pi / 6 * DP**3
BINS = (4, 5)  # bins of 20 mm x 50 mm
HX, HZ = L / BINS[0], H / BINS[1]

CASE = f"""
[run]
end_time = 1.0
[mesh]
builtin = "pseudo2d"
level = "coarse"
[gas]
density = {RHO_G}
[gas.boundary.inlet]
type = "inlet"
velocity = {UF}
[particles]
diameter = {DP}
density = {RHO_P}
"""


def make_run(path, snapshots, missing=(), corrupt=(), case=CASE):
    """A fake run folder: case.resolved.toml + particles/*.vtp + particles.pvd (+ listed missing/corrupt files)."""
    (path / "particles").mkdir(parents=True)
    (path / "case.resolved.toml").write_text(case)
    rows = []
    for k, (t, pos, vel, *gid) in enumerate(snapshots):
        name = f"particles_{k:06d}.vtp"
        n = pos.shape[0]
        gid = np.asarray(gid[0] if gid else np.arange(n), dtype=np.int64)
        data = vtp_bytes(pos, {"velocity": vel, "diameter": np.full(n, DP), "gid": gid})
        if k in corrupt:
            data = data[: len(data) // 2]  # a half-written file
        if k not in missing:
            (path / "particles" / name).write_bytes(data)
        rows.append(f'<DataSet timestep="{t:.9g}" part="0" file="{name}"/>')
    (path / "particles" / "particles.pvd").write_text(
        '<?xml version="1.0"?>\n<VTKFile type="Collection"><Collection>\n'
        + "\n".join(rows)
        + "\n</Collection></VTKFile>"
    )
    return path


def lattice(m=(4, 3, 4), rows=3):
    """Particles in the lowest `rows` bin rows, m per bin and axis, placed symmetrically about bin centres.

    Returns positions (n, 3), the bin (i, j) of each particle and its offset index inside the bin.
    """
    pos, bins, sub = [], [], []
    for i in range(BINS[0]):
        for j in range(rows):
            for a in range(m[0]):
                for b in range(m[1]):
                    for c in range(m[2]):
                        x = (i + (a + 0.5) / m[0]) * HX
                        y = (b + 0.5) / m[1] * D
                        z = (j + (c + 0.5) / m[2]) * HZ
                        pos.append((x, y, z))
                        bins.append((i, j))
                        sub.append((a, b, c))
    return np.array(pos), np.array(bins), np.array(sub)


def bin_velocity(i, j):
    """A prescribed mean velocity per bin (m/s): a double loop, up in the centre, down at the walls."""
    xc = (i + 0.5) / BINS[0]
    return np.array([0.3 * (j - 1.0), 0.05 * i, math.cos(2 * math.pi * xc) * -0.8 + 0.1 * j])


def fluctuations(sub, delta):
    """Velocity fluctuations of magnitude^2 = 3 delta^2 whose mean over each bin's lattice is exactly zero."""
    a, b, c = sub.T  # lattice indices inside the bin: a and c take an even number of values
    sign = np.stack([(-1.0) ** a, (-1.0) ** (a + b), (-1.0) ** c], axis=1)  # each balanced over the bin
    return delta * sign


GRID = Grid(lo=(0.0, 0.0), hi=(L, H), n=BINS, axes=(0, 2), depth=D)


def test_uniform_bed_alpha_flux_agitation_exact():
    """alpha_p = N V_p / dV, flux = rho_p alpha U_bin, q^2 = 3 delta^2, to round-off (NGP)."""
    pos, bins, sub = lattice()
    delta = 0.07
    mean = np.array([bin_velocity(i, j) for i, j in bins])
    vel = mean + fluctuations(sub, delta)
    s = bin_sums(GRID, pos, vel, np.full(len(pos), DP), "ngp")
    acc = TimeAverage(GRID, RHO_P)
    acc.add(0.0, s)
    r = acc.result("cell")
    per_bin = 4 * 3 * 4
    alpha = per_bin * VP / (HX * HZ * D)
    assert np.allclose(r["alpha_p"][:, :3], alpha, rtol=1e-13, atol=0)
    assert np.all(r["alpha_p"][:, 3:] == 0.0)
    for i in range(BINS[0]):
        for j in range(3):
            assert np.allclose(r["mass_flux"][i, j], RHO_P * alpha * bin_velocity(i, j), rtol=1e-12, atol=1e-12)
            assert np.allclose(r["velocity"][i, j], bin_velocity(i, j), rtol=1e-12, atol=1e-13)
    assert np.allclose(r["q2"][:, :3], 3 * delta**2, rtol=1e-12, atol=0)
    assert np.all(r["q2"][:, 3:] == 0.0)


def test_cic_uniform_bed_and_volume_conservation():
    """CIC with folding: a bed uniform within bins stays exactly uniform, walls included; volume conserved."""
    pos, bins, sub = lattice(m=(2, 1, 2), rows=BINS[1])  # fills the box
    vel = np.tile([0.1, 0.0, -0.2], (len(pos), 1))
    s = bin_sums(GRID, pos, vel, np.full(len(pos), DP), "cic")
    alpha = 4 * VP / (HX * HZ * D)
    assert np.allclose(s.s0 / GRID.bin_volume, alpha, rtol=1e-13)
    # a random cloud: the deposited volume is the particles' volume whatever the positions
    rng = np.random.default_rng(1)
    p = rng.uniform([0, 0, 0], [L, D, H], size=(500, 3))
    d = rng.uniform(0.5e-3, 2e-3, 500)
    s = bin_sums(GRID, p, rng.normal(size=(500, 3)), d, "cic")
    assert abs(s.s0.sum() - (math.pi / 6 * d**3).sum()) <= 1e-14 * s.s0.sum()


def test_depth_average_independent_of_y_distribution():
    """The bin spans the whole depth: moving particles along y changes nothing (exactly)."""
    pos, _, sub = lattice()
    vel = fluctuations(sub, 0.1) + 0.5
    a = bin_sums(GRID, pos, vel, np.full(len(pos), DP))
    squeezed = pos.copy()
    squeezed[:, 1] = 0.1 * D + 0.2 * squeezed[:, 1]  # all in the back fifth of the bed
    b = bin_sums(GRID, squeezed, vel, np.full(len(pos), DP))
    for f in ("s0", "s1", "s2", "q"):
        assert np.array_equal(getattr(a, f), getattr(b, f))


def test_time_average_and_agitation_definitions():
    """Two snapshots with different beds: arithmetic means of alpha and flux; q^2 'cell' vs 'window'."""
    pos, bins, sub = lattice()
    n = len(pos)
    u1, u2 = np.array([0.0, 0.0, 0.4]), np.array([0.2, 0.0, -0.6])
    acc = TimeAverage(GRID, RHO_P)
    acc.add(0.0, bin_sums(GRID, pos, np.tile(u1, (n, 1)), np.full(n, DP)))
    half = sub[:, 2] < 2  # the second snapshot keeps the lower half of each bin's particles only
    acc.add(0.1, bin_sums(GRID, pos[half], np.tile(u2, (half.sum(), 1)), np.full(half.sum(), DP)))
    alpha1 = 48 * VP / GRID.bin_volume
    cell, window = acc.result("cell"), acc.result("window")
    assert np.allclose(cell["alpha_p"][:, :3], 0.75 * alpha1, rtol=1e-13)
    assert np.allclose(cell["mass_flux"][:, :3], RHO_P * alpha1 * (u1 + 0.5 * u2) / 2, rtol=1e-12, atol=1e-12)
    assert np.allclose(cell["q2"], 0.0, atol=1e-15)  # uniform velocity in each snapshot
    # window: volume-weighted mean U = (2 u1 + u2)/3, variance about it
    U = (2 * u1 + u2) / 3
    q2 = (2 * np.sum((u1 - U) ** 2) + np.sum((u2 - U) ** 2)) / 3
    assert np.allclose(cell["velocity"][:, :3], U, rtol=1e-12, atol=1e-14)
    assert np.allclose(window["q2"][:, :3], q2, rtol=1e-10)


def test_bubble_frequency_fraction_and_bed_agitation_exact():
    """A dense bed (α_p = 0.5 in rows 0-2) with one bin of row 1 emptied per snapshot, in turn across the width."""
    pos, bins, sub = lattice()
    d = (6.0 / math.pi * 0.5 * GRID.bin_volume / 48) ** (1 / 3)  # 48 particles per bin: α_p = 0.5
    delta = 0.05
    acc = TimeAverage(GRID, RHO_P)
    for k in range(4):
        keep = ~((bins[:, 0] == k) & (bins[:, 1] == 1))
        vel = np.where((bins[:, 1] == 0)[:, None], fluctuations(sub, delta), 0.0)  # agitation in row 0 only
        acc.add(0.1 * k, bin_sums(GRID, pos[keep], vel[keep], np.full(keep.sum(), d)))
    r = acc.result()
    assert np.allclose(r["alpha_p"][:, 0], 0.5, rtol=1e-13)
    freq = r["bubble_frequency"]
    assert np.array_equal(freq[:, 0], np.zeros(4)) and np.array_equal(freq[:, 2], np.zeros(4))
    assert np.array_equal(freq[:, 1], np.full(4, 0.25))  # each bin of row 1 void in one snapshot of four
    assert np.array_equal(freq[:, 3:], np.ones((4, 2)))  # above the bed: always void
    from febed.post.fields import AveragedFields

    avg = AveragedFields(None, GRID, (0.0, 0.3), acc.times, "ngp", "cell", r["alpha_p"], r["mass_flux"],
                         r["velocity"], r["q2"], 0.0, bubble_frequency=freq)  # fmt: skip
    # the bins below 0.8 x 0.15 m: rows 0 and 1 (centres 25 and 75 mm)
    assert avg.bubble_fraction(0.8 * 0.15) == 0.125
    assert math.isnan(avg.bubble_fraction(0.01))  # no bin centre below 10 mm
    # q_p² = 3 δ² in row 0 (α 0.5), 0 in rows 1 (α 0.375) and 2 (α 0.5): the solid-volume-weighted mean
    assert avg.bed_agitation(0.15) == pytest.approx(3 * delta**2 * 0.5 / (0.5 + 0.375 + 0.5), rel=1e-12)
    # the threshold decides: half-emptied bins (α_p 0.25) are bubble at 0.3, not at the default 0.15
    for alpha, expect in ((0.15, 0.0), (0.3, 1.0)):
        a = TimeAverage(GRID, RHO_P, bubble_alpha=alpha)
        half = sub[:, 2] < 2
        a.add(0.0, bin_sums(GRID, pos[half], np.zeros((half.sum(), 3)), np.full(half.sum(), d)))
        assert np.all(a.result()["bubble_frequency"][:, :3] == expect)
    with pytest.raises(ValueError, match="bubble_alpha"):
        TimeAverage(GRID, RHO_P, bubble_alpha=1.5)


def test_run_folder_window_rank_order_and_incomplete_files(tmp_path):
    """From files: window selection, snapshot order of the ranks irrelevant (bitwise), missing/half files skipped."""
    pos, bins, sub = lattice()
    n = len(pos)
    snaps = []
    for k in range(6):
        vel = np.array([bin_velocity(i, j) for i, j in bins]) * (1 + 0.1 * k) + fluctuations(sub, 0.01 * k)
        snaps.append((0.05 * k, pos, vel))
    a = make_run(tmp_path / "a", snaps)
    # the same particles gathered in another order (as from 2 ranks), plus a listed file not yet written and a
    # half-written one after the window
    perm = np.random.default_rng(3).permutation(n)
    b_snaps = [(t, p[perm], v[perm], perm) for t, p, v in snaps]
    b_snaps[1:1] = [(0.025, pos, snaps[0][2])]
    b = make_run(tmp_path / "b", b_snaps, missing={1})
    assert len(list_snapshots(b)) == 6
    fa = average_fields(a, window=(0.1, 0.2), bins=BINS)
    fb = average_fields(b, window=(0.1, 0.2), bins=BINS)
    assert fa.times == pytest.approx([0.1, 0.15, 0.2]) and fb.times == fa.times
    for name in ("alpha_p", "mass_flux", "velocity", "q2"):
        assert np.array_equal(getattr(fa, name), getattr(fb, name)), name
    # the average equals the mean of the three snapshots' exact fields
    alpha = 48 * VP / GRID.bin_volume
    for i in range(BINS[0]):
        for j in range(3):
            U = bin_velocity(i, j) * (1 + 0.1 * np.array([2, 3, 4])[:, None])
            assert np.allclose(fa.mass_flux[i, j], RHO_P * alpha * U.mean(axis=0), rtol=1e-12, atol=1e-12)
    assert np.allclose(fa.q2[:, :3], 3 * (0.01**2 * (4 + 9 + 16)) / 3, rtol=1e-10)
    # a half-written file is skipped with a warning, not an error
    c = make_run(tmp_path / "c", snaps, corrupt={5})
    assert read_snapshot(c / "particles" / "particles_000005.vtp") is None
    fc = average_fields(c, window=(0.1, 0.25), bins=BINS)
    assert fc.times == pytest.approx([0.1, 0.15, 0.2])


def test_profile_interpolates_between_rows(tmp_path):
    """A flux linear in z: the profile at any height is exact; at z/H = 0.092 too."""
    pos, bins, sub = lattice(m=(2, 1, 2), rows=BINS[1])
    n = len(pos)
    vel = np.zeros((n, 3))
    zc = (bins[:, 1] + 0.5) * HZ
    vel[:, 2] = 0.3 + 2.0 * zc  # the same in each bin: linear across bin centres
    run = make_run(tmp_path / "r", [(0.0, pos, vel)])
    f = average_fields(run, bins=BINS)
    alpha = 4 * VP / GRID.bin_volume
    for z in (HZ / 2, 0.1, 0.17, H - HZ / 2):
        x, prof = f.profile("mass_flux_z", z)
        assert np.allclose(prof, RHO_P * alpha * (0.3 + 2.0 * z), rtol=1e-12)
    # below the first row of centres (z/H = 0.092 here) and above the last: the nearest row
    assert np.allclose(f.profile("mass_flux_z", 0.092 * H)[1], RHO_P * alpha * (0.3 + HZ), rtol=1e-12)
    assert np.allclose(f.profile("mass_flux_z", H)[1], RHO_P * alpha * (0.3 + 2 * H - HZ), rtol=1e-12)
    with pytest.raises(ValueError, match="height"):
        f.profile("mass_flux_z", 2 * H)
    with pytest.raises(ValueError, match="quantity"):
        f.profile("flux", 0.1)


def test_post_run_writes_tables_and_figures(tmp_path):
    """`post_run` on a fake run with probes: files, the summary numbers and the normalised profile."""
    pos, bins, sub = lattice()
    vel = np.array([bin_velocity(i, j) for i, j in bins])
    run = make_run(tmp_path / "r", [(0.1 * k, pos, vel) for k in range(4)])
    w_a = (RHO_P - RHO_G) * 9.81 * len(pos) * VP / (L * D)
    t = np.linspace(0, 0.3, 31)
    dp = w_a * (1 + 0.1 * np.sin(40 * t))
    with open(run / "probes.csv", "w") as fh:
        fh.write("time,particles,bed_height,dp_bed\n")
        for tt, p in zip(t, dp, strict=True):
            fh.write(f"{tt!r},{len(pos)},0.15,{p!r}\n")
    res = post_run(run, window=(0.1, 0.3), bins=BINS)
    names = {f.name for f in res.files}
    assert {"fields.csv", "fields.npz", "profile_zH0.092.csv", "summary.csv", "timeseries.csv"} <= names
    assert {"fields.png", "profile_zH0.092.png", "timeseries.png", "snapshots.png"} <= names
    sel = (t >= 0.1 - 1e-12) & (t <= 0.3 + 1e-12)
    assert res.summary.dp_mean == pytest.approx(dp[sel].mean(), rel=1e-12)
    assert res.summary.weight_per_area == pytest.approx(w_a, rel=1e-12)
    assert res.values["bed_height_over_H"] == pytest.approx(0.15 / H, rel=1e-12)
    # bed-averaged circulation: the rows below the bed height 0.15 m (bin centres 25, 75, 125 mm); the central
    # third holds bins 1, 2 of 4 (centres x/L 0.375, 0.625), the outer 15 % bins 0, 3 (0.125, 0.875)
    alpha_b = 48 * VP / GRID.bin_volume
    flux = {i: np.mean([RHO_P * alpha_b * bin_velocity(i, j)[2] for j in range(3)]) / (RHO_G * UF) for i in range(4)}
    assert res.values["bed_flux_centre/rhoUf"] == pytest.approx((flux[1] + flux[2]) / 2, rel=1e-10)
    assert res.values["bed_flux_walls/rhoUf"] == pytest.approx((flux[0] + flux[3]) / 2, rel=1e-10)
    assert res.values["bed_flux_centre/rhoUf"] > 0 > res.values["bed_flux_walls/rhoUf"]  # the prescribed loops
    c, w = res.fields.circulation(0.1, centre=0.1, wall=0.13)  # two rows; no bin centre within 0.05 of x/L = 0.5
    assert math.isnan(c) and w == pytest.approx(RHO_P * alpha_b * np.mean([bin_velocity(i, j)[2] for i in (0, 3)
                                                                           for j in range(2)]), rel=1e-10)  # fmt: skip
    # this synthetic bed is dilute (α_p 0.0017): every bin is void at the default threshold 0.15
    assert res.values["bubble_fraction"] == 1.0
    sparse = post_run(run, window=(0.1, 0.3), bins=BINS, figures=False, out=tmp_path / "p2", bubble_alpha=1e-3)
    assert sparse.values["bubble_fraction"] == 0.0  # rows 0-2 hold α_p 0.0017 > 1e-3 in every snapshot
    assert abs(sparse.values["q2_bed/Uf2"]) < 1e-25  # one velocity per bin: no agitation (round-off)
    prof = np.loadtxt(run / "post" / "profile_zH0.092.csv", delimiter=",", skiprows=1)
    alpha = 48 * VP / GRID.bin_volume  # z/H = 0.092 lies in the first bin row (below its centre)
    expect = [RHO_P * alpha * bin_velocity(i, 0)[2] / (RHO_G * UF) for i in range(BINS[0])]
    assert np.allclose(prof[:, 4], expect, rtol=1e-8)


def test_bad_arguments(tmp_path):
    pos, _, _ = lattice()
    run = make_run(tmp_path / "r", [(0.0, pos, np.zeros_like(pos))])
    with pytest.raises(ValueError, match="kernel"):
        average_fields(run, kernel="sph")
    with pytest.raises(ValueError, match="bins"):
        average_fields(run, bins=(0, 3))
    with pytest.raises(ValueError, match="window"):
        average_fields(run, window=(2.0, 3.0))
    with pytest.raises(ValueError, match="agitation"):
        average_fields(run, agitation="favre")
    with pytest.raises(ValueError, match="run_dir"):
        post_run(tmp_path)


def test_probe_series_of_a_running_run(tmp_path):
    """A row being written (no newline, cut in a cell) is dropped; complete rows are kept."""
    from febed.post import read_series

    (tmp_path / "probes.csv").write_text("time,dp_bed,bed_height\n0.0,1.0,0.1\n0.001,2.0,,\n0.002,3.0,0.3\n0.003,4.")
    s = read_series(tmp_path)
    assert s["time"].tolist() == [0.0, 0.002] and s["dp_bed"].tolist() == [1.0, 3.0]
    (tmp_path / "probes.csv").write_text("time,dp_bed\n")
    assert read_series(tmp_path) == {}


def test_command_line(tmp_path, capsys):
    """`python -m febed.post RUN_DIR ...` (= `febed post`): tables written, errors as messages with status 2."""
    from febed.post.cli import main

    pos, bins, _ = lattice()
    vel = np.array([bin_velocity(i, j) for i, j in bins])
    run = make_run(tmp_path / "r", [(0.1 * k, pos, vel) for k in range(3)])
    assert main([str(run), "--bins", "4", "5", "--window", "0", "0.2", "--no-figures", "--kernel", "cic"]) == 0
    assert "3 particle snapshots" in capsys.readouterr().out
    data = np.genfromtxt(run / "post" / "fields.csv", delimiter=",", names=True)
    assert data.size == 20 and np.isclose(data["alpha_p"].sum() * GRID.bin_volume, len(pos) * VP, rtol=1e-12)
    assert not list((run / "post").glob("*.png"))
    assert main([str(run), "--window", "5", "6"]) == 2
    assert "window" in capsys.readouterr().err


def test_scg_run_uses_the_coarse_grain_density(tmp_path):
    from febed.post.rundata import run_info

    make_run(tmp_path / "r", [])
    assert run_info(tmp_path / "r").rho_p == RHO_P
    text = (tmp_path / "r" / "case.resolved.toml").read_text()
    (tmp_path / "r" / "case.resolved.toml").write_text(text + '[coarse_grain]\nmodel = "scg"\nratio = 4.0\n')
    assert run_info(tmp_path / "r").rho_p == pytest.approx(RHO_P / 16, rel=1e-14)  # ρ d²/(4 d)², seed 003 eq 7


@pytest.mark.parametrize("contact", ["stiffness = 800.0", "stiffness = 5.0\nstiffness_wall = 800.0"])
def test_bottom_support_is_the_elastic_force_of_the_overlaps(tmp_path, contact):
    """Particles pressed into the bottom plane by known overlaps: k_n,w Σδ over the buoyant weight, averaged."""
    from febed.post.rundata import run_info
    from febed.post.support import bottom_support

    pos, _, _ = lattice()
    n = len(pos)
    snaps = []
    for k, deltas in enumerate(([1e-5, 3e-5, 0.0], [2e-5, 0.0, 0.0])):
        p = pos.copy()
        p[:3, 2] = 0.5 * DP - np.asarray(deltas)  # the first three rest on the bottom (0 overlap: touching)
        snaps.append((0.1 * k, p, np.zeros_like(p)))
    run = make_run(tmp_path / "r", snaps, case=CASE + f"[contact]\n{contact}\n")
    weight = (RHO_P - RHO_G) * 9.81 * n * VP
    expect = np.mean([800.0 * 4e-5 / weight, 800.0 * 2e-5 / weight])
    assert bottom_support(run, run_info(run), (0.0, 0.1)) == pytest.approx(expect, rel=1e-9)
    assert post_run(run, bins=BINS, figures=False, window=(0.0, 0.1)).values["bottom_support/W"] == pytest.approx(
        expect, rel=1e-9
    )
    tm = make_run(tmp_path / "tm", snaps, case=CASE + f'[contact]\n{contact}\n[coarse_grain]\nmodel = "tm"\n')
    assert math.isnan(bottom_support(tm, run_info(tm)))  # parcels' stiffness: not covered


def test_compare_runs_made_separately(tmp_path, capsys):
    """`febed compare`: each run's row holds what `febed post` finds over the same window, whatever its mesh."""
    from febed.post import collect
    from febed.post.cli import main

    pos, bins, _ = lattice()
    vel = np.array([bin_velocity(i, j) for i, j in bins])
    w_a = (RHO_P - RHO_G) * 9.81 * len(pos) * VP / (L * D)
    runs = {}
    for level, gain in (("coarse", 1.0), ("intermediate", 1.1)):
        run = make_run(tmp_path / level, [(0.1 * k, pos, gain * vel) for k in range(5)],
                       case=CASE.replace('level = "coarse"', f'level = "{level}"'))  # fmt: skip
        t = np.linspace(0, 0.4, 41)
        with open(run / "probes.csv", "w") as fh:
            fh.write("time,particles,bed_height,dp_bed\n")
            for tt in t:
                fh.write(f"{tt!r},{len(pos)},0.15,{gain * w_a * (1 + 0.1 * np.sin(40 * tt))!r}\n")
        runs[level] = run
    windows = [(0.1, 0.3), (0.2, 0.4)]
    table = collect.compare_runs(list(runs.values()), ["C1", "C2"], windows, out=tmp_path / "cmp")
    assert [r["run"] for r in table.rows] == ["C1", "C2"]
    for r, run, w in zip(table.rows, runs.values(), windows, strict=True):
        ref = post_run(run, window=w, figures=False, out=tmp_path / f"post-{run.name}").values
        assert (r["window_t0"], r["window_t1"]) == w and r["snapshots"] == ref["snapshots"] == 3
        for key in ("dp_bed_over_weight", "bed_height_mean", "bed_flux_centre/rhoUf", "bed_flux_walls/rhoUf",
                    "bubble_fraction", "q2_bed/Uf2"):  # fmt: skip
            assert r[key] == pytest.approx(ref[key], rel=1e-12, abs=1e-30), key
        # this lattice leaves z/H = 0.16's bin row empty on these meshes: NaN in both (exact values: the next test)
        np.testing.assert_allclose(r["depth_spread/Uf"], ref["depth_zH0.16_spread_all/Uf"], rtol=1e-12)
        np.testing.assert_allclose(r["depth_asymmetry"], ref["depth_zH0.16_front_back_asymmetry"], rtol=1e-12)
    # the profiles in long form: each run on its own mesh's bins (17 and 35 across the width), as `febed post`'s
    prof = np.genfromtxt(tmp_path / "cmp" / "profiles_flux.csv", delimiter=",", names=True, dtype=None, encoding=None)
    for label, run, n in (("C1", "coarse", 17), ("C2", "intermediate", 35)):
        ref = np.loadtxt(tmp_path / f"post-{run}" / "profile_zH0.092.csv", delimiter=",", skiprows=1)
        mine = prof[prof["run"] == label]
        assert len(mine) == n and np.allclose(mine["fluxrhoUf"], ref[:, 4], rtol=1e-5, atol=1e-9)
    assert {f.name for f in table.figures} == {"profiles_flux.png", "comparison_runs.png"}
    # the command line: one window for all runs, folder names as labels
    assert main(["compare", *map(str, runs.values()), "--window", "0.1", "0.4", "-o", str(tmp_path / "c2")]) == 0
    out = capsys.readouterr().out
    assert "coarse" in out and "intermediate" in out and "comparison.csv" in out
    # bad input: a message naming what is wrong, status 2
    for argv, what in (
        (["compare", str(runs["coarse"]), "--labels", "a", "b"], "2 label(s) for 1 run folder"),
        (["compare", *map(str, runs.values()), "--labels", "a", "a"], "labels must differ"),
        (["compare", *map(str, runs.values()), *["--window", "0", "1"] * 3], "3 window"),
        (["compare", str(runs["coarse"]), "--window", "0.3", "0.1"], "T0 < T1"),
        (["compare", str(tmp_path / "nowhere")], "does not exist"),
    ):
        assert main([*argv, "-o", str(tmp_path / "bad")]) == 2
        assert what in capsys.readouterr().err, argv


def test_depth_profile_solid_volume_weighted_per_band_exact(tmp_path):
    """Seed 001 Fig 11's profile across the depth: only the slab's particles, volume-weighted over time."""
    import dataclasses

    from febed.post.depth import DepthProfile
    from febed.post.rundata import run_info

    ys = [(k + 0.5) * D / 3 for k in range(3)]  # one particle per depth bin of 5 mm and per column below
    cols = {"centre": 0.04, "wall_left": 0.005, "wall_right": 0.075, "between": 0.02}  # x/L 0.5, .06, .94, .25
    pos, diam, kind = [], [], []
    for name, x in cols.items():
        for k, y in enumerate(ys):
            pos += [(x, y, 0.03), (x, y, 0.07)]  # in the slab z/H 0-0.2 (z/H = 0.16 is in row 0), and above it
            diam += [2 * DP if name == "between" else DP] * 2
            kind += [(name, k, True), (name, k, False)]
    pos, diam = np.array(pos), np.array(diam)

    def velocities(scale_centre):
        v = np.zeros_like(pos)
        for n, (name, k, inside) in enumerate(kind):
            if not inside:
                v[n, 2] = 100.0  # outside the slab: must not count
            elif name == "centre":
                v[n, 2] = scale_centre * 0.1 * (k + 1)
            elif name.startswith("wall"):
                v[n, 2] = -0.2 + 0.1 * k
            else:
                v[n, 2] = 1.0
        return v

    run = make_run(tmp_path / "r", [(0.0, pos, velocities(1.0)), (0.1, pos, velocities(2.0))])
    for s in (0, 1):  # make_run writes one diameter for all: put the mixed diameters in
        path = run / "particles" / f"particles_{s:06d}.vtp"
        data = vtp_bytes(pos, {"velocity": velocities(1.0 + s), "diameter": diam, "gid": np.arange(len(pos))})
        path.write_bytes(data)
    res = post_run(run, window=(0.0, 0.1), bins=BINS, depth_bins=3, out=tmp_path / "post")
    prof = np.genfromtxt(tmp_path / "post" / "depth_zH0.16.csv", delimiter=",", names=True)
    k = np.arange(3)
    centre, walls = 0.15 * (k + 1), -0.2 + 0.1 * k
    every = (0.3 * (k + 1) + 2 * 2 * walls + 2 * 8 * 1.0) / 22  # volumes 1 (centre), 2 x 1 (walls), 8 (between)
    assert np.allclose(prof["yD"], (k + 0.5) / 3, rtol=1e-12)
    assert np.allclose(prof["U_pzUf_centre"] * UF, centre, rtol=1e-12)
    assert np.allclose(prof["U_pzUf_walls"] * UF, walls, rtol=1e-12)
    assert np.allclose(prof["U_pzUf_all"] * UF, every, rtol=1e-12)
    assert np.allclose(prof["solid_share_all"], 1 / 3, rtol=1e-12)
    assert res.values["depth_zH0.16_spread_centre/Uf"] == pytest.approx(0.3 / UF, rel=1e-12)
    assert res.values["depth_zH0.16_spread_walls/Uf"] == pytest.approx(0.2 / UF, rel=1e-12)
    assert any(f.name == "depth_zH0.16.png" for f in res.files)
    assert res.values["depth_zH0.16_front_back_asymmetry"] == pytest.approx(0.0, abs=1e-12)  # 1/3 per bin
    lopsided = DepthProfile(run_info(run), Grid(lo=(0.0, 0.0), hi=(L, H), n=BINS, axes=(0, 2), depth=D), 3)
    lopsided.add({"pos": pos[[0, 2]], "velocity": np.zeros((2, 3)), "diameter": np.array([DP, DP])})  # bins 0, 1
    assert lopsided.asymmetry() == pytest.approx((1.5 - 0.5) / 2.0, rel=1e-12)  # the middle bin is half front
    # a run without a depth, and bad settings, say so
    info = run_info(run)
    grid = Grid(lo=(0.0, 0.0), hi=(L, H), n=BINS, axes=(0, 2), depth=D)
    with pytest.raises(ValueError, match="3D run"):
        DepthProfile(dataclasses.replace(info, dim=2), grid, 3)
    with pytest.raises(ValueError, match="depth bins"):
        DepthProfile(info, grid, 0)
    with pytest.raises(ValueError, match="depth bins"):  # what `febed post --depth-bins 0` gets
        post_run(run, window=(0.0, 0.1), bins=BINS, depth_bins=0, figures=False, out=tmp_path / "p0")
    with pytest.raises(ValueError, match="z/H"):
        DepthProfile(info, grid, 3, height=1.5)
    assert np.isnan(DepthProfile(info, grid, 3).spread())  # nothing added: no profile


def test_means_over_consecutive_windows(tmp_path, capsys):
    """`febed post --split DT`: one row per whole window, each what `febed post --window a b` finds there."""
    from febed.post.cli import main
    from febed.post.windows import split_window, spread, window_edges

    pos, bins, _ = lattice()
    vel = np.array([bin_velocity(i, j) for i, j in bins])
    # the loops turn over at t = 0.45 s: the snapshots at 0-0.4 s go one way, those at 0.5-0.8 s the other
    run = make_run(tmp_path / "r", [(0.1 * k, pos, vel if k <= 4 else -vel) for k in range(9)])
    w_a = (RHO_P - RHO_G) * 9.81 * len(pos) * VP / (L * D)
    t = np.linspace(0, 0.8, 81)
    with open(run / "probes.csv", "w") as fh:
        fh.write("time,particles,bed_height,dp_bed\n")
        for tt in t:
            fh.write(f"{tt!r},{len(pos)},0.15,{w_a * (1.0 + 0.1 * (tt > 0.4))!r}\n")
    rows = split_window(run, (0.0, 0.8), 0.4, bins=BINS)
    assert [(r["window_t0"], r["window_t1"]) for r in rows] == [(0.0, 0.4), (0.4, 0.8)]
    for r in rows:
        window = (r["window_t0"], r["window_t1"])
        ref = post_run(run, window=window, bins=BINS, figures=False, out=tmp_path / "p").values
        for key in ("dp_bed_over_weight", "bottom_support/W", "bed_height_mean", "bed_flux_centre/rhoUf",
                    "bed_flux_walls/rhoUf", "bubble_fraction", "snapshots"):  # fmt: skip
            assert r[key] == pytest.approx(ref[key], rel=1e-12, nan_ok=True), key
    # window 1: five snapshots one way; window 2: its first snapshot (t = 0.4 s, on the boundary) that way, four back
    first, second = rows
    assert first["bed_flux_centre/rhoUf"] > 0 > first["bed_flux_walls/rhoUf"]
    assert second["bed_flux_centre/rhoUf"] == pytest.approx(-0.6 * first["bed_flux_centre/rhoUf"], rel=1e-12)
    assert second["bed_flux_walls/rhoUf"] == pytest.approx(-0.6 * first["bed_flux_walls/rhoUf"], rel=1e-12)
    s = spread(rows, "bed_flux_centre/rhoUf")
    c = first["bed_flux_centre/rhoUf"]
    assert s["n"] == 2 and s["mean"] == pytest.approx(0.2 * c) and s["std"] == pytest.approx(1.6 * c / math.sqrt(2))
    assert (s["min"], s["max"]) == (pytest.approx(-0.6 * c), pytest.approx(c))
    # whole windows only, without round-off in their edges
    assert window_edges(0.0, 1.0, 0.3) == [(0.0, 0.3), (0.3, 0.6), (0.6, 0.9)]
    assert window_edges(0.0, 0.3, 0.1) == [(0.0, 0.1), (0.1, 0.2), (0.2, 0.3)]
    assert len(window_edges(5.0, 15.0, 1.0)) == 10
    # the command line: the spread printed, windows.csv (and windows.png) written
    argv = [str(run), "--bins", "4", "5", "--window", "0", "0.8", "--split", "0.4"]
    assert main([*argv, "-o", str(tmp_path / "o")]) == 0
    out = capsys.readouterr().out
    assert "2 windows of 0.4 s from 0 s" in out and "windows.csv" in out and "windows.png" in out
    assert "standard error" in out
    table = np.genfromtxt(tmp_path / "o" / "windows.csv", delimiter=",", names=True)
    assert table.size == 2 and np.allclose(table["bed_flux_centrerhoUf"], [c, -0.6 * c], rtol=1e-5)
    for bad, what in (("0", "must be a number > 0"), ("-1", "must be a number > 0"), ("1.0", "longer than")):
        assert main([str(run), "--window", "0", "0.8", "--split", bad, "--no-figures", "-o", str(tmp_path / "b")]) == 2
        assert what in capsys.readouterr().err, bad


def test_compare_with_split_gives_each_runs_standard_errors(tmp_path, capsys):
    """`febed compare --split DT`: each row's KEY_se is the standard error `spread` gives its windows of DT s."""
    from febed.post import collect
    from febed.post.cli import main
    from febed.post.windows import SE_KEYS, split_window, spread, standard_errors

    pos, bins, _ = lattice()
    vel = np.array([bin_velocity(i, j) for i, j in bins])
    runs = []
    w_a = (RHO_P - RHO_G) * 9.81 * len(pos) * VP / (L * D)
    for name, turn in (("a", 4), ("b", 2)):  # the loops reverse after snapshot `turn` (t = 0.1 turn s)
        run = make_run(tmp_path / name, [(0.1 * k, pos, vel if k <= turn else -vel) for k in range(9)])
        with open(run / "probes.csv", "w") as fh:
            fh.write("time,particles,bed_height,dp_bed\n")
            for tt in np.linspace(0, 0.8, 81):
                fh.write(f"{tt!r},{len(pos)},0.15,{w_a * (1.0 + 0.1 * np.sin(20 * tt))!r}\n")
        runs.append(run)

    def extra(run_dir, window):
        return standard_errors(run_dir, window, 0.2)

    table = collect.compare_runs(runs, windows=[(0.0, 0.8)], out=tmp_path / "cmp", extra=extra)
    for r, run in zip(table.rows, runs, strict=True):
        parts = split_window(run, (0.0, 0.8), 0.2)
        assert len(parts) == 4
        for key in SE_KEYS:
            assert r[f"{key}_se"] == pytest.approx(spread(parts, key)["sem"], rel=1e-12, nan_ok=True), key
        assert r["bed_flux_centre/rhoUf_se"] > 0.0  # the loops reverse inside the window
    header = (tmp_path / "cmp" / "comparison.csv").read_text().splitlines()[0]
    assert "bed_flux_centre/rhoUf_se" in header
    # the command line prints a standard-error line under each run; bad values are named
    assert main(["compare", *map(str, runs), "--window", "0", "0.8", "--split", "0.2", "-o", str(tmp_path / "c")]) == 0
    assert capsys.readouterr().out.count("standard error") == 2
    bad = ((["--split", "0"], "must be a number > 0"), (["--split", "0.2", "--no-fields"], "particle averages"))
    for extra, what in bad:
        assert main(["compare", *map(str, runs), "--window", "0", "0.8", *extra, "-o", str(tmp_path / "x")]) == 2
        assert what in capsys.readouterr().err, extra


def test_window_spread_standard_error_widens_for_correlated_windows():
    """`spread`'s standard error: std/√n for uncorrelated windows, std/√n_eff (AR(1)) for correlated ones."""
    from febed.post.windows import spread

    def rows(values):
        return [{"x": v} for v in values]

    # a ramp 1, 2, 3, 4: d = (-1.5, -0.5, 0.5, 1.5), r1 = (0.75 - 0.25 + 0.75) / 5 = 0.25, n_eff = 4 (0.75/1.25) = 2.4
    s = spread(rows([1.0, 2.0, 3.0, 4.0]), "x")
    assert s["r1"] == pytest.approx(0.25, rel=1e-14)
    assert s["sem"] == pytest.approx(math.sqrt(5.0 / 3.0) / math.sqrt(2.4), rel=1e-14)
    # alternating windows are anti-correlated (r1 = -0.75): they never narrow the error below std/√n
    s = spread(rows([1.0, -1.0, 1.0, -1.0]), "x")
    assert s["r1"] == pytest.approx(-0.75, rel=1e-14)
    assert s["sem"] == pytest.approx(s["std"] / 2.0, rel=1e-14)
    # two windows: no correlation to estimate, std/√2; NaN windows are left out; one window: no spread at all
    s = spread(rows([3.0, math.nan, 5.0]), "x")
    assert s["n"] == 2 and math.isnan(s["r1"]) and s["sem"] == pytest.approx(math.sqrt(2.0) / math.sqrt(2.0))
    s = spread(rows([3.0]), "x")
    assert s["mean"] == 3.0 and math.isnan(s["std"]) and math.isnan(s["sem"])
    assert spread(rows([]), "x")["n"] == 0


def test_loops_in_time_demo_draws_each_runs_windows(tmp_path, monkeypatch, capsys):
    """`demos/pseudo2d/loops_in_time.py`: every run's windows printed as `split_window` gives them, one figure."""
    import runpy
    import sys
    from pathlib import Path

    from febed.post.windows import split_window

    pos, bins, _ = lattice()
    vel = np.array([bin_velocity(i, j) for i, j in bins])
    runs = [make_run(tmp_path / f"r{g}", [(0.1 * k, pos, g * vel) for k in range(7)]) for g in (1, 2)]
    for run in runs:
        with open(run / "probes.csv", "w") as fh:
            fh.write("time,particles,bed_height,dp_bed\n")
            fh.writelines(f"{0.01 * k!r},{len(pos)},0.15,500.0\n" for k in range(61))
    script = Path(__file__).parents[2] / "demos" / "pseudo2d" / "loops_in_time.py"
    figure = tmp_path / "loops.png"
    argv = [str(script), *map(str, runs), "--labels", "one", "two", "--from", "0", "--split", "0.3", "-o", str(figure)]
    monkeypatch.setattr(sys, "argv", argv)
    runpy.run_path(str(script), run_name="__main__")
    out = capsys.readouterr().out
    assert figure.is_file() and "one:" in out and "two:" in out
    lines = [ln for ln in out.splitlines() if "centre" in ln]
    assert len(lines) == 4  # two whole windows of 0.3 s in 0-0.6 s per run
    for run, printed in zip(runs, (lines[:2], lines[2:]), strict=True):
        for r, ln in zip(split_window(run, (0.0, 0.6), 0.3), printed, strict=True):
            assert math.isfinite(r["bed_flux_centre/rhoUf"]) and f"centre {r['bed_flux_centre/rhoUf']:+6.1f}" in ln
    assert lines[2].split("centre")[1].split()[0] != lines[0].split("centre")[1].split()[0]  # twice the velocity
    # a run whose output from its start is shorter than one window is left out, with a line saying so
    monkeypatch.setattr(sys, "argv", [*argv[:6], "--from", "0", "0.5", *argv[8:]])
    runpy.run_path(str(script), run_name="__main__")
    out = capsys.readouterr().out
    assert "one:" in out and "two: its output from 0.5 s ends at 0.6 s, short of one 0.3 s window; left out" in out
