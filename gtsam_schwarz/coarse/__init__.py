"""Coarse spaces: rigid / unit modes, GDSW and RGDSW partitions of unity, harmonic extension.

Plain numpy/scipy: nothing here knows GTSAM.
"""

from .extension import HarmonicExtension
from .modes import COARSE_SPACES, interface_values, rigid_modes
from .space import CoarseSpace, gdsw_coarse_space

__all__ = ["COARSE_SPACES", "CoarseSpace", "HarmonicExtension", "gdsw_coarse_space", "interface_values",
           "rigid_modes"]
