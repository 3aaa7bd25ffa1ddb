"""A self-contained HTML report: parameter tables and figures embedded as PNG.

The page needs nothing but itself (no scripts or styles fetched); a small
inline script records, once the page has loaded, how many figures decoded
(``data-figures-loaded`` against ``data-figures`` on ``<body>``), so a
headless browser can check the page.
"""

from __future__ import annotations

import base64
import html
from pathlib import Path

import numpy as np

from .. import __version__
from ..binding import bound_scans
from ..jsonio import atomic_write_text, read_json
from . import plots
from .free import diagnosis_rms_line
from .located import located_figure, located_table
from .summary import geometry_rows, truth_lines

FORMATS = ("conecal-geometry", "conecal-poses", "conecal-diagnosis")

_STYLE = """
body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;color:#222}
h1{font-size:1.5em} h2{font-size:1.2em;border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:2em}
table{border-collapse:collapse;font-size:.9em;margin:.5em 0} td,th{padding:.2em .7em;border-bottom:1px solid #eee}
th{text-align:left;background:#f4f4f4} td.num{text-align:right;font-family:monospace}
.warn{color:#b00;font-weight:bold} figure{margin:1em 0} figcaption{font-size:.85em;color:#555}
img{max-width:100%}
"""

_SCRIPT = """
window.addEventListener('load', function () {
  var imgs = document.querySelectorAll('img.figure'), ok = 0;
  imgs.forEach(function (im) { if (im.complete && im.naturalWidth > 0) ok++; });
  document.body.setAttribute('data-figures-loaded', String(ok));
});
"""


def _fmt(v, unit=""):
    if v is None:
        return "∞" if unit == "sigma" else "–"
    if isinstance(v, float) and not np.isfinite(v):
        return "∞"
    return f"{v:.6g}"


def _figure(png: bytes | None, caption: str) -> str:
    if png is None:
        return ""
    data = base64.b64encode(png).decode("ascii")
    return (f'<figure><img class="figure" alt="{html.escape(caption)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")


def _param_table(fit: dict) -> str:
    params = sorted(fit.get("parameters", {}).items(), key=lambda kv: kv[1].get("index", 0))
    rows = []
    for name, p in params:
        if not p.get("free", True):
            continue
        note = "" if p.get("determined", True) else '<span class="warn">undetermined</span>'
        rows.append(f"<tr><td>{html.escape(name)}</td><td>{html.escape(str(p.get('unit', '')))}</td>"
                    f"<td class=num>{_fmt(p.get('initial'))}</td><td class=num>{_fmt(p.get('value'))}</td>"
                    f"<td class=num>{_fmt(p.get('sigma'), 'sigma')}</td><td>{note}</td></tr>")
    if not rows:
        return ""
    return ("<table><tr><th>parameter</th><th>unit</th><th>initial</th><th>final</th><th>± 1σ</th><th></th></tr>"
            + "".join(rows) + "</table>")


def _summary_table(doc, path) -> str:
    rows = "".join(f"<tr><td>{html.escape(k)}</td><td class=num>{html.escape(v)}</td><td>{html.escape(u)}</td></tr>"
                   for k, v, u in geometry_rows(doc))
    truth = "".join(f"<li>{html.escape(line)}</li>" for line in truth_lines(doc, path))
    return (f"<table><tr><th>set-up (lab frame)</th><th>value</th><th>unit</th></tr>{rows}</table>"
            + (f"<p>Against the simulation's truth:</p><ul>{truth}</ul>" if truth else ""))


def _geometry_section(path, doc, extra_figures) -> tuple[str, int]:
    fit = doc.get("fit", {})
    stage = doc.get("stage", "?")
    parts = [f"<h2>{html.escape(str(path))} — {html.escape(stage)} on {html.escape(str(doc.get('scan', '?')))}</h2>"]
    parts.append(_summary_table(doc, path))
    parts.append(_param_table(fit))
    if stage == "rp-grid":
        pl = fit.get("planes", {})
        parts.append(f"<p>Redundant-plane cost {_fmt(fit.get('cost_nominal'))} (nominal geometry) → "
                     f"{_fmt(fit.get('cost_final'))} over {pl.get('used')} planes of {pl.get('pairs')} view pairs; "
                     f"dropped automatically: {pl.get('truncated')} planes through truncated borders, "
                     f"{pl.get('holder')} through a holder (found in {pl.get('holder_views')} views).</p>")
    elif fit.get("rms_px") is not None:
        parts.append(f"<p>Reprojection RMS <b>{fit['rms_px']:.4f} px</b> over {fit.get('n_observations')} markers, "
                     f"reduced χ² {_fmt(fit.get('chi2_reduced'))}, outliers {fit.get('outliers', 0)}, "
                     f"start: {html.escape(str(fit.get('start')))}, {fit.get('function_evaluations')} function "
                     f"evaluations, converged: {fit.get('converged')}.</p>")
    if fit.get("undetermined"):
        parts.append(f'<p class="warn">The data do not determine: {html.escape(", ".join(fit["undetermined"]))}</p>')
    figs = [(plots.residual_vectors(doc), "Residual vectors at the measured marker positions."),
            (plots.residuals_vs_frame(doc), "Residuals against frame, and RMS per marker."),
            (plots.cost_slices(doc), "rp-grid: the cost along each parameter through the optimum "
                                     "(cf. the paper's Figures 7 and 8)."),
            (plots.convergence(doc), "Convergence: χ² at each evaluation of the least-squares solver."),
            (plots.geometry_sketch(doc), "Source, detector and axes in the lab frame.")] + extra_figures
    figs = [(p, c) for p, c in figs if p is not None]
    parts += [_figure(p, c) for p, c in figs]
    return "\n".join(parts), len(figs)


def _poses_section(path, doc) -> tuple[str, int]:
    sm = doc.get("summary", {})
    parts = [f"<h2>{html.escape(str(path))} — fit-pose on {html.escape(str(doc.get('scan', '?')))}</h2>",
             f"<p>{sm.get('ok')}/{sm.get('frames')} frames ok, reprojection RMS {_fmt(sm.get('rms_px'))} px.</p>",
             _summary_table(doc, path)]
    pl = doc.get("placement")
    if pl:
        parts.append(f"<p>Robot placement error: offset mean {np.round(pl['offset_mean_mm'], 3).tolist()} mm, "
                     f"std {np.round(pl['offset_std_mm'], 3).tolist()} mm, rotation "
                     f"{pl['rotation_mean_deg']:.3f} ± {pl['rotation_std_deg']:.3f} deg.</p>")
    figs = [(plots.placement(doc), "Robot placement error and reprojection RMS per frame."),
            (plots.geometry_sketch(doc), "Source and detector in the lab frame.")]
    if doc.get("motion") == "free":
        from .free import free_html

        extra, more = free_html(doc)
        parts += extra
        figs = more + figs
    figs = [(p, c) for p, c in figs if p is not None]
    parts += [_figure(p, c) for p, c in figs]
    return "\n".join(parts), len(figs)


def _diagnosis_section(path, doc) -> tuple[str, int]:
    parts = [f"<h2>{html.escape(str(path))} — diagnose {html.escape(str(doc.get('stage', '')))} on "
             f"{html.escape(str(doc.get('scan', '?')))}</h2>",
             f"<p><b>{html.escape(doc.get('verdict', ''))}</b></p>",
             f"<p>{html.escape(diagnosis_rms_line(doc)).replace('->', '→').capitalize()}; held-out χ² gain "
             f"{doc.get('heldout_gain_chi2') or 0:.1f}.</p>"]
    if "before" in doc:   # fit-pose: the holder's pose against the arm's model
        b, a = doc["before"], doc["after"]
        parts.append(f"<p>Holder pose RMS {b['rms_translation_mm']:.4f} → {a['rms_translation_mm']:.4f} mm, "
                     f"{b['rms_rotation_deg']:.4f} → {a['rms_rotation_deg']:.4f} deg; the arm's repeatability "
                     f"(estimated) {', '.join(f'{x:.4f}' for x in a['repeatability']['translation_mm'])} mm.</p>")
    # where first, then what: the located curves before any candidate effect
    parts.append(located_table(doc))
    loc_png = located_figure(doc)
    if loc_png is not None:
        parts.append(_figure(loc_png, "Located: each curve freed per frame (± σ) against the variable it follows, "
                                      "with the shape that predicts it on held-out frames; the residual "
                                      "displacement field over the detector."))
    rows = "".join(f"<tr><td>{html.escape(c['effect'])}</td><td class=num>{c['heldout_gain_chi2']:.1f}</td>"
                   f"<td class=num>{c['bic_gain']:.1f}</td><td>{'yes' if c['claimable'] else ''}</td></tr>"
                   for c in doc.get("candidates", []))
    parts.append("<table><tr><th>candidate</th><th>held-out χ² gain</th><th>BIC gain</th><th>beats noise</th></tr>"
                 + rows + "</table>")
    png = plots.diagnosis(doc)
    parts.append(_figure(png, "Residuals against time before and after modelling the effect (dashed: ±2σ noise)."))
    n = int(png is not None) + int(loc_png is not None)
    img = doc.get("image_level") or {}
    if img.get("candidates"):
        rows = "".join(f"<tr><td>{html.escape(c['effect'])}</td><td class=num>{c['heldout_gain_chi2']:.1f}</td>"
                       f"<td class=num>{c['bic_gain']:.1f}</td><td>{'yes' if c['claimable'] else ''}</td></tr>"
                       for c in img["candidates"])
        parts.append(f"<h3>Image level</h3><p>{html.escape(img.get('verdict', ''))}; {img.get('n_patches', 0)} "
                     f"marker patches, noise {img.get('noise_floor_attenuation', 0):.4f} (attenuation).</p>"
                     "<table><tr><th>candidate</th><th>held-out χ² gain</th><th>BIC gain</th><th>beats noise</th></tr>"
                     + rows + "</table>")
        png2 = plots.image_profiles(doc)
        if png2 is not None:
            parts.append(_figure(png2, "Recorded minus rendered shadow against distance from its centre, before and "
                                       "after modelling the image effect (bars: ±2 standard errors)."))
            n += 1
    return "\n".join(parts), n


def reconstruction_figure(doc, path) -> tuple[bytes, dict] | None:
    """FDK (itk-rtk) of the scan behind an rp-grid result, nominal vs corrected:
    central slices and their sharpness. None when not possible here."""
    from ..geometry.misalignment import NAMES, misaligned
    from ..errors import InputError
    from ..scan import load_scan

    if doc.get("stage") != "rp-grid":
        return None
    try:
        from ..export.rtk import fdk_scan, sharpness

        scan = load_scan(bound_scans(doc, path)[0])
    except (InputError, KeyError):
        return None
    nominal = scan.nominal_geometry()
    p = np.array([doc["misalignment"][n]["value"] for n in NAMES])
    rows, cols = nominal.shape
    vox = nominal.pixel_pitch[0] * np.linalg.norm(nominal.source) / nominal.sdd
    n = int(min(rows, cols) * 0.7)
    vols = fdk_scan(scan, [misaligned(nominal, q) for q in (np.zeros(5), p)], step=max(1, scan.n_frames // 180),
                    size=(n, n, 3), spacing=vox)
    sh = [sharpness(v) for v in vols]
    png = plots.slices([v[1] for v in vols], [f"nominal geometry (sharpness {sh[0]:.4f})",
                                             f"rp-grid geometry (sharpness {sh[1]:.4f})"])
    return png, {"nominal": sh[0], "rp_grid": sh[1]}


def write_report(results: list, out_dir, *, reconstruct: bool = False) -> Path:
    """Write ``out_dir/index.html`` for the result files; returns its path."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    sections, n_fig = [], 0
    for path in results:
        doc = read_json(path, FORMATS)
        if doc["format"].startswith("conecal-poses"):
            sec, n = _poses_section(path, doc)
        elif doc["format"].startswith("conecal-diagnosis"):
            sec, n = _diagnosis_section(path, doc)
        else:
            extra = []
            if reconstruct:
                rec = reconstruction_figure(doc, path)
                if rec is not None:
                    extra.append((rec[0], "FDK (itk-rtk) central slice with the nominal and the corrected geometry; "
                                          "sharpness = gradient energy / signal energy (higher is sharper)."))
            sec, n = _geometry_section(path, doc, extra)
        sections.append(sec)
        n_fig += n
    page = (f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>conecal report</title>'
            f"<style>{_STYLE}</style><script>{_SCRIPT}</script></head>"
            f'<body data-figures="{n_fig}"><h1>conecal report</h1>'
            f"<p>conecal {__version__}; {len(results)} result file(s). Lengths in mm, angles in degrees, "
            f"residuals in px (measured − predicted), σ at 1σ.</p>" + "\n".join(sections) + "</body></html>")
    target = out_dir / "index.html"
    atomic_write_text(target, page)
    return target
