"""A real image-intensifier C-arm recording through conecal, default options (issue 29).

The recording: github.com/zsustc/Calibration-of-a-C-arm-x-ray-device-Winter-school,
folder ``uncalibrated`` (29 cropped 1024x1024 8-bit JPEG frames of a C-arm with an
image intensifier; an acrylic plate with a 5x5 grid of 3 mm steel spheres, imaged at
tilts up to 55 deg; two frames have rods across the plate, one has no plate, two are
the same file). It is not ours to redistribute: clone it and pass its folder.

The script writes a ``motion: free`` scan (frames as float32 transmission = value/255;
5x5 grid at a 20 mm pitch, which only scales the pose translations; pixel pitch 0.23 mm
and sdd 1000 mm as rough nominals), runs ``conecal detect`` and ``conecal fit-pose``
with default options, and prints:

- frames ok / ambiguous / rejected and the reasons;
- reprojection RMS of the pinhole (no distortion) and of the chosen model, per frame
  and pooled, and each family's held-out RMS;
- "right": for every ok frame, the labels conecal gave must be a grid labelling
  (a homography from the grid's indices to the centres fits within 3 px, a pinhole's
  misfit on this intensifier being 1.7 px RMS) covering at least 21 of the 25 spheres,
  so that no shifted labelling is possible;
- OpenCV ``calibrateCamera`` (Brown k1 k2 p1 p2 k3; rational + thin prism) on the same
  centres and identities, in the same run, and times.

    git clone https://github.com/zsustc/Calibration-of-a-C-arm-x-ray-device-Winter-school carm_ws
    python benchmarks/bench_real_carm.py carm_ws/uncalibrated
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

PITCH_MM = 20.0


def write_free_scan(scan: Path, stack: np.ndarray, phantom: list[str], pixel_mm: float, sod: float, sdd: float,
                    diameter_mm: float) -> None:
    """A ``motion: free`` scan at ``scan``: ``stack`` (frames, rows, cols) as
    transmission, one log row per frame, ``phantom`` rows "id,x,y,z" (mm) and
    the nominal geometry given. Shared by the real-recording benchmarks."""
    import tifffile

    scan.mkdir(parents=True)
    # one page per frame even for a 3- or 4-frame stack (else read as colour samples)
    tifffile.imwrite(scan / "projections.tif", stack, photometric="minisblack")
    (scan / "log.csv").write_text("frame,time\n" + "".join(f"{k},{k}.0\n" for k in range(len(stack))))
    (scan / "phantom.csv").write_text("id,x,y,z\n" + "\n".join(phantom) + "\n")
    rows, cols = stack.shape[1:]
    (scan / "scan.yaml").write_text(f"""format: conecal-scan/1
motion: free
projections: projections.tif
values: transmission
log: log.csv
detector:
  rows: {rows}
  cols: {cols}
  pixel_pitch: [{pixel_mm}, {pixel_mm}]
nominal:
  sod: {sod}
  sdd: {sdd}
markers:
  diameter: {diameter_mm}
  phantom: phantom.csv
""")


def write_scan(images: Path, scan: Path) -> int:
    import cv2

    files = sorted(images.glob("*.jpg"), key=lambda p: int(re.sub(r"\D", "", p.stem) or 0))
    if not files:
        raise SystemExit(f"{images}: no .jpg frames")
    stack = np.stack([cv2.imread(str(f), cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255.0 for f in files])
    rows = [f"{i},{(i % 5 - 2) * PITCH_MM},{(i // 5 - 2) * PITCH_MM},0" for i in range(25)]
    write_free_scan(scan, stack, rows, 0.23, 900.0, 1000.0, 3.0)
    return len(files)


def pairs(poses: dict, markers: dict, frame: dict):
    ms = markers["frames"][frame["frame"]]["markers"]
    ids = np.array([sid for _, sid in frame["matched"]])
    xy = np.array([[ms[mi]["x"], ms[mi]["y"]] for mi, _ in frame["matched"]])
    return ids, xy


def grid_rms(ids, xy) -> float:
    """RMS (px) of a homography from the grid's indices to the centres."""
    import cv2

    g = np.column_stack([ids % 5, ids // 5]).astype(np.float64)
    H, _ = cv2.findHomography(g, xy)
    p = np.column_stack([g, np.ones(len(g))]) @ H.T
    return float(np.sqrt(np.mean(np.sum((p[:, :2] / p[:, 2:] - xy) ** 2, 1))))


def opencv(poses, markers, shape):
    import cv2

    obj, img = [], []
    for f in poses["frames"]:
        if f["status"] != "ok":
            continue
        ids, xy = pairs(poses, markers, f)
        obj.append(np.column_stack([(ids % 5 - 2) * PITCH_MM, (ids // 5 - 2) * PITCH_MM, np.zeros(len(ids))])
                   .astype(np.float32))
        img.append(xy.astype(np.float32))
    rows, cols = shape
    K = np.array([[1000 / 0.23, 0, (cols - 1) / 2], [0, 1000 / 0.23, (rows - 1) / 2], [0, 0, 1]])
    out = {}
    for name, flags in [("Brown k1 k2 p1 p2 k3", 0), ("rational + thin prism", cv2.CALIB_RATIONAL_MODEL
                                                        | cv2.CALIB_THIN_PRISM_MODEL)]:
        t0 = time.perf_counter()
        rms, *_ = cv2.calibrateCamera(obj, img, (cols, rows), K.copy(), None,
                                      flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_ASPECT_RATIO)
        out[name] = (rms, time.perf_counter() - t0)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("images", type=Path, help="the recording's 'uncalibrated' folder")
    ap.add_argument("--work", type=Path, default=None, help="keep the scan and outputs here")
    ap.add_argument("--fit-pose-args", default="", help="extra fit-pose options, e.g. '--frame-intrinsics c0,r0'")
    a = ap.parse_args(argv)
    work = a.work or Path(tempfile.mkdtemp(prefix="conecal-real-"))
    scan = work / "scan"
    if not (scan / "scan.yaml").exists():
        n = write_scan(a.images, scan)
        print(f"# {n} frames from {a.images} -> {scan}")
    m, p = work / "markers.json", work / "poses.json"
    t0 = time.perf_counter()
    if not m.exists():
        subprocess.run(["conecal", "-q", "detect", str(scan), "-o", str(m)], check=True)
    t1 = time.perf_counter()
    subprocess.run(["conecal", "-q", "fit-pose", str(scan), "--markers", str(m), "-o", str(p),
                    *a.fit_pose_args.split()], check=True)
    t2 = time.perf_counter()
    markers, poses = json.loads(m.read_text()), json.loads(p.read_text())
    frames = poses["frames"]
    ok = [f for f in frames if f["status"] == "ok"]
    print(f"detect {t1 - t0:.1f} s, fit-pose {t2 - t1:.1f} s")
    print(f"frames: {len(ok)}/{len(frames)} ok; " + "; ".join(f"{n} x {r}" for r, n in poses["summary"]["reasons"].items()
                                                              if not r.startswith("ok")))
    wrong = []
    print("frame status      n  RMS px  pinhole  grid-homography RMS")
    for f in frames:
        line = f"{f['frame']:5d} {f['status']:10s}"  # (a rejected frame's whole reason)
        if f["status"] == "ok":
            ids, xy = pairs(poses, markers, f)
            g = grid_rms(ids, xy)
            if len(ids) < 21 or g > 3.0:
                wrong.append(f["frame"])
            line += f" {len(ids):3d}  {f['rms_px']:.3f}   {f['rms_px_pinhole']:.3f}    {g:.2f}"
        print(line)
    r = np.array([f["rms_px"] for f in ok])
    n = np.array([f["n_spheres"] for f in ok])
    pin = np.array([f["rms_px_pinhole"] for f in ok])
    print(f"pooled RMS over ok frames: pinhole {np.sqrt(np.sum(n * pin ** 2) / n.sum()):.3f} px, "
          f"{poses['distortion']['model'] if poses.get('distortion') else 'none'} "
          f"({next(c['family'] for c in poses['distortion_choice'] if c['chosen'])}) "
          f"{np.sqrt(np.sum(n * r ** 2) / n.sum()):.3f} px")
    print("held-out (leave-markers-out) RMS per family: " + ", ".join(
        f"{c['family']} {c['heldout_rms_px']:.3f}" for c in poses["distortion_choice"] if c.get("heldout_rms_px")))
    print(f"ok frames that are not a full grid labelling (wrong ok): {wrong or 'none'}")
    intr = poses["intrinsics"]
    print("intrinsics: " + ", ".join(f"{k} {v['value']:.1f} +- {v['sigma']:.1f} {v['unit']}" for k, v in intr.items()))
    shape = (markers["detector"]["shape"] if "shape" in markers.get("detector", {}) else (1024, 1024))
    for name, (rms, dt) in opencv(poses, markers, shape).items():
        print(f"OpenCV calibrateCamera, {name}, same centres and identities: RMS {rms:.3f} px, {dt * 1000:.0f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
