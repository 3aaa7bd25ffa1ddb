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


def _helix(n=31, turns=1.25, radius=30.0, length=50.0, removed=(4, 13, 22)):
    """A helix of ``n`` sphere positions (mm), its axis along y, with the
    positions ``removed`` (which break its screw and turn symmetries)."""
    a = np.linspace(0, 2 * np.pi * turns, n)
    P = np.column_stack([radius * np.cos(a), np.linspace(-length / 2, length / 2, n), radius * np.sin(a)])
    return np.delete(P, removed, axis=0)


def test_a_tied_frame_is_searched_near_its_neighbours_and_the_data_name_it():
    """Frame 4's tie holds only wrong identifications (a helix's turned
    labellings can fill the whole search's best votes); searched near the
    pose frames 3 and 5 predict, the right one explains every detection and
    wins on the data alone. With no ok neighbour nothing is searched."""
    from conecal.calib.run import FreeOptions
    from conecal.calib.second_look import Tie, _searched_near

    points = _helix()
    shape = describe_phantom(points, np.arange(1, len(points) + 1), radius=1.25)
    poses = _sweep(np.random.default_rng(3), n=9, step_deg=5.0)
    k = 4
    R, t = poses[k]
    rng = np.random.default_rng(1)
    order = rng.permutation(len(points))[:23]                 # 23 of 28 seen, in no order
    xy = CAM.project(points[order] @ R.T + t) + rng.normal(0, 0.05, (23, 2))
    turned = rotvec_to_matrix([0.0, 0.0, np.pi]) @ R            # a wrong pose, 180 deg about the beam
    wrong = Candidate(np.arange(18), order[:18], turned, t, 0.1)
    fr = {"frame": k}
    posed = {j: p for j, p in enumerate(poses) if j != k}
    ties = {k: (fr, Tie("two fit alike", [wrong]))}
    got = list(_searched_near(CAM, None, shape, points, posed, ties, {k: (xy,)}, 0.5, 0.07, FreeOptions()))
    assert len(got) == 1 and got[0][0] is fr
    c = got[0][1][0]
    assert len(c.sph) >= 22 and np.array_equal(c.sph, order[c.det])
    assert list(_searched_near(CAM, None, shape, points, {}, ties, {k: (xy,)}, 0.5, 0.07, FreeOptions())) == []


def test_a_twin_the_phantoms_symmetry_makes_is_no_rival():
    """A marked grid keeps one symmetry (its diagonal mirror, seen from
    behind): the two labellings put every sphere in the same place, so the
    second look names the frame (by the search's convention), where it had
    called them a tie."""
    from conecal.calib.neighbours import _relabellings, _twins
    from conecal.calib.run import FreeOptions
    from conecal.calib.second_look import Tie, _rank
    from conecal.calib.search import by_convention

    assert SHAPE.symmetries
    R, t = _sweep(np.random.default_rng(2))[3]
    pts = SHAPE.points
    xy = CAM.project(pts @ R.T + t) + np.random.default_rng(0).normal(0, 0.03, (len(pts), 2))
    perms = _relabellings(SHAPE)
    (R0, t0), (R1, t1) = _twins(pts, perms, R, t)[:2]
    det = np.arange(len(pts))
    a = Candidate(det, perms[0][det], R0, t0, 0.05)
    b = Candidate(det, perms[1][det], R1, t1, 0.05)
    got = _rank(CAM, SHAPE, pts, xy, [a, b], 0.5, 0.05, FreeOptions())
    assert not isinstance(got, Tie) and got is not None
    want = by_convention([a, b], SHAPE)
    assert np.allclose(got[0].R, want.R, atol=1e-3)


class _Bundle:
    """What the second look reads of a bundle: one camera, no distortion,
    the ok frames' poses (slot order) and a residual scale of 0.05 px."""

    def __init__(self, poses):
        self.R = np.array([R for R, _ in poses])
        self.t = np.array([t for _, t in poses])
        self.camera = CAM
        self.residual_px = np.full((40, 2), 0.035)

    def frame_camera(self, s):
        return CAM

    def frame_distortion(self, s):
        return None


def test_a_winner_that_leaves_detections_unexplained_waits_for_the_search_near_its_neighbours(monkeypatch):
    """A frame the denser search names with a labelling that leaves 5 of its
    23 detections unexplained (an independent generator's biplane: every
    sphere named wrong at 1.9x the floor, the right labelling never voted) is
    not taken as it is: searched near the pose its ok neighbours predict,
    the right one explains every detection and names the frame."""
    from conecal.calib import second_look as sl
    from conecal.calib.run import FreeOptions
    from conecal.calib.search import SearchResult
    from conecal.documents.status import OK, rejected

    points = _helix()
    shape = describe_phantom(points, np.arange(1, len(points) + 1), radius=1.25)
    poses = _sweep(np.random.default_rng(3), n=9, step_deg=5.0)
    rng = np.random.default_rng(2)
    dets, usable, orders = {}, [], {}
    for k, (R, t) in enumerate(poses):
        order = orders[k] = rng.permutation(len(points))[:23]
        dets[k] = (CAM.project(points[order] @ R.T + t) + rng.normal(0, 0.03, (23, 2)), np.full(23, 0.03))
        if k != 4:
            best = Candidate(np.arange(23), order, R, t, 0.04)
            usable.append({"frame": k, "slot": len(usable), "pairs": (np.arange(23), order), "status": OK,
                           "search": SearchResult(OK, best)})
    R, t = poses[4]
    turned = rotvec_to_matrix([0.0, 0.0, np.pi]) @ R
    wrong = Candidate(np.arange(18), rng.permutation(len(points))[:18], turned, t, 0.09)
    fr = {"frame": 4, "status": rejected("residual", "0.42 px"),
          "search": SearchResult(rejected("residual", ""), wrong)}
    # (the denser search returns the wrong labelling as the only one at the floor)
    monkeypatch.setattr(sl, "_decide", lambda *a, **k: (wrong, ""))
    b = _Bundle([poses[k] for k in range(9) if k != 4])
    won, lost = sl.second_look(b, [fr], usable, dets, shape, points, FreeOptions())
    assert fr in won and lost == []
    c = fr["search"].best
    assert len(c.sph) >= 22 and np.array_equal(c.sph, orders[4][c.det])   # every detection named as made
    # (an ok frame whose visible beads admit the helix moved by one is doubted
    # by that rival and named by its neighbours: named as made)
    for o in won:
        assert np.array_equal(o["search"].best.sph, orders[o["frame"]][o["search"].best.det]), o["frame"]


def test_a_detection_too_uncertain_to_name_a_sphere_is_not_unexplained():
    """Three detections left unexplained by a frame's identity send it to a
    second look, unless their 3 sigma exceed the gate: markers over two
    spheres nearly on top (sigma 1.5-1.9 px) cannot say which sphere, if
    any, they are."""
    from conecal.calib.second_look import _unexplained

    explained = np.arange(21)
    sure = np.r_[np.full(21, 0.04), 0.05, 0.04, 0.37]
    vague = np.r_[np.full(21, 0.04), 1.5, 1.9, 0.37]
    assert _unexplained(sure, explained, 1.4)
    assert not _unexplained(vague, explained, 1.4)
    assert _unexplained(vague, explained, 6.0)      # a wide gate: their place says enough
    assert not _unexplained(sure, np.arange(22), 1.4)   # two left: too few


def test_a_rival_doubts_an_identification_by_count_or_by_a_clearly_better_fit():
    """Explaining one detection fewer doubts nothing at the same fit (a
    helix's turned labellings), but does when it fits far closer (the right
    labelling of a grid under a bump the model lacks, against a turned one
    that bends to keep one more sphere)."""
    from conecal.calib.second_look import _doubts

    R, t = _sweep(np.random.default_rng(5))[2]
    pts = SHAPE.points
    rng = np.random.default_rng(1)
    xy = CAM.project(pts @ R.T + t) + rng.normal(0, 0.1, (len(pts), 2))
    every = np.arange(len(pts))
    pooled = 0.14                                          # the scan's 2-D RMS, px
    close = Candidate(every[:-1], every[:-1], R, t)        # one fewer, at the noise
    bent = Candidate(every, every, R, t + R @ np.array([0.05, 0.0, 0.0]))   # all, 0.1 mm off: ~0.2 px more
    same = Candidate(every, every, R, t)
    assert _doubts(CAM, pts, xy, close, bent, len(bent.sph), pooled)
    assert not _doubts(CAM, pts, xy, close, same, len(same.sph), pooled)
    assert _doubts(CAM, pts, xy, same, bent, len(bent.sph), pooled)   # as many: always a rival


def test_a_grids_turns_put_every_sphere_where_it_was_and_the_right_one_wins_back():
    """``lattice.turned``: each relabelling by a turn of the whole lattice,
    posed alike, projects its spheres where the original's were (the grid's
    missing corner drops one); ranked with the calibrated camera, a frame
    labelled with the grid turned gets its right labelling back from them
    (it explains the detection the turn put on the hole)."""
    from conecal.calib.lattice import turned
    from conecal.calib.run import FreeOptions
    from conecal.calib.second_look import Tie, _rank

    R, t = _sweep(np.random.default_rng(4))[5]
    pts = SHAPE.points
    det = np.arange(len(pts))
    true = Candidate(det, det.copy(), R, t, 0.03)
    turns = turned(SHAPE, pts, true)
    assert len(turns) == 7     # a square lattice: 8 maps, the identity left out
    for c in turns:
        assert len(c.sph) >= len(pts) - 1
        assert np.allclose(CAM.project(pts[c.sph] @ c.R.T + c.t), CAM.project(pts[true.sph] @ R.T + t)[c.det],
                           atol=1e-6)
    xy = CAM.project(pts @ R.T + t) + np.random.default_rng(1).normal(0, 0.03, (len(pts), 2))
    wrong = next(c for c in turns if not np.array_equal(c.sph, c.det))
    alone = _rank(CAM, SHAPE, pts, xy, [wrong], 0.5, 0.05, FreeOptions())
    assert not isinstance(alone, Tie) and alone[0].sph.tolist() != alone[0].det.tolist()
    got = _rank(CAM, SHAPE, pts, xy, [wrong] + turned(SHAPE, pts, wrong), 0.5, 0.05, FreeOptions())
    best = got.cands[0] if isinstance(got, Tie) else got[0]
    # (the best explains the most: the right labelling, or its twin by the
    # grid's one symmetry, the same image)
    twin = SHAPE.symmetries[0][0] @ SHAPE.lattice.T
    right = [np.arange(len(pts)), [SHAPE.lattice_index()[tuple(v)] for v in (twin.T + SHAPE.symmetries[0][1])]]
    assert any(np.array_equal(best.sph, np.asarray(r)[best.det]) for r in right)
