"""GDSW-type coarse spaces: interface modes extended by discrete harmonic extension (paper Sec. 3.3).

Each interface component gets the rigid-body modes of the pose graph (translations and rotation
about the component's centroid) written in each pose's GTSAM tangent coordinates; without vertex
geometry, the algebraic unit vectors per dof are used (the paper's choice, identical in span for
single-pose components). GDSW: one set of modes per component. RGDSW: modes only on coarse nodes,
spread to the other interface vertices with weights 1/#ancestors. Interior values solve
A_II φ_I = −A_IΓ φ_Γ; A_II is block diagonal over subdomain interiors (every edge lies in one
subdomain), so one factorization and one multi-column solve extend every basis function at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .decomposition import Decomposition
from .interface import Interface
from .linear_system import VertexGeometry
from .local_solvers import Gather, SparseCholesky, factorize

COARSE_SPACES = ("gdsw", "rgdsw")


@dataclass(frozen=True)
class CoarseSpace:
    Phi: sp.csr_matrix  # n × n_c coarse basis
    A0: sp.csr_matrix  # Φᵀ A Φ
    column_component: np.ndarray  # interface component (coarse node) of each column

    @property
    def size(self) -> int:
        return self.Phi.shape[1]


def rigid_modes(geometry: VertexGeometry, vertices: np.ndarray, centers: np.ndarray,
                rotation: bool) -> np.ndarray:
    """Rigid-body modes at ``vertices`` about ``centers`` in GTSAM tangent coordinates.

    Returns (len(vertices), dim, n_modes). Pose2 tangent (v_x, v_y, ω): translation t ↦
    (Rᵀt, 0), rotation about c ↦ (Rᵀ J (x − c), 1). Pose3 tangent (ω, v): translation t ↦
    (0, Rᵀt), rotation about axis e_k at c ↦ (Rᵀe_k, Rᵀ(e_k × (x − c))).
    """
    R = geometry.rotations[vertices]
    Rt = np.swapaxes(R, 1, 2)
    r = geometry.positions[vertices] - centers
    m = len(vertices)
    if geometry.d == 2:
        modes = np.zeros((m, 3, 3))
        modes[:, :2, 0:2] = Rt  # translations x, y
        perp = np.stack([-r[:, 1], r[:, 0]], axis=1)  # J (x − c)
        modes[:, :2, 2] = np.einsum("mij,mj->mi", Rt, perp)
        modes[:, 2, 2] = 1.0
        return modes if rotation else modes[:, :, :2]
    modes = np.zeros((m, 6, 6))
    modes[:, 3:, 0:3] = Rt  # translations
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1.0
        modes[:, :3, 3 + k] = Rt[:, :, k]
        modes[:, 3:, 3 + k] = np.einsum("mij,mj->mi", Rt, np.cross(e, r))
    return modes if rotation else modes[:, :, :3]


def interface_values(interface: Interface, offsets: np.ndarray, kind: str = "gdsw",
                     geometry: VertexGeometry | None = None, rotation: bool = True,
                     translation_mask: np.ndarray | None = None):
    """Φ_Γ as triplets (global dof, column, value) and the interface component of each column."""
    comp = interface.component
    nverts = interface.size
    if kind == "gdsw":
        pair_v, pair_node, weight = np.arange(nverts), comp, np.ones(nverts)
        nodes = np.arange(interface.n_components)
    elif kind == "rgdsw":
        is_node, anc = interface.coarse_nodes()
        A = sp.csr_matrix(anc[comp])  # interface vertex × ancestor node
        counts = np.diff(A.indptr)
        pair_v = np.repeat(np.arange(nverts), counts)
        pair_node = A.indices
        weight = 1.0 / counts[pair_v]
        nodes = np.flatnonzero(is_node)
    else:
        raise ValueError(f"unknown coarse space {kind!r}; choose one of {', '.join(COARSE_SPACES)}")
    node_col = np.full(interface.n_components, -1, dtype=np.int64)
    node_col[nodes] = np.arange(len(nodes))
    verts = interface.vertices[pair_v]
    starts = offsets[verts]
    dim = int(offsets[verts[0] + 1] - starts[0]) if len(verts) else 0
    uniform = len(verts) and np.all(offsets[verts + 1] - starts == dim)
    if geometry is not None and uniform and dim == {2: 3, 3: 6}[geometry.d]:
        # centroid of every coarse node's own vertices
        cnt = np.bincount(comp, minlength=interface.n_components)
        centers = np.stack([np.bincount(comp, weights=geometry.positions[interface.vertices, k],
                                        minlength=interface.n_components) for k in range(geometry.d)], 1)
        centers /= np.maximum(cnt, 1)[:, None]
        M = rigid_modes(geometry, verts, centers[pair_node], rotation)  # (pairs, dim, modes)
        n_modes = M.shape[2]
        rows = (starts[:, None, None] + np.arange(dim)[None, :, None]).repeat(n_modes, 2)
        cols = (node_col[pair_node][:, None, None] * n_modes + np.arange(n_modes)[None, None, :]).repeat(dim, 1)
        vals = M * weight[:, None, None]
    else:
        # algebraic modes: a unit vector per selected dof (paper Sec. 3.3, "(0,0,1) at the node")
        dims = offsets[verts + 1] - starts
        n_modes = int(dims.max()) if len(dims) else 0
        p = np.repeat(np.arange(len(verts)), dims)
        local = np.arange(int(dims.sum())) - np.repeat(np.cumsum(dims) - dims, dims)
        rows = starts[p] + local
        cols = node_col[pair_node][p] * n_modes + local
        vals = weight[p]
        if not rotation and translation_mask is not None:
            keep = translation_mask[rows]
            rows, cols, vals = rows[keep], cols[keep], vals[keep]
    rows, cols, vals = np.ravel(rows), np.ravel(cols), np.ravel(vals)
    nz = vals != 0.0
    rows, cols, vals = rows[nz], cols[nz], vals[nz]
    # renumber columns densely (drops modes that vanish everywhere, e.g. unused dofs)
    used, cols = np.unique(cols, return_inverse=True)
    column_component = nodes[used // max(n_modes, 1)]
    return rows, cols.ravel(), vals, column_component


class HarmonicExtension:
    """Φ = [Φ_Γ; −A_II⁻¹ A_IΓ Φ_Γ] and A_0 = Φᵀ A Φ for one decomposition and interface.

    Interior and interface dofs, the patterns of A_II, A_IΓ and A_Γ·, and the symbolic
    factorization of A_II are computed once and reused for every new matrix with the same pattern.
    The right-hand sides are compressed: subdomain i only sees the K_i coarse columns whose
    subdomain set contains i, so all subdomains share K = max K_i columns of one solve with A_II.
    """

    def __init__(self, decomposition: Decomposition, interface: Interface):
        offsets = decomposition.structure.offsets
        self.n = decomposition.structure.n_dofs
        owner_dof = np.repeat(interface.interior_subdomain, np.diff(offsets))  # −1 on Γ
        self.interior = np.flatnonzero(owner_dof >= 0)
        self.gamma = np.flatnonzero(owner_dof < 0)
        self.sub = owner_dof[self.interior]
        I, G = self.interior, self.gamma
        self._A_II = Gather(lambda M: M[I][:, I])
        self._A_IG = Gather(lambda M: M[I][:, G])
        self._A_G = Gather(lambda M: M[G])
        self._factor = None
        self._cached = None  # (signature of the interface values, plan)

    def _solve_interior(self, A, B):
        pattern = self._A_II.pattern
        A_II = self._A_II(A)
        if isinstance(self._factor, SparseCholesky) and self._A_II.pattern is pattern:
            self._factor.refactor(A_II)  # same pattern: numbers only
        else:
            self._factor = factorize(A_II, "the interior matrix A_II")
        return self._factor(B)

    def _plan(self, A_IG: sp.csr_matrix, gamma_rows, gamma_cols, col_subdomains) -> dict:
        """Symbolic part of one extension: which products of A_IΓ and Φ_Γ entries add up to which
        entry of the compressed right-hand side, and where Φ's entries go in its CSR arrays."""
        nc, nI = col_subdomains.shape[0], len(self.interior)
        P = sp.csr_matrix(col_subdomains.T)  # subdomain × column
        P.sort_indices()
        counts = np.diff(P.indptr)
        K = int(counts.max())
        pair_sub = np.repeat(np.arange(P.shape[0]), counts)
        pair_key = pair_sub * np.int64(nc) + P.indices  # sorted
        local_k = np.arange(len(P.indices)) - P.indptr[pair_sub]
        # Φ_Γ triplets grouped by interface dof; every A_IΓ entry (i, g) meets each triplet of row g
        gpos = np.searchsorted(self.gamma, gamma_rows)
        by_g = np.argsort(gpos, kind="stable")
        g_ptr = np.searchsorted(gpos[by_g], np.arange(len(self.gamma) + 1))
        C = A_IG.tocoo()
        deg = g_ptr[C.col + 1] - g_ptr[C.col]
        term_a = np.repeat(np.arange(C.nnz), deg)
        first = np.repeat(g_ptr[C.col] - np.cumsum(deg) + deg, deg)
        term_phi = by_g[first + np.arange(len(term_a))]
        rows = C.row[term_a]
        key = self.sub[rows] * np.int64(nc) + gamma_cols[term_phi]
        at = np.minimum(np.searchsorted(pair_key, key), len(pair_key) - 1)
        if np.any(pair_key[at] != key):
            raise AssertionError("interface coupling outside its subdomain: decomposition is inconsistent")
        # A_IG entry order in C equals A_IG.data order (CSR → COO keeps it)
        table = np.full((P.shape[0], K), -1, dtype=np.int64)
        table[pair_sub, local_k] = P.indices
        cols = table[self.sub]
        r, k = np.nonzero(cols >= 0)  # row-major: already grouped by (sorted) interior row
        # Φ's CSR layout without a sort: Γ triplets (sorted by row) and interior entries are two
        # row-sorted lists with disjoint rows, merged by counting how many of the other come first
        g_order = np.argsort(gamma_rows, kind="stable")
        g_rows = gamma_rows[g_order]
        i_rows = self.interior[r]
        slot = np.empty(len(g_rows) + len(i_rows), dtype=np.int64)
        slot[:len(g_rows)] = np.arange(len(g_rows)) + np.searchsorted(i_rows, g_rows)
        slot[len(g_rows):] = np.arange(len(i_rows)) + np.searchsorted(g_rows, i_rows, side="right")
        indices = np.empty(len(slot), dtype=np.int64)
        indices[slot[:len(g_rows)]] = gamma_cols[g_order]
        indices[slot[len(g_rows):]] = cols[r, k]
        indptr = np.zeros(self.n + 1, dtype=np.int64)
        np.cumsum(np.bincount(np.concatenate([g_rows, i_rows]), minlength=self.n), out=indptr[1:])
        return {"K": K, "term_a": term_a, "term_phi": term_phi, "target": rows * K + local_k[at],
                "x_entries": r * K + k, "g_order": g_order, "slot": slot,
                "indices": indices, "indptr": indptr, "gpos": gpos, "nI": nI}

    def __call__(self, A: sp.spmatrix, gamma_rows: np.ndarray, gamma_cols: np.ndarray,
                 gamma_vals: np.ndarray, col_subdomains: sp.csr_matrix) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        """(Φ, A_0) for interface values given as triplets (global dof, column, value)."""
        n, nc = self.n, col_subdomains.shape[0]
        A = sp.csr_matrix(A)
        if nc == 0 or len(self.interior) == 0:
            Phi_G = sp.csr_matrix((gamma_vals, (gamma_rows, gamma_cols)), shape=(n, nc))
            return Phi_G, (Phi_G.T @ A @ Phi_G).tocsr()
        pattern = self._A_IG.pattern
        A_IG = self._A_IG(A)
        col_subdomains = sp.csr_matrix(col_subdomains)
        signature = (gamma_rows, gamma_cols, col_subdomains.indptr, col_subdomains.indices)
        cached = self._cached
        if (cached is None or self._A_IG.pattern is not pattern
                or not all(np.array_equal(a, b) for a, b in zip(cached[0], signature))):
            self._cached = cached = (tuple(np.array(a, copy=True) for a in signature),
                                     self._plan(A_IG, gamma_rows, gamma_cols, col_subdomains))
        plan = cached[1]
        K, nI = plan["K"], plan["nI"]
        weights = -A_IG.data[plan["term_a"]] * gamma_vals[plan["term_phi"]]
        Bc = np.bincount(plan["target"], weights=weights, minlength=nI * K).reshape(nI, K)
        X = self._solve_interior(A, Bc)
        data = np.empty(len(plan["slot"]))
        data[plan["slot"]] = np.concatenate([gamma_vals[plan["g_order"]], X.ravel()[plan["x_entries"]]])
        Phi = sp.csr_matrix((data, plan["indices"], plan["indptr"]), shape=(n, nc))
        # (AΦ)_I = A_II Φ_I + A_IΓ Φ_Γ = 0 for the harmonic extension, so Φᵀ A Φ = Φ_Γᵀ (AΦ)_Γ:
        # only the interface rows of A enter (Φ is dense on subdomain interiors; A Φ would not be)
        Phi_GG = sp.csr_matrix((gamma_vals, (plan["gpos"], gamma_cols)), shape=(len(self.gamma), nc))
        A0 = (Phi_GG.T @ (self._A_G(A) @ Phi)).tocsr()
        return Phi, ((A0 + A0.T) * 0.5).tocsr()


def harmonic_extension(A: sp.spmatrix, decomposition: Decomposition, interface: Interface,
                       gamma_rows: np.ndarray, gamma_cols: np.ndarray, gamma_vals: np.ndarray,
                       col_subdomains: sp.csr_matrix) -> sp.csr_matrix:
    """Φ with Φ_Γ given as triplets and Φ_I = −A_II⁻¹ A_IΓ Φ_Γ (one-off :class:`HarmonicExtension`)."""
    return HarmonicExtension(decomposition, interface)(A, gamma_rows, gamma_cols, gamma_vals, col_subdomains)[0]


def gdsw_coarse_space(A: sp.spmatrix, decomposition: Decomposition, interface: Interface,
                      kind: str = "gdsw", geometry: VertexGeometry | None = None,
                      rotation: bool = True, translation_mask: np.ndarray | None = None,
                      extension: HarmonicExtension | None = None) -> CoarseSpace:
    """GDSW (``kind="gdsw"``) or RGDSW (``"rgdsw"``) coarse space, with or without rotations.

    Pass the same ``extension`` for successive matrices to reuse its symbolic work."""
    offsets = decomposition.structure.offsets
    rows, cols, vals, column_component = interface_values(
        interface, offsets, kind, geometry, rotation, translation_mask)
    col_subdomains = sp.csr_matrix(interface.component_subdomains()[column_component]) \
        if len(column_component) else sp.csr_matrix((0, decomposition.n_subdomains))
    extension = extension or HarmonicExtension(decomposition, interface)
    Phi, A0 = extension(A, rows, cols, vals, col_subdomains)
    return CoarseSpace(Phi=Phi, A0=A0, column_component=column_component)
