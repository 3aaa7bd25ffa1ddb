"""The shadow size detect looks for follows the one it measures, not the
nominal magnification the user typed (issue 32, item 2)."""

import json

import numpy as np
import yaml
from click.testing import CliRunner

from conecal.cli.main import cli
from conecal.detect import DetectOptions
from conecal.detect.options import Blob
from conecal.detect.size import KEEP_WITHIN, measured_size, second_size, size_ratio
from conecal.simulate import rotation_scan, write_scan


def _measured(rng, p, n=30, depth=0.08):
    """Moment diameters (px) of shadows of declared sizes ``p`` at random
    depths: a mixture, each read 4.5 % small (as a blurred shadow's is)."""
    return rng.choice(p, n) * rng.uniform(1 - depth, 1 + depth, n) * 0.955


def test_a_wrong_magnification_is_measured_with_two_sphere_sizes():
    rng = np.random.default_rng(3)
    p = np.array([9.64, 12.86])          # 0.9 and 1.2 mm spheres at magnification 2.14, 0.2 mm pixels
    d = _measured(rng, p)
    for typed in (0.75, 1.0, 1.25):
        s = size_ratio(d, p * typed)
        assert abs(s * typed - 0.955) < 0.04, (typed, s)
    assert size_ratio(d[:4], p) is None             # too few shadows to say


def test_shadows_of_one_declared_size_keep_the_typed_magnification():
    # every shadow as large as the small sphere's: either size fits as well at
    # some magnification, and the typed one is kept (no 25 % jump)
    p = np.array([9.64, 12.86])
    s = size_ratio(np.full(12, 9.64), p)
    assert abs(s - 1) < 0.01


def test_a_phantom_of_two_bead_sizes_declared_by_one_is_looked_for_at_both():
    # a coded helix of 1.6 and 3.2 mm beads whose scan.yaml declares 1.6 mm:
    # the larger class sets the measured scale, the smaller must stay in range
    rng = np.random.default_rng(5)
    typed = np.array([6.1])
    d = np.concatenate([_measured(rng, typed * 1.05, 10), _measured(rng, typed * 2.0, 18)])
    s = size_ratio(d, typed)
    s2 = second_size(d, typed, s)
    assert s2 is not None and abs(np.log(min(s, s2) / 1.0)) < 0.1 and abs(np.log(max(s, s2) / 1.91)) < 0.1
    blobs = [Blob(x=float(10 * i), y=0.0, radius=float(r / 2), sigma=0.05, mu_px=0.05, peak=0.3, anisotropy=1.0,
                  flags=[], snr=50.0)
             for i, r in enumerate(d)]
    opt = measured_size(blobs, DetectOptions(diameter_px=(0.6 * 6.1, 1.6 * 6.1), shadow_px=(6.1,)))
    assert len(opt.shadow_px) == 2 and opt.diameter_px[0] < 5.6 and 12.8 < opt.diameter_px[1]
    # one class, wherever its scale: no second size, one range
    one = _measured(rng, typed * 1.8, 28)
    assert second_size(one, typed, size_ratio(one, typed)) is None
    # a few shadows of another size (a phantom's two large beads among 16): not a class
    few = np.concatenate([_measured(rng, typed, 24), _measured(rng, typed * 2.0, 3)])
    assert second_size(few, typed, size_ratio(few, typed)) is None


def _scan_yaml_with(path, factor: float) -> None:
    """The scan's nominal source-object distance times ``factor`` (its
    magnification over ``factor``), as a user's wrong guess."""
    cfg = yaml.safe_load((path / "scan.yaml").read_text())
    cfg["nominal"]["sod"] = cfg["nominal"]["sod"] * factor
    (path / "scan.yaml").write_text(yaml.safe_dump(cfg))


def test_detect_finds_the_same_markers_when_the_nominal_magnification_is_25_percent_off(tmp_path):
    sc = rotation_scan(2, rows=256, cols=256, n_frames=4, diameters=(2.0, 1.2), n_spheres=6)
    root = write_scan(sc, tmp_path / "scan", seed=2)
    runner = CliRunner()
    res = runner.invoke(cli, ["detect", str(root), "-o", str(tmp_path / "right.json"), "--workers", "1"])
    assert res.exit_code == 0, res.output
    right = json.loads((tmp_path / "right.json").read_text())
    assert 1 / KEEP_WITHIN <= right["options"]["size_scale"] <= KEEP_WITHIN
    _scan_yaml_with(root, 4 / 3)           # magnification typed 25 % small
    res = runner.invoke(cli, ["detect", str(root), "-o", str(tmp_path / "wrong.json"), "--workers", "1"])
    assert res.exit_code == 0, res.output
    assert "the shadows measure" in res.output
    wrong = json.loads((tmp_path / "wrong.json").read_text())
    assert 1.2 < wrong["options"]["size_scale"] < 1.45
    # the range looked for is the right one's to within the measurement's few %
    ratio = np.array(wrong["options"]["diameter_px"]) / np.array(right["options"]["diameter_px"])
    assert np.all(np.abs(ratio - 1) < 0.1), ratio
    assert sum(len(f["markers"]) for f in right["frames"]) >= 15
    for fa, fb in zip(right["frames"], wrong["frames"]):
        a = sorted((m["x"], m["y"]) for m in fa["markers"])
        b = sorted((m["x"], m["y"]) for m in fb["markers"])
        assert len(a) == len(b)
        assert np.abs(np.array(a) - np.array(b)).max() < 0.02


def test_a_blob_without_sigma_never_becomes_a_marker():
    """The independent renderer's ball phantom, nominal magnification 25 %
    low, searched at the typed size (as with --diameter-px): a merged blob
    whose centroid had no sigma was taken for an unsplit pair, and its
    infinite sigma passed to a neighbour; the scan's whole markers file was
    then invalid (exit 1, nothing written)."""
    from benchmarks import carm_images as gen
    from conecal.detect import DetectOptions, detect_frame
    from conecal.detect.noise import noise_correlation, noise_pixel

    sc = gen._setup("ball3d_ii_m25", 1)
    g8 = gen.render_frame(sc, 7)[0]
    a = (-np.log(np.maximum(g8.astype(np.float64) / 255.0, 1e-6))).astype(np.float32)
    mid = (-np.log(np.maximum(gen.render_frame(sc, 6)[0].astype(np.float64) / 255.0, 1e-6))).astype(np.float32)
    opt = DetectOptions(diameter_px=(5.582, 14.886), pixel_noise=noise_pixel(mid), noise_kappa=noise_correlation(mid))
    blobs = detect_frame(a, opt)
    assert len(blobs) >= 20
    assert all(np.isfinite([b.x, b.y, b.sigma]).all() for b in blobs)
