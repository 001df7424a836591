"""Discrete harmonic extension of interface values into subdomain interiors (paper Sec. 3.3).

Interior values solve A_II φ_I = −A_IΓ φ_Γ; A_II is block diagonal over subdomain interiors (every
edge lies in one subdomain), so a few factorizations (one per group of subdomains with similar
coarse-column counts) and one multi-column solve each extend every basis function at once.
"""

from __future__ import annotations

import hashlib

import numpy as np
import scipy.sparse as sp

from ..dd.decomposition import Decomposition
from ..dd.interface import Interface
from ..solvers import Submatrix, block_cholesky
from ..solvers.factory import KEEPS_ANALYSIS, factorize_local
from ..solvers.gather import pattern_of, sharing_vertex_level
from ..util import vertex_dofs
from ..util.gathered import entries
from ..util.sparse import as_csr, row_entries
from ..util.threads import WORKERS, local_threads, on_local_thread, wait_all


class CoarseBasis:
    """Φ stored with its rows permuted: ``local`` = [Φ_I; Φ_Γ] (interior rows, then interface rows),
    Φ = P·local with ``order`` = the global row of each local row. Applying Φ or Φᵀ costs one
    permutation of a vector; the interior rows are written straight from the extension's solve
    (no merge with the interface rows, no transposed copy). ``local`` may hold single-precision
    numbers (:attr:`HarmonicExtension.SINGLE_FROM`): the products then round their vector to it, and
    A_0 is assembled from the rounded Φ, so the coarse correction stays that of a fixed basis."""

    def __init__(self, local: sp.csr_matrix, order: np.ndarray, plan: dict | None = None):
        self.local, self.order = local, order
        self.shape = local.shape
        self.plan = plan  # the extension's symbolic plan it was built from (its storage is reusable with it)

    @property
    def nnz(self) -> int:
        return self.local.nnz

    @property
    def nbytes(self) -> int:
        L = self.local
        return L.data.nbytes + L.indices.nbytes + L.indptr.nbytes + self.order.nbytes

    def matvec(self, z: np.ndarray) -> np.ndarray:
        """Φ z (in Φ's precision: scipy would otherwise convert Φ itself to the vector's, a copy per
        product)."""
        y = np.empty(self.shape[0])
        L = self.local
        y[self.order] = L @ z.astype(L.dtype, copy=False)
        return y

    def rmatvec(self, x: np.ndarray) -> np.ndarray:
        """Φᵀ x (through the CSC view of the local rows; in Φ's precision, returned in double)."""
        L = self.local
        return (L.T @ x[self.order].astype(L.dtype, copy=False)).astype(np.float64, copy=False)

    def vertex_rows(self, d: int) -> np.ndarray | None:
        """The vertex of every block of ``d`` consecutive local rows, or None where the local rows
        do not come in whole vertices of ``d`` dofs each (global dofs d·v … d·v + d − 1)."""
        o = self.order
        if d < 1 or len(o) % d:
            return None
        o = o.reshape(-1, d)
        if not (np.all(o[:, 0] % d == 0) and np.all(o == o[:, :1] + np.arange(d))):
            return None
        return o[:, 0] // d

    TRANSFORM_CHUNK = 1 << 21  # entries of Φ per step of transform_vertex_rows (its temporaries)

    def transform_vertex_rows(self, T, d: int | None = None) -> None:
        """Φ ← diag(T_1, …, T_m) Φ in place, T (m, d, d) for the vertices of :meth:`vertex_rows`, or a
        function of ``d`` × ``d`` maps giving T for the positions ``idx`` among them, called for a block of
        vertices at a time: no m × d × d array beside the caller's peak (1M 2D poses: 69 MiB, and its
        factors' temporaries). Storage and pattern are kept: an entry a row of a vertex lacks is zero in
        the product when every row's pattern contains those of the rows its T mixes in, as for rigid
        modes. Vertices whose d rows share one pattern (the interiors) are multiplied as dense d × K
        blocks, those whose rows' columns are nested in their longest row's (the interface, whose
        rotation rows lack the translation columns) as dense blocks on those columns, any others entry
        by entry."""
        L = self.local
        T_of = T if callable(T) else T.__getitem__
        if not L.has_sorted_indices:
            L.sort_indices()
        d = int(d) if callable(T) else T.shape[1]
        lengths = np.diff(L.indptr).reshape(-1, d)   # in the index type: no int64 copies
        start = L.indptr[:-1:d]   # first entry of every vertex (a view)
        uniform = self._uniform_vertices(lengths, start)
        data = L.data
        K = lengths[:, 0]
        for k in np.unique(K[uniform]):  # the distinct row lengths (a few dozen at most)
            if k == 0:
                continue
            verts = np.flatnonzero(uniform & (K == k))
            step = max(1, self.TRANSFORM_CHUNK // (d * int(k)))
            for c0 in range(0, len(verts), step):   # blocks of vertices (bounded temporaries)
                v = verts[c0:c0 + step]
                at = start[v, None] + np.arange(d * int(k))   # (int64: the arange's type)
                data[at] = np.matmul(T_of(v), data[at].reshape(len(v), d, int(k))).reshape(len(v), -1)
        other = np.flatnonzero(~uniform)
        if len(other):
            other = self._transform_nested(T_of, other, start, lengths, d)
        if len(other):
            self._transform_entries(T_of, other, start, lengths, d)

    def _uniform_vertices(self, lengths: np.ndarray, start: np.ndarray) -> np.ndarray:
        """Whether the d rows of each vertex have one pattern (same lengths and columns). An
        extension's interior rows have it by construction (a row holds its subdomain's columns);
        the others are compared."""
        indices = self.local.indices
        d = lengths.shape[1]
        same = np.all(lengths == lengths[:, :1], axis=1)
        known = 0 if self.plan is None else self.plan["nI"] // d   # the interior rows' vertex blocks
        cand = known + np.flatnonzero(same[known:] & (lengths[known:, 0] > 0))
        K = lengths[cand, 0]
        first = np.repeat(start[cand], K) + (np.arange(int(K.sum())) - np.repeat(np.cumsum(K) - K, K))
        bad = np.zeros(len(first), dtype=bool)
        for i in range(1, d):
            bad |= indices[first] != indices[first + np.repeat(K, K) * i]
        owner = np.repeat(np.arange(len(cand)), K)
        same[cand[np.unique(owner[bad])]] = False
        return same

    def _transform_nested(self, T_of, verts, start, lengths, d) -> np.ndarray:
        """Vertices whose rows' columns all lie in the columns of their longest row (interface rows:
        the rotation rows hold a subset of the others' columns), multiplied as dense d × L blocks on
        those L columns: each entry placed by one search among them (``T_of``: the maps of vertex
        positions, :meth:`transform_vertex_rows`). Returns the vertices that are not nested (for
        :meth:`_transform_entries`)."""
        L = self.local
        data, indices, nc = L.data, L.indices, max(L.shape[1], 1)
        longest = lengths[verts].max(axis=1)
        ref = np.argmax(lengths[verts], axis=1)   # the first longest row of each vertex
        row_start = start[verts, None] + np.concatenate(
            [np.zeros((len(verts), 1), dtype=np.int64), np.cumsum(lengths[verts], axis=1)[:, :-1]], axis=1)
        left = []
        for length in np.unique(longest):   # the distinct lengths (a few dozen at most)
            sel = np.flatnonzero(longest == length)
            width = int(length)
            step = max(1, self.TRANSFORM_CHUNK // (2 * d * max(width, 1)))
            for c0 in range(0, len(sel), step):   # blocks of vertices (bounded temporaries)
                g = sel[c0:c0 + step]
                v, m = verts[g], len(g)
                ref_at = row_start[g, ref[g]][:, None] + np.arange(width)   # the union's columns
                ref_key = (np.arange(m)[:, None] * np.int64(nc) + indices[ref_at]).ravel()
                n_v = lengths[v].sum(axis=1)
                ends = np.cumsum(n_v)
                pos = np.repeat(start[v] - (ends - n_v), n_v) + np.arange(int(ends[-1]))
                local_v = np.repeat(np.arange(m), n_v)
                i = np.repeat(np.tile(np.arange(d), m), lengths[v].ravel())
                key = local_v * np.int64(nc) + indices[pos]
                at = np.minimum(np.searchsorted(ref_key, key), len(ref_key) - 1)
                hit = ref_key[at] == key
                if not hit.all():   # not nested: those vertices go entry by entry
                    bad = np.zeros(m, dtype=bool)
                    bad[local_v[~hit]] = True
                    left.append(v[bad])
                    keep = ~bad[local_v]
                    pos, local_v, i, at = pos[keep], local_v[keep], i[keep], at[keep]
                    if not len(pos):
                        continue
                col = at - local_v * width   # place among the vertex's union columns
                D = np.zeros((m, d, width))
                D[local_v, i, col] = data[pos]
                D = np.matmul(T_of(v), D)
                data[pos] = D[local_v, i, col]
        return np.sort(np.concatenate(left)) if left else np.zeros(0, dtype=np.int64)

    def _transform_entries(self, T_of, verts, start, lengths, d) -> None:
        """The general case of :meth:`transform_vertex_rows` for the rows of ``verts``: every entry
        (v, i, c) ← Σ_k T_v[i, k] Φ[(v, k), c], the entry of row k in column c found by a search of
        the sorted (row, column) keys (0 where row k has no entry there); in blocks of vertices."""
        L = self.local
        data, indices, nc = L.data, L.indices, max(L.shape[1], 1)
        n_v = lengths[verts].sum(axis=1)
        ends = np.cumsum(n_v)
        c0 = 0
        while c0 < len(verts):   # a loop over blocks of vertices (bounded temporaries)
            base = int(ends[c0 - 1]) if c0 else 0
            c1 = max(c0 + 1, int(np.searchsorted(ends, base + self.TRANSFORM_CHUNK // 2, side="right")))
            v, n = verts[c0:c1], n_v[c0:c1]
            pos = np.repeat(start[v] - (ends[c0:c1] - n - base), n) + np.arange(int(n.sum()))
            Tv = T_of(v)
            mixes = np.any(Tv != 0.0, axis=0) & ~np.eye(d, dtype=bool)   # (i, k ≠ i) pairs this block's T mixes
            local = np.repeat(np.arange(len(v) * d), lengths[v].ravel())   # the block's rows
            vertex, i = np.divmod(local, d)   # (positions in v)
            row = v[vertex] * d + i
            col = indices[pos].astype(np.int64)
            key = row * nc + col
            old = data[pos]
            new = Tv[vertex, i, i] * old   # k = i: the entry itself
            for k in range(d):
                sel = np.flatnonzero(mixes[i, k])
                if not len(sel):
                    continue
                want = (v[vertex[sel]] * d + k) * nc + col[sel]
                at = np.minimum(np.searchsorted(key, want), len(key) - 1)
                new[sel] += np.where(key[at] == want, Tv[vertex[sel], i[sel], k] * old[at], 0.0)
            data[pos] = new
            c0 = c1

    def tocsr(self) -> sp.csr_matrix:
        """Φ in global row order (a copy: for tests, plots and other back-ends)."""
        inverse = np.empty_like(self.order)
        inverse[self.order] = np.arange(len(self.order))
        return sp.csr_matrix(self.local[inverse])


def column_groups(K_sub: np.ndarray, weight: np.ndarray, max_groups: int = 3) -> np.ndarray:
    """Group of every subdomain for the extension's solves: subdomains with K_i columns solved
    together at their group's largest K_i, the thresholds chosen to minimize Σ_g |I_g|·K_g (at
    most ``max_groups``; one factorization per group, their sum the same as one)."""
    K_sub = np.asarray(K_sub)
    u = np.unique(K_sub)
    if len(u) <= 1 or max_groups <= 1:
        return np.zeros(len(K_sub), dtype=np.int64)
    W = np.cumsum(np.bincount(np.searchsorted(u, K_sub), weights=weight, minlength=len(u)))  # weight with K ≤ u[j]
    a, b = np.meshgrid(np.arange(len(u)), np.arange(len(u)), indexing="ij")
    cost = W[a] * u[a] + (W[b] - W[a]) * u[b] + (W[-1] - W[b]) * u[-1]
    if max_groups == 2:
        cost = np.where(a == b, cost, np.inf)
    cost = np.where(a <= b, cost, np.inf)
    i, j = np.unravel_index(int(np.argmin(cost)), cost.shape)
    return (K_sub > u[i]).astype(np.int64) + (K_sub > u[j]).astype(np.int64)


def _rows_to_csr(X: np.ndarray, k_row: np.ndarray, out: np.ndarray, rows_per_block: int = 2048) -> None:
    """out = the first k_row[r] entries of every row r of X, row after row (CSR data). X is
    column-major (CHOLMOD's solution): it is read in blocks of rows made row-major in cache, not
    entry by entry across columns, and with no whole-size temporary (fresh pages: 2D 360 000 poses
    0.58 → 0.38 s per build)."""
    K = X.shape[1]
    k = np.arange(K)
    at = 0
    for r0 in range(0, X.shape[0], rows_per_block):  # a loop over blocks of rows (a few hundred)
        r1 = min(r0 + rows_per_block, X.shape[0])
        kr = k_row[r0:r1]
        block = np.ascontiguousarray(X[r0:r1])[k[None, :] < kr[:, None]]
        out[at:at + len(block)] = block
        at += len(block)


def _phi_rows(local: sp.csr_matrix, blocks: np.ndarray, d: int, ncp: int):
    """Φ's local rows of the vertex blocks ``blocks`` (d rows each) in double precision, ``ncp``
    columns: CSR for d = 1, BSR of d×d blocks otherwise."""
    rows = (blocks[:, None] * d + np.arange(d)).ravel() if d > 1 else blocks
    at, indptr = row_entries(local, rows)
    R = sp.csr_matrix((local.data[at].astype(np.float64), local.indices[at], indptr), shape=(len(rows), ncp))
    return R if d == 1 else R.tobsr((d, d))


class _Group:
    """The interior dofs of some subdomains, their A_II and A_IΓ gathers and A_II's factorization."""

    def __init__(self, interior: np.ndarray, sub: np.ndarray, gamma: np.ndarray, n: int,
                 offsets: np.ndarray | None = None, ordered: bool = False):
        self.interior, self.sub = interior, sub
        self.ordering = "natural" if ordered else None  # interior rows already in a fill-reducing order
        self._shared: dict = {}   # the interior rows' entries, found once for both gathers
        self.offsets = offsets
        self.A_II = Submatrix(interior, interior, n, self._shared, offsets)
        self.A_IG = Submatrix(interior, gamma, n, self._shared, offsets)
        self.factor = None
        self._same = None  # prepare's finding: the factor's analysis applies to A (None: not prepared)

    def prepare(self, A) -> None:
        """A_II's positions for A (symbolic; the groups one after the other) and whether the factor's
        analysis still applies, for a :meth:`refactor` that may then run on another thread."""
        self._same = self.A_II.renew(A)[1]

    def refactor(self, A, block_dtype=None):
        """A_II's factor for A's numbers; by dense vertex blocks in ``block_dtype`` where it applies."""
        if self._same is None:
            self.prepare(A)
        A_II = self.A_II(A)
        same, self._same = self._same, None
        if same and isinstance(self.factor, KEEPS_ANALYSIS) and getattr(self.factor, "dtype", None) in (None, block_dtype):
            self.factor.refactor(A_II)  # same pattern: numbers only (the analysis is kept by release)
        else:   # simplicial where CHOLMOD would choose it: its solves then run on the local threads
            self.factor = factorize_local(A_II, "the interior matrix A_II", natural=self.ordering == "natural",
                                          block=block_cholesky.vertex_block(self.offsets), block_dtype=block_dtype)

    def solve(self, B: np.ndarray) -> np.ndarray:
        """A_II⁻¹ B (F-ordered n_I × k), the columns split over the local threads where the factor allows."""
        if getattr(self.factor, "releases_gil", False):
            return self.factor.solve(B, local_threads())
        return self.factor(B)

    def release(self) -> None:
        """Drop the factor's numbers and the gathers' positions; keep the symbolic analysis."""
        if isinstance(self.factor, KEEPS_ANALYSIS):
            self.factor.release_numeric()
        else:
            self.factor = None
        self.A_II.forget()
        self.A_IG.forget()
        self._shared.clear()


def _digest(*arrays: np.ndarray) -> bytes:
    """A fingerprint of the interface values' pattern (copies of it took 120 MB at 91 125 3D poses)."""
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(memoryview(a).cast("B"))
    return h.digest()


def _symmetric_part(A0: sp.spmatrix) -> sp.csr_matrix:
    """(A₀ + A₀ᵀ)/2: A₀ symmetric to rounding (the mean with its transpose, scaled in place)."""
    A0 = (A0 + A0.T).tocsr()
    A0.data *= 0.5
    return A0


# interior rows are factorized in pieces of at most about 1/GROUP_PIECES of them (whole subdomains):
# jobs the local threads share evenly
GROUP_PIECES = 2 * WORKERS


class HarmonicExtension:
    """Φ = [Φ_Γ; −A_II⁻¹ A_IΓ Φ_Γ] and A_0 = Φᵀ A Φ for one decomposition and interface.

    Interior and interface dofs, the patterns of A_II, A_IΓ and A_Γ·, the symbolic factorization
    of A_II and the pattern of Φ are computed once and reused for every new matrix with the same
    pattern. The right-hand sides are compressed: subdomain i only sees the K_i coarse columns whose
    subdomain set contains i. Subdomains are solved in up to ``max_groups`` groups of similar K_i
    (:func:`column_groups`), each group one factorization of its block-diagonal A_II and one solve
    with its largest K_i columns, in blocks of at most ``block_columns`` columns (None: all at once)
    to bound the memory. ``vertex_order``: (vertices, their subdomains), every subdomain's vertices
    in a fill-reducing order (the one-level blocks'); the interior dofs then follow it, and A_II is
    factorized in that order (the order it induces on a subset has no more fill than on the whole).
    """

    # Φ's numbers in single precision from this many entries: the largest array a two-level
    # preconditioner holds after the subdomain factors (1M 2D lawnmower poses: 36.9M entries, 148 MiB
    # saved); the same CG counts to 1e-10 on lawnmower 600x600 (13.2M entries), and its products'
    # vectors rounded to it cost nothing measurable (docs/survey.md, thirty-sixth pass)
    SINGLE_FROM = 4_000_000

    def __init__(self, decomposition: Decomposition, interface: Interface, block_columns: int | None = None,
                 max_groups: int = 3, vertex_order: tuple[np.ndarray, np.ndarray] | None = None):
        offsets = decomposition.structure.offsets
        self.offsets = offsets
        self.n = decomposition.structure.n_dofs
        owner_dof = np.repeat(interface.interior_subdomain, np.diff(offsets))  # −1 on Γ
        self._interior_subdomain = interface.interior_subdomain
        self.interior = np.flatnonzero(owner_dof >= 0)
        self.ordered = False
        self.gamma = np.flatnonzero(owner_dof < 0)
        self.sub = owner_dof[self.interior]
        if vertex_order is not None:
            self.order_interiors(vertex_order)
        self.block_columns, self.max_groups = block_columns, max_groups
        self.keep_factors = True  # False: each group's A_II factorization is dropped after its solve
        # called once every group is extended (its factors dropped where not kept), before A_0: a
        # caller's work that should not sit beside the interior factors starts there
        self.on_extended = None
        self.groups: list[_Group] = []
        self.order = None  # rows of Φ's local storage: the groups' interior dofs, then Γ
        self._local_row = None  # Φ's local row of every global dof (the inverse of ``order``)
        self._cached = None  # (signature of the interface values, plan, A's pattern, read-only value arrays)
        dims = np.unique(np.diff(offsets))
        self.vertex_dofs = int(dims[0]) if len(dims) == 1 else 1  # dofs of every vertex (1: not all the same)
        self._block = 1  # d where Φ's local rows come in whole vertices (set by the plan): A_0 in blocks

    def order_interiors(self, vertex_order: tuple[np.ndarray, np.ndarray]) -> None:
        """Put the interior dofs in ``vertex_order`` (vertices, their subdomains): each interior vertex
        where it lies in its own subdomain's fill-reducing order (before the first extension)."""
        vertices, subdomain = vertex_order
        owner = self._interior_subdomain
        own = vertices[owner[vertices] == subdomain]
        if len(own) == np.count_nonzero(owner >= 0):
            self.interior, self.ordered = vertex_dofs(own, self.offsets), True
            self.sub = owner[own].repeat(np.diff(self.offsets)[own])

    def _make_groups(self, col_subdomains) -> sp.csr_matrix:
        """The groups of :meth:`_plan` (``self.groups``: interior rows and subdomains, no numbers);
        returns the subdomain × column pattern P the rest of the plan reads. Made first so that the
        groups' factorizations can start while the plan goes on."""
        P = sp.csr_matrix(col_subdomains.T)  # subdomain × column
        P.sort_indices()
        group_of_sub = column_groups(np.diff(P.indptr), np.bincount(self.sub, minlength=P.shape[0]), self.max_groups)
        in_group = group_of_sub[self.sub]
        pieces = []
        for g in np.unique(in_group):  # at most max_groups
            pieces += self._pieces(np.flatnonzero(in_group == g))
        pieces.sort(key=len, reverse=True)   # the largest first: the local threads then end together
        self.groups = [_Group(self.interior[rows], self.sub[rows], self.gamma, self.n, self.offsets, self.ordered)
                       for rows in pieces]
        return P

    def _pieces(self, rows: np.ndarray) -> list[np.ndarray]:
        """A group's interior rows in pieces of whole subdomains, each at most about 1/GROUP_PIECES of
        all interior rows (their factorizations are the jobs of the local threads: a group of half the
        interior would keep one thread busy while the other waits; each row keeps its place, so a
        subdomain's rows stay in its fill-reducing order)."""
        k = int(np.ceil(GROUP_PIECES * len(rows) / max(len(self.interior), 1)))
        if k <= 1:
            return [rows]
        sub = self.sub[rows]
        size = np.bincount(sub)
        before = np.cumsum(size) - size   # rows of the group's subdomains numbered lower
        piece = np.minimum((before * k) // len(rows), k - 1)[sub]
        return [rows[piece == j] for j in range(k) if np.any(piece == j)]

    def _plan(self, gamma_rows, gamma_cols, col_subdomains, P: sp.csr_matrix) -> dict:
        """Symbolic part of one extension after :meth:`_make_groups` (which gave ``P``): the pattern of
        Φ_Γ (interface rows) and of Φ's local rows, and the compressed column of each (subdomain, coarse
        column) pair."""
        nc = col_subdomains.shape[0]
        counts = np.diff(P.indptr)
        pair_sub = np.repeat(np.arange(P.shape[0]), counts)
        idx = np.int32 if max(nc, self.n) < 2**31 - 1 else np.int64
        table = np.zeros((P.shape[0], max(int(counts.max()), 1)), dtype=idx)
        table[pair_sub, np.arange(len(P.indices)) - P.indptr[pair_sub]] = P.indices
        # Φ_Γ's entries in (interface row, column) order: rows by a map of Γ, one stable sort of the
        # combined key (the entries come nearly sorted; 32 768 3D poses: 0.12 s against 0.35 s for a
        # binary search of Γ and a lexsort)
        where = np.empty(self.n, dtype=np.int32 if len(self.gamma) < 2**31 - 1 else np.int64)
        where[self.gamma] = np.arange(len(self.gamma))
        gpos = where[gamma_rows]
        del where
        g_order = np.argsort(gpos.astype(np.int64) * max(nc, 1) + gamma_cols, kind="stable")
        if len(g_order) < 2**31 - 1:
            g_order = g_order.astype(np.int32)
        ptr_G = np.searchsorted(gpos[g_order], np.arange(len(self.gamma) + 1))
        plans, indices, k_rows = [], [], []
        for group in self.groups:  # the column groups' pieces (a few)
            k_row = counts[group.sub]
            K, nI = int(k_row.max()), len(group.interior)
            prefix = np.arange(K)[None, :] < k_row[:, None]
            indices.append(table[group.sub, :K][prefix])  # Φ_I: row r holds its subdomain's K_i columns
            k_rows.append(k_row)
            plans.append({"K": K, "nI": nI, "k_row": k_row, "target": None})
        nnz_I = sum(len(i) for i in indices)
        indptr = np.r_[0, np.cumsum(np.concatenate(k_rows)), nnz_I + ptr_G[1:]].astype(np.int64)
        offset = 0
        for plan, ind in zip(plans, indices):
            plan["offset"], plan["row_start"] = offset, np.r_[0, np.cumsum(plan["k_row"])]
            offset += len(ind)
        self.order = np.r_[np.concatenate([grp.interior for grp in self.groups]), self.gamma]
        self._local_row = np.empty(self.n, dtype=np.int32 if self.n < 2**31 - 1 else np.int64)
        self._local_row[self.order] = np.arange(self.n)
        d = self.vertex_dofs
        whole = d > 1 and len(self.order) % d == 0 and len(self.interior) % d == 0
        if whole:
            o = self.order.reshape(-1, d)
            whole = bool(np.all(o[:, 0] % d == 0) and np.all(o[:, 1:] == o[:, :1] + np.arange(1, d)))
        self._block = d if whole else 1
        indices = np.r_[np.concatenate(indices), gamma_cols[g_order].astype(idx)]
        if indptr[-1] < 2**31 - 1:
            indptr = indptr.astype(np.int32)
        return {"groups": plans, "nI": len(self.interior), "nnz_I": nnz_I, "g_order": g_order,
                "indices": indices, "indptr": indptr, "ptr_G": ptr_G, "nc": nc,
                "pair_key": pair_sub * np.int64(nc) + P.indices, "local_k": np.arange(len(P.indices)) - P.indptr[pair_sub]}

    def columns_per_block(self, K: int) -> int:
        return K if self.block_columns is None else max(1, min(K, int(self.block_columns)))

    def _targets(self, group: _Group, R: sp.csr_matrix, plan: dict, gplan: dict) -> np.ndarray:
        """Position k·n_I + r in the compressed right-hand side of every entry (r, column) of
        R = A_IΓ Φ_Γ: k is the column's place among the K_i columns of row r's subdomain."""
        nI, nc = gplan["nI"], plan["nc"]
        rows = np.repeat(np.arange(nI), np.diff(R.indptr))
        key = group.sub[rows] * np.int64(nc) + R.indices
        pair_key = plan["pair_key"]
        at = np.minimum(np.searchsorted(pair_key, key), len(pair_key) - 1)
        if np.any(pair_key[at] != key):
            raise AssertionError("interface coupling outside its subdomain: decomposition is inconsistent")
        dtype = np.int32 if gplan["K"] * nI < 2**31 - 1 else np.int64
        return (plan["local_k"][at] * np.int64(nI) + rows).astype(dtype)

    @staticmethod
    def interior_factor_dtype(single: bool):
        """The interior factors' precision where they are made by vertex blocks (None: CHOLMOD's):
        for a Φ in single precision (:attr:`SINGLE_FROM`), which needs no more from its extension,
        :data:`.block_cholesky.PRECISION`."""
        return block_cholesky.PRECISION if single else None

    def _start_factorizations(self, A, dtype) -> list | None:
        """The groups' A_II gathered and factorized side by side on the local threads (CHOLMOD holds
        no GIL; lawnmower 1000x1000: 1.9 -> 1.1 s), each group's positions on its thread too (one
        group's beside another's factorization): all interior factors at once, as the memory estimate
        counts. Their futures; None (nothing started) for one group or on a local thread."""
        if len(self.groups) <= 1 or on_local_thread():
            return None
        pool = local_threads()
        return [pool.submit(group.refactor, A, dtype) for group in self.groups]

    def _extend(self, group: _Group, A_IG: sp.csr_matrix, Phi_G: sp.csr_matrix, plan: dict, gplan: dict,
                data: np.ndarray) -> None:
        """One group's Φ_I = −A_II⁻¹ A_IΓ Φ_Γ into data (row-major), a block of columns of the
        compressed right-hand side at a time. A_IΓ Φ_Γ is one sparse product; where its entries go
        in the compressed right-hand side is found once, from the product's structural pattern
        (scipy's product keeps that pattern and order unless an entry cancels to exactly zero, and
        then the positions are found anew)."""
        K, nI = gplan["K"], gplan["nI"]
        R = A_IG @ Phi_G
        target = gplan["target"]
        if target is None:  # the structural pattern: the same product of all-ones matrices
            ones = lambda M: sp.csr_matrix((np.ones(M.nnz), M.indices, M.indptr), shape=M.shape)
            structural = ones(A_IG) @ ones(Phi_G)
            target = gplan["target"] = self._targets(group, structural, plan, gplan)
            del structural
        if R.nnz != len(target):  # an exact cancellation dropped entries: positions for this product
            target = self._targets(group, R, plan, gplan)
        values = -R.data
        del R
        k_row = gplan["k_row"]
        out = data[gplan["offset"]:gplan["offset"] + gplan["row_start"][-1]]
        width = self.columns_per_block(K)
        for k0 in range(0, K, width):  # a loop over blocks of coarse columns (one when memory allows)
            k1 = min(K, k0 + width)
            B = np.zeros((k1 - k0) * nI)
            if k0 == 0 and k1 == K:
                B[target] = values
            else:
                keep = (target >= k0 * nI) & (target < k1 * nI)
                B[target[keep] - k0 * nI] = values[keep]
                del keep
            X = group.solve(B.reshape(k1 - k0, nI).T)  # F-ordered nI × (k1 − k0)
            del B
            if k0 == 0 and k1 == K:
                _rows_to_csr(X, k_row, out)  # row-major prefix of every row: Φ_I's CSR order
            else:
                sel = np.arange(k0, k1)[None, :] < k_row[:, None]
                out[(gplan["row_start"][:-1, None] + np.arange(k0, k1)[None, :])[sel]] = X[sel]
                del sel
            del X

    def __call__(self, A: sp.spmatrix, gamma_rows: np.ndarray, gamma_cols: np.ndarray,
                 gamma_vals: np.ndarray, col_subdomains: sp.csr_matrix,
                 recycle: CoarseBasis | None = None) -> tuple[CoarseBasis, sp.csr_matrix]:
        """(Φ, A_0) for interface values given as triplets (global dof, column, value).

        ``recycle``: a previous Φ of this extension that its owner no longer uses; its storage is
        overwritten when the pattern is the same (memory already paged in: fresh pages cost up to
        10 ms/MiB on the benchmark machines, 2.4 s for Φ at 360 000 2D poses)."""
        n, nc = self.n, col_subdomains.shape[0]
        A = as_csr(A)
        if nc == 0 or len(self.interior) == 0:
            Phi_G = sp.csr_matrix((gamma_vals, (gamma_rows, gamma_cols)), shape=(n, nc))
            return CoarseBasis(Phi_G, np.arange(n)), (Phi_G.T @ A @ Phi_G).tocsr()
        if not A.has_sorted_indices:
            A = A.sorted_indices()
        col_subdomains = sp.csr_matrix(col_subdomains)
        arrays = (gamma_rows, gamma_cols, col_subdomains.indptr, col_subdomains.indices)
        cached = self._cached
        # the coarse space's cached (read-only) pattern again: no digest; other arrays are not kept
        same = cached is not None and cached[3] is not None and all(a is b for a, b in zip(arrays, cached[3]))
        signature = cached[0] if same else _digest(*arrays)
        with sharing_vertex_level():   # the groups' gathers read A's vertex level once
            started = None
            if cached is None or not cached[2].matches(A) or cached[0] != signature:
                self._cached = None
                frozen = not any(a.flags.writeable for a in arrays)
                P = self._make_groups(col_subdomains)
                # Φ's entries: each interior row holds its subdomain's columns (the plan's count)
                single = int(np.diff(P.indptr)[self.sub].sum()) + len(gamma_vals) >= self.SINGLE_FROM
                # a new plan: the groups' factorizations start now and run while the rest of the
                # plan is made (1M 2D poses: 0.36 s on this thread)
                started = self._start_factorizations(A, self.interior_factor_dtype(single))
                try:
                    plan = self._plan(gamma_rows, gamma_cols, col_subdomains, P)
                except BaseException:
                    for job in started or ():
                        job.exception()   # ended (the plan's error is the one raised)
                    raise
                self._cached = cached = (signature, plan, pattern_of(A), arrays if frozen else None)
            plan = cached[1]
            dtype = np.float32 if len(plan["indices"]) >= self.SINGLE_FROM else np.float64
            factor_dtype = self.interior_factor_dtype(dtype == np.float32)
            reuse = (recycle is not None and recycle.plan is plan and recycle.local.data.shape == plan["indices"].shape
                     and recycle.local.data.dtype == dtype)
            data = recycle.local.data if reuse else np.empty(len(plan["indices"]), dtype=dtype)
            del recycle
            Phi_G = sp.csr_matrix((gamma_vals[plan["g_order"]], plan["indices"][plan["nnz_I"]:], plan["ptr_G"]),
                                  shape=(len(self.gamma), nc))
            side_by_side = len(self.groups) > 1 and not on_local_thread()
            if side_by_side:
                wait_all(started if started is not None else self._start_factorizations(A, factor_dtype))
            for group, gplan in zip(self.groups, plan["groups"]):
                if not side_by_side:
                    group.refactor(A, factor_dtype)
                self._extend(group, group.A_IG(A), Phi_G, plan, gplan, data)
                if not self.keep_factors:  # the next refactor finds the gathers' positions again
                    group.release()
            if self.on_extended is not None:   # while A's vertex level is still shared
                self.on_extended()
        data[plan["nnz_I"]:] = gamma_vals[plan["g_order"]]
        local = sp.csr_matrix((data, plan["indices"], plan["indptr"]), shape=(n, nc))
        # (AΦ)_I = A_II Φ_I + A_IΓ Φ_Γ = 0 for the harmonic extension, so Φᵀ A Φ = Φ_Γᵀ (AΦ)_Γ:
        # only the interface rows of A enter (Φ is dense on subdomain interiors; A Φ would not be)
        # in blocks of interface rows: A_Γ·Φ (|Γ| × n_c, K_i columns per row) never exists whole
        return CoarseBasis(local, self.order, plan), self._coarse_matrix(A, local, plan["nI"])

    def _coarse_matrix(self, A: sp.csr_matrix, local: sp.csr_matrix, nI: int) -> sp.csr_matrix:
        """A_0 = Σ_blocks Φ_Γᵀ (A_Γ·Φ) over blocks of interface rows, each product in double precision
        with only the rows of Φ its block of A_Γ reads (no whole copy of Φ: in d×d blocks it was one
        of ~9.5 bytes per entry, 350 MiB at 1M 2D poses; a single-precision Φ would be converted
        whole by every product). Where Φ's local rows come in whole vertices of d dofs the products
        are in d×d blocks (BSR: one index per block of a vertex's dofs; 3D survey 32x32x32: 0.67 s
        against 1.33 s for the CSR products), its columns padded to a multiple of d."""
        d, nc = self._block, local.shape[1]
        ncp = -(-nc // d) * d
        step = -(-self.a0_block_rows(len(self.gamma)) // d) * d
        A0 = None
        for r0 in range(0, len(self.gamma), step):
            r1 = min(r0 + step, len(self.gamma))
            B = self._interface_rows(A, r0, r1)   # A_Γ's rows, columns numbered as Φ's local rows
            vertex = B.indices // d
            blocks = np.unique(vertex)   # the vertex blocks of Φ's rows it reads
            B = sp.csr_matrix((B.data, np.searchsorted(blocks, vertex) * d + B.indices % d, B.indptr),
                              shape=(r1 - r0, d * len(blocks)))
            del vertex
            X = (B if d == 1 else B.tobsr((d, d))) @ _phi_rows(local, blocks, d, ncp)   # (A_Γ·Φ) for these rows
            del B
            G = _phi_rows(local, np.arange((nI + r0) // d, (nI + r1) // d), d, ncp)   # Φ_Γ's rows r0:r1
            # (A_Γ·Φ)ᵀ Φ_Γ = A_0ᵀ in CSR: the big product's transpose is a free CSC view, and only Φ_Γ's
            # few entries per row are converted (Φ_Γᵀ·(A_Γ·Φ) converted the product: 1 s at 91k poses)
            part = (X.T @ G).tocsr() if d == 1 else (G.T @ X).tocsr()
            del X, G
            A0 = part if A0 is None else A0 + part
            del part
        if A0 is None:
            A0 = sp.csr_matrix((nc, nc))
        if ncp != nc:
            A0 = A0[:nc, :nc]
        return _symmetric_part(A0)

    def _interface_rows(self, A: sp.csr_matrix, r0: int, r1: int) -> sp.csr_matrix:
        """Rows Γ[r0:r1] of A, their columns numbered as Φ's local rows: entries taken by row
        ranges, nothing kept between builds (a scipy submatrix with stored positions took 2.6 s per
        build at 91 125 3D poses in the low-memory mode, which drops them; this takes ~0.1 s)."""
        rows = self.gamma[r0:r1]
        at, indptr = row_entries(A, rows)
        B = sp.csr_matrix((entries(A, at), self._local_row[A.indices[at]], indptr), shape=(len(rows), self.n))
        B.has_sorted_indices = False  # (renumbered columns; scipy's product does not need them sorted)
        return B

    A0_BLOCKS = 8  # at most this many blocks of interface rows for A_0 (each block's A_Γ·Φ 1/8 of the whole)
    A0_MIN_BLOCK_ROWS = 20000  # smaller interfaces: one product (3D 32x32x32: |Γ| 114k rows, 6 blocks)

    @classmethod
    def a0_block_rows(cls, n_gamma: int) -> int:
        """Interface rows per block of A_0's assembly."""
        blocks = min(cls.A0_BLOCKS, max(1, n_gamma // cls.A0_MIN_BLOCK_ROWS))
        return max(1, -(-n_gamma // blocks))
