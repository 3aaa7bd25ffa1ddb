"""``export --format distortion``: a result's detector distortion as a remap-ready TIFF.

Two float32 pages per distortion, ``dc`` then ``dr`` (rows x cols, px),
sampled at every pixel centre (c, r) of the ideal image: the measured
position of an ideal point is (c + dc, r + dr), so
``cv2.remap(img, c + dc, r + dr, cv2.INTER_LINEAR)`` removes the distortion
from an image (SCAN_FORMAT.md, "Outputs"). A per-frame distortion gives
two pages per frame, in frame order.
"""

from __future__ import annotations

import io

import numpy as np
import tifffile

from ..errors import InputError
from ..geometry.distortion import Distortion
from ..jsonio import atomic_write, read_json


def distortion_pages(result_path) -> tuple[list[np.ndarray], list[str]]:
    """Pages (float32 (rows, cols) px) and their descriptions from a
    ``conecal-poses/1`` or ``conecal-geometry/1`` document."""
    doc = read_json(result_path, ("conecal-geometry", "conecal-poses"))
    try:
        shape = tuple(int(v) for v in doc["detector"]["shape"])
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{result_path}: detector.shape: missing or not (rows, cols)") from None
    per_frame = [f for f in doc.get("frames", []) if isinstance(f, dict) and f.get("distortion")]
    pages, names = [], []
    if per_frame:
        for f in per_frame:
            d = Distortion.from_dict(f["distortion"], f"{result_path}: frames[frame {f.get('frame')}].distortion")
            dc, dr = d.field(shape)
            pages += [dc, dr]
            names += [f"dc frame {f.get('frame')}", f"dr frame {f.get('frame')}"]
        return pages, names
    if not doc.get("distortion"):
        raise InputError(f"{result_path}: distortion: this result has no detector distortion (the fit chose none, "
                         "or it is not a free-pose calibration)")
    d = Distortion.from_dict(doc["distortion"], f"{result_path}: distortion")
    dc, dr = d.field(shape)
    return [dc, dr], ["dc", "dr"]


def write_distortion_tiff(path, pages: list[np.ndarray], names: list[str], note: str) -> None:
    def write(fh):
        buf = io.BytesIO()
        tifffile.imwrite(buf, np.stack(pages).astype(np.float32), photometric="minisblack",
                         description=f"pages: {', '.join(names)} (px); {note}", metadata=None)
        fh.write(buf.getvalue())

    atomic_write(path, write)
