"""The report's view of where a diagnosis located the mismatch: a table of
every located item (level, what, which variable it follows, shape, size)
and the per-frame curves with σ and the displacement field over the
detector, drawn before any effect is named."""

from __future__ import annotations

import html

import numpy as np

from .plots import _plt, _png

MAX_PANELS = 4


def _size(loc: dict) -> str:
    unit = loc.get("unit") or ""
    size = loc.get("size")
    if size is None:
        return ""
    text = f"{1e3 * size:.1f} µm" if unit == "mm" else f"{size:.4g} {unit}"
    if loc.get("size_px") is not None and unit != "px":
        text += f" ({loc['size_px']:.3f} px)"
    return text


def located_table(doc) -> str:
    """An HTML table of ``doc['located']``, empty when nothing was located."""
    items = doc.get("located") or []
    if not items:
        return "<p>Nothing located: no per-frame curve, detector field or image curve differs from the model " \
               "beyond the noise.</p>"
    rows = "".join(
        f"<tr><td>{html.escape(str(loc.get('level', 'geometry')))}</td>"
        f"<td>{html.escape(str(loc.get('component', '')))}</td>"
        f"<td>{html.escape(str(loc.get('variable', '')))}"
        + (f" (or {html.escape(', '.join(loc['also_follows']))})" if loc.get("also_follows") else "")
        + f"</td><td>{html.escape(str(loc.get('shape', '')))}</td><td class=num>{html.escape(_size(loc))}</td></tr>"
        for loc in items)
    return ("<h3>Where the model and the recording differ</h3>"
            "<table><tr><th>level</th><th>what</th><th>follows</th><th>shape</th><th>size (RMS)</th></tr>"
            + rows + "</table>")


def located_figure(doc) -> bytes | None:
    """Each located per-frame curve (value ± σ against the variable it
    follows, with the fitted shape) and the detector displacement field
    (arrows, scaled; colour: magnitude in px)."""
    items = doc.get("located") or []
    curves = [loc for loc in items if loc.get("series")][:MAX_PANELS]
    field = next((loc["field"] for loc in items if loc.get("field")), None)
    places = [loc for loc in items if loc.get("centre_px")]
    n = len(curves) + (field is not None or bool(places))
    if n == 0:
        return None
    plt = _plt()
    ncol = min(n, 3)
    nrow = -(-n // ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.6 * ncol, 3.1 * nrow), squeeze=False)
    axes = axes.ravel()
    for ax in axes[n:]:
        ax.set_visible(False)
    for ax, loc in zip(axes, curves):
        s = loc["series"]
        x, y, e, m = (np.asarray(s[k], float) for k in ("x", "value", "sigma", "model"))
        ax.errorbar(x, y, yerr=e, fmt="o", ms=2, lw=0.6, capsize=0, label="per frame ± σ")
        ax.plot(x, m, "-", lw=1.2, label=loc.get("shape", ""))
        ax.set_xlabel(s["x_variable"])
        ax.set_ylabel(f"{loc['component']} ({loc['unit']})", fontsize=7)
        ax.set_title(f"{loc['component']}", fontsize=8)
        ax.legend(fontsize=6)
    if field is not None:
        ax = axes[n - 1]
        U, V = np.meshgrid(field["u_px"], field["v_px"])
        du, dv = np.asarray(field["du"], float), np.asarray(field["dv"], float)
        mag = np.hypot(du, dv)
        q = ax.quiver(U, V, du, dv, mag, angles="xy", cmap="viridis")
        key = float(f"{mag.max():.1g}") if mag.max() > 0 else 1.0
        ax.quiverkey(q, 0.8, 1.05, key, f"{key:g} px", labelpos="E", fontproperties={"size": 7})
        fig.colorbar(q, ax=ax, label="displacement (px)")
        _detector_axes(ax, (U.min() - 0.1 * np.ptp(U), U.max() + 0.1 * np.ptp(U)),
                       (V.min() - 0.1 * np.ptp(V), V.max() + 0.1 * np.ptp(V)))
        ax.set_title(f"field, max {mag.max():.3f} px", fontsize=8, loc="left")
    if places:
        _draw_places(axes[n - 1], places, field is None)
    return _png(fig)


def _detector_axes(ax, cols: tuple, rows: tuple) -> None:
    """Axes in detector pixels over ``cols``, ``rows`` (low, high) px, rows
    downwards as in the image."""
    ax.set_xlim(*cols)
    ax.set_ylim(rows[1], rows[0])
    ax.set_aspect("equal")
    ax.set_xlabel("detector column (px)")
    ax.set_ylabel("detector row (px)")


def _draw_places(ax, places: list, alone: bool) -> None:
    """Each local place (``diagnose.local_field``): its extent as a circle
    and its displacement from around it as an arrow, labelled in px."""
    from matplotlib.patches import Circle

    for p in places:
        (c, r), rad = p["centre_px"], p["radius_px"]
        d = np.asarray(p["displacement_px"], float)
        ax.add_patch(Circle((c, r), rad, fill=False, color="tab:red", lw=1.2))
        # (drawn at the place's radius per px of displacement: the direction is what reads)
        k = 0.8 * rad / max(float(np.hypot(*d)), 1e-12)
        ax.annotate("", (c + k * d[0], r + k * d[1]), (c, r), arrowprops={"arrowstyle": "->", "color": "tab:red"})
        ax.text(c + rad, r - rad, f"{np.hypot(*d):.2f} px", color="tab:red", fontsize=7)
    if alone:
        xs = [p["centre_px"][0] for p in places]
        ys = [p["centre_px"][1] for p in places]
        pad = 3 * max(p["radius_px"] for p in places)
        _detector_axes(ax, (min(xs) - pad, max(xs) + pad), (min(ys) - pad, max(ys) + pad))
    title = "" if alone else ax.get_title(loc="left") + "\n"
    ax.set_title(title + "red: local places", fontsize=7, loc="left")
