import os

import numpy as np
import pytest

from conecal.geometry import ConeGeometry, rotvec_to_matrix


def random_geometry(rng, shape=(300, 400)) -> ConeGeometry:
    g = ConeGeometry.nominal(sod=rng.uniform(80, 300), sdd=rng.uniform(600, 1200), shape=shape,
                             pixel_pitch=(rng.uniform(0.1, 0.4), rng.uniform(0.1, 0.4)))
    R = rotvec_to_matrix(rng.normal(0, 0.05, 3))
    return g.replace(source=g.source + rng.normal(0, 2, 3), detector_origin=g.detector_origin + rng.normal(0, 5, 3),
                     u=R @ g.u, v=R @ g.v)


def pytest_configure(config):
    """Under pytest-xdist each of the machine's cores runs one worker: a
    worker's BLAS, OpenCV and numba pools would otherwise start a thread per
    core each, and the threads of two workers then spin against each other."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        import cv2
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=1)
        cv2.setNumThreads(1)
        try:
            import numba

            numba.set_num_threads(1)
        except (ImportError, ValueError):
            pass


# The files that take longest (about 80 % of the suite's time), longest first:
# pytest-xdist hands whole files (``--dist loadfile``) to its workers in
# collection order, so one of these started last ran minutes alone at the end.
_LONGEST_FIRST = ("test_free_pose.py", "test_diagnose.py", "test_detect_crowded.py", "test_detect_helix_walls.py",
                  "test_shards.py", "test_rpgrid.py", "test_diagnose_forms.py", "test_report_rtk.py",
                  "test_documents.py", "test_detect_size.py", "test_fit_pose.py", "test_detect_apart.py",
                  "test_fuzz_inputs.py", "test_trust_files.py", "test_free_partial.py", "test_free_neighbours.py")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(_LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture(scope="session")
def small_linear_scan(tmp_path_factory):
    """A tiny simulated linear raster (8 frames, 256x256 px, ~50 px spheres)."""
    from conecal.simulate import linear_raster, write_scan

    sc = linear_raster(3, rows=256, cols=256, counts=(2, 2, 2), steps=(4.0, 4.0, 8.0))
    return write_scan(sc, tmp_path_factory.mktemp("scans") / "linear", seed=3)


@pytest.fixture(scope="session")
def system(tmp_path_factory):
    """A linear raster and a rotation scan of one system (one true geometry), small and fast."""
    from conecal.simulate import linear_raster, rotation_scan, write_scan

    root = tmp_path_factory.mktemp("system")
    lin = linear_raster(11, rows=256, cols=256, counts=(3, 3, 2), steps=(3.0, 3.0, 8.0))
    rot = rotation_scan(11, rows=256, cols=256, sod=100.0, sdd=500.0, n_frames=24, n_spheres=4,
                        true_geometry=lin.geometry)
    return write_scan(lin, root / "lin", seed=1), write_scan(rot, root / "rot", seed=2)


class _Helix:
    """Frames of the independent helix (benchmarks/helix_indep.py: the first
    8 of a seed), generated once a session, and detect's blobs on them, each
    frame with each nominal size once (several tests look at one frame)."""

    def __init__(self):
        self._scans, self._found = {}, {}

    def scan(self, seed: int):
        """(frames, truth) of ``seed``'s first 8 frames."""
        if seed not in self._scans:
            from benchmarks import helix_indep as gen
            self._scans[seed] = gen.make_frames(seed, 8)
        return self._scans[seed]

    def detect(self, seed: int, k: int, sized_by=None):
        """Blobs of frame ``k`` of ``seed``, with the nominal shadow sizes the
        radii of seeds ``sized_by`` (default ``seed`` alone) span and the
        noise measured on the frame, as bench_helix.py does."""
        from conecal.detect import DetectOptions, detect_frame
        from conecal.detect.noise import noise_correlation, noise_pixel
        sized_by = tuple(sized_by or (seed,))
        if (seed, k, sized_by) not in self._found:
            r = [t["r_px"] for s in sized_by for fr in self.scan(s)[1] for t in fr]
            img = np.ascontiguousarray(self.scan(seed)[0][k], np.float32)
            opt = DetectOptions(diameter_px=(2 * min(r) * 0.9, 2 * max(r) * 1.1), pixel_noise=noise_pixel(img),
                                noise_kappa=noise_correlation(img))
            self._found[seed, k, sized_by] = detect_frame(img, opt)
        return self._found[seed, k, sized_by]

    @staticmethod
    def found_once(blobs, t: dict):
        """The one blob within half a radius of true sphere ``t`` (asserted)."""
        near = [b for b in blobs if np.hypot(b.x - t["x"], b.y - t["y"]) < 0.5 * t["r_px"]]
        assert len(near) == 1, (t["id"], near)
        return near[0]


@pytest.fixture(scope="session")
def helix():
    return _Helix()
