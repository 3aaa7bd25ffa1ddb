"""Grangeat's intermediate function of one cone-beam projection.

For a plane through the source, the derivative of the object's plane
integral along the plane normal is, up to Grangeat's geometric factor, the
derivative along ``s`` of the 2D Radon transform of the cosine-weighted
projection on the line where the plane meets the detector. Two views whose
planes coincide must agree; ``rp-grid`` compares them.

Detector coordinates here are (u, v) in mm from the principal point, along
the detector's column and row directions; a line is
``u cos(alpha) + v sin(alpha) = s``.
"""

from __future__ import annotations

import cv2
import numpy as np


def cosine_weighted(projection: np.ndarray, pixel_pitch, principal_point, sdd: float) -> np.ndarray:
    """``g * D / sqrt(D^2 + u^2 + v^2)``: the projection weighted by the
    cosine of each ray's angle to the detector normal (D = sdd, mm)."""
    rows, cols = projection.shape
    u = (np.arange(cols) - principal_point[0]) * pixel_pitch[0]
    v = (np.arange(rows) - principal_point[1]) * pixel_pitch[1]
    w = sdd / np.sqrt(sdd**2 + u[None, :] ** 2 + v[:, None] ** 2)
    return (projection * w).astype(np.float32)


def radon_derivative_table(image: np.ndarray, pixel_pitch: float, principal_point, n_angles: int = 180,
                           n_offsets: int | None = None):
    """Radon transform of ``image`` and its derivative along ``s``.

    Lines ``u cos(a) + v sin(a) = s`` for ``a`` in [0, pi) (n_angles) and
    ``s`` on a grid of one pixel pitch (mm) covering the detector's
    diagonal. The image is rotated by each angle about the principal point
    (bilinear, OpenCV) and summed across, so each angle costs one warp.
    Square pixels are assumed (resample first otherwise).

    Returns (angles rad (n_a,), s mm (n_s,), radon (n_a, n_s) in image
    units * mm, derivative (n_a, n_s) per mm).
    """
    img = np.asarray(image, np.float32)
    rows, cols = img.shape
    half = int(np.ceil(np.hypot(rows, cols) / 2)) + 2
    n_s = n_offsets or 2 * half + 1
    # pad so that rotation about the principal point keeps everything
    size = 2 * half + 1
    # the principal point moves to the canvas centre (sub-pixel, bilinear)
    shift = np.float32([[1, 0, half - principal_point[0]], [0, 1, half - principal_point[1]]])
    canvas = cv2.warpAffine(img, shift, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    angles = np.arange(n_angles) * np.pi / n_angles
    radon = np.empty((n_angles, size), np.float64)
    for k, a in enumerate(angles):
        # rotate so that the direction (cos a, sin a) becomes +u; then columns index s
        R = cv2.getRotationMatrix2D((half, half), np.degrees(a), 1.0)
        rot = cv2.warpAffine(canvas, R, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        radon[k] = rot.sum(axis=0, dtype=np.float64) * pixel_pitch
    s = (np.arange(size) - half) * pixel_pitch
    deriv = np.gradient(radon, pixel_pitch, axis=1)
    if n_s != size:
        lo = (size - n_s) // 2
        s, radon, deriv = s[lo:lo + n_s], radon[:, lo:lo + n_s], deriv[:, lo:lo + n_s]
    return angles, s, radon, deriv
