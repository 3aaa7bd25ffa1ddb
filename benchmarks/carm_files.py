"""The files of a markers-level ``motion: free`` case (scan.yaml, phantom.csv,
log.csv, a blank projections stub, markers.json), as the scan contract
defines them; shared by the independent C-arm generators (their physics is
their own, not this)."""

import json

import numpy as np
import tifffile
import yaml


def write_free_scan(out, *, rows, cols, pitch, sod, sdd, diameter, phantom, frames):
    """``phantom``: (id, x, y, z) rows, mm; ``frames``: conecal-markers/1 frames."""
    scan = {"format": "conecal-scan/1", "motion": "free", "projections": "projections.tif",
            "values": "attenuation", "log": "log.csv",
            "detector": {"rows": rows, "cols": cols, "pixel_pitch": [pitch, pitch]},
            "nominal": {"sod": sod, "sdd": sdd},
            "markers": {"diameter": diameter, "phantom": "phantom.csv"}}
    n = len(frames)
    (out / "scan" / "scan.yaml").write_text(yaml.safe_dump(scan, sort_keys=False))
    (out / "scan" / "phantom.csv").write_text(
        "id,x,y,z\n" + "".join(f"{i},{x:.6f},{y:.6f},{z:.6f}\n" for i, x, y, z in phantom))
    (out / "scan" / "log.csv").write_text("frame,time\n" + "".join(f"{k},{2.0 * k:.1f}\n" for k in range(n)))
    tifffile.imwrite(out / "scan" / "projections.tif", np.zeros((n, rows, cols), np.float32), photometric="minisblack")
    (out / "markers.json").write_text(json.dumps({"format": "conecal-markers/1", "frames": frames}, sort_keys=True))
