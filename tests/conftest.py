import numpy as np
import pytest

from conecal.geometry import ConeGeometry, rotvec_to_matrix


def random_geometry(rng, shape=(300, 400)) -> ConeGeometry:
    g = ConeGeometry.nominal(sod=rng.uniform(80, 300), sdd=rng.uniform(600, 1200), shape=shape,
                             pixel_pitch=(rng.uniform(0.1, 0.4), rng.uniform(0.1, 0.4)))
    R = rotvec_to_matrix(rng.normal(0, 0.05, 3))
    return g.replace(source=g.source + rng.normal(0, 2, 3), detector_origin=g.detector_origin + rng.normal(0, 5, 3),
                     u=R @ g.u, v=R @ g.v)


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
