"""``conecal simulate``: write a simulated scan directory with its truth."""

from __future__ import annotations

import click

from ..effects import REGISTRY, parse_effect
from ..errors import InputError
from ..simulate import BUILDERS, write_scan
from .options import info, progress_bar


def _system_of(scan_dir) -> dict:
    """Builder arguments that reproduce another simulated scan's system."""
    from pathlib import Path

    from ..geometry import ConeGeometry
    from ..jsonio import read_json
    from ..scan import load_config

    cfg = load_config(Path(scan_dir) / "scan.yaml")
    truth = read_json(Path(scan_dir) / "truth.json", "conecal-truth")
    g = ConeGeometry.from_dict(truth["geometry"])
    return {"rows": cfg.detector.rows, "cols": cfg.detector.cols, "pitch": cfg.detector.pixel_pitch[0],
            "sod": cfg.nominal.sod, "sdd": cfg.nominal.sdd, "true_geometry": g}


@click.command("simulate")
@click.argument("kind", type=click.Choice(sorted(BUILDERS)))
@click.argument("out", type=click.Path(file_okay=False))
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed (geometry errors, noise).")
@click.option("--frames", type=click.IntRange(2, 100000), default=None, help="Number of frames (rotation, robot, circular).")
@click.option("--photons", type=click.FloatRange(0), default=None, help="Photons per pixel in the flat field; 0 = noiseless.")
@click.option("--blur-px", type=click.FloatRange(0), default=None, help="Focal-spot/detector blur, Gaussian sigma in px.")
@click.option("--values", type=click.Choice(["attenuation", "transmission", "raw"]), default="attenuation", show_default=True)
@click.option("--effect", "effects", multiple=True, metavar="NAME[:K=V,...]",
              help=f"Switch on a physical effect (repeatable). Known: {', '.join(sorted(REGISTRY))}.")
@click.option("--dense-holder", is_flag=True, help="Add a dense object holder (robot, circular).")
@click.option("--trajectory", type=click.Choice(["turntable", "sweep"]), default=None,
              help="Robot only: 'turntable' (default; the flange turns the holder, other joints wiggle) or "
                   "'sweep' (the elbow also swivels +-60 deg with the holder held in place, one placement error: "
                   "varying load, speeds and directions, for diagnose).")
@click.option("--schedule", type=click.Choice(["uniform", "sweep"]), default=None,
              help="Rotation: step evenly through a turn, or swing back and forth at varying speed.")
@click.option("--truncation", type=click.Choice(["axial", "transaxial"]), default=None,
              help="Circular: an object taller (axial) or wider (transaxial) than the detector sees.")
@click.option("--misalignment", default=None, metavar="random|U,V,ETA,THETA,PHI",
              help="Circular: detector shift (px) and rotations (deg) about its centre, or 'random' "
                   "(shifts within 15 px, angles within 3 deg).")
@click.option("--same-system-as", "same_as", type=click.Path(file_okay=False), default=None,
              help="A simulated scan directory whose true source, detector and nominal set-up to reuse "
                   "(linear and rotation only): two scans of one system.")
@click.option("--phantom", type=click.Choice(["grid", "grid_marked", "balls"]), default=None,
              help="Free only: a planar 5x5 grid, the grid without one corner sphere, or a 3-D ball phantom.")
@click.option("--distortion", type=click.Choice(["intensifier", "none"]), default=None,
              help="Free only: image-intensifier distortion (default) or none.")
@click.option("--guess", default=None, metavar="DEG,MM",
              help="Free only: write a rough pose guess (rx..tz) to log.csv, wrong by DEG degrees and MM mm.")
@click.option("--overwrite", is_flag=True,
              help="Replace OUT if it is a scan directory that conecal simulate wrote (or empty). A directory "
                   "holding anything else, a link, the current directory or one of its parents is refused "
                   "(exit 2) and nothing is touched.")
def command(kind, out, seed, frames, photons, blur_px, values, effects, dense_holder, trajectory, schedule, truncation,
            misalignment, same_as, phantom, distortion, guess, overwrite):
    """Simulate a scan of KIND (linear | rotation | robot | circular | free) into OUT.

    Writes scan.yaml, log.csv, projections.tif (exact line integrals,
    supersampled pixels, blur, Poisson noise, sloped background) and
    truth.json with the true geometry and exact marker centres.

    \b
    Examples:
      conecal simulate linear demo/linear
      conecal simulate rotation demo/rot --frames 36 --effect rotary_wobble:amplitude=0.05
      conecal simulate robot demo/robot --seed 3 --dense-holder
      conecal simulate robot demo/arm --trajectory sweep --effect robot_deflection:compliance=0.002
      conecal simulate free demo/carm --phantom grid_marked --guess 20,10
    """
    kw = {}
    if frames is not None:
        if kind == "linear":
            raise InputError("--frames: a linear raster has its frame count from its raster (3x3x3)")
        kw["n_frames"] = frames
    if dense_holder:
        if kind not in ("robot", "circular"):
            raise InputError("--dense-holder: only for robot and circular scans")
        kw["dense_holder"] = True
    if trajectory is not None:
        if kind != "robot":
            raise InputError("--trajectory: only for robot scans")
        kw["trajectory"] = trajectory
    if schedule is not None:
        if kind != "rotation":
            raise InputError("--schedule: only for rotation scans")
        kw["schedule"] = schedule
    if (truncation or misalignment) and kind != "circular":
        raise InputError("--truncation, --misalignment: only for circular scans")
    if truncation:
        kw["truncation"] = truncation
    if misalignment == "random":
        kw["random_misalignment"] = True
    elif misalignment is not None:
        try:
            vals = [float(x) for x in misalignment.split(",")]
        except ValueError:
            raise InputError(f"--misalignment {misalignment}: expected 'random' or five numbers") from None
        if len(vals) != 5:
            raise InputError(f"--misalignment {misalignment}: expected five numbers U,V,ETA,THETA,PHI")
        kw["shift_px"], kw["rotation_deg"] = tuple(vals[:2]), tuple(vals[2:])
    if (phantom or distortion or guess) and kind != "free":
        raise InputError("--phantom, --distortion, --guess: only for free scans")
    if phantom:
        kw["phantom"] = phantom
    if distortion:
        kw["distortion"] = distortion
    if guess is not None:
        try:
            vals = tuple(float(x) for x in guess.split(","))
        except ValueError:
            vals = ()
        if len(vals) != 2 or min(vals) < 0:
            raise InputError(f"--guess {guess}: expected two numbers DEG,MM >= 0")
        kw["guess_error"] = vals
    if same_as is not None:
        if kind not in ("linear", "rotation"):
            raise InputError("--same-system-as: only for linear and rotation scans")
        kw.update(_system_of(same_as))
    sc = BUILDERS[kind](seed, **kw)
    if photons is not None:
        sc.photons = photons
    if blur_px is not None:
        sc.blur_px = blur_px
    sc.apply_effects([parse_effect(e) for e in effects])
    with progress_bar(f"simulate {kind}") as prog:
        path = write_scan(sc, out, seed=seed, values=values, overwrite=overwrite, progress=prog)
    info(f"wrote {path} ({sc.n_frames} frames, {sc.geometry.shape[1]}x{sc.geometry.shape[0]} px)")
