"""Expose simulated line integrals on a detector and write a scan directory.

The directory is assembled in a temporary sibling folder and renamed into
place at the end, so an interrupted run leaves nothing half-written.
"""

from __future__ import annotations

import csv
import io
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import tifffile
import yaml

from .. import __version__
from ..errors import InputError
from ..jsonio import dumps, umask
from ..effects.imaging import beam_hardened
from ..scan.config import POSE_GUESS_COLUMNS
from .render import render_line_integrals
from .scenarios import Scenario, marker_truth

DARK_LEVEL = 100.0


def expose(sc: Scenario, line_integrals: np.ndarray, rng: np.random.Generator, previous_T: np.ndarray | None = None,
           k: int = 0):
    """Turn line integrals into a transmission image as the detector records it.

    Background plate, beam hardening, focal-spot blur (Gaussian on the
    intensity; the modelled ``sc.blur_px`` and any extra blur in quadrature),
    circular field of view, detector lag, scattered intensity, Poisson noise
    at ``sc.photons`` per pixel and optional JPEG compression. Returns
    (transmission float64, noiseless transmission before lag for the next
    frame's lag).
    """
    im = sc.imaging_at(k)
    rows, cols = line_integrals.shape
    a0, gc, gr = sc.background
    a = line_integrals
    if a0 or gc or gr:
        a = a + (a0 + gc * np.arange(cols)[None, :] / cols + gr * np.arange(rows)[:, None] / rows)
    a = beam_hardened(a, im.beam_hardening)
    T = np.exp(-a)
    blur = float(np.hypot(sc.blur_px, im.extra_blur_px))
    if blur > 0:
        T = cv2.GaussianBlur(T, (0, 0), blur, borderType=cv2.BORDER_REPLICATE)
    clean = T
    lag = sc.lag + im.lag
    if lag > 0 and previous_T is not None:
        T = (1 - lag) * T + lag * previous_T
    if im.scatter:
        T = T + im.scatter
    if sc.fov_radius is not None:
        yy, xx = np.mgrid[0:rows, 0:cols]
        outside = (xx - (cols - 1) / 2) ** 2 + (yy - (rows - 1) / 2) ** 2 > sc.fov_radius**2
        T = np.where(outside, 2e-3, T)
    if sc.photons > 0:
        T = rng.poisson(sc.photons * T) / sc.photons
    if sc.jpeg_quality is not None:
        q = np.clip(T * 255.0, 0, 255).astype(np.uint8)
        ok, buf = cv2.imencode(".jpg", q, [cv2.IMWRITE_JPEG_QUALITY, int(sc.jpeg_quality)])
        T = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED).astype(np.float64) / 255.0
    return T, clean


def _stored(T: np.ndarray, values: str, photons: float) -> np.ndarray:
    if values == "attenuation":
        # half a photon is the floor of a noisy zero count; a noiseless image has none
        floor = 0.5 / photons if photons > 0 else 1e-12
        return (-np.log(np.maximum(T, floor))).astype(np.float32)
    if values == "transmission":
        return T.astype(np.float32)
    return (T * photons + DARK_LEVEL).astype(np.float32)


def write_scan(sc: Scenario, out: str | Path, *, seed: int = 0, values: str = "attenuation", overwrite: bool = False,
               progress: Callable[[int, int], None] | None = None) -> Path:
    """Render every frame of ``sc`` and write the scan directory ``out`` with
    ``scan.yaml``, ``log.csv``, ``projections.tif``, ``truth.json`` (and
    ``phantom.csv``, ``flat.tif``, ``dark.tif`` where needed)."""
    out = Path(out)
    if out.exists() or out.is_symlink():
        if not overwrite:
            raise InputError(f"{out}: already exists (use --overwrite to replace it)")
        check_replaceable(out)
    if values not in ("attenuation", "transmission", "raw"):
        raise InputError(f"--values: must be attenuation, transmission or raw, got {values!r}")
    if values == "raw" and sc.photons <= 0:
        raise InputError("--values raw needs photon noise (--photons > 0)")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        rng = np.random.default_rng(seed + 7919)
        transforms = sc.world.transforms()
        cfg = dict(sc.config, values=values)
        cfg.setdefault("imaging", {"blur_px": float(sc.blur_px)})   # the stated blur, not any extra
        frames_truth = []
        prev = None
        with tifffile.TiffWriter(tmp / "projections.tif", bigtiff=sc.n_frames * np.prod(sc.geometry.shape) * 4 > 3.5e9) as tw:
            for k in range(sc.n_frames):
                T = transforms[k]
                g = sc.frame_geometry(k)
                L = render_line_integrals(g, sc.solids(k, T), ss=sc.supersample, distortion=sc.imaging_at(k))
                img, prev = expose(sc, L, rng, prev, k)
                tw.write(_stored(img, values, sc.photons), contiguous=True, photometric="minisblack")
                frames_truth.append({"frame": k, "R": T.R.tolist(), "t": T.t.tolist(),
                                     "source": g.source.tolist(), "markers": marker_truth(sc, k, T)})
                if progress:
                    progress(k + 1, sc.n_frames)
        if values == "raw":
            rows, cols = sc.geometry.shape
            tifffile.imwrite(tmp / "dark.tif", np.full((rows, cols), DARK_LEVEL, np.float32))
            tifffile.imwrite(tmp / "flat.tif", np.full((rows, cols), sc.photons + DARK_LEVEL, np.float32))
            cfg["flat"], cfg["dark"] = "flat.tif", "dark.tif"
        (tmp / "scan.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False), encoding="utf-8")
        if sc.kind == "robot":
            names = [f"q{j + 1}" for j in range(sc.readings.shape[1])]
        elif sc.kind == "free":
            names = list(POSE_GUESS_COLUMNS[:sc.readings.shape[1]])
        else:
            names = [a["name"] for a in sc.config["axes"]]
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["frame", "time"] + names)
        for k in range(sc.n_frames):
            w.writerow([k, f"{sc.times[k]:.6f}"] + [f"{x:.6f}" for x in sc.readings[k]])
        (tmp / "log.csv").write_text(buf.getvalue(), encoding="utf-8")
        if sc.phantom is not None:
            ids, cad = sc.phantom
            lines = ["id,x,y,z"] + [f"{i},{p[0]:.6f},{p[1]:.6f},{p[2]:.6f}" for i, p in zip(ids, cad)]
            (tmp / "phantom.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
        truth = {"format": "conecal-truth/1", "software": f"conecal {__version__}", "seed": seed, "kind": sc.kind,
                 "geometry": {"format": "conecal-geometry/1", **sc.geometry.to_dict(),
                              "axes": sc.world.chain.to_list() if sc.world.chain is not None else []},
                 "photons": sc.photons, "blur_px": sc.blur_px, "background": list(sc.background),
                 "effects": [e.to_dict() for e in sc.effects],
                 "spheres": [{"id": int(i), "position": p.tolist(), "diameter": float(2 * r)}
                             for i, p, r in zip(sc.sphere_ids, sc.sphere_positions, sc.sphere_radii)],
                 "frames": frames_truth, **sc.truth_extra}
        if sc.frame_warps is not None:
            for fr, w in zip(frames_truth, sc.frame_warps):
                fr["distortion"] = None if w is None else w.to_dict()
        (tmp / "truth.json").write_text(dumps(truth), encoding="utf-8")
        os.chmod(tmp, 0o777 & ~umask())
        _swap_into_place(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


# every name write_scan can put in a scan directory
WRITTEN_NAMES = frozenset({"scan.yaml", "log.csv", "projections.tif", "truth.json", "phantom.csv", "flat.tif",
                           "dark.tif"})


def check_replaceable(out: Path) -> None:
    """Refuse (InputError) to replace ``out`` unless conecal itself wrote it.

    A directory counts as conecal's when it is empty, or when it holds only
    regular files with the names ``write_scan`` writes and a ``truth.json``
    whose ``format`` is ``conecal-truth/...`` and whose ``software`` names
    conecal. The current directory and its ancestors are never replaced,
    and neither is a symbolic link or a file. Nothing is touched here.
    """
    if out.is_symlink():
        raise InputError(f"{out}: is a symbolic link; --overwrite replaces only a scan directory that conecal wrote")
    if not out.is_dir():
        raise InputError(f"{out}: exists and is not a directory; --overwrite replaces only a scan directory "
                         "that conecal wrote")
    real = out.resolve()
    cwd = Path.cwd().resolve()
    if real == cwd or real in cwd.parents:
        raise InputError(f"{out}: is the current directory or one of its parents; --overwrite never replaces it")
    try:
        entries = sorted(os.scandir(out), key=lambda e: e.name)
    except OSError as exc:
        raise InputError(f"{out}: cannot be read ({exc.strerror}); nothing was replaced") from None
    if not entries:
        return
    foreign = [e.name + ("/" if e.is_dir(follow_symlinks=False) else "") for e in entries
               if e.name not in WRITTEN_NAMES or not e.is_file(follow_symlinks=False)]
    if foreign:
        shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
        raise InputError(f"{out}: holds files that conecal did not write ({shown}); --overwrite replaces only a "
                         "scan directory that conecal simulate wrote, so nothing was touched")
    if not _written_by_conecal(out / "truth.json"):
        raise InputError(f"{out}: its truth.json is missing or not conecal's (key 'software'); --overwrite replaces "
                         "only a scan directory that conecal simulate wrote, so nothing was touched")


def _written_by_conecal(truth: Path) -> bool:
    try:
        doc = json.loads(truth.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return (isinstance(doc, dict) and str(doc.get("format", "")).startswith("conecal-truth/")
            and str(doc.get("software", "")).startswith("conecal"))


def _swap_into_place(tmp: Path, out: Path) -> None:
    """Rename the finished directory ``tmp`` to ``out``; an old ``out`` is
    first renamed aside and removed only once the new one is in place, so
    that at every instant one complete scan directory stands at ``out``
    or beside it."""
    if not out.exists():
        os.replace(tmp, out)
        return
    old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old.", dir=out.parent))
    os.rmdir(old)
    os.rename(out, old)
    try:
        os.replace(tmp, out)
    except BaseException:
        os.rename(old, out)
        raise
    shutil.rmtree(old, ignore_errors=True)
