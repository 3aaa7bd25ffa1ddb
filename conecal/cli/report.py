"""``conecal report``: what was estimated, how well."""

from __future__ import annotations

import click

from ..report.free import diagnosis_rms_line
from ..report.summary import geometry_rows, truth_lines
from ..jsonio import read_json


def _fmt(v, unit):
    if v is None:
        return "-"
    return f"{v:.6g}" if unit != "mm" else f"{v:.4f}"


def _truth_comparison(console, doc, path) -> None:
    for line in truth_lines(doc, path):
        console.print(f"  {line}")


def _summary(console, doc) -> None:
    rows = {k: (v, u) for k, v, u in geometry_rows(doc)}
    pick = [k for k in rows if k.startswith(("SOD", "SDD", "magnification", "principal", "detector tilt",
                                             "detector in-plane", "rotation axis", "reference sphere"))]
    for k in pick:
        v, u = rows[k]
        console.print(f"  {k}: {v} {u}".rstrip())


def _report_poses(console, path, doc) -> None:
    """fit-pose: frames kept and why others were rejected, accuracy, helix, robot placement."""
    from collections import Counter

    from ..documents.status import REASONS, reason_of, state_of

    import numpy as np
    from rich.table import Table

    sm = doc.get("summary", {})
    console.print(f"[bold]{path}[/] — fit-pose on {doc.get('scan', '?')}: {sm.get('ok')}/{sm.get('frames')} frames ok, "
                  f"reprojection RMS {sm.get('rms_px', float('nan')):.4f} px")
    reasons = Counter((state_of(f), reason_of(f)) for f in doc["frames"] if state_of(f) != "ok")
    for (state, why), n in reasons.most_common():
        console.print(f"  [yellow]{n} {state}[/]: {REASONS.get(why, why)}")
    if doc.get("motion") == "free":
        from ..report.free import free_terminal

        free_terminal(console, doc)
    ok = [f for f in doc["frames"] if f["status"] == "ok"]
    if ok:
        sr = np.array([f["sigma_rotation_deg"] for f in ok])
        st = np.array([f["sigma_translation_mm"] for f in ok])
        console.print(f"  per-frame 1σ: rotation {np.median(np.linalg.norm(sr, axis=1)):.4f} deg, "
                      f"translation {np.median(np.linalg.norm(st, axis=1)):.4f} mm (medians)")
    h = doc.get("helix")
    if h:
        console.print(f"  holder helix: radius {h['radius_mm']:.4f} mm, pitch {h['pitch_mm_per_turn']:.4f} mm/turn, "
                      f"{h['handedness']}-handed, CAD residual {h['rms_mm']:.4f} mm RMS "
                      f"(worst sphere {max(h['residual_mm']):.4f} mm)")
    pl = doc.get("placement")
    if pl:
        t = Table(title="robot placement error (fitted vs joint log)", title_justify="left")
        for c in ("", "x", "y", "z"):
            t.add_column(c, justify="right")
        t.add_row("offset mean mm", *(f"{v:.3f}" for v in pl["offset_mean_mm"]))
        t.add_row("offset std mm", *(f"{v:.3f}" for v in pl["offset_std_mm"]))
        console.print(t)
        console.print(f"  rotation {pl['rotation_mean_deg']:.3f} ± {pl['rotation_std_deg']:.3f} deg "
                      f"(max {pl['rotation_max_deg']:.3f}); largest offset {pl['offset_max_mm']:.3f} mm")
    ba = doc.get("bundle_adjustment")
    if ba:
        console.print("  bundle adjustment: " + ", ".join(
            f"{n} {p['value']:+.4f} ± {p['sigma']:.4f} mm" for n, p in ba["parameters"].items()))


@click.command("report")
@click.argument("results", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("-o", "--output", "out_dir", type=click.Path(file_okay=False), default=None,
              help="Also write a self-contained HTML report, OUT_DIR/index.html (needs matplotlib).")
@click.option("--reconstruct", is_flag=True,
              help="HTML: for rp-grid results, FDK slices with the nominal and the corrected geometry (needs itk-rtk).")
def command(results, out_dir, reconstruct):
    """Summarise fit RESULTS (conecal-geometry/1, conecal-poses/1) on the terminal.

    One table per result: each parameter's initial and final value with its
    1-sigma uncertainty, the reprojection RMS, and warnings about
    parameters the data do not determine. With -o, the same as an HTML
    page with figures: residual vectors on the detector, residuals per
    frame and per marker, the set-up in 3D, rp-grid cost slices, robot
    placement errors.

    \b
    Examples:
      conecal report demo/geometry.json
      conecal report demo/geometry.json demo/rot.json -o demo/report
    """
    from rich.console import Console
    from rich.table import Table

    console = Console()
    for path in results:
        doc = read_json(path, ("conecal-geometry", "conecal-poses", "conecal-diagnosis"))
        if doc["format"].startswith("conecal-diagnosis"):
            console.print(f"[bold]{path}[/] — diagnose: {doc['verdict']}")
            console.print(f"  {diagnosis_rms_line(doc)}")
            if "before" in doc:   # fit-pose: the holder's pose against the arm's model
                b, a = doc["before"], doc["after"]
                console.print(f"  holder pose RMS {b['rms_translation_mm']:.4f} -> {a['rms_translation_mm']:.4f} mm, "
                              f"{b['rms_rotation_deg']:.4f} -> {a['rms_rotation_deg']:.4f} deg")
            img = doc.get("image_level") or {}
            if "chi2_per_dof_before" in img:
                console.print(f"  image level: chi2/dof {img['chi2_per_dof_before']:.4f} -> "
                              f"{img['chi2_per_dof_after']:.4f} over {img['n_patches']} marker patches")
            continue
        if doc["format"].startswith("conecal-poses"):
            _report_poses(console, path, doc)
            continue
        fit = doc.get("fit", {})
        table = Table(title=f"{path} — {doc.get('stage', '?')} on {doc.get('scan', '?')}", title_justify="left")
        for col in ("parameter", "unit", "initial", "final", "± 1σ", ""):
            table.add_column(col, justify="right" if col not in ("parameter", "unit", "") else "left")
        params = sorted(fit.get("parameters", {}).items(), key=lambda kv: kv[1].get("index", 0))
        for name, p in params:
            if not p.get("free"):
                continue
            sig = p.get("sigma")
            note = "" if p.get("determined", True) else "[bold red]undetermined"
            table.add_row(name, p.get("unit", ""), _fmt(p.get("initial"), p.get("unit")), _fmt(p.get("value"), p.get("unit")),
                          "∞" if sig is None or sig == float("inf") else f"{sig:.2g}", note)
        console.print(table)
        rms = fit.get("rms_px")
        if doc.get("stage") == "rp-grid":
            pl = fit.get("planes", {})
            console.print(f"  redundant-plane cost {fit.get('cost_nominal', float('nan')):.4g} (nominal) -> "
                          f"{fit.get('cost_final', float('nan')):.4g} over {pl.get('used')} planes of {pl.get('pairs')} "
                          f"view pairs; dropped: {pl.get('truncated')} truncated, {pl.get('holder')} through a holder "
                          f"(seen in {pl.get('holder_views')} views)")
            if fit.get("at_search_bound"):
                console.print(f"  [bold red]warning:[/] on the search bound: {', '.join(fit['at_search_bound'])}")
            _summary(console, doc)
            _truth_comparison(console, doc, path)
            if fit.get("undetermined"):
                console.print(f"  [bold red]warning:[/] the data do not determine {', '.join(fit['undetermined'])}")
            continue
        console.print(f"  reprojection RMS [bold]{rms:.4f} px[/] over {fit.get('n_observations')} markers, "
                      f"reduced χ² {fit.get('chi2_reduced', float('nan')):.2f}, outliers {fit.get('outliers', 0)}, "
                      f"start: {fit.get('start')}")
        src = doc["source"]
        det = doc["detector"]
        console.print(f"  source {[round(x, 4) for x in src]} mm; detector origin {[round(x, 4) for x in det['origin']]} mm")
        _summary(console, doc)
        _truth_comparison(console, doc, path)
        if fit.get("undetermined"):
            console.print(f"  [bold red]warning:[/] the data do not determine {', '.join(fit['undetermined'])}")
            for combo in fit.get("null_combinations", []):
                console.print(f"    free combination: {combo}")
    if out_dir is not None:
        from ..report import write_report
        from .options import info

        page = write_report(list(results), out_dir, reconstruct=reconstruct)
        info(f"wrote {page}")
