"""detect on frames of the independent helix (benchmarks/helix_indep.py)
where spheres lie on or across the plastic tube's walls: each case below
was lost before the change its comment names."""

import numpy as np
import pytest


def _detect(helix, seed, k):
    """(blobs, truth) of frame ``k`` of ``seed``, sized as ``bench_helix.py
    --seeds 2 3`` sizes it (the conftest's helix fixture)."""
    return helix.detect(seed, k, sized_by=(2, 3)), helix.scan(seed)[1][k]


def _honest(helix, blobs, truth, ids, bound=3.0):
    """Each sphere of ``ids`` found exactly once, within ``bound`` of its sigma."""
    for t in truth:
        if t["id"] in ids:
            b = helix.found_once(blobs, t)
            assert np.hypot(b.x - t["x"], b.y - t["y"]) < bound * b.sigma, (t["id"], b)


# (seed, frame, the spheres that were lost): one case per way a sphere was lost
_CASES = [
    # a lone sphere on the wall, measured alone (anisotropy 1.47, one sphere's
    # attenuation), and a rough blob of the wall around it split into it and a
    # neighbour; the part took its place and the joint fit lost it
    pytest.param(2, 3, (37,), id="a_sphere_measured_alone_outranks_a_split_part_there"),
    # three spheres in a row on a wall and a seed on the wall's edge beside them;
    # the four did not fit together, and the first seed whose removal let the fit
    # converge was the middle sphere
    pytest.param(2, 5, (28,), id="a_failing_crowd_fit_drops_the_seed_it_fits_best_without"),
    # three stacked spheres across the wall; their ridge's window came out with a
    # negative second moment (anisotropy inf) and was dropped
    pytest.param(3, 1, (15, 47), id="a_ridge_whose_window_has_no_shape_is_split_as_a_rough_blob"),
    # a sphere beside a pair 0.3 of a diameter apart on the wall; the third part
    # took 75 % of the misfit and brought the pair's part (1.36x the frame's
    # contrast) back to it, which was accepted only for one-part blobs
    pytest.param(2, 6, (32, 33, 34), id="a_pair_inside_a_chain_is_split_when_its_parts_regain_the_contrast"),
    # the end of a chain of five along the wall, whose fit with its three nearest
    # neighbours diverged
    pytest.param(2, 6, (15,), id="a_chain_member_whose_local_fit_fails_is_measured_with_fewer_neighbours"),
    # the sphere model on the cleaned patch misfits its disc 1.53x the patch
    # around it (4.09 against 2.67), just over the bar of 1.5x
    pytest.param(3, 6, (36,), id="a_lone_sphere_on_a_walls_edge_is_measured_by_its_model"),
    # along the helix's axis: two small spheres beside a large one, in a line. The
    # split's second part covered both (radius 1.46x, half the contrast) and its
    # third started at the residual's peak on the wall
    pytest.param(2, 1, (3, 19, 35), id="a_part_as_wide_as_two_spheres_of_a_chain_is_started_as_two"),
]


@pytest.mark.parametrize("seed, k, ids", _CASES)
def test_spheres_on_a_tubes_wall_are_found_once_within_their_sigma(helix, seed, k, ids):
    blobs, truth = _detect(helix, seed, k)
    _honest(helix, blobs, truth, ids)
