"""Array helpers below every layer (any layer may import them; they import nothing of the package)."""

from .arrays import sorted_unique, vertex_dofs
from .pages import small_pages, with_small_pages
from .sparse import as_csr, vertex_pattern

__all__ = ["as_csr", "small_pages", "sorted_unique", "vertex_dofs", "vertex_pattern", "with_small_pages"]
