"""rp-grid: Grangeat's relation, table look-ups, Jacobian, holder detection,
a small simulate -> rp-grid -> recover run, and the CLI's bad-input paths."""

import json

import numpy as np
import pytest
from click.testing import CliRunner

from conecal.cli.main import cli
from conecal.consistency import kernels, rpgrid
from conecal.geometry.misalignment import NAMES, misaligned
from conecal.geometry import ConeGeometry


def gaussian_projection(g, c, sig, amp):
    """Exact cone-beam projection of A exp(-|x-c|^2 / 2 sig^2)."""
    rows, cols = g.shape
    P = g.detector_point(*np.meshgrid(np.arange(cols), np.arange(rows)))
    d = P - g.source
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    x = c - g.source
    dist2 = (x**2).sum() - (d @ x) ** 2
    return amp * np.sqrt(2 * np.pi) * sig * np.exp(-dist2 / (2 * sig**2))


def _central_difference(prob, p, k, h):
    """d residuals / d p[k] by central differences of step ``h``."""
    q1, q2 = p.copy(), p.copy()
    q1[k] += h
    q2[k] -= h
    return (prob.residuals(q1) - prob.residuals(q2)) / (2 * h)


def test_grangeat_relation_on_a_tilted_detector():
    """Table value times Grangeat's factor equals d/drho of the 3D Gaussian's plane integral."""
    nom = ConeGeometry.nominal(sod=300, sdd=600, shape=(200, 240), pixel_pitch=(0.4, 0.4))
    g = misaligned(nom, (5, -3, 2, 3, -2))
    c, sig, amp = np.array([3.0, -2.0, 4.0]), 6.0, 0.02
    img = gaussian_projection(g, c, sig, amp)
    opt = rpgrid.RPOptions(smooth_px=0.5)
    tab = rpgrid.build_tables([img], 1, g, opt)
    prob = object.__new__(rpgrid.RPProblem)
    prob.tab = tab
    rng = np.random.default_rng(1)
    pts = c + rng.normal(0, sig, (200, 3))
    m = np.cross(pts - g.source, rng.normal(size=(200, 3)))
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    val = prob._look(rpgrid._frame(g, tab.ref), np.zeros(200, np.int64), m)[0]
    t = m @ g.source - m @ c
    ref = amp * 2 * np.pi * sig**2 * (-t / sig**2) * np.exp(-t**2 / (2 * sig**2))
    assert np.abs(val - ref).max() < 0.01 * np.abs(ref).max()


def test_lookup_symmetry_and_derivatives():
    rng = np.random.default_rng(2)
    tables = rng.normal(size=(2, 36, 41)).astype(np.float32)
    tables = np.cumsum(np.cumsum(tables, axis=2), axis=1).astype(np.float32)   # smooth-ish
    s0, ds = -8.0, 0.4
    view = np.array([1, 1, 1], np.int64)
    alpha = np.array([0.3, 1.2, 2.9])
    s = np.array([-3.0, 0.5, 2.2])
    v, da, dsv = kernels.lookup(tables, view, alpha, s, s0, ds)
    v2, _, _ = kernels.lookup(tables, view, alpha + np.pi, -s, s0, ds)
    assert np.allclose(v, -v2, atol=1e-5)
    h = 1e-5
    vp, _, _ = kernels.lookup(tables, view, alpha, s + h, s0, ds)
    vm, _, _ = kernels.lookup(tables, view, alpha, s - h, s0, ds)
    assert np.allclose(dsv, (vp - vm) / (2 * h), rtol=1e-3, atol=1e-2)
    vp, _, _ = kernels.lookup(tables, view, alpha + h, s, s0, ds)
    vm, _, _ = kernels.lookup(tables, view, alpha - h, s, s0, ds)
    assert np.allclose(da, (vp - vm) / (2 * h), rtol=1e-3, atol=1e-2)


def test_joseph_radon_of_a_constant_image():
    img = np.ones((100, 120), np.float32)
    ang = np.array([0.0, np.pi / 4, np.pi / 2])
    out = kernels.radon_joseph(img, 0.4, 0.4, 59.5, 49.5, np.cos(ang), np.sin(ang), -40.0, 0.4, 201)
    assert np.isclose(out[0, 100], 99 * 0.4, rtol=0.02)        # a column: 100 samples, 99 gaps
    assert np.isclose(out[2, 100], 119 * 0.4, rtol=0.02)
    assert np.isclose(out[0].sum() * 0.4, 100 * 120 * 0.16, rtol=0.02)


def _joseph_reference(img, pu, pv, c_ref, r_ref, alpha, s):
    """One line's Joseph sum, walked along the line (numpy, slow and plain)."""
    ca, sa = np.cos(alpha), np.sin(alpha)
    rows, cols = img.shape
    if abs(ca) >= abs(sa):          # one sample per row, linear across columns
        r = np.arange(rows)
        c = (s - (r - r_ref) * pv * sa) / (ca * pu) + c_ref
        line, n, step = img, cols, pv / abs(ca)
    else:                           # one sample per column, linear across rows
        r = np.arange(cols)
        c = (s - (r - c_ref) * pu * ca) / (sa * pv) + r_ref
        line, n, step = img.T, rows, pu / abs(sa)
    ok = (c >= 0) & (c <= n - 1)
    i = np.minimum(c[ok].astype(int), n - 2)
    f = c[ok] - i
    j = r[ok]
    return step * np.sum(line[j, i] * (1 - f) + line[j, i + 1] * f)


def test_row_ordered_joseph_radon_matches_the_line_by_line_sums():
    rng = np.random.default_rng(11)
    img = rng.random((37, 45)).astype(np.float32)
    ang = np.array([0.0, 0.2, np.pi / 4, 1.0, np.pi / 2, 2.0, 3.0])
    s0, ds, n_s = -14.0, 0.37, 77
    out = kernels.radon_joseph(img, 0.4, 0.5, 21.3, 17.8, np.cos(ang), np.sin(ang), s0, ds, n_s)
    ref = np.array([[_joseph_reference(img, 0.4, 0.5, 21.3, 17.8, a, s0 + k * ds) for k in range(n_s)] for a in ang])
    assert np.allclose(out, ref, rtol=1e-5, atol=1e-4)


def test_fourth_order_derivative_kernel_differentiates_a_cubic_exactly():
    from conecal.consistency.radon import derivative_kernel

    x = np.arange(-40, 41, dtype=float)
    f = 0.3 * x**3 - 2 * x**2 + x
    exact = 0.9 * x**2 - 4 * x + 1
    for order, exact_ok in ((2, False), (4, True)):
        taps = derivative_kernel(3.0, order)
        half = len(taps) // 2
        got = np.array([np.dot(taps, f[k - half:k + half + 1]) for k in range(half, len(x) - half)])
        assert np.allclose(got, exact[half:len(x) - half], atol=1e-6) == exact_ok
        assert np.isclose(np.dot(taps, np.arange(-half, half + 1)), 1.0)       # a line, exactly
    with pytest.raises(ValueError):
        derivative_kernel(3.0, 3)


def test_joseph_variance_gives_the_variance_of_each_line_sum():
    """radon_joseph_variance(var)'s variances against the spread of the Radon
    transforms of many noise images with that pixel variance."""
    rng = np.random.default_rng(5)
    yy, xx = np.mgrid[:40, :48]
    var = (0.5 + np.exp(-((xx - 30) ** 2 + (yy - 15) ** 2) / 80.0)).astype(np.float32)
    ang = np.array([0.0, 0.3, np.pi / 4, 1.2, np.pi / 2])
    args = (0.5, 0.5, 23.5, 19.5, np.cos(ang), np.sin(ang), -12.0, 0.5, 49)
    sums = np.array([kernels.radon_joseph((rng.normal(size=var.shape) * np.sqrt(var)).astype(np.float32), *args)
                     for _ in range(1500)])
    pred = kernels.radon_joseph_variance(var, *args)[0]
    inside = pred > 0.2 * pred.max()
    ratio = sums.var(axis=0)[inside] / pred[inside]
    # 1500 draws: each ratio is known to about 3.7 % (1 sigma)
    assert abs(np.median(ratio) - 1) < 0.02 and np.abs(ratio - 1).max() < 0.2


def test_holder_hull_found_only_for_a_dense_border_object():
    img = np.zeros((120, 120), np.float32)
    yy, xx = np.mgrid[:120, :120]
    img[(xx - 60) ** 2 + (yy - 50) ** 2 < 30**2] = 0.4
    assert rpgrid._holder_hull(img, (0, 119, 0, 119), 2.5) is None
    holder = img.copy()
    holder[95:, 45:75] = 2.5
    hull = rpgrid._holder_hull(holder, (0, 119, 0, 119), 2.5)
    assert hull is not None and hull[:, 1].min() >= 94 and 44 <= hull[:, 0].min() and hull[:, 0].max() <= 75
    # an object that is itself cut by the border is not a holder
    tall = img.copy()
    tall[:, 40:80] = np.maximum(tall[:, 40:80], 0.4)
    assert rpgrid._holder_hull(tall, (0, 119, 0, 119), 2.5) is None


@pytest.fixture(scope="module")
def small_circular(tmp_path_factory):
    from conecal.simulate import circular_scan, write_scan

    sc = circular_scan(7, rows=96, cols=96, pitch=1.0, n_frames=90, shift_px=(3.0, -2.0), rotation_deg=(1.0, 0.0, 0.0))
    return write_scan(sc, tmp_path_factory.mktemp("circ") / "c", seed=7)


def test_jacobian_matches_finite_differences(small_circular):
    """With the Grangeat factors following the geometry, whose derivative
    enters through the principal point and D."""
    from conecal.scan import load_scan

    scan = load_scan(small_circular)
    opt = rpgrid.RPOptions(pairs=100, planes_per_pair=16)
    nom = scan.nominal_geometry()
    tab = rpgrid.build_tables((scan.stack.read(k) for k in range(scan.n_frames)), scan.n_frames, nom, opt)
    prob = rpgrid.RPProblem(nom, scan.nominal_transforms(), tab, [0, 1, 0], opt)
    p = np.array([2.7, -1.6, 0.8, 0.4, -0.3])
    prob.select(p)
    J = prob.jacobian(p)
    for k in range(5):
        Jn = _central_difference(prob, p, k, 1e-4)
        # bilinear look-ups: piecewise-smooth, so the match is to a few per cent
        assert np.linalg.norm(J[:, k] - Jn) < 0.05 * np.linalg.norm(Jn) + 1e-9, NAMES[k]


@pytest.mark.parametrize("fan_sigma_deg", [0.0, 1.0])
def test_noise_weighted_residuals_and_their_jacobian(small_circular, fan_sigma_deg):
    """With noise tables, residuals are disagreements over their noise sigma
    at the current lines (unit weights otherwise), and the Jacobian carries
    the sigma's own derivative; also when both are smoothed along the fans."""
    from conecal.scan import load_scan

    scan = load_scan(small_circular)
    opt = rpgrid.RPOptions(pairs=100, planes_per_pair=16 if fan_sigma_deg == 0 else 144, fan_sigma_deg=fan_sigma_deg)
    nom = scan.nominal_geometry()
    tab = rpgrid.build_tables((scan.stack.read(k) for k in range(scan.n_frames)), scan.n_frames, nom, opt, noise=True)
    assert tab.variance.shape[:2] == (scan.n_frames, opt.n_angles // rpgrid.NOISE_ANGLE_STEP)
    assert abs(np.median(tab.variance[tab.variance > 0]) - 1) < 1e-6
    prob = rpgrid.RPProblem(nom, scan.nominal_transforms(), tab, [0, 1, 0], opt)
    p = np.array([2.7, -1.6, 0.8, 0.4, -0.3])
    prob.select(p)
    assert prob.noise_weighted and np.all(prob._kept.weight == 1.0)
    assert (prob._kept.fan is not None) == (fan_sigma_deg > 0)
    f = rpgrid._frame(misaligned(nom, p), tab.ref)
    A = prob._kept
    S = prob._plane_variance(A, prob._look(f, A.vi, A.mi, variance=True)[1],
                             prob._look(f, A.vj, A.mj, variance=True)[1])
    assert np.all(S > 0)
    with rpgrid._bilinear(prob):
        assert not prob.noise_weighted
    J = prob.jacobian(p)
    # the residuals the Jacobian computed on the way are the same numbers,
    # and reused only at the same point, planes and look-up
    r = prob.residuals(p)
    assert np.array_equal(r, prob._residuals(p, prob._kept))
    with rpgrid._bilinear(prob):
        rb = prob.residuals(p)
        assert np.array_equal(rb, prob._residuals(p, prob._kept)) and not np.allclose(rb, r)
    for k in range(5):
        Jn = _central_difference(prob, p, k, 1e-5)
        assert np.linalg.norm(J[:, k] - Jn) < 1e-3 * np.linalg.norm(Jn) + 1e-9, NAMES[k]


def test_fan_smoothing_stays_within_each_pair_and_is_a_gaussian_in_the_planes_angle(small_circular):
    """Each residual averages planes of its own pair only (the same two views),
    with Gaussian weights in their angle about the baseline that sum to 1."""
    from conecal.scan import load_scan

    scan = load_scan(small_circular)
    opt = rpgrid.RPOptions(pairs=60, planes_per_pair=144, fan_sigma_deg=0.75)
    nom = scan.nominal_geometry()
    tab = rpgrid.build_tables((scan.stack.read(k) for k in range(scan.n_frames)), scan.n_frames, nom, opt)
    prob = rpgrid.RPProblem(nom, scan.nominal_transforms(), tab, [0, 1, 0], opt)
    idx = np.arange(len(prob.vi))
    planes = prob._arrays(idx, np.zeros(5))
    W = planes.fan.tocoo()
    assert np.allclose(np.asarray(planes.fan.sum(axis=1)).ravel(), 1.0)
    vi = planes.vi
    vj = np.empty_like(planes.vj)
    vj[planes.perm] = planes.vj
    assert np.all(vi[W.row] == vi[W.col]) and np.all(vj[W.row] == vj[W.col])
    # within a pair, weights fall off as a Gaussian of the planes' angle
    cosang = np.abs(np.einsum("ij,ij->i", planes.mi[W.row], planes.mi[W.col]).clip(-1, 1))
    dk = np.degrees(np.arccos(cosang))
    diag = np.asarray(planes.fan.diagonal())[W.row]
    expect = np.exp(-0.5 * (dk / 0.75) ** 2)
    assert np.allclose(W.data / diag, expect, atol=2e-3)


def test_band_of_lines_meets_flagged_border_stretches_like_its_lines_do(small_circular):
    """The truncation test of a band of parallel lines (one interval per
    side and prefix sums) agrees with sweeping single lines across it finely."""
    from conecal.scan import load_scan

    scan = load_scan(small_circular)
    opt = rpgrid.RPOptions(pairs=200, planes_per_pair=16)
    nom = scan.nominal_geometry()
    tab = rpgrid.build_tables((scan.stack.read(k) for k in range(scan.n_frames)), scan.n_frames, nom, opt)
    rng = np.random.default_rng(3)
    tab.edge_flags[:] = False
    for k in range(scan.n_frames):           # a few flagged stretches per view, anywhere on the border
        for _ in range(3):
            a = rng.integers(0, tab.edge_flags.shape[1] - 12)
            tab.edge_flags[k, a:a + rng.integers(1, 12)] = True
    prob = rpgrid.RPProblem(nom, scan.nominal_transforms(), tab, [0, 1, 0], opt)
    f = rpgrid._frame(nom, tab.ref)
    *_, alpha, s = prob._lines(f, prob.mi)
    margin = 4.0 * tab.ds
    band = prob._band_truncated(prob.vi, alpha, s, margin)
    swept = np.zeros_like(band)
    for off in np.linspace(-margin, margin, 401):
        swept |= prob._exits(prob.vi, alpha, s + off)[1]
    assert 0.05 < band.mean() < 0.95
    assert np.all(band[swept])                               # nothing the sweep finds is missed
    assert np.mean(band != swept) < 2e-3                     # and little beyond it (between sweep steps)


def test_small_scan_recovers_shift_and_rotation(small_circular, tmp_path):
    out = tmp_path / "rp.json"
    r = CliRunner().invoke(cli, ["rp-grid", str(small_circular), "-o", str(out), "--pairs", "400",
                                 "--range", "theta_deg=2", "--range", "phi_deg=2"])
    assert r.exit_code == 0, r.output
    doc = json.loads(out.read_text())
    assert doc["format"] == "conecal-geometry/1" and doc["stage"] == "rp-grid"
    est = doc["misalignment"]
    assert abs(est["shift_u_px"]["value"] - 3.0) < 0.2
    assert abs(est["eta_deg"]["value"] - 1.0) < 0.1
    assert set(doc["cost_slices"]) == set(NAMES)
    assert doc["fit"]["cost_final"] < 0.2 * doc["fit"]["cost_nominal"]
    assert doc["fit"]["converged"] and doc["fit"]["grangeat_factors"] == "following"
    assert doc["fit"]["planes"]["pairs_drawn"] == "uniformly"       # no truncation: most planes used
    restarts = doc["fit"]["restarts_along_v"]
    assert restarts["offsets_px"] == list(rpgrid.RPOptions().v_restarts_px)
    assert restarts["moved_from"] is None or set(restarts["moved_from"]) == set(NAMES)
    assert doc["fit"]["tables"]["interpolation"] == "spline"
    # the reported sigma is the planes' sigma times the calibration factor
    for n, e in est.items():
        assert e["sigma_factor"] == rpgrid.SIGMA_FACTORS[n] >= 1.0
        if e["sigma"] is not None:
            assert np.isclose(e["sigma"], e["sigma_uncalibrated"] * e["sigma_factor"], rtol=1e-4)


def test_pass_two_draws_more_pairs_only_where_most_planes_were_dropped():
    opt = rpgrid.RPOptions(pairs=1000, min_used_fraction=0.5, max_pairs_factor=4.0)
    assert rpgrid.pass2_pairs(opt, {"used": 30000, "candidates": 40000}) == 1000
    # a quarter used: twice the pairs reach half of the candidates
    assert rpgrid.pass2_pairs(opt, {"used": 10000, "candidates": 40000}) == 2000
    assert rpgrid.pass2_pairs(opt, {"used": 100, "candidates": 40000}) == 4000
    assert rpgrid.pass2_pairs(opt, {"used": 0, "candidates": 40000}) == 4000
    # drawn by yield: 100 pairs in each of three bins, 10 planes a pair in the
    # last only; weighted draws land there and bring 10 planes each
    yield_ = (np.array([0.0, 60.0, 120.0, 180.0]), np.array([0.0, 0.0, 10.0]), np.array([100, 100, 100]))
    assert rpgrid.pass2_pairs(opt, {"used": 10000, "candidates": 40000}, yield_) == 2000


def test_pairs_drawn_by_yield_only_at_separations_that_kept_planes(small_circular):
    """separation_yield counts used planes per pair by the views'
    separation; a problem built with it draws no pair where that is 0."""
    from conecal.scan import load_scan

    scan = load_scan(small_circular)
    opt = rpgrid.RPOptions(pairs=300, planes_per_pair=8)
    nom = scan.nominal_geometry()
    tab = rpgrid.build_tables((scan.stack.read(k) for k in range(scan.n_frames)), scan.n_frames, nom, opt)
    prob = rpgrid.RPProblem(nom, scan.nominal_transforms(), tab, [0, 1, 0], opt)
    prob.select(np.zeros(5))
    edges, per_pair, pairs = prob.separation_yield(bin_deg=10.0)
    assert len(per_pair) == len(pairs) == len(edges) - 1 == 18
    assert pairs.sum() == prob.n_pairs and per_pair[pairs > 0].min() > 0
    assert np.isclose(np.sum(per_pair * pairs), prob.keep.sum())
    only = np.where(edges[:-1] >= 150.0, per_pair, 0.0)
    weighted = rpgrid.RPProblem(nom, scan.nominal_transforms(), tab, [0, 1, 0], opt, (edges, only, pairs))
    sep = weighted._separation(weighted.vi, weighted.vj)
    assert weighted.n_pairs > 50 and sep.min() >= 150.0 - 1e-9


def test_cli_refuses_bad_input(small_circular, small_linear_scan, tmp_path):
    run = CliRunner().invoke
    r = run(cli, ["rp-grid", str(small_linear_scan), "-o", str(tmp_path / "x.json")])
    assert r.exit_code == 2 and "circular" in r.output
    r = run(cli, ["rp-grid", str(small_circular), "-o", str(tmp_path / "x.json"), "--range", "bogus=3"])
    assert r.exit_code == 2 and "unknown parameter" in r.output
    r = run(cli, ["rp-grid", str(small_circular), "-o", str(tmp_path / "x.json"), "--crop", "1,2,3"])
    assert r.exit_code == 2
    r = run(cli, ["rp-grid", str(small_circular), "-o", str(tmp_path / "x.json"), "--crop", "50,10,0,95"])
    assert r.exit_code == 2 and "crop" in r.output
    assert not (tmp_path / "x.json").exists()


def test_tables_refuse_an_unknown_kernel_order_offset_step_or_interpolation():
    from conecal.errors import InputError

    g = ConeGeometry.nominal(sod=100.0, sdd=200.0, shape=(20, 24), pixel_pitch=(0.5, 0.5))
    with pytest.raises(InputError, match="kernel_order"):
        rpgrid.build_tables(iter([np.zeros((20, 24), np.float32)]), 1, g, rpgrid.RPOptions(kernel_order=3))
    with pytest.raises(InputError, match="offset_step_px"):
        rpgrid.build_tables(iter([np.zeros((20, 24), np.float32)]), 1, g, rpgrid.RPOptions(offset_step_px=0.0))
    with pytest.raises(InputError, match="interpolation"):
        rpgrid.build_tables(iter([np.zeros((20, 24), np.float32)]), 1, g, rpgrid.RPOptions(interpolation="quintic"))


def test_slice_sigma_follows_the_profile_of_a_correlated_parameter(monkeypatch):
    """Batches whose minima spread along a narrow (v, theta) valley: with v
    held, each batch's theta minimum collapses towards x and the sigma says
    theta is known; along the profile (the covariance's column) it sees the
    spread, and with a covariance the larger of the two is returned."""
    rng = np.random.default_rng(3)
    valley = np.array([0.0, 4.0, 0.0, 1.0, 0.0])            # v moves 4 px per degree of theta
    minima = [t * valley + rng.normal(0, 0.01, 5) for t in (-2.0, -1.0, 0.0, 1.5, 2.5)]
    across = np.array([0.0, 1.0, 0.0, -4.0, 0.0]) / np.sqrt(17)
    H = 1e4 * np.diag([1.0, 0, 1.0, 0, 1.0]) + 1e4 * np.outer(across, across) + np.outer(valley, valley) / 17

    class Prob:
        def normalised_cost(self, q, m):
            d = q - m
            return float(d @ H @ d)

    monkeypatch.setattr(rpgrid.sigma, "_pair_batches", lambda prob, x, seed, batches: minima)
    opt = rpgrid.RPOptions()
    x = np.zeros(5)
    held = rpgrid.slice_sigma(Prob(), opt, x)
    profile = rpgrid.slice_sigma(Prob(), opt, x, covariance=np.linalg.pinv(H + 1e-6 * np.eye(5)))
    spread = np.std([m[3] for m in minima], ddof=1) / np.sqrt(len(minima))
    k = NAMES.index("theta_deg")
    assert held[k] < 0.2 * spread
    step = 3 * rpgrid.RPOptions().ranges["theta_deg"] / 40
    assert abs(profile[k] - (spread - 0.25 * step)) < 0.1 * spread


def test_whole_range_scans_of_spline_tables_look_up_the_spline_unweighted(small_circular):
    """B-spline tables hold coefficients: the coarse scans (grids, slices)
    must not look them up bilinearly, and are unweighted like the others."""
    from conecal.consistency import kernels
    from conecal.scan import load_scan

    scan = load_scan(small_circular)
    nom = scan.nominal_geometry()
    images = [scan.stack.read(k) for k in range(scan.n_frames)]
    probs = {}
    for interp in ("cubic", "spline"):
        opt = rpgrid.RPOptions(pairs=100, planes_per_pair=16, interpolation=interp)
        tab = rpgrid.build_tables(iter(images), scan.n_frames, nom, opt, noise=True)
        probs[interp] = rpgrid.RPProblem(nom, scan.nominal_transforms(), tab, [0, 1, 0], opt)
    p = np.array([2.7, -1.6, 0.8, 0.4, -0.3])
    for prob in probs.values():
        prob.select(p)
    assert probs["spline"].noise_weighted
    with rpgrid._bilinear(probs["spline"]), rpgrid._bilinear(probs["cubic"]):
        assert probs["spline"].lookup is kernels.lookup_spline and not probs["spline"].noise_weighted
        assert probs["cubic"].lookup is kernels.lookup
        c_spline = probs["spline"].normalised_cost(p)
        c_linear = probs["cubic"].normalised_cost(p)
    assert probs["spline"].lookup is kernels.lookup_spline and probs["spline"].noise_weighted
    # the same function looked up two ways: 1.2 % apart (bilinear on the coefficients: 2.6 %)
    assert abs(c_spline - c_linear) < 0.02 * c_linear


def test_restarts_along_v_leave_a_local_minimum_for_a_lower_one():
    """A cost along v with ripples 0.45 px apart over a shallow bowl at
    v = 0.1 (what transaxial truncation leaves): refined from 0.62 it stops
    in the ripple at ~0.55; the restarts at v -0.5 and -0.25 find the bowl's
    minimum, and from there the answer stays where it is."""
    target = np.array([1.0, 0.1, 0.02, 0.3, -0.2])
    period = 0.45

    class Prob:
        def select(self, p):     # one set of planes here: nothing to choose
            pass

        def residuals(self, q, arrays=None):
            d = np.asarray(q) - target
            return np.concatenate([10 * d[[0, 2, 3, 4]], [0.3 * d[1], 0.6 * np.sin(np.pi * d[1] / period)]])

        def jacobian(self, q, arrays=None):
            d = np.asarray(q) - target
            J = np.zeros((6, 5))
            J[[0, 1, 2, 3], [0, 2, 3, 4]] = 10.0
            J[4, 1] = 0.3
            J[5, 1] = 0.6 * np.pi / period * np.cos(np.pi * d[1] / period)
            return J

    prob, opt = Prob(), rpgrid.RPOptions()
    fit, scale = rpgrid.refine(prob, opt, target + [0, 0.52, 0, 0, 0])
    assert abs(fit.x[1] - target[1] - period) < 0.05            # the neighbouring ripple
    new, scale, evals = rpgrid.restart_along_v(prob, opt, fit, scale)
    assert evals > 0 and new.success
    assert np.allclose(new.x, target, atol=1e-4)
    again, _, _ = rpgrid.restart_along_v(prob, opt, new, scale)
    assert again is new
    assert rpgrid.restart_along_v(prob, rpgrid.RPOptions(v_restarts_px=()), fit, scale)[0] is fit


def test_an_object_filling_the_field_of_view_fails_before_the_tables(small_circular, tmp_path):
    """No usable plane: said after a few views' tables, not after the whole scan's."""
    import shutil
    import time

    import tifffile
    from click.testing import CliRunner

    from conecal.cli.main import cli

    scan = tmp_path / "full"
    shutil.copytree(small_circular, scan)
    stack = tifffile.imread(scan / "projections.tif")
    r, c = np.mgrid[0:stack.shape[1], 0:stack.shape[2]]
    tifffile.imwrite(scan / "projections.tif", (stack + 0.8 + 0.1 * np.sin(r / 7.0) * np.cos(c / 9.0)).astype(np.float32))
    t0 = time.perf_counter()
    res = CliRunner().invoke(cli, ["rp-grid", str(scan), "-o", str(tmp_path / "rp.json")])
    assert res.exit_code == 1 and "0 usable planes" in res.output and "before the tables" in res.output, res.output
    assert time.perf_counter() - t0 < 20 and not (tmp_path / "rp.json").exists()


def test_options_that_lost_their_benchmark_say_they_are_deprecated(tmp_path):
    """Said before any work (here the scan is missing: exit 2 after the warning)."""
    from click.testing import CliRunner

    from conecal.cli.main import cli

    res = CliRunner().invoke(cli, ["rp-grid", str(tmp_path / "none"), "-o", str(tmp_path / "rp.json"),
                                   "--kernel-order", "4", "--fan-sigma-deg", "1"])
    assert "deprecated: --kernel-order 4" in res.output and "deprecated: --fan-sigma-deg" in res.output
    assert res.exit_code == 2
    plain = CliRunner().invoke(cli, ["rp-grid", str(tmp_path / "none"), "-o", str(tmp_path / "rp.json")])
    assert "deprecated" not in plain.output


def test_tables_keeping_every_other_smoothed_offset_look_up_nearly_the_same_values():
    """Pass 2 keeps every k-th offset when its tables would exceed
    max_table_gb: smoothed over 3 px first, then thinned, they look up the
    full tables' values to ~0.1 % (median); tables sampled 2 px apart before
    the smoothing (offset_step_px=2, which lost the benchmark) are off by
    more than twice as much at worst."""
    nom = ConeGeometry.nominal(sod=300, sdd=600, shape=(200, 240), pixel_pitch=(0.4, 0.4))
    g = misaligned(nom, (5, -3, 2, 3, -2))
    rng = np.random.default_rng(3)
    img = sum(gaussian_projection(g, rng.normal(0, 6, 3), rng.uniform(1.5, 4), 0.02) for _ in range(6))
    pts = rng.normal(0, 8, (400, 3))
    m = np.cross(pts - g.source, rng.normal(size=(400, 3)))
    m /= np.linalg.norm(m, axis=1, keepdims=True)

    def look(opt, keep):
        prob = object.__new__(rpgrid.RPProblem)
        prob.tab = rpgrid.build_tables([img], 1, g, opt, keep_every=keep)
        return prob.tab, prob._look(rpgrid._frame(g, prob.tab.ref), np.zeros(400, np.int64), m)[0]

    full_tab, full = look(rpgrid.RPOptions(), 1)
    kept_tab, kept = look(rpgrid.RPOptions(), 2)
    _, coarse = look(rpgrid.RPOptions(offset_step_px=2.0), 1)
    assert kept_tab.tables.shape[2] <= (full_tab.tables.shape[2] + 1) // 2 + 1
    scale = np.abs(full).max()
    assert np.median(np.abs(kept - full)) < 2e-3 * scale
    assert np.abs(kept - full).max() < 0.5 * np.abs(coarse - full).max()


def test_pass2_keeps_every_kth_offset_only_beyond_the_memory_budget():
    from conecal.consistency.rpgrid.pipeline import pass2_keep_every
    from conecal.errors import InputError

    opt = rpgrid.RPOptions()   # 2 GB
    full = 360 * 1455 * 4       # one 1024^2 view's table, bytes
    assert pass2_keep_every(720, full / 4, opt, True) == 1      # 720 x 512^2: as before
    assert pass2_keep_every(1440, full, opt, True) == 2         # 1440 x 1024^2: 3.4 GB in full
    assert pass2_keep_every(1440, full, opt, False) == 2
    with pytest.raises(InputError):
        pass2_keep_every(100000, full, opt, True)
