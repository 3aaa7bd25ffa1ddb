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
fit's and a centroid's x weights (over ``frame.window_radius``) at a few
radii, as detect now takes it
(``noise.noise_autocorrelation``, ``noise.weights_kappa``: rho on the
frame's 61 px high-passed background away from structure, lags up to 16
px; the factor between 1 and kappa).

    python benchmarks/noise_weights.py <case dir with scan/ and markers.json> [--frames 3] [--radii 2 3 4.5]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from conecal.detect.frame import window_radius
from conecal.detect.noise import noise_autocorrelation, noise_correlation, weights_kappa
from conecal.scan.scan import load_scan


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", type=Path)
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--radii", type=float, nargs="*", default=[2.0, 3.0, 4.5])
    ap.add_argument("--blur", type=float, default=1.0, help="the model's blur sigma, px")
    a = ap.parse_args()
    scan = load_scan(a.case / "scan" / "scan.yaml")
    found = json.load(open(a.case / "markers.json"))["frames"]
    print("| frame | kappa | " + " | ".join(f"R {r:g}: model / centroid" for r in a.radii) + " |")
    print("|---|---|" + "---|" * len(a.radii))
    for k in [int(f) for f in scan.log.frame if found[int(f)]["markers"]][:a.frames]:
        img = np.asarray(scan.stack.read(k, check=False), np.float32)
        kappa, rho = noise_correlation(img), noise_autocorrelation(img)
        cells = [f"{weights_kappa(kappa, rho, 'model', R, a.blur):.1f} / "
                 f"{weights_kappa(kappa, rho, 'centroid', window_radius(R, a.blur), a.blur):.1f}" for R in a.radii]
        print(f"| {k} | {kappa:.1f} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
