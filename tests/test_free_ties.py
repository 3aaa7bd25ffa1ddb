"""Free poses: ties between labellings of a grid."""

from __future__ import annotations

import numpy as np

from conecal.calib.camera import Camera
from conecal.calib.phantom import describe_phantom
from conecal.calib.search import search_frame
from conecal.geometry import ConeGeometry, rotvec_to_matrix
from conecal.simulate.carm import grid_phantom

SHAPE = (512, 512)


def _camera():
    g = ConeGeometry.nominal(sod=600.0, sdd=1000.0, shape=SHAPE, pixel_pitch=(0.45, 0.45))
    return Camera.nominal(g, 600.0)


def test_a_grid_corner_moved_beyond_the_gate_still_names_the_grid():
    """A 6x6 grid without one corner, every sphere seen, the opposite corner's
    shadow 4.5 px off (a distortion the nominal camera lacks): the right
    labelling leaves it beyond the gate, as a turned one leaves the detection
    where it puts the missing corner; but the right one has that corner's
    detection inside its predicted shadow, the turned one a sphere where the
    image has none. Not a tie."""
    cam = _camera()
    shape = describe_phantom(grid_phantom(6, pitch=12.0, marked=True), np.arange(35))
    R = rotvec_to_matrix(np.deg2rad([15.0, -10.0, 5.0]))
    t = np.array([2.0, -3.0, 0.0])
    xy = cam.project(shape.points @ R.T + t)
    corner = 34                                   # lattice (5, 5): the missing corner is (0, 0)
    out = xy[corner] - xy.mean(0)
    xy[corner] += 4.5 * out / np.linalg.norm(out)
    res = search_frame(cam, shape, xy)
    assert res.status.ok, res.status
    lab = shape.points[res.best.sph] @ res.best.R.T + res.best.t
    true = (shape.points @ R.T + t)[res.best.det]
    assert np.abs(lab - true).max() < 0.1
    # the corner is still what it is: with it moved 40 px, far off any
    # shadow, nothing tells the labellings apart
    xy[corner] += 40 * out / np.linalg.norm(out)
    assert not search_frame(cam, shape, xy).status.ok
