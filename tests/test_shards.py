"""A scan detected in parts and merged gives the bytes of one run; the
Snakemake workflow runs the sharded sample pipeline (issue 30)."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from conecal.cli.main import cli

ROOT = Path(__file__).resolve().parents[1]


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def test_four_parts_merged_are_the_bytes_of_one_run(system, tmp_path, monkeypatch):
    _, rot = system
    monkeypatch.chdir(rot.parent)
    ranges = ["0:5", "5:11", "11:20", "20:"]
    for i, r in enumerate(ranges):
        res = run("detect", rot.name, "--frames", r, "-o", tmp_path / f"p{i}.json")
        assert res.exit_code == 0, res.output
    # a part is not a markers document a fit may read
    res = run("fit-rotation", rot.name, "--markers", tmp_path / "p0.json", "-o", tmp_path / "g.json")
    assert res.exit_code == 2 and "conecal merge" in res.output, res.output
    res = run("merge", *[tmp_path / f"p{i}.json" for i in (2, 0, 3, 1)], "-o", tmp_path / "merged.json")
    assert res.exit_code == 0, res.output
    res = run("detect", rot.name, "-o", tmp_path / "whole.json")
    assert res.exit_code == 0, res.output
    assert (tmp_path / "merged.json").read_bytes() == (tmp_path / "whole.json").read_bytes()
    doc = json.loads((tmp_path / "merged.json").read_text())
    assert doc["n_ids"] >= 4 and all(m["id"] is not None for f in doc["frames"] for m in f["markers"])
    # --part I/N splits the log the same way a workflow does, without knowing its length
    for i in (1, 2, 3):
        assert run("detect", rot.name, "--part", f"{i}/3", "-o", tmp_path / f"q{i}.json").exit_code == 0
    res = run("merge", *[tmp_path / f"q{i}.json" for i in (1, 2, 3)], "-o", tmp_path / "merged3.json")
    assert res.exit_code == 0 and (tmp_path / "merged3.json").read_bytes() == (tmp_path / "whole.json").read_bytes()


def test_merge_refuses_gaps_overlaps_and_other_scans(system, tmp_path):
    lin, rot = system
    for name, scan, r in (("a", rot, "0:12"), ("b", rot, "12:"), ("c", rot, "10:"), ("l", lin, "0:")):
        assert run("detect", scan, "--frames", r, "-o", tmp_path / f"{name}.json").exit_code == 0
    cases = [((tmp_path / "a.json",), "leave out frame"), ((tmp_path / "a.json", tmp_path / "c.json"), "is also in"),
             ((tmp_path / "a.json", tmp_path / "l.json"), "different scans"),
             ((tmp_path / "a.json", tmp_path / "b.json", tmp_path / "b.json"), "is also in")]
    for parts, why in cases:
        res = run("merge", *parts, "-o", tmp_path / "m.json")
        assert res.exit_code == 2 and why in res.output, res.output
    for bad in ("7", "5:2", "a:b", "-1:3"):
        assert run("detect", rot, "--frames", bad, "-o", tmp_path / "x.json").exit_code == 2
    assert run("detect", rot, "--part", "4/3", "-o", tmp_path / "x.json").exit_code == 2
    assert not (tmp_path / "m.json").exists() and not (tmp_path / "x.json").exists()


@pytest.mark.skipif(subprocess.run([sys.executable, "-c", "import snakemake"]).returncode != 0,
                    reason="snakemake not installed (pip install '.[test]' installs it)")
def test_snakemake_runs_the_sharded_sample_pipeline(tmp_path):
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "workflow" / "Snakefile"), "-j2", "-q",
           "--config", "out=out", "shards=4"]
    r = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    out = tmp_path / "out"
    assert len(list((out / "parts").glob("*.json"))) == 8
    geometry = json.loads((out / "rotation_geometry.json").read_text())
    assert geometry["fit"]["rms_px"] < 0.05
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        assert run("detect", "out/rotation", "-o", "out/whole.json").exit_code == 0
    finally:
        os.chdir(cwd)
    assert (out / "whole.json").read_bytes() == (out / "rotation_markers.json").read_bytes()


def test_robot_fit_pose_parts_merge_into_the_bytes_of_one_run(tmp_path):
    scan = tmp_path / "robot"
    assert run("simulate", "robot", scan, "--frames", "6", "--seed", "2").exit_code == 0
    assert run("detect", scan, "-o", tmp_path / "m.json").exit_code == 0
    for i in (1, 2):
        r = run("fit-pose", scan, "--markers", tmp_path / "m.json", "--part", f"{i}/2", "-o", tmp_path / f"p{i}.json")
        assert r.exit_code == 0, r.output
    r = run("fit-pose", scan, "--markers", tmp_path / "m.json", "-o", tmp_path / "whole.json")
    assert r.exit_code == 0, r.output
    r = run("merge", tmp_path / "p2.json", tmp_path / "p1.json", "-o", tmp_path / "merged.json")
    assert r.exit_code == 0, r.output
    assert (tmp_path / "merged.json").read_bytes() == (tmp_path / "whole.json").read_bytes()
    # a part is not a result: consumers ask for the merge
    r = run("export", tmp_path / "p1.json", "--format", "astra", "-o", tmp_path / "v.txt")
    assert r.exit_code == 2 and "conecal merge" in r.output
    r = run("fit-pose", scan, "--markers", tmp_path / "m.json", "--part", "1/2", "--initial", "previous",
            "-o", tmp_path / "x.json")
    assert r.exit_code == 2 and not (tmp_path / "x.json").exists()
