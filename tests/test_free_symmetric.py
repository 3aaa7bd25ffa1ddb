"""A 3-D phantom's own symmetries (a cube's corners: 24 turns map it onto
itself) give the same image and the same calibration: the frame is labelled
by convention and ok, as a grid's turns are (SCAN_FORMAT, motion: free).
And a sphere predicted in an image intensifier's black surround (as the
flat shows it) is not evidence against a pose."""

from dataclasses import replace
from itertools import product

import numpy as np

from conecal.calib.camera import Camera, Field
from conecal.calib.candidate import Candidate, rigid_fit
from conecal.calib.neighbours import in_sequence
from conecal.calib.partial import partial_maps
from conecal.calib.phantom import describe_phantom
from conecal.calib.search import SearchResult, search_frame, shadow_tally
from conecal.documents.status import OK
from conecal.geometry import ConeGeometry, matrix_to_rotvec, rotvec_to_matrix

CAM = Camera.nominal(ConeGeometry.nominal(sod=600.0, sdd=1000.0, shape=(512, 512), pixel_pitch=(0.45, 0.45)), 600.0)
CUBE = np.array(list(product((-25.0, 25.0), repeat=3)))


def test_a_cubes_24_turns_are_its_whole_symmetries_and_none_is_partial():
    shape = describe_phantom(CUBE, np.arange(8), radius=1.5)
    assert len(shape.perms) == 23 and len(shape.perm_names) == 23
    for p in shape.perms:
        A, o = rigid_fit(CUBE, CUBE[p])
        assert np.linalg.det(A) > 0 and np.allclose(CUBE @ A.T + o, CUBE[p], atol=1e-9)
    assert len({tuple(p) for p in shape.perms}) == 23
    assert partial_maps(CUBE) == ()
    # a cube with one corner moved has none, even by 0.3 mm (0.6 % of its
    # edge: a sphere's place the data see, so another geometry)
    for off in (9.0, 0.3):
        bent = CUBE.copy()
        bent[0] += [0, 0, off]
        assert describe_phantom(bent, np.arange(8), radius=1.5).perms == ()


def test_a_cube_frame_is_ok_by_convention_and_its_pose_puts_every_sphere_where_it_is():
    shape = describe_phantom(CUBE, np.arange(8), radius=1.5)
    rng = np.random.default_rng(3)
    n_ok = 0
    for _ in range(6):
        R, t = rotvec_to_matrix(rng.normal(0, 1.0, 3)), rng.normal(0, 5, 3)
        uv = CAM.project(CUBE @ R.T + t)
        d = np.linalg.norm(uv[:, None] - uv[None], axis=-1) + np.eye(8) * 1e9
        if d.min() < 12:      # (shadows on top of each other: another test's matter)
            continue
        xy = uv + rng.normal(0, 0.05, uv.shape)
        res = search_frame(CAM, shape, xy)
        assert res.status.state == "ok", res.status.sentence
        assert "convention" in res.convention and "24 poses" in res.convention
        b = res.best
        # any of the 24 labellings is right: the pose puts its sphere on its detection
        assert np.abs(CAM.project(CUBE[b.sph] @ b.R.T + b.t) - uv[b.det]).max() < 0.5
        n_ok += 1
    assert n_ok >= 3


def test_a_sphere_whose_shadow_reaches_the_intensifiers_surround_is_not_unseen():
    shape = describe_phantom(CUBE, np.arange(8), radius=1.5)
    R, t = rotvec_to_matrix([0.3, -0.5, 0.2]), np.array([0.0, 0.0, 0.0])
    uv = CAM.project(CUBE @ R.T + t)
    # the beam's edge between the corner farthest right-down and the rest
    reach = uv.sum(1)
    far = int(np.argmax(reach))
    edge = 0.5 * (reach[far] + np.sort(reach)[-2])
    rows, cols = np.mgrid[:512, :512]
    field = Field.from_mask(cols + rows < edge)
    assert field.holds(uv, 2.0).sum() == 7 and not field.holds(uv[far], 1.0)
    assert Field.from_mask(np.ones((512, 512), bool)) is None
    sph = np.array([k for k in range(8) if k != far])
    # (the corner lost: short of it inside the detector, not inside the field)
    assert shadow_tally(CAM, shape, R, t, sph)[1] == 1
    assert shadow_tally(replace(CAM, field=field), shape, R, t, sph)[1] == 0


def test_a_sweeps_frames_of_a_symmetric_phantom_are_labelled_alike_in_scan_order():
    # a cube turned 6 deg per frame, each frame's search labelling one of its
    # 24 by chance: after in_sequence every step is a 6 deg turn again, and
    # every pose still puts each named sphere on its detection
    shape = describe_phantom(CUBE, np.arange(8), radius=1.5)
    rng = np.random.default_rng(7)
    frames, truth = [], []
    for k in range(20):
        R, t = rotvec_to_matrix([0.1, np.radians(6) * k, 0.05]), np.array([2.0, -1.0, 3.0])
        p = shape.perms[rng.integers(len(shape.perms))] if k % 3 else np.arange(8)
        A, a = rigid_fit(CUBE, CUBE[p])
        Rk, tk = R @ A.T, t - R @ A.T @ a        # the same image named by p
        c = Candidate(np.arange(8), p.copy(), Rk, tk, 0.05)
        assert np.allclose(CAM.project(CUBE[c.sph] @ Rk.T + tk), CAM.project(CUBE @ R.T + t))
        frames.append({"frame": k, "status": OK, "search": SearchResult(OK, c)})
        truth.append(CAM.project(CUBE @ R.T + t))
    in_sequence(CAM, shape, frames)
    steps = [np.degrees(np.linalg.norm(matrix_to_rotvec(a["search"].best.R @ b["search"].best.R.T)))
             for a, b in zip(frames[1:], frames)]
    assert np.allclose(steps, 6.0, atol=0.01)
    for fr, uv in zip(frames, truth):
        b = fr["search"].best
        assert np.allclose(CAM.project(CUBE[b.sph] @ b.R.T + b.t), uv[b.det], atol=1e-6)
        assert "scan order" in fr["search"].convention

