"""An image intensifier's S twist about a centre of its own per frame: the
distortion's form, a frame's refit and the bundle, against the twist
written out by hand here (not through the model's basis)."""

from __future__ import annotations

import json

import numpy as np
import tifffile
from click.testing import CliRunner

from conecal.calib.alternatives import RESTARTED, restarted_alternative
from conecal.calib.bundle import Observations, adjust, family_named
from conecal.calib.camera import Camera
from conecal.calib.candidate import refine_pose_and_terms
from conecal.calib.twist import seed_twists
from conecal.cli.main import cli
from conecal.documents.common import Distortion as DistortionDoc
from conecal.geometry import ConeGeometry, rotvec_to_matrix
from conecal.geometry.distortion import Distortion

SHAPE = (512, 512)
RADIUS = 0.5 * np.hypot(511, 511)


def _twist(xy, s, about):
    """s |u|^2 J(u), u = (xy - about) / RADIUS, J(a, b) = (-b, a): px."""
    u = (np.asarray(xy, float) - about) / RADIUS
    w2 = np.sum(u * u, -1, keepdims=True)
    return s * w2 * np.stack([-u[..., 1], u[..., 0]], -1)


def _camera():
    g = ConeGeometry.nominal(sod=600.0, sdd=1000.0, shape=SHAPE, pixel_pitch=(0.45, 0.45))
    return Camera.nominal(g, 600.0)


def _ball(rng, n=40):
    """Points (n, 3) mm spread through a 60 mm ball."""
    p = rng.normal(0, 1, (n, 3))
    return 30.0 * p / np.linalg.norm(p, axis=1, keepdims=True) * rng.uniform(0.3, 1.0, (n, 1))


def _poses(rng, F):
    """F random poses: R (F, 3, 3) within 40 deg per axis, t (F, 3) mm."""
    R = np.stack([rotvec_to_matrix(np.deg2rad(rng.uniform(-40, 40, 3))) for _ in range(F)])
    return R, rng.normal(0, 5, (F, 3))


def _seen(rng, cam, R, t, p, s, about, noise):
    """Every point of ``p`` (n, 3) in every frame, twisted by ``s`` about
    ``about`` (per frame or one for all) with Gaussian ``noise`` px: slot,
    point index, measured (N, 2) px."""
    F = len(R)
    slot = np.repeat(np.arange(F), len(p))
    sph = np.tile(np.arange(len(p)), F)
    q = cam.project(np.einsum("nij,nj->ni", R[slot], p[sph]) + t[slot])
    s, about = np.broadcast_to(s, (F,)), np.broadcast_to(about, (F, 2))
    return slot, sph, q + _twist(q, s[slot, None], about[slot]) + rng.normal(0, noise, q.shape)


def test_twist_turns_about_its_own_centre_and_round_trips():
    about = np.array([330.0, 190.0])
    d = Distortion.radial(SHAPE, k1=1.5, s=2.0, twist_centre=tuple(about))
    xy = np.random.default_rng(1).uniform(0, 511, (50, 2))
    radial = Distortion.radial(SHAPE, k1=1.5).displacement(xy)
    assert np.allclose(d.displacement(xy) - radial, _twist(xy, 2.0, about))
    assert np.allclose(d.displacement(about) - Distortion.radial(SHAPE, k1=1.5).displacement(about), 0.0)
    entry = d.to_dict()
    DistortionDoc.model_validate(entry)
    back = Distortion.from_dict(entry)
    assert back.twist_centre == d.twist_centre and np.allclose(back.displacement(xy), d.displacement(xy))
    # the per-position centre a bundle passes gives the same
    assert np.allclose(d.basis(xy, np.broadcast_to(about, xy.shape)), d.basis(xy))


def test_a_frames_refit_finds_its_twist_centre():
    rng = np.random.default_rng(2)
    cam = _camera()
    P = _ball(rng)
    R, t = rotvec_to_matrix(np.deg2rad([25.0, -10.0, 5.0])), np.array([3.0, -2.0, 5.0])
    about = np.array([256.0 + 90.0, 256.0 - 70.0])
    q = cam.project(P @ R.T + t)
    xy = q + _twist(q, 6.0, about) + rng.normal(0, 0.02, q.shape)
    # started as the second look starts a frame: from the bundle's median twist
    # (from s = 0 a single frame's twist trades with its pose, and a false
    # minimum with s < 0 is nearer)
    start = Distortion.radial(SHAPE, s=4.0)
    i_s = start.names.index("s")
    R2, t2, res, own = refine_pose_and_terms(cam, P, xy, rotvec_to_matrix(np.deg2rad([24.0, -9.0, 4.0])),
                                             t + 0.5, 1.0, start, [i_s], twist=True)
    assert np.sqrt(np.mean(np.sum(res ** 2, 1))) < 0.05
    assert abs(own.coefficients[i_s] - 6.0) < 0.5       # (its turn trades with the pose a little)
    assert np.linalg.norm(np.array(own.twist_centre) - about) < 10.0
    # without its centre the same frame is left well above the noise
    _, _, res0, _ = refine_pose_and_terms(cam, P, xy, R, t, 1.0, start, [i_s])
    assert np.sqrt(np.mean(np.sum(res0 ** 2, 1))) > 0.1


def test_the_bundle_fits_each_frames_twist_and_predicts_held_out_points():
    rng = np.random.default_rng(3)
    cam = _camera()
    pts = _ball(rng, 30)
    F = 6
    R, t = _poses(rng, F)
    s = rng.uniform(3.0, 8.0, F)
    about = np.array([255.5, 255.5]) + rng.uniform(-120, 120, (F, 2))
    slot, sph, xy = _seen(rng, cam, R, t, pts, s, about, 0.02)
    obs = Observations(slot, sph, xy, np.full(len(slot), 0.02))
    # as fit-pose goes: the pinhole, a family nested in it with S per frame,
    # each frame's twist and centre seeded from it, then the family itself
    fam = family_named("radial+tangential, S and its centre per frame")
    base = adjust(family_named("none"), cam, obs, pts, 0.0, R, t)
    nested = adjust(family_named("radial+S+tangential, S per frame"), cam, obs, pts, 0.0, R, t, start=base)
    b = adjust(fam, cam, obs, pts, 0.0, R, t, start=seed_twists(nested, fam, obs, pts))
    rms = float(np.sqrt(np.mean(np.sum(b.residual_px ** 2, 1)) / 2))
    assert rms < 0.025
    # points it never saw, in every frame, where the twists put them (the split
    # between the shared decentring q and a frame's twist centre is measured
    # only at second order; the field they make together is what counts)
    held = _ball(rng, 20)
    hslot, hsph, truth = _seen(rng, cam, R, t, held, s, about, 0.0)
    err = b.predict(held[hsph], hslot) - truth
    assert float(np.sqrt(np.mean(np.sum(err ** 2, 1)))) < 0.05
    # without the twist's centre the same markers are left well above their noise
    plain = adjust(family_named("radial+S+tangential, S per frame"), cam, obs, pts, 0.0, R, t, start=nested)
    assert float(np.sqrt(np.mean(np.sum(plain.residual_px ** 2, 1)) / 2)) > 1.5 * rms
    # a frame's own entry holds its twist centre
    assert np.allclose(b.frame_distortion(2).twist_centre, np.asarray(b.distortion.centre) + b.twist[2])


def test_a_twist_familys_restart_is_listed_and_other_families_have_none():
    rng = np.random.default_rng(4)
    cam = _camera()
    pts = _ball(rng, 25)
    R, t = _poses(rng, 4)
    slot, sph, xy = _seen(rng, cam, R, t, pts, 5.0, np.array([300.0, 200.0]), 0.02)
    obs = Observations(slot, sph, xy, np.full(len(slot), 0.02))
    fits = {"none": adjust(family_named("none"), cam, obs, pts, 0.0, R, t)}
    plain = adjust(family_named("radial+S per frame"), cam, obs, pts, 0.0, R, t, start=fits["none"])
    choice = []
    restarted_alternative(plain, fits, choice, obs, pts, 0.0, cam, 3)
    assert choice == [] and RESTARTED not in fits
    fam = family_named("radial+tangential, S and its centre per frame")
    final = adjust(fam, cam, obs, pts, 0.0, R, t, start=seed_twists(plain, fam, obs, pts))
    restarted_alternative(final, fits, choice, obs, pts, 0.0, cam, 3)
    (row,) = choice
    assert row["family"] == RESTARTED and fits[RESTARTED].family is fam
    assert ("tied" in row) != ("why" in row) and np.isfinite(row["behind_chosen_chi2"])


def test_a_twist_about_its_own_centre_is_written_per_frame_and_exported(tmp_path):
    from test_free_pose import _free_scan       # (the tests folder is on the path)
    d, mdoc, sc = _free_scan(tmp_path, n=8)
    (tmp_path / "m.json").write_text(json.dumps(mdoc))
    r = CliRunner().invoke(cli, ["fit-pose", str(d), "--markers", str(tmp_path / "m.json"), "-o",
                                 str(tmp_path / "p.json"), "--distortion",
                                 "radial+tangential, S and its centre per frame"])
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "p.json").read_text())
    assert "twist centre" in doc["gauge"] and "twist_centre" not in doc["distortion"]
    ok = [f for f in doc["frames"] if f["status"] == "ok"]
    assert ok and all(len(f["distortion"]["twist_centre"]) == 2 for f in ok)
    r = CliRunner().invoke(cli, ["export", str(tmp_path / "p.json"), "--format", "distortion", "-o",
                                 str(tmp_path / "d.tif")])
    assert r.exit_code == 0, r.output
    pages = tifffile.imread(tmp_path / "d.tif")
    last = Distortion.from_dict(ok[-1]["distortion"])
    assert np.allclose(pages[2 * len(ok) - 2], last.field(SHAPE)[0], atol=1e-4)
