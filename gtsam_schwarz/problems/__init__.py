"""A gallery of model problems (like pyamg.gallery): the paper's multi-loop problem, its 3D helix,
the 1D bar chain of the appendix, and survey grids (2D lawnmower, 3D floors) on which direct
factorization fills in."""

from .bars import BarChain, bar_chain
from .loops import HelixLoops, SquareLoops, helix_loops, square_loops, square_trajectory
from .survey import Lawnmower, Survey, Survey3D, lawnmower, lawnmower_cells, survey3d

__all__ = ["BarChain", "HelixLoops", "Lawnmower", "SquareLoops", "Survey", "Survey3D", "bar_chain",
           "helix_loops", "lawnmower", "lawnmower_cells", "square_loops", "square_trajectory", "survey3d"]
