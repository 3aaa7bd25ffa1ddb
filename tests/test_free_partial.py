"""A 3-D phantom's partial symmetries: a uniform helix's screw by one bead
carries every bead but the last onto the next, so a frame that sees neither
end images it alike in two poses. The search offers the moved labelling and
the frame is ambiguous, never a confident wrong name."""

import numpy as np

from conecal.calib.camera import Camera
from conecal.calib.partial import partial_maps
from conecal.calib.phantom import describe_phantom
from conecal.calib.search import search_frame
from conecal.geometry import ConeGeometry, rotvec_to_matrix

CAM = Camera.nominal(ConeGeometry.nominal(sod=600.0, sdd=1000.0, shape=(512, 512), pixel_pitch=(0.45, 0.45)), 600.0)


def _helix(n=30):
    a = np.linspace(0, 2 * np.pi * 1.25, n)
    return np.column_stack([44 * np.cos(a), np.linspace(-66, 66, n), 44 * np.sin(a)])


def test_a_helix_screw_is_a_partial_symmetry_and_random_beads_have_none():
    maps = partial_maps(_helix())
    by_one = tuple(list(range(1, 30)) + [-1])
    assert by_one in maps and all(-1 in m for m in maps)
    rng = np.random.default_rng(0)
    assert partial_maps(rng.uniform(-40, 40, (26, 3))) == ()


def test_a_helix_seen_away_from_its_ends_is_never_named_one_bead_along_with_confidence():
    # (14 of its middle 22 beads, as when its small beads go undetected: the
    # search named one such frame of twelve "ok" with every bead one along)
    P = _helix()
    shape = describe_phantom(P, np.arange(len(P)), radius=1.6)
    rng = np.random.default_rng(5)
    for _ in range(12):
        R, t = rotvec_to_matrix(rng.normal(0, 0.3, 3)), rng.normal(0, 5, 3)
        seen = np.sort(rng.choice(np.arange(4, 26), 14, replace=False))
        xy = CAM.project(P[seen] @ R.T + t) + rng.normal(0, 0.05, (len(seen), 2))
        res = search_frame(CAM, shape, xy)
        right = res.best is not None and np.array_equal(res.best.sph, seen[res.best.det])
        assert res.status.state != "ok" or right
