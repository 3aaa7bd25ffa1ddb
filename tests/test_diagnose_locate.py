"""diagnose locates a mismatch before naming it, claims only what brings the
fit to the noise with a physically possible value, and says when the image
level cannot be trusted."""

import json
from types import SimpleNamespace

import numpy as np
import pytest

from benchmarks import diagnose_cases as bench
from conecal.diagnose.image_select import ImageCandidate, _unphysical, untrusted_values
from conecal.diagnose.locate import FrameCurves, describe, locate
from conecal.diagnose.select import score



def sweep_recording(n=72, seed=0):
    """A stage swinging back and forth at varying speed, irregular times."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.3, 1.5, n))
    theta = 160 * np.sin(2 * np.pi * t / t[-1] * 2.5) + 20 * np.sin(2 * np.pi * t / t[-1] * 7)
    return SimpleNamespace(times=t, readings=theta[:, None], axis_names=["theta"], rotary=[True])


def curves(values, sigma=0.01):
    n = len(values)
    v = np.column_stack([values, np.zeros(n)])
    return FrameCurves(np.arange(n), ("rotation about axis theta", "shift along across"), ("deg", "mm"),
                       v, np.full_like(v, sigma), np.array([1.0, 10.0]))


def test_locate_holds_its_false_alarm_rate():
    rec = sweep_recording()
    rng = np.random.default_rng(1)
    fired = 0
    for _ in range(100):
        c = curves(rng.normal(0, 0.01, 72))
        c = FrameCurves(c.rows, c.names, c.units, rng.normal(0, 0.01, c.values.shape), c.sigma, c.px_per_unit)
        fired += bool(locate(rec, c))
    assert fired <= 4


@pytest.mark.parametrize("kind", ["harmonic3", "direction", "jump", "time"])
def test_locate_finds_the_variable_and_the_shape(kind):
    rec = sweep_recording(seed=2)
    rng = np.random.default_rng(3)
    q = np.deg2rad(rec.readings[:, 0])
    v = np.gradient(rec.readings[:, 0], rec.times)
    order = np.argsort(rec.times)
    signal = {"harmonic3": 0.05 * np.cos(3 * q + 0.4),
              "direction": 0.04 * np.sign(v),
              "jump": 0.05 * (np.arange(72) >= 40),
              "time": 0.08 * (1 - np.exp(-rec.times / (0.3 * rec.times[-1])))}[kind]
    found = locate(rec, curves(signal + rng.normal(0, 0.01, 72)))
    assert found, kind
    top = found[0]
    assert top["component"] == "rotation about axis theta"
    want = {"harmonic3": ("theta", "harmonic 3"), "direction": ("direction of theta", "direction"),
            "jump": ("time", "jump after the 40th"), "time": ("time", "")}[kind]
    assert top["variable"] == want[0] and want[1] in top["shape"], top
    assert abs(top["size"] - np.std(signal)) < 0.3 * np.std(signal) + 0.005
    assert top["variable"] in describe(top)
    # the curve as drawn: each frame's value and σ against the variable, and the shape fitted to it
    s = top["series"]
    x_true = {"harmonic3": rec.readings[:, 0], "direction": v, "jump": rec.times, "time": rec.times}[kind]
    assert np.allclose(s["x"], np.sort(x_true))
    assert np.allclose(s["sigma"], 0.01) and len(s["value"]) == 72
    truth = (signal - signal.mean())[np.argsort(x_true, kind="stable")]
    model = np.asarray(s["model"]) - np.mean(s["model"])
    assert np.sqrt(np.mean((model - truth) ** 2)) < 0.3 * np.std(signal), kind
    del order


def test_a_detector_field_the_library_lacks_is_located_not_named(tmp_path):
    """A quadratic warp along columns only (no radial or S-shaped member of
    ours has it), ~0.1 px at the edges: located over the detector, nothing
    claimed unless it reaches the noise."""
    path = bench.make(tmp_path, "clean", None, seed=21)
    m = json.loads((path / "markers.json").read_text())
    rows, cols = 256, 256
    for f in m["frames"]:
        for mk in f["markers"]:
            z = (mk["y"] - (rows - 1) / 2) / ((rows - 1) / 2)
            mk["x"] += 0.12 * z ** 2 * np.sign(mk["x"] - (cols - 1) / 2)
    (path / "markers.json").write_text(json.dumps(m))
    d = bench.run_one(path, image=False)
    assert d["located"] and d["located"][0]["variable"] == "detector position", d["located"]
    # the field as drawn: 9 x 9 arrows over the detector; what the geometry cannot absorb of the
    # warp varies along the columns and moves the markers along u
    field = d["located"][0]["field"]
    du, dv = np.asarray(field["du"]), np.asarray(field["dv"])
    assert du.shape == (9, 9) and len(field["u_px"]) == 9
    assert np.ptp(du[4]) > 0.05 and np.ptp(du[:, 4]) < 0.5 * np.ptp(du[4]) and np.abs(dv).max() < np.abs(du).max()
    assert d["located"][0]["level"] == "geometry" and "detector position" in d["located"][0]["description"]
    # the report shows where before what: the located table and its figure
    from click.testing import CliRunner
    from conecal.cli.main import cli

    res = CliRunner().invoke(cli, ["report", str(path / "diag.json"), "-o", str(tmp_path / "r")])
    assert res.exit_code == 0, res.output
    page = (tmp_path / "r" / "index.html").read_text()
    assert "Where the model and the recording differ" in page and "polynomial field of degree" in page
    assert page.index("Located: each curve") < page.index("held-out χ² gain</th>")
    for e in d["effects"]:      # any claim must be adequate
        assert d["rms_px_after"] <= 1.15 * d["noise_floor_px"]
    if not d["effects"]:
        assert d["verdict"].startswith("located, not named") and "detector position" in d["verdict"]


def test_claims_need_physical_values_not_pinned_at_a_bound():
    bh = ImageCandidate("beam_hardening", ("beam_hardening",), None, None,
                        impossible=lambda v: "beta < 0" if v[0] < 0 else None)
    assert _unphysical(bh, [-0.02]) == "beta < 0"
    assert _unphysical(bh, [0.05]) is None
    assert "bound" in _unphysical(bh, [3.0])
    lag = ImageCandidate("detector_lag", ("lag",), None, None)
    assert "bound" in _unphysical(lag, [-0.5])


def test_a_broken_heldout_evaluation_is_degenerate_not_scored():
    base = {"heldout": 1000.0, "bic": 1000.0}
    broken = {"heldout": 780000.0, "bic": 900.0, "heldout_r2": np.ones(700)}
    s = score(base, broken, 1)
    assert s.get("degenerate") and not s["claimable"]
    lost = {"heldout": 1004.0, "bic": 1003.0, "heldout_r2": np.ones(700)}
    assert not score(base, lost, 1).get("degenerate")


def test_quantised_images_are_not_trusted():
    im = SimpleNamespace(stored_dtype="uint8", value_step=1.0, sigma_air=2.0)
    assert "uint8" in untrusted_values(im)
    im = SimpleNamespace(stored_dtype="float32", value_step=0.004, sigma_air=0.005)
    assert "steps" in untrusted_values(im)
    im = SimpleNamespace(stored_dtype="float32", value_step=1e-7, sigma_air=0.005)
    assert untrusted_values(im) is None
