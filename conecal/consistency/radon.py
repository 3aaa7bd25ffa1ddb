"""Grangeat's intermediate function of one cone-beam projection.

For a plane through the source, the derivative of the object's plane
integral along the plane normal is, up to Grangeat's geometric factor, the
derivative along ``s`` of the 2D Radon transform of the cosine-weighted
projection on the line where the plane meets the detector. Two views whose
planes coincide must agree; ``rp-grid`` compares them.

Detector coordinates here are (u, v) in mm from the principal point, along
the detector's column and row directions; a line is
``u cos(alpha) + v sin(alpha) = s``. The loops are in :mod:`.kernels`.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import correlate1d

from . import kernels


def cosine_weighted(projection: np.ndarray, pixel_pitch, principal_point, sdd: float) -> np.ndarray:
    """``g * D / sqrt(D^2 + u^2 + v^2)``: the projection weighted by the
    cosine of each ray's angle to the detector normal (D = sdd, mm)."""
    return kernels.cosine_weight(np.asarray(projection, np.float32), float(pixel_pitch[0]), float(pixel_pitch[1]),
                                 float(principal_point[0]), float(principal_point[1]), 0.0, 0.0, float(sdd))


# half-width of the derivative kernel in sigmas, by order (the fourth-order
# taps' side lobes reach further)
KERNEL_REACH = {2: 4, 4: 5}


def derivative_kernel(sigma_bins: float, order: int = 2) -> np.ndarray:
    """Derivative-of-Gaussian taps normalised to differentiate a straight
    line exactly (scipy's sampled kernel under-reads narrow ones by ~14 %).

    ``order`` 4: taps ``x w (a + b x^2)`` that also differentiate a cubic
    exactly, so the smoothing's error starts at sigma^4 instead of sigma^2
    (the derivative of a Gaussian reads f' plus sigma^2/2 times the third
    derivative); at the same sigma its noise is 1.85 times the plain kernel's.
    """
    if order not in KERNEL_REACH:
        raise ValueError(f"derivative kernel order {order}: 2 or 4")
    sigma = max(float(sigma_bins), 0.5)
    half = int(np.ceil(KERNEL_REACH[order] * sigma))
    x = np.arange(-half, half + 1, dtype=float)
    w = np.exp(-x**2 / (2 * sigma**2))
    # correlate1d: out[i] = sum_k taps[k] in[i + k]; d/ds needs taps ~ +x
    if order == 2:
        return x * w / np.sum(x**2 * w)
    m2, m4, m6 = (np.sum(x**k * w) for k in (2, 4, 6))
    a, b = np.linalg.solve([[m2, m4], [m4, m6]], [1.0, 0.0])
    return x * w * (a + b * x**2)


def s_derivative(radon: np.ndarray, ds: float, sigma_bins: float, order: int = 2) -> np.ndarray:
    """d/ds of Radon rows sampled every ``ds`` mm, smoothed by a Gaussian of
    ``sigma_bins`` (``order``: see :func:`derivative_kernel`)."""
    return correlate1d(radon, derivative_kernel(sigma_bins, order), axis=-1, mode="constant") / ds


def radon_derivative_table(image: np.ndarray, pixel_pitch: float, principal_point, n_angles: int = 180,
                           n_offsets: int | None = None, smooth_bins: float = 0.5):
    """Radon transform of ``image`` and its derivative along ``s``.

    Lines ``u cos(a) + v sin(a) = s`` for ``a`` in [0, pi) (n_angles) and
    ``s`` on a grid of one pixel pitch (mm) covering the detector's
    diagonal (Joseph's method, square pixels).

    Returns (angles rad (n_a,), s mm (n_s,), radon (n_a, n_s) in image units * mm,
    derivative (n_a, n_s) per mm).
    """
    img = np.asarray(image, np.float32)
    rows, cols = img.shape
    half = int(np.ceil(np.hypot(rows, cols) / 2)) + 2
    n_s = n_offsets or 2 * half + 1
    angles = np.arange(n_angles) * np.pi / n_angles
    s0 = -(n_s // 2) * pixel_pitch
    radon = kernels.radon_joseph(img, float(pixel_pitch), float(pixel_pitch), float(principal_point[0]),
                                 float(principal_point[1]), np.cos(angles), np.sin(angles), s0, float(pixel_pitch), n_s)
    radon = radon.astype(np.float64)
    s = s0 + np.arange(n_s) * pixel_pitch
    return angles, s, radon, s_derivative(radon, pixel_pitch, smooth_bins)
