"""detect on an independent helix phantom (issue 32's crowded-scene target).

Frames from ``benchmarks/helix_indep.py``, written by a helper session that
never saw conecal's code: 50 steel spheres (0.9 and 1.2 mm) on a helix
inside a plastic tube, random robot poses (every 4th frame looking along
the helix axis, where turns pile up), Poisson noise, scintillator blur
before or after the noise, shadows 9-14 px. Truth: each sphere's own
attenuation centroid, its overlap and the gap to its nearest neighbour.

Each frame is measured with the nominal shadow size exact and off by -25 %
and +25 % (``diameter_px`` = nominal range x 0.9 / 1.1, then scaled; the
declared spheres' shadows at the nominal magnification scaled alike), after
detect's measurement of the size on each seed's middle frame (unless
``--typed-size``), the pixel noise and its correlation measured on the frame
as detect does per scan. Each seed's frames are then one scan: the scan-wide contrast and size
floors of ``conecal detect`` (``pipeline.scan_filter``) are applied, unless
``--frame-only``. Printed per size: spheres measured out of those in the field, by
class (separate: gap >= 0.5 diameter; near: touching to 0.5 d; overlapping),
RMS error, pull std per flag class, false detections, time per frame.

    python benchmarks/bench_helix.py [--seeds 0 1] [--frames 24]
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from conecal.detect import DetectOptions, detect_frame  # noqa: E402
from conecal.detect.noise import noise_autocorrelation, noise_correlation, noise_pixel  # noqa: E402
from conecal.detect.pipeline import scan_filter  # noqa: E402
from conecal.detect.size import measured_size  # noqa: E402
from conecal.stats import mad_sigma  # noqa: E402

HERE = Path(__file__).parent


def _generator():
    spec = importlib.util.spec_from_file_location("helix_indep", HERE / "helix_indep.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def cls(t):
    g = t.get("min_gap_diam", np.inf)
    return "overlapping" if g < 0 else ("near" if g < 0.5 else "separate")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="*", default=[0, 1])
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--scales", type=float, nargs="*", default=[1.0, 0.75, 1.25])
    ap.add_argument("--no-holder", action="store_true", help="without the plastic tube (overlaps alone)")
    ap.add_argument("--typed-size", action="store_true",
                    help="look for the typed (scaled) size, without detect's measurement of it on the middle frame")
    ap.add_argument("--frame-only", action="store_true",
                    help="score each frame's blobs before the scan-wide contrast and size floors")
    a = ap.parse_args()
    gen = _generator()
    if a.no_holder:
        gen.MU_PLASTIC = 0.0
    data = [gen.make_frames(s, a.frames) for s in a.seeds]
    r_all = [t["r_px"] for _, truth in data for fr in truth for t in fr]
    nominal = (2 * min(r_all), 2 * max(r_all))
    print(f"shadow diameters {nominal[0]:.1f}-{nominal[1]:.1f} px; seeds {a.seeds}, {a.frames} frames each\n")
    print("| nominal size | class | in field | measured | RMS px | false | s/frame |")
    print("|---|---|---|---|---|---|---|")
    for scale in a.scales:
        acc = {c: [0, []] for c in ("separate", "near", "overlapping")}
        pulls: dict[str, list] = {}
        false, t_tot, n_fr = 0, 0.0, 0
        scales_seen = []
        for frames, truth in data:
            found = []
            # the typed size: the declared spheres' shadows at the nominal magnification, scaled
            # (and, as detect takes it from phantom.csv, the helix's extent over
            # the source distance the typed size implies)
            typed = DetectOptions(diameter_px=(nominal[0] * 0.9 * scale, nominal[1] * 1.1 * scale),
                                  shadow_px=tuple(d * gen.SDD / gen.SOD / gen.PITCH * scale
                                                  for d in (gen.D_SMALL, gen.D_LARGE)),
                                  depth_extent=(np.hypot(gen.HELIX_RADIUS, gen.HELIX_LENGTH / 2) + gen.D_LARGE / 2)
                                  * scale / gen.SOD)
            if not a.typed_size:
                # as `conecal detect` does once per scan (pipeline.scan_options): the
                # middle frame's shadows measured at the typed size
                mid = np.ascontiguousarray(frames[len(frames) // 2], np.float32)
                typed = measured_size(detect_frame(mid, replace(typed, pixel_noise=noise_pixel(mid),
                                                                noise_kappa=noise_correlation(mid),
                                                                noise_rho=noise_autocorrelation(mid))), typed)
                scales_seen.append(typed.size_scale)
            for img in frames:
                # the generator alternates the blur before and after the noise: a
                # real scan keeps one, so the noise is measured per frame here
                opt = replace(typed, pixel_noise=noise_pixel(img), noise_kappa=noise_correlation(img),
                              noise_rho=noise_autocorrelation(img))
                t0 = time.perf_counter()
                found.append(detect_frame(np.ascontiguousarray(img, np.float32), opt))
                t_tot += time.perf_counter() - t0
                n_fr += 1
            if not a.frame_only:
                # each seed's frames are one scan: its contrast and size floors, as `conecal detect` applies them
                found = scan_filter(found, opt, gen.D_SMALL / gen.D_LARGE)[0]
            for blobs, tr in zip(found, truth):
                used = set()
                for t in tr:
                    c = cls(t)
                    acc[c][0] += 1
                    if not blobs:
                        continue
                    d = [np.hypot(b.x - t["x"], b.y - t["y"]) for b in blobs]
                    i = int(np.argmin(d))
                    if d[i] < 0.5 * t["r_px"] and i not in used:
                        used.add(i)
                        b = blobs[i]
                        acc[c][1].append((b.x - t["x"], b.y - t["y"]))
                        pulls.setdefault(",".join(sorted(b.flags)) or "unflagged", []).extend(
                            [(b.x - t["x"]) / b.sigma, (b.y - t["y"]) / b.sigma])
                false += len(blobs) - len(used)
        for c, (n, errs) in acc.items():
            e = np.array(errs) if errs else np.zeros((0, 2))
            rms = np.sqrt(np.mean(e**2)) if len(e) else float("nan")
            print(f"| {scale:.2f} | {c} | {n} | {len(e)} ({100 * len(e) / max(n, 1):.1f} %) | {rms:.3f} | "
                  f"{false if c == 'separate' else ''} | {t_tot / n_fr:.2f} |", flush=True)
        if scales_seen:
            print("measured / typed size per seed: " + " ".join(f"{v:.3f}" for v in scales_seen))
        tot_n = sum(v[0] for v in acc.values())
        tot_m = sum(len(v[1]) for v in acc.values())
        print(f"| {scale:.2f} | all | {tot_n} | {tot_m} ({100 * tot_m / tot_n:.1f} %) | | {false} | |")
        # std, then the robust std (normal σ from the MAD) and how many |pull| > 5 (a
        # centre off by more than its sigma can say: a wrong "ok")
        print("pull std / robust / >5 per flag class: " + ", ".join(
            f"{k} {np.std(v):.2f} / {mad_sigma(v):.2f} / "
            f"{int(np.sum(np.abs(v) > 5))} (n={len(v) // 2})" for k, v in sorted(pulls.items())), flush=True)


if __name__ == "__main__":
    main()
