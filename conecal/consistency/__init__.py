"""Data consistency of circular scans (Grangeat's redundant plane integrals).

Groundwork for ``rp-grid`` (issue 5): the per-view Radon-derivative table.
"""

from .radon import cosine_weighted, radon_derivative_table

__all__ = ["cosine_weighted", "radon_derivative_table"]
