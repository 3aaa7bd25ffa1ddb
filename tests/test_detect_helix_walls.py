"""detect on frames of the independent helix (benchmarks/helix_indep.py)
where spheres lie on or across the plastic tube's walls: each case below
was lost before the change its comment names."""

import numpy as np


def _detect(helix, seed, k):
    """(blobs, truth) of frame ``k`` of ``seed``, sized as ``bench_helix.py
    --seeds 2 3`` sizes it (the conftest's helix fixture)."""
    return helix.detect(seed, k, sized_by=(2, 3)), helix.scan(seed)[1][k]


def _honest(blobs, truth, ids, bound=3.0):
    """Each sphere of ``ids`` found exactly once, within ``bound`` of its sigma."""
    for t in truth:
        if t["id"] in ids:
            near = [b for b in blobs if np.hypot(b.x - t["x"], b.y - t["y"]) < 0.5 * t["r_px"]]
            assert len(near) == 1, (t["id"], near)
            b = near[0]
            assert np.hypot(b.x - t["x"], b.y - t["y"]) < bound * b.sigma, (t["id"], b)


def test_a_lone_sphere_on_a_wall_measured_alone_outranks_a_split_part_there(helix):
    # seed 2 frame 3: a lone sphere on the wall, measured alone (anisotropy 1.47,
    # one sphere's attenuation), and a rough blob of the wall around it split into
    # it and a neighbour; the part took its place and the joint fit lost it
    blobs, truth = _detect(helix, 2, 3)
    _honest(blobs, truth, (37,))


def test_a_failing_crowd_fit_drops_the_seed_it_fits_best_without(helix):
    # seed 2 frame 5: three spheres in a row on a wall and a seed on the wall's
    # edge beside them; the four did not fit together, and the first seed whose
    # removal let the fit converge was the middle sphere
    blobs, truth = _detect(helix, 2, 5)
    _honest(blobs, truth, (28,))


def test_a_ridge_whose_window_has_no_shape_is_split_as_a_rough_blob(helix):
    # seed 3 frame 1: three stacked spheres across the wall; their ridge's window
    # came out with a negative second moment (anisotropy inf) and was dropped
    blobs, truth = _detect(helix, 3, 1)
    _honest(blobs, truth, (15, 47))


def test_a_pair_inside_a_chain_is_split_when_the_parts_regain_the_spheres_contrast(helix):
    # seed 2 frame 6: a sphere beside a pair 0.3 of a diameter apart on the wall;
    # the third part took 75 % of the misfit and brought the pair's part (1.36x
    # the frame's contrast) back to it, which was accepted only for one-part blobs
    blobs, truth = _detect(helix, 2, 6)
    _honest(blobs, truth, (32, 33, 34))


def test_a_chain_member_whose_local_fit_fails_is_measured_with_fewer_neighbours(helix):
    # seed 2 frame 6: the end of a chain of five along the wall, whose fit with
    # its three nearest neighbours diverged
    blobs, truth = _detect(helix, 2, 6)
    _honest(blobs, truth, (15,))


def test_a_lone_sphere_on_a_walls_edge_is_measured_by_its_model(helix):
    # seed 3 frame 6: the sphere model on the cleaned patch misfits its disc 1.53x
    # the patch around it (4.09 against 2.67), just over the bar of 1.5x
    blobs, truth = _detect(helix, 3, 6)
    _honest(blobs, truth, (36,))


def test_a_part_as_wide_as_two_spheres_of_a_chain_is_started_as_two(helix):
    # seed 2 frame 1 (along the helix's axis): two small spheres beside a large
    # one, in a line. The split's second part covered both (radius 1.46x, half
    # the contrast) and its third started at the residual's peak on the wall
    blobs, truth = _detect(helix, 2, 1)
    _honest(blobs, truth, (3, 19, 35))
