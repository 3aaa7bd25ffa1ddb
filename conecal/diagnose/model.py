"""The fitted model of a result file, re-playable with physical effects switched on.

A fit-rotation or fit-linear result holds the geometry, the axes, the
spheres (fit-rotation) and, per marker observation, the measured centre and
residual. Here each observation is predicted again from a World (the
effects registry's description of how the scan truly moved) and nine
source/detector parameters; an additive per-observation term makes the
prediction equal the fit's own at zero effect (the fit models the
attenuation centroid of the shadow; this model projects the centre, and
their difference does not change with the small effect sizes tried).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..effects import World
from ..errors import InputError
from ..fit.detector_params import NAMES as NAMES9
from ..fit.detector_params import DetectorParams
from ..geometry import ConeGeometry
from ..kinematics import Chain, RotaryAxis


@dataclass(frozen=True, eq=False)
class CentroidPull:
    """What detector lag does to a measured centre: the ghost of the previous
    frame pulls it a fraction ``pull`` of the way back to where the marker
    was then (``detect``'s window sees both), and ``pull2`` towards where it
    was the frame before that (lag decaying over frames). Moves nothing in
    the world."""

    pull: float
    pull2: float = 0.0
    name = "detector_lag"

    @property
    def physics(self) -> str:
        from ..effects.imaging import DetectorLag

        return DetectorLag.physics

    def apply(self, world):
        return world


@dataclass(frozen=True, eq=False)
class EllipseCentreBias:
    """What a point model of the markers leaves out: ``fraction`` of the
    offset between a sphere shadow's attenuation centroid (what ``detect``
    measures) and the projected sphere centre. Moves nothing in the world:
    simulated frames always draw the shadows exactly, so the bias is in
    every recording; fits leave it out only with ``--centre-model projection``."""

    fraction: float
    name = "ellipse_centre_bias"
    physics = ("a sphere's shadow in a cone beam is an ellipse stretched away from the principal point, and the "
               "centroid of its attenuation lies outward of the projected centre, by more the farther out and the "
               "larger the sphere")

    def apply(self, world):
        return world


@dataclass
class Observations:
    row: np.ndarray        # (m,) index into the scan's log rows
    frame: np.ndarray      # (m,) frame numbers
    ids: np.ndarray        # (m,)
    xy: np.ndarray         # (m, 2) measured px
    sigma: np.ndarray      # (m,) px
    points: np.ndarray     # (m, 3) the sphere's position on the sample (sample frame, mm)


def _project(S, O, u, v, n, pitch, X):
    """Per-observation projection: sources S (m,3), detector origins O (m,3),
    shared u, v, normal n; points X (m,3) -> (m,2) px."""
    d = X - S
    t = np.einsum("ij,j->i", O - S, n) / (d @ n)
    P = S + t[:, None] * d - O
    return np.column_stack([P @ u / pitch[0], P @ v / pitch[1]])


class ResultModel:
    """Predictions of a result's observations under effects and a geometry change."""

    n_comp = 2   # each observation: a marker centre (x, y) px

    def __init__(self, doc: dict, scan, path="result"):
        stage = doc.get("stage")
        if stage not in ("fit-rotation", "fit-linear"):
            raise InputError(f"{path}: diagnose works on fit-rotation and fit-linear results (and fit-pose's poses), "
                             f"not {stage!r}")
        if isinstance(doc.get("scan"), list):
            raise InputError(f"{path}: a multi-scan result; diagnose one scan's fit at a time")
        self.doc = doc
        self.stage = stage
        self.geometry = ConeGeometry.from_dict(doc)
        self.params = DetectorParams(self.geometry)
        if not doc.get("axes"):
            raise InputError(f"{path}: axes: a result without axes has no motion to diagnose")
        self.chain = Chain.from_list(doc["axes"])   # typed and checked when the document was read
        missing = [a for a in self.chain.names if a not in scan.log.names]
        if missing:
            raise InputError(f"{scan.root / 'log.csv'}: no column for axis {missing[0]!r} of {path}")
        self.times = np.asarray(scan.log.time, float)
        # the row exposed just before each row (itself for the first)
        order = np.argsort(self.times, kind="stable")
        self.previous_row = np.empty(len(order), int)
        self.previous_row[order] = np.concatenate([order[:1], order[:-1]])
        self.readings = np.column_stack([scan.log.column(a) for a in self.chain.names])
        spheres = {}
        if stage == "fit-rotation":
            for sp in doc.get("spheres", []):
                spheres[int(sp["id"])] = np.asarray(sp["position"], float)
        res = [r for r in doc.get("residuals", []) if "x" in r]
        if not res:
            raise InputError(f"{path}: no residuals with marker positions (written by conecal >= 0.1 fits)")
        row_of = {int(f): i for i, f in enumerate(scan.log.frame)}
        keep = [r for r in res if int(r["frame"]) in row_of and (stage == "fit-linear" or int(r["id"]) in spheres)]
        if len(keep) < 20:
            raise InputError(f"{path}: only {len(keep)} usable observations; diagnose needs at least 20")
        pts = np.array([spheres[int(r["id"])] if stage == "fit-rotation" else np.zeros(3) for r in keep])
        self.obs = Observations(row=np.array([row_of[int(r["frame"])] for r in keep]),
                                frame=np.array([int(r["frame"]) for r in keep]),
                                ids=np.array([int(r["id"]) for r in keep]),
                                xy=np.array([[r["x"], r["y"]] for r in keep], float),
                                sigma=np.array([r["sigma"] for r in keep], float), points=pts)
        # the papers' point model leaves the ellipse-centre bias out; it is a candidate then
        self.centre_model = (doc.get("fit") or {}).get("centre_model", "centroid")
        if stage == "fit-rotation":
            diam = {int(sp["id"]): float(sp.get("diameter", 0.0)) for sp in doc.get("spheres", [])}
            self.radii = np.array([diam[int(r["id"])] / 2 for r in keep])
        else:
            self.radii = np.full(len(keep), scan.config.markers.diameter / 2 if scan.config.markers else 0.0)
        self._setup_base()
        fit_pred = self.obs.xy - np.array([[r["dx"], r["dy"]] for r in keep], float)
        self.offset = np.zeros_like(fit_pred)
        self.offset = fit_pred - self.predict(None, np.zeros(self.n_base))

    def _setup_base(self):
        """The fit's own free parameters, refitted with every candidate effect
        so that an effect is only credited with what they cannot absorb.
        fit-linear: the nine source/detector parameters. fit-rotation: each
        moving rotary axis' direction (2 small rotations) and point (2
        shifts), and every sphere but the reference (3 each); the geometry
        stays as the fit held it."""
        if self.stage == "fit-linear":
            self.base_names = list(NAMES9)
            self.base_scales = np.array([0.05, 0.05, 0.5, 0.05, 0.05, 0.5, 0.01, 0.01, 0.01])
            return
        from ..geometry.rotations import orthonormal_complement

        self._rot = []
        names, scales = [], []
        for k, a in enumerate(self.chain.axes):
            if isinstance(a, RotaryAxis) and np.ptp(self.readings[:, k]) > 0:
                e1, e2 = orthonormal_complement(a.direction)
                self._rot.append((k, e1, e2))
                names += [f"{a.name}_tilt1", f"{a.name}_tilt2", f"{a.name}_shift1", f"{a.name}_shift2"]
                scales += [1e-4, 1e-4, 0.01, 0.01]
        ids = sorted(set(self.obs.ids.tolist()))
        ref = [int(sp["id"]) for sp in self.doc.get("spheres", []) if sp.get("reference")]
        self._free_ids = [i for i in ids if i not in ref]
        for i in self._free_ids:
            names += [f"sphere{i}_{c}" for c in "xyz"]
            scales += [0.01, 0.01, 0.01]
        self._id_index = np.array([self._free_ids.index(i) if i in self._free_ids else -1 for i in self.obs.ids])
        self.base_names = names
        self.base_scales = np.array(scales)

    @property
    def n_base(self) -> int:
        return len(self.base_names)

    @property
    def axis_names(self) -> list[str]:
        return list(self.chain.names)

    @property
    def rotary(self) -> list[bool]:
        return [isinstance(a, RotaryAxis) for a in self.chain.axes]

    def residual_px(self, effects, base) -> np.ndarray:
        """(m, 2) px: measured minus predicted centres."""
        return self.obs.xy - self.predict(effects, base)

    def rms_px(self, effects, base) -> float:
        return float(np.sqrt(np.mean(self.residual_px(effects, base) ** 2)))

    def noise_floor_px(self) -> float:
        return float(np.sqrt(np.mean(self.obs.sigma ** 2)))

    def summary(self, effects, base) -> dict:
        return {}

    def refitted(self, base) -> dict:
        return {"refitted_geometry": {"format": "conecal-geometry/1", **self.geometry_after(base).to_dict(),
                                      "axes": self.doc.get("axes", [])}}

    def _apply_base(self, b):
        """(chain, geometry, per-observation points) under base parameters ``b``."""
        if self.stage == "fit-linear":
            return self.chain, self.params.geometry(b), self.obs.points
        from ..geometry.rotations import rotvec_to_matrix

        chain = self.chain
        i = 0
        for k, e1, e2 in self._rot:
            a = chain.axes[k]
            d = rotvec_to_matrix(b[i] * e1 + b[i + 1] * e2) @ a.direction
            chain = chain.replace_axis(a.name, RotaryAxis(a.name, d, a.point + b[i + 2] * e1 + b[i + 3] * e2))
            i += 4
        delta = np.asarray(b[i:], float).reshape(-1, 3)
        pts = self.obs.points.copy()
        m = self._id_index >= 0
        if delta.size:
            pts[m] += delta[self._id_index[m]]
        return chain, self.geometry, pts

    def world(self, effects=(), chain=None) -> World:
        w = World.start(self.times, self.readings, chain=chain or self.chain)
        for e in effects:
            w = e.apply(w)
        return w

    def predict(self, effects, base, select=None) -> np.ndarray:
        """Predicted centres (m, 2) px of the observations (``select``: a mask)
        with ``effects`` switched on and the fit's parameters moved by ``base``."""
        chain, g, points = self._apply_base(np.asarray(base, float))
        w = self.world(effects or (), chain)
        T = w.transforms()
        o = self.obs
        idx = np.arange(len(o.row)) if select is None else np.flatnonzero(select)
        rows = o.row[idx]
        X = np.einsum("mij,mj->mi", T.R[rows], points[idx]) + T.t[rows]
        S = g.source + w.source_offsets[rows]
        det = w.detector_offsets[rows] if w.detector_offsets is not None else 0.0
        O = g.detector_origin + det
        xy = w.imaging.distort(_project(S, O, g.u, g.v, g.normal, g.pixel_pitch, X), g.shape)
        pulls = [e for e in (effects or ()) if isinstance(e, CentroidPull)]
        if pulls:
            prev = self.previous_row[rows]
            back = {1: sum(e.pull for e in pulls), 2: sum(e.pull2 for e in pulls)}
            shift = np.zeros_like(xy)
            for _, f in sorted(back.items()):
                if f:
                    Xp = np.einsum("mij,mj->mi", T.R[prev], points[idx]) + T.t[prev]
                    Sp = g.source + w.source_offsets[prev]
                    Op = g.detector_origin + (w.detector_offsets[prev] if w.detector_offsets is not None else 0.0)
                    xyp = w.imaging.distort(_project(Sp, Op, g.u, g.v, g.normal, g.pixel_pitch, Xp), g.shape)
                    shift += f * (xyp - xy)
                prev = self.previous_row[prev]
            xy = xy + shift
        bias = sum(e.fraction for e in (effects or ()) if isinstance(e, EllipseCentreBias))
        if bias:
            from ..geometry.sphere import shadow_bias

            xy = xy + bias * shadow_bias(g, X, self.radii[idx])
        return xy + self.offset[idx]

    def lab_centres(self, effects, base, idx) -> tuple[np.ndarray, np.ndarray]:
        """Lab centres (k, 3) mm of observations ``idx`` and their predicted
        shadow centres (k, 2) px, with ``effects`` on and the fit moved by ``base``."""
        chain, _, points = self._apply_base(np.asarray(base, float))
        T = self.world(effects, chain).transforms()
        rows = self.obs.row[idx]
        X = np.einsum("mij,mj->mi", T.R[rows], points[idx]) + T.t[rows]
        select = np.zeros(len(self.obs.row), bool)
        select[idx] = True
        return X, self.predict(effects, base, select)

    def geometry_after(self, base) -> ConeGeometry:
        return self._apply_base(np.asarray(base, float))[1]

    def whitened(self, effects, base, select=None) -> np.ndarray:
        idx = np.arange(len(self.obs.row)) if select is None else np.flatnonzero(select)
        r = (self.obs.xy[idx] - self.predict(effects, base, select)) / self.obs.sigma[idx, None]
        return r.ravel()
