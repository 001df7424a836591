"""A gallery of model problems (like pyamg.gallery): the paper's multi-loop problem, its 3D helix,
and the 1D bar chain of the appendix."""

from .bars import BarChain, bar_chain
from .loops import HelixLoops, SquareLoops, helix_loops, square_loops, square_trajectory

__all__ = ["BarChain", "HelixLoops", "SquareLoops", "bar_chain", "helix_loops", "square_loops",
           "square_trajectory"]
