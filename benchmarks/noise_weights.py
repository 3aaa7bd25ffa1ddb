"""How much the frame's noise correlation factor applies to a small shadow's
centre (issue 32, σ on JPEG and blurred-noise frames): a finding, not a
method of conecal.

detect multiplies every centre variance by one factor per scan, kappa
(``noise.noise_correlation``: the variance of block means of 6-12 px over
the white-noise value). That is right for weights that vary slowly over
the noise's correlation length. A model fit's x weights (the derivative of
a blurred disc: two lobes at the rim) and a centroid's ((x - c) over a
window) vary within a few px, so correlated noise averages out there more
than kappa says. For a weight image w the factor is
sum_d rho(d) A_w(d) / A_w(0) (rho: the noise's autocorrelation, A_w: w's).
This prints, per frame with markers: kappa, and that factor for a model
fit's and a centroid's x weights at a few radii, rho measured on the
frame's high-passed (31 px box) background away from structure and
markers, lags up to ``--lags``. The high-pass puts negative lobes in rho
at long lags, which read high for weights as wide as the box.

    python benchmarks/noise_weights.py <case dir with scan/ and markers.json> [--frames 3] [--radii 2 3 4.5]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from conecal.detect.noise import noise_correlation
from conecal.detect.overlap import render
from conecal.scan.scan import load_scan
from conecal.stats import mad_sigma


def autocorrelation(a: np.ndarray, markers: list, lags: int) -> np.ndarray:
    """rho over lags -L..L (2L+1, 2L+1) of the high-passed frame's background."""
    hp = a - cv2.blur(a, (31, 31), borderType=cv2.BORDER_REPLICATE)
    sm = cv2.blur(hp, (5, 5))
    busy = (np.abs(sm - np.median(sm)) > 4 * mad_sigma(sm)).astype(np.uint8)
    busy = cv2.dilate(busy, np.ones((31, 31), np.uint8))
    for m in markers:
        cv2.circle(busy, (int(m["x"]), int(m["y"])), int(3 * m["radius"] + 10), 1, -1)
    keep = ((busy == 0) & np.isfinite(a)).astype(np.float64)
    x = np.where(keep > 0, hp, 0.0).astype(np.float64)
    shape = (x.shape[0] + lags, x.shape[1] + lags)
    F, M = np.fft.rfft2(x, shape), np.fft.rfft2(keep, shape)
    num, den = np.fft.irfft2(F * np.conj(F), shape), np.fft.irfft2(M * np.conj(M), shape)
    idx = np.r_[0:lags + 1, -lags:0]
    C = num[np.ix_(idx, idx)] / np.maximum(den[np.ix_(idx, idx)], 1.0)
    return np.fft.fftshift(C / C[0, 0])


def factor(rho: np.ndarray, w: np.ndarray) -> float:
    """sum_d rho(d) A_w(d) / A_w(0) for weights ``w`` (odd-sized, centred)."""
    L = rho.shape[0] // 2
    A = cv2.filter2D(w, -1, w[::-1, ::-1].copy(), borderType=cv2.BORDER_CONSTANT)
    c = A.shape[0] // 2
    return float((rho * A[c - L:c + L + 1, c - L:c + L + 1]).sum() / A[c, c])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", type=Path)
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--radii", type=float, nargs="*", default=[2.0, 3.0, 4.5])
    ap.add_argument("--lags", type=int, default=12)
    ap.add_argument("--blur", type=float, default=1.0, help="the model's blur sigma, px")
    a = ap.parse_args()
    scan = load_scan(a.case / "scan" / "scan.yaml")
    found = json.load(open(a.case / "markers.json"))["frames"]
    n = 2 * int(max(a.radii) + 3 * a.blur + a.lags) + 1
    c = n // 2 + 0.3
    yy, xx = np.mgrid[0:n, 0:n]
    print("| frame | kappa | " + " | ".join(f"R {r:g}: model / centroid" for r in a.radii) + " |")
    print("|---|---|" + "---|" * len(a.radii))
    for k in [int(f) for f in scan.log.frame if found[int(f)]["markers"]][:a.frames]:
        img = np.asarray(scan.stack.read(k, check=False), np.float32)
        rho = autocorrelation(img, found[k]["markers"], a.lags)
        cells = []
        for R in a.radii:
            _, J = render((n, n), np.array([[c, c, R, 0.1]]), a.blur, jacobian=True)
            wm = J[:, 0].reshape(n, n).astype(np.float64)
            wc = np.where(np.hypot(xx - c, yy - c) <= R + 2 * a.blur, xx - c, 0.0)
            cells.append(f"{factor(rho, wm):.1f} / {factor(rho, wc):.1f}")
        print(f"| {k} | {noise_correlation(img):.1f} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
