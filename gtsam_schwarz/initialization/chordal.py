"""Chordal initialization of pose graphs: R = proj_SO(d)(argmin Σ w_ij‖R_j − R_i R_ij‖_F²), then
p = argmin Σ ‖p_j − p_i − R_i t_ij‖²_W (g2o/GTSAM: x_j = x_i ∘ z_ij); pure numpy/scipy, no gtsam.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph
from scipy.sparse.linalg import splu

from ..krylov import pcg_columns, threaded
from ..solvers.cost import counted_simplicially, record_column_counts
from ..solvers.sparse import SparseCholesky
from ..util import sorted_unique
from ..util.blas import blas_limits

__all__ = ["ChordalResult", "chordal_initialization", "pose2_from", "project_to_so"]

SOLVERS = ("cg", "direct")
PRECONDITIONERS = ("schwarz", "tree", "jacobi", "none")
ROTATION_METHODS = ("chordal", "lago")
TRANSLATION_WEIGHTS = ("information", "diagonal", "isotropic")


@dataclass
class ChordalResult:
    """Initial poses x_i = (R_i, p_i): ``rotations`` (n,d,d), ``positions`` (n,d); ``info`` holds
    CG iterations per system, seconds, anchors and components."""

    rotations: np.ndarray
    positions: np.ndarray
    info: dict = field(default_factory=dict)


def pose2_from(result: ChordalResult) -> np.ndarray:
    """(n,3) rows (x, y, θ) with θ = atan2(R₁₀, R₀₀) of a 2D :class:`ChordalResult`."""
    R = np.asarray(result.rotations)
    if R.shape[1:] != (2, 2):
        raise ValueError(f"pose2_from needs 2D rotations (n,2,2), got {R.shape}")
    theta = np.arctan2(R[:, 1, 0], R[:, 0, 0])
    return np.column_stack([result.positions, theta])


def project_to_so(M: np.ndarray) -> np.ndarray:
    """Nearest rotations argmin_{R∈SO(d)} ‖R − M_k‖_F = U diag(1,…,det UVᵀ) Vᵀ, M (k,d,d)."""
    if M.shape[1:] == (2, 2):  # 2D: the rotation part (a, b) of M = aI + bJ + (reflection), normalized
        a = M[:, 0, 0] + M[:, 1, 1]
        b = M[:, 1, 0] - M[:, 0, 1]
        r = np.hypot(a, b)
        if np.all(r > 0):
            c, s = a / r, b / r
            return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    U, _, Vt = np.linalg.svd(M)
    det = np.linalg.det(U @ Vt)
    U = U.copy()
    U[:, :, -1] *= np.where(det < 0, -1.0, 1.0)[:, None]
    return U @ Vt


# ----------------------------------------------------------------------------------------------
# input handling


def _edge_weights(information, m: int, d: int, mode: str = "information") -> tuple[np.ndarray, np.ndarray]:
    """Rotation weights w_ij (m,) = tr(Ω_RR)/dim and translation weights Ω_tt (m,d,d) in the frame
    of the measurement (GTSAM tangent order: Pose2 (x,y,θ), Pose3 (ω,v)); ``mode`` "diagonal" or
    "isotropic" (tr(Ω_tt)/d · I) drop the translation correlations."""
    w_rot, W_t = _edge_information(information, m, d)
    if mode == "diagonal":
        W_t = W_t * np.eye(d)
    elif mode == "isotropic":
        W_t = (np.trace(W_t, axis1=1, axis2=2) / d)[:, None, None] * np.eye(d)
    elif mode != "information":
        raise ValueError(f"unknown translation_weights {mode!r}; "
                         f"choose one of {', '.join(TRANSLATION_WEIGHTS)}")
    return w_rot, W_t


def _edge_information(information, m: int, d: int) -> tuple[np.ndarray, np.ndarray]:
    """(w_rot, Ω_tt) from None (unit), (m,) weights, (dof,dof) or (m,dof,dof) information, or the
    pair (w_rot (m,), Ω_tt (m,d,d)) itself (symmetric blocks)."""
    dof = 3 if d == 2 else 6
    if information is None:
        return np.ones(m), np.broadcast_to(np.eye(d), (m, d, d)).copy()
    if isinstance(information, tuple):
        if len(information) != 2:
            raise ValueError("split information must be the pair (rotation weights (m,), translation blocks (m,d,d))")
        w_rot, W_t = (np.asarray(a, dtype=float) for a in information)
        if w_rot.shape != (m,) or W_t.shape != (m, d, d):
            raise ValueError(f"split information must have shapes ({m},) and ({m},{d},{d}), "
                             f"got {w_rot.shape} and {W_t.shape}")
        if not np.array_equal(W_t, np.swapaxes(W_t, 1, 2)):
            raise ValueError("split translation information blocks must be symmetric")
        return w_rot, W_t
    info = np.asarray(information, dtype=float)
    if info.ndim == 1:  # scalar weight per edge
        if info.shape != (m,):
            raise ValueError(f"scalar weights must have shape ({m},), got {info.shape}")
        return info.copy(), info[:, None, None] * np.eye(d)
    if info.shape == (dof, dof):
        info = np.broadcast_to(info, (m, dof, dof))
    if info.shape != (m, dof, dof):
        raise ValueError(f"information must be (m,{dof},{dof}) (or (m,) weights), got {info.shape}")
    if d == 2:
        w_rot, W_t = info[:, 2, 2].copy(), info[:, :2, :2].copy()
    else:
        w_rot, W_t = np.trace(info[:, :3, :3], axis1=1, axis2=2) / 3.0, info[:, 3:, 3:].copy()
    W_t = 0.5 * (W_t + np.swapaxes(W_t, 1, 2))
    return w_rot, W_t


def _as_pose(pose, d: int) -> tuple[np.ndarray, np.ndarray]:
    """(R, p) from None (identity), a pair (R, p), a (d+1)×(d+1) homogeneous matrix or, for d = 2,
    (x, y, θ)."""
    if pose is None:
        return np.eye(d), np.zeros(d)
    if isinstance(pose, (tuple, list)) and len(pose) == 2:
        R, p = np.asarray(pose[0], dtype=float), np.asarray(pose[1], dtype=float)
    else:
        a = np.asarray(pose, dtype=float)
        if a.shape == (d + 1, d + 1):
            R, p = a[:d, :d], a[:d, d]
        elif d == 2 and a.shape == (3,):
            c, s = np.cos(a[2]), np.sin(a[2])
            R, p = np.array([[c, -s], [s, c]]), a[:2]
        else:
            raise ValueError(f"cannot read an anchor pose of dimension {d} from shape {a.shape}")
    if R.shape != (d, d) or p.shape != (d,):
        raise ValueError(f"anchor pose must be (R {d}x{d}, p {d}), got {R.shape}, {p.shape}")
    if not np.allclose(R.T @ R, np.eye(d), atol=1e-8) or np.linalg.det(R) <= 0:
        raise ValueError("anchor rotation is not in SO(d)")
    return R, p


def _anchors(n: int, edges: np.ndarray, anchor, anchor_pose, d: int):
    """One anchor per connected component (the given one for its component, else the component's
    lowest index) and the fixed (R, p) of each."""
    adj = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    ncomp, labels = csgraph.connected_components(adj, directed=False)
    if np.ndim(anchor) == 0:
        a = int(anchor)
        if not 0 <= a < n:
            raise ValueError(f"anchor {a} out of range 0..{n - 1}")
        _, first = sorted_unique(labels, return_index=True)  # lowest index of every component
        first[labels[a]] = a
        anchors = first
        R_fix = np.broadcast_to(np.eye(d), (ncomp, d, d)).copy()
        p_fix = np.zeros((ncomp, d))
        R_fix[labels[a]], p_fix[labels[a]] = _as_pose(anchor_pose, d)
    else:
        anchors = np.asarray(anchor, dtype=np.int64).ravel()
        if anchors.size and (anchors.min() < 0 or anchors.max() >= n):
            raise ValueError("anchor index out of range")
        if anchors.size != ncomp or np.unique(labels[anchors]).size != ncomp:
            raise ValueError(f"need exactly one anchor per connected component ({ncomp} components)")
        if anchor_pose is None:
            poses = [None] * anchors.size
        elif isinstance(anchor_pose, (tuple, list)) and len(anchor_pose) == anchors.size:
            poses = list(anchor_pose)
        else:
            raise ValueError("with several anchors give anchor_pose as a list with one pose per anchor")
        pairs = [_as_pose(p, d) for p in poses]  # one per component, not per pose
        R_fix = np.array([r for r, _ in pairs]).reshape(-1, d, d)
        p_fix = np.array([p for _, p in pairs]).reshape(-1, d)
    return anchors, R_fix, p_fix, ncomp


# ----------------------------------------------------------------------------------------------
# linear algebra


def _normal_equations(n: int, d: int, i, j, S, W, c=None):
    """A, b of min Σ ‖x_j − S_ij x_i − c_ij‖²_W (blocks d×d): A_ii += SᵀWS, A_jj += W,
    A_ij −= SᵀW, A_ji −= WS; b_i −= SᵀWc, b_j += Wc."""
    parts = _edge_blocks(S, W)
    StW = -parts[2]
    # summed into the block pattern of the graph (the pattern's sort is over node pairs, not over the
    # 4m·d² entries as a triplet conversion's: 3D 91 125 poses 0.25 s against 0.9-1.4 s)
    A, _ = _BlockSystem(n, d, i, j, np.zeros(0, dtype=np.int64)).matrix(parts, np.zeros((n * d, 1)),
                                                                        np.zeros((0, 1)))
    b = np.zeros((n, d))
    if c is not None:
        Wc = np.einsum("kab,kb->ka", W, c)
        np.add.at(b, i, -np.einsum("kab,kb->ka", StW, c))
        np.add.at(b, j, Wc)
    return A, b.reshape(n * d)


def _edge_blocks(S, W) -> tuple:
    """The blocks (ii, jj, ij, ji) = (SᵀWS, W, −SᵀW, −WS) that one edge adds to the normal equations."""
    StW = np.swapaxes(S, 1, 2) @ W
    return StW @ S, W, -StW, -(W @ S)


class _BlockSystem:
    """The normal equations' CSR pattern, built once for the rotation and the translation system of the
    direct path: d×d blocks on every node's diagonal and both sides of every edge. Anchored nodes' rows
    and columns hold the identity (their values move to the right-hand side), so both anchored solves
    share one matrix pattern and one symbolic factorization, and nothing is sliced."""

    def __init__(self, n: int, d: int, i: np.ndarray, j: np.ndarray, anchors: np.ndarray):
        self.n, self.d = n, d
        m = len(i)
        lo, hi = np.minimum(i, j), np.maximum(i, j)
        key = lo * n + hi
        order = np.argsort(key, kind="stable")
        ks = key[order]
        first = np.ones(m, dtype=bool)
        np.not_equal(ks[1:], ks[:-1], out=first[1:])
        pid = np.empty(m, dtype=np.int64)
        pid[order] = np.cumsum(first) - 1
        ulo, uhi = lo[order][first], hi[order][first]   # distinct node pairs, sorted by (lo, hi)
        npairs = len(ulo)
        nup, nlow = np.bincount(ulo, minlength=n), np.bincount(uhi, minlength=n)
        rowlen = nup + nlow + 1
        bptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(rowlen, out=bptr[1:])
        # block positions in row-major order: row v holds its lower pairs, its diagonal, its upper pairs
        upper = bptr[ulo] + nlow[ulo] + 1 + np.arange(npairs) - (np.cumsum(nup) - nup)[ulo]
        by_hi = np.argsort(uhi, kind="stable")   # keeps lo increasing within each hi
        lower = np.empty(npairs, dtype=np.int64)
        lower[by_hi] = bptr[uhi[by_hi]] + np.arange(npairs) - (np.cumsum(nlow) - nlow)[uhi[by_hi]]
        diag = bptr[:-1] + nlow
        nb = int(bptr[-1])
        bcols = np.empty(nb, dtype=np.int64)
        bcols[upper], bcols[lower], bcols[diag] = uhi, ulo, np.arange(n)
        itype = np.int32 if nb * d * d < 2**31 else np.int64
        C = sp.bsr_matrix((np.ones((nb, d, d), dtype=bool), bcols.astype(itype), bptr.astype(itype)),
                          shape=(n * d, n * d), blocksize=(d, d)).tocsr()   # the layout (1 byte per entry)
        self.indptr, self.indices, self.nnz = C.indptr, C.indices, nb * d * d
        for a in (self.indptr, self.indices):   # a fixed pattern (others may keep it without a copy)
            a.flags.writeable = False
        a = np.arange(d)

        def entries(p, v):
            """CSR positions (t, d, d) of blocks p in block rows v: bptr[v]·(d² − d) + p·d + a·rowlen[v]·d + b."""
            row = (bptr[v] * (d * d - d) + p * d)[:, None] + (rowlen[v] * d)[:, None] * a
            return row[:, :, None] + a

        ij = np.where(i < j, upper[pid], lower[pid])
        ji = np.where(i < j, lower[pid], upper[pid])
        self.fixed_dofs = (anchors[:, None] * d + a).ravel()
        self.fixed_diagonal = entries(diag[anchors], anchors)[:, a, a].ravel()
        if d == 1 and npairs == m:
            # one unknown per node and every pair once: block positions are CSR positions, each
            # off-diagonal entry has one contribution (written, not summed), diagonals summed per node
            self.contrib = None
            self.scalar = (ij, ji, np.concatenate([i, j]), diag)
            is_anchor = np.zeros(n, dtype=bool)
            is_anchor[anchors] = True
            count = rowlen[anchors]   # the anchors' rows, then their columns (one entry per edge)
            start = np.repeat(bptr[anchors] - (np.cumsum(count) - count), count)
            self.fixed_entries = np.concatenate([start + np.arange(int(count.sum())), ji[is_anchor[i]],
                                                 ij[is_anchor[j]]])
            return
        self.contrib = np.concatenate([entries(diag[i], i), entries(diag[j], j), entries(ij, i),
                                       entries(ji, j)]).reshape(-1)   # (4m·d²,)
        fixed = np.zeros(n * d, dtype=bool)
        fixed[self.fixed_dofs] = True
        self.fixed_entries = np.flatnonzero(np.repeat(fixed, np.diff(self.indptr)) | fixed[self.indices])

    def matrix(self, blocks, rhs: np.ndarray, x_fixed: np.ndarray):
        """The anchored system (A, b) from the edges' (ii, jj, ij, ji) blocks, the free rows' right-hand
        side ``rhs`` (n·d, k) and the anchored dofs' values ``x_fixed`` (n_fixed·d, k)."""
        if self.contrib is None:
            data = self._scalar_data(blocks)
        else:
            values = np.concatenate(blocks).ravel()
            data = np.bincount(self.contrib, values.real, minlength=self.nnz)
            if np.iscomplexobj(values):   # Hermitian (2D rotations as unit complex numbers)
                data = data + 1j * np.bincount(self.contrib, values.imag, minlength=self.nnz)
        A = sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n * self.d,) * 2)
        A.has_sorted_indices = True
        x = np.zeros_like(rhs)
        x[self.fixed_dofs] = x_fixed
        b = rhs - A @ x
        b[self.fixed_dofs] = x_fixed
        data[self.fixed_entries] = 0.0
        data[self.fixed_diagonal] = 1.0
        return A, b


    def _scalar_data(self, blocks) -> np.ndarray:
        """CSR values of the one-unknown system, the numbers the summing path gives: off-diagonal
        entries (one contribution each) written as 0 + v, diagonals summed per node in its order
        (ii of every edge, then jj)."""
        ii, jj, ij, ji = (np.asarray(b).reshape(-1) for b in blocks)
        pos_ij, pos_ji, node, diag = self.scalar
        complex_ = any(np.iscomplexobj(b) for b in (ii, jj, ij, ji))
        data = np.empty(self.nnz, dtype=complex if complex_ else float)
        zero = 0j if complex_ else 0.0
        data[pos_ij] = ij + zero   # + 0 as the sum into zeros: −0 becomes +0
        data[pos_ji] = ji + zero
        w = np.concatenate([ii, jj])
        if complex_:
            data[diag] = np.bincount(node, w.real, minlength=self.n) + 1j * np.bincount(node, w.imag, minlength=self.n)
        else:
            data[diag] = np.bincount(node, w, minlength=self.n)
        return data


def _spanning_tree(n: int, edges: np.ndarray, weight: np.ndarray, anchors: np.ndarray):
    """Edge ids of a BFS spanning forest grown from the anchors (heaviest edge per node pair) and
    the non-root nodes in BFS (root-first) order."""
    i, j = edges[:, 0], edges[:, 1]
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    by_pair = np.lexsort((-weight, hi, lo))
    key = lo[by_pair] * n + hi[by_pair]
    keep = by_pair[np.r_[True, key[1:] != key[:-1]]] if len(key) else by_pair
    # a virtual root n joined to every anchor makes one tree out of the forest
    na = anchors.size
    u = np.concatenate([lo[keep], np.full(na, n)])
    v = np.concatenate([hi[keep], anchors])
    G = sp.csr_matrix((np.ones(u.size), (u, v)), shape=(n + 1, n + 1))
    G = (G + G.T).tocsr()
    order, pred = csgraph.breadth_first_order(G, n, directed=False, return_predecessors=True)
    child = order[1:].astype(np.int64)
    parent = pred[child].astype(np.int64)
    real = parent != n
    # edge id of each tree pair (parent, child) by a sorted lookup of the kept pairs
    pair = lo[keep] * n + hi[keep]
    by_key = np.argsort(pair)
    want = np.minimum(parent[real], child[real]) * n + np.maximum(parent[real], child[real])
    eid = keep[by_key[np.searchsorted(pair[by_key], want)]]
    return eid, child


class _Reduced:
    """Anchored system A_ff x_f = b_f − A_fa x_a over the free nodes; unknown blocks of d."""

    def __init__(self, n: int, d: int, anchors: np.ndarray):
        self.n, self.d = n, d
        fixed_node = np.zeros(n, dtype=bool)
        fixed_node[anchors] = True
        self.free_nodes = np.flatnonzero(~fixed_node)
        self.node_position = np.full(n, -1, dtype=np.int64)
        self.node_position[self.free_nodes] = np.arange(self.free_nodes.size)
        self.free = (self.free_nodes[:, None] * d + np.arange(d)).ravel()
        self.fixed = (anchors[:, None] * d + np.arange(d)).ravel()

    def restrict(self, A):
        A = A.tocsr()
        rows = A[self.free]
        return rows[:, self.free].tocsr(), rows[:, self.fixed].tocsr()

    def expand(self, x_free, x_fixed):
        x = np.zeros((self.n * self.d,) + x_free.shape[1:])
        x[self.free] = x_free
        x[self.fixed] = x_fixed
        return x


def _isotropic(W: np.ndarray) -> bool:
    """Whether every block W_k (m,d,d) is a multiple of the identity."""
    d = W.shape[1]
    return bool(np.all(W[:, ~np.eye(d, dtype=bool)] == 0) and np.all(W[:, np.arange(d), np.arange(d)] == W[:, :1, 0]))


def _positive_definite(W: np.ndarray) -> bool:
    """Whether every symmetric block W_k (m,d,d) is positive definite (closed form for 2×2)."""
    if W.shape[1] == 2:
        return bool(np.all(W[:, 0, 0] > 0) and np.all(W[:, 0, 0] * W[:, 1, 1] - W[:, 0, 1] * W[:, 1, 0] > 0))
    return bool(np.linalg.eigvalsh(W)[:, 0].min() > 0)


def _block_expand(nodes: np.ndarray, d: int) -> np.ndarray:
    return (nodes[:, None] * d + np.arange(d)).ravel()


def _tree_solver(red: _Reduced, A_tree_ff, order: np.ndarray):
    """Exact solve with the spanning-forest part of A: eliminating children before parents
    (reverse BFS order) gives a zero-fill factorization, O(n) to build and apply."""
    nodes = red.node_position[order[::-1]]
    perm = _block_expand(nodes[nodes >= 0], red.d)
    T = A_tree_ff[perm][:, perm].tocsc()
    lu = splu(T, permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True})

    def apply(r):
        z = np.empty_like(r)
        z[perm] = lu.solve(r[perm])
        return z

    return apply


def _block_jacobi(A_ff, d: int):
    """Apply of the inverse d×d diagonal blocks of A_ff."""
    C = A_ff.tocoo()
    same = (C.row // d) == (C.col // d)
    nb = A_ff.shape[0] // d
    D = np.zeros((nb, d, d))
    np.add.at(D, (C.row[same] // d, C.row[same] % d, C.col[same] % d), C.data[same])
    Dinv = np.linalg.inv(D)

    def apply(r):  # r: (n,) or (n, k)
        return np.einsum("kab,kbc->kac", Dinv, r.reshape(nb, d, -1)).reshape(r.shape)

    return apply


class _SchwarzLayout:
    """Aggregates (Voronoi cells of random seeds, by hop distance) of the free-node graph and
    their overlapping extensions by ``overlap`` layers of neighbours."""

    def __init__(self, red: _Reduced, i, j, aggregate_size: int, overlap: int, seed: int):
        nf = red.free_nodes.size
        u, v = red.node_position[i], red.node_position[j]
        keep = (u >= 0) & (v >= 0)
        G = sp.csr_matrix((np.ones(int(keep.sum())), (u[keep], v[keep])), shape=(nf, nf))
        G = (G + G.T).tocsr()
        rng = np.random.default_rng(seed)
        nagg = max(1, nf // max(1, int(aggregate_size)))
        seeds = np.sort(rng.choice(nf, size=nagg, replace=False))
        depth, pred, src = csgraph.dijkstra(G, directed=False, indices=seeds, unweighted=True,
                                            min_only=True, return_predecessors=True)
        label = np.searchsorted(seeds, src)
        # every aggregate's BFS tree from its seed (hop distance ``depth``, parent ``pred``; −1 at
        # seeds and in parts without a seed): the short paths along which local frames are composed
        self.depth = np.where(np.isfinite(depth), depth, 0).astype(np.int64)
        self.pred = np.where(pred >= 0, pred, -1).astype(np.int64)
        lost = src < 0  # in a part of the graph without a seed: one aggregate per such part
        if np.any(lost):
            _, comp = csgraph.connected_components(G, directed=False)
            _, comp_id = sorted_unique(comp[lost], return_inverse=True)
            label[lost] = nagg + comp_id
        _, label = sorted_unique(label, return_inverse=True)
        self.label, self.count = label, int(label.max()) + 1
        # (subdomain, node) pairs of the overlapping subdomains
        sub, node = label, np.arange(nf)
        G.data[:] = 1.0
        for _ in range(int(overlap)):  # each layer vectorized over all (subdomain, node) pairs
            by_node = sp.csr_matrix((np.ones(node.size), (node, np.arange(node.size))),
                                    shape=(nf, node.size))
            hit = (G @ by_node).tocoo()  # hit[w, p]: w is a neighbour of the node of pair p
            pairs = sorted_unique(np.concatenate([sub.astype(np.int64) * nf + node,
                                              sub[hit.col].astype(np.int64) * nf + hit.row]))
            sub, node = pairs // nf, pairs % nf
        self.sub, self.node = sub, node


def _tree_levels(layout: _SchwarzLayout, red: _Reduced, i, j):
    """The aggregates' BFS trees level by level from their seeds: (nodes, parents, edge ids, whether
    each edge runs parent → node) per level, for composing per-node values along the trees."""
    nf = red.free_nodes.size
    u, v = red.node_position[i], red.node_position[j]
    eid = np.flatnonzero((u >= 0) & (v >= 0))
    key = np.minimum(u[eid], v[eid]) * nf + np.maximum(u[eid], v[eid])
    order = np.argsort(key, kind="stable")
    key = key[order]
    tree = layout.pred >= 0
    levels = np.bincount(layout.depth[tree]) if np.any(tree) else np.zeros(0, np.int64)
    by_depth = np.argsort(np.where(tree, layout.depth, 0), kind="stable")
    start = np.searchsorted(np.where(tree, layout.depth, 0)[by_depth], np.arange(len(levels) + 1))
    for level in range(1, len(levels)):  # a few levels: the aggregates' radius in hops
        nodes = by_depth[start[level]:start[level + 1]]
        nodes = nodes[tree[nodes]]
        parent = layout.pred[nodes]
        e = eid[order[np.searchsorted(key, np.minimum(parent, nodes) * nf + np.maximum(parent, nodes))]]
        yield nodes, parent, e, u[e] == parent


def _local_frames(layout: _SchwarzLayout, red: _Reduced, i, j, R_meas) -> np.ndarray:
    """Rotations R̃_v (nf,d,d) of the free nodes composed from their aggregate's seed along its BFS
    tree (R_j = R_i R_ij on every tree edge). Each aggregate's frames then differ from the true
    rotations by one rotation, up to the noise of a few hops: R̃_vᵀ spans the chordal system's
    near-null space {X_v = R_vᵀ Q} aggregate by aggregate (a global spanning tree drifts far
    between neighbours that it joins only around a long loop)."""
    nf, d = red.free_nodes.size, R_meas.shape[1]
    frames = np.broadcast_to(np.eye(d), (nf, d, d)).copy()
    for nodes, parent, e, forward in _tree_levels(layout, red, i, j):
        step = np.where(forward[:, None, None], R_meas[e], np.swapaxes(R_meas[e], 1, 2))
        frames[nodes] = frames[parent] @ step
    return frames


def _local_phases(levels, nf: int, a: np.ndarray) -> np.ndarray:
    """2D :func:`_local_frames` as unit complex numbers q_v = cos θ̃_v + i sin θ̃_v (``a``: the edges'
    e^{iδ_ij}; ``levels``: :func:`_tree_levels`' list): a product of complex numbers per tree edge
    instead of 2 × 2 matrices (1M poses: 0.26 against 0.55 s)."""
    q = np.ones(nf, dtype=complex)
    for nodes, parent, e, forward in levels:
        q[nodes] = q[parent] * np.where(forward, a[e], np.conj(a[e]))
    return q


def _local_positions(levels, nf: int, c: np.ndarray) -> np.ndarray:
    """2D positions x + iy of the free nodes composed from their aggregate's seed (at 0) along its BFS
    tree, p_j = p_i + c_ij on every tree edge (``c``: the edges' R_i t_ij as complex numbers). Each
    aggregate's positions then differ from the least-squares ones by one translation, up to the noise
    of a few hops: the translations' CG starts from them (:meth:`_AggregateSchwarz.solve`), whose
    coarse space of constants removes the translations."""
    p = np.zeros(nf, dtype=complex)
    for nodes, parent, e, forward in levels:
        p[nodes] = p[parent] + np.where(forward, c[e], -c[e])
    return p


def _schwarz(A_ff, layout: _SchwarzLayout, d: int, basis: np.ndarray):
    """Two-level overlapping Schwarz, balancing form M⁻¹ = Q + (I − QA) Σ R_kᵀA_k⁻¹R_k (I − AQ)
    with Q = P (PᵀAP)⁻¹ Pᵀ, P the aggregates times per-node near-null blocks ``basis`` (nf,d,d)."""
    nf = A_ff.shape[0] // d
    k = layout.node.size
    Rm = sp.csr_matrix((np.ones(k * d), (np.arange(k * d), _block_expand(layout.node, d))),
                       shape=(k * d, nf * d))
    Ab = (Rm @ A_ff @ Rm.T).tocoo()
    subx = np.repeat(layout.sub, d)
    same = subx[Ab.row] == subx[Ab.col]
    Ab = sp.csc_matrix((Ab.data[same], (Ab.row[same], Ab.col[same])), shape=Ab.shape)
    local = SparseCholesky(Ab, "the chordal subdomain blocks")
    RmT = Rm.T.tocsr()
    rows = np.broadcast_to(np.arange(nf)[:, None, None] * d + np.arange(d)[None, :, None], basis.shape)
    cols = np.broadcast_to(layout.label[:, None, None] * d + np.arange(d)[None, None, :], basis.shape)
    P = sp.csr_matrix((basis.ravel(), (rows.ravel(), cols.ravel())), shape=(nf * d, layout.count * d))
    PT = P.T.tocsr()
    A0 = PT @ A_ff @ P
    coarse = SparseCholesky(((A0 + A0.T) * 0.5).tocsc(), "the chordal coarse matrix")

    def Q(x):
        return P @ coarse.solve(PT @ x)

    def apply(r):
        z = Q(r)
        s = RmT @ local.solve(Rm @ (r - A_ff @ z))
        return z + s - Q(A_ff @ s)

    return apply


class _AggregateSchwarz:
    """Two-level Schwarz for a Hermitian system with one unknown per node on a fixed CSR pattern (2D
    rotations as unit complex numbers, then positions as x + iy): the aggregates' diagonal blocks (no
    overlap) factorized as one block-diagonal matrix, one coarse function per aggregate with the
    given node values (P), and CG deflated by that coarse space: from x₀ = Qb (Q = P A₀⁻¹ Pᴴ) every
    residual has Pᴴr = 0, so the balancing preconditioner Q + (I − QA) B (I − AQ) of :func:`_schwarz`
    reduces to (I − QA) B: one local and one coarse solve per iteration. Built once for the pattern
    (both factorizations' symbolic work); :meth:`compute` takes the numbers of each system."""

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, label: np.ndarray, count: int):
        n = len(indptr) - 1
        self.label, self.count = label, count
        self.rows, self.cols = np.repeat(np.arange(n), np.diff(indptr)), indices
        self.keep = label[self.rows] == label[indices]   # entries inside an aggregate
        self.local_indptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(np.bincount(self.rows[self.keep], minlength=n), out=self.local_indptr[1:])
        self.local_indices = indices[self.keep]
        # A₀'s CSR pattern (aggregate pairs joined by an entry) and where each entry of A adds into it
        key, self.coarse_position = sorted_unique(label[self.rows].astype(np.int64) * count + label[indices],
                                                  return_inverse=True)
        self.coarse_indptr = np.zeros(count + 1, dtype=np.int64)
        np.cumsum(np.bincount(key // count, minlength=count), out=self.coarse_indptr[1:])
        self.coarse_indices = key % count
        self.coarse_transpose = np.searchsorted(key, self.coarse_indices * count + key // count)
        self.coarse_diagonal = np.searchsorted(key, np.arange(count) * (count + 1))
        # Pᴴ's CSR pattern (row a: the nodes of aggregate a): Pᴴx by one sparse product, not two bincounts
        self.by_label = np.argsort(label, kind="stable")
        self.label_ptr = np.zeros(count + 1, dtype=np.int64)
        np.cumsum(np.bincount(label, minlength=count), out=self.label_ptr[1:])
        self.local = self.coarse = None

    def compute(self, A: sp.csr_matrix, basis: np.ndarray) -> "_AggregateSchwarz":
        """Factorize A's aggregate blocks and A₀ = PᴴAP, P[v, label_v] = basis_v (complex)."""
        # the CSR of a Hermitian matrix read as CSC is its conjugate: conjugated numbers give A's CSC
        # (simplicial: blocks of ~16 nodes have no supernodes worth the name; 1M poses: 0.7 against 1.9 s)
        B = sp.csc_matrix((np.conj(A.data[self.keep]), self.local_indices, self.local_indptr), shape=A.shape)
        if self.local is None:
            self.local = SparseCholesky(B, "the chordal aggregate blocks", mode="simplicial")
        else:
            self.local.refactor(B)
        v = np.conj(basis[self.rows]) * A.data * basis[self.cols]
        size = len(self.coarse_indices)
        data = (np.bincount(self.coarse_position, v.real, minlength=size)
                + 1j * np.bincount(self.coarse_position, v.imag, minlength=size))
        data = 0.5 * (data + np.conj(data[self.coarse_transpose]))   # exactly Hermitian: CHOLMOD reads a triangle
        empty = np.ones(self.count, dtype=bool)   # aggregates without coarse values (the anchors'): any pivot
        empty[self.label[basis != 0]] = False
        data[self.coarse_diagonal[empty]] = 1.0
        A0 = sp.csc_matrix((np.conj(data), self.coarse_indices, self.coarse_indptr), shape=(self.count,) * 2)
        if self.coarse is None:
            self.coarse = SparseCholesky(A0, "the chordal coarse matrix", mode="simplicial")
        else:
            self.coarse.refactor(A0)
        self.A, self.basis = threaded(A), basis   # its products (two per iteration) on the local threads
        self.PH = sp.csr_matrix((np.conj(basis[self.by_label]), self.by_label, self.label_ptr),
                                shape=(self.count, len(basis)))
        return self

    def _coarse(self, x: np.ndarray) -> np.ndarray:
        """Q x = P A₀⁻¹ Pᴴ x for x (n, k): Pᴴ by a sparse product (1M 2D poses: 8 against 12 ms for the
        weighted sums over the aggregates by bincount), P by a gather."""
        Y = self.PH @ x
        return self.basis[:, None] * np.asarray(self.coarse.solve(Y)).reshape(Y.shape)[self.label]

    def _deflated(self, r: np.ndarray) -> np.ndarray:
        s = self.local.solve(r)
        return s - self._coarse(self.A @ s)

    def solve(self, b: np.ndarray, tol: float, maxiter: int | None, guess: np.ndarray | None = None):
        """x with ‖b − Ax‖ ≤ tol‖b‖ per column of b (n, k) by deflated CG, and the CG infos
        (residuals relative to ‖b‖). ``guess`` (n, k): a start corrected on the coarse space,
        x₀ = g + Q(b − Ag), which keeps Pᴴr₀ = 0."""
        if guess is None:
            x0 = self._coarse(b)
        else:
            x0 = guess + self._coarse(b - self.A @ guess)
        r0 = b - self.A @ x0
        bnorm, rnorm = np.linalg.norm(b, axis=0), np.linalg.norm(r0, axis=0)
        ratio = np.divide(rnorm, bnorm, out=np.zeros_like(rnorm), where=bnorm > 0)
        tols = np.divide(tol, ratio, out=np.ones_like(ratio), where=ratio > 0)
        X, infos = [], []
        for c in range(b.shape[1]):   # each column its own tolerance relative to ‖r₀‖
            e, (info,) = pcg_columns(self.A, r0[:, c:c + 1], M=self._deflated, tol=float(tols[c]), maxiter=maxiter)
            info.residuals = [float(r * ratio[c]) for r in info.residuals]
            X.append(x0[:, c] + e[:, 0])
            infos.append(info)
        return np.stack(X, -1), infos


def _direct_solve(A, B):
    try:
        from sksparse.cholmod import cholesky  # optional, faster

        return cholesky(A.tocsc())(B)
    except ImportError:
        lu = splu(A.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                  options={"SymmetricMode": True})
        return lu.solve(np.asarray(B))


# ----------------------------------------------------------------------------------------------


# Options. information: None (unit), (m,) weights, (dof,dof) or (m,dof,dof) in GTSAM tangent order
# (Pose2 (x,y,θ), Pose3 (ω,v)); rotation weight tr(Ω_RR)/dim, translation weight Ω_tt in the frame
# R_i R_ij (translation_weights "diagonal"/"isotropic" drop its correlations, for degenerate Ω_tt);
# or the pair (w_rot (m,), Ω_tt (m,d,d)) those reduce to, given as it is.
# anchor: an index (anchors its component; every other component is anchored at its lowest index)
# or one index per component; anchor_pose: None (identity), (R, p), a homogeneous matrix or, in 2D,
# (x, y, θ); a list of those with a list of anchors. solver "cg": the project's PCG to relative
# residual tol (the right-hand sides side by side), preconditioned by "schwarz" (two-level Schwarz
# on aggregates of about aggregate_size poses grown by overlap layers, balancing form; coarse blocks:
# the rotations composed from each aggregate's seed (rotation system), constants (translations; in 2D
# by CG started from the positions composed along the aggregates' trees)),
# "tree" (exact spanning-tree solve), "jacobi" or "none"; solver "direct": sparse Cholesky (CHOLMOD
# if installed, else SuperLU). translation_solver: the translations' ("cg" or "direct"; None: as
# solver); isotropic translation information makes them one scalar Laplacian. translation_tol: CG's
# tolerance for the translations (None: tol). 2D by CG without overlap: both systems with one complex
# unknown per pose, deflated CG on the aggregates (:class:`_AggregateSchwarz`). rotation "lago" (2D only):
# angles with 2π wraps regularized along the BFS spanning tree instead of the chordal relaxation.
# blas_threads: BLAS threads while solving (None: leave the process setting), as the optimizer's.
def chordal_initialization(n: int, edges, R_meas, t_meas, information=None, anchor=0,
                           anchor_pose=None, solver: str = "cg", *, translation_solver: str | None = None,
                           preconditioner: str = "schwarz",
                           rotation: str = "chordal", tol: float = 1e-10, translation_tol: float | None = None,
                           maxiter: int | None = None,
                           translation_weights: str = "information", aggregate_size: int = 16,
                           overlap: int = 1, seed: int = 0, blas_threads: int | None = 1) -> ChordalResult:
    """Anchored R = proj_SO(d)(argmin_X Σ w_ij‖X_j − X_i R_ij‖_F²), then
    p = argmin Σ ‖p_j − p_i − R_i t_ij‖²_W; returns rotations (n,d,d), positions (n,d), info."""
    args = dict(locals())
    with blas_limits(blas_threads):
        return _chordal(**args)


def _chordal(n, edges, R_meas, t_meas, information, anchor, anchor_pose, solver, translation_solver, preconditioner,
             rotation, tol, translation_tol, maxiter, translation_weights, aggregate_size, overlap, seed,
             blas_threads):
    """Body of :func:`chordal_initialization` (BLAS threads already limited)."""
    t0 = time.perf_counter()
    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}; choose one of {', '.join(SOLVERS)}")
    if preconditioner is None:
        preconditioner = "none"
    if preconditioner not in PRECONDITIONERS:
        raise ValueError(f"unknown preconditioner {preconditioner!r}; "
                         f"choose one of {', '.join(PRECONDITIONERS)}")
    if rotation not in ROTATION_METHODS:
        raise ValueError(f"unknown rotation method {rotation!r}; choose one of {', '.join(ROTATION_METHODS)}")
    n = int(n)
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    R_meas = np.asarray(R_meas, dtype=float)
    t_meas = np.asarray(t_meas, dtype=float)
    m = edges.shape[0]
    if R_meas.ndim != 3 or R_meas.shape[0] != m or R_meas.shape[1] != R_meas.shape[2]:
        raise ValueError(f"R_meas must be (m,d,d) with m = {m}, got {R_meas.shape}")
    d = R_meas.shape[1]
    if d not in (2, 3):
        raise ValueError(f"only d = 2 or 3 are supported, got {d}")
    if t_meas.shape != (m, d):
        raise ValueError(f"t_meas must be ({m},{d}), got {t_meas.shape}")
    if rotation == "lago" and d != 2:
        raise ValueError("rotation='lago' is only defined for 2D pose graphs")
    if n <= 0:
        raise ValueError("need at least one pose")
    if m and (edges.min() < 0 or edges.max() >= n):
        raise ValueError(f"edge index out of range 0..{n - 1}")
    if np.any(edges[:, 0] == edges[:, 1]):
        raise ValueError("self-loop edges (i == j) are not supported")
    w_rot, W_loc = _edge_weights(information, m, d, translation_weights)
    if np.any(~np.isfinite(w_rot)) or np.any(w_rot <= 0):
        raise ValueError("rotation weights must be positive and finite")
    if np.any(~np.isfinite(W_loc)) or (m and not _positive_definite(W_loc)):
        raise ValueError("translation information blocks must be positive definite and finite")
    translation_solver = solver if translation_solver is None else translation_solver
    if translation_solver not in SOLVERS:
        raise ValueError(f"unknown solver {translation_solver!r}; choose one of {', '.join(SOLVERS)}")
    cg_translations = translation_solver == "cg"
    i, j = edges[:, 0], edges[:, 1]
    anchors, R_fix, p_fix, ncomp = _anchors(n, edges, anchor, anchor_pose, d)
    cg = solver == "cg"  # the rotations' solver
    tree_cache = []

    def spanning_tree():
        if not tree_cache:  # only CG's tree preconditioner, its Schwarz rotation basis and LAGO need it
            tree_cache.append(_spanning_tree(n, edges, w_rot, anchors))
        return tree_cache[0]

    # the direct path assembles both systems into one CSR pattern (no slicing, one symbolic analysis).
    # 2D: a pattern with one unknown per pose: rotations x_i ∈ ℂ (X_i e₀, rotated by complex products)
    # and, for isotropic translation information, the x and y of the positions as two right-hand sides
    direct_path = not cg and rotation == "chordal"
    scalar = direct_path and d == 2
    # 2D by CG: the same one-unknown pattern (rotations as complex numbers, then positions as x + iy),
    # preconditioned by aggregates without overlap (:class:`_AggregateSchwarz`): a quarter of the
    # 2×2-block system's entries, one symbolic analysis for both systems
    complex_cg = (cg and d == 2 and rotation == "chordal" and preconditioner == "schwarz" and int(overlap) == 0
                  and n - anchors.size > 0)
    system = _BlockSystem(n, 1 if scalar or complex_cg else d, i, j, anchors) if direct_path or complex_cg else None
    factors, recorded = {}, []

    def direct(blocks, rhs, x_fixed):
        A, b = system.matrix(blocks, rhs, x_fixed)
        if np.iscomplexobj(A.data):   # CSR of a Hermitian A is the CSC of conj(A): conjugate it back
            A = sp.csc_matrix((np.conj(A.data), A.indices, A.indptr), shape=A.shape)
            A.has_sorted_indices = True   # the pattern's rows are sorted: no O(nnz) check per use
        key = (id(system), A.dtype.kind)   # one factorization per pattern and number type
        if key in factors:
            factors[key].refactor(A)
        elif scalar and counted_simplicially(A):
            # the pose graph's vertex pattern (diagonal and every edge), factorized simplicially as CHOLMOD
            # would choose for so sparse a pattern: its column counts answer the cost model's next question
            factors[key] = SparseCholesky(A, "the chordal normal equations", mode="simplicial")
            if not recorded:
                record_column_counts(A, factors[key])
                recorded.append(key)
        else:
            factors[key] = SparseCholesky(A, "the chordal normal equations")
        return np.asarray(factors[key].solve(b)).reshape(rhs.shape)

    red_d, red_1 = _Reduced(n, d, anchors), _Reduced(n, 1, anchors)
    layout = None
    if (cg or cg_translations) and preconditioner == "schwarz" and red_1.free_nodes.size:
        layout = _SchwarzLayout(red_1, i, j, aggregate_size, overlap, seed)
    info: dict = {"n": n, "m": m, "d": d, "components": int(ncomp), "anchors": anchors.tolist(),
                  "solver": solver, "translation_solver": translation_solver,
                  "preconditioner": preconditioner if cg or cg_translations else None,
                  "rotation": rotation}
    if layout is not None:
        info["aggregates"] = layout.count

    aggregates = []

    def complex_solve(blocks, rhs, x_fixed, basis, tol=tol, guess=None):
        """CG on the one-unknown complex system, the free nodes' coarse values ``basis`` (and a start
        ``guess`` at the free nodes)."""
        A, b = system.matrix(blocks, rhs, x_fixed)
        if not aggregates:
            label = np.full(n, layout.count)   # the anchors: an aggregate of their own, no coarse value
            label[red_1.free_nodes] = layout.label
            aggregates.append(_AggregateSchwarz(A.indptr, A.indices, label, layout.count + 1))
        values = np.zeros(n, dtype=complex)
        values[red_1.free_nodes] = basis
        start = None
        if guess is not None:
            start = np.zeros(n, dtype=complex)
            start[red_1.free_nodes] = guess
            start[anchors] = x_fixed[:, 0]
            start = start[:, None]
        z, infos = aggregates[0].compute(A, values).solve(b, tol, maxiter, start)
        return z[:, 0], infos

    levels_cache = []

    def tree_levels():
        """The aggregates' BFS trees level by level (both 2D systems compose along them)."""
        if not levels_cache:
            levels_cache.append(list(_tree_levels(layout, red_1, i, j)))
        return levels_cache[0]

    def tree_of(red, S, W):
        tree_eid, tree_order = spanning_tree()
        A_T, _ = _normal_equations(n, red.d, i[tree_eid], j[tree_eid], S[tree_eid], W[tree_eid])
        return _tree_solver(red, red.restrict(A_T)[0], tree_order)

    def solve(red, A, b, x_fixed, S, W, basis=None, cg=cg, tol=tol):
        """Anchored solve for each column of b; returns the full x and the CG infos."""
        shape = (red.free.size,) + x_fixed.shape[1:]
        if red.free.size == 0:
            return red.expand(np.zeros(shape), x_fixed), []
        A_ff, A_fa = red.restrict(A)
        B = (b[red.free] - A_fa @ x_fixed).reshape(red.free.size, -1)
        if not cg:
            return red.expand(np.asarray(_direct_solve(A_ff, B)).reshape(shape), x_fixed), []
        if preconditioner == "tree":
            M = tree_of(red, S, W)
        elif preconditioner == "jacobi":
            M = _block_jacobi(A_ff, red.d)
        elif preconditioner == "schwarz":
            if basis is None:  # near-null space of an (unsigned) block Laplacian: constants
                basis = np.broadcast_to(np.eye(red.d), (red.free_nodes.size, red.d, red.d))
            elif callable(basis):
                basis = basis(A_ff, B)
            M = _schwarz(A_ff, layout, red.d, basis)
        else:
            M = None
        X, infos = pcg_columns(A_ff, B, M=M, tol=tol, maxiter=maxiter)  # d ≤ 3 right-hand sides side by side
        return red.expand(X.reshape(shape), x_fixed), infos

    # ---- rotations ------------------------------------------------------------------------
    t1 = time.perf_counter()
    if rotation == "chordal":
        # unknown block X_i = R_iᵀ: ‖R_j − R_i R_ij‖_F = ‖X_j − R_ijᵀ X_i‖_F, d right-hand sides
        # In 2D the second column is the first turned by 90° (J commutes with SO(2)): solving for
        # X_i e₀ ≈ (cos θ_i, −sin θ_i) alone is LAGO's relaxation on (cos θ, sin θ).
        S = np.swapaxes(R_meas, 1, 2)
        W = w_rot[:, None, None] * np.eye(d)
        cols = 1 if d == 2 else d
        X_fix = np.swapaxes(R_fix, 1, 2).reshape(-1, d)[:, :cols]

        def full_blocks(X):
            """(N·d, cols) → X_i blocks (N,d,d), completing the 2D second column (−x₁, x₀)."""
            X = X.reshape(-1, d, cols)
            if d == 3:
                return X
            return np.concatenate([X, np.stack([-X[:, 1, 0], X[:, 0, 0]], -1)[:, :, None]], 2)

        def rotation_basis(_A_ff, _B):
            """Near-null blocks X_v ≈ R_vᵀ of the connection Laplacian: the aggregates' local frames."""
            return np.swapaxes(_local_frames(layout, red_d, i, j, R_meas), 1, 2)

        if scalar:  # ‖x_j − R_ijᵀ x_i‖²: x_j − a x_i in ℂ with a = e^{−iδ_ij}
            w = w_rot.astype(complex)
            a_ij = R_meas[:, 0, 0] - 1j * R_meas[:, 1, 0]
            x_fix = X_fix.reshape(-1, 2)   # (x₀, x₁) = X e₀ of every anchor
            z_fix = (x_fix[:, 0] + 1j * x_fix[:, 1]).reshape(-1, 1)
            z = direct((w, w, -w * np.conj(a_ij), -w * a_ij), np.zeros((n, 1), dtype=complex), z_fix)[:, 0]
            X, infos = np.column_stack([z.real, z.imag]).reshape(n * d, cols), []
        elif complex_cg:   # the same, by CG; coarse values: the aggregates' local frames X̃_v e₀
            w, a_ij = w_rot.astype(complex), R_meas[:, 0, 0] - 1j * R_meas[:, 1, 0]
            phases = _local_phases(tree_levels(), red_1.free_nodes.size, np.conj(a_ij))   # R̃_v e₀ as e^{iθ̃_v}
            x_fix = X_fix.reshape(-1, 2)
            z, infos = complex_solve((w, w, -w * np.conj(a_ij), -w * a_ij), np.zeros((n, 1), dtype=complex),
                                     (x_fix[:, 0] + 1j * x_fix[:, 1])[:, None], np.conj(phases))
            X = np.column_stack([z.real, z.imag]).reshape(n * d, cols)
        elif system is not None:  # W = w·I: SᵀW and WS are exact scalings
            StW, WS = w_rot[:, None, None] * R_meas, w_rot[:, None, None] * S
            X, infos = direct((StW @ S, W, -StW, -WS), np.zeros((n * d, cols)), X_fix), []
        else:
            A, _ = _normal_equations(n, d, i, j, S, W)
            X, infos = solve(red_d, A, np.zeros((n * d, cols)), X_fix, S, W, rotation_basis)
        rotations = project_to_so(np.swapaxes(full_blocks(X), 1, 2))
    else:  # LAGO: θ_j − θ_i = δ_ij + 2πk_ij, k_ij from the angles composed along the spanning tree
        delta = np.arctan2(R_meas[:, 1, 0], R_meas[:, 0, 0])
        S = np.ones((m, 1, 1))
        W = w_rot[:, None, None]
        th_fix = np.arctan2(R_fix[:, 1, 0], R_fix[:, 0, 0])
        tree_eid, tree_order = spanning_tree()
        A_T, b_T = _normal_equations(n, 1, i[tree_eid], j[tree_eid], S[tree_eid], W[tree_eid],
                                     delta[tree_eid, None])
        A_T_ff, A_T_fa = red_1.restrict(A_T)
        theta_tree = red_1.expand(_tree_solver(red_1, A_T_ff, tree_order)(b_T[red_1.free] - A_T_fa @ th_fix),
                                  th_fix)
        k = np.round((theta_tree[j] - theta_tree[i] - delta) / (2 * np.pi))
        A, b = _normal_equations(n, 1, i, j, S, W, (delta + 2 * np.pi * k)[:, None])
        theta, infos = solve(red_1, A, b, th_fix, S, W)
        c, s = np.cos(theta), np.sin(theta)
        rotations = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
        info["lago_wraps"] = int(np.count_nonzero(k))
    info["rotation_iterations"] = [c_.iterations for c_ in infos]
    info["rotation_converged"] = all(c_.converged for c_ in infos)
    t2 = time.perf_counter()

    # ---- translations ---------------------------------------------------------------------
    tol_t = tol if translation_tol is None else float(translation_tol)
    # the BetweenFactor translation error lives in the frame R_i R_ij: W = (R_i R_ij) Ω_tt (R_i R_ij)ᵀ
    c = np.einsum("kab,kb->ka", rotations[i], t_meas)
    if _isotropic(W_loc):  # W = R (wI) Rᵀ = wI: the coordinates decouple, one scalar Laplacian, d right-hand sides
        w = W_loc[:, 0, 0]
        wc = w[:, None] * c
        b = np.stack([np.bincount(j, wc[:, a], minlength=n) - np.bincount(i, wc[:, a], minlength=n)
                      for a in range(d)], -1)
        if cg_translations and complex_cg:   # x + iy on the rotations' pattern; coarse values: constants,
            wz = w.astype(complex)            # from the aggregates' positions composed along their trees
            guess = _local_positions(tree_levels(), red_1.free_nodes.size, c[:, 0] + 1j * c[:, 1])
            z, infos = complex_solve((wz, wz, -wz, -wz), (b[:, 0] + 1j * b[:, 1])[:, None],
                                     (p_fix[:, 0] + 1j * p_fix[:, 1])[:, None], np.ones(red_1.free_nodes.size), tol_t,
                                     guess)
            P = np.stack([z.real, z.imag], -1)
        elif cg_translations:
            one = np.ones((m, 1, 1))
            A, _ = _normal_equations(n, 1, i, j, one, w[:, None, None])
            P, infos = solve(red_1, A, b, p_fix, one, w[:, None, None], cg=True, tol=tol_t)
        else:
            if not scalar:  # 3D: a one-unknown pattern of its own for the translations (rotations need 3×3
                system = _BlockSystem(n, 1, i, j, anchors)  # blocks): 1/27 of the block system's flops
            if d == 2 and (id(system), "c") in factors:
                # positions as complex numbers x + iy: the rotations' complex factor of the same pattern
                # is refactorized, not a real one analysed anew (262 145 poses: 32 ms of AMD)
                wz = w.astype(complex)
                z = direct((wz, wz, -wz, -wz), (b[:, 0] + 1j * b[:, 1])[:, None],
                           (p_fix[:, 0] + 1j * p_fix[:, 1])[:, None])[:, 0]
                P, infos = np.stack([z.real, z.imag], -1), []
            else:
                P, infos = direct((w, w, -w, -w), b, p_fix), []
    else:
        Rw = rotations[i] @ R_meas
        W = Rw @ W_loc @ np.swapaxes(Rw, 1, 2)
        if not cg_translations:  # S = I: the blocks are ±W
            if system is None or system.d != d:   # correlated x, y (2D), rotations by CG or LAGO: d×d blocks
                system = _BlockSystem(n, d, i, j, anchors)
            Wc = np.einsum("kab,kb->ka", W, c)
            b = np.stack([np.bincount(j, Wc[:, a], minlength=n) - np.bincount(i, Wc[:, a], minlength=n)
                          for a in range(d)], -1)
            P, infos = direct((W, W, -W, -W), b.reshape(n * d, 1), p_fix.reshape(-1, 1)), []
        else:
            S = np.broadcast_to(np.eye(d), (m, d, d))
            A, b = _normal_equations(n, d, i, j, S, W, c)
            P, infos = solve(red_d, A, b, p_fix.reshape(-1), S, W, cg=True, tol=tol_t)
    positions = P.reshape(n, d)
    t3 = time.perf_counter()
    info["translation_iterations"] = [c_.iterations for c_ in infos]
    info["translation_converged"] = all(c_.converged for c_ in infos)
    info["setup_seconds"] = t1 - t0
    info["rotation_seconds"] = t2 - t1
    info["translation_seconds"] = t3 - t2
    info["seconds"] = t3 - t0
    return ChordalResult(rotations=rotations, positions=positions, info=info)
