"""diagnose on a free-pose result: is a local displacement on the detector
located where it is, and is nothing located where there is none?

Two kinds of case:

- ``grid_ii_local`` of ``benchmarks/carm_images3.py`` (a renderer written by
  a helper session from the scan contract alone): an intensifier's
  pincushion plus a Gaussian dent of its screen (1.5-2.5 px, sigma 26 px),
  rendered into the images; detect, fit-pose and diagnose by the CLI.
- A scan without a dent (``--base``: cage_ii_jpeg of the same renderer,
  ball3d_ii of ``carm_images.py``), detected once; then a displacement of
  this script's own forms added to every marker's centre, and fit-pose and
  diagnose run again on the changed markers. Forms (none of them conecal's):
  ``bump`` (a translation A exp(-d^2 / 2 s^2) e), ``crater`` (radial,
  A (d / s) exp(1/2 - d^2 / 2 s^2), largest at d = s), ``scratch`` (A e_perp
  across a 4 s long line segment, Gaussian of width s across it), and
  ``none`` (nothing added: any place located is a false one).

Printed per run: the largest injected displacement on a marker, the places
diagnose located (centre, size), the distance of the nearest to the truth,
and the verdict. A place counts as found when its centre is within its
radius plus the form's width of the truth; any other place is false.

    python benchmarks/bench_local_field.py --work W [--seeds 1 2] [--amplitudes 0.2 0.5 1.5]
"""

from __future__ import annotations

import argparse
import importlib
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

FORMS = ("bump", "crater", "scratch")
WIDTHS = (15.0, 30.0, 50.0)


def displacement(form: str, xy: np.ndarray, centre, amp: float, width: float, angle: float) -> np.ndarray:
    """The injected field (N, 2) px at detector positions ``xy`` (N, 2) px."""
    d = xy - np.asarray(centre)
    e = np.array([np.cos(angle), np.sin(angle)])
    if form == "none":
        return np.zeros_like(xy)
    if form == "bump":
        return amp * np.exp(-(d ** 2).sum(1) / (2 * width ** 2))[:, None] * e
    if form == "crater":
        r2 = (d ** 2).sum(1)
        return amp * d / width * np.exp(0.5 - r2 / (2 * width ** 2))[:, None]
    if form == "scratch":
        along = d @ e
        across = d @ np.array([-e[1], e[0]])
        w = np.exp(-across ** 2 / (2 * width ** 2)) * (np.abs(along) <= 2 * width)
        return amp * w[:, None] * np.array([-e[1], e[0]])
    raise ValueError(form)


def _run(cmd: list) -> None:
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def diagnose(scan: Path, markers: Path, out: Path) -> dict:
    _run(["conecal", "-q", "fit-pose", str(scan), "--markers", str(markers), "-o", str(out / "poses.json")])
    _run(["conecal", "-q", "diagnose", str(out / "poses.json"), str(scan), "--markers", str(markers),
          "-o", str(out / "diagnosis.json")])
    return json.loads((out / "diagnosis.json").read_text())


def places(diag: dict) -> list:
    return [loc for loc in diag["located"] if loc.get("centre_px")]


def score(diag: dict, centre, width: float | None) -> dict:
    """Found / false places against a truth ``centre`` (None: nothing there)."""
    found, false, dist = False, 0, None
    for p in places(diag):
        d = float(np.hypot(*(np.asarray(p["centre_px"]) - centre))) if centre is not None else np.inf
        if centre is not None and d <= p["radius_px"] + width:
            found, dist = True, d if dist is None else min(dist, d)
        else:
            false += 1
    other = [loc["component"] for loc in diag["located"] if not loc.get("centre_px")]
    return {"found": found, "distance_px": None if dist is None else round(dist, 1), "false_places": false,
            "places": [[round(v) for v in p["centre_px"]] + [round(p["size_px"], 3)] for p in places(diag)],
            "other_located": other}


def base_case(gen: str, name: str, seed: int, root: Path) -> Path:
    out = root / f"{name}_{seed}"
    if not (out / "markers.json").exists():
        importlib.import_module(gen).make_case(name, seed, out)
        _run(["conecal", "-q", "detect", str(out / "scan"), "-o", str(out / "markers.json")])
    return out


def injected(base: Path, form: str, amp: float, width: float, rng, out: Path) -> tuple:
    """The base case's markers with the field added; returns (path, centre, max px)."""
    doc = json.loads((base / "markers.json").read_text())
    xy = np.array([[m["x"], m["y"]] for f in doc["frames"] for m in f["markers"]], float)
    # a centre among the markers (a place no marker crosses cannot be seen)
    centre = xy[rng.integers(len(xy))] + rng.normal(0, 5, 2)
    angle = rng.uniform(0, 2 * np.pi)
    moved = displacement(form, xy, centre, amp, width, angle)
    i = 0
    for f in doc["frames"]:
        for m in f["markers"]:
            m["x"], m["y"] = m["x"] + float(moved[i, 0]), m["y"] + float(moved[i, 1])
            i += 1
    out.mkdir(parents=True, exist_ok=True)
    path = out / "markers.json"
    path.write_text(json.dumps(doc))
    return path, centre, float(np.hypot(*moved.T).max())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--seeds", type=int, nargs="*", default=[1])
    ap.add_argument("--amplitudes", type=float, nargs="*", default=[0.2, 0.5, 1.5])
    ap.add_argument("--base", nargs="*", default=["carm_images3:cage_ii_jpeg", "carm_images:ball3d_ii"])
    ap.add_argument("--no-dent-case", action="store_true", help="skip the renderer's own dent (grid_ii_local)")
    a = ap.parse_args(argv)
    a.work.mkdir(parents=True, exist_ok=True)
    print("# bench_local_field: diagnose's local places against the truth")
    for seed in a.seeds:
        if not a.no_dent_case:
            t0 = time.perf_counter()
            b = base_case("carm_images3", "grid_ii_local", seed, a.work)
            truth = json.loads((b / "truth.json").read_text())["distortion"][0]
            diag = diagnose(b / "scan", b / "markers.json", b)
            print(json.dumps({"case": "grid_ii_local (rendered dent)", "seed": seed,
                              "truth": [round(v) for v in truth["dent_centre"]] + [round(truth["dent_amplitude_px"], 2)],
                              **score(diag, np.asarray(truth["dent_centre"]), truth["dent_sigma_px"]),
                              "time_s": round(time.perf_counter() - t0, 1)}), flush=True)
        for spec in a.base:
            gen, name = spec.split(":")
            b = base_case(gen, name, seed, a.work)
            rng = np.random.default_rng([seed, len(name)])
            runs = [("none", 0.0, 0.0)] + [(f, amp, WIDTHS[(i + j) % len(WIDTHS)])
                                           for i, f in enumerate(FORMS) for j, amp in enumerate(a.amplitudes)]
            for form, amp, width in runs:
                t0 = time.perf_counter()
                out = a.work / f"{name}_{seed}_{form}_{amp:g}"
                path, centre, biggest = injected(b, form, amp, width, rng, out)
                diag = diagnose(b / "scan", path, out)
                print(json.dumps({"case": name, "seed": seed, "form": form, "amplitude_px": amp, "width_px": width,
                                  "truth": [round(v) for v in centre] + [round(biggest, 2)],
                                  **score(diag, None if form == "none" else centre, width),
                                  "time_s": round(time.perf_counter() - t0, 1)}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
