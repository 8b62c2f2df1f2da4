"""Numba kernels of the node-based gas step: sparse row loops over the constant nodal operators.

Every kernel loops over the *owned* rows of a CSR structure whose columns are local node indices
(owned + ghost), the momentum sweep over the same entries by edge (`febed.gas.edges`); the caller refreshes
the ghost values afterwards. The per-entry coefficients are those of
`febed.gas.operators.NodalOperators` (for row i, column j):

* `grad[k, d]  = ∫ φ_i ∂_d φ_j dx`  (Galerkin gradient; its rows sum to zero),
* `tens[k, :]  = ∫ ∂_d φ_i ∂_e φ_j dx` for (d, e) = (x,x), (y,y), [(z,z)], then the symmetric sums
  ∫ (∂_d φ_i ∂_e φ_j + ∂_e φ_i ∂_d φ_j) dx for d < e; the stiffness (Laplacian) is the sum of the first gdim.

Viscous and Taylor-Galerkin terms use the edge form Σ_j c_ij (a_j − a_i): it vanishes for a constant
field whatever the edge coefficients, and is exact for constant coefficients.
"""

from __future__ import annotations

import numpy as np
from numba import njit

# The row loops below may reorder their sums (LLVM's `reassoc`) and fuse multiply-adds (`contract`): the
# predictor of benchmarks/gas_step.py's hex-mesh step, mostly the momentum sweep, takes 0.66-0.72 of the time
# it took without, with results that change only at round-off and keep the IEEE NaN/Inf semantics. These
# kernels are called from Python only, never from another compiled kernel, so every run executes the same
# machine code for them, compiled or from the cache (the DEM's force loops, inlined into their integrators,
# cannot reassociate: febed/dem/contact.py).
ROWS = {"reassoc", "contract"}


def momentum_rhs(edges, q, u, gradp, nu, rho, half_dt_tg, out):
    """Explicit momentum right-hand side per node [N]: −ρ∇·(q⊗u) − ∇p + ∇·(ν∇u) + Taylor-Galerkin term.

    The convection is in skew-symmetric group form (see the comment above `_edges3`). One pass over the
    operators' entries by edge (`febed.gas.edges.EdgeOperators`).

    Args:
        edges: the `EdgeOperators` of the nodal operators (`NodalOperators.edges`).
        q: (n_ext, gdim) superficial velocity ε u [m/s] at the owned, ghost and extra column nodes.
        u: (n_ext, gdim) interstitial velocity [m/s].
        gradp: (n_owned, gdim) Galerkin pressure gradient Σ_j grad_ij p_j [N].
        nu: (n_ext,) nodal viscous coefficient ε (μ + ρ ν_t) [Pa s].
        rho: gas density [kg/m^3].
        half_dt_tg: Δt/2 if the Taylor-Galerkin streamline term is on, else 0 [s].
        out: (n_owned, gdim) result.
    """
    e = edges
    kernel = _edges3 if q.shape[1] == 3 else _edges2
    kernel(e.ei, e.ej, e.g_ij, e.g_ji, e.tens, e.g_diag, e.oi, e.oj, e.o_grad, e.o_tens, q, u, gradp, nu, rho,
           half_dt_tg, out)  # fmt: skip


# seed 001 eq 36, explicit part: the convection −ρ∇·(q⊗u) in skew-symmetric nodal-product (group) form
# ½ Σ_j (grad_ij·u_j + grad_ij·u_i) q_j + ½ q_i Σ_j grad_ij·u_j  (= ½∇·(q⊗u) + ½u·∇q + ½q∇·u, consistent
# with ∇·(q⊗u) for any ∇·u, and energy-neutral for divergence-free u); the viscous stress ∇·(ε μ_eff ∇u)
# and the Taylor-Galerkin (Lax-Wendroff) streamline term ρ Δt/2 ∇·(ū ū·∇q), which cancels the anti-diffusion
# of the forward-Euler convection step, both in edge form with edge-averaged coefficients: the term of the
# edge (i, j) in row j is minus that in row i. Each edge i < j of two owned nodes is visited once and adds to
# both rows; the entries whose column is not such a node (ghost and extra columns) add to their row only; the
# ½ q_i Σ_j grad_ij·u_j term and the pressure gradient are added last. Written out per dimension (scalar
# accumulators are ~5x faster in Numba than small-array loops).
@njit(cache=True, fastmath=ROWS)
def _edges3(ei, ej, gij, gji, tens, gd, oi, oj, og, ot, q, u, gradp, nu, rho, hdt, out):  # pragma: no cover
    n = out.shape[0]
    dv = np.empty(n)  # Σ_j grad_ij·u_j
    for i in range(n):
        sc = gd[i, 0] * u[i, 0] + gd[i, 1] * u[i, 1] + gd[i, 2] * u[i, 2]
        dv[i] = sc
        s = rho * sc
        out[i, 0] = -s * q[i, 0]
        out[i, 1] = -s * q[i, 1]
        out[i, 2] = -s * q[i, 2]
    for e in range(ei.size):
        i = ei[e]
        j = ej[e]
        ui0, ui1, ui2 = u[i, 0], u[i, 1], u[i, 2]
        uj0, uj1, uj2 = u[j, 0], u[j, 1], u[j, 2]
        qi0, qi1, qi2 = q[i, 0], q[i, 1], q[i, 2]
        qj0, qj1, qj2 = q[j, 0], q[j, 1], q[j, 2]
        b0, b1, b2 = 0.5 * (ui0 + uj0), 0.5 * (ui1 + uj1), 0.5 * (ui2 + uj2)
        dv[i] += gij[e, 0] * uj0 + gij[e, 1] * uj1 + gij[e, 2] * uj2
        dv[j] += gji[e, 0] * ui0 + gji[e, 1] * ui1 + gji[e, 2] * ui2
        sij = rho * (gij[e, 0] * b0 + gij[e, 1] * b1 + gij[e, 2] * b2)
        sji = rho * (gji[e, 0] * b0 + gji[e, 1] * b1 + gji[e, 2] * b2)
        t0, t1, t2 = tens[e, 0], tens[e, 1], tens[e, 2]
        c = (t0 + t1 + t2) * 0.5 * (nu[i] + nu[j])
        w = t0 * b0 * b0 + t1 * b1 * b1 + t2 * b2 * b2
        w = rho * hdt * (w + tens[e, 3] * b0 * b1 + tens[e, 4] * b0 * b2 + tens[e, 5] * b1 * b2)
        d0 = c * (uj0 - ui0) + w * (qj0 - qi0)
        d1 = c * (uj1 - ui1) + w * (qj1 - qi1)
        d2 = c * (uj2 - ui2) + w * (qj2 - qi2)
        out[i, 0] -= sij * qj0 + d0
        out[i, 1] -= sij * qj1 + d1
        out[i, 2] -= sij * qj2 + d2
        out[j, 0] -= sji * qi0 - d0
        out[j, 1] -= sji * qi1 - d1
        out[j, 2] -= sji * qi2 - d2
    for e in range(oi.size):
        i = oi[e]
        j = oj[e]
        ui0, ui1, ui2 = u[i, 0], u[i, 1], u[i, 2]
        uj0, uj1, uj2 = u[j, 0], u[j, 1], u[j, 2]
        b0, b1, b2 = 0.5 * (ui0 + uj0), 0.5 * (ui1 + uj1), 0.5 * (ui2 + uj2)
        dv[i] += og[e, 0] * uj0 + og[e, 1] * uj1 + og[e, 2] * uj2
        s = rho * (og[e, 0] * b0 + og[e, 1] * b1 + og[e, 2] * b2)
        t0, t1, t2 = ot[e, 0], ot[e, 1], ot[e, 2]
        c = (t0 + t1 + t2) * 0.5 * (nu[i] + nu[j])
        w = t0 * b0 * b0 + t1 * b1 * b1 + t2 * b2 * b2
        w = rho * hdt * (w + ot[e, 3] * b0 * b1 + ot[e, 4] * b0 * b2 + ot[e, 5] * b1 * b2)
        out[i, 0] -= s * q[j, 0] + c * (uj0 - ui0) + w * (q[j, 0] - q[i, 0])
        out[i, 1] -= s * q[j, 1] + c * (uj1 - ui1) + w * (q[j, 1] - q[i, 1])
        out[i, 2] -= s * q[j, 2] + c * (uj2 - ui2) + w * (q[j, 2] - q[i, 2])
    for i in range(n):
        d = 0.5 * rho * dv[i]
        out[i, 0] -= d * q[i, 0] + gradp[i, 0]
        out[i, 1] -= d * q[i, 1] + gradp[i, 1]
        out[i, 2] -= d * q[i, 2] + gradp[i, 2]


@njit(cache=True, fastmath=ROWS)
def _edges2(ei, ej, gij, gji, tens, gd, oi, oj, og, ot, q, u, gradp, nu, rho, hdt, out):  # pragma: no cover
    n = out.shape[0]
    dv = np.empty(n)
    for i in range(n):
        sc = gd[i, 0] * u[i, 0] + gd[i, 1] * u[i, 1]
        dv[i] = sc
        s = rho * sc
        out[i, 0] = -s * q[i, 0]
        out[i, 1] = -s * q[i, 1]
    for e in range(ei.size):
        i = ei[e]
        j = ej[e]
        ui0, ui1 = u[i, 0], u[i, 1]
        uj0, uj1 = u[j, 0], u[j, 1]
        qi0, qi1 = q[i, 0], q[i, 1]
        qj0, qj1 = q[j, 0], q[j, 1]
        b0, b1 = 0.5 * (ui0 + uj0), 0.5 * (ui1 + uj1)
        dv[i] += gij[e, 0] * uj0 + gij[e, 1] * uj1
        dv[j] += gji[e, 0] * ui0 + gji[e, 1] * ui1
        sij = rho * (gij[e, 0] * b0 + gij[e, 1] * b1)
        sji = rho * (gji[e, 0] * b0 + gji[e, 1] * b1)
        t0, t1 = tens[e, 0], tens[e, 1]
        c = (t0 + t1) * 0.5 * (nu[i] + nu[j])
        w = rho * hdt * (t0 * b0 * b0 + t1 * b1 * b1 + tens[e, 2] * b0 * b1)
        d0 = c * (uj0 - ui0) + w * (qj0 - qi0)
        d1 = c * (uj1 - ui1) + w * (qj1 - qi1)
        out[i, 0] -= sij * qj0 + d0
        out[i, 1] -= sij * qj1 + d1
        out[j, 0] -= sji * qi0 - d0
        out[j, 1] -= sji * qi1 - d1
    for e in range(oi.size):
        i = oi[e]
        j = oj[e]
        ui0, ui1 = u[i, 0], u[i, 1]
        uj0, uj1 = u[j, 0], u[j, 1]
        b0, b1 = 0.5 * (ui0 + uj0), 0.5 * (ui1 + uj1)
        dv[i] += og[e, 0] * uj0 + og[e, 1] * uj1
        s = rho * (og[e, 0] * b0 + og[e, 1] * b1)
        t0, t1 = ot[e, 0], ot[e, 1]
        c = (t0 + t1) * 0.5 * (nu[i] + nu[j])
        w = rho * hdt * (t0 * b0 * b0 + t1 * b1 * b1 + ot[e, 2] * b0 * b1)
        out[i, 0] -= s * q[j, 0] + c * (uj0 - ui0) + w * (q[j, 0] - q[i, 0])
        out[i, 1] -= s * q[j, 1] + c * (uj1 - ui1) + w * (q[j, 1] - q[i, 1])
    for i in range(n):
        d = 0.5 * rho * dv[i]
        out[i, 0] -= d * q[i, 0] + gradp[i, 0]
        out[i, 1] -= d * q[i, 1] + gradp[i, 1]


@njit(cache=True, fastmath=ROWS)
def divergence(indptr, indices, grad, q, out):  # pragma: no cover
    """Galerkin divergence per node, out_i = ∫ φ_i ∇·q_h dx [m^3/s in 3D]."""
    n = indptr.size - 1
    three = q.shape[1] == 3
    for i in range(n):
        s = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            j = indices[k]
            s += grad[k, 0] * q[j, 0] + grad[k, 1] * q[j, 1]
            if three:
                s += grad[k, 2] * q[j, 2]
        out[i] = s


@njit(cache=True, fastmath=ROWS)
def gradient(indptr, indices, grad, f, out):  # pragma: no cover
    """Galerkin gradient per node, out_i = ∫ φ_i ∇f_h dx (divide by ∫φ_i for the lumped L2 projection)."""
    n = indptr.size - 1
    three = grad.shape[1] == 3
    for i in range(n):
        g0 = 0.0
        g1 = 0.0
        g2 = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            fj = f[indices[k]]
            g0 += grad[k, 0] * fj
            g1 += grad[k, 1] * fj
            if three:
                g2 += grad[k, 2] * fj
        out[i, 0] = g0
        out[i, 1] = g1
        if three:
            out[i, 2] = g2


@njit(cache=True, fastmath=ROWS)
def strain_rate_norm(indptr, indices, grad, u, mass, out):  # pragma: no cover
    """Nodal |S| = sqrt(2 S:S) of the lumped L2-projected velocity gradient [1/s].

    Scalar accumulators for the 4 or 9 gradient entries (a small-array loop is several times slower).
    """
    n = indptr.size - 1
    three = u.shape[1] == 3
    for i in range(n):
        g00 = g01 = g02 = g10 = g11 = g12 = g20 = g21 = g22 = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            j = indices[k]
            a0 = grad[k, 0]
            a1 = grad[k, 1]
            u0 = u[j, 0]
            u1 = u[j, 1]
            g00 += a0 * u0
            g01 += a1 * u0
            g10 += a0 * u1
            g11 += a1 * u1
            if three:
                a2 = grad[k, 2]
                u2 = u[j, 2]
                g02 += a2 * u0
                g12 += a2 * u1
                g20 += a0 * u2
                g21 += a1 * u2
                g22 += a2 * u2
        s01 = 0.5 * (g01 + g10)
        s02 = 0.5 * (g02 + g20)
        s12 = 0.5 * (g12 + g21)
        s2 = g00 * g00 + g11 * g11 + g22 * g22 + 2.0 * (s01 * s01 + s02 * s02 + s12 * s12)
        out[i] = np.sqrt(2.0 * s2) / mass[i]


@njit(cache=True)
def predictor_update(q, rhs, mass, eps_new, K, Kv, f, g, rho, dt, out):  # pragma: no cover
    """Lumped predictor with implicit diagonal momentum exchange, per owned node [m/s].

    seed 001 eq 36 with −K_i(u_i − v̄_i) implicit: (ρ/Δt + K_i/ε_i^{n+1}) q*_i =
    ρ q_i^n/Δt + rhs_i/ΔV_i + K_i v̄_i + f_i + ε_i^{n+1} ρ g, where K_i v̄_i is given as `Kv` and f_i is a
    force density.
    """
    n = out.shape[0]
    gdim = out.shape[1]
    for i in range(n):
        a = rho / dt + K[i] / eps_new[i]
        for c in range(gdim):
            out[i, c] = (rho * q[i, c] / dt + rhs[i, c] / mass[i] + Kv[i, c] + f[i, c] + eps_new[i] * rho * g[c]) / a


@njit(cache=True)
def pressure_rhs(div, mass, eps, eps_old, dt, out):  # pragma: no cover
    """Poisson right-hand side b_i = −(D q*_i + ΔV_i (ε_i^{n+1} − ε_i^n)/Δt) (seed 001 eq 39); returns Σ storage."""
    total = 0.0
    for i in range(out.size):
        s = mass[i] * (eps[i] - eps_old[i]) / dt
        out[i] = -(div[i] + s)
        total += s
    return total


@njit(cache=True)
def correct(q_star, g_phi, mass, w, rho_dt, gp, q, grad_p):  # pragma: no cover
    """Correction (seed 001 eq 37) on owned rows: q = q* − w G φ/ΔV; G p += ρ/Δt G φ; ∇p = G p/ΔV.

    w = s/(1 + K Δt/(ρ ε)) with the drag-weighted projection (s the pressure's share, 1 by default), 1 without.
    """
    for i in range(g_phi.shape[0]):
        c = w[i] / mass[i]
        for d in range(g_phi.shape[1]):
            gp[i, d] += rho_dt * g_phi[i, d]
            q[i, d] = q_star[i, d] - c * g_phi[i, d]
            grad_p[i, d] = gp[i, d] / mass[i]


@njit(cache=True)
def repredict(q_star, g_phi, mass, c):  # pragma: no cover
    """q* −= c G φ / ΔV on owned rows: `predictor_update` redone after p += ρ/Δt φ.

    c = 1/(1 + K Δt/(ρ ε)), times the pressure's share s with the drag-weighted projection.
    """
    for i in range(g_phi.shape[0]):
        a = c[i] / mass[i]
        for d in range(g_phi.shape[1]):
            q_star[i, d] -= a * g_phi[i, d]


@njit(cache=True)
def max_rates(u, mu, width, n):  # pragma: no cover
    """(max_i |u_i|/Δ_i, max_i μ_i/Δ_i²) over the first n nodes: the CFL and Fourier rates before scaling."""
    rc = 0.0
    rf = 0.0
    for i in range(n):
        s = 0.0
        for d in range(u.shape[1]):
            s += u[i, d] * u[i, d]
        r = np.sqrt(s) / width[i]
        if r > rc:
            rc = r
        f = mu[i] / (width[i] * width[i])
        if f > rf:
            rf = f
    return rc, rf


# --- boundary conditions (febed.gas.boundary, VANSSolver._with_backflow)
@njit(cache=True)
def project_rows(q, rows, proj):  # pragma: no cover
    """q[rows[k]] = proj[k] q[rows[k]]: the slip walls' tangential projections, in place."""
    gdim = q.shape[1]
    qi = np.empty(gdim)
    for k in range(rows.size):
        i = rows[k]
        for d in range(gdim):
            qi[d] = q[i, d]
        for d in range(gdim):
            s = 0.0
            for e in range(gdim):
                s += proj[k, d, e] * qi[e]
            q[i, d] = s


@njit(cache=True)
def zero_rows(q, rows):  # pragma: no cover
    """q[rows] = 0: the no-slip nodes."""
    for k in range(rows.size):
        for d in range(q.shape[1]):
            q[rows[k], d] = 0.0


@njit(cache=True)
def add_rows(q, rows, scale, weight, normal):  # pragma: no cover
    """q[rows[k]] += (scale w_k) n: an inlet's part of its nodes' superficial velocity."""
    for k in range(rows.size):
        v = scale * weight[k]
        for d in range(q.shape[1]):
            q[rows[k], d] += v * normal[d]


@njit(cache=True)
def divide_rows(q, eps, u):  # pragma: no cover
    """The interstitial velocity u = q/ε, row by row."""
    for i in range(q.shape[0]):
        for d in range(q.shape[1]):
            u[i, d] = q[i, d] / eps[i]


@njit(cache=True)
def add_wall_friction(K, eps_mu, volume, friction_nodes, friction_area, law_nodes, law_area, law_h):  # pragma: no cover
    """K += the walls' implicit shear coefficients in place (`febed.gas.boundary.NodalBoundary.wall_friction`).

    Partial-slip nodes first, ε μ a/ΔV/λ with their own λ folded into `friction_area` (a/λ); then the wall-law
    nodes, ε μ a (1/λ)/ΔV with 1/λ of `febed.gas.boundary.porous_slip_inverse` at the K so far, operation for
    operation.
    """
    for k in range(friction_nodes.size):
        i = friction_nodes[k]
        K[i] += eps_mu[i] * friction_area[k] / volume[i]
    for k in range(law_nodes.size):
        i = law_nodes[k]
        h = law_h[k]
        kappa = np.sqrt(max(K[i], 0.0) / eps_mu[i])
        kappa = max(kappa, 1e-12 / h)
        kh = kappa * h
        a = np.sqrt(4.0 + kh * kh)
        inv_lam = a * (a + 2.0) / (kappa * h * h)
        K[i] += eps_mu[i] * law_area[k] * inv_lam / volume[i]


@njit(cache=True)
def backflow_coefficients(rows, bnormal, q, mass, coef, out):  # pragma: no cover
    """out[k] = coef max(−q_i·B_i, 0)/ΔV_i at the outlet rows i = rows[k]; True if any is positive."""
    inflowing = False
    for k in range(rows.size):
        i = rows[k]
        flux = 0.0
        for d in range(q.shape[1]):
            flux += bnormal[i, d] * q[i, d]
        c = coef * max(-flux, 0.0) / mass[i]
        out[k] = c
        if c > 0.0:
            inflowing = True
    return inflowing


# --- the drag-weighted pressure operator (VANSParameters.drag_weighted_projection; febed.gas.weighted)
@njit(cache=True)
def cell_means(dofs, w, out):  # pragma: no cover
    """out[c] = mean of w over the nodes of cell c (`dofs` (n_cells, n_dofs) local node indices)."""
    nd = dofs.shape[1]
    for c in range(dofs.shape[0]):
        s = 0.0
        for a in range(nd):
            s += w[dofs[c, a]]
        out[c] = s / nd


@njit(cache=True)
def csr_weighted_sum(start, cell, value, wc, vals):  # pragma: no cover
    """vals[e] = Σ_k wc[cell[k]] value[k] over start[e] <= k < start[e + 1]: the cells' entries of each CSR entry."""
    for e in range(vals.size):
        s = 0.0
        for k in range(start[e], start[e + 1]):
            s += wc[cell[k]] * value[k]
        vals[e] = s


@njit(cache=True)
def cell_products(dofs, K, wc, cells, x, y):  # pragma: no cover
    """Products of the listed cells: y = Σ_m wc[c] K[m] x, c = cells[m], over the local nodes.

    y is overwritten; the caller adds the ghost rows to their owners.
    """
    y[:] = 0.0
    nd = dofs.shape[1]
    xc = np.empty(nd)
    for m in range(cells.size):
        c = cells[m]
        for b in range(nd):
            xc[b] = x[dofs[c, b]]
        for a in range(nd):
            s = 0.0
            for b in range(nd):
                s += K[m, a, b] * xc[b]
            y[dofs[c, a]] += wc[c] * s


@njit(cache=True)
def rows_dot(indptr, indices, vals, rows, x):  # pragma: no cover
    """Σ_{i in rows} Σ_j A_ij x_j for the matrix `vals` (owned rows, extended columns)."""
    s = 0.0
    for i in rows:
        for k in range(indptr[i], indptr[i + 1]):
            s += vals[k] * x[indices[k]]
    return s
