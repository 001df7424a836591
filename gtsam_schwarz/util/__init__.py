"""Array helpers below every layer (any layer may import them; they import nothing of the package)."""

from .arrays import sorted_unique
from .sparse import vertex_pattern

__all__ = ["sorted_unique", "vertex_pattern"]
