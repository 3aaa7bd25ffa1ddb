"""Identities a frame's pattern leaves open, taken from the neighbouring frames."""

from __future__ import annotations

import numpy as np

from conecal.calib.camera import Camera
from conecal.calib.candidate import Candidate
from conecal.calib.neighbours import by_neighbours, jumps, predicted
from conecal.calib.phantom import describe_phantom
from conecal.geometry import ConeGeometry, rotvec_to_matrix
from conecal.simulate.carm import grid_phantom

CAM = Camera.nominal(ConeGeometry.nominal(sod=600.0, sdd=1000.0, shape=(512, 512), pixel_pitch=(0.45, 0.45)), 600.0)
SHAPE = describe_phantom(grid_phantom(marked=True), np.arange(1, 25))


def _sweep(rng, n=12, step_deg=4.0, jitter_deg=1.5):
    """A C-arm sweep: the phantom 20 mm off the isocentre, the arm turned
    ``step_deg`` per frame about the lab y axis, with jitter."""
    out = []
    for k in range(n):
        a = np.deg2rad(-20 + step_deg * k + rng.uniform(-jitter_deg, jitter_deg))
        M = rotvec_to_matrix([0.0, a, 0.0])
        R0 = rotvec_to_matrix(np.deg2rad([25.0, 0.0, 10.0]))
        out.append((M @ R0, M @ np.array([20.0, -5.0, 10.0])))
    return out


def _tie(R, t):
    """The true identification and one a pitch off it (a grid whose missing
    corner went unseen fits both)."""
    sph = np.arange(len(SHAPE.points))
    shift = R @ (SHAPE.points[1] - SHAPE.points[0])
    return [Candidate(sph, sph, R, t - shift, 0.05), Candidate(sph, sph, R, t, 0.05)]


def test_a_sweep_breaks_a_tie_and_a_shuffled_scan_does_not():
    rng = np.random.default_rng(4)
    poses = _sweep(rng)
    k = 6
    posed = {j: p for j, p in enumerate(poses) if j != k}
    chosen = by_neighbours(CAM, SHAPE, SHAPE.points, posed, {k: _tie(*poses[k])})
    assert set(chosen) == {k}
    c, why = chosen[k]
    assert np.allclose(c.R, poses[k][0]) and np.allclose(c.t, poses[k][1]) and "frame(s) 5 and 7" in why
    # the same poses in no order: neighbours predict nothing, the tie stays
    shuffled = [poses[j] for j in rng.permutation(len(poses))]
    k = 6
    posed = {j: p for j, p in enumerate(shuffled) if j != k}
    assert by_neighbours(CAM, SHAPE, SHAPE.points, posed, {k: _tie(*shuffled[k])}) == {}


def test_a_pose_turned_off_its_sweep_stands_out_and_a_shuffled_scan_has_none():
    """A frame labelled with the phantom turned by 180 deg about its normal
    lies far from what its neighbours predict: it is searched again near
    them. Shuffled, every frame misses alike and none stands out."""
    rng = np.random.default_rng(5)
    poses = _sweep(rng)
    turn = rotvec_to_matrix(np.pi * SHAPE.n)
    c = SHAPE.points.mean(0)
    for k in (2, 7):
        posed = dict(enumerate(poses))
        R, t = poses[k]
        posed[k] = (R @ turn, t + R @ c - R @ turn @ c)
        preds = predicted(CAM, SHAPE, SHAPE.points, posed)
        assert jumps(CAM, SHAPE, SHAPE.points, posed, preds) == {k}
    shuffled = dict(enumerate(poses[j] for j in rng.permutation(len(poses))))
    assert len(jumps(CAM, SHAPE, SHAPE.points, shuffled, predicted(CAM, SHAPE, SHAPE.points, shuffled))) <= 2


def test_neighbours_never_choose_wrong_and_keep_ties_when_the_steps_jitter():
    """However much the sweep jitters, a tie broken is broken right; beyond
    a pitch's worth of jitter ties are kept."""
    decided = {}
    for jitter in (1.5, 12.0, 30.0, 45.0):
        decided[jitter] = 0
        for seed in range(8):
            poses = _sweep(np.random.default_rng(seed), jitter_deg=jitter)
            for k in (3, 6):
                posed = {j: p for j, p in enumerate(poses) if j != k}
                for c, _ in by_neighbours(CAM, SHAPE, SHAPE.points, posed, {k: _tie(*poses[k])}).values():
                    assert np.allclose(c.t, poses[k][1]), (jitter, seed, k)
                    decided[jitter] += 1
    assert decided[1.5] == 16 and decided[30.0] == decided[45.0] == 0, decided


def test_a_frame_whose_visible_grid_is_symmetric_takes_its_identity_from_the_sweep(tmp_path):
    """A marked grid (one corner missing) turned through a sweep; in frame 4
    the other three corners' markers are lost, so four turns of the pattern
    fit it alike. The calibration names it from its neighbours, rightly:
    the spheres it names are the ones seen."""
    import sys

    sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
    from test_free_pose import _free_scan

    from conecal.calib.run import calibrate_free
    from conecal.scan import load_scan

    d, mdoc, sc = _free_scan(tmp_path, distortion="none", seed=4, n=8)
    ids, cad = sc.phantom
    rng = np.random.default_rng(2)
    frames, truth = [], {}
    for k in range(8):
        M = rotvec_to_matrix([0.0, np.deg2rad(-24 + 4 * k + rng.uniform(-1, 1)), 0.0])
        R = M @ rotvec_to_matrix(np.deg2rad([30.0, 0.0, 20.0]))
        X = cad @ R.T + M @ np.array([10.0, -5.0, 5.0])
        keep = np.ones(len(cad), bool)
        if k == 4:
            keep[[3, 19, 23]] = False          # the corners the missing one could be turned to
        xy = sc.geometry.project(X[keep]) + rng.normal(0, 0.03, (keep.sum(), 2))
        truth[k] = cad[keep]
        frames.append({"frame": k, "markers": [{"id": None, "x": float(x), "y": float(y), "sigma": 0.03,
                                                "flags": []} for x, y in xy]})
    s = load_scan(d)
    res = calibrate_free(s, {"format": "conecal-markers/1", "frames": frames}, s.nominal_geometry())
    fr = res.frames[4]
    assert fr["status"].ok and "neighbouring frame(s) 3 and 5" in fr.get("identified_by", ""), fr["status"]
    # the spheres named are the ones seen, up to the grid's own symmetry (a rigid map carries one set on the other)
    d_, p_ = (np.asarray(v) for v in fr["pairs"])
    A, B = cad[p_], truth[4][d_]
    a, b = A - A.mean(0), B - B.mean(0)
    U, _, Vt = np.linalg.svd(a.T @ b)
    R = (U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt).T
    assert len(p_) == len(truth[4]) and np.abs(a @ R.T - b).max() < 0.05
