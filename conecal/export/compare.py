"""Two results compared in physical terms, for golden-file tests.

Geometry files: points filling the field of view (a 7x7x7 grid in the cube
the detector sees at the lab origin) are moved by each file's own axes
through a fixed set of readings and projected with each file's geometry;
the largest difference in px is the verdict, with the parameters that moved
by more than ``tol_sigma`` of their combined sigma listed. Pose files: each
frame's status (ok, ambiguous or rejected, and the reason key) must match, and points filling the field of view around
the holder must project within ``tol_px``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..documents.status import reason_of, state_of
from ..geometry import ConeGeometry, RigidTransform
from ..jsonio import read_json
from .views import chain_from_doc


@dataclass
class Comparison:
    max_px: float
    where: str
    lines: list[str] = field(default_factory=list)
    agree: bool = True


def _fov_points(g: ConeGeometry, n: int = 7) -> np.ndarray:
    rows, cols = g.shape
    half = 0.45 * min(rows * g.pixel_pitch[1], cols * g.pixel_pitch[0]) / float(g.magnification(np.zeros(3)))
    s = np.linspace(-half, half, n)
    return np.stack(np.meshgrid(s, s, s, indexing="ij"), -1).reshape(-1, 3)


def _readings(chain, rng) -> np.ndarray:
    cols = []
    for a in chain.axes:
        cols.append(rng.uniform(0, 360, 24) if a.type == "rotary" else rng.uniform(-5, 5, 24))
    return np.column_stack(cols)


def compare_files(path_a, path_b, tol_px: float = 0.05, tol_sigma: float = 3.0) -> Comparison:
    a = read_json(path_a, ("conecal-geometry", "conecal-poses"))
    b = read_json(path_b, ("conecal-geometry", "conecal-poses"))
    if a["format"] != b["format"]:
        c = Comparison(np.inf, "format", [f"formats differ: {a['format']} vs {b['format']}"], False)
        return c
    ga, gb = ConeGeometry.from_dict(a), ConeGeometry.from_dict(b)
    if ga.shape != gb.shape:
        return Comparison(np.inf, "detector", [f"detector shapes differ: {list(ga.shape)} vs {list(gb.shape)}"], False)
    lines = []
    if a["format"].startswith("conecal-poses"):
        fa = {f["frame"]: f for f in a["frames"]}
        fb = {f["frame"]: f for f in b["frames"]}
        worst, where = 0.0, "-"
        # the whole field of view around the holder: poses fitted with two
        # geometries agree on the holder's spheres but not away from them
        cube = _fov_points(ga, 5)
        for k in sorted(set(fa) | set(fb)):
            if k not in fa or k not in fb:
                lines.append(f"frame {k}: only in {'A' if k in fa else 'B'}")
                continue
            if _state(fa[k]) != _state(fb[k]):
                lines.append(f"frame {k}: status {fa[k]['status']!r} vs {fb[k]['status']!r}")
                continue
            if fa[k]["status"] != "ok":
                continue
            Ta = RigidTransform(np.array(fa[k]["R"]), np.array(fa[k]["t"]))
            Tb = RigidTransform(np.array(fb[k]["R"]), np.array(fb[k]["t"]))
            d = np.hypot(*(ga.project(Ta.apply(cube)) - gb.project(Tb.apply(cube))).T).max()
            if d > worst:
                worst, where = float(d), f"frame {k}"
        agree = worst <= tol_px and not lines
        if worst > tol_px:
            lines.insert(0, f"largest reprojection difference {worst:.4g} px at {where} (tolerance {tol_px} px)")
        return Comparison(worst, where, lines, agree)
    X = _fov_points(ga)
    worst, where = float(np.hypot(*(ga.project(X) - gb.project(X)).T).max()), "lab, at rest"
    if a.get("axes") and b.get("axes"):
        ca, cb = chain_from_doc(a, path_a), chain_from_doc(b, path_b)
        if ca.names == cb.names:
            q = _readings(ca, np.random.default_rng(0))
            Ta, Tb = ca.transforms(q), cb.transforms(q)
            for k in range(len(q)):
                d = float(np.hypot(*(ga.project(Ta[k].apply(X)) - gb.project(Tb[k].apply(X))).T).max())
                if d > worst:
                    worst, where = d, "readings " + ", ".join(f"{n}={v:.3g}" for n, v in zip(ca.names, q[k]))
        else:
            lines.append(f"axes differ: {ca.names} vs {cb.names}")
    pa = a.get("fit", {}).get("parameters", {})
    pb = b.get("fit", {}).get("parameters", {})
    moved = []
    for n in sorted(set(pa) & set(pb)):
        sa, sb = pa[n].get("sigma"), pb[n].get("sigma")
        if not (pa[n].get("free") and pb[n].get("free")) or sa is None or sb is None:
            continue
        s = float(np.hypot(sa, sb))
        diff = pb[n]["value"] - pa[n]["value"]
        if s > 0 and abs(diff) > tol_sigma * s:
            moved.append(f"{n}: {pa[n]['value']:.6g} -> {pb[n]['value']:.6g} {pa[n].get('unit', '')} "
                         f"({abs(diff) / s:.1f} sigma)")
    agree = worst <= tol_px and not moved and not lines
    head = f"largest reprojection difference {worst:.4g} px ({where}); tolerance {tol_px} px"
    return Comparison(worst, where, [head] + moved + lines, agree)


def _state(frame: dict) -> tuple:
    """A poses frame's state and reason key (the detail's numbers may differ)."""
    return (state_of(frame), "" if frame["status"] == "ok" else reason_of(frame))
