"""fit-rotation: Jacobian, recovery of axes and spheres, chains of axes, bundle."""

import json

import numpy as np
from click.testing import CliRunner

from conecal.cli.main import cli
from conecal.fit.markers import Observations
from conecal.fit.rotation import AxisSpec, ChainModel, fit_rotation
from conecal.geometry import ConeGeometry


def test_chain_jacobian_matches_finite_differences(rng):
    g = ConeGeometry.nominal(sod=150, sdd=600, shape=(512, 512), pixel_pitch=(0.2, 0.2))
    d2 = np.array([0.1, 0, 1.0]) / np.linalg.norm([0.1, 0, 1.0])
    axes = [AxisSpec("x", "linear", np.array([1.0, 0, 0]), np.zeros(3)),
            AxisSpec("t1", "rotary", np.array([0, 1.0, 0]), np.array([2.0, 0, 1])),
            AxisSpec("t2", "rotary", d2, np.array([0.0, 1, 0]))]
    m = 30
    q = np.column_stack([rng.uniform(-2, 2, m), rng.uniform(0, 360, m), rng.uniform(-10, 10, m)])
    model = ChainModel(g, axes, [1, 2], q, rng.integers(0, 4, m), 4, [0], np.full(4, 1.0), refine_geometry=True)
    x = rng.normal(0, 0.5, model.size())
    J = model.jacobian(x)
    for i in range(x.size):
        e = np.zeros(x.size)
        e[i] = 1e-5
        fd = (model.predict(x + e) - model.predict(x - e)) / 2e-5
        assert np.allclose(J[:, :, i], fd, rtol=1e-5, atol=1e-6 * max(1, np.abs(fd).max())), model.names()[i]


class FakeLog:
    def __init__(self, names, readings):
        self.names, self.readings = tuple(names), readings
        self.frame = np.arange(len(readings))

    def __len__(self):
        return len(self.readings)

    def column(self, n):
        return self.readings[:, self.names.index(n)]


class FakeScan:
    """Just what fit_rotation reads: config.axes, config.markers, log, root."""

    def __init__(self, axes_cfg, readings, diameter=2.0):
        from conecal.scan.config import AxisSpec as CfgAxis, MarkerSpec

        class Cfg:
            pass

        self.config = Cfg()
        self.config.axes = tuple(CfgAxis(**a) for a in axes_cfg)
        self.config.markers = MarkerSpec(diameter=diameter)
        self.log = FakeLog([a["name"] for a in axes_cfg], readings)
        self.root = "fake"


def test_two_rotary_axes_of_a_chain_are_recovered(rng):
    """A tilt axis under a rotation stage (hexapod rotation + stage), both moving."""
    g = ConeGeometry.nominal(sod=150, sdd=600, shape=(512, 512), pixel_pitch=(0.2, 0.2))
    true = [AxisSpec("tilt", "rotary", np.array([1.0, 0.004, 0.003]) / np.linalg.norm([1, 0.004, 0.003]),
                     np.array([0.0, 0.3, -0.2])),
            AxisSpec("theta", "rotary", np.array([0.005, 1.0, -0.004]) / np.linalg.norm([0.005, 1, -0.004]),
                     np.array([2.2, 0.0, 0.8]))]
    cfg = [{"name": "tilt", "type": "rotary", "direction": [1, 0, 0], "point": [0, 0, 0]},
           {"name": "theta", "type": "rotary", "direction": [0, 1, 0], "point": [2, 0, 1]}]
    tilt, theta = np.meshgrid([-10.0, 0.0, 10.0], np.arange(0, 360, 15.0), indexing="ij")
    q = np.column_stack([tilt.ravel(), theta.ravel()])
    spheres = np.array([[0, 0, 0], [4.0, -3, 2], [-3, 2, 5], [5, 4, -3.0]])
    n = len(q)
    sph = np.repeat(np.arange(4)[None], n, 0).ravel()
    rows = np.repeat(np.arange(n), 4)
    truth = ChainModel(g, true, [0, 1], q[rows], sph, 4, [0], np.full(4, 1.0))
    x_true = np.zeros(truth.size())
    x_true[8:] = spheres[1:].ravel()
    sigma = 0.05
    xy = truth.predict(x_true) + rng.normal(0, sigma, (len(rows), 2))
    obs = Observations(rows, rows, sph, xy, np.full(len(rows), sigma))
    fit = fit_rotation(FakeScan(cfg, q), obs, g)
    sig = dict(zip(fit.result.names, fit.result.sigma))
    for est, tru in zip(fit.axes, true):
        ang = np.degrees(np.arccos(est.direction @ tru.direction))
        s_ang = np.hypot(sig[f"{tru.name}_tilt_a"], sig[f"{tru.name}_tilt_b"])
        assert ang < 0.02 and ang < 4 * s_ang, (tru.name, ang, s_ang)
        dp = est.point - tru.point
        dp -= (dp @ tru.direction) * tru.direction
        s_pt = np.hypot(sig[f"{tru.name}_offset_a"], sig[f"{tru.name}_offset_b"])
        assert np.linalg.norm(dp) < 0.05 and np.linalg.norm(dp) < 4 * s_pt, (tru.name, np.linalg.norm(dp), s_pt)
    assert fit.result.undetermined == []
    assert abs(np.sqrt(fit.result.reduced_chi2) - 1) < 0.1


def test_end_to_end_through_detect_and_the_cli(system, tmp_path):
    lin, rot = system
    run = CliRunner().invoke
    for scan, out in ((lin, "lm.json"), (rot, "rm.json")):
        assert run(cli, ["detect", str(scan), "-o", str(tmp_path / out)]).exit_code == 0
    r = run(cli, ["fit-linear", str(lin), "--markers", str(tmp_path / "lm.json"), "-o", str(tmp_path / "g.json")])
    assert r.exit_code == 0, r.output
    r = run(cli, ["fit-rotation", str(rot), "--markers", str(tmp_path / "rm.json"), "--geometry", str(tmp_path / "g.json"),
                  "-o", str(tmp_path / "g2.json")])
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "g2.json").read_text())
    truth = json.loads((rot / "truth.json").read_text())["rotary_axis"]
    ax = next(a for a in doc["axes"] if a["name"] == "theta")
    d = np.array(ax["direction"])
    assert np.degrees(np.arccos(abs(d @ truth["direction"]))) < 0.02           # deg
    dp = np.array(ax["point"]) - truth["point"]
    assert np.linalg.norm(dp - (dp @ d) * d) < 0.02                              # mm
    assert doc["fit"]["rms_px"] < 0.1
    assert sum(s["reference"] for s in doc["spheres"]) == 1
    # one bundle over both scans, geometry refined
    r = run(cli, ["fit-rotation", str(rot), str(lin), "--markers", str(tmp_path / "rm.json"),
                  "--markers", str(tmp_path / "lm.json"), "--geometry", str(tmp_path / "g.json"),
                  "--refine-geometry", "-o", str(tmp_path / "g3.json")])
    assert r.exit_code == 0, r.output
    doc3 = json.loads((tmp_path / "g3.json").read_text())
    assert doc3["fit"]["undetermined"] == []
    assert sum(s["reference"] for s in doc3["spheres"]) == 2


def test_rotation_alone_cannot_fix_the_geometry(system, tmp_path):
    _, rot = system
    run = CliRunner().invoke
    assert run(cli, ["detect", str(rot), "-o", str(tmp_path / "rm.json")]).exit_code == 0
    r = run(cli, ["fit-rotation", str(rot), "--markers", str(tmp_path / "rm.json"), "--refine-geometry",
                  "-o", str(tmp_path / "g.json")])
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "g.json").read_text())
    assert "source_z" in doc["fit"]["undetermined"]
    assert any({"source_z", "detector_centre_z"} <= set(c) for c in doc["fit"]["null_combinations"])


def test_fit_rotation_bad_inputs(system, tmp_path):
    lin, rot = system
    run = CliRunner().invoke
    assert run(cli, ["detect", str(lin), "-o", str(tmp_path / "lm.json")]).exit_code == 0
    r = run(cli, ["fit-rotation", str(lin), "--markers", str(tmp_path / "lm.json"), "-o", str(tmp_path / "x.json")])
    assert r.exit_code == 2 and "rotary" in r.output
    r = run(cli, ["fit-rotation", str(rot), str(lin), "--markers", str(tmp_path / "lm.json"), "-o", str(tmp_path / "x.json")])
    assert r.exit_code == 2 and "--markers" in r.output
