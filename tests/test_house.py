"""The house rules that a change can silently break (issue 31): no import
cycle and no import up the declared layering, no module over ~500 lines,
the robust-σ constant written in one place."""

import re
from pathlib import Path

from benchmarks import import_graph

ROOT = Path(__file__).resolve().parents[1]


def test_no_import_cycle_and_nothing_imports_upwards(capsys):
    assert import_graph.main() == 0, capsys.readouterr().out


def test_layering_check_catches_an_upward_import(monkeypatch, capsys):
    # the check must be able to fail: declare geometry above the stages that use it
    layers = [row for row in import_graph.LAYERS if row != ["binding", "geometry"]] + [["geometry"]]
    layers[0] = layers[0] + ["binding"]
    monkeypatch.setattr(import_graph, "LAYERS", layers)
    assert import_graph.main() == 1
    assert "conecal.kinematics -> conecal.geometry" in capsys.readouterr().out


def test_no_module_is_longer_than_about_500_lines():
    long = {str(p.relative_to(ROOT)): n for p in (ROOT / "conecal").rglob("*.py")
            if (n := len(p.read_text().splitlines())) > 520}
    assert not long, long


def test_the_mad_to_sigma_factor_is_written_once():
    hits = [str(p.relative_to(ROOT)) for p in (ROOT / "conecal").rglob("*.py")
            if re.search(r"1\.4826", p.read_text())]
    assert hits == ["conecal/stats.py"], hits


def test_numba_caches_go_to_the_users_cache_not_beside_the_sources(tmp_path):
    """A compiled kernel's cache lands under $XDG_CACHE_HOME/conecal/numba (the installed package
    directory is not written to), and a user's NUMBA_CACHE_DIR is left to win."""
    import os
    import subprocess
    import sys

    code = ("import numpy as np\n"
            "from conecal.detect.kernels import _outside_all\n"
            "_outside_all(0, 0, np.zeros(1), np.zeros(1), np.zeros(1))\n"
            "from numba import config; print(config.CACHE_DIR)\n")
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["XDG_CACHE_HOME"] = str(tmp_path / "xdg")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert Path(out.stdout.strip()) == tmp_path / "xdg" / "conecal" / "numba"
    assert list((tmp_path / "xdg").rglob("kernels._outside_all-*.nbi"))
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "mine")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert Path(out.stdout.strip()) == tmp_path / "mine"
    assert list((tmp_path / "mine").rglob("kernels._outside_all-*.nbi"))
