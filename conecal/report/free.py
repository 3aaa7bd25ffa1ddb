"""Report pieces for a free-pose calibration (``fit-pose`` on ``motion: free``)."""

from __future__ import annotations

import html

import numpy as np

from ..geometry.distortion import Distortion
from .plots import _plt, _png


def distortion_field(doc) -> bytes | None:
    """Heat map of |displacement| with a colour bar and arrows (px)."""
    d = doc.get("distortion")
    if not d:
        return None
    plt = _plt()
    rows, cols = doc["detector"]["shape"]
    dist = Distortion.from_dict(d)
    dc, dr = dist.field((rows, cols))
    mag = np.hypot(dc, dr)
    fig, ax = plt.subplots(figsize=(5.6, 4.6))
    im = ax.imshow(mag, cmap="viridis", origin="upper", extent=(-0.5, cols - 0.5, rows - 0.5, -0.5))
    fig.colorbar(im, ax=ax, label="|displacement| (px)")
    step = max(rows, cols) // 16
    r, c = np.mgrid[step // 2:rows:step, step // 2:cols:step]
    ax.quiver(c, r, dc[r, c], dr[r, c], color="white", angles="xy", scale_units="xy",
              scale=max(float(mag.max()), 1e-9) / (0.8 * step))
    ax.plot(*dist.centre, "r+", ms=10, label="distortion centre")
    pp = (doc["intrinsics"]["c0"]["value"], doc["intrinsics"]["r0"]["value"])
    ax.plot(*pp, "wx", ms=8, label="principal point")
    ax.legend(loc="lower right", fontsize=7)
    ax.set_xlabel("column (px)")
    ax.set_ylabel("row (px)")
    ax.set_title(f"detector distortion: {d.get('family', d['model'])} (arrows: measured − ideal)", fontsize=9)
    return _png(fig)


def rms_before_after(doc) -> bytes | None:
    frames = [f for f in doc.get("frames", []) if f.get("rms_px") is not None]
    if not frames:
        return None
    plt = _plt()
    fr = [f["frame"] for f in frames]
    fig, ax = plt.subplots(figsize=(7, 3))
    if any("rms_px_pinhole" in f for f in frames):
        ax.plot(fr, [f.get("rms_px_pinhole", np.nan) for f in frames], "o", ms=4, label="pinhole (no distortion)")
    ax.plot(fr, [f["rms_px"] for f in frames], "s", ms=4, label="chosen model")
    bad = [f for f in frames if f["status"] != "ok"]
    if bad:
        ax.plot([f["frame"] for f in bad], [f["rms_px"] for f in bad], "rx", ms=8, label="not ok")
    ax.set_yscale("log")
    ax.set_xlabel("frame")
    ax.set_ylabel("reprojection RMS (px)")
    ax.legend(fontsize=7)
    return _png(fig)


def frame_intrinsics(doc) -> bytes | None:
    """sdd and principal point per frame with 1-sigma bars, when freed per frame."""
    frames = [f for f in doc.get("frames", []) if f.get("intrinsics")]
    if not frames:
        return None
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(9, 2.8))
    shared = doc["intrinsics"]
    for ax, (n, unit) in zip(axes, (("sdd", "mm"), ("c0", "px"), ("r0", "px"))):
        x = [f["frame"] for f in frames]
        ax.errorbar(x, [f["intrinsics"][n]["value"] for f in frames],
                    [f["intrinsics"][n]["sigma"] for f in frames], fmt="o", ms=3, lw=0.8)
        ax.axhline(shared[n]["value"], color="k", lw=0.8, ls="--", label="shared")
        ax.set_xlabel("frame")
        ax.set_ylabel(f"{n} ({unit})")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    return _png(fig)


def _num(v, f="{:.4g}"):
    return "–" if v is None else f.format(v)


def free_html(doc) -> tuple[list[str], list]:
    """HTML paragraphs/tables and (png, caption) figures."""
    it = doc["intrinsics"]
    rows = "".join(f"<tr><td>{n}</td><td>{p['unit']}</td><td class=num>{p['value']:.6g}</td>"
                   f"<td class=num>{p['sigma']:.3g}</td><td class=num>{_num(p.get('sigma_statistical'), '{:.3g}')}</td>"
                   f"<td class=num>{_num(p.get('sigma_model'), '{:.3g}')}</td></tr>" for n, p in it.items())
    parts = ["<table><tr><th>intrinsic</th><th>unit</th><th>value</th><th>± 1σ</th><th>statistical</th>"
             f"<th>model</th></tr>{rows}</table>"]
    d = doc.get("distortion")
    if d:
        sig = d.get("sigma", {})
        prow = "".join(f"<tr><td>{html.escape(k)}</td><td class=num>{v:.4g}</td><td class=num>{_num(sig.get(k))}</td>"
                       f"</tr>" for k, v in d["parameters"].items() if v or sig.get(k))
        parts.append(f"<p>Distortion <b>{html.escape(d.get('family', d['model']))}</b> (model {d['model']}, "
                     f"centre ({d['centre'][0]:.1f}, {d['centre'][1]:.1f}) px, up to {d['max_displacement_px']:.3f} "
                     f"px; coefficients in px at the normalising radius {d['radius_px']:.1f} px):</p>"
                     f"<table><tr><th>term</th><th>value</th><th>± 1σ</th></tr>{prow}</table>")
    else:
        parts.append("<p>No detector distortion claimed (the held-out markers chose none).</p>")
    ch = "".join(f"<tr><td>{html.escape(r['family'])}</td><td class=num>{r.get('parameters', '')}</td>"
                 f"<td class=num>{_num(r.get('heldout_rms_px'))}</td><td class=num>{_num(r.get('behind_chosen_chi2'))}"
                 f" ± {_num(r.get('behind_se'))}</td><td>{'chosen' if r.get('chosen') else ''}</td></tr>"
                 for r in doc.get("distortion_choice", []))
    parts.append("<p>Distortion families on held-out markers (behind: paired held-out χ² difference to the chosen):"
                 f"</p><table><tr><th>family</th><th>parameters</th><th>held-out RMS px</th><th>behind</th><th></th>"
                 f"</tr>{ch}</table>")
    ref = doc.get("phantom_refinement")
    if ref:
        verdict = "kept" if ref["chosen"] else "not kept"
        parts.append(f"<p>Phantom refined (each sphere's offset from phantom.csv, prior σ {ref['prior_sigma_mm']:g} mm): "
                     f"{verdict}; held-out RMS {ref['heldout_rms_px_cad']:.3f} px with the CAD positions, "
                     f"{ref['heldout_rms_px_refined']:.3f} px refined.</p>")
        if ref.get("spheres"):
            srow = "".join(f"<tr><td>{r['id']}</td><td class=num>{', '.join(f'{v:+.3f}' for v in r['offset_mm'])}</td>"
                           f"<td class=num>{', '.join(f'{v:.3f}' for v in r['sigma_mm'])}</td></tr>"
                           for r in ref["spheres"])
            parts.append("<details><summary>Each sphere's offset from phantom.csv (mm, phantom frame)</summary>"
                         "<table><tr><th>id</th><th>offset x, y, z</th><th>± 1σ</th></tr>" + srow + "</table></details>")
    sm = doc.get("summary", {})
    if sm.get("adequacy"):
        parts.append(f"<p>Adequacy: {html.escape(sm['adequacy'])}.</p>")
    parts.append(f"<p>Gauge: {html.escape(doc.get('gauge', ''))}.</p>")
    fr_rows = []
    for f in doc.get("frames", []):
        sr, st = f.get("sigma_rotation_deg"), f.get("sigma_translation_mm")
        fr_rows.append(
            f"<tr><td>{f['frame']}</td><td>{html.escape(f['status'][:90])}</td><td class=num>{f.get('n_spheres', '')}</td>"
            f"<td class=num>{_num(f.get('rms_px_pinhole'))}</td><td class=num>{_num(f.get('rms_px'))}</td>"
            f"<td class=num>{', '.join(f'{v:.3g}' for v in sr) if sr else '–'}</td>"
            f"<td class=num>{', '.join(f'{v:.3g}' for v in st) if st else '–'}</td></tr>")
    parts.append("<details><summary>Per frame: status, spheres, RMS (px) pinhole → chosen, 1σ of the pose</summary>"
                 "<table><tr><th>frame</th><th>status</th><th>spheres</th><th>RMS pinhole</th><th>RMS</th>"
                 "<th>σ rotation (deg; x, y, z)</th><th>σ translation (mm; x, y, z)</th></tr>"
                 + "".join(fr_rows) + "</table></details>")
    figs = [(distortion_field(doc), "Detector distortion field (colour: magnitude in px; arrows: direction)."),
            (rms_before_after(doc), "Reprojection RMS per frame: pinhole model vs the chosen model."),
            (frame_intrinsics(doc), "Intrinsics freed per frame (--frame-intrinsics): each frame's value with its "
                                    "1σ; dashed: the shared value, the centre of the per-frame prior.")]
    return parts, figs


def free_terminal(console, doc) -> None:
    it = doc["intrinsics"]
    console.print("  " + ", ".join(f"{n} {p['value']:.4f} ± {p['sigma']:.4f} {p['unit']} (model part "
                                   f"{_num(p.get('sigma_model'), '{:.3g}')})" for n, p in it.items()))
    d = doc.get("distortion")
    console.print(f"  distortion: {d['family']} up to {d['max_displacement_px']:.3f} px" if d else
                  "  distortion: none claimed")
    sm = doc.get("summary", {})
    console.print(f"  {sm.get('ambiguous', 0)} ambiguous, {sm.get('rejected', 0)} rejected")


def diagnosis_rms_line(doc: dict) -> str:
    """The residual sentence of a diagnosis: before -> after against the noise
    floor, or (free-pose: nothing refitted) the RMS and the reduced chi2."""
    if doc.get("rms_px_before") is not None and doc.get("rms_px_after") is not None:
        floor = doc.get("noise_floor_px")
        return (f"residual RMS {doc['rms_px_before']:.4f} -> {doc['rms_px_after']:.4f} px"
                + (f" (noise floor {floor:.4f} px)" if floor is not None else ""))
    if doc.get("rms_px") is not None:
        chi2 = doc.get("chi2_reduced")
        return f"residual RMS {doc['rms_px']:.4f} px" + (f", reduced chi2 {chi2:.2f}" if chi2 is not None else "")
    return "residual RMS not stated"
