"""Property-based corruption of scan inputs: a clear message and exit 2, never a traceback."""

import json
import shutil

import pytest
import yaml
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conecal.cli.main import cli

FUZZ = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

scalars = st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**6), st.floats(allow_nan=True, allow_infinity=True),
                    st.text(max_size=8), st.lists(st.floats(-1e3, 1e3), max_size=5))


def check(result, fit: bool = False):
    """Exit 0 or 2 (bad input: one line starting with 'Error:'); for a fit
    also 1 with 'Fit failed: <why>'. Never an internal error or a traceback."""
    allowed = (0, 1, 2) if fit else (0, 2)
    assert result.exit_code in allowed, (result.exit_code, result.output, result.exception)
    assert "internal error" not in result.output and "Traceback" not in result.output, result.output
    if result.exit_code:
        lines = result.output.strip().splitlines()
        start = "Fit failed" if result.exit_code == 1 else "Error"
        assert lines and lines[-1].startswith(start), result.output


@pytest.fixture
def pristine(small_linear_scan, tmp_path):
    """A factory of fresh copies of the valid scan: one per hypothesis example."""
    count = iter(range(10**6))

    def fresh():
        d = tmp_path / f"s{next(count)}"
        shutil.copytree(small_linear_scan, d)
        return d

    return fresh


def _paths(obj, prefix=()):
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield prefix + (k,)
            yield from _paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield prefix + (i,)
            yield from _paths(v, prefix + (i,))


@FUZZ
@given(data=st.data())
def test_yaml_corruptions(pristine, data):
    scan_dir = pristine()
    cfg = yaml.safe_load((scan_dir / "scan.yaml").read_text())
    paths = list(_paths(cfg))
    for _ in range(data.draw(st.integers(1, 3))):
        path = data.draw(st.sampled_from(paths))
        node = cfg
        try:
            for p in path[:-1]:
                node = node[p]
            if data.draw(st.booleans()):
                node[path[-1]] = data.draw(scalars)
            elif isinstance(node, dict):
                node.pop(path[-1], None)
        except (KeyError, IndexError, TypeError):
            pass
    (scan_dir / "scan.yaml").write_text(yaml.safe_dump(cfg))
    check(CliRunner().invoke(cli, ["detect", str(scan_dir), "-o", str(scan_dir / "m.json")]))


@FUZZ
@given(text=st.text(max_size=300))
def test_arbitrary_yaml_text(pristine, text):
    scan_dir = pristine()
    (scan_dir / "scan.yaml").write_text(text)
    check(CliRunner().invoke(cli, ["detect", str(scan_dir), "-o", str(scan_dir / "m.json")]))


@FUZZ
@given(data=st.data())
def test_log_corruptions(pristine, data):
    scan_dir = pristine()
    lines = (scan_dir / "log.csv").read_text().splitlines()
    i = data.draw(st.integers(0, len(lines) - 1))
    action = data.draw(st.sampled_from(["replace_cell", "drop_line", "dup_line", "garbage"]))
    if action == "replace_cell":
        cells = lines[i].split(",")
        j = data.draw(st.integers(0, len(cells) - 1))
        cells[j] = data.draw(st.one_of(st.text(max_size=6).filter(lambda t: "," not in t and "\n" not in t and "\r" not in t),
                                       st.sampled_from(["nan", "inf", "-1", "1e309", ""])))
        lines[i] = ",".join(cells)
    elif action == "drop_line":
        lines.pop(i)
    elif action == "dup_line":
        lines.insert(i, lines[i])
    else:
        lines[i] = data.draw(st.text(max_size=40).filter(lambda t: "\n" not in t and "\r" not in t))
    (scan_dir / "log.csv").write_text("\n".join(lines) + "\n")
    check(CliRunner().invoke(cli, ["detect", str(scan_dir), "-o", str(scan_dir / "m.json")]))


@FUZZ
@given(cut=st.floats(0.0, 0.999), flip=st.lists(st.integers(0, 10**7), max_size=5))
def test_tiff_corruptions(pristine, cut, flip):
    scan_dir = pristine()
    p = scan_dir / "projections.tif"
    b = bytearray(p.read_bytes())
    for pos in flip:
        b[pos % len(b)] ^= 0xFF
    if cut > 0.5:
        b = b[: int(len(b) * cut)]
    p.write_bytes(bytes(b))
    check(CliRunner().invoke(cli, ["detect", str(scan_dir), "-o", str(scan_dir / "m.json")]))


@FUZZ
@given(data=st.data())
def test_markers_file_corruptions(pristine, data):
    scan_dir = pristine()
    run = CliRunner().invoke
    m = scan_dir / "m.json"
    if not m.exists():
        assert run(cli, ["detect", str(scan_dir), "-o", str(m)]).exit_code == 0
    doc = json.loads(m.read_text())
    fr = data.draw(st.sampled_from(doc["frames"]))
    if fr["markers"]:
        mk = fr["markers"][0]
        key = data.draw(st.sampled_from(sorted(mk)))
        mk[key] = data.draw(scalars)
    else:
        fr["frame"] = data.draw(scalars)
    bad = scan_dir / "bad.json"
    bad.write_text(json.dumps(doc, allow_nan=True))
    check(run(cli, ["fit-linear", str(scan_dir), "--markers", str(bad), "-o", str(scan_dir / "g.json")]), fit=True)
