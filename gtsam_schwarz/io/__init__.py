"""Pose-graph files: g2o / TORO reading with line-numbered errors, initial guesses, atomic writing."""

from .atomic import atomic_write
from .g2o import QUATERNION_TOLERANCE, GraphFileError, LoadedGraph, load_graph, read_vertices, write_g2o

__all__ = ["GraphFileError", "LoadedGraph", "QUATERNION_TOLERANCE", "atomic_write", "load_graph", "read_vertices", "write_g2o"]
