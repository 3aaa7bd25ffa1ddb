"""The distortion choice's paired held-out test counts frames, not markers."""

from __future__ import annotations

import numpy as np

from conecal.stats import mostly_behind, not_worse, paired_behind


def test_a_gain_one_frame_makes_is_no_gain_for_the_detector():
    rng = np.random.default_rng(2)
    frames = np.repeat(np.arange(24), 30)
    # the simpler family's held-out chi-square per marker: as good as the
    # flexible one's everywhere but in one frame, where it is far worse (a
    # wrong labelling the flexible family's own term absorbs)
    flexible = rng.chisquare(2, frames.size)
    simple = flexible + rng.normal(0, 0.3, frames.size)
    simple[frames == 5] += 40.0
    # marker by marker, the flexible family wins by many standard errors ...
    assert not not_worse(*paired_behind(simple, flexible))
    # ... frame by frame, one frame is no evidence about the detector
    assert not_worse(*paired_behind(simple, flexible, frames))
    assert not mostly_behind(simple, flexible, frames)
    # a gain every frame shares still counts
    shared = flexible + 1.0 + rng.normal(0, 0.3, frames.size)
    assert not not_worse(*paired_behind(shared, flexible, frames))


def test_a_gain_every_frame_shares_counts_though_two_frames_hold_most_of_it():
    # (the third renderer's cage: the shared S trailed the per-frame S in 17
    # of 18 frames, by 1150 and 658 in the two most twisted, 0-200 elsewhere)
    rng = np.random.default_rng(3)
    frames = np.repeat(np.arange(18), 25)
    flexible = rng.chisquare(2, frames.size)
    simple = flexible + rng.uniform(0.2, 2.0, frames.size)
    simple[frames == 4] += 46.0
    simple[frames == 17] += 26.0
    # the clusters' standard error, made of those two, cannot tell ...
    assert not_worse(*paired_behind(simple, flexible, frames))
    # ... that nearly every frame is better fitted by the flexible family
    assert mostly_behind(simple, flexible, frames)
    # half the frames better, half worse: no evidence either way
    mixed = flexible + np.where(frames % 2 == 0, 1.0, -1.0)
    assert not mostly_behind(mixed, flexible, frames)
