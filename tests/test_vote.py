"""The orientation vote's compiled inner loop against a plain histogram."""

import numpy as np

from conecal.calib.vote import _offset_votes, _orientations


def test_the_compiled_vote_is_each_orientations_histogram_mode():
    rng = np.random.default_rng(3)
    Rs = _orientations(60, seed=2)
    P = rng.uniform(-20, 20, (12, 3))
    det = rng.uniform(0, 30, (15, 2)).astype(np.float32)
    depths = np.array([600.0, 700.0])
    f, cell, nb = (1400.0, 1500.0), 6.0, 32
    votes, best = _offset_votes(Rs, P, det, f[0], f[1], depths, cell, nb)
    for k in range(len(Rs)):
        X = P @ Rs[k].T
        for zi, z in enumerate(depths):
            pred = (np.stack([f[0] * X[:, 0], f[1] * X[:, 1]], -1) / (z + X[:, 2:3]) / cell).astype(np.float32)
            for si, shift in enumerate((0.0, 0.5)):
                q = np.floor(det[:, None, :] - pred[None] + np.float32(shift)).astype(int).reshape(-1, 2)
                q = q[(q >= 0).all(1) & (q < nb).all(1)]
                counts = np.bincount(q[:, 0] * nb + q[:, 1], minlength=nb * nb)
                assert votes[k, zi, si] == counts.max()
                assert best[k, zi, si] == counts.argmax()      # ties: the lowest cell
    assert votes.max() >= 3       # the test votes for something


def test_a_phantom_far_off_the_nominal_sod_is_searched_where_its_shadows_put_it():
    """A ball phantom 0.72 of the nominal sod from the source (the user's
    magnification 25 % low): its markers' shadow radii put it there, and the
    orientation search looking there names every detection."""
    from dataclasses import replace

    from conecal.calib.camera import Camera
    from conecal.calib.phantom import describe_phantom
    from conecal.calib.run import shadow_depth
    from conecal.calib.search import SearchOptions, search_frame
    from conecal.geometry import ConeGeometry, rotvec_to_matrix

    cam = Camera.nominal(ConeGeometry.nominal(sod=900.0, sdd=1100.0, shape=(768, 768), pixel_pitch=(0.35, 0.35)),
                         900.0)
    rng = np.random.default_rng(4)
    pts = rng.uniform(-30, 30, (20, 3))
    shape = describe_phantom(pts, np.arange(1, 21), radius=1.5)
    R, t = rotvec_to_matrix([0.4, -0.3, 0.9]), np.array([5.0, -3.0, 0.72 * 900.0 - 900.0])
    X = pts @ R.T + t
    xy = cam.project(X) + rng.normal(0, 0.05, (20, 2))
    # each shadow's radius (px) as its depth makes it, read 5 % small
    r = 0.95 * 1.5 * cam.sdd / (X[:, 2] + cam.sod) / 0.35
    doc = {"frames": [{"markers": [{"radius": float(v), "flags": []} for v in r]}]}
    depth = shadow_depth(doc, 3.0, cam)
    assert 0.72 * 900 < depth < 0.8 * 900
    assert shadow_depth({"frames": [{"markers": doc["frames"][0]["markers"][:10]}]}, 3.0, cam) is None
    found = search_frame(cam, shape, xy, None, replace(SearchOptions(), depth_mm=depth))
    assert found.status.ok and len(found.best.sph) == 20
    assert np.array_equal(found.best.sph, np.arange(20)[found.best.det])
