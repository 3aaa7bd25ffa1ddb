"""rp-grid's table kernel: the row-ordered Joseph Radon transform against
the line-by-line walk it replaced, side by side in one run.

Both give the same sums (printed: the largest difference); the tables of
a 360-view scan are most of rp-grid's time. One view of 256x256 at 360
angles over [0, pi) and 363 offsets, like rp-grid's tables.

    python benchmarks/bench_radon.py            # ~10 s on 2 cores
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from numba import njit, prange

from conecal.consistency import kernels


@njit(cache=True)
def _line_walk(img, s, a_major, a_minor, p_major, p_minor, ref_major, ref_minor):
    n_major, n_minor = img.shape
    m_at0 = (s + ref_major * p_major * a_major) / (a_minor * p_minor) + ref_minor
    dm = -p_major * a_major / (a_minor * p_minor)
    lo, hi = 0, n_major - 1
    if dm > 1e-12:
        lo = max(lo, int(np.ceil((0.0 - m_at0) / dm)))
        hi = min(hi, int(np.floor((n_minor - 1 - m_at0) / dm)))
    elif dm < -1e-12:
        lo = max(lo, int(np.ceil((n_minor - 1 - m_at0) / dm)))
        hi = min(hi, int(np.floor((0.0 - m_at0) / dm)))
    elif m_at0 < 0 or m_at0 > n_minor - 1:
        return 0.0
    acc = 0.0
    for j in range(lo, hi + 1):
        m = m_at0 + dm * j
        i = min(int(m), n_minor - 2)
        f = m - i
        acc += img[j, i] * (1.0 - f) + img[j, i + 1] * f
    return acc * p_major / abs(a_minor)


@njit(cache=True, parallel=True)
def radon_line_by_line(img, pu, pv, c_ref, r_ref, cos_a, sin_a, s0, ds, n_s):
    """The earlier kernel: each line walked across the image's rows."""
    out = np.zeros((cos_a.shape[0], n_s), np.float32)
    img_t = img.T
    for a in prange(cos_a.shape[0]):
        for k in range(n_s):
            s = s0 + k * ds
            if abs(cos_a[a]) >= abs(sin_a[a]):
                out[a, k] = _line_walk(img, s, sin_a[a], cos_a[a], pv, pu, r_ref, c_ref)
            else:
                out[a, k] = _line_walk(img_t, s, cos_a[a], sin_a[a], pu, pv, c_ref, r_ref)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=30)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[:256, :256]
    img = (np.exp(-((xx - 120) ** 2 + (yy - 130) ** 2) / 4000.0) + 0.01 * rng.random((256, 256))).astype(np.float32)
    ang = np.arange(360) * np.pi / 360
    call = (img, 0.2, 0.2, 127.5, 127.5, np.cos(ang), np.sin(ang), -36.2, 0.2, 363)
    new, old = kernels.radon_joseph(*call), radon_line_by_line(*call)      # compile, and compare
    times = {"row-ordered (conecal)": [], "line by line (before)": []}
    for _ in range(args.repeats):       # interleaved: both see the same machine load
        for name, f in (("row-ordered (conecal)", kernels.radon_joseph), ("line by line (before)", radon_line_by_line)):
            t = time.perf_counter()
            f(*call)
            times[name].append(time.perf_counter() - t)
    med = {k: float(np.median(v)) for k, v in times.items()}
    for k, v in med.items():
        print(f"{k:24s} {1e3 * v:7.1f} ms a view (median of {args.repeats})")
    print(f"speed-up {med['line by line (before)'] / med['row-ordered (conecal)']:.2f}x; "
          f"largest difference {np.abs(new - old).max():.2e} of sums up to {np.abs(old).max():.1f}")


if __name__ == "__main__":
    main()
