"""One bundle adjustment: every frame's pose, the shared intrinsics and the
detector distortion, from identified sphere centres.

Measured centre of sphere ``p`` (phantom frame, mm) in frame k::

    X = R_k p + t_k                                  (lab, mm)
    q = project(X) + shadow_bias(X)                  (ideal pixel, px)
    m = q + D(q)                                     (detector distortion, px)

``R_k = exp(w_k) R0_k`` (``w_k`` a rotation vector about the lab axes,
perturbing the start ``R0_k``). ``project`` has the shared intrinsics
(``sdd`` mm, principal point ``c0, r0`` px); ``D`` is a
:class:`~conecal.geometry.distortion.Distortion` whose free coefficients
are shared, or per frame for those a family lists as such. The cone-beam
shadow bias (a sphere's shadow centroid is not the projection of its
centre) is evaluated at the start of each pass and held while the pose
moves by fractions of a mm. Analytic Jacobians, the distortion's position
and centre derivatives included.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import sparse as sp

from ..geometry import rotvec_to_matrix
from ..geometry.cone import so3_left_jacobian
from ..geometry.distortion import Distortion, default_radius, detector_centre
from ..geometry.rotations import skew
from ..geometry.sphere import shadow_bias
from ..fit.core import FitResult, Parameter, solve
from .camera import INTRINSIC_UNITS, INTRINSICS, Camera

POSE = ("rx", "ry", "rz", "tx", "ty", "tz")


@dataclass(frozen=True)
class Family:
    """A distortion model: ``model`` (None: no distortion), the coefficients
    it frees (shared), those it frees per frame, a free centre, a degree;
    ``twist_centre``: the S twist turns about a centre of its own per frame
    (px from the distortion's centre, fitted per frame)."""

    name: str
    model: str | None = None
    shared: tuple = ()
    per_frame: tuple = ()
    free_centre: bool = False
    degree: int = 0
    twist_centre: bool = False

    @property
    def k(self) -> int:
        """Shared parameter count (the per-frame ones count once per frame)."""
        return len(self.shared) + 2 * self.free_centre

    @property
    def k_frame(self) -> int:
        """Parameters per frame."""
        return len(self.per_frame) + 2 * self.twist_centre

    def start(self, shape) -> Distortion | None:
        if self.model is None:
            return None
        if self.model == "polynomial":
            return Distortion.polynomial(shape, self.degree)
        return Distortion.radial(shape)


@dataclass
class Observations:
    """Identified centres: ``slot`` (N,) index of the frame in the bundle,
    ``sph`` (N,) phantom point index, ``xy`` (N, 2) px, ``sigma`` (N,) px."""

    slot: np.ndarray
    sph: np.ndarray
    xy: np.ndarray
    sigma: np.ndarray

    def subset(self, keep) -> "Observations":
        return Observations(self.slot[keep], self.sph[keep], self.xy[keep], self.sigma[keep])

    def __len__(self) -> int:
        return len(self.slot)


@dataclass
class Bundle:
    """A solved bundle: camera, distortion (shared part; None for none), per-frame
    coefficient values for the family's per-frame terms (F, n), poses
    R (F, 3, 3), t (F, 3) lab mm, residuals (N, 2) px, the fit."""

    family: Family
    camera: Camera
    distortion: Distortion | None
    per_frame: np.ndarray
    R: np.ndarray
    t: np.ndarray
    residual_px: np.ndarray
    fit: FitResult | None = None
    covariance_scale: float = 1.0
    names: list = field(default_factory=list)
    slot: np.ndarray | None = None     # each residual's frame slot
    # per-frame intrinsics: name -> prior sigma (mm or px) of a frame's offset
    # from the shared value, and the offsets (F, 3) in INTRINSICS order
    frame_intrinsics: dict = field(default_factory=dict)
    offsets: np.ndarray | None = None
    # the factor the priors were scaled by: sqrt(reduced chi-square) of the fit
    prior_scale: float = 1.0
    # the phantom refined: each point's offset (P, 3) mm from its CAD position,
    # and the prior sigma (mm) it was fitted with; None / 0: CAD as given
    point_offsets: np.ndarray | None = None
    points_sigma: float = 0.0
    # each frame's twist centre (F, 2) px from the distortion's centre (a
    # family with ``twist_centre``), else None
    twist: np.ndarray | None = None

    def phantom(self, points: np.ndarray) -> np.ndarray:
        """The phantom's points (P, 3) mm as this bundle has them."""
        return points if self.point_offsets is None else points + self.point_offsets

    def frame_camera(self, slot: int) -> Camera:
        """The camera of frame ``slot``: the shared intrinsics plus its offsets."""
        if self.offsets is None:
            return self.camera
        return self.camera.with_intrinsics(self.camera.intrinsics() + self.offsets[slot])

    def frame_distortion(self, slot: int | None) -> Distortion | None:
        """Frame ``slot``'s distortion: the shared part with its per-frame
        terms (and twist centre); ``None``: each at its median over the
        frames (for a frame outside the bundle)."""
        if self.distortion is None or not self.family.per_frame:
            return self.distortion
        values = np.median(self.per_frame, axis=0) if slot is None else self.per_frame[slot]
        k = list(self.distortion.coefficients)
        for n, v in zip(self.family.per_frame, values):
            k[self.distortion.names.index(n)] = float(v)
        about = None
        if self.twist is not None:
            about = np.asarray(self.distortion.centre) + (np.median(self.twist, 0) if slot is None else self.twist[slot])
        return self.distortion.with_coefficients(k, twist_centre=about)

    def predict(self, points: np.ndarray, slot: np.ndarray, radius: float | None = None) -> np.ndarray:
        """Measured position (N, 2) px of phantom points (N, 3) in frames ``slot``;
        with ``radius`` (mm) the sphere shadow's centroid, else the point's."""
        X = np.einsum("nij,nj->ni", self.R[slot], points) + self.t[slot]
        q = self.camera.project(X, None if self.offsets is None else self.offsets[slot])
        if radius:
            q = q + shadow_bias(self.camera.geometry(), X, radius, coarse=True)
        return _distort(self, q, slot)

    def sigma(self, name: str) -> float:
        i = self.fit.names.index(name)
        return float(self.fit.sigma[i] * np.sqrt(self.covariance_scale))

    def covariance_of(self, names: list) -> np.ndarray:
        """The stated covariance (scaled by the reduced chi-square) of the free
        parameters ``names``."""
        free = [n for n, f in zip(self.fit.names, self.fit.free) if f]
        idx = [free.index(n) for n in names]
        return self.fit.covariance[np.ix_(idx, idx)] * self.covariance_scale

    def frame_intrinsic(self, slot: int, name: str) -> tuple[float, float]:
        """Frame ``slot``'s own value of intrinsic ``name`` (shared + offset) and
        its sigma (with the covariance of the two)."""
        i = INTRINSICS.index(name)
        value = float(self.camera.intrinsics()[i] + (self.offsets[slot, i] if self.offsets is not None else 0.0))
        names = [name] + ([f"frame{slot}_{name}_offset"] if name in self.frame_intrinsics else [])
        return value, float(np.sqrt(max(self.covariance_of(names).sum(), 0.0)))


def _distort(b: Bundle, q, slot):
    if b.distortion is None:
        return q
    about = None if b.twist is None else np.asarray(b.distortion.centre) + b.twist[slot]
    basis = b.distortion.basis(q, about)                 # (N, 2, n)
    coef = np.tile(np.asarray(b.distortion.coefficients), (len(q), 1))
    for j, n in enumerate(b.family.per_frame):
        coef[:, b.distortion.names.index(n)] = b.per_frame[slot, j]
    return q + np.einsum("nij,nj->ni", basis, coef)


def adjust(family: Family, camera: Camera, obs: Observations, points: np.ndarray, radius: float,
           R0: np.ndarray, t0: np.ndarray, start: Bundle | None = None, passes: int = 2,
           max_nfev: int = 60, covariance: bool = True, probe: bool = False,
           frame_intrinsics: dict | None = None, points_sigma: float | None = None,
           centre_sigma: float = 0.0) -> Bundle:
    """Fit all poses, the intrinsics and ``family``'s distortion to ``obs``.

    ``R0``, ``t0``: starting poses per slot; ``start``: a solved bundle whose
    camera, distortion and poses to start from (same slots). Residuals are
    whitened by ``obs.sigma``; the covariance is scaled by the reduced
    chi-square when it exceeds 1 (``covariance_scale``), so that sigmas stay
    honest when detect's sigmas are too small. ``probe``: return the start
    vector and ``model(x, need_jac) -> (measured (N, 2), d/dx (N, 2, P))``
    instead of solving (for the tests).

    ``frame_intrinsics``: name (of ``INTRINSICS``) -> sigma (mm or px) frees
    that intrinsic per frame as an offset from the shared value, with a
    zero-mean Gaussian prior of that sigma (a sagging C-arm: the prior
    keeps a frame's offset from trading with its pose where one view cannot
    tell them apart, and the shared value is the offsets' centre). None:
    as ``start`` has it, else none.

    ``points_sigma`` (mm): refine the phantom: every point's offset from its
    CAD position is fitted, with a zero-mean Gaussian prior of that sigma
    (which also holds the gauge: a rigid motion or scaling of the whole
    phantom is the poses'). None: as ``start`` has it, else 0 (CAD as given).

    ``centre_sigma`` (px): hold the principal point at the detector centre
    with a prior of this sigma (0: free), the alternative a planar phantom
    may not tell from the free one.
    """
    F = len(R0) if R0 is not None else len(start.R)
    shape = camera.shape
    dist = family.start(shape)
    per = np.zeros((F, len(family.per_frame)))
    tw = np.zeros((F, 2 * family.twist_centre))
    if frame_intrinsics is None:
        frame_intrinsics = dict(start.frame_intrinsics) if start is not None else {}
    fi_idx = [INTRINSICS.index(n) for n in frame_intrinsics]
    fi_sig = np.array([float(frame_intrinsics[n]) for n in frame_intrinsics])
    off = np.zeros((F, 3))
    if start is not None and start.offsets is not None:
        off[:, fi_idx] = start.offsets[:, fi_idx]
    if start is not None:
        camera, R0, t0 = start.camera, start.R.copy(), start.t.copy()
        if dist is not None and start.distortion is not None and start.distortion.model == dist.model:
            dist = dist.with_coefficients(start.distortion.coefficients, start.distortion.centre)
            # terms this family holds at zero stay at zero
            keep = set(family.shared) | set(family.per_frame)
            dist = dist.with_coefficients([v if n in keep else 0.0 for n, v in zip(dist.names, dist.coefficients)])
            for j, n in enumerate(family.per_frame):
                per[:, j] = start.per_frame[:, start.family.per_frame.index(n)] if n in start.family.per_frame \
                    else dist.coefficients[dist.names.index(n)]
            if family.twist_centre and start.twist is not None:
                tw[:] = start.twist
    if points_sigma is None:
        points_sigma = start.points_sigma if start is not None else 0.0
    P = len(points) if points_sigma else 0
    poff = np.zeros((len(points), 3))
    if P and start is not None and start.point_offsets is not None:
        poff = start.point_offsets.copy()
    R0 = np.array(R0, float)
    t0 = np.array(t0, float)
    pts = points[obs.sph]
    slot = obs.slot
    N = len(obs)
    # parameter layout
    names = list(INTRINSICS)
    values = list(camera.intrinsics())
    scales = [1.0, 1.0, 1.0]
    units = ["mm", "px", "px"]
    if family.free_centre:
        names += ["distortion_c0", "distortion_r0"]
        values += list(dist.centre)
        scales += [1.0, 1.0]
        units += ["px", "px"]
    i_coef = len(names)
    names += [f"distortion_{n}" for n in family.shared]
    values += [dist.coefficients[dist.names.index(n)] for n in family.shared]
    scales += [0.1] * len(family.shared)
    units += ["px"] * len(family.shared)
    i_pts = len(names)
    for j in range(P):
        names += [f"point{j}_{a}" for a in "xyz"]
    values += list(poff[:P].ravel())
    scales += [0.01] * 3 * P
    units += ["mm"] * 3 * P
    i_pose = len(names)
    n_per = len(family.per_frame)
    npd = 6 + family.k_frame
    npf = npd + len(fi_idx)
    twist_names = ["twist_dc", "twist_dr"] if family.twist_centre else []
    for k in range(F):
        names += [f"frame{k}_{n}" for n in POSE] + [f"frame{k}_distortion_{n}" for n in family.per_frame]
        names += [f"frame{k}_distortion_{n}" for n in twist_names]
        names += [f"frame{k}_{INTRINSICS[i]}_offset" for i in fi_idx]
        values += [0, 0, 0, *t0[k]] + list(per[k]) + list(tw[k]) + list(off[k, fi_idx])
        scales += [1e-3, 1e-3, 1e-3, 0.01, 0.01, 0.01] + [0.1] * n_per + [1.0] * len(twist_names) + [0.1] * len(fi_idx)
        units += ["rad"] * 3 + ["mm"] * 3 + ["px"] * (n_per + len(twist_names))
        units += [INTRINSIC_UNITS[INTRINSICS[i]] for i in fi_idx]
    shared_idx = [dist.names.index(n) for n in family.shared] if dist is not None else []
    per_idx = [dist.names.index(n) for n in family.per_frame] if dist is not None else []
    i_s = dist.names.index("s") if family.twist_centre else None
    sig = obs.sigma[:, None]
    inv_sig = 1.0 / obs.sigma[:, None, None]
    bias = np.zeros((N, 2))

    def unpack(x):
        cam = camera.with_intrinsics(x[:3])
        d = None
        if dist is not None:
            centre = tuple(x[3:5]) if family.free_centre else dist.centre
            coef = np.array(dist.coefficients)
            coef[shared_idx] = x[i_coef:i_coef + len(shared_idx)]
            d = dist.with_coefficients(coef, centre)
        blocks = x[i_pose:].reshape(F, npf)
        Rk = rotvec_to_matrix(blocks[:, :3]) @ R0
        return cam, d, blocks, Rk

    def obs_points(x):
        return pts + x[i_pts:i_pose].reshape(P, 3)[obs.sph] if P else pts

    def offsets(blocks):
        o = np.zeros((F, 3))
        o[:, fi_idx] = blocks[:, npd:]
        return o

    def model(x, need_jac=False, sparse=False):
        cam, d, blocks, Rk = unpack(x)
        Rp = np.einsum("nij,nj->ni", Rk[slot], obs_points(x))
        X = Rp + blocks[slot, 3:6]
        own = offsets(blocks)[slot] if fi_idx else None
        # residual evaluations (most calls) need no derivatives
        q, JX, JK = cam.project_jacobians(X, own) if need_jac else (cam.project(X, own), None, None)
        q = q + bias
        if d is None:
            m = q
            A = None
            basis = None
        else:
            about = np.asarray(d.centre) + blocks[slot, 6 + n_per:npd] if family.twist_centre else None
            basis = d.basis(q, about)
            coef = np.tile(np.asarray(d.coefficients), (N, 1))
            if per_idx:
                coef[:, per_idx] = blocks[slot, 6:6 + n_per]
            m = q + np.einsum("nij,nj->ni", basis, coef)
            if need_jac:
                grad = d.basis_gradient(q, about)
                Jq = np.einsum("nikj,nk->nij", grad, coef)                    # d displacement / d q
                Jc = -Jq                                                      # ... / d centre
                A = np.eye(2)[None] + Jq          # d m / d q
        if not need_jac:
            return m, None
        # each measurement depends on the shared parameters and its own frame's
        # block only: the Jacobian is built as those two blocks
        AJX = JX if A is None else A @ JX
        JKa = JK if A is None else A @ JK
        Jall = np.zeros((N, 2, i_pose + npf))     # the shared columns, then the frame's block
        Js, Jf = Jall[:, :, :i_pose], Jall[:, :, i_pose:]
        Js[:, :, :3] = JKa
        if family.free_centre:
            Js[:, :, 3:5] = Jc
        for j, ci in enumerate(shared_idx):
            Js[:, :, i_coef + j] = basis[:, :, ci]
        if P:
            JP = AJX @ Rk[slot]                                               # d m / d point (N, 2, 3)
            for a in range(3):
                Js[np.arange(N), :, i_pts + 3 * obs.sph + a] = JP[:, :, a]
        Jf[:, :, :3] = AJX @ (-skew(Rp) @ so3_left_jacobian(blocks[:, :3])[slot])
        Jf[:, :, 3:6] = AJX
        for j, ci in enumerate(per_idx):
            Jf[:, :, 6 + j] = basis[:, :, ci]
        if family.twist_centre:
            # the twist's centre: the S term's basis moves with it
            Jf[:, :, 6 + n_per:npd] = -coef[:, i_s, None, None] * grad[:, :, i_s, :]
        for j, i in enumerate(fi_idx):
            Jf[:, :, npd + j] = JKa[:, :, i]
        if sparse:
            # rows whitened by obs.sigma, the priors' rows below them, on the fixed pattern
            data = (np.take_along_axis(Jall, local[:, None, :], axis=2) * inv_sig).ravel()
            return m, sp.csr_matrix((np.concatenate([data, ps * pw]), pattern[0], pattern[1]),
                                    shape=(2 * N + len(pcol), len(x)))
        cols = i_pose + slot * npf
        J = np.zeros((N, 2, len(x)))
        J[:, :, :i_pose] = Js
        rows = np.arange(N)
        for a in range(npf):
            J[rows, :, cols + a] = Jf[:, :, a]
        return m, J

    params = [Parameter(n, v, scale=s, unit=u, undetermined_sigma=np.inf) for n, v, s, u in zip(names, values, scales, units)]
    x = np.array(values, float)
    # Gaussian priors, one row each: column, weight (1/sigma), centre
    centre = np.array(detector_centre(shape))
    pcol, pw, p0 = [], [], []

    def prior(cols, weights, at):
        pcol.append(np.asarray(cols, int))
        pw.append(np.broadcast_to(np.asarray(weights, float), (len(pcol[-1]),)))
        p0.append(np.broadcast_to(np.asarray(at, float), (len(pcol[-1]),)))

    if family.free_centre:
        # A free distortion centre is blind while the distortion is nil: a weak
        # prior (half the normalising radius about the detector centre) keeps it
        # put there, and is negligible against any distortion the data show.
        prior([3, 4], 1.0 / (0.5 * dist.radius), centre)
    if family.twist_centre:
        # a frame's twist centre is blind while its twist is nil: as weak a
        # prior as the distortion centre's, about that centre
        prior((i_pose + np.arange(F)[:, None] * npf + 6 + n_per + np.arange(2)[None]).ravel(),
              1.0 / (0.5 * dist.radius), 0.0)
    # the per-frame intrinsics' zero-mean prior: one row per frame and name
    prior((i_pose + np.arange(F)[:, None] * npf + npd + np.arange(len(fi_idx))[None]).ravel(),
          np.tile(1.0 / fi_sig, F) if fi_idx else [], 0.0)
    # the refined phantom's zero-mean prior: one row per point and axis
    prior(np.arange(i_pts, i_pose), 1.0 / points_sigma if P else [], 0.0)
    if centre_sigma:
        prior([1, 2], 1.0 / centre_sigma, centre)
    pcol, pw, p0 = np.concatenate(pcol), np.concatenate(pw), np.concatenate(p0)
    # The Jacobian's sparsity pattern: each measurement row holds the shared
    # camera and distortion, its own sphere's refined position (not the other
    # spheres': stored zeros made J^T J 20x slower) and its own frame's block
    # (ascending columns), then one row per prior; fixed for the whole fit, so
    # built once. ``local``: those columns' places in the model's (N, 2, i_pose
    # + npf) block.
    own_pt = i_pts + 3 * obs.sph[:, None] + np.arange(3) if P else np.zeros((N, 0), int)
    local = np.concatenate([np.broadcast_to(np.arange(i_pts), (N, i_pts)), own_pt,
                            np.broadcast_to(i_pose + np.arange(npf), (N, npf))], 1)
    w = local.shape[1]
    idx = np.concatenate([local[:, :w - npf], (i_pose + slot * npf)[:, None] + np.arange(npf)], 1)
    pattern = (np.concatenate([np.repeat(idx, 2, axis=0).ravel(), pcol]),
               np.concatenate([np.arange(0, 2 * N * w + 1, w), 2 * N * w + np.arange(1, len(pcol) + 1)]))

    # Priors weigh against the data at the data's real scatter: where detect's
    # sigma is too small (real images: the model leaves several times it), the
    # data are whitened by that sigma times sqrt(reduced chi-square), so a
    # prior is scaled up by the same factor and refitted once (the full fits
    # only; a held-out refit keeps its start's factor).
    ps = start.prior_scale if start is not None else 1.0
    if probe:
        return x, model

    def prior_r(x):
        return ps * pw * (x[pcol] - p0)

    def markers_chi2(fit):
        res = model(fit.x)[0] - obs.xy
        fit.chi2 = float(np.sum((res / sig) ** 2))
        fit.dof = int(2 * N - fit.free.sum())
        return res

    fit = None
    for k_pass in range(passes + 1):
        if k_pass == passes:
            # the prior's factor, once, from the markers' reduced chi-square
            s = float(np.sqrt(max(1.0, fit.reduced_chi2))) if np.isfinite(fit.reduced_chi2) else 1.0
            if not (covariance and len(pcol) and abs(s / ps - 1) > 0.2):
                break
            ps = s
        else:
            cam, d, blocks, Rk = unpack(x)
            X = np.einsum("nij,nj->ni", Rk[slot], obs_points(x)) + blocks[slot, 3:6]
            new_bias = shadow_bias(cam.geometry(), X, radius, coarse=True) if radius else np.zeros((N, 2))
            # a pass that would move the bias by less than a thousandth of a pixel
            # would end where the last one did
            if k_pass and float(np.abs(new_bias - bias).max()) < 1e-3:
                continue
            bias[:] = new_bias
        params = [Parameter(p.name, v, scale=p.scale, unit=p.unit, undetermined_sigma=np.inf) for p, v in zip(params, x)]
        fit = solve(params, lambda x: np.concatenate([((model(x)[0] - obs.xy) / sig).ravel(), prior_r(x)]),
                    lambda x: model(x, True, sparse=True)[1],
                    max_nfev=max_nfev, tol=1e-8, large=True, covariance=covariance)
        x = fit.x
        markers_chi2(fit)
    cam, d, blocks, Rk = unpack(x)
    # the reduced chi-square of the markers alone (the prior rows are not data)
    res = markers_chi2(fit)
    scale = max(1.0, fit.reduced_chi2) if np.isfinite(fit.reduced_chi2) else 1.0
    return Bundle(family, cam, d, blocks[:, 6:6 + n_per].copy(), Rk, blocks[:, 3:6].copy(), res, fit, scale, names,
                  slot.copy(), dict(frame_intrinsics), offsets(blocks) if fi_idx else None, ps,
                  x[i_pts:i_pose].reshape(P, 3).copy() if P else None, float(points_sigma),
                  blocks[:, 6 + n_per:npd].copy() if family.twist_centre else None)


FAMILIES = (
    Family("none"),
    Family("radial", "radial_tangential", ("k1", "k2"), free_centre=True),
    Family("radial+S", "radial_tangential", ("k1", "k2", "s"), free_centre=True),
    Family("radial+S+tangential", "radial_tangential", ("k1", "k2", "p1", "p2", "s"), free_centre=True),
    Family("radial+S per frame", "radial_tangential", ("k1", "k2"), ("s",), free_centre=True),
    Family("radial+S+tangential, S per frame", "radial_tangential", ("k1", "k2", "p1", "p2"), ("s",),
           free_centre=True),
    Family("radial+tangential, S and its centre per frame", "radial_tangential", ("k1", "k2", "p1", "p2", "q1", "q2"),
           ("s",), free_centre=True, twist_centre=True),
    Family("polynomial3", "polynomial", tuple(Distortion.polynomial((2, 2), 3).names), degree=3),
)


def family_named(name: str) -> Family:
    for f in FAMILIES:
        if f.name == name:
            return f
    raise KeyError(name)


__all__ = ["Bundle", "Family", "FAMILIES", "Observations", "adjust", "family_named", "default_radius",
           "detector_centre"]
