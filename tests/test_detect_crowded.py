"""detect on touching and overlapping shadows: found, centred, honest, no rods split into spheres."""

import numpy as np
import pytest

from conecal.detect import DetectOptions, detect_frame
from conecal.detect.overlap import render


def _pairs(gap, rng, R=6.0, mu=0.05, n=3):
    """Pairs of equal spheres whose shadows are ``gap`` diameters apart
    (0 touching, -0.5 overlapping by half a diameter), in random directions."""
    sph = []
    for cx in np.arange(n) * 100 + 60:
        for cy in np.arange(n) * 100 + 60:
            d = 2 * R * (1 + gap)
            ang = rng.uniform(0, np.pi)
            x0, y0 = cx + rng.uniform(-1, 1), cy + rng.uniform(-1, 1)
            sph += [[x0 - d / 2 * np.cos(ang), y0 - d / 2 * np.sin(ang), R, mu],
                    [x0 + d / 2 * np.cos(ang), y0 + d / 2 * np.sin(ang), R, mu]]
    return np.array(sph)


def test_the_model_jacobian_matches_finite_differences():
    s = np.array([[20.3, 18.7, 6.2, 0.05], [27.1, 21.4, 5.5, 0.06]])
    m, J = render((40, 48), s, 1.0, jacobian=True)
    for k in range(8):
        h = 1e-3 if k % 4 != 3 else 1e-5
        sp, sm = s.copy(), s.copy()
        sp.flat[k] += h
        sm.flat[k] -= h
        num = (render((40, 48), sp, 1.0).astype(float) - render((40, 48), sm, 1.0)).ravel() / (2 * h)
        # sampled 3x3 per pixel, the rim's derivative is approximate: the
        # Jacobian steers Gauss-Newton, it need not be exact at the rim
        assert np.corrcoef(num, J[:, k])[0, 1] > 0.98, k


@pytest.mark.parametrize("R", [3.3, 6.2, 11.7])
def test_the_model_holds_each_spheres_attenuation_and_both_paths_agree(R):
    # a shadow's chords integrate to the sphere's volume times mu; the blur keeps it
    s = np.array([[20.3, 18.7, 6.2, 0.05], [28.2 + R, 24.6, R, 0.06]])
    m = render((48, 64), s, 0.8)
    mj, J = render((48, 64), s, 0.8, jacobian=True)
    volume = 4 / 3 * np.pi * s[:, 2] ** 3 * s[:, 3]
    assert m.sum() == pytest.approx(volume.sum(), rel=2e-3)
    np.testing.assert_allclose(mj, m, atol=1e-6)
    # the model is linear in mu: its mu column times mu is each sphere's shadow
    np.testing.assert_allclose(J[:, 3::4] @ s[:, 3], m.ravel(), atol=1e-6)


@pytest.mark.parametrize("gap", [0.0, -0.25, -0.5])
def test_touching_and_overlapping_pairs_are_all_measured(gap):
    rng = np.random.default_rng(3)
    sph = _pairs(gap, rng)
    img = (render((320, 320), sph, 1.0) + 0.1 + rng.normal(0, 0.004, (320, 320))).astype(np.float32)
    opt = DetectOptions(diameter_px=(7.2, 19.2), blur_px=1.0)
    blobs = detect_frame(img, opt)
    assert len(blobs) == len(sph)               # none lost, none invented
    err, sig = [], []
    for s in sph:
        b = min(blobs, key=lambda b: np.hypot(b.x - s[0], b.y - s[1]))
        err += [b.x - s[0], b.y - s[1]]
        sig += [b.sigma, b.sigma]
        assert "overlap" in b.flags
    err, sig = np.array(err), np.array(sig)
    assert np.sqrt(np.mean(err**2)) < 0.05
    assert 0.6 < np.std(err / sig) < 1.6
    # measured alone, the merged pairs are lost
    alone = detect_frame(img, DetectOptions(diameter_px=(7.2, 19.2), blur_px=1.0, joint_overlaps=False))
    assert len(alone) < len(sph) // 2


@pytest.mark.parametrize("gap", [-0.3, -0.5])
def test_overlapping_pairs_whose_cores_are_clipped_are_measured(gap):
    # the independent renderer's steel balls on an intensifier: the display's
    # floor clips every core at one level (3.46). Weighed as measurements, the
    # flat cores misfit any pair's model, and 14 of 73 overlapping balls were
    # lost or left inside one marker's σ
    rng = np.random.default_rng(5)
    sph = _pairs(gap, rng)
    img = render((320, 320), sph, 1.0) + 0.1 + rng.normal(0, 0.004, (320, 320))
    img = np.minimum(img, 0.1 + 0.45).astype(np.float32)      # below a lone sphere's peak of 0.6
    blobs = detect_frame(img, DetectOptions(diameter_px=(7.2, 19.2), blur_px=1.0))
    for s in sph:
        b = min(blobs, key=lambda b: np.hypot(b.x - s[0], b.y - s[1]))
        assert np.hypot(b.x - s[0], b.y - s[1]) < 0.3 and "overlap" in b.flags, (s, b)
    assert len(blobs) == len(sph)


def test_a_rod_is_not_split_into_spheres():
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:200, 0:200]
    # a bar 12 px wide, 30 px long (a merged pair's size), and a long one
    img = 0.1 + rng.normal(0, 0.004, (200, 200))
    for (x0, y0, length) in [(60, 60, 30), (140, 40, 120)]:
        inside = (np.abs(xx - x0) < 6) & (np.abs(yy - y0 - length / 2) < length / 2)
        img += 0.5 * inside
    img = img.astype(np.float32)
    import cv2

    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    blobs = detect_frame(img, DetectOptions(diameter_px=(7.2, 19.2), blur_px=1.0))
    assert blobs == []


def test_a_sphere_beside_a_plate_edge_is_measured_with_the_step_removed():
    import cv2

    from conecal.detect.noise import noise_pixel

    rng = np.random.default_rng(5)
    R, errs, sig = 8.0, [], []
    for trial in range(8):
        x0, y0 = 100.3 + rng.uniform(-0.5, 0.5), 100.6
        img = np.full((200, 200), 0.1, np.float32)
        img[:, int(x0 + R + 2 + trial % 3):] += 0.2      # the plate's edge 2-4 px beside the shadow
        img = cv2.GaussianBlur(img, (0, 0), 1.0) + render((200, 200), np.array([[x0, y0, R, 0.05]]), 1.0)
        img = (img + rng.normal(0, 0.004, img.shape)).astype(np.float32)
        opt = DetectOptions(diameter_px=(9.6, 25.6), blur_px=1.0, pixel_noise=noise_pixel(img))
        (b,) = detect_frame(img, opt)
        assert "clutter" not in b.flags
        errs += [b.x - x0, b.y - y0]
        sig += [b.sigma, b.sigma]
        # measured alone, the step pulls the centroid by a large fraction of a px
        (b1,) = detect_frame(img, DetectOptions(diameter_px=(9.6, 25.6), blur_px=1.0, pixel_noise=opt.pixel_noise,
                                                joint_overlaps=False))
        assert "clutter" in b1.flags
    errs, sig = np.array(errs), np.array(sig)
    assert np.sqrt(np.mean(errs**2)) < 0.03
    assert np.sqrt(np.mean((errs / sig) ** 2)) < 2.0


def test_near_pairs_of_larger_spheres_keep_their_neighbour_out_of_the_window():
    """Shadows half a diameter apart: the centroid window used to reach the
    neighbour, the size swelled and the pair was lost (a quarter of them)."""
    rng = np.random.default_rng(11)
    sph = np.concatenate([_pairs(0.5, rng, R=R) for R in (6.3, 6.6)])
    sph[len(sph) // 2:, 0] += 320
    img = (render((320, 640), sph, 1.0) + 0.1 + rng.normal(0, 0.004, (320, 640))).astype(np.float32)
    blobs = detect_frame(img, DetectOptions(diameter_px=(7.2, 19.2), blur_px=1.0))
    assert len(blobs) == len(sph)
    err = [min(np.hypot(b.x - s[0], b.y - s[1]) for b in blobs) for s in sph]
    assert max(err) < 0.05


@pytest.mark.parametrize("dist", [0, 4, 8])
def test_a_sphere_at_the_foot_of_a_high_step_is_not_lost(dist):
    """A 0.5 step 0-8 px beside the shadow spoils its background: the shadow
    was dropped (misshapen, or no background at all); now the step is fitted
    and removed and the sphere measured."""
    import cv2

    rng = np.random.default_rng(dist)
    R, errs = 8.0, []
    for trial in range(4):
        x0, y0 = 100.3 + rng.uniform(-0.5, 0.5), 100.6 + rng.uniform(-0.5, 0.5)
        img = np.full((200, 200), 0.1, np.float32)
        img[:, int(x0 + R + dist):] += 0.5
        img = cv2.GaussianBlur(img, (0, 0), 1.0) + render((200, 200), np.array([[x0, y0, R, 0.05]]), 1.0)
        img = (img + rng.normal(0, 0.004, img.shape)).astype(np.float32)
        blobs = detect_frame(img, DetectOptions(diameter_px=(9.6, 25.6), blur_px=1.0))
        assert len(blobs) == 1 and "clutter" not in blobs[0].flags
        errs.append(np.hypot(blobs[0].x - x0, blobs[0].y - y0))
    assert max(errs) < 0.05


def test_a_sphere_beside_a_tube_wall_is_measured_with_the_wall_removed():
    """A hollow tube seen side-on: its wall's chord 2(sqrt(Ro^2-u^2) - sqrt(Ri^2-u^2))
    peaks in a cusp at the inner radius, a ridge (not a step) running at a
    slant beside the shadow. Measured alone the centroid is pulled by a large
    fraction of a pixel and flagged; with the wall's profile fitted it is not."""
    import cv2

    from conecal.detect.noise import noise_pixel

    rng = np.random.default_rng(8)
    R, errs, sig, pulled = 6.0, [], [], []
    yy, xx = np.mgrid[0:160, 0:160].astype(float)
    for trial in range(6):
        x0, y0 = 80.3 + rng.uniform(-0.5, 0.5), 80.6 + rng.uniform(-0.5, 0.5)
        ang = rng.uniform(0.3, 1.2)
        u = (xx - 80) * np.cos(ang) + (yy - 80) * np.sin(ang) + 100 + R + 3 + trial
        Ro, Ri = 150.0, 100.0
        wall = 2 * (np.sqrt(np.maximum(Ro**2 - u**2, 0)) - np.sqrt(np.maximum(Ri**2 - u**2, 0))) * 0.004
        img = cv2.GaussianBlur(wall.astype(np.float32), (0, 0), 1.0) + render((160, 160), np.array([[x0, y0, R, 0.05]]), 1.0)
        img = (img + rng.normal(0, 0.004, img.shape)).astype(np.float32)
        opt = DetectOptions(diameter_px=(8.0, 16.0), blur_px=1.0, pixel_noise=noise_pixel(img))
        (b,) = [b for b in detect_frame(img, opt) if np.hypot(b.x - x0, b.y - y0) < R]
        errs += [b.x - x0, b.y - y0]
        sig += [b.sigma, b.sigma]
        alone = [b for b in detect_frame(img, DetectOptions(diameter_px=(8.0, 16.0), blur_px=1.0,
                                                            pixel_noise=opt.pixel_noise, joint_overlaps=False))
                 if np.hypot(b.x - x0, b.y - y0) < R]
        pulled += [np.hypot(alone[0].x - x0, alone[0].y - y0) if alone else np.inf]
    errs, sig = np.array(errs), np.array(sig)
    assert np.median(pulled) > 0.2
    assert np.sqrt(np.mean(errs**2)) < 0.05
    assert np.sqrt(np.mean((errs / sig) ** 2)) < 2.0


def test_a_cluster_of_three_and_a_pair_nearly_on_top_of_each_other_are_split():
    rng = np.random.default_rng(5)
    R, mu = 5.0, 0.05
    sph = [[70 + 6 * np.cos(t), 70 + 6 * np.sin(t), R, mu] for t in (0.3, 2.4, 4.5)]   # a triangle, 50 % overlaps
    sph += [[190.0, 80.0, R, mu], [192.4, 82.1, R, mu]]                              # 70 % overlap
    sph += [[x, y, R, mu] for x, y in ((60, 200), (190, 200), (120, 130), (220, 150))]  # the frame's spheres alone
    sph = np.array(sph)
    img = (render((260, 260), sph, 1.0) + 0.1 + rng.normal(0, 0.003, (260, 260))).astype(np.float32)
    blobs = detect_frame(img, DetectOptions(diameter_px=(8.0, 12.0), blur_px=1.0))
    assert len(blobs) == len(sph)
    for s in sph[:5]:
        b = min(blobs, key=lambda b: np.hypot(b.x - s[0], b.y - s[1]))
        assert np.hypot(b.x - s[0], b.y - s[1]) < 0.3
        assert "overlap" in b.flags


def _on_a_wall(seed, spacing, R=5.0, amp=1.0):
    """A tube's wall seen end-on (an annulus of attenuation ``amp``, twice the
    spheres' peak, its edges blurred) with a chain of spheres 4 px inside its
    inner edge, ``spacing`` px apart along it."""
    import cv2

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:320, 0:320].astype(float)
    cx, cy, Ri, Ro = 160.0, 360.0, 190.0, 226.0
    r = np.hypot(xx - cx, yy - cy)
    wall = cv2.GaussianBlur(((r > Ri) & (r < Ro)).astype(np.float32) * amp, (0, 0), 1.2)
    rm = Ri + R + 4 + rng.uniform(-1, 1)
    t0 = -np.pi / 2 - 4 * spacing / rm
    sph = np.array([[cx + rm * np.cos(t0 + k * spacing / rm) + rng.uniform(-.5, .5),
                     cy + rm * np.sin(t0 + k * spacing / rm) + rng.uniform(-.5, .5), R, 0.05] for k in range(9)])
    img = (wall + render((320, 320), sph, 1.0) + 0.05 + rng.normal(0, 0.004, (320, 320))).astype(np.float32)
    return img, sph


@pytest.mark.parametrize("spacing, rms_max", [(24.0, 0.1), (15.0, 0.25)])
def test_a_chain_of_spheres_at_a_high_wall_edge_is_found(spacing, rms_max):
    """Separate spheres (2.4 diameters apart) and near ones (1.5) just inside a
    wall's edge twice their height: measured with the edge's profile removed
    (a plane or quadratic under the chain swells a sphere to follow the wall;
    before, 10 and 0 of 36 were found, and near ones 2 px off with sigma 0.1)."""
    from conecal.detect.noise import noise_pixel

    found, err, pull, false = 0, [], [], 0
    for seed in (0, 1):
        img, sph = _on_a_wall(seed, spacing)
        blobs = detect_frame(img, DetectOptions(diameter_px=(8.0, 12.0), blur_px=1.0, pixel_noise=noise_pixel(img)))
        for s in sph:
            b = min(blobs, key=lambda b: np.hypot(b.x - s[0], b.y - s[1]))
            if np.hypot(b.x - s[0], b.y - s[1]) < 2.5:
                found += 1
                err += [b.x - s[0], b.y - s[1]]
                pull += [(b.x - s[0]) / b.sigma, (b.y - s[1]) / b.sigma]
        false += sum(min(np.hypot(b.x - s[0], b.y - s[1]) for s in sph) > 2.5 for b in blobs)
    assert found >= 16 and false == 0
    assert np.sqrt(np.mean(np.square(err))) < rms_max
    assert np.std(pull) < 2.0


def _stretched_scene(seed, pair):
    """Eight round shadows (R 9 px) around one at the centre that is either
    one sphere's shadow stretched by 1.3 along a random direction (an image
    intensifier's periphery) or two shadows 0.45 R apart (a deep pair)."""
    import cv2

    rng = np.random.default_rng(seed)
    n, R = 300, 9.0
    sph = [[x + rng.uniform(-0.5, 0.5), y + rng.uniform(-0.5, 0.5), R, 0.07]
           for x in (60, 150, 240) for y in (60, 150, 240) if (x, y) != (150, 150)]
    img = render((n, n), np.array(sph), 1.0)
    x0, y0 = 150.2 + rng.uniform(-0.5, 0.5), 150.4 + rng.uniform(-0.5, 0.5)
    ang = rng.uniform(0, np.pi)
    c, s = np.cos(ang), np.sin(ang)
    if pair:
        d = 0.45 * R / 2
        img = img + render((n, n), np.array([[x0 - d * c, y0 - d * s, R, 0.07], [x0 + d * c, y0 + d * s, R, 0.07]]), 1.0)
    else:
        A = np.array([[c, -s], [s, c]]) @ np.diag([1.3, 1.0]) @ np.array([[c, s], [-s, c]])
        M = np.hstack([A, (np.array([x0, y0]) - A @ [x0, y0])[:, None]])
        one = render((n, n), np.array([[x0, y0, R, 0.07]]), 1.0).astype(np.float32)
        img = img + cv2.warpAffine(one, M, (n, n), flags=cv2.INTER_LINEAR)
    return (img + 0.2 + rng.normal(0, 0.01, (n, n))).astype(np.float32), x0, y0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_stretched_shadow_is_one_sphere_and_a_deep_pair_is_two(seed):
    """Anisotropy 1.3 used to send a lone shadow to the merged blobs, where no
    split was had and it was dropped (a real C-arm's periphery lost a sphere
    so); it holds one sphere's attenuation, so it is kept. A deep pair that
    elongated holds two spheres' and is still split."""
    opt = DetectOptions(diameter_px=(9.0, 24.0), blur_px=1.0)
    img, x0, y0 = _stretched_scene(seed, pair=False)
    blobs = detect_frame(img, opt)
    assert len(blobs) == 9
    (b,) = [b for b in blobs if np.hypot(b.x - x0, b.y - y0) < 6]
    assert np.hypot(b.x - x0, b.y - y0) < 0.05 and b.anisotropy > opt.max_anisotropy
    img, x0, y0 = _stretched_scene(seed, pair=True)
    near = [b for b in detect_frame(img, opt) if np.hypot(b.x - x0, b.y - y0) < 6]
    assert len(near) == 2 and all(np.hypot(b.x - x0, b.y - y0) > 1.5 for b in near)


def test_weak_mottle_beside_spheres_is_not_measured_as_a_crowd(monkeypatch):
    """Weak bumps 14 px apart (an intensifier's blot: 0.1-0.3 of a sphere's
    peak) used to chain into a group of seeds, each fitted jointly and
    dropped (a real 1024² frame took 10 s so). Only peaks as strong as half
    the frame's lone spheres' are seeds now."""
    import conecal.detect.crowded as crowded

    calls = []
    fit = crowded.fit_group
    monkeypatch.setattr(crowded, "fit_group", lambda *a, **k: calls.append(1) or fit(*a, **k))
    rng = np.random.default_rng(0)
    n = 300
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32)
    sph = np.array([[x + rng.uniform(-0.5, 0.5), y + rng.uniform(-0.5, 0.5), 9.0, 0.07]
                    for x in (50, 130) for y in (50, 130, 250)])
    img = 0.3 + render((n, n), sph, 1.0)
    for k in range(9):
        bx, by = 220 + 14 * (k % 3) + rng.uniform(-2, 2), 190 + 14 * (k // 3) + rng.uniform(-2, 2)
        img += 0.2 * np.exp(-((xx - bx) ** 2 + (yy - by) ** 2) / (2 * 4.0**2))
    img = (img + rng.normal(0, 0.01, (n, n))).astype(np.float32)
    blobs = detect_frame(img, DetectOptions(diameter_px=(8.7, 23.2), blur_px=1.0))
    for s in sph:
        assert min(np.hypot(b.x - s[0], b.y - s[1]) for b in blobs) < 0.05
    assert calls == []


def test_weak_peaks_chain_into_seeds_only_through_shadows_or_strong_peaks():
    """Crowd seeds: unaccounted peaks within touching reach (here 20.5 px) of
    a shadow measured alone, or of a peak linked to one; a link between two
    weak peaks carries nothing (a spine's edges raised a 34-member group)."""
    from conecal.detect.seeds import crowd_seeds as _crowd_seeds
    from conecal.detect.options import Blob

    opt = DetectOptions(diameter_px=(7.2, 19.2), blur_px=1.0)
    kept = [Blob(0.0, 0.0, 5.0, 0.05, 0.05, 1.0, 1.0, [], 50.0)]
    chain = [(15.0, 0.0), (30.0, 0.0), (45.0, 0.0)]
    assert _crowd_seeds(chain, kept, 5.0, opt, strong=[]) == [(15.0, 0.0)]
    assert _crowd_seeds(chain, kept, 5.0, opt, strong=[(30.0, 0.0)]) == chain
    assert _crowd_seeds(chain, kept, 5.0, opt) == chain                 # every peak strong
    assert _crowd_seeds(chain[1:], kept, 5.0, opt, strong=[]) == []     # weak and away from any shadow


@pytest.mark.parametrize("seed", [0, 1])
def test_a_larger_ball_with_a_flattened_core_is_measured(seed):
    """A box phantom's big ball (R 17.5 px among 9.5 px ones, beyond the
    nominal size) whose core an 8-bit display flattens: the background ring
    of the nominal size lay inside it, nothing was left above it, and the
    ball was lost (a real recording lost 2 of 162 so); its flat top also
    reads as a ridge, and as a merged blob it has four times its neighbours'
    attenuation. Both ways it is now one sphere, and nothing else is found."""
    rng = np.random.default_rng(seed)
    n = 320
    small = [[x + rng.uniform(-0.5, 0.5), y + rng.uniform(-0.5, 0.5), 9.5, 0.1]
             for x in (50, 160, 270) for y in (50, 160, 270) if (x, y) != (160, 160)]
    x0, y0 = 160.3 + rng.uniform(-0.5, 0.5), 159.6 + rng.uniform(-0.5, 0.5)
    img = render((n, n), np.array(small + [[x0, y0, 17.5, 0.1]]), 1.0)
    img = np.minimum(img, 2.0) + 0.2 + rng.normal(0, 0.005, (n, n))
    blobs = detect_frame(img.astype(np.float32), DetectOptions(diameter_px=(8.3, 22.2), blur_px=1.0))
    assert len(blobs) == 9
    (b,) = [b for b in blobs if np.hypot(b.x - x0, b.y - y0) < 6]
    assert np.hypot(b.x - x0, b.y - y0) < 0.1 and 16 < b.radius < 19


def test_a_round_merged_blob_of_the_neighbours_material_is_one_larger_sphere():
    """A big ball's flat top can read as a ridge, and its blob is then set
    aside as merged: round and with its neighbours' attenuation per px of
    chord, it is one (larger) sphere; twice that (two spheres on one line of
    sight) or elongated, it is not."""
    from conecal.detect.crowded import _one_sphere
    from conecal.detect.options import Blob

    lone = [Blob(100.0 * k, 0.0, 9.5, 0.01, 0.11, 2.0, 1.02, [], 300.0, 0.1) for k in range(4)]

    def big(mu, aniso):
        return Blob(150.0, 0.0, 17.7, 0.02, mu, 3.9, aniso, ["clutter"], 66.0, 0.18)

    assert _one_sphere(big(0.072, 1.02), lone)
    assert not _one_sphere(big(0.22, 1.02), lone)
    assert not _one_sphere(big(0.072, 1.3), lone)


def test_a_chain_is_started_evenly_along_its_long_axis():
    from conecal.detect.options import Blob
    from conecal.detect.split import _axis_chain
    for sph in (np.array([[30.0, 27.0, 5.0, 0.05], [36.0, 31.0, 5.0, 0.05]]),
                np.array([[24.0, 23.0, 5.0, 0.05], [30.0, 27.0, 5.0, 0.05], [36.0, 31.0, 5.0, 0.05]])):
        img = render((60, 64), sph, 1.0) + 0.2
        m = Blob(30.0, 27.0, 7.0, 0.1, 0.05, 0.5, 1.5, [], 30.0)
        starts = _axis_chain(img, (0, 0, 64, 60), np.array([0.2, 0.0, 0.0]), False, np.ones((60, 64)), m, 5.0,
                             0.05, len(sph))
        got = sorted(map(tuple, starts[:, :2]))
        assert np.allclose(got, sorted(map(tuple, sph[:, :2])), atol=0.6), got


def test_helix_spheres_on_a_tube_wall_and_a_pair_beside_its_end_are_found_once(helix):
    # an independent generator's frames (benchmarks/helix_indep.py): lone spheres on
    # the tube's curved wall (plane-fitted anisotropy 1.6-1.7), a pair overlapping by
    # 0.4 of a diameter whose split had soaked up the wall, lost before
    truth = helix.scan(0)[1]
    for k, ids in ((3, (11, 49)), (0, (26, 45))):
        blobs = helix.detect(0, k)
        for t in truth[k]:
            near = [b for b in blobs if np.hypot(b.x - t["x"], b.y - t["y"]) < 0.5 * t["r_px"]]
            assert len(near) <= 1, (k, t["id"], near)      # no sphere given twice
            if t["id"] in ids:
                b = near[0] if near else None
                assert b is not None and b.sigma < 0.3 and np.hypot(b.x - t["x"], b.y - t["y"]) < 3 * b.sigma, (k, t["id"], b)


def test_lone_spheres_where_a_tubes_walls_cross_are_measured_with_the_walls_removed(helix):
    # the independent helix (benchmarks/helix_indep.py), seed 2, frame 0: three
    # steel spheres 2-3 diameters from any other, on the tube's walls seen at a
    # slant (the background a curved ramp and a second edge across it). The
    # centroid on the cleaned patch stays elongated (1.26-1.3) and the sphere
    # model misfits its disc 1.2-1.5x the patch around it: all three were lost
    blobs, truth = helix.detect(2, 0), helix.scan(2)[1][0]
    for t in truth:
        if t["id"] in (20, 28, 40):
            b = helix.found_once(blobs, t)
            assert b.sigma < 0.3 and np.hypot(b.x - t["x"], b.y - t["y"]) < 3 * b.sigma, (t["id"], b)


def test_three_touching_spheres_on_a_tubes_wall_are_split(helix):
    # the independent helix, seed 2, frame 1: three spheres overlapping by a fifth
    # of a diameter inside the tube's wall seen end-on. Measured alone their blob
    # took in the wall and read 6.7 spheres' attenuation, over the split's bound
    blobs, truth = helix.detect(2, 1), helix.scan(2)[1]   # (the scan's shadow sizes)
    for t in truth[1]:
        if t["id"] in (5, 21, 37):
            b = helix.found_once(blobs, t)
            assert np.hypot(b.x - t["x"], b.y - t["y"]) < 0.3, (t["id"], b)



def test_two_helix_spheres_in_one_round_shadow_are_never_one_confident_centre(helix):
    # the independent helix, seed 2: two pairs 0.3-0.4 of a diameter apart on the
    # tube (frames 3 and 6) make one round shadow (anisotropy 1.05-1.16) that no
    # split separates, 1.4x denser than the spheres on the same background. The
    # marker between them was one centre at sigma 0.045 px, 0.8-1.5 px from either
    truth = helix.scan(2)[1]
    for k, (i, j) in ((3, (11, 12)), (6, (0, 1))):
        p, q = [next(t for t in truth[k] if t["id"] == n) for n in (i, j)]
        for b in helix.detect(2, k):
            e = min(np.hypot(b.x - p["x"], b.y - p["y"]), np.hypot(b.x - q["x"], b.y - q["y"]))
            if e < 0.5 * p["r_px"]:
                assert e < 3 * b.sigma, (k, e, b)



def test_spheres_hidden_in_one_shadow_are_fitted_as_two_or_three(helix):
    # the independent helix: two pairs 0.3-0.4 of a diameter apart on the tube
    # (seed 2, frames 3 and 6), one 0.8 apart (seed 3, frame 0) and a chain of
    # three overlapping by a fifth of a diameter (seed 3, frame 1). Each was one
    # marker between them whose σ (1.2-5 px) covered them; one sphere misfits
    # its disc 4-8x the patch around it, two or three fit it to the noise. And
    # three where a third sphere's marker was pressed against the pair (seed 2
    # frame 5, seed 3 frames 1 and 5), 1.1-2.5 px off at σ 1.3-3.2: fitted
    # again with the pair
    for seed, k, ids in ((2, 3, (11, 12)), (2, 6, (0, 1)), (3, 0, (16, 17)), (3, 1, (17, 33, 49)),
                         (2, 5, (10, 26, 42)), (3, 1, (15, 31, 47)), (3, 5, (17, 33, 49))):
        blobs, got = helix.detect(seed, k), set()
        for t in helix.scan(seed)[1][k]:
            if t["id"] in ids:
                i = int(np.argmin([np.hypot(b.x - t["x"], b.y - t["y"]) for b in blobs]))
                b, e = blobs[i], np.hypot(blobs[i].x - t["x"], blobs[i].y - t["y"])
                assert e < 0.5 and e < 3 * b.sigma and "overlap" in b.flags, (seed, k, t["id"], e, b)
                got.add(i)
        assert len(got) == len(ids), (seed, k)     # one marker each


def test_chains_of_three_across_a_tubes_wall_seen_end_on_are_split(helix):
    # the independent helix, seed 2, frame 1 (along the helix's axis): two chains
    # of three touching spheres lie across the tube's wall seen end-on. No window
    # had a background (the wall's band through it: a negative second moment),
    # so no candidate was measured and all six were lost
    blobs, truth = helix.detect(2, 1), helix.scan(2)[1]
    for t in truth[1]:
        if t["id"] in (2, 18, 34, 4, 20, 36):
            b = helix.found_once(blobs, t)
            assert np.hypot(b.x - t["x"], b.y - t["y"]) < max(0.7, 3 * b.sigma), (t["id"], b)


def test_two_small_spheres_half_overlapped_are_never_one_confident_centre(helix):
    # the independent helix, seed 3, frame 1, the nominal size 25 % small: two
    # 0.9 mm spheres overlapping by half a diameter hold one 1.2 mm sphere's
    # attenuation, so no density test sees them; measured as one (anisotropy
    # 1.42) the marker lay 2.3 px from either at sigma 0.5 px
    from conecal.detect import DetectOptions, detect_frame
    from conecal.detect.noise import noise_correlation, noise_pixel
    r = [t["r_px"] for s in (2, 3) for fr in helix.scan(s)[1] for t in fr]
    img = np.ascontiguousarray(helix.scan(3)[0][1], np.float32)
    opt = DetectOptions(diameter_px=(2 * min(r) * 0.9 * 0.75, 2 * max(r) * 1.1 * 0.75), pixel_noise=noise_pixel(img),
                        noise_kappa=noise_correlation(img))
    truth = {t["id"]: t for t in helix.scan(3)[1][1]}
    p, q = truth[9], truth[42]
    near = [b for b in detect_frame(img, opt) if np.hypot(b.x - (p["x"] + q["x"]) / 2, b.y - (p["y"] + q["y"]) / 2) < 4]
    assert near
    for b in near:
        e = min(np.hypot(b.x - t["x"], b.y - t["y"]) for t in (p, q))
        assert e < 3 * b.sigma, (e, b)


def test_overlapping_balls_on_a_log_display_are_fitted_as_two_or_three():
    # an independent renderer's ball phantom (benchmarks/carm_images.py, ball3d_ii, seed 1,
    # frame 1): a chain of three and a pair overlapping by about half a diameter, on an
    # 8-bit log display that deepens their overlap beyond a sum of spheres. No split
    # fitted them to the noise, so all five were lost; fitted as two or three with σ
    # for the misfit they leave, each is found. Measured as `conecal detect` measures
    # this scan, in the response it finds there (options.response_lambda 0.91), where
    # the display's floor clips the cores at one level: weighed as measurements, the
    # clipped cores left ball 1 3.9 px from its marker (σ 0.58) and ball 15 1.6 px
    from benchmarks import carm_images as gen
    from conecal.detect.gain import linearised
    from conecal.detect.noise import noise_correlation, noise_pixel

    sc = gen._setup("ball3d_ii", 1)

    def att(k):
        a = -np.log(np.maximum(gen.render_frame(sc, k)[0].astype(np.float64) / 255.0, 1e-6))
        return linearised(a.astype(np.float32), 0.91)

    a, mid = att(1), att(6)
    opt = DetectOptions(diameter_px=(6.3, 16.8), pixel_noise=noise_pixel(mid), noise_kappa=noise_correlation(mid))
    blobs = detect_frame(a, opt)
    got = set()
    for c in gen.render_frame(sc, 1)[1]:
        if c["id"] in (0, 1, 15, 12, 16):
            i = int(np.argmin([np.hypot(b.x - c["x"], b.y - c["y"]) for b in blobs]))
            e = np.hypot(blobs[i].x - c["x"], blobs[i].y - c["y"])
            assert e < 0.3 and e < 3 * blobs[i].sigma, (c["id"], e, blobs[i])
            got.add(i)
    assert len(got) == 5


def test_two_balls_nearly_on_top_under_a_clipped_core_are_never_one_confident_centre():
    # the same scan, frame 10, with the options `conecal detect` records for it:
    # balls 0 and 15 lie 1.7 px apart, ball 1 3.4 px from them, every core
    # clipped at the display's floor. The joint fit gives ball 1 its own centre
    # and balls 0 and 15 one part 1.4x as dense as a ball, 0.6 and 1.1 px from
    # them, which stood at σ 0.14. A part denser than any one sphere may hide a
    # second: its σ covers it
    from benchmarks import carm_images as gen
    from conecal.detect.gain import linearised

    sc = gen._setup("ball3d_ii", 1)
    a = -np.log(np.maximum(gen.render_frame(sc, 10)[0].astype(np.float64) / 255.0, 1e-6))
    opt = DetectOptions(diameter_px=(7.549, 20.131), pixel_noise=0.0078, noise_kappa=1.3623, max_anisotropy=1.25)
    blobs = detect_frame(linearised(a.astype(np.float32), 0.91), opt)
    for c in gen.render_frame(sc, 10)[1]:
        if c["id"] in (0, 1, 15):
            b = min(blobs, key=lambda b: np.hypot(b.x - c["x"], b.y - c["y"]))
            e = np.hypot(b.x - c["x"], b.y - c["y"])
            assert e < max(0.3, 3 * b.sigma) and "overlap" in b.flags, (c["id"], e, b)


def test_a_seed_left_out_keeps_the_fit_the_try_without_it_had(monkeypatch):
    """A large sphere with a small one touching it, measured with a seed in
    the bare background: the group's joint fit fails, the try without the
    seed fits. That try is the group's fit; refitting the same members on
    their own smaller patch could fail where the try held, and both spheres
    were lost (an independent cage phantom's 4 mm bead and a 2 mm one beside
    it, benchmarks/RESULTS.md, session 36). Here the smaller patch's refit is
    made to fail: the two spheres must still be measured from the try."""
    from conecal.detect import crowded
    from conecal.detect.options import Blob

    rng = np.random.default_rng(5)
    big, small = [80.3, 80.6, 7.8, 0.04], [74.6, 70.9, 3.6, 0.04]
    lone = [[20.2, 20.4, 3.6, 0.04], [140.7, 20.1, 3.6, 0.04], [20.5, 140.3, 3.6, 0.04]]   # the frame's typical sphere
    img = (render((160, 160), np.array([big, small, *lone]), 1.0) + 0.1 + rng.normal(0, 0.002, (160, 160)))
    img = img.astype(np.float32)
    real = crowded.fit_group
    calls = []

    def fit_group(a, spheres, *args, box=None, **kw):
        calls.append((len(spheres), box is None))
        if box is None and len(spheres) == 2:
            return None     # the reduced group on its own patch
        return real(a, spheres, *args, box=box, **kw)

    monkeypatch.setattr(crowded, "fit_group", fit_group)
    from conecal.detect import split as split_module
    monkeypatch.setattr(split_module, "split", lambda *a, **k: None)   # (the blob is no split's)
    opt = DetectOptions(diameter_px=(5.0, 18.0), blur_px=1.0, shadow_px=(7.2, 15.6))   # two sizes declared
    blob = Blob(80.0, 79.0, 9.0, 0.0, 0.03, 0.0, 1.4, ["clutter"], 0.6)
    seeds = [(74.0, 71.0), (88.0, 95.0)]
    alone = [Blob(x, y, R, 0.01, mu, 0.0, 1.0, [], 50.0) for x, y, R, mu in lone]
    out = crowded.measure_crowded(img, [blob, *alone], [blob], opt, 0.002, None, seeds, seeds)
    assert (3, True) in calls and (2, False) in calls        # the seed sank the fit; the try without it held
    for s in (big, small):
        b = min(out, key=lambda b: np.hypot(b.x - s[0], b.y - s[1]))
        assert np.hypot(b.x - s[0], b.y - s[1]) < 0.3, (s, [(o.x, o.y) for o in out])
