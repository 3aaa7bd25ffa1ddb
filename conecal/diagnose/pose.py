"""The robot behind a fit-pose result, re-playable with physical effects switched on.

fit-pose measures the holder's pose in every frame; the arm's model (its
joint log through the DH table) predicts it. The difference is where a
robot's left-out physics shows: a joint's zero offset, the arm yielding
under the holder's weight, encoders read before the frame is exposed,
backlash in a joint. Each observation is one frame's pose: the rotation
(rotation vector of R_fit R_model^T, rad, lab frame) and the translation
(t_fit - t_model, mm, lab frame).

The fit's own free parameters here are the arm's registration: a rigid
correction on the lab side of the base (6) and one on the holder side of
the flange (6), refitted with every candidate so that an effect is credited
only with what registration cannot absorb.

Noise per frame is the pose's own sigma from fit-pose plus the arm's
repeatability, estimated once from the registration-only residuals by
differences of successive frames (a smooth effect barely changes between
frames; repeatability does), so that the whitened residuals of a clean
arm have unit variance and the claim thresholds mean what they say.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.optimize import least_squares

from ..effects import World
from ..effects.motion import Backlash, EncoderLatency
from ..effects.robot import JointOffset, RobotDeflection
from ..errors import InputError
from ..geometry import ConeGeometry, RigidTransform, rotvec_to_matrix
from ..geometry.rotations import skew
from .model import Observations
from ..stats import difference_sigma

def small_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) rad of rotations (..., 3, 3) below 90 deg."""
    v = 0.5 * np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    scale = np.where(s > 1e-12, np.arcsin(np.clip(s, 0, 1)) / np.where(s > 1e-12, s, 1.0), 1.0)
    return v * scale


@dataclass
class PoseObservations:
    row: np.ndarray        # (m,) index into the scan's log rows
    frame: np.ndarray      # (m,)
    ids: np.ndarray        # (m,) zeros: one observation per frame
    R: np.ndarray          # (m, 3, 3) fitted holder rotations
    t: np.ndarray          # (m, 3) mm fitted holder positions
    sigma_fit: np.ndarray  # (m, 6) rad, rad, rad, mm, mm, mm


class PoseModel:
    """Predictions of a fit-pose result's per-frame poses under effects and a registration change."""

    stage = "fit-pose"
    n_comp = 6
    component_names = ("rx", "ry", "rz", "x", "y", "z")

    def __init__(self, doc: dict, scan, path="result"):
        if scan.config.motion != "robot":
            raise InputError(f"{path}: a fit-pose result needs the robot scan it came from; "
                             f"{scan.root} is a {scan.config.motion} scan")
        self.doc = doc
        self.geometry = ConeGeometry.from_dict(doc)
        self.robot = scan.robot()
        self.axis_names = list(scan.config.joint_names)
        self.rotary = [True] * len(self.axis_names)
        self.times = np.asarray(scan.log.time, float)
        self.readings = np.asarray(scan.log.readings, float)
        row_of = {int(f): i for i, f in enumerate(scan.log.frame)}
        ok = [f for f in doc.get("frames", []) if f.get("status") == "ok" and int(f["frame"]) in row_of]
        if len(ok) < 20:
            raise InputError(f"{path}: only {len(ok)} frames with an ok pose; diagnose needs at least 20")
        sig = np.array([np.concatenate([np.deg2rad(f["sigma_rotation_deg"]), f["sigma_translation_mm"]]) for f in ok],
                       float)
        if not np.all(np.isfinite(sig)) or np.any(sig <= 0):
            raise InputError(f"{path}: frames without finite pose sigmas (written by conecal >= 0.1 fit-pose)")
        self.obs = PoseObservations(row=np.array([row_of[int(f["frame"])] for f in ok]),
                                    frame=np.array([int(f["frame"]) for f in ok]), ids=np.zeros(len(ok), int),
                                    R=np.array([f["R"] for f in ok], float), t=np.array([f["t"] for f in ok], float),
                                    sigma_fit=sig)
        self.points = (scan.phantom.positions if scan.phantom is not None else np.zeros((1, 3)))
        self.base_names = ([f"base_r{c}" for c in "xyz"] + [f"base_{c}" for c in "xyz"]
                           + [f"tool_r{c}" for c in "xyz"] + [f"tool_{c}" for c in "xyz"])
        self.base_scales = np.array([1e-3] * 3 + [0.1] * 3 + [1e-3] * 3 + [0.1] * 3)
        self.repeatability = np.zeros(6)
        self.repeatability = self._repeatability()

    @property
    def n_base(self) -> int:
        return len(self.base_names)

    @property
    def sigma(self) -> np.ndarray:
        """(m, 6) per-frame noise: the fit's sigma and the arm's repeatability."""
        return np.sqrt(self.obs.sigma_fit ** 2 + self.repeatability ** 2)

    def _repeatability(self) -> np.ndarray:
        sol = least_squares(lambda b: self.whitened(None, b), np.zeros(self.n_base), x_scale=self.base_scales,
                            method="lm")
        r = self._residual(None, sol.x)
        order = np.argsort(self.obs.row)
        d = np.diff(r[order], axis=0)
        spread = difference_sigma(d, axis=0)
        return np.sqrt(np.clip(spread ** 2 - np.median(self.obs.sigma_fit ** 2, axis=0), 0, None))

    def world(self, effects=()) -> World:
        w = World.start(self.times, self.readings, robot=self.robot)
        for e in effects or ():
            w = e.apply(w)
        return w

    def _arm(self, effects) -> RigidTransform:
        """The arm's holder transforms of the observed frames under ``effects``;
        the last is kept, since a least-squares step varies the registration
        far more often than the effect."""
        key = tuple((e.name, tuple(sorted(e.to_dict().items()))) for e in effects or ())
        if getattr(self, "_arm_key", None) != key:
            w = self.world(effects)
            self._arm_key, self._arm_T = key, self.robot.transforms(w.true_readings[self.obs.row])
        return self._arm_T

    def predict_poses(self, effects, base, select=None) -> RigidTransform:
        """Holder-to-lab transforms (m) of the observed frames under ``effects``
        and the registration corrections ``base`` (rad, mm)."""
        b = np.asarray(base, float)
        idx = np.arange(len(self.obs.row)) if select is None else np.flatnonzero(select)
        T = self._arm(effects)[idx]
        lab = RigidTransform(rotvec_to_matrix(b[0:3]), b[3:6])
        tool = RigidTransform(rotvec_to_matrix(b[6:9]), b[9:12])
        n = len(idx)
        return (RigidTransform(np.broadcast_to(lab.R, (n, 3, 3)), np.broadcast_to(lab.t, (n, 3))) @ T
                @ RigidTransform(np.broadcast_to(tool.R, (n, 3, 3)), np.broadcast_to(tool.t, (n, 3))))

    def _residual(self, effects, base, select=None) -> np.ndarray:
        """(m, 6): fitted minus modelled pose (rad, rad, rad, mm, mm, mm)."""
        idx = np.arange(len(self.obs.row)) if select is None else np.flatnonzero(select)
        T = self.predict_poses(effects, base, select)
        rot = small_rotvec(self.obs.R[idx] @ np.swapaxes(T.R, -1, -2))
        return np.column_stack([rot, self.obs.t[idx] - T.t])

    def whitened(self, effects, base, select=None) -> np.ndarray:
        idx = np.arange(len(self.obs.row)) if select is None else np.flatnonzero(select)
        return (self._residual(effects, base, select) / self.sigma[idx]).ravel()

    # what diagnose reports in detector pixels: how far the model puts the
    # holder's spheres from where the fitted pose puts them
    @cached_property
    def _px_jacobian(self) -> np.ndarray:
        """(m, 2 n_spheres, 6): projected sphere positions against a pose
        perturbation (small rotation about the holder's origin, rad; shift, mm),
    the way ``_residual`` splits a pose difference."""
        g = self.geometry
        out = []
        for R, t in zip(self.obs.R, self.obs.t):
            Rp = self.points @ R.T                      # lever from the holder's origin, mm
            _, J = g.project_jacobian(Rp + t)           # (n, 2, 3) px per mm
            Jw = J @ (-skew(Rp))                        # d(w x Rp) = -[Rp]x dw
            out.append(np.concatenate([Jw, J], axis=2).reshape(-1, 6))
        return np.array(out)

    def _shadow_shifts(self, effects, base) -> np.ndarray:
        """(m, 2 n_spheres) px: every sphere shadow moved by the pose difference."""
        return np.einsum("mkj,mj->mk", self._px_jacobian, self._residual(effects, base))

    def residual_px(self, effects, base) -> np.ndarray:
        """(m, 2) px: displacement of the holder's mean sphere shadow, fitted minus modelled."""
        d = self._shadow_shifts(effects, base)
        return d.reshape(len(d), -1, 2).mean(axis=1)

    def rms_px(self, effects, base) -> float:
        return float(np.sqrt(np.mean(self._shadow_shifts(effects, base) ** 2)))

    def noise_floor_px(self) -> float:
        J = self._px_jacobian
        return float(np.sqrt(np.mean(np.einsum("mkj,mj,mkj->mk", J, self.sigma ** 2, J))))

    def summary(self, effects, base) -> dict:
        """Pose residual RMS in physical units and the noise model."""
        r = self._residual(effects, base)
        return {"rms_translation_mm": float(np.sqrt(np.mean(r[:, 3:] ** 2))),
                "rms_rotation_deg": float(np.degrees(np.sqrt(np.mean(r[:, :3] ** 2)))),
                "repeatability": {"rotation_deg": np.degrees(self.repeatability[:3]).tolist(),
                                  "translation_mm": self.repeatability[3:].tolist()}}

    def refitted(self, base) -> dict:
        """The arm's registration after the corrections: base and flange (4x4)."""
        b = np.asarray(base, float)
        lab = RigidTransform(rotvec_to_matrix(b[0:3]), b[3:6])
        tool = RigidTransform(rotvec_to_matrix(b[6:9]), b[9:12])
        return {"refitted_robot": {"dh": self.robot.dh.tolist(), "base": (lab @ self.robot.base).matrix().tolist(),
                                   "flange": (self.robot.flange @ tool).matrix().tolist()}}


def candidates(model: PoseModel) -> list:
    """Every robot effect this recording could show, parameterised."""
    from .candidate import Candidate

    out = []
    q = model.readings
    for k, name in enumerate(model.axis_names):
        # a still joint's offset still bends the arm differently as the others move
        out.append(Candidate(f"joint_offset:{name}", ("offset",), ("deg",), (0.005,),
                             lambda x, n=name: JointOffset(n, float(x[0])),
                             lambda x, s, n=name: f"joint {n} stands {x[0]:+.4f} ± {s[0]:.4f} deg away from its "
                                                  "encoder reading (a zero offset)"))
        v = np.gradient(q[:, k], model.times)
        if (v > 0).any() and (v < 0).any():
            out.append(Candidate(f"backlash:{name}", ("amount",), ("deg",), (0.005,),
                                 lambda x, n=name: Backlash(n, float(x[0])),
                                 lambda x, s, n=name: f"joint {n} has {x[0]:+.4f} ± {s[0]:.4f} deg backlash "
                                                      "(error follows the direction of motion)"))
    out.append(Candidate("robot_deflection", ("compliance_times_payload",), ("deg·kg/(N·m)",), (1e-3,),
                         lambda x: RobotDeflection(float(x[0]), 1.0),
                         lambda x, s: f"the arm yields under the holder's weight: {x[0]:+.2e} ± {s[0]:.1e} deg per "
                                      "N·m of gravity moment per kg of payload (divide by the payload's kg for "
                                      "the joints' compliance)"))
    if np.ptp(q, axis=0).max() > 0:
        out.append(Candidate("encoder_latency", ("latency",), ("s",), (0.005,),
                             lambda x: EncoderLatency(float(x[0])),
                             lambda x, s: f"frames were exposed {1e3 * x[0]:+.1f} ± {1e3 * s[0]:.1f} ms after the "
                                          "joints were read (error ∝ joint speed)"))
    return out


class PoseScene:
    """A fit-pose result as the image level sees it: in every frame with an
    ok pose, every sphere of the holder placed by that pose (lab, mm) and
    projected with the result's geometry.

    Every sphere is listed, not only those fit-pose identified: a sphere it
    left out still casts a shadow that a neighbour's patch must account for.
    There is nothing to refit at the scene level (``n_base`` is 0): each
    patch's shadow is re-centred by the image level itself."""

    stage = "fit-pose"
    n_base = 0

    def __init__(self, doc: dict, scan, path="result"):
        if scan.phantom is None or scan.config.markers is None:
            raise InputError(f"{scan.root / 'scan.yaml'}: markers.phantom: the image level of a fit-pose result "
                             "needs the holder's phantom.csv")
        self.geometry = ConeGeometry.from_dict(doc)
        self.times = np.asarray(scan.log.time, float)
        row_of = {int(f): i for i, f in enumerate(scan.log.frame)}
        ok = [f for f in doc.get("frames", []) if f.get("status") == "ok" and int(f["frame"]) in row_of]
        ids = np.asarray(scan.phantom.ids, int)
        P = np.asarray(scan.phantom.positions, float)
        rows, frames, sid, X = [], [], [], []
        for f in ok:
            R, t = np.asarray(f["R"], float), np.asarray(f["t"], float)
            rows.append(np.full(len(ids), row_of[int(f["frame"])]))
            frames.append(np.full(len(ids), int(f["frame"])))
            sid.append(ids)
            X.append(P @ R.T + t)
        if not ok:
            raise InputError(f"{path}: no frame with an ok pose")
        self.X = np.concatenate(X)
        # xy: where the fitted pose projects each sphere (no measurement, so no sigma)
        self.obs = Observations(row=np.concatenate(rows), frame=np.concatenate(frames), ids=np.concatenate(sid),
                                xy=self.geometry.project(self.X), sigma=np.full(len(self.X), np.nan),
                                points=np.tile(P, (len(ok), 1)))
        d = float(scan.config.markers.diameter)
        self.doc = {"spheres": [{"id": int(i), "diameter": d} for i in ids]}

    def geometry_after(self, base) -> ConeGeometry:
        return self.geometry

    def lab_centres(self, effects, base, idx) -> tuple[np.ndarray, np.ndarray]:
        """Lab centres (k, 3) mm of entries ``idx`` and their projections (k, 2) px."""
        return self.X[idx], self.obs.xy[idx]
