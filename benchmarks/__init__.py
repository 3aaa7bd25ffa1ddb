"""Benchmarks: scripts run from the shell (``python benchmarks/bench_*.py``),
their independent generators, and the scenario builders the tests share
(``diagnose_cases``). Not part of the installed package."""
