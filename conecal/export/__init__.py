"""Per-view geometry for reconstructors: ASTRA cone_vec rows, projection matrices."""

from .views import astra_vectors, per_view, projection_matrices, views, write_array

__all__ = ["astra_vectors", "per_view", "projection_matrices", "views", "write_array"]
