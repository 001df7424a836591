"""Domain decomposition of a pose graph: structure, partitioners, overlapping subdomains, interface.

Plain numpy/scipy (and pymetis): nothing here knows GTSAM.
"""

from .decomposition import Decomposition, decompose, segments
from .geometry import VertexGeometry
from .index_sets import IndexSets, vertex_dofs
from .interface import Interface, find_interface
from .partition import (PARTITIONERS, PARTITIONS, auto_partition, choose_partition, coordinate_cells,
                        default_subdomains, geometric_partition, interface_count, metis_partition,
                        partition_edges, segment_partition)
from .structure import GraphStructure

__all__ = ["Decomposition", "GraphStructure", "IndexSets", "Interface", "PARTITIONERS", "PARTITIONS",
           "VertexGeometry", "auto_partition", "choose_partition", "coordinate_cells", "decompose",
           "default_subdomains", "find_interface", "geometric_partition", "interface_count", "metis_partition", "partition_edges", "segment_partition", "segments",
           "vertex_dofs"]
