"""Coarse basis functions on the interface: rigid-body or unit modes, GDSW and RGDSW partitions of unity.

Each interface component gets the rigid-body modes of the pose graph (translations and rotation
about the component's centroid) written in each pose's GTSAM tangent coordinates; without vertex
geometry, the algebraic unit vectors per dof are used (the paper's choice, identical in span for
single-pose components). GDSW: one set of modes per component. RGDSW: modes only on coarse nodes,
spread to the other interface vertices with weights 1/#ancestors (paper Sec. 3.3). "gdsw-linear":
nodes at the ends of (and along) every entity with hat-function weights; "rgdsw-linear": the same
with the end nodes of entities that meet merged into junction nodes (:mod:`.linear`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..dd.geometry import VertexGeometry
from ..dd.interface import Interface
from .linear import junction_linear_partition, linear_partition
from ..util import sorted_unique

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


def rigid_transport(old: VertexGeometry, new: VertexGeometry, vertices: np.ndarray) -> np.ndarray:
    """(len(vertices), dim, dim) maps T_v = Ad(X_new⁻¹ X_old) taking a rigid motion's tangent
    coordinates at each vertex's old pose to those at its new pose: T_v · rigid_modes(old) =
    rigid_modes(new) about the same centers (the modes are M_v = Ad(X_v⁻¹) times a per-center
    constant, :func:`rigid_modes`). Pose2: [[R_nᵀR_o, R_nᵀJ(x_n − x_o)], [0, 1]]; Pose3 (ω, v):
    [[R_nᵀR_o, 0], [−R_nᵀ[x_n − x_o]×R_o, R_nᵀR_o]]."""
    dx = new.positions[vertices] - old.positions[vertices]
    m = len(vertices)
    if new.d == 2:   # elementwise: (cos, sin) of both headings (batched 2 × 2 products cost 4× more)
        cn, sn = new.rotations[vertices, 0, 0], new.rotations[vertices, 1, 0]
        co, so = old.rotations[vertices, 0, 0], old.rotations[vertices, 1, 0]
        c, s = cn * co + sn * so, cn * so - sn * co   # R_nᵀR_o
        T = np.zeros((m, 3, 3))
        T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
        T[:, 0, 2] = cn * -dx[:, 1] + sn * dx[:, 0]   # R_nᵀ J dx, J dx = (−dx_y, dx_x)
        T[:, 1, 2] = -sn * -dx[:, 1] + cn * dx[:, 0]
        T[:, 2, 2] = 1.0
        return T
    Rn_t = np.swapaxes(new.rotations[vertices], 1, 2)
    R = Rn_t @ old.rotations[vertices]
    cross = np.zeros((m, 3, 3))  # −[dx]×
    cross[:, 0, 1], cross[:, 0, 2], cross[:, 1, 2] = dx[:, 2], -dx[:, 1], dx[:, 0]
    cross[:, 1, 0], cross[:, 2, 0], cross[:, 2, 1] = -dx[:, 2], dx[:, 1], -dx[:, 0]
    T = np.zeros((m, 6, 6))
    T[:, :3, :3] = T[:, 3:, 3:] = R
    T[:, 3:, :3] = Rn_t @ cross @ old.rotations[vertices]
    return T


def rigid_mode_pattern(d: int, rotation: bool) -> np.ndarray:
    """(dim, n_modes) mask of the entries of :func:`rigid_modes` that are not zero by construction
    (a translation does not move the rotation coordinates); the others are nonzero for generic poses."""
    dim = 3 if d == 2 else 6
    mask = np.ones((dim, dim), dtype=bool)
    if d == 2:
        mask[2, :2] = False
    else:
        mask[:3, :3] = False
    return mask if rotation else mask[:, :d]  # the d translations


def gdsw_partition(interface: Interface):
    """GDSW: every interface component is a coarse node; each of its vertices has weight 1.

    Returns (vertex, node, weight) pairs — interface vertex index, coarse node (component), weight —
    and the coarse nodes."""
    nverts = interface.size
    return np.arange(nverts), interface.component, np.ones(nverts), np.arange(interface.n_components)


def rgdsw_partition(interface: Interface):
    """RGDSW: coarse nodes are the components with maximal subdomain sets; every interface vertex
    takes weight 1/#ancestors from each ancestor node (a partition of unity on Γ)."""
    is_node, anc = interface.coarse_nodes()
    A = sp.csr_matrix(anc[interface.component])  # interface vertex × ancestor node
    counts = np.diff(A.indptr)
    pair_v = np.repeat(np.arange(interface.size), counts)
    return pair_v, A.indices, 1.0 / counts[pair_v], np.flatnonzero(is_node)


# interface partitions of unity by name: a new coarse space is one function plus one line here.
# A function returns (vertex, node, weight) pairs and the nodes as components — or, for nodes that
# are not components, (vertex, node, weight) pairs, the node count and the component of each node
COARSE_SPACES = {"gdsw": gdsw_partition, "rgdsw": rgdsw_partition, "gdsw-linear": linear_partition,
                 "rgdsw-linear": junction_linear_partition}
# spaces whose every column lies on one component's vertices or on its descendants': the component's
# subdomain set is the column's (others take the union over the column's vertices)
COMPONENT_SPACES = ("gdsw", "rgdsw")


def interface_values(interface: Interface, offsets: np.ndarray, kind: str = "gdsw",
                     geometry: VertexGeometry | None = None, rotation: bool = True,
                     translation_mask: np.ndarray | None = None):
    """Φ_Γ as triplets (global dof, column, value) and the interface component of each column."""
    try:
        partition_of_unity = COARSE_SPACES[kind]
    except KeyError:
        raise ValueError(f"unknown coarse space {kind!r}; choose one of {', '.join(COARSE_SPACES)}") from None
    comp = interface.component
    # the partition of unity depends on the interface only: computed once per interface and kind
    cache = interface.__dict__.setdefault("_partitions_of_unity", {})  # (a frozen dataclass's own dict)
    pou = cache[kind] if kind in cache else cache.setdefault(kind, partition_of_unity(interface))
    if len(pou) == 4:  # nodes are interface components
        pair_v, pair_node, weight, nodes = pou
        node_col = np.full(interface.n_components, -1, dtype=np.int64)
        node_col[nodes] = np.arange(len(nodes))
    else:  # nodes of their own, each in one component
        pair_v, pair_node, weight, n_nodes, nodes = pou
        node_col = np.arange(n_nodes)
    verts = interface.vertices[pair_v]
    starts = offsets[verts]
    dim = int(offsets[verts[0] + 1] - starts[0]) if len(verts) else 0
    uniform = len(verts) and np.all(offsets[verts + 1] - starts == dim)
    if geometry is not None and uniform and dim == {2: 3, 3: 6}[geometry.d]:
        # the triplets' pattern does not depend on the poses: found once per interface (a rebuild
        # only computes the modes' numbers; 3D 91 125 poses: 1.4 s per rebuild before)
        rows, cols, pairs, mask, column_component = _rigid_pattern(
            interface, offsets, kind, pou, verts, starts, dim, geometry.d, rotation, node_col, nodes)
        if len(pou) == 4:
            # centroid of every coarse node's own vertices
            cnt = np.bincount(comp, minlength=interface.n_components)
            centers = np.stack([np.bincount(comp, weights=geometry.positions[interface.vertices, k],
                                            minlength=interface.n_components) for k in range(geometry.d)], 1)
            centers /= np.maximum(cnt, 1)[:, None]
        else:
            # weighted centroid of every node's support
            cnt = np.bincount(pair_node, weights=weight, minlength=n_nodes)
            centers = np.stack([np.bincount(pair_node, weights=weight * geometry.positions[verts, k],
                                            minlength=n_nodes) for k in range(geometry.d)], 1)
            centers /= np.where(cnt > 0, cnt, 1.0)[:, None]
        if pairs is not None:
            verts, pair_node, weight = verts[pairs], pair_node[pairs], weight[pairs]
        M = rigid_modes(geometry, verts, centers[pair_node], rotation)  # (pairs, dim, modes)
        vals = (M[:, mask] * weight[:, None]).ravel()  # structural zeros kept as explicit zeros
        return rows, cols, vals, column_component
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
    used, cols = sorted_unique(cols, return_inverse=True)
    column_component = nodes[used // max(n_modes, 1)]
    return rows, cols.ravel(), vals, column_component


def _rigid_pattern(interface: Interface, offsets, kind, pou, verts, starts, dim: int, d: int, rotation: bool,
                   node_col, nodes):
    """Rows, renumbered columns, the pairs of nonzero weight (None: all), the modes' structural
    mask and the component of each column of the rigid-mode triplets; cached on the interface."""
    cache = interface.__dict__.setdefault("_rigid_patterns", {})  # (a frozen dataclass's own dict)
    key = (kind, d, rotation)
    if key in cache and cache[key][0] is offsets:
        return cache[key][1:]
    pair_node, weight = pou[1], pou[2]
    mask = rigid_mode_pattern(d, rotation)
    n_modes = mask.shape[1]
    pairs = None if np.all(weight != 0.0) else np.flatnonzero(weight != 0.0)
    if pairs is not None:
        starts, pair_node = starts[pairs], pair_node[pairs]
    mode_dim, mode = np.nonzero(mask)  # row-major: the order of M[:, mask]
    itype = np.int32 if max(int(offsets[-1]), len(node_col) * n_modes) < 2**31 - 1 else np.int64
    rows = (starts[:, None] + mode_dim[None, :]).astype(itype).ravel()
    # columns numbered densely by node (nodes without a vertex dropped): every mode of a node has an
    # entry at each of its vertices, so the nodes are renumbered, not the (pairs x entries) columns
    used, node = sorted_unique(node_col[pair_node], return_inverse=True)
    cols = (node.astype(itype).reshape(-1, 1) * n_modes + mode[None, :].astype(itype)).ravel()
    rows.flags.writeable = cols.flags.writeable = False  # shared by every rebuild (recognised by identity)
    result = rows, cols, pairs, mask, nodes[np.repeat(used, n_modes)]
    cache[key] = (offsets, *result)
    return result


def column_subdomains(interface: Interface, offsets: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                      n_columns: int) -> sp.csr_matrix:
    """(n_columns × N) incidence: the union of the subdomain sets of the interface vertices where
    each column of Φ_Γ (triplet rows = global dofs, cols) is nonzero — the subdomains whose
    interiors its harmonic extension reaches."""
    dims = np.diff(offsets)
    if len(dims) and np.all(dims == dims[0]):   # one pose kind: a division, not a search of the offsets
        vertex = rows // int(dims[0])
    else:
        vertex = np.searchsorted(offsets, rows, side="right") - 1
    where = np.zeros(len(dims), dtype=np.int64)   # each interface vertex's place in Γ, by a map (no search)
    where[interface.vertices] = np.arange(interface.size)
    where = where[vertex]
    P = sp.csr_matrix((np.ones(len(rows)), (cols, where)), shape=(n_columns, interface.size))
    C = sp.csr_matrix(P @ interface.subdomains)
    C.data[:] = 1.0
    C.sort_indices()
    return C
