"""Two-level Schwarz: the one-level operator plus a GDSW / RGDSW coarse correction (paper Sec. 3.3)."""

from __future__ import annotations

import numpy as np

from ..coarse import CoarseSpace, HarmonicExtension, gdsw_coarse_space
from ..coarse.modes import rigid_transport
from ..dd.decomposition import Decomposition
from ..dd.geometry import VertexGeometry
from ..dd.interface import find_interface
from ..solvers import SingularLocalMatrixError, factorize
from ..solvers.memory import bound_heap_fragmentation
from ..util.threads import on_local_thread, side_thread
from .base import SchwarzOperator, SumOperator
from .memory import fit_memory
from .one_level import AdditiveSchwarz, _need


class CoarseCorrection(SchwarzOperator):
    """R_0ᵀ A_0⁻¹ R_0 with R_0 = Φᵀ and A_0 = Φᵀ A Φ for a given coarse space.

    A rank-deficient Φ (dependent coarse vectors) makes A_0 singular: then the dependent
    directions are dropped (pseudo-inverse on the range of the diagonally scaled A_0), which
    gives the same coarse space without them. ``dropped`` counts them.
    """

    DROP_TOL = 1e-10

    def __init__(self, coarse: CoarseSpace):
        self.coarse = coarse
        self.n = coarse.basis.shape[0]
        self.dropped = 0
        try:
            self._solve = factorize(coarse.A0, "the coarse matrix A_0")
        except SingularLocalMatrixError:
            self._solve = self._range_solver(coarse.A0)

    @property
    def coarse_size(self) -> int:
        return self.coarse.size

    def _range_solver(self, A0):
        nc = A0.shape[0]
        if nc > 8000:
            raise SingularLocalMatrixError(f"the coarse matrix A_0 ({nc} × {nc}) is singular")
        D = A0.diagonal()
        s = np.where(D > 0, 1.0 / np.sqrt(np.where(D > 0, D, 1.0)), 0.0)
        w, V = np.linalg.eigh(s[:, None] * A0.toarray() * s[None, :])
        keep = w > self.DROP_TOL * max(w.max(), 0.0)
        self.dropped = int(nc - keep.sum())
        W = s[:, None] * V[:, keep]
        inv = 1.0 / w[keep]
        return lambda r: W @ (inv * (W.T @ r))

    def update(self, A, geometry=None):
        raise NotImplementedError("a coarse correction is rebuilt by its two-level operator")

    def apply(self, x):
        if self.coarse.size == 0:
            return np.zeros(self.n)
        return self.coarse.basis.matvec(self._solve(self.coarse.basis.rmatvec(x)))


class TwoLevelSchwarz(SumOperator):
    """Two-level additive Schwarz: one-level operator + GDSW/RGDSW coarse correction (Sec. 3.3).

    ``setup`` finds the interface and plans the harmonic extension (symbolic, once per graph);
    ``update`` refactors the subdomains and recomputes Φ (from the poses in ``geometry`` for rigid
    modes) and A_0. With a Φ of at least ``CONCURRENT_FROM`` entries the coarse correction is applied
    on a second thread while this one runs the local solves (:class:`SumOperator`'s ``concurrent``):
    its Φᵀ and Φ products run in scipy without Python's GIL, CHOLMOD's solves hold it. Lawnmower
    600x600 (Φ 13.2M entries): CG 3.7-4.1 → 3.1-3.3 s per run; 3D survey 32x32x32 (a small Φ)
    and lawnmower 100x100 gained nothing or lost (0.49 → 0.55 s), hence the threshold.
    """

    CONCURRENT_FROM = 4_000_000

    def __init__(self, decomposition: Decomposition, kind: str = "gdsw", rotation: bool = True,
                 translation_mask: np.ndarray | None = None, interface_grouping: str = "components",
                 coarse_modes: str = "rigid", memory_limit=None):
        self.decomposition = decomposition
        self.memory_limit = memory_limit  # bytes (None: $GTSAM_SCHWARZ_MEMORY_LIMIT or what is available)
        self.memory = None  # the MemoryEstimate of the first update
        self.kind, self.rotation, self.translation_mask = kind, rotation, translation_mask
        self.interface_grouping = interface_grouping
        self.rigid = coarse_modes == "rigid"
        self.one_level = AdditiveSchwarz(decomposition.index_sets(overlapping=True))
        self.n = self.one_level.n
        self.parts = [self.one_level]
        self.interface = self.extension = self.coarse_space = self.coarse = None
        self._subdomains_factored = False
        self._geometry = None  # the poses Φ's rigid modes are written at (a build's or the last transport's)
        self._ahead = None  # (old poses, new poses, vertices, Future) of transport_ahead, until settled
        self._ordering = None  # the subdomain blocks' order being found by setup (a Future), until ordered()
        # the same order found before setup, from the decomposition and A's vertex pattern (a Future of
        # ``vertex_block_order``; set by a caller that started it, taken by setup)
        self.block_order = None

    @classmethod
    def create(cls, n, decomposition=None, translation_mask=None, kind="gdsw", rotation=True,
               interface_grouping="components", coarse_modes="rigid", memory_limit=None, **options):
        mask = translation_mask if translation_mask is not None else np.ones(n, dtype=bool)
        return cls(_need(decomposition, kind), kind, rotation, mask, interface_grouping, coarse_modes, memory_limit)

    @property
    def uses_geometry(self) -> bool:
        """Rigid-body coarse modes need the poses at the linearization point."""
        return self.rigid

    @property
    def coarse_size(self) -> int:
        return self.coarse_space.size if self.coarse_space is not None else 0

    def setup(self, A):
        """Interface components and the harmonic extension (symbolic, once per graph). The subdomain
        blocks' fill-reducing order, which the extension's interiors then follow, is found on the side
        thread (CHOLMOD's ordering holds no GIL; 1M 2D poses 1.0 s) while the interface is found and
        the memory estimate's coarse columns are counted here (or only put in place there, where
        ``block_order`` brings it found ahead of the first linearization); :meth:`ordered` takes it."""
        bound_heap_fragmentation()
        local = self.one_level.solver
        ahead, self.block_order = self.block_order, None
        self._ordering = None if on_local_thread() else side_thread().submit(local.order_vertices, A, ahead)
        self.interface = find_interface(self.decomposition, self.interface_grouping)
        self.extension = HarmonicExtension(self.decomposition, self.interface)
        if self._ordering is None:
            self._order_interiors(local.order_vertices(A, ahead))
        self.memory = None
        return self

    def ordered(self) -> None:
        """Wait for the subdomain blocks' order found by :meth:`setup` and put the extension's
        interiors in it (before anything reads the blocks' order or the interiors' positions)."""
        job, self._ordering = self._ordering, None
        if job is not None:
            self._order_interiors(job.result())

    def _order_interiors(self, reordered: bool) -> None:
        if reordered:   # one fill-reducing order for the subdomain blocks and their interiors
            sets = self.one_level.solver.sets
            self.extension.order_interiors((sets.vertices, np.repeat(np.arange(sets.count), np.diff(sets.vertex_ptr))))

    def release(self, factors: bool | None = None) -> None:
        """Drop Φ, A_0 and (``factors``; None: in the low-memory mode) the subdomain factors until the
        next :meth:`update`, which refactors them with a new analysis: for a caller that knows the
        next solve rebuilds (they then do not sit beside the next linearization's arrays)."""
        self.settle_transport(undo=False)   # Φ is dropped: a multiplication under way only finishes
        self.coarse_space = self.coarse = self._geometry = None
        self.parts = [self.one_level]
        if factors or (factors is None and self.memory is not None and self.memory.low_memory):
            self.one_level.solver.release()
            self._subdomains_factored = False

    def update(self, A, geometry: VertexGeometry | None = None, subdomains: bool = True):
        """New numbers in A (and poses in ``geometry``): interface, index sets, submatrix patterns
        and symbolic factorizations are kept; numbers, Φ and A_0 are recomputed. ``subdomains=False``
        keeps the one-level part's factorizations of an earlier A where they are still held
        (:meth:`update_coarse`)."""
        self.settle_transport(undo=False)   # Φ is rebuilt: a multiplication under way only finishes
        if self.extension is None:
            self.setup(A)
        if self.memory is None:  # before the heavy work: estimate the peak, adapt or stop (its coarse
            # columns are counted while the blocks' order is still found; it then waits for the order)
            self.memory = fit_memory(self, A, self.memory_limit, self.kind, geometry=geometry)
        self.ordered()
        low = self.memory.low_memory
        self.extension.block_columns = self.memory.block_columns
        self.extension.keep_factors = not low
        # low memory: the subdomain blocks' gather positions are dropped chunk by chunk as they are
        # gathered (else they wait for the next refactorization beside the factors, CG and the next
        # linearization: 1M 2D poses, 383 MiB; LM there keeps the subdomains to the end)
        self.one_level.solver.keep_positions = not low
        # the previous Φ is not needed while the new one is built: its storage takes the new numbers
        previous = self.coarse_space.basis if self.coarse_space is not None else None
        self.release(factors=low)
        refactor = subdomains or not self._subdomains_factored
        # the subdomain blocks' symbolic work (gather positions) on the side thread while the
        # extension assembles A_0 on one core, after the interior factors are gone (1M 2D poses:
        # setup 9.9 / 12.4 against 15.2 / 14.8 s, the same peak); started with the extension, the
        # positions sat beside the interior factors and raised that peak by ~190 MiB
        ahead = []
        if refactor:
            self.extension.on_extended = lambda: ahead.append(self._prepare_subdomains(A))
        try:
            self.coarse_space = gdsw_coarse_space(A, self.decomposition, self.interface, self.kind, geometry,
                                                  self.rotation, self.translation_mask, self.extension,
                                                  recycle=previous)
        finally:
            self.extension.on_extended = None
            for job in ahead:
                if job is not None:
                    job.result()
        del previous
        self._geometry = geometry if self.rigid else None
        if refactor:
            self.refactor_subdomains(A)
        self.concurrent = self.coarse_space.basis.nnz >= self.CONCURRENT_FROM
        self.coarse = CoarseCorrection(self.coarse_space)
        self.parts = [self.one_level, self.coarse]
        return self

    def update_coarse(self, A, geometry: VertexGeometry | None = None):
        """The coarse level (Φ from the poses in ``geometry``, A_0) for A, with the subdomain
        factorizations of the last :meth:`update` kept (refactorized if they were released): a
        lagged one-level part. The coarse level carries the low-energy modes, which a small change
        of H moves; the local solves are insensitive to it. Measured after LM's first step from the
        chordal start (H changed by 3e-4 to 1.2e-3, :class:`~gtsam_schwarz.solvers.change.EntryChange`):
        the same CG counts as a full update on lawnmowers 100x100 to 1000x1000, a 3D survey 32³,
        city10000, M3500 and sphere2500; a stale coarse level instead took 30 CG against 11
        (lawnmower 600x600), and stale subdomains after large steps (H changed by 6e-2 to 0.2)
        200 to 2 900. In the low-memory mode the factorizations are released before the extension
        and refactorized (keeping them through it saved nothing at 360 000 2D poses: their 0.9 s
        refactorization against ~0.75 s more for the extension's factors in fresh memory)."""
        return self.update(A, geometry, subdomains=False)

    def can_transport(self, geometry: VertexGeometry | None) -> bool:
        """Whether :meth:`transport` applies: a built coarse level of rigid modes written at known
        poses, one pose kind (every vertex ``dim`` dofs, Φ's local rows in whole vertices)."""
        return self._transport_vertices(geometry) is not None

    def _transport_vertices(self, geometry: VertexGeometry | None) -> np.ndarray | None:
        """The vertex of each of Φ's local row blocks where :meth:`transport` applies, else None."""
        if self.coarse is None or self.coarse_space is None or self._geometry is None or geometry is None:
            return None
        dim = 3 if geometry.d == 2 else 6
        offsets = self.decomposition.structure.offsets
        if geometry.d != self._geometry.d or len(offsets) - 1 != len(geometry.positions):
            return None
        if not np.array_equal(offsets, np.arange(len(offsets)) * dim):
            return None
        return self.coarse_space.basis.vertex_rows(dim)

    def transport(self, A, geometry: VertexGeometry):
        """The coarse level carried to new poses instead of rebuilt: Φ ← diag(T_v) Φ with
        T_v = Ad(X_v,new⁻¹ X_v,old) (:func:`~gtsam_schwarz.coarse.modes.rigid_transport`), A_0 and its
        factorization kept, the subdomain factorizations kept (refactorized for A if released).

        Φ's interface values are rigid modes written in each pose's tangent coordinates; after an LM
        step they are the modes at the new poses times T_v, and what went stale in a kept coarse
        level was that frame, not the energy (A_0 = ΦᵀAΦ of the old H): lawnmower 600x600, second
        solve 15 CG against 14 after a full rebuild and 27-30 with Φ kept as it was. It costs a
        multiplication of Φ's d × d vertex blocks (no extension, no A_0, no factorization).
        Without it (:meth:`can_transport` False) this is :meth:`update_coarse`."""
        if not self.settle_transport(to=geometry):   # not multiplied ahead (transport_ahead) to these poses
            vertices = self._transport_vertices(geometry)
            if vertices is None:
                return self.update_coarse(A, geometry)
            self._transform(self._geometry, geometry, vertices)
        self._geometry = geometry
        if not self._subdomains_factored:
            self.refactor_subdomains(A)
        return self

    def transport_ahead(self, geometry: VertexGeometry) -> None:
        """Start :meth:`transport`'s multiplication of Φ for ``geometry`` on the side thread, ahead of
        the next solve (beside its linearization: lawnmower 1M poses ~0.8 s on one core): a
        :meth:`transport` to the same poses then only waits for it; any other use of Φ first
        settles it (:meth:`settle_transport`)."""
        self.settle_transport()
        vertices = self._transport_vertices(geometry)
        if vertices is None or on_local_thread():
            return
        old = self._geometry
        self._ahead = (old, geometry, vertices, side_thread().submit(self._transform, old, geometry, vertices))

    def settle_transport(self, to: VertexGeometry | None = None, undo: bool = True) -> bool:
        """Wait for a multiplication started by :meth:`transport_ahead`. Returns True where it went to
        the poses ``to`` (Φ is at them now); otherwise, with ``undo``, Φ is carried back to the poses
        of the coarse level (the inverse map: a lagged solve uses Φ as it was, to rounding)."""
        if self._ahead is None:
            return False
        old, new, vertices, job = self._ahead
        self._ahead = None
        job.result()
        if to is not None and _same_poses(new, to):
            return True
        if undo:
            self._transform(new, old, vertices)
        return False

    def _transform(self, old: VertexGeometry, new: VertexGeometry, vertices: np.ndarray) -> None:
        """Φ's vertex rows multiplied by their rigid transports, made a block of vertices at a time."""
        self.coarse_space.basis.transform_vertex_rows(lambda idx: rigid_transport(old, new, vertices[idx]),
                                                      3 if new.d == 2 else 6)

    def _prepare_subdomains(self, A):
        """A future of the one-level solver's symbolic preparation for A on the side thread (None
        where the solver has none or the caller is a worker thread itself)."""
        prepare = getattr(self.one_level.solver, "prepare", None)
        if prepare is None or on_local_thread():
            return None
        return side_thread().submit(prepare, A)

    def refactor_subdomains(self, A):
        """The one-level part's factorizations for A, the coarse level kept (after :meth:`update_coarse`
        for the same A, when the kept factorizations proved too stale)."""
        self.one_level.update(A)
        self._subdomains_factored = True
        return self

    @property
    def subdomains_factored(self) -> bool:
        """Whether the one-level part holds factorizations (of the last full :meth:`update`'s A)."""
        return self._subdomains_factored


def _same_poses(a: VertexGeometry, b: VertexGeometry) -> bool:
    return a is b or (np.array_equal(a.positions, b.positions) and np.array_equal(a.rotations, b.rotations))
