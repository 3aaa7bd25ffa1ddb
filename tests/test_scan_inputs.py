"""Bad input gets one line naming the file and the key, row or frame, and exit code 2."""

import shutil

import numpy as np
import pytest
import tifffile
import yaml
from click.testing import CliRunner

from conecal.cli.main import cli
from conecal.scan import load_scan


@pytest.fixture
def scan_copy(small_linear_scan, tmp_path):
    dst = tmp_path / "scan"
    shutil.copytree(small_linear_scan, dst)
    return dst


def run_detect(scan_dir, tmp_path):
    res = CliRunner().invoke(cli, ["detect", str(scan_dir), "-o", str(tmp_path / "m.json")])
    return res


def edit_yaml(scan_dir, fn):
    p = scan_dir / "scan.yaml"
    cfg = yaml.safe_load(p.read_text())
    fn(cfg)
    p.write_text(yaml.safe_dump(cfg))


def assert_input_error(res, *needles, tmp_path=None):
    assert res.exit_code == 2, res.output
    msg = res.output.strip().splitlines()
    assert len(msg) == 1, res.output          # one line, no traceback
    for n in needles:
        assert n in msg[0], msg[0]
    if tmp_path is not None:
        assert not (tmp_path / "m.json").exists()  # nothing half-written


def test_valid_scan_loads(small_linear_scan):
    s = load_scan(small_linear_scan)
    assert s.n_frames == 8 and s.config.motion == "linear"
    a = s.stack.read(0)
    assert a.dtype == np.float32 and a.shape == (256, 256)


def test_missing_projection_file(scan_copy, tmp_path):
    (scan_copy / "projections.tif").unlink()
    assert_input_error(run_detect(scan_copy, tmp_path), "scan.yaml", "projections", tmp_path=tmp_path)


def test_missing_scan_dir(tmp_path):
    assert_input_error(run_detect(tmp_path / "nope", tmp_path), "scan.yaml", "not found")


def test_a_log_may_list_a_subset_of_the_pages_but_not_one_past_the_end(scan_copy, tmp_path):
    import json

    log = (scan_copy / "log.csv").read_text().splitlines()
    (scan_copy / "log.csv").write_text("\n".join([log[0]] + log[1:3] + log[5:]) + "\n")   # pages 2 and 3 left out
    res = run_detect(scan_copy, tmp_path)
    assert res.exit_code == 0, res.output
    frames = [f["frame"] for f in json.loads((tmp_path / "m.json").read_text())["frames"]]
    assert frames == [0, 1, 4, 5, 6, 7]
    (tmp_path / "m.json").unlink()
    last = log[-1].split(",")
    (scan_copy / "log.csv").write_text("\n".join(log + [",".join(["8", str(float(last[1]) + 1)] + last[2:])]) + "\n")
    assert_input_error(run_detect(scan_copy, tmp_path), "log.csv", "frame 8 is past the last page", tmp_path=tmp_path)


def test_nan_pixel_names_the_frame(scan_copy, tmp_path):
    p = scan_copy / "projections.tif"
    stack = tifffile.imread(p)
    stack[5, 10, 20] = np.nan
    tifffile.imwrite(p, stack)
    assert_input_error(run_detect(scan_copy, tmp_path), "frame 5", "row 10, col 20", "nan", tmp_path=tmp_path)


def test_inf_pixel(scan_copy, tmp_path):
    p = scan_copy / "projections.tif"
    stack = tifffile.imread(p)
    stack[2, 0, 0] = np.inf
    tifffile.imwrite(p, stack)
    assert_input_error(run_detect(scan_copy, tmp_path), "frame 2", "inf")


def test_time_going_backwards(scan_copy, tmp_path):
    lines = (scan_copy / "log.csv").read_text().splitlines()
    cells = lines[4].split(",")
    cells[1] = "0.5"
    lines[4] = ",".join(cells)
    (scan_copy / "log.csv").write_text("\n".join(lines) + "\n")
    assert_input_error(run_detect(scan_copy, tmp_path), "log.csv", "line 5", "time")


def test_unknown_axis_column(scan_copy, tmp_path):
    text = (scan_copy / "log.csv").read_text().replace("frame,time,x,y,z", "frame,time,x,y,w", 1)
    (scan_copy / "log.csv").write_text(text)
    assert_input_error(run_detect(scan_copy, tmp_path), "log.csv", "'w'", "not an axis")


def test_non_numeric_log_value(scan_copy, tmp_path):
    lines = (scan_copy / "log.csv").read_text().splitlines()
    lines[3] = lines[3].rsplit(",", 1)[0] + ",abc"
    (scan_copy / "log.csv").write_text("\n".join(lines) + "\n")
    assert_input_error(run_detect(scan_copy, tmp_path), "log.csv", "line 4", "'z'")


def test_negative_pitch(scan_copy, tmp_path):
    edit_yaml(scan_copy, lambda c: c["detector"].__setitem__("pixel_pitch", [-0.2, 0.2]))
    assert_input_error(run_detect(scan_copy, tmp_path), "scan.yaml", "detector.pixel_pitch.0")


@pytest.mark.parametrize("pitch,words", [([1.4e306, 0.2], "pixel_pitch is in mm"), ([1e-177, 0.2], "below 0.1 micrometre")])
def test_absurd_pitch_is_bad_input_not_a_crash(scan_copy, tmp_path, pitch, words):
    # found by the fuzz test: the corner sat at -inf, or the shadow was 1e178 px wide
    edit_yaml(scan_copy, lambda c: c["detector"].__setitem__("pixel_pitch", pitch))
    assert_input_error(run_detect(scan_copy, tmp_path), "scan.yaml", "detector", words)


def test_unknown_key(scan_copy, tmp_path):
    edit_yaml(scan_copy, lambda c: c["nominal"].__setitem__("sid", 3))
    assert_input_error(run_detect(scan_copy, tmp_path), "scan.yaml", "nominal.sid", "unknown key")


def test_unknown_axis_type_and_missing_key(scan_copy, tmp_path):
    edit_yaml(scan_copy, lambda c: c["axes"][0].__setitem__("type", "prismatic"))
    assert_input_error(run_detect(scan_copy, tmp_path), "scan.yaml", "axes.0.type")
    edit_yaml(scan_copy, lambda c: (c["axes"][0].__setitem__("type", "linear"), c.pop("nominal")))
    assert_input_error(run_detect(scan_copy, tmp_path), "scan.yaml", "nominal", "missing")


def test_newer_format_asks_for_an_upgrade(scan_copy, tmp_path):
    edit_yaml(scan_copy, lambda c: c.__setitem__("format", "conecal-scan/2"))
    assert_input_error(run_detect(scan_copy, tmp_path), "scan.yaml", "upgrade conecal")


def test_truncated_tiff(scan_copy, tmp_path):
    p = scan_copy / "projections.tif"
    data = p.read_bytes()
    p.write_bytes(data[: int(len(data) * 0.6)])
    assert_input_error(run_detect(scan_copy, tmp_path), "projections.tif")


def test_wrong_frame_shape(scan_copy, tmp_path):
    edit_yaml(scan_copy, lambda c: c["detector"].__setitem__("rows", 200))
    assert_input_error(run_detect(scan_copy, tmp_path), "projections.tif", "frame 0", "shape")


def test_invalid_yaml(scan_copy, tmp_path):
    (scan_copy / "scan.yaml").write_text("format: [unclosed\n")
    assert_input_error(run_detect(scan_copy, tmp_path), "scan.yaml", "not valid YAML")


def test_transmission_and_raw_values_give_the_same_attenuation(tmp_path):
    from conecal.simulate import linear_raster, write_scan

    sc = linear_raster(1, rows=64, cols=64, counts=(1, 1, 2), steps=(1, 1, 1), diameter=1.0)
    sc.photons = 0  # noiseless, so the three encodings must agree
    a = load_scan(write_scan(sc, tmp_path / "a")).stack.read(1)
    t = load_scan(write_scan(sc, tmp_path / "t", values="transmission")).stack.read(1)
    assert np.allclose(a, t, atol=1e-5)
    sc.photons = 1e6
    r = load_scan(write_scan(sc, tmp_path / "r", values="raw")).stack.read(1)
    assert np.abs(a - r).mean() < 2e-3  # photon noise only (sigma ~1e-3)


def test_folder_of_tiffs_is_a_stack(small_linear_scan, tmp_path):
    dst = tmp_path / "scan"
    shutil.copytree(small_linear_scan, dst)
    stack = tifffile.imread(dst / "projections.tif")
    (dst / "projections.tif").unlink()
    (dst / "proj").mkdir()
    for k, img in enumerate(stack):
        tifffile.imwrite(dst / "proj" / f"img_{k:04d}.tif", img)
    edit_yaml(dst, lambda c: c.__setitem__("projections", "proj"))
    s = load_scan(dst)
    assert np.array_equal(s.stack.read(3), stack[3])


def _raw_scan(tmp_path, frames, flat, dark, **imwrite):
    """A scan of ``frames`` (raw counts) with ``flat`` and ``dark`` as given."""
    from conecal.simulate import linear_raster, write_scan

    sc = linear_raster(1, rows=frames.shape[1], cols=frames.shape[2], counts=(1, 1, 2), steps=(1, 1, 1),
                       diameter=1.0)
    d = write_scan(sc, tmp_path / "raw", values="raw")
    tifffile.imwrite(d / "projections.tif", frames, **(imwrite or {"photometric": "minisblack"}))
    tifffile.imwrite(d / "flat.tif", flat, **({"photometric": "rgb", "planarconfig": "separate"} if flat.ndim == 3
                                              else {}))
    tifffile.imwrite(d / "dark.tif", dark)
    return d


def test_a_grey_image_stored_as_colour_and_a_stack_of_flats_in_one_page_are_read(tmp_path):
    # an image viewer's RGB export of a grey radiograph; flats written by
    # tifffile as one planar four-sample page (read as RGB and alpha)
    rng = np.random.default_rng(0)
    grey = (rng.random((2, 24, 32)) * 150 + 50).astype(np.uint8)
    flats = np.full((4, 24, 32), 240, np.uint16)
    flats[1] = 225       # the colour samples' mean is 235
    flats[3] = 0         # the alpha sample is left out
    d = _raw_scan(tmp_path, np.repeat(grey[..., None], 3, -1), flats, np.zeros((24, 32), np.uint16),
                  photometric="rgb")
    s = load_scan(d)
    assert s.stack.read_raw(1).dtype == np.uint8 and np.array_equal(s.stack.read_raw(1), grey[1])
    assert np.allclose(s.stack.read(1), -np.log(grey[1] / 235.0), atol=1e-5)


def test_an_intensifiers_dark_surround_in_the_flat_reads_as_no_transmission(tmp_path):
    # outside an intensifier's circular field the flat is as dark as the dark image
    yy, xx = np.mgrid[0:40, 0:40]
    inside = np.hypot(xx - 19.5, yy - 19.5) < 18
    flat = np.where(inside, 200, 0).astype(np.uint8)
    frames = np.repeat(np.where(inside, 100, 0).astype(np.uint8)[None], 3, 0)
    d = _raw_scan(tmp_path, frames, flat, np.zeros((40, 40), np.uint8))
    s = load_scan(d)
    a = s.stack.read(0)
    assert s.stack.dead_pixels == int((~inside).sum())
    assert np.allclose(a[inside], np.log(2.0), atol=1e-5)
    assert (a[~inside] > 10).all()     # as dark as detect's invalid pixels, not NaN
    res = CliRunner().invoke(cli, ["detect", str(d), "-o", str(tmp_path / "m.json")])
    assert res.exit_code == 0, res.output
    assert "not brighter than the dark image" in res.output


def test_an_intensifiers_glare_rim_in_the_flat_reads_as_no_transmission(tmp_path):
    """Beyond the field the flat holds only glare, a sixth of the field's
    signal: a frame's noise divided by it is no transmission (it read as
    speckle of hundreds of touching shadows)."""
    yy, xx = np.mgrid[0:40, 0:40]
    inside = np.hypot(xx - 19.5, yy - 19.5) < 18
    flat = np.where(inside, 220, 40).astype(np.uint8)
    noise = np.random.default_rng(0).integers(-8, 9, (3, 40, 40))
    frames = (np.where(inside, 110, 40)[None] + noise).astype(np.uint8)
    s = load_scan(_raw_scan(tmp_path, frames, flat, np.zeros((40, 40), np.uint8)))
    a = s.stack.read(0)
    assert s.stack.dead_pixels == int((~inside).sum())
    assert (a[~inside] > 10).all() and (a[inside] < 1.5).all()


def test_a_flat_darker_than_the_dark_almost_everywhere_is_bad_input(tmp_path):
    frames = np.full((3, 20, 20), 100, np.uint16)
    d = _raw_scan(tmp_path, frames, np.full((20, 20), 50, np.uint16), np.full((20, 20), 60, np.uint16))
    res = run_detect(d, tmp_path)
    assert_input_error(res, "flat.tif", "not brighter than the dark image", tmp_path=tmp_path)
