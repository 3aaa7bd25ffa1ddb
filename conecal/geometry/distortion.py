"""Detector distortion: where the detector records what ideally falls at a pixel.

A distortion maps the ideal pinhole projection ``(c, r)`` (px) to the
measured position ``(c + dc, r + dr)`` (SCAN_FORMAT.md, "Detector
distortion"). Every model works in normalised coordinates about its own
centre ``(c0, r0)`` (px): ``d = ((c, r) - (c0, r0)) / R``, ``R`` (px) a
fixed normalising radius (the detector's half-diagonal by default), and
every coefficient is a displacement in px at ``|d| = 1``, so coefficients
of different models and detectors compare directly.

Models (each linear in its coefficients for a fixed centre; ``basis``
returns the design so that a fit can solve for them, or differentiate):

``radial_tangential``
    ``k1 rho^2 d + k2 rho^4 d + k3 rho^6 d`` (radial: pincushion > 0),
    ``p1, p2`` Brown-Conrady decentring (tangential), and ``s rho^2 d_perp``
    (S-shaped twist, counter-clockwise > 0, as a magnetic field bends an
    image intensifier's electrons), about a centre that need not be the
    principal point; ``q1, q2`` the twist's own decentring: the tangential
    terms turned a quarter counter-clockwise, ``q1 J(p1 basis) + q2 J(p2
    basis)`` with ``J(u, v) = (-v, u)``, which is what an S twist ``s``
    about a centre moved by ``delta`` (normalised) adds to first order
    (``q = -s delta``): a field across the tube moves the twist's centre
    as the C-arm turns. Files written before q1, q2 existed read them as 0.
    ``twist_centre`` (optional, px): the S twist turns about this point
    instead of ``centre`` (exactly, to every order: the C-arm's own twist
    centre, which a frame's entry holds; q1, q2 then stand for a static
    decentring of their own).
``polynomial``
    ``dc, dr`` each a polynomial in ``d`` of total degree 2..n (the affine
    part is left out: a shift, scale, rotation or shear of the image is the
    geometry's, not the distortion's: that is the gauge).

Converters come in pairs (``to_dict``/``from_dict``) and are tested by
round trips.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError

RADIAL_TERMS = ("k1", "k2", "k3", "p1", "p2", "s", "q1", "q2")
# terms a distortion entry may leave out (read as 0): added after files were written
OPTIONAL_TERMS = ("q1", "q2")


def default_radius(shape) -> float:
    """Half the detector diagonal (px) for ``shape = (rows, cols)``."""
    rows, cols = shape
    return 0.5 * float(np.hypot(cols - 1, rows - 1))


def detector_centre(shape) -> tuple[float, float]:
    rows, cols = shape
    return ((cols - 1) / 2.0, (rows - 1) / 2.0)


def term_names(model: str, degree: int = 0) -> tuple:
    """The coefficient names of ``model`` (of ``degree`` for a polynomial), in order."""
    if model == "radial_tangential":
        return RADIAL_TERMS
    return tuple(f"{a}_x{i}y{j}" for a in ("dc", "dr") for i, j in poly_terms(int(degree)))


def missing_terms(model: str, degree: int, parameters) -> list:
    """The names ``model`` needs that ``parameters`` lacks (a term added after
    files were written, ``OPTIONAL_TERMS``, is read as 0 and not needed)."""
    return [n for n in term_names(model, degree) if n not in parameters and n not in OPTIONAL_TERMS]


def poly_terms(degree: int) -> list[tuple[int, int]]:
    """Exponents ``(i, j)`` of ``x^i y^j`` with ``2 <= i + j <= degree``."""
    return [(n - j, j) for n in range(2, degree + 1) for j in range(n + 1)]


@dataclass(frozen=True, eq=False)
class Distortion:
    """One detector distortion (px). ``coefficients`` in the order of
    ``names``; ``centre`` (c0, r0) px; ``radius`` px.

    >>> d = Distortion.radial((300, 300), k1=1.0)
    >>> bool(np.allclose(d.distort(d.undistort([[10.0, 20.0]])), [[10.0, 20.0]]))
    True
    """

    model: str
    centre: tuple
    radius: float
    coefficients: tuple
    degree: int = 0
    twist_centre: tuple | None = None
    names: tuple = field(init=False)

    def __post_init__(self):
        if self.model == "radial_tangential":
            names = term_names(self.model)
        elif self.model == "polynomial":
            if int(self.degree) < 2:
                raise InputError(f"distortion: a polynomial needs degree >= 2, not {self.degree}")
            names = term_names(self.model, self.degree)
        else:
            raise InputError(f"distortion: unknown model {self.model!r} (radial_tangential, polynomial)")
        c = np.asarray(self.centre, float)
        k = np.asarray(self.coefficients, float)
        if c.shape != (2,) or not np.isfinite(c).all():
            raise InputError(f"distortion: centre must be two finite numbers (c0, r0) px, not {self.centre!r}")
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise InputError(f"distortion: radius must be a positive number of px, not {self.radius!r}")
        if k.shape != (len(names),) or not np.isfinite(k).all():
            raise InputError(f"distortion {self.model}: needs {len(names)} finite coefficients ({', '.join(names)})")
        object.__setattr__(self, "centre", (float(c[0]), float(c[1])))
        if self.twist_centre is not None:
            tc = np.asarray(self.twist_centre, float)
            if self.model != "radial_tangential" or tc.shape != (2,) or not np.isfinite(tc).all():
                raise InputError(f"distortion: twist_centre must be two finite numbers (c, r) px of a "
                                 f"radial_tangential model, not {self.twist_centre!r}")
            object.__setattr__(self, "twist_centre", (float(tc[0]), float(tc[1])))
        object.__setattr__(self, "coefficients", tuple(float(v) for v in k))
        object.__setattr__(self, "names", names)

    # -- constructors -------------------------------------------------------
    @classmethod
    def radial(cls, shape, *, centre=None, radius=None, twist_centre=None, **coeffs) -> "Distortion":
        """A ``radial_tangential`` distortion for a detector of ``shape``;
        unnamed coefficients are zero."""
        bad = set(coeffs) - set(RADIAL_TERMS)
        if bad:
            raise InputError(f"distortion: unknown radial_tangential terms {sorted(bad)}")
        return cls("radial_tangential", centre if centre is not None else detector_centre(shape),
                   radius or default_radius(shape), tuple(float(coeffs.get(n, 0.0)) for n in RADIAL_TERMS),
                   twist_centre=twist_centre)

    @classmethod
    def polynomial(cls, shape, degree: int, coefficients=None, *, centre=None, radius=None) -> "Distortion":
        n = 2 * len(poly_terms(degree))
        return cls("polynomial", centre if centre is not None else detector_centre(shape),
                   radius or default_radius(shape), tuple(np.zeros(n) if coefficients is None else coefficients),
                   degree=degree)

    def with_coefficients(self, coefficients, centre=None, twist_centre=None) -> "Distortion":
        return Distortion(self.model, self.centre if centre is None else centre, self.radius, tuple(coefficients),
                          self.degree, self.twist_centre if twist_centre is None else twist_centre)

    # -- the map ------------------------------------------------------------
    def _normalised(self, xy) -> np.ndarray:
        return (np.asarray(xy, float) - np.asarray(self.centre)) / self.radius

    def _twisted(self, xy, about, x, y):
        """Normalised positions about the twist's centre: ``about`` (..., 2) px
        if given (one per position: a bundle's frames), else this model's;
        ``x, y``: the positions about ``centre``, which they are without one."""
        if about is None:
            if self.twist_centre is None:
                return x, y
            about = self.twist_centre
        u = (np.asarray(xy, float) - np.asarray(about, float)) / self.radius
        return u[..., 0], u[..., 1]

    def basis(self, xy, twist_about=None) -> np.ndarray:
        """(..., 2, n) px per unit coefficient: ``displacement = basis @ coefficients``;
        ``twist_about``: see ``_twisted``."""
        d = self._normalised(xy)
        x, y = d[..., 0], d[..., 1]
        if self.model == "radial_tangential":
            r2 = x * x + y * y
            r4 = r2 * r2
            xy2 = 2 * x * y
            B = np.empty(x.shape + (2, 8))     # filled in place: this runs in every bundle step
            B[..., 0, 0], B[..., 1, 0] = x * r2, y * r2                    # k1
            B[..., 0, 1], B[..., 1, 1] = x * r4, y * r4                    # k2
            B[..., 0, 2], B[..., 1, 2] = x * r4 * r2, y * r4 * r2          # k3
            B[..., 0, 3], B[..., 1, 3] = r2 + 2 * x * x, xy2               # p1
            B[..., 0, 4], B[..., 1, 4] = xy2, r2 + 2 * y * y               # p2
            u, v = self._twisted(xy, twist_about, x, y)
            w2 = u * u + v * v
            B[..., 0, 5], B[..., 1, 5] = -v * w2, u * w2                   # s, about its own centre
            B[..., 0, 6], B[..., 1, 6] = -xy2, r2 + 2 * x * x              # q1: p1 turned
            B[..., 0, 7], B[..., 1, 7] = -(r2 + 2 * y * y), xy2            # q2: p2 turned
            return B
        mono = np.stack([x ** i * y ** j for i, j in poly_terms(int(self.degree))], -1)
        z = np.zeros_like(mono)
        return np.stack([np.concatenate([mono, z], -1), np.concatenate([z, mono], -1)], -2)

    def basis_gradient(self, xy, twist_about=None) -> np.ndarray:
        """(..., 2, n, 2): d basis / d position (per px); the displacement's
        gradient is this contracted with the coefficients, and its derivative
        by the centre (the twist's centre moved with it) is minus that."""
        d = self._normalised(xy)
        x, y = d[..., 0], d[..., 1]
        z = np.zeros_like(x)
        if self.model == "radial_tangential":
            r2 = x * x + y * y
            xy2 = 2 * x * y
            g = np.empty(x.shape + (2, 8, 2))  # (..., component, term, d/dx d/dy)
            for t, n in enumerate((1, 2, 3)):
                rn, rm = r2 ** n, n * r2 ** (n - 1)
                g[..., 0, t, 0], g[..., 0, t, 1] = rn + 2 * x * x * rm, xy2 * rm
                g[..., 1, t, 0], g[..., 1, t, 1] = xy2 * rm, rn + 2 * y * y * rm
            g[..., 0, 3, 0], g[..., 0, 3, 1], g[..., 1, 3, 0], g[..., 1, 3, 1] = 6 * x, 2 * y, 2 * y, 2 * x    # p1
            g[..., 0, 4, 0], g[..., 0, 4, 1], g[..., 1, 4, 0], g[..., 1, 4, 1] = 2 * y, 2 * x, 2 * x, 6 * y    # p2
            u, v = self._twisted(xy, twist_about, x, y)
            w2, uv2 = u * u + v * v, 2 * u * v
            g[..., 0, 5, 0], g[..., 0, 5, 1] = -uv2, -(w2 + 2 * v * v)                                         # s
            g[..., 1, 5, 0], g[..., 1, 5, 1] = w2 + 2 * u * u, uv2
            g[..., 0, 6:8, :], g[..., 1, 6:8, :] = -g[..., 1, 3:5, :], g[..., 0, 3:5, :]                     # q1, q2
            return g / self.radius
        terms = poly_terms(int(self.degree))
        dx = np.stack([i * x ** max(i - 1, 0) * y ** j if i else z for i, j in terms], -1)
        dy = np.stack([j * x ** i * y ** max(j - 1, 0) if j else z for i, j in terms], -1)
        mono = np.stack([dx, dy], -1)                                          # (..., m, 2)
        zero = np.zeros_like(mono)
        return np.stack([np.concatenate([mono, zero], -2), np.concatenate([zero, mono], -2)], -3) / self.radius

    def displacement(self, xy) -> np.ndarray:
        """``(dc, dr)`` (..., 2) px at ideal positions ``xy`` (..., 2) px."""
        return self.basis(xy) @ np.asarray(self.coefficients)

    def distort(self, xy) -> np.ndarray:
        """Measured position (..., 2) px of what ideally falls at ``xy``."""
        xy = np.asarray(xy, float)
        return xy + self.displacement(xy)

    def undistort(self, xy, iterations: int = 8) -> np.ndarray:
        """Ideal position of a measured ``xy``, by fixed-point iteration
        (converges while the displacement's gradient is well below 1)."""
        xy = np.asarray(xy, float)
        x = xy.copy()
        for _ in range(iterations):
            x = xy - self.displacement(x)
        return x

    def centre_jacobian(self, xy) -> np.ndarray:
        """(..., 2, 2) d displacement / d centre (px/px), the twist's centre moved with it."""
        return -np.einsum("...inj,n->...ij", self.basis_gradient(xy), np.asarray(self.coefficients))

    def field(self, shape) -> tuple[np.ndarray, np.ndarray]:
        """``dc, dr`` (rows, cols) float32 px at every pixel centre of the ideal image."""
        rows, cols = shape
        r, c = np.mgrid[0:rows, 0:cols].astype(float)
        d = self.displacement(np.stack([c, r], -1))
        return d[..., 0].astype(np.float32), d[..., 1].astype(np.float32)

    # -- documents ----------------------------------------------------------
    def to_dict(self, sigma=None) -> dict:
        """The geometry's ``distortion`` entry (px); ``sigma``: 1σ of each coefficient."""
        out = {"model": self.model, "centre": list(self.centre), "radius_px": self.radius,
               "parameters": dict(zip(self.names, self.coefficients)),
               "units": "px of displacement at the normalising radius; centre in px (column, row)"}
        if self.model == "polynomial":
            out["degree"] = int(self.degree)
        if self.twist_centre is not None:
            out["twist_centre"] = list(self.twist_centre)
        if sigma is not None:
            out["sigma"] = dict(zip(self.names, (float(s) for s in sigma)))
        return out

    @classmethod
    def from_dict(cls, d: dict, where: str = "distortion") -> "Distortion":
        if not isinstance(d, dict):
            raise InputError(f"{where}: expected a mapping with model, centre, radius_px, parameters")
        model = d.get("model")
        try:
            degree = int(d.get("degree", 0))
            names = term_names(model, degree)
            params = d["parameters"]
            missing = missing_terms(model, degree, params)
            if missing:
                raise InputError(f"{where}.parameters: missing {missing[0]!r}")
            tc = d.get("twist_centre")
            return cls(model, tuple(d["centre"]), float(d["radius_px"]), tuple(float(params.get(n, 0.0)) for n in names),
                       degree, None if tc is None else tuple(tc))
        except KeyError as exc:
            raise InputError(f"{where}: missing key {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise InputError(f"{where}: {exc}") from None

    def __repr__(self) -> str:
        terms = ", ".join(f"{n}={v:+.4g}" for n, v in zip(self.names, self.coefficients) if v)
        tc = "" if self.twist_centre is None else f", twist about ({self.twist_centre[0]:.1f}, {self.twist_centre[1]:.1f})"
        return f"Distortion({self.model}, centre=({self.centre[0]:.1f}, {self.centre[1]:.1f}){tc}, {terms or 'zero'})"
