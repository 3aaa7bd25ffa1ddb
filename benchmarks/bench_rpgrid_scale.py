"""rp-grid's memory and time as the scan grows (issue 31): a simulated
circular scan of V views of N x N pixels (the detector's physical size held,
so finer pixels), then ``conecal rp-grid`` in its own process, its memory
sampled from /proc every 0.2 s.

Printed per scan: the stack's size on disk, peak resident memory (and its
anonymous part: what the process itself allocated, as opposed to pages of
the memory-mapped stack that the kernel may drop at any time), wall time
with the split tables / search / sigma that rp-grid reports, and every
estimate's error against the truth (px of that scan's detector and deg).

    python benchmarks/bench_rpgrid_scale.py --views 720 --size 512 --work /tmp/rps
    python benchmarks/bench_rpgrid_scale.py --views 1440 --size 1024 --work /tmp/rps   # ~6 GB of disk
    PYTHONPATH=<checkout of another commit> python benchmarks/bench_rpgrid_scale.py ... --keep   # side by side
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

from conecal.geometry.misalignment import NAMES
from conecal.simulate import write_scan
from conecal.simulate.scenarios import circular_scan

BASE_SIZE, BASE_PITCH = 256, 0.4   # the scenario's default detector: 102.4 mm


def _status(pid: int) -> dict:
    out = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            k, _, v = line.partition(":")
            if k in ("VmRSS", "RssAnon", "RssFile", "VmHWM"):
                out[k] = int(v.split()[0]) * 1024
    except (FileNotFoundError, ProcessLookupError):
        pass
    return out


def run_measured(cmd: list[str], cwd: Path) -> tuple[float, dict]:
    """Wall time and peak memory (bytes) of one process run in ``cwd``."""
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, cwd=cwd)
    peak = {"VmRSS": 0, "RssAnon": 0, "RssFile": 0, "VmHWM": 0}
    while p.poll() is None:
        for k, v in _status(p.pid).items():
            peak[k] = max(peak[k], v)
        time.sleep(0.2)
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)}: exit {p.returncode}")
    return time.perf_counter() - t0, peak


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=720)
    ap.add_argument("--size", type=int, default=512, help="detector pixels per side")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--keep", action="store_true", help="keep the simulated scan")
    a = ap.parse_args(argv)
    pitch = BASE_PITCH * BASE_SIZE / a.size
    sc = circular_scan(a.seed, rows=a.size, cols=a.size, pitch=pitch, n_frames=a.views, random_misalignment=True)
    scan = a.work / f"circ_{a.views}x{a.size}_s{a.seed}"
    t0 = time.perf_counter()
    if not (scan / "truth.json").exists():
        write_scan(sc, scan, seed=a.seed, overwrite=scan.exists())
    t_sim = time.perf_counter() - t0
    stack_gb = (scan / "projections.tif").stat().st_size / 1e9
    out = a.work / f"rp_{a.views}x{a.size}_s{a.seed}.json"
    # the conecal on sys.path (PYTHONPATH=<another checkout> measures that one; run
    # in the work folder, so that a checkout in the current folder does not come first)
    wall, peak = run_measured([sys.executable, "-c", "from conecal.cli.main import cli; cli()",
                               "-q", "rp-grid", str(scan.resolve()), "-o", str(out.resolve())], a.work)
    doc = json.loads(out.read_text())
    truth = json.loads((scan / "truth.json").read_text())["misalignment"]
    sec = doc["fit"]["seconds"]
    tables = sec.get("tables_pass1", 0) + sec.get("tables_pass2", 0)
    search = sec.get("search_pass1", 0) + sec.get("refine_pass2", 0)
    sigma = sec.get("sigma", float("nan"))
    print(f"# {a.views} views of {a.size}^2 ({pitch:.3f} mm px), seed {a.seed}: stack {stack_gb:.2f} GB "
          f"(simulated in {t_sim:.0f} s)")
    print(f"peak RSS {peak['VmHWM'] / 1e9:.2f} GB (anonymous {peak['RssAnon'] / 1e9:.2f} GB, "
          f"mapped file {peak['RssFile'] / 1e9:.2f} GB); tables {doc['fit']['tables']['megabytes']:.0f} MB")
    print(f"wall {wall:.1f} s: tables {tables:.1f} s, search {search:.1f} s, sigma {sigma:.1f} s "
          f"(rp-grid's split: {json.dumps({k: round(v, 1) for k, v in sec.items()})})")
    print("| parameter | truth | estimate | error | sigma | error/sigma |\n|---|---|---|---|---|---|")
    for n in NAMES:
        p = doc["misalignment"][n]
        err = p["value"] - truth[n]
        s = p["sigma"]
        print(f"| {n} | {truth[n]:+.3f} | {p['value']:+.3f} | {err:+.3f} | "
              f"{'-' if s is None else f'{s:.3f}'} | {'-' if not s else f'{err / s:+.2f}'} |")
    if not a.keep:
        shutil.rmtree(scan)
    return 0


if __name__ == "__main__":
    sys.exit(main())
