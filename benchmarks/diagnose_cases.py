"""Scenario builders for diagnose: simulated scans with one effect switched
on, their fits, and diagnose's answer. Imported by ``bench_diagnose.py`` and
by the tests (``from benchmarks.diagnose_cases import ...``), so that a test
and the benchmark build the same scan from the same call.

The scans come from conecal's own simulator (``conecal.simulate.scenarios``):
they test diagnose against its own library of effect forms. The independent
forms are in ``formvariants.py`` / ``formvariants_image.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from conecal.cli.main import cli
from conecal.effects import parse_effect
from conecal.simulate import write_scan
from conecal.simulate.scenarios import linear_raster, robot_helix, rotation_scan

# name -> (scan kind, --effect spec, labels diagnose may name for it)
EFFECTS = {
    "clean": ("rotation", None, set()),
    "rotary_wobble": ("rotation", "rotary_wobble:amplitude=0.05", {"rotary_wobble"}),
    "rotary_runout": ("rotation", "rotary_runout:amplitude=0.0015,phase=30,harmonic=2", {"rotary_runout:2"}),
    "focal_spot_drift": ("rotation", "focal_spot_drift:velocity=0.0005/0/0", {"focal_spot_drift", "detector_drift"}),
    "detector_drift": ("rotation", "detector_drift:velocity=0.001/0.0005/0", {"focal_spot_drift", "detector_drift"}),
    "encoder_latency": ("rotation", "encoder_latency:latency=0.02", {"encoder_latency"}),
    "backlash": ("rotation", "backlash:axis=theta,amount=0.2", {"backlash"}),
    "distortion_radial": ("rotation", "detector_distortion:radial_px=0.5", {"detector_distortion:radial"}),
    "distortion_s": ("rotation", "detector_distortion:radial_px=0,s_px=0.5", {"detector_distortion:s_shaped"}),
    "blur": ("rotation", "blur:sigma_px=0.4", {"blur"}),
    "beam_hardening": ("rotation", "beam_hardening:beta=0.05", {"beam_hardening"}),
    "detector_lag": ("rotation", "detector_lag:fraction=0.05", {"detector_lag"}),
    "scatter": ("rotation", "scatter:fraction=0.02", {"scatter"}),
    "clean_raster": ("linear", None, set()),
    "axis_scale": ("linear", "axis_scale:axis=x,scale=0.002", {"axis_scale"}),
    "axis_nonorthogonality": ("linear", "axis_nonorthogonality:axis=y,towards=x,angle=0.05",
                              {"axis_nonorthogonality"}),
    # a 7-joint arm carrying the helix holder, elbow swivelling +-60 deg (fit-pose results)
    "clean_arm": ("robot", None, set()),
    "joint_offset": ("robot", "joint_offset:joint=q2,offset=0.025", {"joint_offset:q2"}),
    "robot_deflection": ("robot", "robot_deflection:compliance=0.001,payload_kg=2", {"robot_deflection"}),
    "arm_encoder_latency": ("robot", "encoder_latency:latency=0.025", {"encoder_latency"}),
    "joint_backlash": ("robot", "backlash:axis=q3,amount=0.005", {"backlash:q3"}),
    # the image level on fit-pose results: the arm's frames rendered in full (640², ~50 spheres
    # each), through detect and fit-pose; every frame's holder re-rendered from its fitted pose
    "clean_arm_frames": ("robot_frames", None, set()),
    "arm_blur": ("robot_frames", "blur:sigma_px=0.4", {"blur"}),
    "arm_beam_hardening": ("robot_frames", "beam_hardening:beta=0.05", {"beam_hardening"}),
    "arm_detector_lag": ("robot_frames", "detector_lag:fraction=0.05", {"detector_lag"}),
    "arm_scatter": ("robot_frames", "scatter:fraction=0.02", {"scatter"}),
}
# fit-pose's accuracy per pose component (benchmarks/bench_pose.py: mean
# errors 0.004 deg, 0.008 mm as 3-vector norms)
POSE_NOISE = (0.0025, 0.005)   # deg, mm
# drifts of source and detector have near-identical signatures in one
# rotation scan: naming either (the other reported as ambiguous) counts


def make(root: Path, name: str, spec, seed: int, noise: float = 0.02, photons: float = 3e4,
         kind: str = "rotation") -> Path:
    """Simulate a scan with ``spec`` switched on and write truth centroids
    plus Gaussian noise of ``noise`` px as its markers (``noise=None``: run
    ``conecal detect`` on the frames instead). A robot scan gets true poses
    plus fit-pose's noise as its poses.json instead (``noise=None``: frames
    rendered in full, then detect and fit-pose with the true geometry)."""
    if kind.startswith("robot"):
        return make_arm(root, name, spec, seed, full=noise is None or kind == "robot_frames")
    if kind == "linear":
        sc = linear_raster(seed, rows=256, cols=256, pitch=0.4, steps=(4.0, 4.0, 8.0), counts=(5, 5, 3), dt=2.0)
    elif kind == "rotation_point":
        # larger spheres nearer the source, for fits with --centre-model projection:
        # an ellipse-centre bias of up to ~0.03 px
        sc = rotation_scan(seed, rows=256, cols=256, pitch=0.4, n_frames=72, schedule="sweep", sod=100.0,
                           diameters=(4.0,), n_spheres=3)
    else:
        sc = rotation_scan(seed, rows=256, cols=256, pitch=0.4, n_frames=72, schedule="sweep")
    sc.photons = photons
    if spec:
        sc.apply_effects([parse_effect(spec)])
    path = write_scan(sc, root / f"{name}_{seed}", seed=seed)
    truth = json.loads((path / "truth.json").read_text())
    (path / "geometry.json").write_text(json.dumps(truth["geometry"]))
    if noise is None:   # the markers as detect measures them
        out = CliRunner().invoke(cli, ["detect", str(path), "-o", str(path / "markers.json")])
        if out.exit_code != 0:
            raise RuntimeError(out.output)
        return path
    rng = np.random.default_rng(seed + 99)
    frames = [{"frame": fr["frame"], "markers": [
        {"id": m["id"], "x": m["centroid"][0] + rng.normal(0, noise), "y": m["centroid"][1] + rng.normal(0, noise),
         "sigma": noise, "flags": []} for m in fr["markers"] if m["inside"]]} for fr in truth["frames"]]
    (path / "markers.json").write_text(json.dumps({"format": "conecal-markers/1",
                                                   "detector": {"shape": [256, 256]}, "frames": frames}))
    return path


def make_arm(root: Path, name: str, spec, seed: int, full: bool = False, frames: dict | None = None) -> Path:
    """A robot sweep scan and its poses.json: true holder poses plus Gaussian
    noise of ``POSE_NOISE`` (the frames are rendered on a small detector, which
    diagnose does not read; the poses carry the full 640² geometry), or, with
    ``full``, the frames in full through detect and fit-pose. ``frames``:
    scenario settings (rows, cols, pitch, n_frames) to render real frames
    with true poses plus noise (the image level, isolated from detect)."""
    from conecal.geometry import rotvec_to_matrix

    def scenario(**kw):
        sc = robot_helix(seed, trajectory="sweep", **{**(frames or {}), **kw})
        if spec:
            sc.apply_effects([parse_effect(spec)])
        return sc

    sc = scenario()
    path = root / f"{name}_{seed}"
    if full:
        write_scan(sc, path, seed=seed)
        (path / "geometry.json").write_text(json.dumps({"format": "conecal-geometry/1", **sc.geometry.to_dict()}))
        r = CliRunner()
        for args in (["detect", str(path), "-o", str(path / "markers.json")],
                     ["fit-pose", str(path), "--markers", str(path / "markers.json"), "--geometry",
                      str(path / "geometry.json"), "-o", str(path / "fit.json")]):
            out = r.invoke(cli, args)
            if out.exit_code != 0:
                raise RuntimeError(out.output)
        return path
    write_scan(sc if frames else scenario(rows=48, cols=48, pitch=2.5, body="none"), path, seed=seed)
    T = sc.world.transforms()
    rng = np.random.default_rng(seed + 99)
    poses = []
    for k in range(sc.n_frames):
        dR = rotvec_to_matrix(np.deg2rad(POSE_NOISE[0]) * rng.normal(size=3))
        poses.append({"frame": k, "status": "ok", "R": (dR @ T.R[k]).tolist(),
                      "t": (T.t[k] + POSE_NOISE[1] * rng.normal(size=3)).tolist(),
                      "sigma_rotation_deg": [POSE_NOISE[0]] * 3, "sigma_translation_mm": [POSE_NOISE[1]] * 3})
    (path / "fit.json").write_text(json.dumps({"format": "conecal-poses/1", **sc.geometry.to_dict(), "frames": poses}))
    return path


def run_one(path: Path, kind: str = "rotation", image: bool = True, extra: tuple = ()) -> dict:
    """Fit (unless a robot scan: its fit.json is there), then diagnose with ``extra`` options."""
    r = CliRunner()
    if kind.startswith("robot"):
        # the image level needs real frames; "robot" scans carry 48² stand-ins
        real = image and kind == "robot_frames"
        out = r.invoke(cli, ["diagnose", str(path / "fit.json"), str(path), "-o", str(path / "diag.json")]
                       + ([] if real else ["--no-image"]) + list(extra))
        if out.exit_code != 0:
            raise RuntimeError(out.output)
        return json.loads((path / "diag.json").read_text())
    if kind == "linear":
        out = r.invoke(cli, ["fit-linear", str(path), "--markers", str(path / "markers.json"), "-o", str(path / "fit.json")])
    else:
        out = r.invoke(cli, ["fit-rotation", str(path), "--markers", str(path / "markers.json"),
                             "--geometry", str(path / "geometry.json"), "-o", str(path / "fit.json")]
                       + (["--centre-model", "projection"] if kind == "rotation_point" else []))
    if out.exit_code != 0:
        raise RuntimeError(out.output)
    out = r.invoke(cli, ["diagnose", str(path / "fit.json"), str(path), "-o", str(path / "diag.json")]
                   + ([] if image else ["--no-image"]) + list(extra))
    if out.exit_code != 0:
        raise RuntimeError(out.output)
    return json.loads((path / "diag.json").read_text())


def named(d: dict) -> list[str]:
    """Labels diagnose claimed, both levels, without the axis suffix (distortion
    keeps its kind, runout its harmonic; on an arm the joint is part of the answer)."""
    if d.get("stage") == "fit-pose":
        return [e["effect"] for e in d["effects"]]
    out = []
    for e in d["effects"]:
        parts = e["effect"].split(":")
        out.append(e["effect"] if parts[0] == "detector_distortion" else
                   f"{parts[0]}:{parts[2]}" if parts[0] == "rotary_runout" else parts[0])
    return out
