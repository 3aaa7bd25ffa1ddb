"""Image-level effects for the "diagnose" benchmark: rotation-stage marker
scans whose marker GEOMETRY is clean and whose effect lives in the
projections only.

Built on ``formvariants.py`` (same folder; loaded with importlib as the
benchmarks do) and written against /work/shared/SCAN_FORMAT.md only.  Usage::

    from formvariants_image import CASES, make_case
    label = make_case("lag_far", seed=3, out=pathlib.Path("/tmp/x"))

``make_case`` writes the same files as ``formvariants.make_case`` for the
case "clean" of the same seed (``scan/{scan.yaml,log.csv,projections.tif}``,
``geometry.json``, ``markers.json`` with the TRUE shadow centres + N(0, 0.02
px) noise, exactly formvariants' clean draws), then replaces the projections
by its own images and writes ``effect.json``; it returns the label
``{"family", "variable", "nameable", "ambiguous_with"}``.

Image chain (every case): attenuation line integrals p = MU * chord (exact
chords from ``formvariants.render``), intensity I = I0 exp(-p) with I0 =
20000 counts, the effect in its physical domain, quantum noise as a Gaussian
of variance I (one noise field per frame, the same draws in every case of a
seed), and stored values round(1000 * -ln(I / I0)) clipped to 0..65535 as
uint16 (``values: attenuation``, scale 1000 per unit of -ln(I/I0), stated
in effect.json).  Negative attenuations (noise in the flat background,
scatter) are clipped to 0 by the uint16 store.

Cases (``CASES``; name -> (builder, one-line form, label)):
  image_clean          no effect.
  lag_far              detector lag: I_rec[i] = (1-a) I[i] + a sum_j w_j I[i-j],
                       j = 1..3, w_j ~ exp(-j/tau), on the noisy intensities.
  disc_focal_spot      uniform disc focal spot of radius r_spot: each sphere's
                       shadow blurred (in intensity) by a disc of radius
                       r_spot (M_s - 1) / pitch px, M_s its own magnification.
  scatter_field        I_rec = I + s I0 g(c, r), g an off-centre Gaussian bump.
  beam_hardening_poly  p' = p - c p^2 before the exponential.
  jpeg8                the clean scan exported as 8 bit (per-frame window over
                       the 1..99 percentiles) and JPEG-75 compressed.

Random streams: children 0-2 of ``SeedSequence(seed)`` are the ones
formvariants uses (geometry/phantom, marker noise, effect); child 3 draws the
image noise (the same fields in every case of a seed); spawn key
(4, crc32(case name)) draws each case's effect parameters.

Deviations / limits (also in each effect.json):
- lag_far: at the 4 deg step a sphere's shadow moves at most ~0.3 of its
  diameter per frame (outer spheres, ~8.5 mm from the axis: ~15 px against a
  ~50 px shadow), NOT more than one diameter; the lag ghosts j = 1..3 reach
  ~0.3, 0.6, 0.9 diameters, so they overlap the shadow (a trailing smear).
  effect.json["params"]["motion"] has the numbers per seed.
- jpeg8: SCAN_FORMAT.md cannot declare an 8-bit / windowed / unknown transfer
  (values: attenuation | transmission | raw); the pages are uint8 and
  scan.yaml keeps ``values: attenuation`` as the closest.
- disc_focal_spot: the per-sphere layer product is exact only where blurred
  shadows do not overlap.
"""
from __future__ import annotations

import importlib.util
import json
import os
import pathlib
import time
import zlib

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent


def _load_formvariants():
    spec = importlib.util.spec_from_file_location("formvariants", HERE / "formvariants.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


fv = _load_formvariants()

I0 = 20000.0          # counts in the open beam
SCALE = 1000.0        # stored value = SCALE * -ln(I / I0)
N_PRE = 3             # lag: frames before frame 0 that can leak in


# ---------------------------------------------------------------- helpers
def _streams(seed, name):
    """Image noise: child 3 of SeedSequence(seed) (children 0-2 are
    formvariants'); effect parameters: child (4, crc32(name)), one stream
    per case."""
    ss = np.random.SeedSequence(seed).spawn(4)
    eff = np.random.SeedSequence(seed, spawn_key=(4, zlib.crc32(name.encode())))
    return np.random.default_rng(ss[3]), np.random.default_rng(eff)


def _noise_fields(rng_noise, n):
    """n standard-normal fields (ROWS, COLS), float32, drawn in frame order."""
    return [rng_noise.standard_normal((fv.ROWS, fv.COLS), dtype=np.float32) for _ in range(n)]


def _noisy(I, n):
    """Quantum noise: Gaussian with variance I (counts)."""
    return np.clip(I + np.sqrt(np.clip(I, 0, None)) * n, 1.0, None)


def _store(I):
    # float32 -ln(I/I0): the contract's ``values: attenuation`` has no scale
    # key, so an integer store with a factor would be read as attenuation x1000
    return (-np.log(I / I0)).astype(np.float32)


def _magnification(S, p, g):
    n = np.cross(g["u"], g["v"])
    X = fv._intersect(S, p, g["origin"], n)
    return np.linalg.norm(X - S) / np.linalg.norm(p - S)


def _sim(seed):
    g, P, S, uv, meas, label, params, k, t, th = fv.simulate("clean", seed)
    return dict(g=g, P=P, S=S, uv=uv, k=k, t=t, th=th)


def _attenuation(sim, i):
    """Noise-free line integral p = MU * chord (float64, full frame)."""
    return fv.MU * fv.render(sim["S"][i], sim["P"][i], sim["g"])


def _disc_kernel(radius_px, sub=9):
    """Uniform disc of the given radius (px), pixel-area weighted, sum 1."""
    h = int(np.ceil(radius_px)) + 1
    off = (np.arange(sub) + 0.5) / sub - 0.5
    x = (np.arange(-h, h + 1)[:, None] + off[None]).ravel()
    X, Y = np.meshgrid(x, x)
    inside = (X * X + Y * Y <= radius_px * radius_px).astype(float)
    K = inside.reshape(2 * h + 1, sub, 2 * h + 1, sub).mean(axis=(1, 3))
    return K / K.sum()


# ---------------------------------------------------------------- cases
# Each builder gets (sim, rng_eff, noise(list of F + N_PRE fields)) and returns
# (stack of stored frames (F, ROWS, COLS) uint16 or uint8, params dict).
def build_image_clean(sim, rng, noise):
    F = fv.N_FRAMES
    out = np.empty((F, fv.ROWS, fv.COLS), np.float32)
    for i in range(F):
        out[i] = _store(_noisy(I0 * np.exp(-_attenuation(sim, i)), noise[i]))
    return out, {}


def lag_motion(sim):
    """Shadow motion between consecutive frames vs the shadow diameter."""
    uv, P, S, g = sim["uv"], sim["P"], sim["S"], sim["g"]
    step = np.linalg.norm(np.diff(uv, axis=0), axis=2)              # (F-1, N) px
    M = np.array([[_magnification(S[i], P[i, j], g) for j in range(P.shape[1])]
                  for i in range(P.shape[0])])
    diam = fv.DIAMETER * M / fv.PITCH                                # px
    ratio = step / diam[1:]
    radius = np.hypot(sim["g"]["phantom"][:, 0], sim["g"]["phantom"][:, 2])
    outer = int(np.argmax(radius))
    return dict(
        step_deg=float(fv.STEP_DEG),
        sphere_radius_from_axis_mm=radius.round(3).tolist(),
        max_step_px_per_sphere=step.max(0).round(2).tolist(),
        shadow_diameter_px_per_sphere=diam.mean(0).round(2).tolist(),
        max_step_in_diameters_per_sphere=ratio.max(0).round(3).tolist(),
        outer_sphere=outer,
        outer_max_step_in_diameters=float(ratio[:, outer].max().round(3)),
        moves_more_than_one_diameter=bool(ratio[:, outer].max() > 1.0),
        lag_reach_in_diameters_j1_j3=[float((j * ratio[:, outer].max()).round(3))
                                      for j in (1, 2, 3)])


def build_lag_far(sim, rng, noise):
    a = rng.uniform(0.03, 0.08)
    tau = rng.uniform(1.0, 2.0)
    j = np.arange(1, N_PRE + 1)
    w = np.exp(-j / tau)
    w /= w.sum()
    F = fv.N_FRAMES
    # noisy intensities of frames 0..F-1; the stage was already turning at the
    # same speed before the scan, so frame -j is at angle -4j deg = frame F-j
    # (same noise-free image, its own noise draw).
    clean = [I0 * np.exp(-_attenuation(sim, i)) for i in range(F)]
    Iz = [_noisy(clean[i], noise[i]) for i in range(F)]
    pre = {-jj: _noisy(clean[F - jj], noise[F + jj - 1]) for jj in j}

    def frame(i):
        return Iz[i] if i >= 0 else pre[i]

    out = np.empty((F, fv.ROWS, fv.COLS), np.float32)
    for i in range(F):
        rec = (1 - a) * Iz[i]
        for jj, ww in zip(j, w):
            rec = rec + a * ww * frame(i - jj)
        out[i] = _store(rec)
    params = dict(a=a, tau_frames=tau, weights_j1_j3=w.tolist(),
                  domain="noisy intensity (counts), before the log",
                  before_frame_0="stage already turning: frame -j = frame F-j with fresh noise",
                  motion=lag_motion(sim))
    return out, params


def _blurred_transmission(sim, i, r_spot):
    """Transmission of frame i seen from a uniform disc focal spot of radius
    r_spot (mm).  A source point displaced by d in the spot plane moves the
    shadow of an object point at magnification M by d (M - 1) on the
    detector, so each sphere's shadow is blurred by a disc of radius
    r_spot (M_s - 1) / pitch px, M_s = |S->detector| / |S->sphere| along the
    ray through the sphere centre.  The blur acts on intensity: the
    absorbed fraction 1 - T_s of each sphere is convolved with its own disc
    and the layers multiply, T = prod_s (1 - K_s * (1 - T_s)) (exact where
    the blurred shadows do not overlap)."""
    from scipy.signal import fftconvolve
    S, Pf, g = sim["S"][i], sim["P"][i], sim["g"]
    T = np.ones((fv.ROWS, fv.COLS))
    radii = []
    for j in range(Pf.shape[0]):
        chord = fv.render(S, Pf[j:j + 1], g)
        rows = np.nonzero(chord.any(axis=1))[0]
        cols = np.nonzero(chord.any(axis=0))[0]
        if rows.size == 0:
            continue
        rpx = r_spot * (_magnification(S, Pf[j], g) - 1.0) / fv.PITCH
        radii.append(rpx)
        K = _disc_kernel(rpx)
        h = K.shape[0] // 2
        r0, r1 = max(0, rows[0] - h), min(fv.ROWS, rows[-1] + h + 1)
        c0, c1 = max(0, cols[0] - h), min(fv.COLS, cols[-1] + h + 1)
        absorbed = 1.0 - np.exp(-fv.MU * chord[r0:r1, c0:c1])
        b = np.clip(fftconvolve(absorbed, K, mode="same"), 0.0, 1.0)
        T[r0:r1, c0:c1] *= 1.0 - b
    return T, radii


def build_disc_focal_spot(sim, rng, noise):
    r_spot = rng.uniform(0.1, 0.3)
    F = fv.N_FRAMES
    out = np.empty((F, fv.ROWS, fv.COLS), np.float32)
    radii = []
    for i in range(F):
        T, rad = _blurred_transmission(sim, i, r_spot)
        radii += rad
        out[i] = _store(_noisy(I0 * T, noise[i]))
    # frames whose blurred shadows touch (there the layer product is approximate)
    uv = sim["uv"]
    reach = (fv.DIAMETER * fv.SDD / fv.SOD / fv.PITCH) * 1.1 + 2 * max(radii)
    d = np.linalg.norm(uv[:, :, None] - uv[:, None, :], axis=-1)
    iu = np.triu_indices(uv.shape[1], 1)
    touching = int(np.sum((d[:, iu[0], iu[1]] < reach).any(axis=1)))
    M0 = fv.SDD / fv.SOD
    return out, dict(
        r_spot_mm=r_spot, spot="uniform disc, in the source plane",
        blur_radius_px_min_max=[min(radii), max(radii)],
        blur_radius_px_at_phantom_centre=r_spot * (M0 - 1) / fv.PITCH,
        form_of_radius="r_spot (M_s - 1) / pitch, M_s each sphere's own magnification per frame",
        domain="noise-free intensity (absorbed fraction per sphere, convolved), then noise",
        frames_where_blurred_shadows_may_overlap=touching,
        overlap_note="where two blurred shadows overlap the product of separately blurred "
                     "layers is an approximation (it drops the covariance of the two absorbed "
                     "fractions within one kernel)")


def build_scatter_field(sim, rng, noise):
    s = rng.uniform(0.02, 0.06)
    fwhm = rng.uniform(0.28, 0.38) * fv.COLS
    sig = fwhm / (2 * np.sqrt(2 * np.log(2)))
    off = rng.uniform(60.0, 140.0)
    phi = rng.uniform(0, 2 * np.pi)
    cc = np.array([(fv.COLS - 1) / 2, (fv.ROWS - 1) / 2]) + off * np.array([np.cos(phi), np.sin(phi)])
    C, R = np.meshgrid(np.arange(fv.COLS), np.arange(fv.ROWS))
    gfield = np.exp(-((C - cc[0]) ** 2 + (R - cc[1]) ** 2) / (2 * sig * sig))
    F = fv.N_FRAMES
    out = np.empty((F, fv.ROWS, fv.COLS), np.float32)
    for i in range(F):
        I = I0 * np.exp(-_attenuation(sim, i)) + s * I0 * gfield
        out[i] = _store(_noisy(I, noise[i]))
    return out, dict(
        s=s, g="exp(-|x - centre|^2 / (2 sigma^2)), peak 1", centre_px=cc.tolist(),
        sigma_px=sig, fwhm_px=fwhm,
        domain="added to the noise-free intensity; noise of variance I + s I0 g",
        background_min_attenuation_before_clip=-SCALE * np.log1p(s),
        note="the open background gets -ln(1 + s g) < 0, clipped to 0 by the uint16 store; "
             "the field survives inside the shadows")


def build_beam_hardening_poly(sim, rng, noise):
    f = rng.uniform(0.03, 0.10)
    F = fv.N_FRAMES
    p = np.empty((F, fv.ROWS, fv.COLS), np.float32)
    for i in range(F):
        p[i] = _attenuation(sim, i)
    pmax = float(p.max())
    c = f / pmax
    out = np.empty((F, fv.ROWS, fv.COLS), np.float32)
    for i in range(F):
        pi = p[i].astype(np.float64)
        out[i] = _store(_noisy(I0 * np.exp(-(pi - c * pi * pi)), noise[i]))
    return out, dict(
        c=c, loss_at_deepest_chord=f, loss_at_one_sphere_centre=c * fv.MU * fv.DIAMETER, deepest_p=pmax, deepest_chord_mm=pmax / fv.MU,
        form="p' = p - c p^2 (p = mu * chord), I = I0 exp(-p'), then noise",
        monotonic_up_to_p=1 / (2 * c))


def build_jpeg8(sim, rng, noise):
    import cv2
    clean, _ = build_image_clean(sim, rng, noise)
    F = fv.N_FRAMES
    out = np.empty((F, fv.ROWS, fv.COLS), np.uint8)
    windows = []
    for i in range(F):
        v = clean[i].astype(np.float64)
        lo, hi = np.percentile(v, [1.0, 99.0])
        if hi <= lo:
            hi = lo + 1.0
        q = np.clip(np.rint((v - lo) / (hi - lo) * 255.0), 0, 255).astype(np.uint8)
        ok, buf = cv2.imencode(".jpg", q, [int(cv2.IMWRITE_JPEG_QUALITY), 75])
        if not ok:
            raise RuntimeError("cv2.imencode failed")
        dec = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
        out[i] = dec
        windows.append([float(lo), float(hi)])
    return out, dict(
        window="per frame: the stored clean value v (1000 * -ln I/I0) mapped linearly, "
               "255 (v - lo) / (hi - lo), lo/hi its 1st/99th percentile, rounded, clipped 0..255",
        windows_lo_hi_per_frame=windows, jpeg_quality=75, codec="cv2.imencode .jpg, 8-bit grey",
        stored="uint8 TIFF pages; scan.yaml keeps values: attenuation",
        format_note="SCAN_FORMAT.md has no way to declare an 8-bit / windowed / unknown "
                    "transfer (values: attenuation | transmission | raw); 'attenuation' is the "
                    "closest (the values increase with -ln I/I0, up to an unknown per-frame "
                    "affine map, clipping and JPEG loss)")


def _label(family, variable, nameable=True, ambiguous_with=()):
    return dict(family=family, variable=variable, nameable=nameable,
                ambiguous_with=list(ambiguous_with))


# name -> (builder, one-line form, label)
CASES = {
    "image_clean": (build_image_clean, "no effect; Gaussian quantum noise of variance I",
                    _label("none", "none")),
    "lag_far": (build_lag_far, "I_rec[i] = (1-a)I[i] + a*sum_{j=1..3} w_j I[i-j], "
                "w_j ~ exp(-j/tau), a 3-8 %, tau 1-2 frames",
                _label("detector_lag", "frame")),
    "disc_focal_spot": (build_disc_focal_spot, "uniform disc focal spot r_spot 0.1-0.3 mm: each "
                        "shadow blurred in intensity by a disc of radius r_spot (M_s - 1)/pitch px",
                        _label("blur", "image")),
    "scatter_field": (build_scatter_field, "I_rec = I + s I0 g(c, r), g an off-centre Gaussian "
                      "bump (FWHM ~ 1/3 detector, peak 1), s 2-6 %",
                      _label("scatter", "image")),
    "beam_hardening_poly": (build_beam_hardening_poly, "p' = p - c p^2 before I = I0 exp(-p'), "
                            "c so the deepest chord loses 3-10 %",
                            _label("beam_hardening", "image")),
    "jpeg8": (build_jpeg8, "the clean scan windowed to 8 bit over the 1..99 percentile per "
              "frame and JPEG-75 compressed (no image effect to claim)",
              _label("none", "none")),
}


# ---------------------------------------------------------------- writing
def _write_json(path, obj):
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, sort_keys=True, indent=1))
    os.replace(tmp, path)


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating,)):
        return float(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.bool_,)):
        return bool(x)
    return x


def make_case(name: str, seed: int, out: pathlib.Path, images: bool = True) -> dict:
    import tifffile
    if name not in CASES:
        raise KeyError(f"unknown case {name!r}; known: {sorted(CASES)}")
    out = pathlib.Path(out)
    # scan.yaml, log.csv, geometry.json, markers.json exactly as formvariants'
    # clean case (its projections are replaced below)
    fv.make_case("clean", seed, out, images=False)
    sim = _sim(seed)
    rng_noise, rng_eff = _streams(seed, name)
    builder, form, label = CASES[name]
    stack, params = None, {}
    if images:
        noise = _noise_fields(rng_noise, fv.N_FRAMES + N_PRE)
        stack, params = builder(sim, rng_eff, noise)
    else:   # formvariants' flat pages stay: no image, so no effect is in it
        params = {"note": "images=False: flat pages, the effect is NOT present"}
    if stack is not None:
        tif = out / "scan" / "projections.tif"
        tmp = tif.with_name("projections.tmp.tif")
        with tifffile.TiffWriter(tmp) as tw:
            for page in stack:
                tw.write(page, contiguous=True)
        os.replace(tmp, tif)
    _write_json(out / "effect.json", _jsonable({
        "case": name, "seed": int(seed), "label": label, "form": form,
        "params": params,
        "image_chain": {"I0_counts": I0, "mu_per_mm": fv.MU,
                        "noise": "Gaussian, variance I (counts), per frame",
                        "stored": "uint16 round(1000 * -ln(I/I0)), clipped to 0..65535",
                        "values_scale_per_unit_neg_ln": SCALE},
        "geometry_source": "formvariants.simulate('clean', seed)",
        "phantom_mm": sim["g"]["phantom"],
        "true_source_per_frame": sim["S"]}))
    return dict(label)


if __name__ == "__main__":   # self-check: every case, seed 0, vs image_clean
    import sys

    import tifffile
    import yaml
    root = pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else "/tmp/fvi_check")
    seed = int(sys.argv[2]) if len(sys.argv) > 2 else 0
    fv.make_case("clean", seed, root / "_fv_clean", images=False)
    ref_markers = json.loads((root / "_fv_clean" / "markers.json").read_text())
    stacks, secs, labels = {}, {}, {}
    for nm in CASES:
        t0 = time.perf_counter()
        labels[nm] = make_case(nm, seed, root / nm)
        secs[nm] = time.perf_counter() - t0
        d = root / nm
        desc = yaml.safe_load((d / "scan" / "scan.yaml").read_text())
        assert desc["values"] == "attenuation", desc["values"]
        assert json.loads((d / "markers.json").read_text()) == ref_markers, nm
        stk = tifffile.imread(d / "scan" / "projections.tif")
        assert stk.shape == (fv.N_FRAMES, fv.ROWS, fv.COLS), stk.shape
        stacks[nm] = stk
    ref = stacks["image_clean"].astype(np.float64)
    shadow = ref > 100            # inside the sphere shadows (p > 0.1)
    for nm in CASES:
        stk = stacks[nm].astype(np.float64)
        note = ""
        if nm == "jpeg8":        # back through the stored windows
            w = np.array(json.loads((root / nm / "effect.json").read_text())
                         ["params"]["windows_lo_hi_per_frame"])
            stk = w[:, 0, None, None] + stk * ((w[:, 1] - w[:, 0]) / 255.0)[:, None, None]
            note = "  (uint8 mapped back through its windows)"
        diff = np.abs(stk - ref)
        print(f"{nm:20s} {str(stacks[nm].dtype):6s} {secs[nm]:5.1f} s  "
              f"max|d|={diff.max():7.1f}  mean|d| in shadows={diff[shadow].mean():6.2f}  "
              f"outside={diff[~shadow].mean():5.2f}  (units 1e-3 of -ln I/I0)  "
              f"label={labels[nm]}{note}")
