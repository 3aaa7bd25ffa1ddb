"""Laws of the projection model: Jacobians, round trips, invariances."""

import numpy as np
import pytest

from conecal.geometry import (ConeGeometry, RigidTransform, matrix_to_rotvec, rotvec_to_matrix, shadow_centroid,
                              shadow_conic, shadow_ellipse)
from conecal.geometry.sphere import shadow_bias
from conecal.simulate.render import Sphere, render_line_integrals
from conftest import random_geometry


def test_nominal_follows_the_scan_format():
    g = ConeGeometry.nominal(sod=100, sdd=1000, shape=(512, 256), pixel_pitch=(0.2, 0.3))
    assert np.allclose(g.source, [0, 0, -100])
    assert np.allclose(g.project([0, 0, 0]), [127.5, 255.5])
    # +x runs along columns, +y along rows (downwards in the image)
    c, r = g.project([1.0, 2.0, 0.0])
    assert c == pytest.approx(127.5 + 10 / 0.2) and r == pytest.approx(255.5 + 20 / 0.3)
    assert np.allclose(g.principal_point, [127.5, 255.5])
    assert g.sdd == pytest.approx(1000)
    # the centre of img[0, 0] is pixel (0, 0)
    assert np.allclose(g.detector_point(0, 0), g.detector_origin)


def test_projection_lies_on_the_ray_and_the_detector(rng):
    g = random_geometry(rng)
    X = rng.normal(0, 10, (50, 3))
    cr = g.project(X)
    D = g.detector_point(cr[:, 0], cr[:, 1])
    # D in the detector plane and collinear with source and X
    assert np.allclose((D - g.detector_origin) @ g.normal, 0, atol=1e-9)
    assert np.allclose(np.cross(D - g.source, X - g.source), 0, atol=1e-6)


def test_point_jacobian_matches_finite_differences(rng):
    g = random_geometry(rng)
    X = rng.normal(0, 10, (20, 3))
    _, J = g.project_jacobian(X)
    h = 1e-6
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        fd = (g.project(X + e) - g.project(X - e)) / (2 * h)
        assert np.allclose(J[:, :, j], fd, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("at_zero", [True, False])
def test_geometry_jacobian_matches_finite_differences(rng, at_zero):
    base = random_geometry(rng)
    X = rng.normal(0, 10, (20, 3))
    delta0 = np.zeros(9) if at_zero else np.concatenate([rng.normal(0, 1, 6), rng.normal(0, 0.05, 3)])
    g = base.perturbed(delta0)
    J = g.geometry_jacobian(X, rotvec=delta0[6:9])
    h = 1e-6
    for j in range(9):
        e = np.zeros(9)
        e[j] = h
        fd = (base.perturbed(delta0 + e).project(X) - base.perturbed(delta0 - e).project(X)) / (2 * h)
        assert np.allclose(J[:, :, j], fd, rtol=1e-5, atol=1e-5), g.PARAMETERS[j]


def test_projection_matrix_round_trip(rng):
    for _ in range(10):
        g = random_geometry(rng)
        P = g.projection_matrix()
        X = rng.normal(0, 10, (10, 3))
        h = np.column_stack([X, np.ones(10)]) @ P.T
        assert np.allclose(h[:, :2] / h[:, 2:], g.project(X))
        assert np.all(h[:, 2] > 0)
        g2 = ConeGeometry.from_projection_matrix(7.3 * P, pixel_pitch=g.pixel_pitch, shape=g.shape)
        for a in ("source", "detector_origin", "u", "v"):
            assert np.allclose(getattr(g, a), getattr(g2, a), atol=1e-8)


def test_astra_and_dict_round_trips(rng):
    g = random_geometry(rng)
    vec = g.to_astra_vec()
    assert np.allclose(vec[3:6], g.detector_point((g.shape[1] - 1) / 2, (g.shape[0] - 1) / 2))
    g2 = ConeGeometry.from_astra_vec(vec, shape=g.shape)
    g3 = ConeGeometry.from_dict(g.to_dict())
    for h in (g2, g3):
        assert np.allclose(h.project([1.0, 2, 3]), g.project([1.0, 2, 3]))
        assert np.allclose(h.detector_origin, g.detector_origin)


def test_geometry_is_immutable_and_validated():
    g = ConeGeometry.nominal(sod=100, sdd=1000, shape=(10, 10), pixel_pitch=(1, 1))
    with pytest.raises(AttributeError):
        g.source = np.zeros(3)
    with pytest.raises(ValueError):
        g.source[0] = 1.0
    with pytest.raises(ValueError, match="pixel_pitch"):
        g.replace(pixel_pitch=(-1, 1))
    with pytest.raises(ValueError, match="parallel"):
        g.replace(v=g.u)


def test_rigid_transform_laws(rng):
    def rand():
        return RigidTransform(rotvec_to_matrix(rng.normal(0, 1, 3)), rng.normal(0, 5, 3))

    A, B, C = rand(), rand(), rand()
    p = rng.normal(0, 3, (7, 3))
    assert np.allclose(((A @ B) @ C).apply(p), (A @ (B @ C)).apply(p))
    assert np.allclose((A @ B).apply(p), A.apply(B.apply(p)))
    assert np.allclose((A @ B).inverse().matrix(), (B.inverse() @ A.inverse()).matrix())
    assert np.allclose((A @ A.inverse()).matrix(), np.eye(4))


def test_rotvec_round_trip(rng):
    for _ in range(20):
        w = rng.normal(0, 1, 3)
        w *= rng.uniform(0, 3.0) / np.linalg.norm(w)
        assert np.allclose(matrix_to_rotvec(rotvec_to_matrix(w)), w, atol=1e-8)


def test_transformed_geometry_projects_transformed_points(rng):
    g = random_geometry(rng)
    T = RigidTransform(rotvec_to_matrix(rng.normal(0, 0.5, 3)), rng.normal(0, 5, 3))
    X = rng.normal(0, 5, (5, 3))
    assert np.allclose(g.transformed(T).project(T.apply(X)), g.project(X))


def test_shadow_outline_is_the_tangent_cone(rng):
    g = random_geometry(rng)
    C = np.array([15.0, -10.0, 5.0])
    R = 1.5
    Q = shadow_conic(g, C, R)
    # rays tangent to the sphere: points on the sphere perpendicular to (C - S)
    d = C - g.source
    dist = np.linalg.norm(d)
    e1 = np.cross(d, [0, 0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d / dist, e1)
    for phi in np.linspace(0, 2 * np.pi, 7):
        # tangent point: at angle alpha off the axis
        sa = R / dist
        dirn = np.sqrt(1 - sa**2) * d / dist + sa * (np.cos(phi) * e1 + np.sin(phi) * e2)
        X = g.source + dirn * 10.0
        h = np.append(g.project(X), 1.0)
        assert abs(h @ Q @ h) / np.abs(Q).max() < 1e-9


def test_ellipse_centre_offset_follows_clackdoyle_mennessier():
    g = ConeGeometry.nominal(sod=100, sdd=1000, shape=(2048, 2048), pixel_pitch=(0.2, 0.2))
    C = np.array([12.0, 5.0, 0.0])
    ctr, axes, _ = shadow_ellipse(g, C, 1.0)
    proj = g.project(C)
    pp = g.principal_point
    e = np.linalg.norm(proj - pp) * 0.2                      # mm on the detector
    A = np.pi * axes[0] * axes[1] * 0.2 * 0.2                # mm^2
    bias = np.linalg.norm(ctr - proj) * 0.2
    # e * A / (pi * f^2): a length (the "/ (pi f)" drops a power of f)
    assert bias == pytest.approx(e * A / (np.pi * 1000**2), rel=0.02)
    # outward, along the line from the principal point
    assert np.dot(ctr - proj, proj - pp) > 0


def test_shadow_centroid_matches_a_rendered_image():
    g = ConeGeometry.nominal(sod=100, sdd=500, shape=(160, 160), pixel_pitch=(0.2, 0.2))
    # far off the principal ray, where the offset is large: shift the detector to the shadow
    g = g.replace(detector_origin=g.detector_origin + [30.0, -25.0, 0.0])
    C = np.array([6.0, -5.0, 0.0])
    img = render_line_integrals(g, [Sphere(C, 1.0, 1.0)], ss=8)
    rr, cc = np.mgrid[0:160, 0:160]
    m = img.sum()
    centroid = np.array([(cc * img).sum() / m, (rr * img).sum() / m])
    pred = shadow_centroid(g, C, 1.0)
    bias = np.linalg.norm(shadow_bias(g, C, 1.0))
    assert bias > 0.01                                        # the effect is real here
    assert np.allclose(centroid, pred, atol=2e-3)
