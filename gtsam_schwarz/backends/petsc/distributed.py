"""The nonlinear loop with per-rank linearization: each rank linearizes only the factors it owns.

A factor belongs to the rank that owns its first variable (``layout.rank_layout``: vertices are
owned by subdomain). Each rank builds a :class:`~gtsam_schwarz.linearization.native.NativeLinearizer`
on its factors (``from_arrays`` on a slice of the whole graph's factor arrays; when some factors need
GTSAM, a ``NativeLinearizer`` of the rank's sub-graph, which hands those to GTSAM), adds its H blocks into
the PETSc MPIAIJ matrix (MatSetValues with ADD_VALUES; rows of other ranks go through PETSc's
assembly) and its g into a PETSc Vec, and keeps the poses its factors touch plus the poses it owns.
The step stays distributed: each rank scatters only the entries of its poses and retracts them.
The error, ‖g‖, the step's norms and the model's predicted decrease are sums over the ranks
(allgathered and summed in rank order, so every rank takes the same decisions).

Still on every rank (see docs/distributed.md): the file, the whole graph's factor arrays (from
which the rank's slice is cut), the initial error and the decomposition. The chordal initialization
runs on rank 0 alone and is broadcast. Graphs with variables that are not poses, or with Pose2 and
Pose3 mixed, fall back to the replicated linearization (every rank linearizes all, rows gathered).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ...coarse.modes import rigid_modes
from ...dd.index_sets import vertex_dofs
from ...dd.structure import GraphStructure
from ...linearization import native_kernels as nk
from ...linearization.native import NativeLinearizer, NativeState
from ...nonlinear.gauge import FREE_TOL
from ...nonlinear.optimizer import SchwarzOptimizer
from ...util import sorted_unique
from .solver import PetscSchwarzSolver, petsc


@dataclass
class DistributedSystem:
    """H (PETSc Mat, this rank's rows) and g, −g (PETSc Vecs) in the layout's numbering."""

    H: object
    g: object
    rhs: object
    gnorm: float
    error: float
    seconds: dict = field(default_factory=dict)


def replicated_reason(linearizer) -> str:
    """Why ``linearizer`` cannot be split by rank ("" when it can: a pure Pose2 or Pose3 native graph)."""
    if not isinstance(linearizer, NativeLinearizer):
        return f"{type(linearizer).__name__} is not the native linearizer"
    if linearizer._others is not None and linearizer._others.var_keys:
        return "the graph has variables that are not poses"
    if (linearizer._k2 is None) == (linearizer._k3 is None):
        return "the graph mixes Pose2 and Pose3 (or has no poses)"
    return ""


def _sqrt_info(F, sel: np.ndarray, d: int) -> np.ndarray:
    """(m, d, d) upper-triangular square-root information of the factors ``sel`` of F."""
    if d == 6:
        return F.R[sel]
    r = F.rows(sel)
    R = np.zeros((len(sel), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 0, 2], R[:, 1, 1], R[:, 1, 2], R[:, 2, 2] = r
    return R


def _slice(F, sel: np.ndarray, d: int):
    """(measurements, sqrt information, robust) of the factors ``sel`` of F, in from_arrays' formats."""
    z = F.z[:, sel].T if d == 3 else (F.zR[sel], F.zt[sel])
    robust = None if F.robust is None else (F.robust.code[sel], F.robust.param[sel])
    return z, _sqrt_info(F, sel, d), robust


class RankLinearizer:
    """The factors of one rank: native linearization, assembly into PETSc, retraction of its poses."""

    def __init__(self, full: NativeLinearizer, layout, rank: int, comm, graph=None, values=None):
        self.PETSc = PETSc = petsc()
        self.comm, self.rank, self.layout = comm, rank, layout
        K = full._k2 or full._k3
        d = self.d = K.d
        if not np.array_equal(K.gvar, np.arange(K.n)):
            raise AssertionError("a pure pose graph numbers its poses 0..n-1")
        vrank = layout.dof_rank[full.offsets[:-1]]
        B, P = K.between, K.prior
        own_b = np.flatnonzero(vrank[B.i] == rank) if B is not None else np.zeros(0, np.int64)
        own_p = np.flatnonzero(vrank[P.j] == rank) if P is not None else np.zeros(0, np.int64)
        self.n_factors = len(own_b) + len(own_p)
        parts = [B.i[own_b], B.j[own_b]] if B is not None else []
        parts += [P.j[own_p]] if P is not None else []
        gtsam_factors = full._others is not None and full._others.graph.size() > 0
        if gtsam_factors:  # factors the kernels do not cover: GTSAM linearizes them on the first key's rank
            if graph is None or values is None:
                raise ValueError("a graph with GTSAM-linearized factors needs the gtsam graph and values")
            O = full._others
            keys = [np.asarray(O.graph.at(k).keys(), dtype=np.uint64) for k in range(O.graph.size())]
            first = np.searchsorted(full.keys, np.array([k[0] for k in keys], dtype=np.uint64))
            own_o = np.flatnonzero(vrank[first] == rank)
            parts += [np.searchsorted(full.keys, np.concatenate([keys[k] for k in own_o]))] if len(own_o) else []
            ids = np.sort(np.concatenate([B.ids[own_b] if B is not None else np.zeros(0, np.int64),
                                          P.ids[own_p] if P is not None else np.zeros(0, np.int64),
                                          full._other_ids[own_o]]))
            self.n_factors += len(own_o)
        touched = sorted_unique(np.concatenate(parts)) if parts else np.zeros(0, np.int64)
        self.owned = np.flatnonzero(vrank == rank)  # the poses this rank reports (geometry, values)
        self.hold = sorted_unique(np.concatenate([touched, self.owned]))  # the poses this rank keeps and retracts
        self.sel = None if len(touched) == len(self.hold) else np.searchsorted(self.hold, touched)
        self.owned_at = np.searchsorted(self.hold, self.owned)
        self.local = None
        if self.n_factors and gtsam_factors:
            import gtsam

            sub = gtsam.NonlinearFactorGraph()
            for idx in ids.tolist():  # setup only: one gtsam call per factor of the rank
                sub.push_back(graph.at(idx))
            self.local = NativeLinearizer(sub, values)
            if not np.array_equal(self.local.keys, K.keys[touched]):
                raise AssertionError("the rank's linearizer numbers its poses differently")
        elif self.n_factors:
            kw = {}
            if len(own_b):
                z, R, rob = _slice(B, own_b, d)
                kw.update(edges=np.stack([K.keys[B.i[own_b]], K.keys[B.j[own_b]]], 1), measurements=z,
                          sqrt_information=R, robust=rob)
            if len(own_p):
                z, R, rob = _slice(P, own_p, d)
                kw.update(prior_keys=K.keys[P.j[own_p]], prior_measurements=z, prior_sqrt_information=R,
                          prior_robust=rob)
            poses = np.zeros((len(touched), 3)) if d == 3 else np.tile(np.eye(4), (len(touched), 1, 1))
            self.local = NativeLinearizer.from_arrays("pose2" if d == 3 else "pose3", K.keys[touched], poses, **kw)
            if not np.array_equal(self.local.keys, K.keys[touched]):
                raise AssertionError("the rank's linearizer numbers its poses differently")
        n = layout.n
        dof = lambda v: (full.offsets[v][:, None] + np.arange(d)).ravel()  # noqa: E731
        IT = PETSc.IntType
        self.touched_rows = layout.position[dof(touched)].astype(IT)  # local dof → PETSc row
        hold_rows = layout.position[dof(self.hold)].astype(IT)
        lo, hi = layout.rows(rank)
        # the distributed step's entries of this rank's poses, scattered into a sequential Vec
        self._xloc = PETSc.Vec().createSeq(len(hold_rows), comm=PETSc.COMM_SELF)
        self._xis = PETSc.IS().createGeneral(hold_rows, comm=PETSc.COMM_SELF)
        self._scatter = None
        self.n, self.lo, self.hi = n, lo, hi
        self.H = self.g = self._cols = None
        self.seconds = {"blocks": 0.0, "assemble": 0.0}

    # -- state ------------------------------------------------------------------------------------
    def state(self, full_state: NativeState) -> NativeState:
        """This rank's poses out of a state of the whole graph."""
        h = self.hold
        if self.d == 3:
            return NativeState(pose2=np.ascontiguousarray(full_state.pose2[:, h]))
        return NativeState(R3=np.ascontiguousarray(full_state.R3[h]), t3=np.ascontiguousarray(full_state.t3[h]))

    def _touched(self, state: NativeState) -> NativeState:
        if self.sel is None:
            return state
        s = self.sel
        if self.d == 3:
            return NativeState(pose2=state.pose2[:, s])
        return NativeState(R3=state.R3[s], t3=state.t3[s])

    def owned_poses(self, state: NativeState) -> tuple:
        """(owned vertices, their pose arrays): this rank's share of a gathered state."""
        o = self.owned_at
        if self.d == 3:
            return self.owned, (state.pose2[:, o],)
        return self.owned, (state.R3[o], state.t3[o])

    def error(self, state: NativeState) -> float:
        """Σ of this rank's factors' errors."""
        return 0.0 if self.local is None else float(self.local.error(self._touched(state)))

    def retract(self, state: NativeState, x) -> NativeState:
        """This rank's poses ⊕ their entries of the distributed step ``x`` (a PETSc Vec)."""
        PETSc = self.PETSc
        if self._scatter is None:
            self._scatter = PETSc.Scatter().create(x, self._xis, self._xloc, None)
        self._scatter.scatter(x, self._xloc, addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        v = self._xloc.getArray(readonly=True).reshape(-1, self.d)
        if self.d == 3:
            return NativeState(pose2=nk.pose2_retract(state.pose2, v))
        R, t = nk.pose3_retract(state.R3, state.t3, v)
        return NativeState(R3=R, t3=t)

    # -- H and g into PETSc ---------------------------------------------------------------------
    def _create(self, H: sp.csr_matrix) -> None:
        """The MPIAIJ matrix with this rank's rows, preallocated exactly: every rank sends the
        (row, column) pairs of its contributions to the rows' owners (one all-to-all, once)."""
        PETSc, lay = self.PETSc, self.layout
        mpi = self.comm.tompi4py()
        n, lo, hi = self.n, self.lo, self.hi
        rows = np.repeat(self.touched_rows.astype(np.int64), np.diff(H.indptr))
        cols = self.touched_rows.astype(np.int64)[H.indices]
        key = rows * np.int64(n) + cols
        dest = np.searchsorted(lay.ranges, rows, side="right") - 1
        order = np.argsort(dest, kind="stable")
        bounds = np.searchsorted(dest[order], np.arange(lay.ranks + 1))
        send = [sorted_unique(key[order[bounds[r]:bounds[r + 1]]]) for r in range(lay.ranks)]
        mine = sorted_unique(np.concatenate(mpi.alltoall(send)))
        r = mine // n - lo
        indptr = np.zeros(hi - lo + 1, dtype=np.int64)
        np.cumsum(np.bincount(r, minlength=hi - lo), out=indptr[1:])
        IT = PETSc.IntType
        self.H = PETSc.Mat().createAIJ(size=((hi - lo, n), (hi - lo, n)),
                                       csr=(indptr.astype(IT), (mine % n).astype(IT), np.zeros(len(mine))),
                                       comm=self.comm)
        self.H.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
        self.H.assemble()
        self.g, self.rhs = self.H.createVecs()
        self._indptr, self._cols = H.indptr.astype(IT), cols.astype(IT)

    def linearize(self, state: NativeState) -> tuple[object, object, float]:
        """H and g of all ranks' factors at ``state`` into PETSc; returns (H, g, this rank's error)."""
        PETSc = self.PETSc
        t0 = time.perf_counter()
        if self.local is not None:
            system = self.local.linearize(self._touched(state))
            H, g, error = system.H, system.g, system.error
        else:
            H, g, error = sp.csr_matrix((0, 0)), np.zeros(0), 0.0
        t1 = time.perf_counter()
        if self.H is None:
            self._create(H)
        elif len(self._cols) != H.nnz:
            raise AssertionError("the rank's H changed its pattern")
        ADD = PETSc.InsertMode.ADD_VALUES
        self.H.zeroEntries()
        if H.nnz:
            self.H.setValuesIJV(self._indptr, self._cols, H.data, addv=ADD, rowmap=self.touched_rows)
        self.H.assemble()
        self.g.zeroEntries()
        if len(g):
            self.g.setValues(self.touched_rows, g, addv=ADD)
        self.g.assemblyBegin()
        self.g.assemblyEnd()
        self.g.copy(self.rhs)
        self.rhs.scale(-1.0)
        self.seconds["blocks"] += t1 - t0
        self.seconds["assemble"] += time.perf_counter() - t1
        return self.H, self.g, error

    def destroy(self) -> None:
        for o in (self.H, self.g, self.rhs, self._xloc, self._xis, self._scatter):
            if o is not None:
                o.destroy()


class DistributedOptimizer(SchwarzOptimizer):
    """``SchwarzOptimizer`` run by every rank of ``comm``, each linearizing its own factors into PETSc;
    ``optimize()`` returns the Values on rank 0, None elsewhere (``replicated``: why a graph cannot be split)."""

    def __init__(self, graph, initial, params=None, comm=None, local_solver: str = "auto",
                 coarse_matrix: str = "harmonic", options: dict | None = None, linearizer=None):
        PETSc = petsc()
        self.comm = comm if comm is not None else PETSc.COMM_WORLD
        self.mpi = self.comm.tompi4py()
        self.rank = self.comm.getRank()
        t0 = time.perf_counter()
        super().__init__(graph, initial, params, linearizer=linearizer)
        self.init_seconds = time.perf_counter() - t0  # the whole graph's linearizer, initial error, chordal start
        self.setup_seconds = 0.0
        full = self.linearizer
        self.linear_solver = PetscSchwarzSolver(self.nonlinear_params.linear_solver, full.offsets,
                                                full.translation_mask(), comm=self.comm, local_solver=local_solver,
                                                options=options, coarse_matrix=coarse_matrix)
        self.replicated = replicated_reason(full)
        self.distributed = not self.replicated
        self.part: RankLinearizer | None = None
        if self.distributed:
            t0 = time.perf_counter()
            pattern = full.pattern.matrix(np.ones(full.pattern.nnz))
            layout = self.linear_solver.set_layout(pattern, full.geometry(self._state))
            dec = self.linear_solver.decomposition
            structure = dec.structure if dec is not None else GraphStructure.from_matrix(pattern, full.offsets)
            self._components = connected_components(structure.adjacency(), directed=False)
            self.part = RankLinearizer(full, layout, self.rank, self.comm, graph, initial)
            self._state = self.part.state(self._state)
            self._error = self._sum(self.part.error(self._state))[0]
            self.setup_seconds = time.perf_counter() - t0
        self._geometry_cache = None

    chordal_ahead = False  # rank 0 alone computes the start (below): no analysis on every rank

    def _initialize(self, method: str, prepared=None) -> dict:
        """The global initialization on rank 0 alone, its poses broadcast (the others sleep meanwhile)."""
        if self.mpi.Get_size() == 1 or method == "file" or replicated_reason(self.linearizer):
            return super()._initialize(method)
        payload = None
        if self.rank == 0:
            record = super()._initialize(method)
            st = self._state
            payload = (record, NativeState(pose2=st.pose2, R3=st.R3, t3=st.t3), self._error)
        request = self.mpi.Ibarrier()
        while not request.Test():  # a blocking broadcast would spin a core for the whole start
            time.sleep(0.005)
        record, state, error = self.mpi.bcast(payload, root=0)
        if self.rank:
            self._state, self._error = state, error
        return record

    # -- reductions (summed in rank order: the same bits on every rank) -----------------------------
    def _sum(self, *values: float) -> np.ndarray:
        return np.sum(np.array(self.mpi.allgather(np.asarray(values, dtype=float))), axis=0)

    def _max(self, value: float) -> float:
        return float(max(self.mpi.allgather(float(value))))

    # -- the whole graph's poses, gathered (coarse modes, gauge, the result) ------------------------
    def _full_state(self, state: NativeState, root: int | None) -> NativeState | None:
        mine = self.part.owned_poses(state)
        parts = self.mpi.allgather(mine) if root is None else self.mpi.gather(mine, root=root)
        if parts is None:
            return None
        full = self.linearizer
        K = full._k2 or full._k3
        if K.d == 3:
            P = np.empty((4, K.n))
            for v, (a,) in parts:
                P[:, v] = a
            return NativeState(pose2=P)
        R, t = np.empty((K.n, 3, 3)), np.empty((K.n, 3))
        for v, (a, b) in parts:
            R[v], t[v] = a, b
        return NativeState(R3=R, t3=t)

    def _geometry(self):
        """Poses of every vertex (allgathered once per state): the rigid coarse modes use them."""
        if not self.distributed:
            return self.linearizer.geometry(self._state)
        if self._geometry_cache is None or self._geometry_cache[0] is not self._state:
            self._geometry_cache = (self._state, self.linearizer.geometry(self._full_state(self._state, None)))
        return self._geometry_cache[1]

    def values(self):
        """The estimate as ``gtsam.Values`` on rank 0 (None on the others); collective."""
        if not self.distributed:
            return super().values()
        full = self._full_state(self._state, 0)
        return self.linearizer.values(full) if full is not None else None

    # -- the loop's pieces, distributed -------------------------------------------------------------
    def _anchors(self, H) -> np.ndarray:
        """``gauge.free_components`` on the distributed H (zᵀHz and zᵀDz summed over the ranks' rows)."""
        full = self.linearizer
        geometry = self._geometry()
        offsets = full.offsets
        nv = len(offsets) - 1
        if geometry is None or nv == 0:
            return np.zeros(0, dtype=np.int64)
        lay = self.linear_solver.layout
        n_comp, comp = self._components
        d = geometry.d
        lo, hi = lay.rows(self.rank)
        vertex = np.repeat(np.arange(nv), np.diff(offsets))
        modes = rigid_modes(geometry, np.arange(nv), np.zeros((nv, d)), rotation=False)  # (nv, dim, d)
        n = len(vertex)
        local = np.arange(n) - offsets[vertex]
        cols = comp[vertex][:, None] * d + np.arange(d)
        Z = sp.csr_matrix((modes[vertex, local].ravel(), (np.repeat(np.arange(n), d), cols.ravel())),
                          shape=(n, n_comp * d))[lay.order]  # rows in the layout's numbering
        indptr, indices, data = H.getValuesCSR()
        Hl = sp.csr_matrix((data, indices, indptr), shape=(hi - lo, lay.n))
        Zo = Z[lo:hi]
        diag = H.getDiagonal().getArray(readonly=True)
        zHz = np.asarray(Zo.multiply(Hl @ Z).sum(axis=0)).ravel()
        zDz = np.asarray(Zo.multiply(Zo).multiply(diag[:, None]).sum(axis=0)).ravel()
        zHz, zDz = np.split(self._sum(*zHz, *zDz), 2)
        ratio = (zHz / np.where(zDz > 0, zDz, 1.0)).reshape(n_comp, d).max(axis=1)
        free = np.flatnonzero(ratio < FREE_TOL)
        first = np.full(n_comp, nv, dtype=np.int64)
        np.minimum.at(first, comp, np.arange(nv))
        return first[free]

    def _linearize(self):
        if not self.distributed:
            return super()._linearize()
        t0 = time.perf_counter()
        H, g, error = self.part.linearize(self._state)
        garr = g.getArray(readonly=True)
        gg, err = self._sum(float(garr @ garr), error)
        total = time.perf_counter() - t0
        if self.anchors is None:
            self.anchors = self._anchors(H)
            dofs = vertex_dofs(self.anchors, self.linearizer.offsets) if len(self.anchors) else np.zeros(0, np.int64)
            lay = self.linear_solver.layout
            lo, hi = lay.rows(self.rank)
            at = lay.position[dofs]
            self._anchor_rows = at[(at >= lo) & (at < hi)] - lo
            self._anchor_dofs = dofs if len(dofs) else None
        return DistributedSystem(H=H, g=g, rhs=self.part.rhs, gnorm=float(np.sqrt(gg)), error=float(err),
                                 seconds={"linearize": total, "export": 0.0})

    def _iterate(self) -> bool:
        if not self.distributed:
            return super()._iterate()
        iteration = self.iterations() + 1
        system = self._linearize()
        if self._gradient_converged(system.gnorm):
            return False
        if self.method == "gn":
            return self._gauss_newton(system, system.gnorm, iteration)
        return self._levenberg_marquardt(system, system.gnorm, iteration)

    def _damping(self, system: DistributedSystem, lam: float) -> np.ndarray | None:
        """This rank's rows of D in H + λD (+ the anchors' diagonal once more), as ``_damped``."""
        if lam == 0.0 and self._anchor_dofs is None:
            return None
        return self._damping_diagonal(system.H.getDiagonal().getArray(readonly=True), lam, self._anchor_rows)

    def _try_step(self, system, gnorm, lam, iteration, seconds):
        if not self.distributed:
            return super()._try_step(system, gnorm, lam, iteration, seconds)
        tol = self.forcing.tolerance(gnorm)
        t0 = time.perf_counter()
        result = self.linear_solver.solve_distributed(system.H, self._damping(system, lam), system.rhs, tol,
                                                      self._geometry)
        t1 = time.perf_counter()
        x = result.x
        new_state = self.part.retract(self._state, x)
        Hx = system.H.createVecLeft() if not hasattr(self, "_Hx") else self._Hx
        self._Hx = Hx
        system.H.mult(x, Hx)
        xa = x.getArray(readonly=True)
        xx, gx, xHx, err = self._sum(float(xa @ xa), float(system.g.getArray(readonly=True) @ xa),
                                     float(xa @ Hx.getArray(readonly=True)), self.part.error(new_state))
        step_max = self._max(np.abs(xa).max() if len(xa) else 0.0)
        new_error = float(err)
        t2 = time.perf_counter()
        self.forcing.solved(gnorm, tol)
        predicted = float(gx + 0.5 * xHx)
        record = self._record(iteration, gnorm, lam, new_error, predicted, float(np.sqrt(xx)), step_max, result,
                              seconds, t1 - t0 - result.setup_seconds, t2 - t1)
        return record, new_state

    def destroy(self) -> None:
        if self.part is not None:
            self.part.destroy()
        self.linear_solver.destroy()
