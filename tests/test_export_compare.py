"""export: per-view geometry agrees with the lab model; compare: physical verdicts."""

import json

import numpy as np
import pytest
from click.testing import CliRunner

from conecal.cli.main import cli
from conecal.geometry import ConeGeometry
from conecal.kinematics import Chain, LinearAxis, RotaryAxis


@pytest.fixture(scope="module")
def rotation_result(system, tmp_path_factory):
    """fit-linear then fit-rotation on the shared two-scan system."""
    dl, dr = system
    root = tmp_path_factory.mktemp("exp")
    run = CliRunner().invoke
    for args in (["detect", dl, "-o", root / "lm.json"], ["detect", dr, "-o", root / "rm.json"],
                 ["fit-linear", dl, "--markers", root / "lm.json", "-o", root / "g.json"],
                 ["fit-rotation", dr, "--markers", root / "rm.json", "--geometry", root / "g.json", "-o", root / "g2.json"]):
        r = run(cli, [str(a) for a in args])
        assert r.exit_code == 0, r.output
    return root, dr


@pytest.mark.parametrize("fmt,ext", [("astra", ".txt"), ("matrices", ".npy")])
def test_export_views_project_like_the_lab_model(rotation_result, fmt, ext):
    root, scan = rotation_result
    out = root / f"views{ext}"
    r = CliRunner().invoke(cli, ["export", str(root / "g2.json"), "--scan", str(scan), "--format", fmt, "-o", str(out)])
    assert r.exit_code == 0, r.output
    arr = np.load(out) if ext == ".npy" else np.loadtxt(out)
    doc = json.loads((root / "g2.json").read_text())
    g = ConeGeometry.from_dict(doc)
    chain = Chain(tuple(LinearAxis(a["name"], a["direction"], a.get("scale", 1.0)) if a["type"] == "linear"
                        else RotaryAxis(a["name"], a["direction"], a["point"]) for a in doc["axes"]))
    from conecal.scan import load_scan

    s = load_scan(scan)
    T = chain.transforms(s.log.readings)
    p = np.random.default_rng(0).uniform(-5, 5, (20, 3))           # points at rest on the sample
    for k in range(len(T)):
        lab = g.project(T[k].apply(p))
        if fmt == "astra":
            view = ConeGeometry.from_astra_vec(arr[k], shape=g.shape).project(p)
        else:
            h = np.column_stack([p, np.ones(len(p))]) @ arr[k].reshape(3, 4).T
            view = h[:, :2] / h[:, 2:]
        assert np.allclose(view, lab, atol=1e-6)


def test_compare_verdicts(rotation_result, tmp_path):
    root, _ = rotation_result
    run = CliRunner().invoke
    a = root / "g2.json"
    assert run(cli, ["compare", str(a), str(a)]).exit_code == 0
    doc = json.loads(a.read_text())
    noisy = json.loads(json.dumps(doc))
    noisy["source"] = [x * (1 + 1e-12) for x in doc["source"]]         # float noise never fails
    (tmp_path / "noisy.json").write_text(json.dumps(noisy))
    assert run(cli, ["compare", str(a), str(tmp_path / "noisy.json")]).exit_code == 0
    moved = json.loads(json.dumps(doc))
    moved["detector"]["origin"] = [doc["detector"]["origin"][0] + 0.05] + doc["detector"]["origin"][1:]  # 0.25 px
    (tmp_path / "moved.json").write_text(json.dumps(moved))
    r = run(cli, ["compare", str(a), str(tmp_path / "moved.json")])
    assert r.exit_code == 1 and "px" in r.output and "DIFFER" in r.output
    theta = next(x for x in moved["axes"] if x["name"] == "theta")
    moved["detector"]["origin"] = doc["detector"]["origin"]
    theta["point"] = [theta["point"][0] + 0.02] + theta["point"][1:]          # 0.02 mm axis shift
    (tmp_path / "axis.json").write_text(json.dumps(moved))
    r = run(cli, ["compare", str(a), str(tmp_path / "axis.json")])
    assert r.exit_code == 1 and "theta=" in r.output
    (tmp_path / "bad.json").write_text('{"format": "conecal-markers/1"}')
    assert run(cli, ["compare", str(a), str(tmp_path / "bad.json")]).exit_code == 2


def test_export_needs_a_scan_for_a_geometry(rotation_result):
    root, _ = rotation_result
    r = CliRunner().invoke(cli, ["export", str(root / "g2.json"), "--format", "astra", "-o", str(root / "x.txt")])
    assert r.exit_code == 2 and "--scan" in r.output
