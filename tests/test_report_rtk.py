"""HTML report (rendered in headless Chromium when installed), RTK geometry
XML read back by itk-rtk, and an FDK check that the calibrated geometry
reconstructs sharper than the nominal one."""

import json
import re
import shutil
import subprocess

import numpy as np
import pytest
from click.testing import CliRunner

from conecal.cli.main import cli
from conecal.geometry.misalignment import misaligned
from conecal.export import per_view, projection_matrices
from conecal.geometry import ConeGeometry

itk = pytest.importorskip("itk", reason="itk-rtk is a test extra")


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def _project(M, X):
    h = np.einsum("vij,pj->vpi", M[:, :, :3], X) + M[:, None, :, 3]
    return h[..., :2] / h[..., 2:]


@pytest.fixture(scope="module")
def circular(tmp_path_factory):
    from conecal.simulate import circular_scan, write_scan

    sc = circular_scan(3, rows=96, cols=96, pitch=1.0, n_frames=90, shift_px=(4.0, -2.0), rotation_deg=(1.5, 0.5, -0.5))
    return write_scan(sc, tmp_path_factory.mktemp("circ") / "c", seed=3)


def test_rtk_xml_reprojects_like_conecal(circular, tmp_path):
    from conecal.export.rtk import read_rtk_xml, rtk_matrices
    from conecal.scan import load_scan

    scan = load_scan(circular)
    truth = json.loads((circular / "truth.json").read_text())
    g = ConeGeometry.from_dict(truth["geometry"])
    doc = {"format": "conecal-geometry/1", **g.to_dict(),
           "axes": [{"name": "theta", "type": "rotary", "direction": [0, 1, 0], "point": [0, 0, 0]}]}
    (tmp_path / "g.json").write_text(json.dumps(doc))
    r = run("export", tmp_path / "g.json", "--scan", circular, "--format", "rtk", "-o", tmp_path / "g.xml")
    assert r.exit_code == 0, r.output
    geo = read_rtk_xml(tmp_path / "g.xml")
    views = per_view(g, scan.nominal_transforms())
    P = projection_matrices(views).reshape(-1, 3, 4)
    M = rtk_matrices(geo, g)
    X = np.random.default_rng(0).normal(0, 15, (30, 3))
    assert len(M) == scan.n_frames
    assert np.abs(_project(M, X) - _project(P, X)).max() < 1e-6


def test_fdk_with_the_true_geometry_is_sharper(circular):
    from conecal.export.rtk import fdk, sharpness
    from conecal.scan import load_scan

    scan = load_scan(circular)
    truth = json.loads((circular / "truth.json").read_text())["misalignment"]
    p = [truth[k] for k in ("shift_u_px", "shift_v_px", "eta_deg", "theta_deg", "phi_deg")]
    stack = np.stack([scan.stack.read(k) for k in range(scan.n_frames)])
    T = scan.nominal_transforms()
    nominal = scan.nominal_geometry()
    vols = [fdk(stack, per_view(misaligned(nominal, q), T), size=(64, 64, 3), spacing=0.5) for q in (np.zeros(5), p)]
    assert sharpness(vols[1]) > 1.1 * sharpness(vols[0])


def test_html_report_every_figure_loads(circular, small_linear_scan, tmp_path):
    m = tmp_path / "m.json"
    g = tmp_path / "g.json"
    rp = tmp_path / "rp.json"
    assert run("detect", small_linear_scan, "-o", m).exit_code == 0
    assert run("fit-linear", small_linear_scan, "--markers", m, "-o", g).exit_code == 0
    r = run("rp-grid", circular, "-o", rp, "--pairs", "200", "--range", "theta_deg=1", "--range", "phi_deg=1")
    assert r.exit_code == 0, r.output
    out = tmp_path / "report"
    r = run("report", g, rp, "-o", out, "--reconstruct")
    assert r.exit_code == 0, r.output
    page = (out / "index.html").read_text()
    n = int(re.search(r'data-figures="(\d+)"', page).group(1))
    assert n >= 6 and page.count('<img class="figure"') == n
    assert "http://" not in page and "https://" not in page          # self-contained
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        pytest.skip("headless Chromium not installed (Debian: apt-get install chromium)")
    dom = subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--virtual-time-budget=5000",
                          "--dump-dom", (out / "index.html").as_uri()], capture_output=True, text=True, timeout=120).stdout
    loaded = re.search(r'data-figures-loaded="(\d+)"', dom)
    assert loaded is not None, dom[:500]
    assert int(loaded.group(1)) == n
