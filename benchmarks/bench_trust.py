"""Trusting conecal with files (issue 30): every target measured in one run.

1. ``simulate --overwrite`` on a folder conecal did not write, on ``.`` and on ``..``.
2. Every consumer given corrupted result documents: each key the consumers
   read (source, detector, axes, frames, poses, verdicts) deleted, made a
   string, NaN, null, the wrong length or an impossible value.
3. Every output of the sample Makefiles (linear + rotation, robot, free-pose
   C-arm, rp-grid) validated against ``conecal schema`` (jsonschema).
4. Every result paired with every scan it was not computed from.
5. Files: umask 022 -> mode 0644; an unwritable ``-o`` fails before the work;
   SIGTERM to a running detect leaves no process and no file.
6. detect in 4 parts + merge == one run (bytes); the Snakemake workflow from a
   clean checkout (``git clone`` of this repository, then ``snakemake -j2``).

    python benchmarks/bench_trust.py            # ~4 min on 2 cores (rp-grid's sample is most of it)
    python benchmarks/bench_trust.py --no-rpgrid
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jsonschema
import yaml

ROOT = Path(__file__).resolve().parents[1]
CONECAL = [sys.executable, "-c", "import sys; sys.path.insert(0, %r); from conecal.cli.main import cli; cli()" % str(ROOT)]


def conecal(*args, cwd=None, **kw):
    return subprocess.run(CONECAL + [str(a) for a in args], cwd=cwd, capture_output=True, text=True, **kw)


class _Run:
    def __init__(self, code, stderr):
        self.returncode, self.stderr = code, stderr


def invoke(*args):
    """In this process (hundreds of runs): exit code and standard error."""
    sys.path.insert(0, str(ROOT))
    from click.testing import CliRunner

    from conecal.cli.main import cli

    r = CliRunner().invoke(cli, [str(a) for a in args])
    return _Run(r.exit_code, r.stderr)


def tree(path: Path) -> dict:
    return {str(p.relative_to(path)): (p.read_bytes() if p.is_file() else None) for p in sorted(path.rglob("*"))}


def overwrite(tmp: Path) -> list[str]:
    precious = tmp / "precious"
    (precious / "sub").mkdir(parents=True)
    (precious / "thesis.txt").write_text("four years\n")
    (precious / "sub" / "data.csv").write_text("1,2\n")
    before = tree(tmp)
    rows = []
    for target, cwd in ((precious, tmp), (".", precious), ("..", precious / "sub")):
        r = conecal("simulate", "linear", target, "--overwrite", cwd=cwd)
        intact = tree(tmp) == before
        rows.append(f"  simulate linear {target} --overwrite (cwd {Path(cwd).name}): exit {r.returncode}, "
                    f"every file intact: {intact}; {r.stderr.strip().splitlines()[-1][:90]}")
    return rows


def sample_outputs(out: Path, rpgrid: bool) -> None:
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    jobs = [["make", "-s", "-j2", f"OUT={out}"], ["make", "-s", "-f", "Makefile.pose", f"OUT={out}", "FRAMES=24"],
            ["make", "-s", "-f", "Makefile.free", f"OUT={out}"]]
    if rpgrid:
        jobs.append(["make", "-s", "-f", "Makefile.rpgrid", f"OUT={out}"])
    for cmd in jobs:
        r = subprocess.run(cmd, cwd=ROOT / "sample_configs", capture_output=True, text=True, env=env)
        if r.returncode:
            raise SystemExit(f"{' '.join(cmd)} failed: {r.stderr[-500:]}")
    for result, scan, name in (("rotation_geometry.json", "rotation", "diag_rotation.json"),
                               ("poses.json", "robot", "diag_robot.json"),
                               ("carm_poses.json", "carm", "diag_carm.json")):
        r = conecal("diagnose", out / result, out / scan, "--no-image", "-o", out / name)
        if r.returncode:
            raise SystemExit(f"diagnose {result}: {r.stderr[-300:]}")


def schemas(out: Path) -> list[str]:
    sch = {n: json.loads(conecal("schema", n).stdout) for n in
           ("scan", "markers", "geometry", "poses", "diagnosis", "truth")}
    n_ok, bad = 0, []
    for f in sorted(out.rglob("*.json")):
        doc = json.loads(f.read_text())
        name = doc["format"].split("/")[0].removeprefix("conecal-")
        try:
            jsonschema.validate(doc, sch[name])
            n_ok += 1
        except jsonschema.ValidationError as exc:
            bad.append(f"{f.name}: {exc.message[:80]}")
    for f in sorted(out.rglob("scan.yaml")):
        try:
            jsonschema.validate(yaml.safe_load(f.read_text()), sch["scan"])
            n_ok += 1
        except jsonschema.ValidationError as exc:
            bad.append(f"{f}: {exc.message[:80]}")
    return [f"  {n_ok} outputs valid, {len(bad)} invalid"] + [f"    {b}" for b in bad]


def _leaves(doc, keys):
    """Paths to corrupt: each listed key and, for lists/dicts, their first items' keys."""
    out = []
    for k in keys:
        if k not in doc:
            continue
        out.append((k,))
        v = doc[k]
        if isinstance(v, dict):
            out += [(k, kk) for kk in v]
        elif isinstance(v, list) and v:
            out.append((k, 0))
            if isinstance(v[0], dict):
                out += [(k, 0, kk) for kk in v[0] if kk in ("direction", "type", "name", "point", "frame", "status",
                                                          "R", "t", "effect", "variable")]
            elif isinstance(v[0], (int, float)):
                out.append((k, 0))
    return out


MUTATIONS = [("deleted", None), ("a string", "x"), ("NaN", math.nan), ("null", "NULL"), ("wrong length", [1.0, 2.0]),
             ("zero", 0), ("negative", -1.0), ("a dict", {"a": 1})]


def _mutate(doc, path, value):
    d = copy.deepcopy(doc)
    tgt = d
    for k in path[:-1]:
        tgt = tgt[k]
    if value is None:
        del tgt[path[-1]]
    else:
        tgt[path[-1]] = None if value == "NULL" else value
    return d


def corruptions(out: Path, tmp: Path) -> list[str]:
    geometry_keys = ("source", "detector", "axes", "format")
    docs = {
        "geometry": (out / "rotation_geometry.json", geometry_keys, [
            ("fit-rotation", out / "rotation", "--markers", out / "rotation_markers.json", "--geometry", "BAD",
             "-o", tmp / "o.json"),
            ("fit-pose", out / "robot", "--markers", out / "robot_markers.json", "--geometry", "BAD", "-o", tmp / "o.json"),
            ("export", "BAD", "--scan", out / "rotation", "--format", "astra", "-o", tmp / "o.txt"),
            ("compare", "BAD", out / "rotation_geometry.json"), ("report", "BAD"),
            ("diagnose", "BAD", out / "rotation", "--no-image", "-o", tmp / "o.json")]),
        "poses": (out / "poses.json", ("source", "detector", "frames", "format", "motion"), [
            ("export", "BAD", "--format", "matrices", "-o", tmp / "o.txt"), ("compare", "BAD", out / "poses.json"),
            ("report", "BAD"), ("diagnose", "BAD", out / "robot", "--no-image", "-o", tmp / "o.json")]),
        "free poses": (out / "carm_poses.json", ("intrinsics", "distortion", "frames", "detector"), [
            ("export", "BAD", "--format", "distortion", "-o", tmp / "o.tif"), ("report", "BAD"),
            ("diagnose", "BAD", out / "carm", "--no-image", "-o", tmp / "o.json")]),
        "diagnosis": (out / "diag_rotation.json", ("verdict", "result", "effects", "located", "rms_px_before",
                                                   "refitted_geometry", "image_level", "format"), [("report", "BAD")]),
    }
    rows = []
    for kind, (src, keys, consumers) in docs.items():
        doc = json.loads(src.read_text())
        tally = {"exit 2, one line naming file and key": 0,
                 "exit 0 (still a valid document; compare: exit 1, it differs)": 0,
                 "exit 1 'Fit failed' (a valid document the fit cannot use)": 0, "other": 0}
        examples = []
        cases = [(p, m) for p in _leaves(doc, keys) for m in MUTATIONS]
        for i, (path, (what, value)) in enumerate(cases):
            bad = tmp / f"bad_{kind.replace(' ', '_')}_{i}.json"
            bad.write_text(json.dumps(_mutate(doc, path, value)))
            key = ".".join(str(p) for p in path[:1])
            for cons in consumers:
                r = invoke(*[bad if a == "BAD" else a for a in cons])
                lines = r.stderr.strip().splitlines()
                if r.returncode == 2 and len(lines) == 1 and str(bad) in lines[0] and "internal" not in lines[0]:
                    tally["exit 2, one line naming file and key"] += 1
                    if key not in lines[0] and len(examples) < 3:
                        examples.append(f"key {key} not named: {lines[0][:110]}")
                elif (r.returncode == 0 or (r.returncode == 1 and cons[0] == "compare")) \
                        and "internal" not in r.stderr and "Traceback" not in r.stderr:
                    tally["exit 0 (still a valid document; compare: exit 1, it differs)"] += 1
                elif r.returncode == 1 and lines and lines[-1].startswith("Fit failed"):
                    tally["exit 1 'Fit failed' (a valid document the fit cannot use)"] += 1
                else:
                    tally["other"] += 1
                    if len(examples) < 3:
                        examples.append(f"{cons[0]} {'.'.join(map(str, path))} {what}: exit {r.returncode} "
                                        f"{(lines or [''])[-1][:110]}")
        n = len(cases) * len(consumers)
        rows.append(f"  {kind}: {len(cases)} corrupted documents x {len(consumers)} consumers = {n} runs: "
                    + ", ".join(f"{k} {v}" for k, v in tally.items()))
        rows += [f"    {e}" for e in examples]
    return rows


def pairing(out: Path, tmp: Path) -> list[str]:
    results = {"linear_geometry.json": "linear", "rotation_geometry.json": "rotation", "poses.json": "robot",
               "carm_poses.json": "carm"}
    scans = ["linear", "rotation", "robot", "carm"] + (["circular"] if (out / "circular").exists() else [])
    if (out / "rp.json").exists():
        results["rp.json"] = "circular"
    n = n2 = 0
    other = []
    for res, own in results.items():
        for sc in scans:
            if sc == own:
                continue
            for cmd in (("diagnose", out / res, out / sc, "--no-image", "-o", tmp / "p.json"),
                        ("export", out / res, "--scan", out / sc, "--format", "astra", "-o", tmp / "p.txt")):
                r = invoke(*cmd)
                n += 1
                line = (r.stderr.strip().splitlines() or [""])[-1]
                if r.returncode == 2 and str(out / sc) in line and res in line:
                    n2 += 1
                else:
                    other.append(f"    {cmd[0]} {res} with {sc}: exit {r.returncode} {line[:100]}")
    return [f"  {n} pairings of a result with a scan it was not computed from: {n2} exit 2 naming both"] + other[:6]


def files(out: Path, tmp: Path) -> list[str]:
    rows = []
    old = os.umask(0o022)
    try:
        r = conecal("detect", out / "linear", "-o", tmp / "umask.json")
        rows.append(f"  umask 022: output mode {oct((tmp / 'umask.json').stat().st_mode & 0o777)} (exit {r.returncode})")
    finally:
        os.umask(old)
    ro = tmp / "readonly"
    ro.mkdir()
    os.chmod(ro, 0o555)
    t0 = time.perf_counter()
    r = conecal("detect", out / "rotation", "-o", ro / "m.json")
    rows.append(f"  unwritable -o: exit {r.returncode} after {time.perf_counter() - t0:.2f} s "
                f"(whole detect takes longer); {r.stderr.strip().splitlines()[-1][:90]}")
    if os.geteuid() == 0:
        rows.append("    (running as root: a read-only folder is still writable for root; the check above is "
                    "then only the parent-is-a-file case)")
        (tmp / "afile").write_text("x")
        t0 = time.perf_counter()
        r = conecal("detect", out / "rotation", "-o", tmp / "afile" / "m.json")
        rows.append(f"  -o under a file: exit {r.returncode} after {time.perf_counter() - t0:.2f} s")
    long_scan = out / "robot"   # 24 frames of 640x640 with ~40 spheres: long enough to be stopped
    p = subprocess.Popen(CONECAL + ["detect", str(long_scan), "-o", str(tmp / "term.json"), "--workers", "2"],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    time.sleep(4.0)
    kids = subprocess.run(["pgrep", "-P", str(p.pid)], capture_output=True, text=True).stdout.split()
    p.send_signal(signal.SIGTERM)
    rc = p.wait(timeout=30)
    time.sleep(0.5)
    alive = [k for k in kids if subprocess.run(["kill", "-0", k], capture_output=True).returncode == 0]
    leftovers = [f.name for f in tmp.iterdir() if f.name.startswith((".term", "term"))]
    rows.append(f"  SIGTERM to detect (parent only, {len(kids)} workers): exit {rc}, workers alive after "
                f"{len(alive)}, files left {leftovers}")
    return rows


def shards(out: Path, tmp: Path) -> list[str]:
    rows = []
    for i in range(1, 5):
        conecal("detect", "rotation", "--part", f"{i}/4", "-o", tmp / f"part{i}.json", cwd=out)
    conecal("merge", *[tmp / f"part{i}.json" for i in (3, 1, 4, 2)], "-o", tmp / "merged.json", cwd=out)
    conecal("detect", "rotation", "-o", tmp / "whole.json", cwd=out)
    same = (tmp / "merged.json").read_bytes() == (tmp / "whole.json").read_bytes()
    rows.append(f"  detect in 4 parts + merge == one detect, byte for byte: {same}")
    clone = tmp / "checkout"
    subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "snakemake", "-s", "workflow/Snakefile", "-j2", "-q"], cwd=clone,
                       capture_output=True, text=True, env=env)
    ok = r.returncode == 0 and (clone / "out" / "rotation_geometry.json").exists()
    rows.append(f"  snakemake -j2 from a clean checkout (HEAD of this repository): exit {r.returncode}, "
                f"result written: {ok}, {time.perf_counter() - t0:.0f} s")
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--no-rpgrid", action="store_true", help="skip the rp-grid sample (~2 min)")
    ap.add_argument("--samples", type=Path, default=None,
                    help="keep the sample pipelines' outputs here, and reuse them when they exist")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        print("1. --overwrite", *overwrite(tmp / "ow"), sep="\n", flush=True)
        out = a.samples.resolve() if a.samples else tmp / "out"
        t0 = time.perf_counter()
        if not (out / "diag_carm.json").exists():
            sample_outputs(out, rpgrid=not a.no_rpgrid)
        print(f"(sample pipelines ran in {time.perf_counter() - t0:.0f} s)")
        print("3. schema", *schemas(out), sep="\n", flush=True)
        work = tmp / "work"
        work.mkdir()
        print("2. corrupted results", *corruptions(out, work), sep="\n", flush=True)
        print("4. pairing", *pairing(out, work), sep="\n", flush=True)
        print("5. files", *files(out, work), sep="\n", flush=True)
        print("6. parts", *shards(out, work), sep="\n", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
