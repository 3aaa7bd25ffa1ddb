"""``detect`` over a whole scan: frames in parallel, then contrast and identity."""

from __future__ import annotations

import multiprocessing as mp
import signal
from dataclasses import replace
from typing import Callable

import numpy as np
from threadpoolctl import threadpool_limits

from .. import __version__
from ..scan import Scan
from . import kernels
from .crowded import detect_frame
from .frame import NonFiniteFrame
from .options import DetectOptions
from .gain import MIN_ALONE, linearised, response_lambda, with_background, with_gain_sigma
from .noise import noise_autocorrelation, noise_correlation, noise_pixel, noise_small
from .peaks import small_frame
from .size import MIN_SHADOWS, measured_size
from .track import track

MARKERS_FORMAT = "conecal-markers/1"

_WORKER = None
_ABORT = None          # a multiprocessing Event: set, the queued frames are skipped


def _run_worker(k):
    # after an error or an interrupt the queued frames end at once (see measure_frames)
    if _ABORT is not None and _ABORT.is_set():
        return None
    return _WORKER(k)


def _worker_init() -> None:
    """A worker ends with the parent: SIGTERM back to its default (the parent's
    handler raises for clean-up it alone must do), Ctrl-C left to the parent,
    and on Linux the kernel sends SIGTERM if the parent dies first."""
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def options_for_scan(scan: Scan, *, threshold: float = 10.0, blur_px: float = 1.0,
                     diameter_px: tuple[float, float] | None = None) -> DetectOptions:
    """Expected shadow sizes from ``markers.diameter(s)`` and the nominal
    magnification, widened for depth changes (x0.6 .. x1.6)."""
    if diameter_px is None:
        cfg = scan.config
        if cfg.markers is None:
            from ..errors import InputError
            raise InputError(f"{scan.root / 'scan.yaml'}: markers: this scan declares no markers (give --diameter-px)")
        ds = cfg.markers.diameters or (cfg.markers.diameter,)
        m = cfg.nominal.sdd / cfg.nominal.sod
        pitch = float(np.sqrt(cfg.detector.pixel_pitch[0] * cfg.detector.pixel_pitch[1]))
        px = [d * m / pitch for d in ds]
        size = max(cfg.detector.rows, cfg.detector.cols)
        if not all(np.isfinite(px)) or max(px) > size or min(px) < 0.5:
            from ..errors import InputError
            raise InputError(f"{scan.root / 'scan.yaml'}: markers.diameter: a {max(ds):g} mm sphere casts a "
                             f"{max(px):.3g} px shadow at pixel pitch {pitch:g} mm and magnification {m:.3g} "
                             f"(expected 0.5 px to the detector's {size} px; give --diameter-px to override)")
        extent = 0.0
        if scan.phantom is not None and len(scan.phantom.positions):
            pts = np.asarray(scan.phantom.positions, float)
            extent = (float(np.max(np.linalg.norm(pts - pts.mean(0), axis=1))) + max(ds) / 2) / cfg.nominal.sod
        return DetectOptions(diameter_px=(0.6 * min(px), 1.6 * max(px)), threshold=threshold, blur_px=blur_px,
                             shadow_px=tuple(float(d) for d in px), depth_extent=extent)
    return DetectOptions(diameter_px=tuple(float(d) for d in diameter_px), threshold=threshold, blur_px=blur_px)


def kinematic_predictor(scan: Scan):
    """Image motion predicted from the log and the nominal kinematics.

    A marker seen at ``xy`` in frame ``k1`` is placed on its ray at the
    depth of the sample origin, carried to frame ``k2`` by the nominal
    transforms and projected. Exact for a sphere at the sample origin,
    approximate elsewhere (good enough for a gate).
    """
    try:
        T = scan.nominal_transforms()
    except Exception:  # a log the nominal kinematics cannot read: no prediction
        return None
    g = scan.nominal_geometry()
    Tinv = T.inverse()

    def predict(k1, xy, k2):
        D = g.detector_point(xy[0], xy[1])
        d = D - g.source
        d /= np.linalg.norm(d)
        O = T.t[k1]
        X = g.source + np.dot(O - g.source, d) * d
        Xs = Tinv[k1].apply(X)
        return g.project(T[k2].apply(Xs))

    return predict


def lag_corrected(a: np.ndarray, previous: np.ndarray, lag: float) -> np.ndarray:
    """Attenuation of a frame with a fraction ``lag`` of the previous frame's
    intensity removed: ``T = (T_rec - lag T_prev) / (1 - lag)`` (one step of
    the recursion; the error is of order lag^2)."""
    T = (np.exp(-a.astype(np.float64)) - lag * np.exp(-previous.astype(np.float64))) / (1.0 - lag)
    return (-np.log(np.maximum(T, 1e-6))).astype(np.float32)


def detect_scan(scan: Scan, opt: DetectOptions, *, workers: int = 2, lag: float = 0.0,
                progress: Callable[[int, int], None] | None = None) -> dict:
    """Detect, filter and track markers in every frame; returns a
    ``conecal-markers/1`` document (frames in log order). ``lag``: remove
    that fraction of the previous frame (in time) from each frame first, as
    ``diagnose`` measures it."""
    frames_idx = [int(f) for f in scan.log.frame]
    opt, results = measure_frames(scan, opt, frames_idx, workers=workers, lag=lag, progress=progress)
    return assemble(scan, opt, frames_idx, results)


def scan_options(scan: Scan, opt: DetectOptions) -> DetectOptions:
    """``opt`` with the scan's pixel noise and shadow size, measured once on
    the middle frame of the whole log (and the frames a quarter of the log
    either side when it holds too few shadows), so that every shard of a scan
    uses the same: the sizes looked for follow the measured ones when the
    nominal magnification was off (:func:`conecal.detect.size.measured_size`)."""
    frames_idx = [int(f) for f in scan.log.frame]
    if not frames_idx or (opt.pixel_noise and (opt.size_scale or not opt.shadow_px)
                          and opt.response_lambda is not None):
        return opt
    scan.stack.read(frames_idx[0], check=False)   # a bad stack is named at its first frame
    mid = scan.stack.read(frames_idx[len(frames_idx) // 2], check=False)
    if not np.isfinite(mid).all():
        return opt
    noise_here = not opt.pixel_noise
    if noise_here:
        # JPEG, 8-bit or scintillator-blurred frames: noise correlated over a
        # few px, which neighbour differences miss (then every marker looked
        # like clutter)
        opt = _noise_of(mid, opt)
    # the frames measured so far (page -> blobs), in the order they were read
    seen = {}
    if opt.response_lambda is None:
        lam = _response(scan, frames_idx, mid, opt, seen)
        opt = replace(opt, response_lambda=lam)
        if lam:
            # (the shadows were found in attenuation: measured again as the frames will be)
            seen = {}
            mid = linearised(mid, lam)
            if opt.max_attenuation is not None:
                # (the same pixels: the response is monotonic)
                opt = replace(opt, max_attenuation=linearised(opt.max_attenuation, lam))
            if noise_here:
                opt = _noise_of(mid, opt)
    if opt.shadow_px and not opt.size_scale:
        # the middle frame's shadows, and a quarter's either side of it while too few
        def shadows(q):
            k = frames_idx[q * len(frames_idx) // 4]
            if k not in seen:
                a = mid if q == 2 else linearised(scan.stack.read(k, check=False), opt.response_lambda)
                seen[k] = detect_frame(a, opt) if np.isfinite(a).all() else []
            return seen[k]
        blobs = shadows(2)
        for q in (1, 3):
            if len(blobs) >= MIN_SHADOWS or len(frames_idx) < 4:
                break
            blobs = blobs + shadows(q)
        sized = measured_size(blobs, opt)
        if sized.factor != opt.factor:
            sized = replace(sized, noise_reference=noise_small(small_frame(mid, sized)) * sized.factor)
        opt = sized
    return opt


def _noise_of(mid: np.ndarray, opt: DetectOptions) -> DetectOptions:
    """``opt`` with frame ``mid``'s pixel noise (over its pixels under
    ``opt.max_attenuation``), the noise's correlation factor and the
    neighbour-difference noise at ``opt.factor`` (attenuation units)."""
    return replace(opt, pixel_noise=noise_pixel(mid, limit=opt.max_attenuation), noise_kappa=noise_correlation(mid),
                   noise_rho=noise_autocorrelation(mid), noise_reference=noise_small(small_frame(mid, opt)) * opt.factor)


def _response(scan: Scan, frames_idx: list[int], mid: np.ndarray, opt: DetectOptions, seen: dict) -> float:
    """:func:`conecal.detect.gain.response_lambda` from the middle frame's
    shadows and, while fewer than twice the markers it needs stand alone,
    the quarter frames' and the eighth frames' (filling ``seen``: page ->
    blobs found in attenuation)."""
    order = [2 * len(frames_idx) // 4] + [q * len(frames_idx) // 8 for q in (2, 6, 1, 3, 5, 7)]
    results = []
    for n, i in enumerate(dict.fromkeys(order)):
        if sum(len(r) for r in results) >= 2 * MIN_ALONE or (n and len(frames_idx) < 4):
            break
        k = frames_idx[i]
        a = mid if n == 0 else scan.stack.read(k, check=False)
        if not np.isfinite(a).all():
            continue
        seen[k] = detect_frame(a, opt)
        results.append([b for b in with_background(a, seen[k], opt) if not b.flags or b.flags == ["clutter"]])
    return response_lambda(results)


def measure_frames(scan: Scan, opt: DetectOptions, frames_idx: list[int], *, workers: int = 2, lag: float = 0.0,
                   progress: Callable[[int, int], None] | None = None) -> tuple[DetectOptions, list[list]]:
    """The blobs of each frame in ``frames_idx`` (page numbers), before the
    scan-wide contrast filter and tracking; and the options used."""
    # The joint fits' matrices are small (tens of columns): BLAS's threads only
    # spin on them, and in two workers they fight for the cores (a helix frame
    # took 2.7 s with them, 1.3 s without; forked workers inherit the limit)
    with threadpool_limits(limits=1, user_api="blas"):
        return _measure_frames(scan, opt, frames_idx, workers, lag, progress)


def _measure_frames(scan, opt, frames_idx, workers, lag, progress):
    """:func:`measure_frames`' work, under its thread limit."""
    opt = scan_options(scan, opt)
    all_idx = [int(f) for f in scan.log.frame]
    order = np.argsort(np.asarray(scan.log.time, float), kind="stable")
    previous = {all_idx[order[i]]: all_idx[order[i - 1]] for i in range(1, len(order))}

    def one(k):
        a = scan.stack.read(k, check=False)
        if lag and k in previous:
            a = lag_corrected(a, scan.stack.read(previous[k], check=False), lag)
        a = linearised(a, opt.response_lambda or 0.0)
        try:
            return with_background(a, detect_frame(a, opt), opt)
        except NonFiniteFrame:
            scan.stack.check_finite(k, a)  # raises InputError naming the pixel
            raise

    results = []
    if workers > 1 and "fork" in mp.get_all_start_methods():
        # Processes, not threads: the per-marker work is many small numpy calls
        # that hold the GIL. Forked workers inherit the open scan.
        global _WORKER, _ABORT
        _WORKER = one
        kernels.warm_up()
        ctx = mp.get_context("fork")
        # On any exception (an error in a frame, Ctrl-C, SIGTERM) the queued
        # frames are cancelled or skipped and the workers end after the frame
        # in hand; they are never killed. (multiprocessing.Pool hung twice
        # under the fuzz test: terminate() killed a worker holding the result
        # queue's lock, and a worker that died mid-frame left imap waiting for
        # ever; the executor reports a dead worker instead.)
        from concurrent.futures import ProcessPoolExecutor
        from concurrent.futures.process import BrokenProcessPool

        _ABORT = ctx.Event()
        ex = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_init)
        try:
            chunk = max(1, min(16, len(frames_idx) // (4 * workers)))
            for n, res in enumerate(ex.map(_run_worker, frames_idx, chunksize=chunk), 1):
                results.append(res)
                if progress:
                    progress(n, len(frames_idx))
        except BrokenProcessPool:
            _ABORT.set()
            from ..errors import FitError
            raise FitError("a detect worker process died (killed, or out of memory); no output was written. "
                           "Run with --workers 1 to see where") from None
        except BaseException:
            _ABORT.set()
            raise
        finally:
            ex.shutdown(wait=True, cancel_futures=True)
            _WORKER = _ABORT = None
    else:
        for n, k in enumerate(frames_idx, 1):
            results.append(one(k))
            if progress:
                progress(n, len(frames_idx))
    return opt, results


def scan_filter(results: list[list], opt: DetectOptions, spread: float = 1.0) -> tuple[list[list], float]:
    """Every frame's blobs without the ones no marker makes, and the scan's
    reference contrast (attenuation per px of chord). Ghosts (detector lag)
    and faint blobs are sphere-shaped but far weaker than the markers: below
    ``opt.min_relative_contrast`` of the scan's median unflagged contrast, or
    of the frame's own when that is lower (:func:`_frame_contrast`). A speck
    or an edge's corner measured as a 3 px "sphere" among 10 px ones: under
    half the frame's sphere radius times ``spread`` (the declared diameters'
    smallest over largest)."""
    mus = np.array([b.mu_px for res in results for b in res if not b.flags])
    if mus.size == 0:
        mus = np.array([b.mu_px for res in results for b in res])
    ref = float(np.median(mus)) if mus.size else 0.0
    R = _nominal_radius(opt)
    floors = [opt.min_relative_contrast * min(ref, _frame_contrast(res, ref, R)) for res in results]
    results = [[b for b in res if b.mu_px >= f] for res, f in zip(results, floors)]
    floors = [0.5 * spread * (_frame_radius(res) or R) for res in results]
    return [[b for b in res if b.radius >= f] for res, f in zip(results, floors)], ref


# a blob measured this surely (σ over radius) with a declared sphere's size is a
# sphere's shadow to a frame whose spheres are all flagged (a real spine over a
# box phantom: spheres 0.013-0.027, blots 0.08-0.17)
_SURE = 0.05


def _nominal_radius(opt: DetectOptions) -> float:
    """The largest declared sphere's shadow radius (px, at the measured
    scale), else the middle of the searched range's."""
    if opt.shadow_px:
        return float(max(opt.shadow_px)) / 2
    return float(np.sqrt(opt.diameter_px[0] * opt.diameter_px[1])) / 2


def _frame_contrast(res: list, ref: float, R: float = 0.0) -> float:
    """The frame's own marker contrast (median attenuation per px of chord
    of its unflagged blobs, when 3 or more; else of its blobs of a declared
    sphere's size, 0.8-1.25 ``R`` px, measured to ``_SURE`` of their radius,
    when 3 or more): a display image windowed per frame (a spine over the
    phantom) holds every sphere at a third of the scan's contrast, and the
    scan's reference removed them all; a ghost is faint beside its own
    frame's markers. ``ref`` when the frame has fewer. (With a spine over
    every sphere, whether three stood unflagged changed with a 1 % change of
    the measured size, and with it 9 of 16 markers.)"""
    own = [b.mu_px for b in res if not b.flags]
    if len(own) < 3:
        own = [b.mu_px for b in res if 0.8 * R <= b.radius <= 1.25 * R and b.sigma <= _SURE * b.radius]
    return float(np.median(own)) if len(own) >= 3 else ref


def _frame_radius(res: list) -> float:
    """The median radius (px) of the frame's unflagged blobs, when 3 or more,
    else of all its blobs, when 3 or more (a spine over every sphere); else 0
    (then the declared size stands: a lone blot of 4 px in a frame of the
    spine alone was kept as a marker)."""
    own = [b.radius for b in res if not b.flags]
    own = own if len(own) >= 3 else [b.radius for b in res]
    return float(np.median(own)) if len(own) >= 3 else 0.0


def assemble(scan: Scan, opt: DetectOptions, frames_idx: list[int], results: list[list]) -> dict:
    """The markers document from every frame's blobs: scan-wide contrast
    filter, identities across frames, frames in log order."""
    # (the declared sizes at the measured scale, and a second size class measured)
    results, ref = scan_filter(results, opt, min(opt.shadow_px) / max(opt.shadow_px) if opt.shadow_px else 1.0)
    results, gain = with_gain_sigma(results, opt)
    robot = scan.config.motion in ("robot", "free")
    # A robot re-places the holder with mm-level jumps between frames, and free
    # poses are unrelated, so image tracks are not identities there: fit-pose
    # assigns phantom ids instead.
    ids, spans = track(results, predictor=kinematic_predictor(scan),
                       kinematic_first=scan.config.motion == "linear")
    frames = []
    rows, cols = scan.stack.shape
    for k, res, fid in zip(frames_idx, results, ids):
        # float(): Python's correctly rounded round(), the same for a part read back from JSON
        markers = [{"id": None if robot else int(i), "x": round(float(b.x), 6), "y": round(float(b.y), 6),
                    "sigma": round(float(b.sigma), 6), "radius": round(float(b.radius), 4),
                    "contrast": round(float(b.peak), 5), "flags": sorted(b.flags)}
                   for b, i in sorted(zip(res, fid), key=lambda t: (t[1], t[0].x))]
        seen = set(fid)
        pos = len(frames)
        missing = [] if robot else sorted(i for i, (a, z) in spans.items() if a < pos < z and i not in seen)
        frames.append({"frame": k, "markers": markers, "missing": missing})
    return {"format": MARKERS_FORMAT, "software": f"conecal {__version__}",
            "centre": "attenuation centroid of the sphere shadow (predict with conecal.geometry.shadow_centroid); "
                      "with options.response_lambda > 0, of (1 - exp(-lambda a)) / lambda, the response that "
                      "makes the image's shadows add (a log display stored as transmission)",
            "units": {"x": "px (column)", "y": "px (row)", "sigma": "px, 1 sigma", "radius": "px",
                      "contrast": "attenuation above background"},
            "detector": {"shape": [rows, cols]},
            "options": {"diameter_px": list(opt.diameter_px), "threshold": opt.threshold, "blur_px": opt.blur_px,
                        "pixel_noise": round(opt.pixel_noise, 8), "noise_kappa": round(opt.noise_kappa, 4),
                        "noise_reference": round(opt.noise_reference, 8),
                        "max_anisotropy": opt.max_anisotropy, "min_relative_contrast": opt.min_relative_contrast,
                        "size_scale": round(opt.size_scale, 4), "response_lambda": opt.response_lambda or 0.0,
                        # (the noise's autocorrelation that scales each centre's sigma with its
                        # estimator's weights: with it a sigma can be recomputed from this file)
                        "noise_autocorrelation": [[round(v, 4) for v in row] for row in opt.noise_rho]},
            "reference_mu_px": round(ref, 6), "contrast_gain": gain.document(),
            "identities": "phantom ids are assigned by fit-pose" if robot else "tracked across frames",
            "n_ids": 0 if robot else len(spans), "frames": frames}
