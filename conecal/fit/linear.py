"""Source and detector from one sphere moved by linear axes (Blumensath et al.).

The sphere traces a virtual phantom: at log row k it sits at
``X_k = sum_j q_kj * s_j * d_j`` in the lab frame (origin at the sphere
when every axis reads zero, axes along the manipulator's). Unknowns: the
source (mm), the detector centre (mm) and the detector's rotation about its
centre (deg, rotation vector applied to the nominal u, v); optionally each
axis' scale ``s_j`` and its tilt towards the axes before it (deg; the first
axis and the second's roll about it fix the lab frame's orientation).

Gauge: the first axis' scale stays 1 (a common scale of all axes trades
exactly against the source-to-object distance), so the other scales are
relative to it. The tilts of an axis along the beam trade against lateral
source and detector shifts; the fit reports such combinations as
undetermined rather than returning noise.

The model predicts what ``detect`` measures: the centroid of the sphere
shadow, i.e. the projection of ``X_k`` plus the cone-beam shadow offset.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import FitError, InputError
from ..geometry import ConeGeometry
from ..geometry.sphere import shadow_bias
from .core import FitResult, Parameter, solve
from .detector_params import DEG, DetectorParams
from .detector_params import NAMES as DETECTOR_NAMES
from .markers import Observations


@dataclass(frozen=True, eq=False)
class LinearModel:
    """Maps the parameter vector to geometry and sphere positions, with Jacobians."""

    base: ConeGeometry          # nominal geometry: parameters are changes to it
    directions: np.ndarray      # (n_axes, 3) nominal unit directions
    axis_names: tuple
    readings: np.ndarray        # (m, n_axes) per observation
    radius: float               # sphere radius, mm

    @property
    def n_axes(self):
        return len(self.axis_names)

    def __post_init__(self):
        object.__setattr__(self, "detector", DetectorParams(self.base))

    def parameter_names(self):
        names = list(DETECTOR_NAMES)
        names += [f"scale_{a}" for a in self.axis_names]
        names += [f"tilt_{self.axis_names[j]}_to_{self.axis_names[k]}" for j in range(self.n_axes) for k in range(j)]
        return names

    def geometry(self, x) -> ConeGeometry:
        return self.detector.geometry(x[:9])

    def directions_at(self, x):
        n = self.n_axes
        scales = x[9:9 + n]
        tilts = x[9 + n:]
        D = self.directions.copy()
        raw = self.directions.copy()
        t = 0
        for j in range(n):
            for k in range(j):
                raw[j] = raw[j] + tilts[t] * DEG * self.directions[k]
                t += 1
        norms = np.linalg.norm(raw, axis=1)
        D = raw / norms[:, None]
        return D, scales, norms

    def points(self, x):
        D, scales, _ = self.directions_at(x)
        return (self.readings * scales) @ D

    def from_geometry(self, g: ConeGeometry) -> np.ndarray:
        """Parameter vector (geometry part; axes nominal) that reproduces ``g``."""
        x = self.nominal_vector()
        x[:9] = self.detector.vector(g)
        return x

    def nominal_vector(self):
        n = self.n_axes
        return np.concatenate([np.zeros(9), np.ones(n), np.zeros(n * (n - 1) // 2)])

    def predict(self, x):
        g = self.geometry(x)
        X = self.points(x)
        return g.project(X) + shadow_bias(g, X, self.radius)

    def bias(self, x, coarse: bool = False):
        g = self.geometry(x)
        return shadow_bias(g, self.points(x), self.radius, coarse)

    def jacobian(self, x):
        """d(predicted c, r)/dx, (m, 2, n_params): analytic for the projection;
        the shadow offset (< 0.1 px, smooth) by central differences."""
        g = self.geometry(x)
        X = self.points(x)
        n = self.n_axes
        _, Jx = g.project_jacobian(X)                    # (m, 2, 3)
        J = np.zeros((X.shape[0], 2, len(self.parameter_names())))
        J[:, :, 0:9] = self.detector.jacobian(g, X, x[:9])
        D, scales, norms = self.directions_at(x)
        for j in range(n):
            J[:, :, 9 + j] = Jx @ D[j] * self.readings[:, j, None]
        t = 0
        for j in range(n):
            for k in range(j):
                dd = (self.directions[k] - D[j] * (D[j] @ self.directions[k])) / norms[j] * DEG
                J[:, :, 9 + n + t] = (Jx @ dd) * (self.readings[:, j] * scales[j])[:, None]
                t += 1
        return J + self.bias_jacobian(x)

    def bias_jacobian(self, x):
        """Derivative of the shadow offset (central differences). It changes
        very slowly, so it is reused while no parameter moved by more than
        0.2 mm, 0.2 deg or 1e-4 in scale since it was computed."""
        steps = np.where(np.arange(x.size) < 9, 1e-3, 1e-5)
        cached = self.__dict__.get("_bias_jac")
        if cached is not None and np.all(np.abs(x - cached[0]) <= np.where(np.arange(x.size) < 9, 0.2, 1e-4)):
            return cached[1]
        Jb = np.empty((self.readings.shape[0], 2, x.size))
        for i in range(x.size):
            e = np.zeros(x.size)
            e[i] = steps[i]
            Jb[:, :, i] = (self.bias(x + e, True) - self.bias(x - e, True)) / (2 * steps[i])
        object.__setattr__(self, "_bias_jac", (x.copy(), Jb))
        return Jb


def dlt_start(X: np.ndarray, xy: np.ndarray, base: ConeGeometry) -> ConeGeometry | None:
    """Closed-form start: a DLT projection matrix turned into the nearest
    geometry with orthonormal u, v. None if the points are (nearly) coplanar."""
    if len(X) < 6:
        return None
    Xc = X - X.mean(0)
    sv = np.linalg.svd(Xc, compute_uv=False)
    if sv[2] < 1e-3 * sv[0]:
        return None
    # normalise for conditioning (Hartley)
    mx, sx = X.mean(0), np.sqrt(2.0) / np.mean(np.linalg.norm(Xc, axis=1)) * np.sqrt(1.5)
    mu, su = xy.mean(0), np.sqrt(2.0) / np.mean(np.linalg.norm(xy - xy.mean(0), axis=1))
    Xn = (X - mx) * sx
    un = (xy - mu) * su
    A = []
    for (x, y, z), (c, r) in zip(Xn, un):
        A.append([x, y, z, 1, 0, 0, 0, 0, -c * x, -c * y, -c * z, -c])
        A.append([0, 0, 0, 0, x, y, z, 1, -r * x, -r * y, -r * z, -r])
    _, _, Vt = np.linalg.svd(np.asarray(A))
    Pn = Vt[-1].reshape(3, 4)
    Tx = np.diag([sx, sx, sx, 1.0])
    Tx[:3, 3] = -mx * sx
    Tu = np.diag([su, su, 1.0])
    Tu[:2, 2] = -mu * su
    P = np.linalg.solve(Tu, Pn @ Tx)
    # sign: points in front of the source have positive depth
    if np.median((np.column_stack([X, np.ones(len(X))]) @ P.T)[:, 2]) < 0:
        P = -P
    try:
        g = ConeGeometry.from_projection_matrix(P, pixel_pitch=base.pixel_pitch, shape=base.shape)
    except (ValueError, np.linalg.LinAlgError):
        return None
    # nearest orthonormal (u, v, n) keeping the handedness of the nominal detector
    M = np.column_stack([g.u, g.v, np.cross(g.u, g.v) / np.linalg.norm(np.cross(g.u, g.v))])
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        return None
    centre = g.detector_centre
    rows, cols = base.shape
    u, v = R[:, 0], R[:, 1]
    origin = centre - (cols - 1) / 2 * base.pixel_pitch[0] * u - (rows - 1) / 2 * base.pixel_pitch[1] * v
    return base.replace(source=g.source, detector_origin=origin, u=u, v=v)


@dataclass
class LinearFit:
    geometry: ConeGeometry
    directions: np.ndarray
    scales: np.ndarray
    result: FitResult
    model: LinearModel
    obs: Observations
    residual_px: np.ndarray   # (m, 2) measured - predicted
    start: str


def fit_linear(scan, obs: Observations, *, axis_scales: bool = False, axis_tilts: bool = False,
               loss: str = "linear", marker_id: int | None = None, centre_model: str = "centroid") -> LinearFit:
    """Fit source and detector (and optionally the axes' scales and tilts) to
    the track of one sphere. Raises FitError when it cannot.

    ``centre_model``: "centroid" (what detect measures) or "projection" (the
    projected sphere centre, the papers' model, which leaves out the
    shadow's ellipse-centre bias)."""
    from .rotation import CENTRE_MODELS

    if centre_model not in CENTRE_MODELS:
        raise InputError(f"centre model must be one of {', '.join(CENTRE_MODELS)}, not {centre_model!r}")
    axes = scan.config.axes
    if any(a.type != "linear" for a in axes):
        raise InputError(f"{scan.root / 'scan.yaml'}: axes: fit-linear needs linear axes only; use fit-rotation")
    if obs.xy.shape[0] == 0:
        raise FitError("no usable markers (all missing or flagged)")
    ids, counts = np.unique(obs.ids, return_counts=True)
    if marker_id is None:
        marker_id = int(ids[np.argmax(counts)])
    sel = obs.ids == marker_id
    if not sel.any():
        raise InputError(f"--marker-id: no marker with id {marker_id} in the markers file")
    obs = Observations(obs.row[sel], obs.frame[sel], obs.ids[sel], obs.xy[sel], obs.sigma[sel])
    if scan.config.markers is None:
        raise InputError(f"{scan.root / 'scan.yaml'}: markers: fit-linear needs markers.diameter")
    base = scan.nominal_geometry()
    dirs = np.array([np.asarray(a.direction, float) / np.linalg.norm(a.direction) for a in axes])
    # a sphere of radius 0 has no shadow bias: the point model
    model = LinearModel(base, dirs, tuple(a.name for a in axes), scan.log.readings[obs.row],
                        scan.config.markers.diameter / 2 if centre_model == "centroid" else 0.0)
    names = model.parameter_names()
    n = model.n_axes
    x_nom = model.nominal_vector()

    def residuals(x):
        return ((obs.xy - model.predict(x)) / obs.sigma[:, None]).ravel()

    def jacobian(x):
        return -(model.jacobian(x) / obs.sigma[:, None, None]).reshape(-1, len(names))

    def params(x0):
        ps = []
        for i, nm in enumerate(names):
            if i < 6:
                ps.append(Parameter(nm, x0[i], unit="mm", scale=1.0))
            elif i < 9:
                ps.append(Parameter(nm, x0[i], unit="deg", scale=1.0))
            elif i < 9 + n:
                # the first axis' scale is the unit of length of the raster: a common
                # scale of all axes trades exactly against the source distance, so
                # the others are estimated relative to it
                ps.append(Parameter(nm, x0[i], free=axis_scales and i > 9, unit="", scale=1e-3, lower=0.5, upper=2.0))
            else:
                ps.append(Parameter(nm, x0[i], free=axis_tilts, unit="deg", scale=0.1))
        return ps

    starts = [("nominal", x_nom)]
    g_dlt = dlt_start(model.points(x_nom), obs.xy, base)
    if g_dlt is not None:
        starts.append(("dlt", model.from_geometry(g_dlt)))
    best = None
    for label, x0 in starts:
        try:
            res = solve(params(x0), residuals, jacobian, loss=loss)
        except (FitError, ValueError, np.linalg.LinAlgError):
            continue  # this start broke down numerically; the other may not
        if best is None or res.cost < best[1].cost - 1e-9:
            best = (label, res)
    if best is None:
        raise FitError("the fit did not converge from the nominal geometry nor from the DLT start")
    label, res = best
    # report the nominal as the initial guess, whatever the start was
    res.initial = x_nom.copy()
    g = model.geometry(res.x)
    D, scales, _ = model.directions_at(res.x)
    resid = obs.xy - model.predict(res.x)
    return LinearFit(g, D, scales, res, model, obs, resid, label)
