"""Array helpers below every layer (any layer may import them; they import nothing of the package)."""

from .arrays import sorted_unique, vertex_dofs
from .pages import small_pages, with_small_pages
from .sparse import vertex_pattern

__all__ = ["small_pages", "sorted_unique", "vertex_dofs", "vertex_pattern", "with_small_pages"]
