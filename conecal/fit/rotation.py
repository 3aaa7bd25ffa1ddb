"""Rotary axes (or a chain of them) and sphere positions from a rotation scan.

Several spheres fixed to the sample are turned by known readings of a chain
of axes (``SCAN_FORMAT.md``: lab outwards, ``P = A1(q1)(...An(qn)(p))``).
Unknowns: for every rotary axis whose reading varies in the scan, its
direction (two tilts from nominal, deg) and a point on it (two offsets
perpendicular to the nominal direction, mm; the position along the axis
is not a property of the axis); the sample-frame position of every sphere
but the reference one, which sits at the lab origin at zero readings and
so is ``p = 0`` (the contract's lab frame); optionally the 9 detector
parameters (bundle adjustment). When no sphere's track follows the origin's
nominal path (within ``REFERENCE_MM`` at the object) and source and
detector are held, there is no reference: every sphere is free, and the
depth of the whole scene along the beam rests on perspective alone (its
sigma says how well; the fit reports it undetermined when it is not).
Linear axes and rotary axes that do not move keep the values given.

The model predicts what ``detect`` measures: the shadow centroid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import FitError, InputError
from ..geometry import ConeGeometry, axis_angle
from ..geometry.rotations import orthonormal_complement, skew
from ..geometry.sphere import shadow_bias
from ..kinematics import Chain, LinearAxis, RotaryAxis
from .core import FitResult, Parameter, solve
from .detector_params import DEG, UNITS as DETECTOR_UNITS, DetectorParams
from .detector_params import NAMES as DETECTOR_NAMES
from .markers import Observations

REFERENCE_MM = 2.0   # a sphere nearer the lab origin's nominal path is the reference marker


@dataclass(frozen=True, eq=False)
class AxisSpec:
    """One axis of the chain as the fit sees it (directions unit, mm, deg)."""

    name: str
    type: str                 # 'linear' | 'rotary'
    direction: np.ndarray
    point: np.ndarray         # rotary only (zeros for linear)
    scale: float = 1.0        # linear only


class ChainModel:
    """Parameter vector -> predicted shadow centroids, with analytic Jacobian.

    Layout of x: [per free rotary axis: tilt_a, tilt_b (deg), offset_a,
    offset_b (mm)] + [per non-reference sphere: x, y, z (mm)] + [9 detector
    parameters if ``refine_geometry``]. Reference spheres (one per scan) sit
    at the sample origin.
    """

    def __init__(self, geometry: ConeGeometry, axes: list[AxisSpec], free_axes: list[int], readings: np.ndarray,
                 sphere_of_obs: np.ndarray, n_spheres: int, references, radii: np.ndarray,
                 refine_geometry: bool = False, centroid: bool = True):
        self.g0 = geometry
        self.axes = axes
        self.free_axes = list(free_axes)
        self.q = np.asarray(readings, float)               # (m, n_axes) per observation
        self.sph = np.asarray(sphere_of_obs, int)
        self.n_spheres = n_spheres
        self.references = sorted({int(r) for r in np.atleast_1d(references)})
        self.radii = np.asarray(radii, float)
        # False: the papers' point model (the projected sphere centre), which
        # leaves out the shadow's ellipse-centre bias
        self.centroid = centroid
        self.refine = refine_geometry
        self.detector = DetectorParams(geometry)
        self.frames = {j: orthonormal_complement(axes[j].direction) for j in self.free_axes}
        self.others = [s for s in range(n_spheres) if s not in self.references]
        self.n_axis_par = 4 * len(self.free_axes)
        self.n_sph_par = 3 * len(self.others)

    # ---------------------------------------------------------------- layout
    def names(self) -> list[str]:
        out = []
        for j in self.free_axes:
            n = self.axes[j].name
            out += [f"{n}_tilt_a", f"{n}_tilt_b", f"{n}_offset_a", f"{n}_offset_b"]
        for s in self.others:
            out += [f"sphere{s}_x", f"sphere{s}_y", f"sphere{s}_z"]
        if self.refine:
            out += list(DETECTOR_NAMES)
        return out

    def units(self) -> list[str]:
        out = []
        for _ in self.free_axes:
            out += ["deg", "deg", "mm", "mm"]
        out += ["mm"] * self.n_sph_par
        if self.refine:
            out += list(DETECTOR_UNITS)
        return out

    def size(self) -> int:
        return self.n_axis_par + self.n_sph_par + (9 if self.refine else 0)

    def axis_state(self, x, j):
        """Direction d, point c, unnormalised direction norm, and the frame (e1, e2) of free axis j."""
        k = self.free_axes.index(j)
        ta, tb, oa, ob = x[4 * k:4 * k + 4]
        e1, e2 = self.frames[j]
        a = self.axes[j]
        raw = a.direction + np.tan(ta * DEG) * e1 + np.tan(tb * DEG) * e2
        nrm = np.linalg.norm(raw)
        return raw / nrm, a.point + oa * e1 + ob * e2, nrm, (e1, e2)

    def spheres(self, x) -> np.ndarray:
        P = np.zeros((self.n_spheres, 3))
        P[self.others] = x[self.n_axis_par:self.n_axis_par + self.n_sph_par].reshape(-1, 3)
        return P

    def geometry(self, x) -> ConeGeometry:
        return self.detector.geometry(x[-9:]) if self.refine else self.g0

    def axes_at(self, x) -> list[AxisSpec]:
        out = []
        for j, a in enumerate(self.axes):
            if j in self.free_axes:
                d, c, _, _ = self.axis_state(x, j)
                out.append(AxisSpec(a.name, a.type, d, c, a.scale))
            else:
                out.append(a)
        return out

    # ---------------------------------------------------------------- forward
    def _forward(self, x):
        """Lab points (m, 3) plus what the Jacobian needs."""
        p = self.spheres(x)[self.sph]
        axes = self.axes_at(x)
        n = len(axes)
        ys = [None] * n             # point entering axis j (after the inner axes)
        rots = [None] * n
        y = p
        for j in range(n - 1, -1, -1):
            ax = axes[j]
            ys[j] = y
            if ax.type == "linear":
                rots[j] = None
                y = y + (ax.scale * self.q[:, j])[:, None] * ax.direction
            else:
                R = axis_angle(ax.direction, self.q[:, j] * DEG)
                rots[j] = R
                y = ax.point + np.einsum("mij,mj->mi", R, y - ax.point)
        return y, ys, rots, axes

    def predict(self, x) -> np.ndarray:
        X, *_ = self._forward(x)
        g = self.geometry(x)
        return g.project(X) + shadow_bias(g, X, self.radii[self.sph]) if self.centroid else g.project(X)

    def lab_points(self, x) -> np.ndarray:
        return self._forward(x)[0]

    def jacobian(self, x) -> np.ndarray:
        X, ys, rots, axes = self._forward(x)
        g = self.geometry(x)
        m = X.shape[0]
        _, Jx = g.project_jacobian(X)
        # the shadow offset follows the points: its derivative by central differences
        r = self.radii[self.sph]
        h = 1e-4
        for k in range(3 if self.centroid else 0):
            e = np.zeros(3)
            e[k] = h
            Jx[:, :, k] += (shadow_bias(g, X + e, r, True) - shadow_bias(g, X - e, r, True)) / (2 * h)
        J = np.zeros((m, 2, self.size()))
        # cumulative rotation of the axes outside axis j: L_j = R_0 ... R_{j-1}
        L = np.broadcast_to(np.eye(3), (m, 3, 3)).copy()
        Ls = []
        for j in range(len(axes)):
            Ls.append(L.copy())
            if rots[j] is not None:
                L = L @ rots[j]
        JxL = [Jx @ Lj for Lj in Ls]
        for k, j in enumerate(self.free_axes):
            d, c, nrm, (e1, e2) = self.axis_state(x, j)
            th = self.q[:, j] * DEG
            v = ys[j] - c
            s, co = np.sin(th)[:, None, None], (1 - np.cos(th))[:, None, None]
            dv = np.einsum("mi,i->m", v, d)[:, None, None]
            Jd = -s * skew(v) + co * (dv * np.eye(3) + d[None, :, None] * v[:, None, :])
            ta, tb = x[4 * k], x[4 * k + 1]
            for col, (e, t) in enumerate(((e1, ta), (e2, tb))):
                dd = (e - d * (d @ e)) / nrm * (DEG / np.cos(t * DEG) ** 2)
                J[:, :, 4 * k + col] = np.einsum("mij,mj->mi", JxL[j], Jd @ dd)
            Jc = np.eye(3) - rots[j]
            J[:, :, 4 * k + 2] = np.einsum("mij,mj->mi", JxL[j], Jc @ e1)
            J[:, :, 4 * k + 3] = np.einsum("mij,mj->mi", JxL[j], Jc @ e2)
        # spheres: dX/dp = L_total
        Jp = Jx @ L
        for i, s_ in enumerate(self.others):
            rows = self.sph == s_
            J[rows, :, self.n_axis_par + 3 * i:self.n_axis_par + 3 * i + 3] = Jp[rows]
        if self.refine:
            x9 = x[-9:]
            Jg = self.detector.jacobian(g, X, x9)
            for i in range(9 if self.centroid else 0):
                e = np.zeros(9)
                e[i] = 1e-3
                gp, gm = self.detector.geometry(x9 + e), self.detector.geometry(x9 - e)
                Jg[:, :, i] += (shadow_bias(gp, X, r, True) - shadow_bias(gm, X, r, True)) / 2e-3
            J[:, :, -9:] = Jg
        return J


CENTRE_MODELS = ("centroid", "projection")


def chain_specs(scan, geometry_doc: dict | None) -> list[AxisSpec]:
    """The scan's axes, taking calibrated values from a geometry file where it names them."""
    known = {a["name"]: a for a in (geometry_doc or {}).get("axes", [])}
    out = []
    for a in scan.config.axes:
        k = known.get(a.name, {})
        d = np.asarray(k.get("direction", a.direction), float)
        p = np.asarray(k.get("point", a.point if a.point is not None else (0, 0, 0)), float)
        out.append(AxisSpec(a.name, a.type, d / np.linalg.norm(d), p, float(k.get("scale", 1.0))))
    return out


def _chain(axes: list[AxisSpec]) -> Chain:
    """The kinematic chain these axes describe (readings in mm and degrees)."""
    return Chain(tuple(LinearAxis(a.name, a.direction, a.scale) if a.type == "linear"
                       else RotaryAxis(a.name, a.direction, a.point) for a in axes))


def triangulate(g: ConeGeometry, axes, readings, xy) -> np.ndarray:
    """Sample-frame point closest (least squares) to the rays through ``xy``."""
    T = _chain(axes).transforms(readings)
    R, t = T.R, T.t
    D = g.detector_point(xy[:, 0], xy[:, 1])
    d = D - g.source
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    Rt = np.swapaxes(R, 1, 2)
    o = np.einsum("mij,mj->mi", Rt, g.source - t)   # ray origins in the sample frame
    ds = np.einsum("mij,mj->mi", Rt, d)
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for oi, di in zip(o, ds):
        M = np.eye(3) - np.outer(di, di)
        A += M
        b += M @ oi
    return np.linalg.lstsq(A, b, rcond=None)[0]


@dataclass
class RotationFit:
    model: ChainModel
    result: FitResult
    axes: list[AxisSpec]
    geometry: ConeGeometry
    spheres: np.ndarray            # (n, 3) sample frame, mm
    sphere_labels: list[tuple]     # (scan index, marker id) per sphere
    obs: Observations              # all scans, rows index the stacked readings
    scan_of_obs: np.ndarray
    residual_px: np.ndarray


def _readings_by_name(scan, names: list[str]) -> np.ndarray:
    """The scan's log readings in the chain's axis order; axes it lacks read 0."""
    own = list(scan.log.names)
    extra = [n for n in own if n not in names]
    if extra:
        raise InputError(f"{scan.root / 'scan.yaml'}: axes: {extra[0]!r} is not in the first scan's chain "
                         f"({', '.join(names)}); scans fitted together share one chain")
    out = np.zeros((len(scan.log), len(names)))
    for j, n in enumerate(names):
        if n in own:
            out[:, j] = scan.log.column(n)
    return out


def _declared_radius(scan, geometry: ConeGeometry, position, radius_px) -> float:
    """The declared sphere radius (mm) nearest to a sphere's apparent size:
    scans may hold spheres of several sizes (``markers.diameters``)."""
    declared = scan.config.markers.diameters or (scan.config.markers.diameter,)
    if len(declared) == 1 or radius_px is None or not np.isfinite(radius_px).any():
        return declared[0] / 2
    mm = 2 * np.nanmedian(radius_px) * geometry.pixel_pitch[0] / geometry.magnification(position)
    return min(declared, key=lambda d: abs(d - mm)) / 2


def fit_rotation(scans, obs_list, geometry: ConeGeometry, *, geometry_doc: dict | None = None,
                 refine_geometry: bool = False, loss: str = "linear", min_frames: int = 3,
                 centre_model: str = "centroid") -> RotationFit:
    """Calibrate the moving rotary axes and the sphere positions of one or
    several scans of one manipulator (one bundle adjustment).

    ``centre_model``: "centroid" predicts what ``detect`` measures, the
    attenuation centroid of each shadow; "projection" predicts the projected
    sphere centre, as the papers do (``diagnose`` then finds the
    ellipse-centre bias left out).

    Each scan has its own spheres and its own reference sphere (at the lab
    origin at zero readings). The chain is the first scan's; the others may
    use a subset of its axes (missing axes read zero). With
    ``refine_geometry`` source and detector are estimated jointly: add a
    linear raster scan to pin them down.
    """
    if centre_model not in CENTRE_MODELS:
        raise InputError(f"centre model must be one of {', '.join(CENTRE_MODELS)}, not {centre_model!r}")
    if not isinstance(scans, (list, tuple)):
        scans, obs_list = [scans], [obs_list]
    axes = chain_specs(scans[0], geometry_doc)
    names = [a.name for a in axes]
    q_scans = [_readings_by_name(sc, names) for sc in scans]
    q_all = np.vstack(q_scans)
    free = [j for j, a in enumerate(axes) if a.type == "rotary" and np.ptp(q_all[:, j]) > 1e-6]
    if not free:
        raise InputError(f"{scans[0].root / 'log.csv'}: no rotary axis moves; nothing for fit-rotation to calibrate")
    rows, xy, sig, sph, frames, ids_out, scan_of = [], [], [], [], [], [], []
    labels, refs, radii, p0 = [], [], [], []
    offset_rows = 0
    for k, (sc, obs, q) in enumerate(zip(scans, obs_list, q_scans)):
        if sc.config.markers is None:
            raise InputError(f"{sc.root / 'scan.yaml'}: markers: fit-rotation needs markers.diameter")
        if np.any(obs.ids < 0):
            raise InputError(f"{sc.root}: markers need identities (ids); found null ids")
        ids, counts = np.unique(obs.ids, return_counts=True)
        ids = [int(i) for i, c in zip(ids, counts) if c >= min_frames]
        if not ids:
            raise FitError(f"{sc.root}: no sphere is seen in {min_frames} or more frames")
        keep = np.isin(obs.ids, ids)
        o = Observations(obs.row[keep], obs.frame[keep], obs.ids[keep], obs.xy[keep], obs.sigma[keep],
                         None if obs.radius is None else obs.radius[keep])
        local = np.array([ids.index(int(i)) for i in o.ids])
        rq = q[o.row]
        # the reference sphere: the track that follows the lab origin's path best
        origin_px = geometry.project(_chain(axes).transforms(rq).t)   # the sample origin's path
        dist = np.hypot(*(o.xy - origin_px).T)
        med = [np.median(dist[local == s]) for s in range(len(ids))]
        ref = int(np.argmin(med))
        # at the object, mm: a sphere this near the origin's nominal path is the
        # contract's reference marker (the nominal axis may be ~1 mm off)
        ref_mm = med[ref] * geometry.pixel_pitch[0] / float(geometry.magnification(np.zeros((1, 3)))[0])
        use_ref = refine_geometry or ref_mm < REFERENCE_MM
        base = len(labels)
        for s_, i in enumerate(ids):
            labels.append((k, i))
            # the lab origin is the reference marker's position at zero readings; a
            # phantom with no sphere there (on a stage calibrated apart) must fit too:
            # then every sphere is free, and only refining source and detector would
            # need a reference to fix the gauge
            if s_ == ref and use_ref:
                refs.append(base + s_)
                p0.append(np.zeros(3))
            else:
                sel = local == s_
                p0.append(triangulate(geometry, axes, rq[sel], o.xy[sel]))
            radii.append(_declared_radius(sc, geometry, p0[-1], o.radius[local == s_] if o.radius is not None else None))
        rows.append(o.row + offset_rows)
        xy.append(o.xy)
        sig.append(o.sigma)
        sph.append(local + base)
        frames.append(o.frame)
        ids_out.append(o.ids)
        scan_of.append(np.full(len(o.row), k))
        offset_rows += len(q)
    obs = Observations(np.concatenate(rows), np.concatenate(frames), np.concatenate(ids_out),
                       np.vstack(xy), np.concatenate(sig))
    sph = np.concatenate(sph)
    model = ChainModel(geometry, axes, free, q_all[obs.row], sph, len(labels), refs, np.array(radii), refine_geometry,
                       centre_model == "centroid")
    pnames, units = model.names(), model.units()
    x0 = np.zeros(model.size())
    x0[model.n_axis_par:model.n_axis_par + model.n_sph_par] = np.array(p0)[model.others].ravel()

    def residuals(x):
        return ((obs.xy - model.predict(x)) / obs.sigma[:, None]).ravel()

    def jacobian(x):
        return -(model.jacobian(x) / obs.sigma[:, None, None]).reshape(-1, len(pnames))

    scales = {"deg": 0.01, "mm": 0.01}
    # sigma beyond 10 mm or 10 deg: practically undetermined
    params = [Parameter(n, v, unit=u, scale=scales.get(u, 1.0), undetermined_sigma=10.0)
              for n, v, u in zip(pnames, x0, units)]
    res = solve(params, residuals, jacobian, loss=loss)
    return RotationFit(model, res, model.axes_at(res.x), model.geometry(res.x), model.spheres(res.x),
                       labels, obs, np.concatenate(scan_of), obs.xy - model.predict(res.x))
