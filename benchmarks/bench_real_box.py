"""detect on a second real C-arm recording: a Surgivisio box phantom (16
small and 2 large balls in a plastic frame with drilled holes), alone and
under a spine phantom, 8-bit BMP display images windowed per frame (issue 32).

The recording is github.com/mbontasuarez/XRayCalib, folder ``dataset`` (not
ours to redistribute: clone it). The script writes a ``motion: free`` scan of
its 25 valid BMP frames (grey value/255 as transmission, a 2.5 mm ball, 0.3
mm pixels, magnification 1.67 nominal), runs ``conecal detect`` with default
options, prints markers and flags per frame and the time, and writes an
overlay per frame (green: unflagged, red: flagged) to look at. Frames named
``Fiducial_*`` hold 18 balls; ``AC_*`` are a fine dot grid (no balls of the
declared size) and ``NA_*`` a spine alone: no markers expected there.
``--raw`` reads the same frames from the recording's 12-bit DICOM files.

    python benchmarks/bench_real_box.py <clone>/dataset --work /tmp/box
"""

from __future__ import annotations

import argparse
import collections
import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import tifffile

from bench_real_carm import write_free_scan


def _raw(bmp: Path) -> np.ndarray:
    """The 12-bit DICOM frame the BMP was made from (same series number)."""
    import pydicom  # only for --raw; not a conecal dependency

    num = re.search(r"_\.(\d+)\.1\.", bmp.name).group(1)
    ima = next(bmp.parent.glob(f"*.XA._.{num}.1.*.IMA"))
    return pydicom.dcmread(ima).pixel_array.astype(np.float32)


def write_scan(images: Path, scan: Path, raw: bool = False) -> list[str]:
    files = sorted(f for f in images.glob("*.BMP") if "Invalid" not in f.name)
    if not files:
        raise SystemExit(f"{images}: no .BMP frames")
    # grey 0 (outside the field) kept finite: half a grey level
    if raw:
        stack = np.stack([np.maximum(_raw(f), 0.5) / 4095.0 for f in files])
    else:
        stack = np.stack([np.maximum(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE).astype(np.float32), 0.5) / 255.0
                          for f in files])
    write_free_scan(scan, stack, [f"{i},{10.0 * i},0,0" for i in range(18)], 0.3, 600.0, 1000.0, 2.5)
    return [re.sub(r"^.*\.\d+_", "", f.stem) for f in files]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("images", type=Path, help="the recording's 'dataset' folder")
    ap.add_argument("--work", type=Path, default=None, help="keep the scan, markers and overlays here")
    ap.add_argument("--raw", action="store_true",
                    help="read the 12-bit DICOM frames (.IMA, needs pydicom) instead of the BMPs")
    a = ap.parse_args(argv)
    work = a.work or Path(tempfile.mkdtemp(prefix="conecal_box_"))
    names = write_scan(a.images, work / "scan", a.raw)
    t0 = time.perf_counter()
    subprocess.run(["conecal", "-q", "detect", str(work / "scan"), "-o", str(work / "markers.json")], check=True)
    print(f"# {len(names)} frames -> {work}; detect {time.perf_counter() - t0:.1f} s")
    doc = json.loads((work / "markers.json").read_text())
    stack = tifffile.imread(work / "scan" / "projections.tif")
    print("| frame | name | markers | flags |\n|---|---|---|---|")
    for f in doc["frames"]:
        k = f["frame"]
        flags = collections.Counter(",".join(m["flags"]) or "-" for m in f["markers"])
        print(f"| {k} | {names[k]} | {len(f['markers'])} | {dict(flags)} |")
        img = cv2.cvtColor((stack[k] * 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)
        for m in f["markers"]:
            cv2.circle(img, (int(round(m["x"])), int(round(m["y"]))), int(m["radius"]) + 3,
                       (0, 0, 255) if m["flags"] else (0, 255, 0), 2)
        cv2.imwrite(str(work / f"overlay_{k:02d}.png"), img)
    return 0


if __name__ == "__main__":
    sys.exit(main())
