"""detect and fit-pose end to end on rendered image-intensifier radiographs
(issues 29 and 32).

Frames from ``benchmarks/carm_images.py``, written by a helper session that
never saw conecal's code: a 6x6 steel-sphere grid in a PMMA plate whose edges
cross the field, or a 3-D ball phantom whose shadows touch and overlap, at
free poses; veiling glare, vignetting, a pincushion and a per-frame S-twist,
blur, quantum noise, an 8-bit log display (and JPEG in two cases), rods and
a soft background in one; nominal magnification off by -25 / +25 % in two.
Truth: each sphere's own attenuation centroid after the distortion.

Per case: ``conecal detect`` (the CLI, default options) and the free-pose
calibration (``calibrate_free``, default options) on its markers. Printed:
spheres found of those in the field and not truncated, by overlap; RMS and
pull std per flag class; false detections; frames ok / ambiguous /
rejected; wrong ok (an ok frame whose labels are not the true ones up to
the symmetry of the spheres it matched) and turned ok (right up to that, but
no symmetry of the whole phantom: the pose is turned); reprojection RMS;
held-out 3-D points' RMS (carried through the symmetry a frame was labelled by).
``--gen carm_images2``: a second renderer, written by another helper session
without conecal's code (a helix cylinder and grids on a flat panel and an
intensifier, multi-page flats, a flat black outside the intensifier's field).
``--gen carm_images3``: a third, by a third helper session from the scan
contract alone (a coded helix of 1.6 and 3.2 mm beads declared by the
smaller, a two-plate cage on an 8-bit log display with JPEG q70 and the
nominal magnification 20 % off, a grid beside a plate's edge and an
aluminium wedge on a flat panel, a grid under a local dent of the input
screen, a cube's corners; per-frame cubic or tangent-twist distortion fields;
glare beyond the intensifier's field in the flat).
``--gen carm_images4``: a fourth, by a fourth helper session from the scan
contract alone (a tilted flat panel with rectangular pixels, heel effect,
scatter and beam hardening; barrel distortion with a per-frame turn and a
smooth residual field in an elliptical field, lead letters; a chiral helix
whose images are mirrored, where no frame can be ok; a dense two-size ball
phantom under a sagging pincushion with wires, magnification 20 % off; a
plain grid as control). Each printed row lists the frames it counts wrong or
turned (``wrong_or_turned_frames``).

    python benchmarks/bench_images.py [--cases ball3d_ii grid_ii] [--seeds 1 2]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import importlib  # noqa: E402
from bench_free import identity_map, whole_symmetry  # noqa: E402
from conecal.calib.run import FreeOptions, calibrate_free  # noqa: E402
from conecal.calib.document import free_document  # noqa: E402
from conecal.scan import load_scan  # noqa: E402
from conecal.stats import mad_sigma  # noqa: E402

def _match(markers: list, centres: list):
    """For each marker the truth centre it is (index) or None: nearest within
    half the shadow's diameter, each truth once."""
    out, used = [None] * len(markers), set()
    if not centres:
        return out
    T = np.array([[c["x"], c["y"]] for c in centres])
    for i, m in enumerate(markers):
        d = np.hypot(T[:, 0] - m["x"], T[:, 1] - m["y"])
        j = int(np.argmin(d))
        # (a renderer may give a shadow cut by the field's edge the centroid of its
        # visible part, up to a radius from the sphere's own centre)
        if d[j] < (1.0 if centres[j].get("truncated") else 0.5) * centres[j]["diameter_px"] and j not in used:
            used.add(j)
            out[i] = j
    return out


def run_case(gen, name: str, seed: int, root: Path, reuse: bool = False) -> dict:
    """``reuse``: fit the case's markers already in ``root`` (rendered and
    detected by an earlier run), so that two builds of fit-pose compare on
    the same markers."""
    out = root / f"{name}_{seed}"
    mpath = out / "markers.json"
    t0 = time.perf_counter()
    if not (reuse and mpath.exists()):
        gen.make_case(name, seed, out)
        subprocess.run(["conecal", "-q", "detect", str(out / "scan"), "-o", str(mpath)], check=True)
    truth = json.loads((out / "truth.json").read_text())
    t_detect = time.perf_counter() - t0
    mdoc = json.loads(mpath.read_text())
    by_frame = {int(f["frame"]): f["markers"] for f in mdoc["frames"]}
    n_in = {"overlap": 0, "separate": 0}
    found = {"overlap": 0, "separate": 0}
    errs = {"overlap": [], "separate": []}
    pulls: dict = {}
    by_flag: dict = {}
    false = 0
    true_ids = {}
    either = {}   # (frame, marker) -> ids of every sphere whose centre lies inside the marker's shadow
    for k, centres in enumerate(truth["centres"]):
        ms = by_frame.get(k, [])
        which = _match(ms, centres)
        true_ids[k] = [None if j is None else int(centres[j]["id"]) for j in which]
        for i, m in enumerate(ms):
            either[k, i] = {int(c["id"]) for c in centres
                            if np.hypot(c["x"] - m["x"], c["y"] - m["y"]) < 0.5 * c["diameter_px"]}
        false += sum(j is None for j in which)
        hit = {j: m for m, j in zip(ms, which) if j is not None}
        for j, c in enumerate(centres):
            if c["truncated"]:
                continue
            cls = "overlap" if c["overlap"] else "separate"
            n_in[cls] += 1
            if j in hit:
                m = hit[j]
                found[cls] += 1
                e = (m["x"] - c["x"], m["y"] - c["y"])
                errs[cls].append(e)
                key = ",".join(sorted(m["flags"])) or "unflagged"
                pulls.setdefault(key, []).extend([e[0] / m["sigma"], e[1] / m["sigma"]])
                by_flag.setdefault(key, []).append(e)
    scan = load_scan(out / "scan")
    t1 = time.perf_counter()
    try:
        res = calibrate_free(scan, mdoc, scan.nominal_geometry(), FreeOptions())
    except Exception as exc:   # a failed fit is a result here, not a crash
        return {"case": name, "seed": seed, "fit_failed": str(exc), "time_detect_s": t_detect}
    t_fit = time.perf_counter() - t1
    doc = free_document(res, FreeOptions(), {"format": "conecal-poses/1"})
    b = res.bundle
    n_ok = n_amb = wrong = turned = 0
    held, wrong_frames = [], []
    for fr, f in zip(doc["frames"], res.frames):
        st = fr["status"]
        n_amb += st.startswith("ambiguous")
        if st != "ok":
            continue
        n_ok += 1
        # a marker on two shadows nearly on top of each other (flagged overlap,
        # sigma their half-separation) is either sphere: the name fit-pose gave
        # it is right if it is one of them, through the symmetry the frame was
        # named by
        k = fr["frame"]
        cover = {d: either.get((k, d), set()) for d, _ in fr.get("matched", [])}
        to_ours = identity_map(fr, true_ids[k], scan.phantom, cover)
        if to_ours is None:
            wrong += 1
            wrong_frames.append(fr["frame"])
            continue
        if not whole_symmetry(to_ours, scan.phantom.positions):
            turned += 1     # right projections, the pose turned: wrong for a reconstruction
            wrong_frames.append(fr["frame"])
        h = next(h for h in truth["heldout"] if h["frame"] == fr["frame"])
        if h["points"]:
            # (labelled by a symmetry of the phantom, the pose is the symmetric
            # one: the held-out points, in the true phantom frame, are carried along)
            P, Q = to_ours(np.array(h["points"])), np.array(h["pixels"])
            held.append(np.sum((b.predict(P, np.full(len(P), f["slot"])) - Q) ** 2, 1))
    # the intrinsics against the renderer's truth, in their stated sigma (the
    # principal point is where a model's leftover structure shows first)
    it = doc["intrinsics"]
    true = {"sdd": truth["sdd"], "c0": truth["principal_point"][0], "r0": truth["principal_point"][1]}
    intr_z = {k: round(float((it[k]["value"] - v) / it[k]["sigma"]), 1) if it[k].get("sigma") else None
              for k, v in true.items()}
    intr_err = {k: round(float(it[k]["value"] - v), 1) for k, v in true.items()}
    return {"case": name, "seed": seed,
            "intrinsics_err": intr_err, "intrinsics_z": intr_z,
            "found": {c: f"{found[c]}/{n_in[c]}" for c in n_in},
            "rms_px": {c: float(np.sqrt(np.mean(np.square(errs[c])))) if errs[c] else None for c in errs},
            "pull_std": {k: [round(float(np.std(v)), 2), round(float(mad_sigma(v)), 2), len(v) // 2]
                         for k, v in sorted(pulls.items())},
            "rms_px_by_flag": {k: round(float(np.sqrt(np.mean(np.square(v)))), 3) for k, v in sorted(by_flag.items())},
            "false": false, "frames": len(doc["frames"]), "ok": n_ok, "ambiguous": n_amb, "wrong_ok": wrong,
            "turned_ok": turned, "wrong_or_turned_frames": wrong_frames,
            "rms_fit_px": doc["summary"]["rms_px"], "family": doc["distortion"]["family"] if doc["distortion"] else
            "none", "heldout_rms_px": float(np.sqrt(np.mean(np.concatenate(held)))) if held else None,
            "time_detect_s": round(t_detect, 1), "time_fit_s": round(t_fit, 1)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="*")
    ap.add_argument("--seeds", type=int, nargs="*", default=[1])
    ap.add_argument("--work", type=Path, help="keep the cases here (default: a temporary folder)")
    ap.add_argument("--gen", default="carm_images", help="renderer module in benchmarks/ (carm_images, carm_images2, carm_images3, carm_images4)")
    ap.add_argument("--reuse", action="store_true",
                    help="with --work: fit the markers an earlier run left there (no rendering, no detect)")
    a = ap.parse_args(argv)
    gen = importlib.import_module(a.gen)
    cases = a.cases or list(gen.CASES)
    print(f"# bench_images: cases from benchmarks/{a.gen}.py (independent renderer)")
    with tempfile.TemporaryDirectory() as tmp:
        root = a.work or Path(tmp)
        for seed in a.seeds:
            for name in cases:
                print(json.dumps(run_case(gen, name, seed, root, a.reuse and a.work is not None)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
