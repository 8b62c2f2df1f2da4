"""Coupling on the particles' own ranks, for particles shared by work (`[run] particle_partition = "work"`).

With the particles in work-balanced boxes (`febed.parallel.BoxExchange`), a particle may sit in a cell that
another rank owns. Each rank then couples its own particles anyway (docs/scaling.md, "The gas in compact
blocks"):

- it holds the coupling arrays of the **whole mesh** (`MeshArrays` of the mesh read on every rank alone), so
  it locates its particles wherever they are;
- before the particles' forces, it **gathers** the gas values of the nodes its particles' cells touch: from
  its own nodal arrays where it has the node (owned or ghost), from the node's owner otherwise;
- after the projection of its particles onto those nodes, it **sends the sums to the nodes' owners**, which
  add them; the filter and the division by the node volumes then run on the gas partition as before.

`NodeOwners` maps every node of the whole mesh to its owner rank and its index there (by the mesh file's
node numbers, which both meshes keep); `OwnerCoupler` is the `Coupler` doing the above. The sums are the
same as the mesh partition's, added in another order: the nodal fields agree to round-off
(tests/parallel/test_mpi_owner_coupling.py).

The whole mesh's coupling arrays cost every rank what they cost a serial run (0.37 kB per node for
hexahedra, more for tetrahedra; `febed.preflight.WHOLE_MESH_BYTES`): the price of locating a particle
anywhere without redistributing the mesh as the boxes move.
"""

from __future__ import annotations

from mpi4py import MPI

import numpy as np
from numba import njit

from febed.coupling.exchange import Coupler
from febed.coupling.mesh_arrays import CELL_KINDS, NUM_VERTICES, MeshArrays, extract_mesh_arrays
from febed.coupling.projection import exchange_add_kernel


@njit(cache=True)
def touched_nodes(cell_dofs, cell, mark):
    """The nodes (sorted) of the cells of `cell` (-1 skipped); `mark` (nd,) bool scratch, left all False.

    The work is in the particles and the nodes they touch, not in the whole mesh's nodes.
    """
    out = np.empty(min(cell.size * cell_dofs.shape[1], mark.size), dtype=np.int64)
    count = 0
    for p in range(cell.size):
        c = cell[p]
        if c < 0:
            continue
        for k in range(cell_dofs.shape[1]):
            d = cell_dofs[c, k]
            if not mark[d]:
                mark[d] = True
                out[count] = d
                count += 1
    out = np.sort(out[:count])
    for j in range(count):
        mark[out[j]] = False
    return out


@njit(cache=True)
def add_rows(out, rows, src, src_rows):
    """out[rows[i]] += src[src_rows[i]] for every i, repeated rows summed in order (out and src 2D)."""
    for i in range(rows.size):
        r = rows[i]
        s = src_rows[i]
        for a in range(out.shape[1]):
            out[r, a] += src[s, a]


def dof_inputs(mesh, Q) -> np.ndarray:
    """The mesh file's node number of each local dof of the P1/Q1 space Q (its dofs are the mesh vertices)."""
    nv = NUM_VERTICES[_kind(mesh)]
    tdim = mesh.topology.dim
    imap = mesh.topology.index_map(tdim)
    nc = imap.size_local + imap.num_ghosts
    dofs = Q.dofmap.list.array.reshape(-1, nv)[:nc]
    nodes = mesh.geometry.dofmap.array.reshape(-1, nv)[:nc]
    n = Q.dofmap.index_map.size_local + Q.dofmap.index_map.num_ghosts
    out = np.full(n, -1, dtype=np.int64)
    out[dofs] = np.asarray(mesh.geometry.input_global_indices, dtype=np.int64)[nodes]
    return out


def _kind(mesh) -> int:
    import dolfinx.mesh

    return CELL_KINDS[dolfinx.mesh.to_string(mesh.topology.cell_type)]


class NodeOwners:
    """Where each node of the whole mesh is in the distributed mesh, and the exchanges between the two.

    Attributes:
        owner: (Nw,) int32, rank owning whole-mesh node k; remote: (Nw,) int32, its index on that rank;
        local: (Nw,) int32, its local index on this rank (owned or ghost), -1 if this rank lacks it;
        num_owned: this rank's owned nodes (local indices below it).
    """

    def __init__(self, whole_inputs: np.ndarray, inputs: np.ndarray, num_owned: int, comm):
        """From the file node number of each whole-mesh node and of each local node (owned first) (collective)."""
        self.comm = comm
        self.num_owned = int(num_owned)
        own = np.ascontiguousarray(inputs[:num_owned], dtype=np.int64)
        counts = np.array(comm.allgather(own.size), dtype=np.int64)
        every = np.empty(int(counts.sum()), dtype=np.int64)
        comm.Allgatherv(own, [every, counts])
        top = int(max(every.max(initial=-1), whole_inputs.max(initial=-1), inputs.max(initial=-1))) + 1
        owner = np.full(top, -1, dtype=np.int32)
        remote = np.full(top, -1, dtype=np.int32)
        owner[every] = np.repeat(np.arange(counts.size, dtype=np.int32), counts)
        first = np.concatenate([[0], np.cumsum(counts)[:-1]])
        remote[every] = np.arange(every.size) - np.repeat(first, counts)
        here = np.full(top, -1, dtype=np.int32)
        here[inputs] = np.arange(inputs.size, dtype=np.int32)
        self.owner = owner[whole_inputs]
        self.remote = remote[whole_inputs]
        self.local = here[whole_inputs]
        orphans = int(np.count_nonzero(self.owner < 0))
        if comm.allreduce(orphans, op=MPI.SUM):
            raise RuntimeError(f"{orphans} node(s) of the whole mesh have no owner in the distributed mesh: the two "
                               "meshes were not read from the same file")  # fmt: skip

    def _plan(self, far: np.ndarray):
        """The nodes `far` ordered by owner, with the counts to and from every rank (collective)."""
        who = self.owner[far]
        far = far[np.argsort(who, kind="stable")]
        send = np.bincount(who, minlength=self.comm.size).astype(np.int64)
        recv = np.empty_like(send)
        self.comm.Alltoall(send, recv)
        return far, send, recv

    def _ask(self, far, send, recv) -> np.ndarray:
        """Send each owner the indices (on it) of the nodes asked of it; returns the indices asked of this rank."""
        asked = np.empty(int(recv.sum()), dtype=np.int32)
        self.comm.Alltoallv([np.ascontiguousarray(self.remote[far]), send], [asked, recv])
        return asked

    def gather(self, nodes: np.ndarray, fields: list[np.ndarray], whole: list[np.ndarray]) -> None:
        """Copy the local nodal `fields` (nd,) / (nd, k) into `whole` (Nw,) / (Nw, k) at `nodes` (collective).

        Nodes this rank holds are read here (ghost values must be current); the rest come from their owners.
        """
        loc = self.local[nodes]
        here = loc >= 0
        for src, dst in zip(fields, whole, strict=True):
            dst[nodes[here]] = src[loc[here]]
        far, send, recv = self._plan(nodes[~here])
        asked = self._ask(far, send, recv)
        cols = [1 if f.ndim == 1 else f.shape[1] for f in fields]
        width = sum(cols)
        out = np.empty((asked.size, width))
        j = 0
        for f, c in zip(fields, cols, strict=True):
            out[:, j : j + c] = f[asked].reshape(-1, c)
            j += c
        back = np.empty((far.size, width))
        self.comm.Alltoallv([out, recv * width], [back, send * width])
        j = 0
        for dst, c in zip(whole, cols, strict=True):
            dst[far] = back[:, j : j + c].reshape((far.size, *dst.shape[1:]))
            j += c

    def add_to_owners(self, nodes: np.ndarray, whole: np.ndarray, out: np.ndarray) -> None:
        """Zero `out` (nd, k), then add the sums `whole` (Nw, k) at `nodes` to their owners' rows (collective).

        After it, each rank's owned rows of `out` hold every rank's sums; its ghost rows are zero.
        """
        out[:] = 0.0
        loc = self.local[nodes]
        mine = (loc >= 0) & (loc < self.num_owned)
        add_rows(out, loc[mine], whole, nodes[mine])
        far, send, recv = self._plan(nodes[~mine])  # ghost rows here too: their owners sum them
        k = whole.shape[1]
        asked = self._ask(far, send, recv)
        got = np.empty((asked.size, k))
        self.comm.Alltoallv([np.ascontiguousarray(whole[far]), send * k], [got, recv * k])
        add_rows(out, asked, got, np.arange(asked.size))  # a node may come from several ranks


class OwnerCoupler(Coupler):
    """The `Coupler` of particles owned apart from the mesh: located on the whole mesh `ma`, coupled to `gas_ma`.

    `locate`, the interpolation and the projection kernels run on the whole mesh's arrays (`self.ma`); the
    nodal fields in and out are the gas partition's (`self.gas_ma`), as for `Coupler`.
    """

    def __init__(self, gas_ma: MeshArrays, whole_ma: MeshArrays, nodes: NodeOwners, drag: str, rho_g: float,
                 mu_g: float, **options):  # fmt: skip
        """Set up for the gas partition's arrays, the whole mesh's and the map between them (`build`).

        drag, rho_g, mu_g and the options (filter_passes, void_floor, pressure_gradient) are `Coupler`'s.
        """
        super().__init__(whole_ma, drag, rho_g, mu_g, **options)
        self.gas_ma = gas_ma
        self.nodes = nodes
        self._mark = np.zeros(whole_ma.num_dofs, dtype=np.bool_)
        self._touched = None  # the nodes of the particles' cells, found once per `locate`
        g = whole_ma.gdim
        nw = whole_ma.num_dofs
        self._gas_whole = [np.zeros((nw, g)), np.zeros(nw), np.zeros((nw, g))]
        self._sums = {}

    @classmethod
    def build(cls, gas_ma: MeshArrays, gas_mesh, gas_Q, whole_mesh, depth: float, **kw) -> OwnerCoupler:
        """The coupler of a distributed mesh (with its P1/Q1 space) and the same file read on this rank alone."""
        import dolfinx.fem

        whole_Q = dolfinx.fem.FunctionSpace(whole_mesh, ("Lagrange", 1))
        whole_ma = extract_mesh_arrays(whole_mesh, whole_Q, depth=depth)
        nodes = NodeOwners(dof_inputs(whole_mesh, whole_Q), dof_inputs(gas_mesh, gas_Q), gas_ma.num_owned_dofs,
                           gas_ma.comm)  # fmt: skip
        return cls(gas_ma, whole_ma, nodes, **kw)

    def touched(self, cell: np.ndarray | None = None) -> np.ndarray:
        """The whole-mesh nodes of the cells of `cell` (default: the particles' cells since the last `locate`)."""
        if cell is not None:
            return touched_nodes(self.ma.cell_dofs, cell, self._mark)
        if self._touched is None:
            self._touched = touched_nodes(self.ma.cell_dofs, self.cell, self._mark)
        return self._touched

    def locate(self, x: np.ndarray) -> np.ndarray:
        """As `Coupler.locate`, on the whole mesh: every particle inside the domain is found."""
        self._touched = None
        return super().locate(x)

    def reset_cells(self, cell: np.ndarray | None = None) -> None:
        """As `Coupler.reset_cells`."""
        self._touched = None
        super().reset_cells(cell)

    def _gathered(self, u_nodes, eps_nodes, gradp_nodes):
        whole = self._gas_whole
        self.nodes.gather(self.touched(), [u_nodes, eps_nodes, gradp_nodes], whole)
        return whole

    def gas_at_particles(self, u_nodes, eps_nodes, gradp_nodes):
        """As `Coupler.gas_at_particles`, from the gas partition's nodal arrays (collective)."""
        return super().gas_at_particles(*self._gathered(u_nodes, eps_nodes, gradp_nodes))

    def forces(self, u_nodes, eps_nodes, gradp_nodes, v, d_orig, n_orig):
        """As `Coupler.forces`, from the gas partition's nodal arrays (collective)."""
        return super().forces(*self._gathered(u_nodes, eps_nodes, gradp_nodes), v, d_orig, n_orig)

    def forces_into(self, u_nodes, eps_nodes, gradp_nodes, v, d_orig, n_orig, record, mass, drag=None) -> float:
        """As `Coupler.forces_into`, from the gas partition's nodal arrays (collective)."""
        whole = self._gathered(u_nodes, eps_nodes, gradp_nodes)
        return super().forces_into(*whole, v, d_orig, n_orig, record, mass, drag)

    def _deposit(self, cell, d3, n_orig, K, v, F, g, out) -> None:
        cols = out.shape[1]
        buf = self._sums.get(cols)
        if buf is None:
            buf = self._sums[cols] = np.zeros((self.ma.num_dofs, cols))
        nodes = self.touched(None if cell is self.cell else cell)
        buf[nodes] = 0.0  # only the rows read back (not the whole mesh's)
        exchange_add_kernel(self.ma.cell_dofs, cell, self.w, d3, n_orig, K, v, F, g, buf)
        self.nodes.add_to_owners(nodes, buf, out)
        self.gas_ma.update_ghosts(out)
