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
