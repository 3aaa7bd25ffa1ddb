"""Trusting conecal with a user's files: --overwrite never deletes what conecal
did not write; SIGTERM ends a run like Ctrl-C (workers gone, nothing partial)."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from conecal.cli.main import cli
from conecal.simulate import rotation_scan, write_scan

CONECAL = [sys.executable, "-c", "from conecal.cli.main import cli; cli()"]


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def tree(path: Path) -> dict:
    return {str(p.relative_to(path)): (p.read_bytes() if p.is_file() else None) for p in sorted(path.rglob("*"))}


@pytest.fixture
def precious(tmp_path):
    d = tmp_path / "precious"
    (d / "sub").mkdir(parents=True)
    (d / "thesis.txt").write_text("four years\n")
    (d / "sub" / "data.csv").write_text("1,2\n")
    return d


def test_overwrite_refuses_a_directory_conecal_did_not_write(precious):
    before = tree(precious)
    res = run("simulate", "linear", precious, "--overwrite")
    assert res.exit_code == 2
    assert "did not write" in res.output and "thesis.txt" in res.output
    assert tree(precious) == before


def test_overwrite_refuses_cwd_and_its_ancestors(precious, monkeypatch):
    monkeypatch.chdir(precious / "sub")
    before = tree(precious)
    for out in (".", "..", str(precious.parent)):
        res = run("simulate", "linear", out, "--overwrite")
        assert res.exit_code == 2 and "current directory" in res.output, (out, res.output)
    assert tree(precious) == before
    assert not [p for p in precious.parent.iterdir() if p.name.startswith(".")]   # no temporary left


def test_overwrite_refuses_a_conecal_scan_the_user_added_to(tmp_path):
    scan = write_scan(rotation_scan(1, rows=64, cols=64, n_frames=3), tmp_path / "scan")
    (scan / "notes.txt").write_text("mine\n")
    before = tree(scan)
    res = run("simulate", "linear", scan, "--overwrite")
    assert res.exit_code == 2 and "notes.txt" in res.output
    assert tree(scan) == before


def test_overwrite_refuses_links_files_and_a_foreign_truth(tmp_path, precious):
    (tmp_path / "link").symlink_to(precious)
    assert run("simulate", "linear", tmp_path / "link", "--overwrite").exit_code == 2
    (tmp_path / "afile").write_text("x")
    assert run("simulate", "linear", tmp_path / "afile", "--overwrite").exit_code == 2
    assert (tmp_path / "afile").read_text() == "x"
    fake = tmp_path / "fake"
    fake.mkdir()
    (fake / "truth.json").write_text('{"format": "someone-else/1"}')
    res = run("simulate", "linear", fake, "--overwrite")
    assert res.exit_code == 2 and "truth.json" in res.output
    assert (fake / "truth.json").read_text() == '{"format": "someone-else/1"}'


def test_overwrite_replaces_conecals_own_scan_and_an_empty_directory(tmp_path):
    scan = write_scan(rotation_scan(1, rows=64, cols=64, n_frames=3), tmp_path / "scan")
    old = (scan / "log.csv").read_text()
    write_scan(rotation_scan(2, rows=64, cols=64, n_frames=4), scan, overwrite=True)
    assert (scan / "log.csv").read_text() != old
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scan"]            # the old one is gone, no temporary
    (tmp_path / "empty").mkdir()
    write_scan(rotation_scan(2, rows=64, cols=64, n_frames=3), tmp_path / "empty", overwrite=True)
    assert (tmp_path / "empty" / "scan.yaml").exists()


def _children(pid: int) -> list[int]:
    kids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            kids.append(int(stat.parent.name))
    return kids


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc to see the workers")
def test_sigterm_to_detect_ends_its_workers_and_writes_nothing(tmp_path):
    scan = write_scan(rotation_scan(5, rows=256, cols=256, n_frames=400), tmp_path / "scan")
    out = tmp_path / "m.json"
    proc = subprocess.Popen(CONECAL + ["detect", str(scan), "-o", str(out), "--workers", "2"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    kids = []
    while time.monotonic() < deadline and len(kids) < 2 and proc.poll() is None:
        kids = _children(proc.pid)
        time.sleep(0.05)
    assert len(kids) == 2, "detect never started its workers"
    time.sleep(0.3)
    proc.terminate()
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "SIGTERM" in err and "Traceback" not in err
    time.sleep(0.5)
    assert not [k for k in kids if _alive(k)]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scan"]           # no m.json, no temporary


def test_sigterm_to_simulate_leaves_no_partial_directory(tmp_path):
    out = tmp_path / "scan"
    proc = subprocess.Popen(CONECAL + ["simulate", "rotation", str(out), "--frames", "5000"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not list(tmp_path.glob(".scan.*/projections.tif")):
        time.sleep(0.05)
    assert list(tmp_path.glob(".scan.*/projections.tif")), "simulate never started writing"
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert os.listdir(tmp_path) == []


def test_files_get_the_umask_mode_and_stdout_and_late_flags_work(tmp_path):
    import json

    scan = tmp_path / "scan"
    write_scan(rotation_scan(0, n_frames=6, rows=96, cols=96, pitch=0.8), scan)
    old = os.umask(0o022)
    try:
        assert run("detect", scan, "-o", tmp_path / "m.json", "-q").exit_code == 0     # -q after the subcommand
    finally:
        os.umask(old)
    assert (tmp_path / "m.json").stat().st_mode & 0o777 == 0o644
    res = subprocess.run(CONECAL + ["detect", str(scan), "-o", "-"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and json.loads(res.stdout)["format"] == "conecal-markers/1"
    assert not (Path.cwd() / "-").exists()


def test_output_in_a_file_as_folder_fails_before_the_work(tmp_path):
    (tmp_path / "afile").write_text("x")
    t0 = time.monotonic()
    res = run("detect", tmp_path / "nowhere", "-o", tmp_path / "afile" / "m.json")
    assert res.exit_code == 2 and "not a directory" in res.output and time.monotonic() - t0 < 2


def test_a_closed_pipe_ends_quietly(tmp_path):
    scan = tmp_path / "scan"
    write_scan(rotation_scan(0, n_frames=6, rows=96, cols=96, pitch=0.8), scan)
    p = subprocess.Popen(CONECAL + ["detect", str(scan), "-o", "-"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    p.stdout.read(10)
    p.stdout.close()
    err = p.stderr.read().decode()
    assert p.wait(timeout=120) in (0, 141) and "Traceback" not in err
