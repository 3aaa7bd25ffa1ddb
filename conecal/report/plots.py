"""The report's figures (matplotlib, rendered off-screen to PNG bytes).

Each function takes a result document and returns PNG bytes, or None when
the document has nothing to show for that figure.
"""

from __future__ import annotations

import io

import numpy as np


def _plt():
    try:
        import matplotlib
    except ImportError:  # pragma: no cover - depends on the environment
        from ..errors import InputError

        raise InputError("the HTML report needs matplotlib: pip install 'conecal[plots]'") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _png(fig) -> bytes:
    plt = _plt()
    buf = io.BytesIO()
    import warnings

    with warnings.catch_warnings():   # labels of neighbouring panels must not overlap
        warnings.simplefilter("ignore")
        try:
            fig.tight_layout()
        except (ValueError, RuntimeError):
            pass
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def _residuals(doc):
    res = doc.get("residuals") or []
    res = [r for r in res if "dx" in r]
    if not res:
        return None
    return {k: np.array([r.get(k, np.nan) for r in res], float) for k in ("frame", "id", "x", "y", "dx", "dy", "sigma")}


def residual_vectors(doc) -> bytes | None:
    """Residual vectors at their markers on the detector, magnified."""
    r = _residuals(doc)
    if r is None or not np.isfinite(r["x"]).any():
        return None
    plt = _plt()
    rows, cols = doc["detector"]["shape"]
    mag = np.sqrt(r["dx"] ** 2 + r["dy"] ** 2)
    scale = 0.1 * max(rows, cols) / max(float(np.percentile(mag, 95)), 1e-9)
    fig, ax = plt.subplots(figsize=(5.5, 5.5 * rows / cols))
    q = ax.quiver(r["x"], r["y"], r["dx"] * scale, r["dy"] * scale, mag, angles="xy", scale_units="xy", scale=1,
                  cmap="viridis", width=0.004)
    fig.colorbar(q, ax=ax, label="|residual| (px)", shrink=0.8)
    ax.set_xlim(0, cols)
    ax.set_ylim(rows, 0)
    ax.set_aspect("equal")
    ax.set_xlabel("column (px)")
    ax.set_ylabel("row (px)")
    ax.set_title(f"residuals on the detector (arrows x{scale:.0f}; 95th pct {np.percentile(mag, 95):.3f} px)",
                 fontsize=9)
    return _png(fig)


def residuals_vs_frame(doc) -> bytes | None:
    """Residual components against frame number, and RMS per marker id."""
    r = _residuals(doc)
    if r is None:
        return None
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.2))
    a1.plot(r["frame"], r["dx"], ".", ms=3, label="dx (column)")
    a1.plot(r["frame"], r["dy"], ".", ms=3, label="dy (row)")
    a1.axhline(0, color="k", lw=0.5)
    a1.set_xlabel("frame")
    a1.set_ylabel("residual (px)")
    a1.legend(fontsize=8)
    a1.set_title("residuals vs frame", fontsize=9)
    ids = np.unique(r["id"][np.isfinite(r["id"])])
    rms = [np.sqrt(np.mean(r["dx"][r["id"] == i] ** 2 + r["dy"][r["id"] == i] ** 2)) for i in ids]
    a2.bar([str(int(i)) for i in ids], rms)
    a2.set_xlabel("marker id")
    a2.set_ylabel("RMS (px)")
    a2.set_title("per-marker error", fontsize=9)
    a2.tick_params(axis="x", labelsize=7)
    return _png(fig)


def geometry_sketch(doc) -> bytes | None:
    """Source, detector outline, axes and (for rp-grid) the source circle, in 3D (lab frame, mm)."""
    from ..geometry import ConeGeometry

    plt = _plt()
    g = ConeGeometry.from_dict(doc)
    rows, cols = g.shape
    corners = np.array([g.detector_point(c, r) for c, r in ((0, 0), (cols - 1, 0), (cols - 1, rows - 1),
                                                             (0, rows - 1), (0, 0))])
    fig = plt.figure(figsize=(5.5, 4.5))
    ax = fig.add_subplot(projection="3d")
    ax.plot(*corners.T, "k-", lw=1)
    ax.scatter(*g.source, color="r", s=30)
    ax.text(*g.source, " source", fontsize=8)
    c = g.detector_centre
    ax.plot(*np.stack([g.source, c]).T, "r:", lw=0.8)
    ax.text(*c, " detector", fontsize=8)
    size = 0.25 * np.linalg.norm(c - g.source)
    for a in doc.get("axes", []):
        d = np.asarray(a["direction"], float)
        p = np.asarray(a.get("point", [0, 0, 0]), float)
        seg = np.stack([p - size * d, p + size * d]) if a.get("type") == "rotary" else np.stack([p, p + size * d])
        ax.plot(*seg.T, "-", lw=2, label=f"{a['name']} ({a.get('type')})")
    if doc.get("stage") == "rp-grid" and doc.get("axes"):
        d = np.asarray(doc["axes"][0]["direction"], float)
        from ..geometry.rotations import axis_angle

        circle = np.array([axis_angle(d, t) @ g.source for t in np.linspace(0, 2 * np.pi, 73)])
        ax.plot(*circle.T, "r--", lw=0.6, label="source trajectory (sample frame)")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    if doc.get("axes"):
        ax.legend(fontsize=7, loc="upper left")
    ax.set_title("set-up (lab frame)", fontsize=9)
    return _png(fig)


def cost_slices(doc) -> bytes | None:
    """rp-grid: the redundant-plane cost along each parameter through the optimum."""
    sl = doc.get("cost_slices")
    if not sl:
        return None
    plt = _plt()
    names = list(sl)
    fig, axes = plt.subplots(1, len(names), figsize=(2.6 * len(names), 2.6))
    est = doc.get("misalignment", {})
    for ax, n in zip(np.atleast_1d(axes), names):
        ax.plot(sl[n]["values"], sl[n]["cost"], "-", lw=1.2)
        if n in est:
            ax.axvline(est[n]["value"], color="r", lw=0.8)
        ax.set_xlabel(n, fontsize=8)
        ax.tick_params(labelsize=7)
        ax.xaxis.set_major_locator(plt.MaxNLocator(4))
        ax.yaxis.set_major_locator(plt.MaxNLocator(4))
    np.atleast_1d(axes)[0].set_ylabel("c_RP")
    fig.suptitle("cost slices through the estimate (red), centred on it", fontsize=9)
    return _png(fig)


def placement(doc) -> bytes | None:
    """fit-pose: robot placement error per frame and reprojection RMS per frame."""
    frames = [f for f in doc.get("frames", []) if f.get("status") == "ok" and f.get("placement_error")]
    if not frames:
        return None
    plt = _plt()
    off = np.array([f["placement_error"]["offset_mm"] for f in frames])
    rot = np.array([f["placement_error"]["rotation_deg"] for f in frames])
    fr = np.array([f["frame"] for f in frames])
    rms = np.array([f["rms_px"] for f in frames])
    fig, (a1, a2, a3) = plt.subplots(1, 3, figsize=(12, 3.3))
    sc = a1.scatter(off[:, 0], off[:, 1], c=off[:, 2], s=10, cmap="coolwarm")
    fig.colorbar(sc, ax=a1, label="offset z (mm)")
    a1.set_xlabel("offset x (mm)")
    a1.set_ylabel("offset y (mm)")
    a1.set_title("placement error (colour: z)", fontsize=9)
    a1.set_aspect("equal", adjustable="datalim")
    a2.plot(fr, rot, ".", ms=3)
    a2.set_xlabel("frame")
    a2.set_ylabel("rotation error (deg)")
    a2.set_title("placement rotation per frame", fontsize=9)
    a3.plot(fr, rms, ".", ms=3)
    a3.set_xlabel("frame")
    a3.set_ylabel("RMS (px)")
    a3.set_title("reprojection RMS per frame", fontsize=9)
    return _png(fig)


def slices(images: list[np.ndarray], titles: list[str]) -> bytes:
    """Reconstructed slices side by side on one grey scale."""
    plt = _plt()
    fig, axes = plt.subplots(1, len(images), figsize=(3.2 * len(images), 3.4))
    lo = min(float(np.percentile(v, 1)) for v in images)
    hi = max(float(np.percentile(v, 99.5)) for v in images)
    for ax, v, t in zip(np.atleast_1d(axes), images, titles):
        ax.imshow(v, cmap="gray", vmin=lo, vmax=hi)
        ax.set_title(t, fontsize=9)
        ax.axis("off")
    return _png(fig)


def diagnosis(doc) -> bytes | None:
    """diagnose: residuals against time before and after modelling the effect."""
    obs = doc.get("observations")
    if not obs:
        return None
    plt = _plt()
    t = np.asarray(obs["time"], float)
    b = np.asarray(obs["before"], float)
    a = np.asarray(obs["after"], float)
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.3), sharey=True)
    for ax, r, title in ((axes[0], b, f"before (RMS {doc['rms_px_before']:.4f} px)"),
                         (axes[1], a, f"after (RMS {doc['rms_px_after']:.4f} px)")):
        ax.plot(t, r[:, 0], ".", ms=3, label="dx")
        ax.plot(t, r[:, 1], ".", ms=3, label="dy")
        ax.axhline(0, color="k", lw=0.5)
        for s in (-2, 2):
            ax.axhline(s * doc["noise_floor_px"], color="grey", lw=0.5, ls="--")
        ax.set_xlabel("time (s)")
        ax.set_title(title, fontsize=9)
    axes[0].set_ylabel("residual (px)")
    axes[0].legend(fontsize=8)
    fig.suptitle(doc.get("verdict", "")[:140], fontsize=8)
    return _png(fig)


def image_profiles(doc) -> bytes | None:
    """diagnose, image level: mean recorded minus modelled attenuation against
    distance from the shadow centre (in shadow radii), before and after."""
    img = doc.get("image_level") or {}
    before, after = img.get("radial_residual_before"), img.get("radial_residual_after")
    if not before or not after:
        return None
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 3.3))
    for prof, label, fmt in ((before, f"line-integral model (χ²/dof {img['chi2_per_dof_before']:.3f})", "o-"),
                             (after, f"with the effect found (χ²/dof {img['chi2_per_dof_after']:.3f})", "s-")):
        r, m, e = (np.asarray(prof[k], float) for k in ("radius", "mean", "stderr"))
        ax.errorbar(r, m, yerr=2 * e, fmt=fmt, ms=3, capsize=2, label=label)
    ax.axhline(0, color="k", lw=0.5)
    ax.axvline(1, color="grey", lw=0.5, ls=":")
    ax.set_xlabel("distance from the shadow centre (shadow radii)")
    ax.set_ylabel("recorded − model (attenuation)")
    ax.set_title(img.get("verdict", "")[:90], fontsize=8)
    ax.legend(fontsize=7)
    return _png(fig)


def convergence(doc) -> bytes | None:
    """chi^2 at each function evaluation of the solver."""
    h = (doc.get("fit") or {}).get("chi2_history")
    if not h or len(h) < 2:
        return None
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5, 3))
    ax.semilogy(np.arange(1, len(h) + 1), np.maximum(h, 1e-300), "o-", ms=3)
    ax.set_xlabel("function evaluation")
    ax.set_ylabel("χ²")
    ax.set_title("convergence", fontsize=9)
    return _png(fig)
