"""Coarse spaces: rigid / unit modes, GDSW, RGDSW and piecewise-linear partitions of unity,
harmonic extension.

Plain numpy/scipy: nothing here knows GTSAM.
"""

from .extension import HarmonicExtension
from .linear import entity_coordinate, junction_linear_partition, linear_partition
from .modes import COARSE_SPACES, column_subdomains, interface_values, rigid_modes
from .extension import CoarseBasis
from .space import CoarseSpace, coarse_columns, gdsw_coarse_space

__all__ = ["COARSE_SPACES", "CoarseBasis", "CoarseSpace", "coarse_columns", "HarmonicExtension", "column_subdomains", "entity_coordinate",
           "gdsw_coarse_space", "interface_values", "junction_linear_partition", "linear_partition",
           "rigid_modes"]
