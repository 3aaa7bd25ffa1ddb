"""Reports: the self-contained HTML page and its figures."""

from .html import write_report

__all__ = ["write_report"]
