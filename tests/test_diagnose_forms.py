"""diagnose on a form no effect of the library has, from the independent
form-variant generator (benchmarks/formvariants.py): located, described,
not named."""

import json

import numpy as np
from click.testing import CliRunner

from benchmarks import formvariants as fv
from conecal.cli.main import cli



def test_an_eccentric_encoder_is_described_not_claimed_as_drift(tmp_path):
    """The theta reading off by e sin(theta + phi): a flexible drift spline
    reached the noise too and was claimed; a two-parameter description of the
    reading now explains it better, so nothing is claimed and e is measured."""
    fv.make_case("encoder_eccentric", 0, tmp_path)
    truth = json.loads((tmp_path / "effect.json").read_text())["params"]["eccentric_deg"]
    r = CliRunner()
    res = r.invoke(cli, ["fit-rotation", str(tmp_path / "scan"), "--markers", str(tmp_path / "markers.json"),
                         "--geometry", str(tmp_path / "geometry.json"), "-o", str(tmp_path / "fit.json")])
    assert res.exit_code == 0, res.output
    res = r.invoke(cli, ["diagnose", str(tmp_path / "fit.json"), str(tmp_path / "scan"), "-o",
                         str(tmp_path / "diag.json"), "--no-image"])
    assert res.exit_code == 0, res.output
    d = json.loads((tmp_path / "diag.json").read_text())
    assert d["effects"] == []
    assert d["located"][0]["variable"] == "theta" and d["located"][0]["shape"].startswith("harmonic 1")
    desc = [x for x in d["descriptions"] if x["description"].startswith("reading_harmonic:theta:1")]
    assert desc, d["descriptions"]
    p = desc[0]["parameters"]
    assert abs(np.hypot(p["a_cos"], p["a_sin"]) - truth) < 0.1 * truth
    assert "eccentric" in d["verdict"]


def test_a_warp_centred_far_off_the_detector_is_not_a_distortion():
    from conecal.diagnose.candidates import _far_centre

    assert _far_centre((58.0, -12892.0), (512, 512)) is not None      # the fit seen on a two-speed scan
    assert _far_centre((-200.0, 150.0), (512, 512)) is None            # an intensifier's off-centre point
