"""Piecewise-linear partitions of unity along interface entities (coarse spaces "gdsw-linear" and
"rgdsw-linear" for grid-like pose graphs: surveys, stacked floors).

2D pose graphs behave like linear elasticity; on grids, METIS subdomains have long, ragged
interfaces, and the low-energy interface functions the coarse space must capture vary *along* the
interface edges (bending, stretching). GDSW's rigid modes are constant on each interface entity,
RGDSW's are constant around each cross point: neither contains them. Measured on a 150 × 150
lawnmower survey, 45 METIS subdomains, at the dead-reckoning linearization (random right-hand
side, CG to 1e-8):

=====================================================  =============  ====  ====
coarse space                                            per subdomain   κ    CG
=====================================================  =============  ====  ====
gdsw (graph-connected components: fragmented)              70.2         80    57
gdsw on two-hop entities (one rigid set per entity)         9.5        325    92
gdsw-linear: hats at both ends of every entity             16.7         52    49
rgdsw-linear, spacing ∞ (junction nodes only)               5.4        144    67
rgdsw-linear, spacing 4                                    13.6         29    41
rgdsw-linear, spacing 3.25 (the default)                   17.5         24    38
rgdsw-linear, spacing 3                                    18.7         21    36
every interface dof (the full discrete harmonic space)    124          5.0   18
=====================================================  =============  ====  ====

Every interface entity (vertices with equal subdomain sets, connected through at most two graph
edges: ``find_interface(group="two-hop")``) gets coarse nodes about ``spacing`` graph hops apart
along it — at least its two ends — and hat functions between consecutive nodes as weights: a vertex
at intrinsic coordinate t between nodes k and k+1 (in units of their distance) has weights 1 − t and
t. The intrinsic coordinate is the graph distance from one end of the entity (the vertex farthest
from an arbitrary start), for all entities at once by two multi-source BFS. ``rgdsw-linear`` then
merges the end nodes of entities that meet into one junction node — as RGDSW makes a cross point the
one node of the edges around it, but also where edges meet without a shared cross point, which
METIS partitions of pose graphs produce at most junctions — so the basis is continuous across
junctions. The weights of every interface vertex sum to one, so the rigid modes of all nodes times
their weights reproduce the rigid modes on Γ, whose harmonic extension is the null space of the
pose graph.

Why a spacing of a few hops: the default overlap grows along odometry only, so across an interface
that runs along the rows of a survey the overlapping subdomains do not overlap at all, and the coarse
space alone must resolve the interface there (with ``grow_along="all"``, the default spacing gives ~27 CG
iterations instead of ~37, and even the junction nodes alone give κ ≈ 18).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, dijkstra

from ..dd.interface import Interface
from ..util import sorted_unique

DEFAULT_SPACING = np.inf  # gdsw-linear: nodes at both ends of each entity only: rigid ⊗ {1, linear}
JUNCTION_SPACING = 3.25  # rgdsw-linear on curves (2D): ~18 coarse vectors per subdomain, ~37 CG on lawnmower surveys
FACE_RATIO = 3.0  # an entity with more vertices per unit of intrinsic length is a face (2D curves: ≤ 2)
FACE_SPACING = 6.0  # rgdsw-linear with faces (3D): nodes more than 3 two-hop steps apart, every vertex within 3 of one
FACE_RADIUS = 5  # rgdsw-linear with faces (3D): distance hats max(0, 1 − hops/5), normalized


def _within_components(interface: Interface) -> sp.csr_matrix:
    """The two-hop neighbour graph of Γ restricted to pairs in the same component."""
    N = interface.neighbours
    if N is None:
        raise ValueError("a linear coarse space needs the interface's two-hop neighbours: "
                         "find_interface(decomposition, group='two-hop')")
    C = N.tocoo()
    same = interface.component[C.row] == interface.component[C.col]
    m = interface.size
    return sp.csr_matrix((np.ones(int(same.sum())), (C.row[same], C.col[same])), shape=(m, m))


def _first_of_each(component: np.ndarray, n: int) -> np.ndarray:
    first = np.zeros(n, dtype=np.int64)
    first[component[::-1]] = np.arange(len(component))[::-1]
    return first


def entity_coordinate(interface: Interface) -> np.ndarray:
    """Intrinsic coordinate of every interface vertex along its entity: the graph distance (in the
    two-hop graph within the entity) from the entity's end, an eccentric vertex found as the
    farthest one from the entity's first vertex."""
    comp = interface.component
    nc = interface.n_components
    if interface.size == 0:
        return np.zeros(0)
    G = _within_components(interface)
    d0 = dijkstra(G, directed=False, unweighted=True, indices=_first_of_each(comp, nc), min_only=True)
    order = np.lexsort((d0, comp))  # by component, then distance: the last of each is the farthest
    far = np.zeros(nc, dtype=np.int64)
    far[comp[order]] = order
    d = dijkstra(G, directed=False, unweighted=True, indices=far, min_only=True)
    return np.where(np.isfinite(d), d, 0.0)


def linear_partition(interface: Interface, spacing=DEFAULT_SPACING, coordinate: np.ndarray | None = None):
    """Hat functions along every interface entity, nodes about ``spacing`` hops apart (at least
    the entity's two ends; one node for an entity whose vertices are all at one end). ``spacing``
    may be one number or one per entity.

    Returns (vertex, node, weight) pairs, the node count, and the entity (component) of each node,
    in the form :func:`~gtsam_schwarz.coarse.modes.interface_values` takes."""
    comp = interface.component
    nc = interface.n_components
    t = entity_coordinate(interface) if coordinate is None else coordinate
    length = np.zeros(nc)
    np.maximum.at(length, comp, t)
    spacing = np.broadcast_to(np.asarray(spacing, dtype=float), (nc,))
    with np.errstate(divide="ignore", invalid="ignore"):
        pieces = np.where(np.isfinite(spacing), np.maximum(1, np.round(length / spacing)), 1).astype(np.int64)
    pieces[length == 0] = 0  # a single node
    first_node = np.r_[0, np.cumsum(pieces + 1)][:-1]
    h = np.where(pieces > 0, length / np.maximum(pieces, 1), 1.0)
    x = t / h[comp]  # position in units of the node spacing
    k = np.clip(np.floor(x).astype(np.int64), 0, np.maximum(pieces[comp] - 1, 0))
    f = np.where(pieces[comp] > 0, x - k, 0.0)
    m = interface.size
    pair_v = np.r_[np.arange(m), np.arange(m)]
    pair_node = np.r_[first_node[comp] + k, first_node[comp] + k + 1]
    weight = np.r_[1.0 - f, f]
    keep = weight > 1e-14
    pair_v, pair_node, weight = pair_v[keep], pair_node[keep], weight[keep]
    node_component = np.repeat(np.arange(nc), pieces + 1)
    used, pair_node = sorted_unique(pair_node, return_inverse=True)  # drop nodes without weight
    return pair_v, pair_node.ravel(), weight, len(used), node_component[used]


def junction_linear_partition(interface: Interface, spacing=JUNCTION_SPACING, face_spacing=FACE_SPACING,
                              face_radius=FACE_RADIUS):
    """:func:`linear_partition` with the end nodes of entities that meet merged into junction nodes,
    and an interface with faces (3D) covered by nodes spread over all of it instead of hats along one coordinate.

    Where interface edges meet (a cross point shared by three or more subdomains, or — frequent on
    METIS partitions of pose graphs, whose edge subdomains need not share a vertex where three parts
    meet — just edge ends lying side by side), the end nodes of all entities there become one node,
    as RGDSW makes a cross point the one coarse node of the edges around it. Two end nodes are
    merged when a vertex where one has weight 1 is at most two graph edges from such a vertex of
    the other (transitively). The weights still sum to one at every interface vertex, and the basis
    functions are continuous across junctions.

    An entity with more than ``FACE_RATIO`` vertices per unit of its intrinsic length is a face (a
    2D patch of a 3D decomposition; 2D curves have at most 2). An interface with faces is covered
    as a whole instead, across entity boundaries: nodes are a maximal set of interface vertices
    pairwise more than ⌊face_spacing/2⌋ steps apart in the two-hop graph of Γ, junction vertices
    (more subdomains) first (:func:`spread_nodes`), with distance hats max(0, 1 − hops/face_radius)
    normalized to sum one as weights (:func:`distance_hats`). The weights are continuous across
    entities, so nothing is merged; merging sampled nodes transitively (the earlier construction)
    chained junctions into a few huge nodes as subdomains shrank, and CG grew with their number.

    Returns (vertex, node, weight) pairs, the node count, and for each node the component of
    largest multiplicity among its vertices (a merged node's support spans several components:
    the coarse space takes the union of their subdomain sets, see
    :func:`~gtsam_schwarz.coarse.modes.column_subdomains`)."""
    m, nc = interface.size, interface.n_components
    if m == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), 0, np.zeros(0, np.int64)
    comp = interface.component
    t = entity_coordinate(interface)
    length = np.zeros(nc)
    np.maximum.at(length, comp, t)
    if np.any(np.bincount(comp, minlength=nc) > FACE_RATIO * (length + 1)):
        # a 3D interface (it has faces): nodes spread over all of Γ, distance hats across entities
        G = interface.neighbours
        multiplicity = np.diff(sp.csr_matrix(interface.subdomains).indptr)
        nodes = spread_nodes(G, face_spacing, multiplicity)
        pair_v, pair_node, weight = distance_hats(G, nodes, max(face_radius, face_spacing // 2 + 1))
        n_nodes = len(nodes)
        anchors = (np.zeros(0, np.int64), np.zeros(0, np.int64))  # continuous already: no merging
    else:  # curves: hats along each, end nodes merged
        pair_v, pair_node, weight, n_nodes, node_component = linear_partition(interface, spacing, t)
        first = np.r_[True, node_component[1:] != node_component[:-1]]
        last = np.r_[node_component[1:] != node_component[:-1], True]
        anchor_pair = (first | last)[pair_node] & (weight >= 1.0 - 1e-12)
        anchors = (pair_node[anchor_pair], pair_v[anchor_pair])
    anchor = sp.csr_matrix((np.ones(len(anchors[0])), anchors), shape=(n_nodes, m))
    near = interface.neighbours + sp.identity(m, format="csr")
    link = (anchor @ near @ anchor.T).tocsr()
    _, label = connected_components(link, directed=False)
    n_merged = int(label.max()) + 1
    merged = label[pair_node]
    # representative component: the one with the most subdomains among the node's vertices
    multiplicity = np.diff(sp.csr_matrix(interface.subdomains).indptr)
    order = np.lexsort((-multiplicity[pair_v], merged))  # by node, largest multiplicity first
    head = np.r_[True, merged[order][1:] != merged[order][:-1]]
    representative = np.empty(n_merged, dtype=np.int64)
    representative[merged[order][head]] = comp[pair_v[order][head]]
    # both ends of a short entity may have become one node: one pair per (vertex, node)
    key, inverse = sorted_unique(pair_v * np.int64(n_merged) + merged, return_inverse=True)
    weight = np.bincount(inverse.ravel(), weights=weight, minlength=len(key))
    return key // n_merged, key % n_merged, weight, n_merged, representative


def spread_nodes(G: sp.csr_matrix, spacing: float, multiplicity: np.ndarray, seed: int = 0) -> np.ndarray:
    """Nodes on the whole interface graph ``G`` about ``spacing`` hops apart: a maximal set of
    vertices pairwise more than r = ⌊spacing/2⌋ hops apart (Luby's rounds, all at once), so every
    vertex is within r of a node; vertices shared by more subdomains (junctions) win ties first."""
    m = G.shape[0]
    r = max(int(spacing // 2), 1)
    step = _pattern(G + sp.identity(m, format="csr"))  # every row holds its diagonal: none is empty
    # the r-hop neighbourhood is r one-hop steps: its max and reach are taken by r sweeps over G
    # (the r-hop pattern itself had ~10x G's entries: 2.5 s to build at 91 125 3D poses)
    rng = np.random.default_rng(seed)
    priority = multiplicity.astype(float) + 0.5 * rng.random(m)
    alive = np.ones(m, dtype=bool)
    chosen = np.zeros(m, dtype=bool)
    while alive.any():
        p = np.where(alive, priority, -np.inf)
        best = p
        for _ in range(r):
            best = np.maximum.reduceat(best[step.indices], step.indptr[:-1])
        win = alive & (p >= best)
        chosen |= win
        near = win.astype(float)
        for _ in range(r):
            near = step @ near
        alive &= ~(near > 0)
    return np.flatnonzero(chosen)


def distance_hats(G: sp.csr_matrix, nodes: np.ndarray, radius: float):
    """Weights max(0, 1 − hops(v, k)/r), r = ⌈radius⌉, normalized to sum one at every vertex they
    reach (Shepard's partition of unity): (vertex, node index, weight) pairs. On a curve with nodes r
    apart these are the hats."""
    radius = max(int(np.ceil(radius)), 1)
    D = bounded_distances(G, nodes, radius).tocoo()  # node × vertex: 1 + radius − hops
    w = (D.data - 1.0) / radius
    keep = w > 0
    pair_node, pair_v, w = D.row[keep], D.col[keep], w[keep]
    total = np.bincount(pair_v, weights=w, minlength=G.shape[0])
    return pair_v, pair_node, w / total[pair_v]

def _pattern(M) -> sp.csr_matrix:
    M = sp.csr_matrix(M)
    M.data[:] = 1.0
    return M


def bounded_distances(G: sp.csr_matrix, sources: np.ndarray, radius: int) -> sp.csr_matrix:
    """(len(sources) × n): 1 + radius − (hops from the source) for every vertex within ``radius``
    hops of each source in the graph ``G`` (0 = out of reach): a bounded BFS from all sources at
    once by sparse products."""
    n, k = G.shape[0], len(sources)
    reached = sp.csr_matrix((np.ones(k), (np.arange(k), sources)), shape=(k, n))
    D = reached * float(radius + 1)
    level, step = reached, _pattern(G)
    for hop in range(1, radius + 1):
        nxt = _pattern(level @ step)
        nxt = sp.csr_matrix(nxt - nxt.multiply(reached))
        nxt.eliminate_zeros()
        if nxt.nnz == 0:
            break
        D = D + nxt * float(radius + 1 - hop)
        reached, level = reached + nxt, nxt
    return sp.csr_matrix(D)

