"""Partitioners: edge → subdomain maps, by name (a registry, like the preconditioners').

Each partitioner takes a :class:`GraphStructure` and a number of subdomains and returns the
subdomain of every edge (the paper's nonoverlapping edge subdomains E_i, Sec. 3.1).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import pymetis  # the field's standard graph partitioner
import scipy.sparse as sp

from .structure import GraphStructure
from ..util import sorted_unique


def segment_partition(structure: GraphStructure, n_subdomains: int) -> np.ndarray:
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


def metis_partition(structure: GraphStructure, n_subdomains: int, seed: int = 0) -> np.ndarray:
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
    e = structure.edges
    v = np.r_[e[:, 0], e[:, 1]]
    part = np.r_[edge_subdomain, edge_subdomain]
    n_parts = int(part.max(initial=0)) + 1
    verts = sorted_unique(v * np.int64(n_parts) + part) // n_parts  # one entry per (vertex, subdomain)
    return int(np.count_nonzero(np.bincount(verts, minlength=structure.n_vertices) >= 2))


def auto_partition(structure: GraphStructure, n_subdomains: int) -> np.ndarray:
    """Trajectory segments or METIS, whichever has the smaller interface (so the smaller coarse space).

    Segments are the paper's choice and win on its model problem (one loop per subdomain, 2
    interface poses each); on real datasets with loop closures across the whole map they cut
    far more (M3500: 915 coarse functions against 252 with METIS)."""
    seg = segment_partition(structure, n_subdomains)
    met = metis_partition(structure, n_subdomains)
    return seg if interface_count(structure, seg) <= interface_count(structure, met) else met


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


PARTITIONERS: dict[str, Callable[[GraphStructure, int], np.ndarray]] = {
    "auto": auto_partition,
    "segments": segment_partition,
    "metis": metis_partition,
}
PARTITIONS = tuple(PARTITIONERS)


def partition_edges(structure: GraphStructure, n_subdomains: int, name: str = "auto") -> np.ndarray:
    """Edge → subdomain by the partitioner registered as ``name``."""
    try:
        partitioner = PARTITIONERS[name]
    except KeyError:
        raise ValueError(f"unknown partition {name!r}; choose one of {', '.join(PARTITIONERS)}") from None
    return partitioner(structure, n_subdomains)
