"""Free poses: a look starts its fit from the look before when that ends lower."""

from __future__ import annotations

import numpy as np

from conecal.calib.bundle import Observations, adjust, family_named
from conecal.calib.camera import Camera
from conecal.calib.phantom import describe_phantom
from conecal.calib.restart import from_before
from conecal.geometry import ConeGeometry, rotvec_to_matrix
from conecal.geometry.distortion import Distortion
from conecal.simulate.carm import ball_phantom, random_poses


def _scan():
    g = ConeGeometry.nominal(sod=600.0, sdd=1000.0, shape=(512, 512), pixel_pitch=(0.45, 0.45))
    cam = Camera.nominal(g, 600.0)
    rng = np.random.default_rng(5)
    pts = ball_phantom(rng)
    poses = random_poses(rng, 5, 40.0, 20.0, 10.0)
    F, P = len(poses.R), len(pts)
    slot, sph = np.repeat(np.arange(F), P), np.tile(np.arange(P), F)
    X = np.einsum("nij,nj->ni", poses.R[slot], pts[sph]) + poses.t[slot]
    # a twist that differs per frame (px at the field's edge: a few)
    xy = np.empty((len(X), 2))
    for k in range(F):
        d = Distortion.radial((512, 512), k1=2.0, s=(-3.0, 2.0, 4.0, -2.5, 3.0)[k])
        xy[slot == k] = d.distort(cam.project(X[slot == k]))
    xy += rng.normal(0, 0.03, xy.shape)
    return cam, pts, poses, Observations(slot, sph, xy, np.full(len(xy), 0.03))


def test_the_looks_fit_is_restarted_from_the_last_looks_when_that_ends_lower():
    cam, pts, poses, obs = _scan()
    fam = family_named("radial+S per frame")
    good = adjust(fam, cam, obs, pts, 0.0, poses.R, poses.t)
    # a fit stopped at its start (every pose turned by 3 deg): a stand-in for a
    # false minimum, which a single evaluation cannot leave either
    turned = rotvec_to_matrix(np.tile(np.radians([3.0, 0.0, 0.0]), (len(poses.R), 1))) @ poses.R
    poor = adjust(fam, cam, obs, pts, 0.0, turned, poses.t, max_nfev=1)
    assert poor.fit.chi2 > 2 * good.fit.chi2          # the case is one a restart can mend
    shape = describe_phantom(pts, list(range(len(pts))), radius=1.0)
    frames = [{"frame": k} for k in range(len(poses.R))]
    fits = {fam.name: poor}
    from_before(fits, (good, [fr["frame"] for fr in frames]), frames, cam, obs, shape, 0.0)
    assert fits[fam.name].fit.chi2 < 1.1 * good.fit.chi2
    # another set of frames: the slots do not match, nothing is restarted
    fits = {fam.name: poor}
    from_before(fits, (good, [1, 0, 2, 3, 4]), frames, cam, obs, shape, 0.0)
    assert fits[fam.name] is poor
