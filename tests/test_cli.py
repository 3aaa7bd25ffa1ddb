"""The command line: exit codes, outputs, the demo pipeline."""

import json
import os
from pathlib import Path

from click.testing import CliRunner

from conecal import __version__
from conecal.cli.main import cli

GOLDEN = Path(__file__).parent / "golden"


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def test_version_and_help():
    assert run("--version").output.strip().endswith(__version__)
    res = run("--help")
    assert res.exit_code == 0
    for cmd in ("simulate", "detect", "fit-linear", "report"):
        assert cmd in res.output
        sub = run(cmd, "--help")
        assert sub.exit_code == 0 and "Examples" in sub.output


def test_a_command_imports_only_its_own_stage():
    """``conecal --version`` or one command does not import every stage (it
    took seconds on each call of a Makefile or a pipeline)."""
    import subprocess
    import sys

    code = ("import sys; from click.testing import CliRunner; from conecal.cli.main import cli; "
            "r = CliRunner().invoke(cli, ['compare', '--help']); assert r.exit_code == 0, r.output; "
            "print(sorted(m for m in ('conecal.detect', 'conecal.diagnose', 'conecal.calib', 'conecal.rpgrid') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_usage_errors_exit_2(tmp_path):
    assert run("simulate", "bogus", tmp_path / "x").exit_code == 2
    assert run("simulate", "linear", tmp_path / "x", "--effect", "gremlins").exit_code == 2
    res = run("detect", tmp_path / "nope")
    assert res.exit_code == 2


def test_pipeline_and_golden_markers(tmp_path):
    scan = tmp_path / "scan"
    assert run("simulate", "linear", scan, "--seed", "4").exit_code == 0
    assert run("simulate", "linear", scan).exit_code == 2          # exists: not overwritten
    res = run("detect", scan, "-o", tmp_path / "m.json")
    assert res.exit_code == 0, res.output
    res = run("fit-linear", scan, "--markers", tmp_path / "m.json", "-o", tmp_path / "g.json")
    assert res.exit_code == 0, res.output
    geo = json.loads((tmp_path / "g.json").read_text())
    assert geo["format"] == "conecal-geometry/1" and geo["fit"]["rms_px"] < 0.05
    truth = json.loads((scan / "truth.json").read_text())["geometry"]
    assert abs(geo["source"][2] - truth["source"][2]) < 0.1          # mm
    res = run("report", tmp_path / "g.json")
    assert res.exit_code == 0 and "source_z" in res.output
    # golden file: detect's output for this seed, to 1e-4 px
    doc = json.loads((tmp_path / "m.json").read_text())
    golden = GOLDEN / "markers_linear_seed4.json"
    if os.environ.get("CONECAL_REGEN_GOLDEN"):
        golden.parent.mkdir(exist_ok=True)
        golden.write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")
    ref = json.loads(golden.read_text())
    assert len(ref["frames"]) == len(doc["frames"])
    for fa, fb in zip(ref["frames"], doc["frames"]):
        assert [m["id"] for m in fa["markers"]] == [m["id"] for m in fb["markers"]]
        for ma, mb in zip(fa["markers"], fb["markers"]):
            assert abs(ma["x"] - mb["x"]) < 1e-4 and abs(ma["y"] - mb["y"]) < 1e-4
            assert ma["flags"] == mb["flags"]


def test_bad_markers_file_exit_2(tmp_path, small_linear_scan):
    (tmp_path / "m.json").write_text('{"format": "conecal-markers/7", "frames": []}')
    res = run("fit-linear", small_linear_scan, "--markers", tmp_path / "m.json", "-o", tmp_path / "g.json")
    assert res.exit_code == 2 and "upgrade" in res.output
    (tmp_path / "m.json").write_text('{"format": "conecal-markers/1", "frames": []}')
    res = run("fit-linear", small_linear_scan, "--markers", tmp_path / "m.json", "-o", tmp_path / "g.json")
    assert res.exit_code == 1 and "no usable markers" in res.output
    assert not (tmp_path / "g.json").exists()


def test_every_simulated_kind_loads(tmp_path):
    for kind, extra in (("rotation", ["--frames", "4"]), ("robot", ["--frames", "3"]), ("circular", ["--frames", "6"])):
        res = run("simulate", kind, tmp_path / kind, *extra)
        assert res.exit_code == 0, res.output
        from conecal.scan import load_scan

        s = load_scan(tmp_path / kind)
        assert s.config.motion == kind
        assert (tmp_path / kind / "truth.json").exists()
