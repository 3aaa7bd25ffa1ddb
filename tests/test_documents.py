"""Result documents are typed: every output validates against ``conecal schema``,
and every consumer given a corrupted result exits 2 with one line naming the
file and the key (issue 30)."""

import copy
import json

import jsonschema
import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from conecal.cli.main import cli
from conecal.documents import SCHEMA_NAMES


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


@pytest.fixture(scope="module")
def results(system, tmp_path_factory):
    """detect -> fit-linear -> fit-rotation -> diagnose on the shared small system,
    plus a hand-made poses document and a tiny robot scan (no markers needed)."""
    lin, rot = system
    out = tmp_path_factory.mktemp("results")
    for name, scan in (("lin", lin), ("rot", rot)):
        r = run("detect", scan, "-o", out / f"{name}_markers.json")
        assert r.exit_code == 0, r.output
    r = run("fit-linear", lin, "--markers", out / "lin_markers.json", "-o", out / "lin_geometry.json")
    assert r.exit_code == 0, r.output
    r = run("fit-rotation", rot, "--markers", out / "rot_markers.json", "--geometry", out / "lin_geometry.json",
            "-o", out / "rot_geometry.json")
    assert r.exit_code == 0, r.output
    # diagnose needs more observations than the small system has: a 24-frame rotation scan
    assert run("simulate", "rotation", out / "rot24", "--frames", "24").exit_code == 0
    assert run("detect", out / "rot24", "-o", out / "rot24_markers.json").exit_code == 0
    truth = json.loads((out / "rot24" / "truth.json").read_text())["geometry"]
    (out / "rot24_nominal.json").write_text(json.dumps(truth))
    r = run("fit-rotation", out / "rot24", "--markers", out / "rot24_markers.json", "--geometry",
            out / "rot24_nominal.json", "-o", out / "rot24_geometry.json")
    assert r.exit_code == 0, r.output
    r = run("diagnose", out / "rot24_geometry.json", out / "rot24", "--no-image", "-o", out / "diagnosis.json")
    assert r.exit_code == 0, r.output
    g = json.loads((out / "lin_geometry.json").read_text())
    c, s = np.cos(np.radians(10)), np.sin(np.radians(10))
    poses = {"format": "conecal-poses/1", "software": "test", "scan": str(lin), "motion": "robot",
             "source": g["source"], "detector": g["detector"], "axes": [],
             "frames": [{"frame": k, "status": "ok", "R": [[c, -s, 0], [s, c, 0], [0, 0, 1]], "t": [0, 0, k]}
                        for k in range(3)] + [{"frame": 3, "status": "rejected: test", "reason": "few_markers", "R": None, "t": None}]}
    (out / "poses.json").write_text(json.dumps(poses))
    r = run("simulate", "robot", out / "robot", "--frames", "2")
    assert r.exit_code == 0, r.output
    (out / "empty_markers.json").write_text(json.dumps({"format": "conecal-markers/1", "frames": []}))
    return out, lin, rot


def test_every_output_validates_against_its_printed_schema(results, tmp_path):
    out, lin, rot = results
    schemas = {}
    for name in SCHEMA_NAMES:
        r = run("schema", name)
        assert r.exit_code == 0, r.output
        schemas[name] = json.loads(r.output)
        jsonschema.Draft202012Validator.check_schema(schemas[name])
    files = sorted(out.glob("*.json")) + [lin / "truth.json", rot / "truth.json", out / "rot24" / "truth.json"]
    assert len(files) >= 9
    for f in files:
        doc = json.loads(f.read_text())
        jsonschema.validate(doc, schemas[doc["format"].split("/")[0].removeprefix("conecal-")])
    for scan in (lin, rot, out / "robot"):
        jsonschema.validate(yaml.safe_load((scan / "scan.yaml").read_text()), schemas["scan"])
    # the schema says what it must: a markers document without frames is not one
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({"format": "conecal-markers/1"}, schemas["markers"])


def _set(doc, path, value):
    d = doc
    for k in path[:-1]:
        d = d[k]
    if value is DELETE:
        del d[path[-1]]
    else:
        d[path[-1]] = value


DELETE = object()
NAN = float("nan")
GEOMETRY_CORRUPTIONS = [
    (("source",), DELETE), (("detector", "u"), [1.0, 0.0]), (("source",), "abc"), (("source", 2), NAN),
    (("detector", "pixel_pitch"), [0.0, 0.2]), (("detector", "shape"), [0, 256]), (("detector",), DELETE),
    (("detector", "origin"), None), (("detector", "u"), [0.0, 0.0, 0.0]), (("detector", "v"), "same as u"),
    (("axes",), "x"), (("axes", 0, "direction"), [0.0, 0.0, 0.0]), (("axes", 0, "type"), "spiral"),
    (("source",), "in the detector plane"),
]
POSES_CORRUPTIONS = [
    (("frames",), DELETE), (("frames", 0, "R"), [[2, 0, 0], [0, 2, 0], [0, 0, 2]]), (("frames", 0, "status"), "fine"),
    (("frames", 0, "t"), [0.0, 0.0]), (("frames", 0, "frame"), -1), (("source",), None), (("frames",), {}),
    (("detector", "pixel_pitch"), [-1, 0.2]), (("frames", 0, "R"), [[1, 0, 0], [0, 1, 0]]),
    (("frames", 1, "R"), [[1, 0, 0], [0, 1, 0], [0, 0, -1]]), (("frames", 2, "t"), None), (("motion",), "helicopter"),
    (("frames", 3, "reason"), "bad luck"), (("frames", 0, "reason"), "residual"),
]
DIAGNOSIS_CORRUPTIONS = [
    (("verdict",), DELETE), (("result",), 5), (("effects",), "x"), (("located",), [{"size": 1}]),
    (("rms_px_before",), "big"), (("format",), "conecal-diagnosis/2"), (("effects",), [{"parameters": {}}]),
    (("noise_floor_px",), [1]), (("refitted_geometry", "detector", "u"), [0, 0, 2]), (("located",), None),
]


def _corrupt(src, corruption, dst):
    doc = json.loads(src.read_text())
    path, value = corruption
    if value == "same as u":
        value = doc["detector"]["u"]
    elif value == "in the detector plane":
        value = doc["detector"]["origin"]
    _set(doc, path, value)
    dst.write_text(json.dumps(doc))   # NaN is written as the bare token NaN, as some tools do
    return dst


def _one_clear_line(r, bad):
    assert r.exit_code == 2, (r.exit_code, r.output)
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error:") and str(bad) in lines[0], r.output
    assert "internal error" not in r.output and "Traceback" not in r.output


@pytest.mark.parametrize("corruption", GEOMETRY_CORRUPTIONS, ids=lambda c: ".".join(map(str, c[0])))
def test_consumers_of_a_corrupt_geometry_exit_2_naming_file_and_key(results, tmp_path, corruption):
    out, lin, rot = results
    bad = _corrupt(out / "rot_geometry.json", corruption, tmp_path / "bad_geometry.json")
    key = str(corruption[0][0])
    consumers = [
        ("fit-rotation", rot, "--markers", out / "rot_markers.json", "--geometry", bad, "-o", tmp_path / "g.json"),
        ("fit-pose", out / "robot", "--markers", out / "empty_markers.json", "--geometry", bad, "-o", tmp_path / "p.json"),
        ("export", bad, "--scan", rot, "--format", "astra", "-o", tmp_path / "v.txt"),
        ("compare", bad, out / "rot_geometry.json"),
        ("report", bad),
        ("diagnose", bad, rot, "--no-image", "-o", tmp_path / "d.json"),
    ]
    for args in consumers:
        r = run(*args)
        _one_clear_line(r, bad)
        assert key in r.output, (args[0], r.output)
    assert not list(tmp_path.glob("[gpvd].*")), "nothing written"


@pytest.mark.parametrize("corruption", POSES_CORRUPTIONS, ids=lambda c: ".".join(map(str, c[0])))
def test_consumers_of_a_corrupt_poses_document_exit_2(results, tmp_path, corruption):
    out, lin, rot = results
    bad = _corrupt(out / "poses.json", corruption, tmp_path / "bad_poses.json")
    for args in (("export", bad, "--format", "matrices", "-o", tmp_path / "v.txt"),
                 ("compare", bad, out / "poses.json"), ("report", bad)):
        _one_clear_line(run(*args), bad)


@pytest.mark.parametrize("corruption", DIAGNOSIS_CORRUPTIONS, ids=lambda c: ".".join(map(str, c[0])))
def test_report_of_a_corrupt_diagnosis_exits_2(results, tmp_path, corruption):
    out, lin, rot = results
    doc = json.loads((out / "diagnosis.json").read_text())
    if corruption[0][0] == "refitted_geometry" and not doc.get("refitted_geometry"):
        doc["refitted_geometry"] = json.loads((out / "rot_geometry.json").read_text())
        (tmp_path / "with_refit.json").write_text(json.dumps(doc))
        src = tmp_path / "with_refit.json"
    else:
        src = out / "diagnosis.json"
    bad = _corrupt(src, corruption, tmp_path / "bad_diagnosis.json")
    _one_clear_line(run("report", bad), bad)


def test_a_corrupt_document_is_never_written(results, monkeypatch):
    """The writer checks too: an invalid document is a bug, reported, not saved."""
    from conecal.documents import InvalidOutput
    from conecal.jsonio import dumps

    out, _, _ = results
    doc = json.loads((out / "lin_geometry.json").read_text())
    dumps(doc)
    broken = copy.deepcopy(doc)
    broken["detector"]["pixel_pitch"] = [0.2, -0.2]
    with pytest.raises(InvalidOutput, match="pixel_pitch"):
        dumps(broken)


def test_a_result_paired_with_a_scan_it_was_not_fitted_on_exits_2(results, tmp_path):
    out, lin, rot = results
    cases = [
        ("diagnose", out / "lin_geometry.json", rot, "--no-image", "-o", tmp_path / "d.json"),
        ("export", out / "lin_geometry.json", "--scan", rot, "--format", "astra", "-o", tmp_path / "v.txt"),
        ("export", out / "rot_geometry.json", "--scan", lin, "--format", "astra", "-o", tmp_path / "v.txt"),
        ("fit-rotation", rot, "--markers", out / "lin_markers.json", "-o", tmp_path / "g.json"),
        ("fit-linear", lin, "--markers", out / "rot_markers.json", "-o", tmp_path / "g.json"),
    ]
    for args in cases:
        r = run(*args)
        assert r.exit_code == 2, (args[0], r.output)
        line = r.output.strip().splitlines()[-1]
        assert "was computed from scan" in line and str(rot if lin.name in line.split("from scan")[1].split(",")[0]
                                                       else lin) in line, line
    assert not list(tmp_path.iterdir()), "nothing written"
    # on purpose: another scan of the same system (here: the same scan, its log re-timed), whose
    # moving axes the result models
    import shutil

    other = tmp_path / "other"
    shutil.copytree(rot, other)
    log = (other / "log.csv").read_text().splitlines()
    (other / "log.csv").write_text("\n".join([log[0]] + [row.replace(",", ",1", 1) for row in log[1:]]) + "\n")
    r = run("export", out / "rot_geometry.json", "--scan", other, "--format", "astra", "-o", tmp_path / "v.txt")
    assert r.exit_code == 2 and "the log differs" in r.output, r.output
    r = run("export", out / "rot_geometry.json", "--scan", other, "--format", "astra", "-o", tmp_path / "v.txt",
            "--other-scan")
    assert r.exit_code == 0, r.output
    # ... but not a log column the result does not model: its motion would be ignored
    r = run("export", out / "lin_geometry.json", "--scan", rot, "--format", "astra", "-o", tmp_path / "w.txt",
            "--other-scan")
    assert r.exit_code == 2 and "column 'theta' moves" in r.output, r.output


def test_markers_stay_bound_to_the_images_not_to_scan_yaml(results, tmp_path):
    """Editing scan.yaml (e.g. its nominal distances) after detect is fine for the
    markers, which depend on the images; the geometry result notices it."""
    import shutil

    out, lin, rot = results
    edited = tmp_path / "rot_edited"
    shutil.copytree(rot, edited)
    cfg = yaml.safe_load((edited / "scan.yaml").read_text())
    cfg["nominal"]["sod"] = cfg["nominal"]["sod"] + 1.0
    (edited / "scan.yaml").write_text(yaml.safe_dump(cfg))
    r = run("fit-rotation", edited, "--markers", out / "rot_markers.json", "--geometry", out / "lin_geometry.json",
            "-o", tmp_path / "g.json")
    assert r.exit_code == 0, r.output
    r = run("export", out / "rot_geometry.json", "--scan", edited, "--format", "astra", "-o", tmp_path / "v.txt")
    assert r.exit_code == 2 and "scan.yaml differs" in r.output, r.output


def test_relative_paths_resolve_from_the_result_file(results, tmp_path, monkeypatch):
    import shutil

    out, lin, rot = results
    home = tmp_path / "project"
    shutil.copytree(rot, home / "scans" / "rot")
    r = run("detect", home / "scans" / "rot", "-o", home / "results" / "m.json")
    assert r.exit_code == 0
    monkeypatch.chdir(home)
    r = run("fit-rotation", "scans/rot", "--markers", "results/m.json", "--geometry", out / "lin_geometry.json",
            "-o", "results/g.json")
    assert r.exit_code == 0, r.output
    doc = json.loads((home / "results" / "g.json").read_text())
    assert doc["scan_binding"]["path"] == "../scans/rot"
    monkeypatch.chdir(tmp_path)          # elsewhere: the truth lines still find the scan
    r = run("report", home / "results" / "g.json")
    assert r.exit_code == 0 and "vs truth" in r.output, r.output
    r = run("export", home / "results" / "g.json", "--scan", home / "scans" / "rot", "--format", "astra",
            "-o", tmp_path / "v.txt")
    assert r.exit_code == 0, r.output


def test_status_sentence_is_made_from_its_fields_and_a_bad_reason_is_refused():
    from conecal.documents.status import OK, REASONS, Status, rejected, reason_of

    st = rejected("residual", "residual 0.9 px RMS, above 0.5 px")
    assert st.fields() == {"status": "rejected: residual 0.9 px RMS, above 0.5 px", "reason": "residual"}
    assert OK.fields() == {"status": "ok"} and OK.ok and not st.ok
    assert reason_of(st.fields()) == "residual"
    # a file written before the reason field: the sentence's words stand in
    assert reason_of({"status": "rejected: 3 markers detected, fewer than 6"}) == "3 markers detected, fewer than 6"
    for bad in (("ok", "residual", ""), ("rejected", "", "x"), ("rejected", "bad luck", "x"), ("fine", "", "")):
        with pytest.raises(ValueError):
            Status(*bad)
    assert set(REASONS) >= {"few_markers", "ambiguous_identity", "mirror_pose", "residual"}
