"""Partitioners: edge → subdomain maps, by name (a registry, like the preconditioners').

Each partitioner takes a :class:`GraphStructure`, a number of subdomains and (optionally) the
vertices' coordinates, and returns the subdomain of every edge (the paper's nonoverlapping edge
subdomains E_i, Sec. 3.1).
"""

from __future__ import annotations

import itertools
from typing import Callable

import numpy as np
import pymetis  # the field's standard graph partitioner
import scipy.sparse as sp

from .structure import GraphStructure
from ..util import sorted_unique


def segment_partition(structure: GraphStructure, n_subdomains: int, coordinates=None) -> np.ndarray:
    """N contiguous trajectory segments: edge → subdomain.

    Odometry edge (u, u+1) sits at position u; a loop closure (u, v) at position v−1, i.e. with the
    segment in which it is observed (its later pose). Positions 0..n−2 are cut into N equal ranges,
    so on the paper's model problem with N = loops every loop (with its closure) is one subdomain.
    """
    npos = max(structure.n_vertices - 1, 1)
    N = int(min(max(int(n_subdomains), 1), npos))
    u, v = structure.edges[:, 0], structure.edges[:, 1]
    pos = np.where(structure.odometry, u, v - 1)
    return (pos * N) // npos


def metis_partition(structure: GraphStructure, n_subdomains: int, coordinates=None, seed: int = 0) -> np.ndarray:
    """Edge → subdomain from a METIS k-way partition of the vertices (pymetis; nested from
    ``NESTED_FROM`` parts, :func:`metis_parts`).

    An edge inside a vertex part goes to that part; a cut edge goes to the part of its later
    vertex, so its earlier vertex becomes an interface pose.
    """
    nv = structure.n_vertices
    N = int(min(max(int(n_subdomains), 1), max(nv, 1)))
    if N == 1 or len(structure.edges) == 0:
        return np.zeros(len(structure.edges), dtype=np.int64)
    adj = structure.adjacency()
    adj.sort_indices()
    return metis_parts(adj, N, seed)[structure.edges[:, 1]]


# METIS k-way's cost grows with the number of parts (its coarsest graph keeps ~30 vertices per part):
# lawnmower 600x600 into 3 600 parts 2.3-2.5 s, 1000x1000 into 10 000 parts 7.6 s. From this many
# parts the graph is first cut into about √N groups and each group into its share of the parts: 1.6
# and 4.7 s, the interface 0.3-0.8 % larger; on the 3D surveys the interface is smaller (32x32x32 into
# 1 024 parts 0.68 → 0.46 s, 25 259 → 23 140 interface poses; 45x45x45 into 2 848 parts 2.4 → 1.4 s,
# 76 125 → 65 637), LM the same CG counts, 2-4 % faster, peaks 3-5 % lower (docs/survey.md,
# "Thirteenth pass").
NESTED_FROM = 512


def _kway(adj: sp.csr_matrix, n_parts: int, seed: int) -> np.ndarray:
    """Vertex → part by one METIS k-way call (all in part 0 for a single part)."""
    if n_parts <= 1:
        return np.zeros(adj.shape[0], dtype=np.int64)
    _, parts = pymetis.part_graph(n_parts, adjacency=pymetis.CSRAdjacency(adj.indptr, adj.indices),
                                  options=pymetis.Options(seed=seed))
    return np.asarray(parts, dtype=np.int64)


def metis_parts(adj: sp.csr_matrix, n_parts: int, seed: int = 0) -> np.ndarray:
    """Vertex → part for a symmetric adjacency (sorted indices, no diagonal): METIS k-way, or from
    ``NESTED_FROM`` parts nested: ~√N groups by k-way, then each group cut into a share of the N
    parts proportional to its vertices (one k-way call per group; part numbers may skip a few)."""
    nv = adj.shape[0]
    if n_parts < NESTED_FROM:
        return _kway(adj, n_parts, seed)
    groups = _kway(adj, int(round(np.sqrt(n_parts))), seed)
    n_groups = int(groups.max()) + 1
    size = np.bincount(groups, minlength=n_groups)
    share = np.minimum(size, np.maximum(1, np.rint(size * (n_parts / nv)).astype(np.int64)))
    first_part = np.cumsum(share) - share
    order = np.argsort(groups, kind="stable")
    start = np.cumsum(size) - size
    # the groups' own adjacencies as diagonal blocks of the permuted graph (edges between groups dropped)
    P = sp.csr_matrix(adj[order][:, order])
    row = np.repeat(np.arange(nv), np.diff(P.indptr))
    group_of = groups[order]
    keep = group_of[row] == group_of[P.indices]
    indptr = np.r_[0, np.cumsum(np.bincount(row[keep], minlength=nv))]
    B = sp.csr_matrix((np.ones(int(indptr[-1])), P.indices[keep], indptr), shape=P.shape)
    del P, row, keep
    parts = np.empty(nv, dtype=np.int64)
    for g in range(n_groups):  # a loop over ~√N groups, each one METIS call
        lo, hi = int(start[g]), int(start[g] + size[g])
        a, b = int(B.indptr[lo]), int(B.indptr[hi])
        block = sp.csr_matrix((B.data[a:b], B.indices[a:b] - lo, B.indptr[lo:hi + 1] - a), shape=(hi - lo, hi - lo))
        parts[order[lo:hi]] = first_part[g] + _kway(block, int(share[g]), seed)
    return parts


def interface_count(structure: GraphStructure, edge_subdomain: np.ndarray) -> int:
    """Vertices whose edges lie in two or more subdomains (the size of Γ for this edge partition)."""
    return _interface_size(structure.edges, edge_subdomain, structure.n_vertices)


def _interface_size(edges: np.ndarray, edge_subdomain: np.ndarray, n_vertices: int) -> int:
    """Vertices whose incident edges lie in two or more subdomains: the least and the largest subdomain
    per vertex over its edges, by unbuffered minimum and maximum (a graph of 1M vertices and 2M edges
    0.04 s against 0.16 s grouping the incidences by vertex with scipy's counting sort)."""
    if len(edges) == 0:
        return 0
    part = np.asarray(edge_subdomain, dtype=np.int64)
    rows = np.r_[edges[:, 0], edges[:, 1]]
    both = np.r_[part, part]
    least = np.full(n_vertices, np.iinfo(np.int64).max)
    largest = np.full(n_vertices, -1, dtype=np.int64)   # −1: a vertex without edges
    np.minimum.at(least, rows, both)
    np.maximum.at(largest, rows, both)
    return int(np.count_nonzero((largest >= 0) & (least != largest)))


# -- geometric: cells of a coordinate multisection -------------------------------------------------

def _cuts_per_axis(extent: np.ndarray, n_parts: int) -> np.ndarray:
    """Slabs per axis: as close to ``n_parts`` cells in all as the roundings allow, cells about as long
    on every axis (an axis shorter than a cell gets one slab; the longest takes what is left)."""
    k = np.ones(len(extent), dtype=np.int64)
    active = extent > 0
    side = 1.0
    while active.any():
        side = (np.prod(extent[active]) / n_parts) ** (1.0 / active.sum())
        short = active & (extent < side)
        if not short.any():
            break
        active &= ~short
    axes = np.flatnonzero(active)
    if len(axes) == 0:
        return k
    longest = int(axes[np.argmax(extent[axes])])
    others = [int(a) for a in axes if a != longest]
    best = None
    for choice in itertools.product(*[(max(1, int(np.floor(extent[a] / side))), int(np.ceil(extent[a] / side)))
                                      for a in others]):   # at most 4 roundings (3D)
        rest = int(np.prod(choice)) if choice else 1
        first = max(1, int(round(n_parts / rest)))
        ks = np.array([first, *choice], dtype=float)
        score = (abs(first * rest - n_parts), float(np.abs(np.log(ks * side / extent[[longest, *others]])).sum()))
        if best is None or score < best[0]:
            best = (score, first, choice)
    k[longest] = best[1]
    k[others] = best[2]
    return k


def coordinate_cells(coordinates: np.ndarray, n_parts: int) -> np.ndarray:
    """Vertex → cell of a multisection of the coordinates (n, d): equal-count slabs along the longest
    axis, each cut into equal-count slabs along the next, and so on; about ``n_parts`` compact cells of
    equal size (one sort per axis, no graph work). Cells are numbered densely from 0."""
    return _multisection(coordinates, n_parts)[0]


def _multisection(coordinates: np.ndarray, n_parts: int) -> tuple[np.ndarray, np.ndarray]:
    """(:func:`coordinate_cells`' cells, the slabs along each axis)."""
    X = np.asarray(coordinates, dtype=np.float64)
    if X.ndim != 2 or not np.all(np.isfinite(X)):
        raise ValueError(f"coordinates must be a finite (n, d) array, got shape {X.shape}")
    n = X.shape[0]
    if n == 0 or n_parts <= 1:
        return np.zeros(n, dtype=np.int64), np.ones(X.shape[1], dtype=np.int64)
    lo, hi = np.percentile(X, [1.0, 99.0], axis=0)   # the extent of the bulk (a few outliers do not set it)
    extent = hi - lo
    k = _cuts_per_axis(extent, min(int(n_parts), n))
    label = np.zeros(n, dtype=np.int64)
    cells = 1   # labels so far lie in 0..cells − 1
    for axis in np.argsort(-extent, kind="stable"):   # a loop over the (two or three) axes
        if k[axis] > 1:
            # by cell, then along the axis: a stable sort along the axis, then a stable one by cell
            # (a radix sort for 16-bit cells; 1M poses 0.14 against 0.18 s for a lexsort of both keys)
            order = np.argsort(X[:, axis], kind="stable")
            if cells > 1:
                by_cell = label[order].astype(np.uint16 if cells <= 1 << 16 else np.int64)
                order = order[np.argsort(by_cell, kind="stable")]
            cell = label[order]
            count = np.bincount(label, minlength=cells)
            rank = np.arange(n) - (np.cumsum(count) - count)[cell]
            label[order] = cell * k[axis] + rank * k[axis] // count[cell]
            cells *= int(k[axis])
    present = np.bincount(label, minlength=cells) > 0   # cells numbered densely, in label order
    return (np.cumsum(present) - 1)[label], k


def geometric_partition(structure: GraphStructure, n_subdomains: int, coordinates=None) -> np.ndarray:
    """Edge → subdomain from :func:`coordinate_cells` of the vertices' coordinates (the poses'
    positions): compact subdomains with straight interfaces where the graph follows the geometry
    (surveys of an area or a building: lawnmower 600x600 into 3 600 cells in 0.1 s, 69 147 interface
    poses against METIS's 72 109 in 1.7–2.2 s). A cut edge goes to its later vertex's cell, as in
    :func:`metis_partition`."""
    X = _coordinates(structure, coordinates)
    if X is None:
        raise ValueError("the geometric partition needs the vertices' coordinates (a graph of Pose2s or "
                         "Pose3s only); choose partition 'metis' or 'auto'")
    N = int(min(max(int(n_subdomains), 1), max(structure.n_vertices, 1)))
    if N == 1 or len(structure.edges) == 0:
        return np.zeros(len(structure.edges), dtype=np.int64)
    return coordinate_cells(X, N)[structure.edges[:, 1]]


def _coordinates(structure: GraphStructure, coordinates) -> np.ndarray | None:
    """The coordinates as an (n_vertices, d) float array, or None where there are none usable."""
    if coordinates is None:
        return None
    X = np.asarray(coordinates, dtype=np.float64)
    if X.ndim != 2 or X.shape[0] != structure.n_vertices or not np.all(np.isfinite(X)):
        return None
    return X


# the full METIS partition is skipped from this many vertices where, on a window of about
# 1/WINDOW_SHARE of the geometric cells (at most WINDOW_MAX_CELLS) around the middle of the map,
# METIS's partition of the window has an interface no smaller than the cells' by GEOMETRIC_TOLERANCE
# (METIS into 3 600 parts: 1.7 s at 360 000 poses, 5 s at 1M; the window's METIS ~1/16 of it). Below,
# all candidates are compared whole.
WINDOW_FROM = 20_000
WINDOW_SHARE = 16
WINDOW_MAX_CELLS = 256   # 1M poses in 10 000 cells: METIS on 256 cells' poses 0.10 s against 0.24 s on
                         # 625, the same verdict (interface ratio 1.00 against 0.95, tolerance 1.1)
GEOMETRIC_TOLERANCE = 1.1


def _geometric_holds(structure: GraphStructure, cells: np.ndarray, X: np.ndarray, slabs: np.ndarray) -> bool:
    """Whether the geometric cells cut a central window of the graph about as well as METIS does (the
    window: the cells whose centroids lie in the middle of the centroids along every cut axis)."""
    n_cells = int(cells.max()) + 1
    cut = np.flatnonzero(slabs > 1)
    size = np.bincount(cells, minlength=n_cells)
    centroid = np.stack([np.bincount(cells, X[:, a], minlength=n_cells) for a in cut], 1) / np.maximum(size, 1)[:, None]
    fraction = min(1.0 / WINDOW_SHARE, WINDOW_MAX_CELLS / n_cells)   # of the cells
    share = fraction ** (1.0 / max(len(cut), 1))   # of the cells along each cut axis
    lo, hi = np.quantile(centroid, [0.5 - share / 2, 0.5 + share / 2], axis=0)
    in_window = np.all((centroid >= lo) & (centroid <= hi), axis=1)
    parts = int(in_window.sum())
    if parts < 8:   # too few cells to judge: compare with METIS on the whole graph
        return False
    inside = in_window[cells]
    e = structure.edges
    e = e[inside[e[:, 0]] & inside[e[:, 1]]]
    local = np.cumsum(inside) - 1
    nw = int(inside.sum())
    u, v = local[e[:, 0]], local[e[:, 1]]
    adj = sp.csr_matrix((np.ones(2 * len(u)), (np.r_[u, v], np.r_[v, u])), shape=(nw, nw))
    adj.sum_duplicates()
    adj.sort_indices()
    metis = metis_parts(adj, parts)
    cells_w = sorted_unique(cells[inside], return_inverse=True)[1]
    return _interface_size(np.stack([u, v], 1), cells_w[v], nw) <= GEOMETRIC_TOLERANCE * _interface_size(
        np.stack([u, v], 1), metis[v], nw)


def choose_partition(structure: GraphStructure, n_subdomains: int, coordinates=None) -> tuple[str, np.ndarray]:
    """("segments" | "geometric" | "metis", edge → subdomain): the candidate with the smallest
    interface (so the smaller coarse space); ties go to the earlier one.

    Segments are the paper's choice and win on its model problem (one loop per subdomain, 2
    interface poses each); on real datasets with loop closures across the whole map they cut
    far more (M3500: 915 coarse functions against 252 with METIS). With coordinates, the geometric
    cells are a candidate: on grid-like worlds (surveys) they cut less than METIS and cost a sort
    instead of a graph partition (lawnmower 1000x1000, LM: coarse space 43 311 against 62 112, CG
    35 against 40, 51 against 67 s); on street networks they cut twice as much (city10000) and METIS
    wins. From :data:`WINDOW_FROM` vertices METIS runs whole only where a window says it may win."""
    candidates = [("segments", segment_partition(structure, n_subdomains))]
    X = _coordinates(structure, coordinates)
    metis_needed = True
    if X is not None and len(structure.edges) and n_subdomains > 1:
        N = int(min(int(n_subdomains), structure.n_vertices))
        cells, slabs = _multisection(X, N)
        if cells.max() + 1 >= 0.9 * N:   # not fewer cells than asked (positions all alike): a fair candidate
            candidates.append(("geometric", cells[structure.edges[:, 1]]))
            metis_needed = structure.n_vertices < WINDOW_FROM or not _geometric_holds(structure, cells, X, slabs)
    if metis_needed:
        candidates.append(("metis", metis_partition(structure, n_subdomains)))
    sizes = [interface_count(structure, part) for _, part in candidates]
    return candidates[int(np.argmin(sizes))]


def auto_partition(structure: GraphStructure, n_subdomains: int, coordinates=None) -> np.ndarray:
    """Segments, geometric cells (given coordinates) or METIS, whichever has the smallest interface
    (:func:`choose_partition`)."""
    return choose_partition(structure, n_subdomains, coordinates)[1]


# poses per subdomain by pose dimension (dofs per pose). In 3D a subdomain's factor and its share
# of Φ grow fast with its size; 64-pose subdomains cost less per solve (setup + CG) than 500-pose
# ones although CG takes a few more iterations (survey 32x32x32: 6.9 vs 10.6 s, 47 vs 38 CG to 1e-8;
# docs/survey.md, "Subdomain size in 3D"), and with inexact steps (11–18 CG per solve) 32 poses
# beat 64 on large graphs (LM, survey 45x45x45: 38.5 vs 44.6 s; 32x32x32: 10.6 vs 12.0 s) but not on
# small ones (8x24x24, 4 608 poses: 1.48 vs 1.35 s), which keep 64 (``SMALL_GRAPH_SUBDOMAIN_SIZE``).
# In 2D, 250 poses for solves to 1e-8: the setup shrinks with the subdomains while such a solve stays
# within 40 CG (300x300: 35 at 500, 38 at 250, 43 at 150, 49 at 100; docs/survey.md, "Subdomain size
# in 2D"). With inexact steps (13–17 CG per solve: forcing "auto", the default) the setup dominates
# and 100 poses are faster (LM with rgdsw-linear, one run each, ``INEXACT_SUBDOMAIN_SIZE``):
# lawnmower 600x600 250 poses 24.6 / 24.6 s, 100 21.8 / 21.0 s; 1000x1000 68.8 / 72.2 against
# 70.6 / 60.9 s; 300x300 4.5 / 4.8 against 4.3 / 3.9 s; peaks 6-13 % lower (docs/survey.md,
# "Thirteenth pass"). In 3D the 32-pose default is already the inexact steps' choice.
DEFAULT_SUBDOMAIN_SIZE = {3: 250, 6: 32}
INEXACT_SUBDOMAIN_SIZE = {3: 100}  # where the steps are solved to Eisenstat-Walker tolerances
SMALL_GRAPH_SUBDOMAIN_SIZE = {6: (16_384, 64)}  # (graphs with fewer poses than this, their size)


def default_subdomain_size(n_vertices: int, dofs_per_pose: int = 3, inexact: bool = False) -> int:
    """Poses per subdomain by pose dimension, graph size and whether the steps are solved inexactly
    (:data:`DEFAULT_SUBDOMAIN_SIZE`, :data:`INEXACT_SUBDOMAIN_SIZE`, :data:`SMALL_GRAPH_SUBDOMAIN_SIZE`)."""
    below, size = SMALL_GRAPH_SUBDOMAIN_SIZE.get(dofs_per_pose, (0, 0))
    if n_vertices < below:
        return size
    if inexact and dofs_per_pose in INEXACT_SUBDOMAIN_SIZE:
        return INEXACT_SUBDOMAIN_SIZE[dofs_per_pose]
    return DEFAULT_SUBDOMAIN_SIZE.get(dofs_per_pose, 250)


def default_subdomains(n_vertices: int, subdomain_size: int | None = None, dofs_per_pose: int = 3,
                       inexact: bool = False) -> int:
    """Number of subdomains chosen from the size: about ``subdomain_size`` poses each (None:
    :func:`default_subdomain_size`)."""
    if subdomain_size is None:
        subdomain_size = default_subdomain_size(n_vertices, dofs_per_pose, inexact)
    return max(1, int(round(n_vertices / max(subdomain_size, 1))))


PARTITIONERS: dict[str, Callable[..., np.ndarray]] = {
    "auto": auto_partition,
    "segments": segment_partition,
    "geometric": geometric_partition,
    "metis": metis_partition,
}
PARTITIONS = tuple(PARTITIONERS)


def partition_edges(structure: GraphStructure, n_subdomains: int, name: str = "auto", coordinates=None) -> np.ndarray:
    """Edge → subdomain by the partitioner registered as ``name`` (``coordinates``: the vertices'
    positions, (n_vertices, d), for the geometric candidate; None: without it)."""
    return named_partition(structure, n_subdomains, name, coordinates)[1]


def named_partition(structure: GraphStructure, n_subdomains: int, name: str = "auto",
                    coordinates=None) -> tuple[str, np.ndarray]:
    """(the partitioner that made it, edge → subdomain): ``auto`` names its choice."""
    try:
        partitioner = PARTITIONERS[name]
    except KeyError:
        raise ValueError(f"unknown partition {name!r}; choose one of {', '.join(PARTITIONERS)}") from None
    if name == "auto":
        return choose_partition(structure, n_subdomains, coordinates)
    return name, partitioner(structure, n_subdomains, coordinates)
