"""Bad input and faults of the pipeline (issue 13, "Bad input and faults"): every case ends as a
clear error (exit 2, the file or flag named, what is wrong) or a correct result.

Scan, survey and CityJSON cases live in tests/test_bad_input_scan.py. The pair here is a
small synthetic town written straight to LAS (ground, three box buildings; the post epoch
is the pre epoch with millimetre noise), so no case waits for a scan.
"""
import csv
import errno
import json
import re
import time
import zipfile
from pathlib import Path

import laspy
import numpy as np
import pytest

from quakescan.cli import main

ORIGIN = np.array([155000.0, 463000.0, 0.0])  # Dutch RD New
RD = "EPSG:28992"
BOXES = ((5.0, 15.0, 6.0), (25.0, 35.0, 9.0), (45.0, 55.0, 12.0))  # x0, x1, height; y 15..25


def town(seed=0, noise=0.0):
    """(xyz world, building_id) of ground and three boxes (roof and walls), 0.3 m spacing."""
    rng = np.random.default_rng(seed)
    parts, ids = [], []
    gx, gy = np.meshgrid(np.arange(0.0, 60.0, 0.5), np.arange(0.0, 40.0, 0.5))
    ground = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    inside = np.zeros(len(ground), bool)
    for x0, x1, _ in BOXES:
        inside |= (ground[:, 0] >= x0) & (ground[:, 0] <= x1) & (ground[:, 1] >= 15) & (ground[:, 1] <= 25)
    parts.append(ground[~inside])
    ids.append(np.zeros((~inside).sum(), np.int64))
    for b, (x0, x1, h) in enumerate(BOXES, start=1):
        u = np.arange(0.0, 10.0 + 1e-9, 0.3)
        rx, ry = np.meshgrid(x0 + u, 15.0 + u)
        roof = np.column_stack([rx.ravel(), ry.ravel(), np.full(rx.size, h)])
        z = np.arange(0.3, h, 0.3)
        uu, zz = np.meshgrid(u, z)
        uu, zz = uu.ravel(), zz.ravel()
        walls = np.vstack([np.column_stack([x0 + uu, np.full_like(uu, 15.0), zz]),
                           np.column_stack([x0 + uu, np.full_like(uu, 25.0), zz]),
                           np.column_stack([np.full_like(uu, x0), 15.0 + uu, zz]),
                           np.column_stack([np.full_like(uu, x1), 15.0 + uu, zz])])
        pts = np.vstack([roof, walls])
        parts.append(pts)
        ids.append(np.full(len(pts), b, np.int64))
    xyz = np.vstack(parts) + ORIGIN
    if noise:
        xyz = xyz + rng.normal(0.0, noise, xyz.shape)
    return xyz, np.concatenate(ids)


def write_cloud(path, xyz, building_id=None, crs=RD, classification=None):
    """A LAS 1.4 file of world points; `building_id` as an extra dimension when given."""
    header = laspy.LasHeader(point_format=6, version="1.4")
    if building_id is not None:
        header.add_extra_dims([laspy.ExtraBytesParams(name="building_id", type=np.uint32)])
    header.offsets = np.floor(xyz.min(axis=0)) if len(xyz) else ORIGIN
    header.scales = np.array([0.001] * 3)
    if crs:
        import pyproj

        header.add_crs(pyproj.CRS.from_user_input(crs))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if classification is None:
        classification = np.where(building_id > 0, 6, 2) if building_id is not None else np.full(len(xyz), 2)
    las.classification = np.asarray(classification, np.uint8)
    if building_id is not None:
        las.building_id = building_id.astype(np.uint32)
    las.write(str(path))
    return path


def footprint_doc(polygons, crs=RD, ids=None):
    """A GeoJSON FeatureCollection of rings (world coordinates) with building_id properties."""
    feats = [{"type": "Feature", "properties": {"building_id": i if ids is None else ids[k]},
              "geometry": {"type": "Polygon", "coordinates": [ring]}}
             for k, (i, ring) in enumerate(polygons, start=0)]
    doc = {"type": "FeatureCollection", "features": feats}
    if crs:
        doc["crs"] = {"type": "name", "properties": {"name": f"urn:ogc:def:crs:EPSG::{crs.split(':')[1]}"}}
    return doc


def box_rings(margin=0.5, origin=ORIGIN):
    out = []
    for b, (x0, x1, _) in enumerate(BOXES, start=1):
        a, c = x0 - margin + origin[0], x1 + margin + origin[0]
        lo, hi = 15.0 - margin + origin[1], 25.0 + margin + origin[1]
        out.append((b, [[a, lo], [c, lo], [c, hi], [a, hi], [a, lo]]))
    return out


def tiny_model(path, radius_m=1.5, split_edit=None, estimator=None, grades=(0, 3, 4, 5)):
    """A model file for the default paper descriptors (a small forest on random rows)."""
    from sklearn.ensemble import RandomForestClassifier

    from quakescan.change.settings import PipelineSettings
    from quakescan.learning.model import DamageModel, save_model

    settings = PipelineSettings()
    names = settings.descriptor_names()
    rng = np.random.default_rng(0)
    x = rng.random((40, len(names)))
    y = np.resize(np.repeat(grades, 10), 40)
    est = estimator or RandomForestClassifier(n_estimators=3, max_depth=3, random_state=0)
    est.fit(x, y)
    split = dict(settings.to_json(), radius_m=radius_m)
    if split_edit:
        split["split"].update(split_edit)
    save_model(DamageModel(est, names, radius_m, split=split), path)
    return path


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("pair")
    xyz, bid = town()
    write_cloud(d / "pre.las", xyz, bid)
    xyz2, _ = town(seed=1, noise=0.002)
    write_cloud(d / "post.las", xyz2, bid)
    tiny_model(d / "model.skops")
    (d / "footprints.geojson").write_text(json.dumps(footprint_doc(box_rings())))
    return d


def run(argv, capsys):
    """(exit code, stdout, stderr) of `quakescan argv`; a traceback fails the test."""
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def classify_args(pair, out, *extra, pre=None, post=None):
    return ["classify", "--pre", pre or pair / "pre.las", "--post", post or pair / "post.las",
            "--model", pair / "model.skops", "--no-las", "-o", out, *extra]


def result_rows(folder):
    with open(folder / "buildings.csv", newline="") as f:
        return {int(r["building_id"]): r for r in csv.DictReader(f)}


def no_partials(folder):
    return sorted(p.name for p in folder.rglob("*") if p.name.endswith((".part", ".tmp")) or ".part." in p.name)


# ------------------------------------------------------------------------- outputs and flags

def test_features_into_a_missing_folder_creates_it(pair, tmp_path, capsys):
    out = tmp_path / "new" / "deeper" / "f.las"
    code, _, err = run(["features", pair / "pre.las", "-o", out, "--radius", "1.5", "--features", "planarity"],
                       capsys)
    assert code == 0, err
    assert len(laspy.read(out).planarity) == len(laspy.read(pair / "pre.las").points)
    assert no_partials(tmp_path) == []


@pytest.mark.parametrize("case", ["existing folder", "its input", "text suffix"])
def test_features_refuses_outputs_it_cannot_write(pair, tmp_path, capsys, case):
    src = tmp_path / "in.las"
    src.write_bytes((pair / "pre.las").read_bytes())
    before = src.read_bytes()
    out = {"existing folder": tmp_path / "dir.las", "its input": src, "text suffix": tmp_path / "f.txt"}[case]
    if case == "existing folder":
        out.mkdir()
    code, _, err = run(["features", src, "-o", out, "--radius", "1.5"], capsys)
    assert code == 2 and str(out) in err
    assert {"existing folder": "existing folder", "its input": "input file",
            "text suffix": ".las or .laz"}[case] in err
    assert src.read_bytes() == before and no_partials(tmp_path) == []
    assert not (tmp_path / "f.txt").exists()


@pytest.mark.parametrize("which,what", [("--pre", "pre-event point cloud"), ("--post", "post-event point cloud"),
                                        ("--model", "model file"), ("--footprints", "footprint file")])
@pytest.mark.parametrize("kind", ["missing", "folder"])
def test_classify_names_a_missing_input(pair, tmp_path, capsys, which, what, kind):
    argv = classify_args(pair, tmp_path / "res")
    bad = tmp_path / "nothing.here"
    if kind == "folder":
        bad.mkdir()
    if which == "--footprints":
        argv += ["--footprints", bad]
    else:
        argv[argv.index(which) + 1] = bad
    code, _, err = run(argv, capsys)
    assert code == 2 and f"{bad}: {what}" in err
    assert ("does not exist" if kind == "missing" else "is a folder") in err
    assert not (tmp_path / "res").exists()


@pytest.mark.parametrize("target", ["pre", "other file"])
def test_classify_output_that_is_a_file_is_refused(pair, tmp_path, capsys, target):
    pre = tmp_path / "pre.las"
    pre.write_bytes((pair / "pre.las").read_bytes())
    out = pre if target == "pre" else tmp_path / "notes.txt"
    if target != "pre":
        out.write_text("keep me")
    before = out.read_bytes()
    code, _, err = run(classify_args(pair, out, pre=pre), capsys)
    assert code == 2 and str(out) in err and ("input file" in err or "existing file" in err)
    assert out.read_bytes() == before


@pytest.mark.parametrize("flag,value", [("--trees", "0"), ("--depth", "0"), ("--seed", "-1"),
                                        ("--test-size", "1.0"), ("--test-size", "-0.1"), ("--radius", "0.1"),
                                        ("--lod-height", "100"), ("--lod-curvature", "0"),
                                        ("--min-changed-share", "1.5"), ("--threads", "0")])
def test_train_flags_out_of_range_name_the_flag(pair, tmp_path, capsys, flag, value):
    code, _, err = run(["train", "--pre", pair / "pre.las", "--post", pair / "post.las", "-o", tmp_path / "m.skops",
                        flag, value], capsys)
    assert code == 2 and flag in err and value in err
    assert not (tmp_path / "m.skops").exists()


@pytest.mark.parametrize("argv,flag", [
    (["experiment", "paper", "--trees", "0"], "--trees"),
    (["experiment", "paper", "--buildings", "2"], "--buildings"),
    (["experiment", "paper", "--seed", "-1"], "--seed"),
    (["experiment", "paper", "--test-mix", "0:5,7:3"], "--test-mix"),
    (["experiment", "paper", "--lod-height", "-1"], "--lod-height"),
    (["robustness", "--pre", "pre", "--post", "post", "--seed", "-1"], "--seed"),
    (["robustness", "--pre", "pre", "--post", "post", "--threads", "-4"], "--threads"),
    (["robustness", "--pre", "pre", "--post", "post", "--radii", "1,-1"], "--radii"),
    (["training-set", "--seed", "-1"], "--seed"),
    (["training-set", "--threads", "0"], "--threads"),
    (["calibrate-lod", "--pre", "a.las", "--post", "b.las", "--seed", "-1"], "--seed"),
    (["calibrate-lod", "--pre", "a.las", "--post", "b.las", "--quantile", "2"], "--quantile"),
    (["calibrate-lod", "--pre", "a.las", "--post", "b.las", "--radius", "0"], "--radius"),
    (["features", "a.las", "-o", "b.las", "--radius", "-1"], "--radius"),
    (["classify", "--pre", "a.las", "--post", "b.las", "--threads", "0"], "--threads"),
])
def test_other_commands_name_a_flag_out_of_range(tmp_path, capsys, argv, flag):
    code, _, err = run([*argv, "-o", tmp_path / "out"] if "-o" not in argv else argv, capsys)
    assert code == 2 and flag in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv", [["experiment", "paper"], ["robustness", "--pre", "pre", "--post", "post"],
                                  ["training-set"], ["evaluate", "r.csv", "--truth", "t.csv"]])
def test_report_folders_that_are_files_are_refused(tmp_path, capsys, argv):
    out = tmp_path / "report"
    out.write_text("keep me")
    code, _, err = run([*argv, "-o", out], capsys)
    assert code == 2 and str(out) in err and "existing file" in err and out.read_text() == "keep me"


# ----------------------------------------------------------------------------- full disk

def _enospc(*_a, **_k):
    raise OSError(errno.ENOSPC, "No space left on device")


def test_atomic_writer_names_the_output_of_a_full_disk_and_leaves_nothing(tmp_path):
    from quakescan.errors import ResultsError
    from quakescan.runtime.atomic import replacing as _atomic  # the one atomic writer (results._atomic before)

    target = tmp_path / "sub" / "x.json"
    with pytest.raises(ResultsError, match=r"x\.json: cannot write: no space left"):
        with _atomic(target) as tmp:
            tmp.write_text("half")
            _enospc()
    assert list((tmp_path / "sub").iterdir()) == []

    class LazrsError(Exception):  # what the LAZ backend raises for a failed write
        pass

    LazrsError.__module__ = "lazrs"
    with pytest.raises(ResultsError, match=r"y\.laz: cannot write: no space left"):
        with _atomic(tmp_path / "y.laz") as tmp:
            tmp.write_bytes(b"LASF")
            raise LazrsError("IoError: No space left on device (os error 28)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sub"]
    with pytest.raises(ValueError):  # a programming error stays what it is
        with _atomic(tmp_path / "z.json"):
            raise ValueError("a bug")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sub"]


def test_classify_on_a_full_disk_names_the_file_and_a_rerun_finishes(pair, tmp_path, capsys, monkeypatch):
    from matplotlib.figure import Figure

    out = tmp_path / "res"
    with monkeypatch.context() as m:
        m.setattr(Figure, "savefig", _enospc)
        code, _, err = run(classify_args(pair, out), capsys)
    assert code == 2 and "damage_map.png" in err and "no space left" in err and "Traceback" not in err
    assert no_partials(out) == [] and not (out / "summary.json").exists()
    code, _, err = run(classify_args(pair, out), capsys)
    assert code == 0, err
    assert (out / "summary.json").is_file() and (out / "damage_map.png").is_file()


def test_features_on_a_full_disk(pair, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(laspy.LasData, "write", lambda self, dest, *a, **k: (open(dest, "wb").write(b"LASF"),
                                                                           _enospc()))
    out = tmp_path / "f.laz"
    code, _, err = run(["features", pair / "pre.las", "-o", out, "--radius", "1.5", "--features", "planarity"],
                       capsys)
    assert code == 2 and str(out) in err and "no space left" in err
    assert list(tmp_path.iterdir()) == []


def test_model_save_on_a_full_disk(tmp_path, monkeypatch):
    import skops.io

    from quakescan.errors import ResultsError

    monkeypatch.setattr(skops.io, "dump", lambda obj, file, **kw: (open(file, "wb").write(b"PK"), _enospc()))
    with pytest.raises(ResultsError, match=r"m\.skops: cannot write: no space left"):
        tiny_model(tmp_path / "m.skops")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("where", ["write", "close"])
def test_the_streaming_las_writer_on_a_full_disk_leaves_no_file(tmp_path, monkeypatch, where):
    """Scan, dim and acquisitions stream through LasChunkWriter: a failure while writing, or
    only when the last chunk is flushed on closing, must not leave a cut file under the name."""
    from quakescan.formats.pointcloud import LasChunkWriter, PointCloudError

    xyz, _ = town()
    out = tmp_path / "c.laz"
    w = LasChunkWriter(out, ORIGIN, RD)
    if where == "write":
        monkeypatch.setattr(LasChunkWriter, "write_record", lambda self, rec, bounds: _enospc())
    with pytest.raises(PointCloudError, match=r"c\.laz: cannot write: no space left"):
        with w:
            if where == "close":
                monkeypatch.setattr(w._writer, "close", lambda: (_ for _ in ()).throw(OSError(errno.ENOSPC, "full")))
            from quakescan.formats.pointcloud import PointChunk

            n = len(xyz)
            z = np.zeros(n, np.uint8)
            w.write(PointChunk(xyz - ORIGIN, np.zeros(n), np.zeros(n), z + 1, z + 1, z + 2, np.zeros(n, np.uint32),
                               z + 255, z, np.ones(n, np.uint16)))
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------- checkpoints

@pytest.mark.parametrize("content", ['{"fingerpr', "", '\x00\x00garbage\n{"building_id": 1}\n', "[1, 2]\n"])
def test_a_corrupt_checkpoint_is_discarded_and_recomputed(pair, tmp_path, capsys, caplog, content):
    clean = tmp_path / "clean"
    assert run(classify_args(pair, clean), capsys)[0] == 0
    out = tmp_path / "res"
    out.mkdir()
    (out / ".checkpoint.jsonl").write_text(content)
    code, _, err = run(classify_args(pair, out), capsys)
    assert code == 0, err
    assert (out / "buildings.csv").read_bytes() == (clean / "buildings.csv").read_bytes()
    assert not (out / ".checkpoint.jsonl").exists()


def test_a_checkpoint_line_with_missing_keys_redoes_its_tile(pair, tmp_path, capsys):
    from quakescan.assessment.record import RowCheckpoint

    path = tmp_path / ".checkpoint.jsonl"
    path.write_text('{"fingerprint": "abc"}\n{"building_id": 1, "n_pre": 5}\n')
    assert RowCheckpoint(path, "abc").rows == {}
    assert path.read_text().startswith('{"fingerprint": "abc"}')


# --------------------------------------------------------------------- silently wrong results

def test_a_building_whose_points_coincide_is_not_assessable(pair, tmp_path, capsys):
    xyz, bid = town()
    xyz[bid == 2] = xyz[bid == 2][0]  # every pre-event point of building 2 on one spot
    pre = write_cloud(tmp_path / "pre.las", xyz, bid)
    code, _, err = run(classify_args(pair, tmp_path / "res", pre=pre), capsys)
    assert code == 0, err
    rows = result_rows(tmp_path / "res")
    assert rows[2]["assessable"] == "0" and rows[2]["predicted_grade"] == ""
    assert "1 distinct pre-event positions" in rows[2]["reason"] and "coincide" in rows[2]["reason"]
    assert rows[1]["assessable"] == rows[3]["assessable"] == "1"


def test_a_pile_of_points_on_one_spot_is_no_survey_of_its_building(pair, tmp_path, capsys):
    xyz, bid = town()
    inside = xyz[bid == 2]
    pile = np.repeat(inside[:1], 3 * len(inside), axis=0)
    pile[:, 2] += np.linspace(0.0, 5.0, len(pile))  # one x/y spot, z spread: a stuck scanner
    post = write_cloud(tmp_path / "post.las", np.vstack([xyz, pile]), np.concatenate([bid, np.full(len(pile), 2)]))
    code, _, err = run(classify_args(pair, tmp_path / "res", post=post), capsys)
    assert code == 0, err
    rows = result_rows(tmp_path / "res")
    assert rows[2]["assessable"] == "0" and rows[2]["predicted_grade"] == ""
    stacked = re.match(r"(\d+) of its (\d+) post-event points lie on one x/y spot", rows[2]["reason"])
    assert stacked and int(stacked[2]) == len(pile) + len(inside) and len(pile) < int(stacked[1]) < int(stacked[2])
    assert rows[1]["assessable"] == rows[3]["assessable"] == "1"


@pytest.mark.parametrize("case", ["10 km apart", "other CRS"])
def test_calibrate_lod_checks_the_pair_as_classify_does(pair, tmp_path, capsys, case):
    xyz, bid = town()
    if case == "10 km apart":
        second = write_cloud(tmp_path / "second.las", xyz + [10_000.0, 0.0, 0.0], bid)
    else:
        second = write_cloud(tmp_path / "second.las", xyz, bid, crs="EPSG:32631")
    code, _, err = run(["calibrate-lod", "--pre", pair / "pre.las", "--post", second], capsys)
    assert code == 2 and str(second) in err
    assert ("no overlap" in err) if case == "10 km apart" else ("differs" in err and "EPSG:32631" in err)


def test_one_epoch_without_crs_is_warned_naming_both_files(pair, tmp_path, capsys, caplog):
    xyz, bid = town(seed=1, noise=0.002)
    post = write_cloud(tmp_path / "post.las", xyz, bid, crs=None)
    code, _, err = run(classify_args(pair, tmp_path / "res", post=post), capsys)
    assert code == 0, err
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any(str(post) in m and str(pair / "pre.las") in m and "names no CRS" in m for m in warned)
    assert json.loads((tmp_path / "res" / "summary.json").read_text())["crs"] == RD


@pytest.mark.parametrize("edit,match", [
    ({"radius_m": 0.1}, "radius_m must lie in"),
    ({"lod_height_m": 100.0}, "lod_height_m must lie in"),
    ({"lod_curvature": -1.0}, "lod_curvature must lie in"),
    ({"min_changed_share": 2.0}, "min_changed_share"),
    ({"unknown_knob": 1}, "invalid split settings"),
    ({"estimator": "dummy"}, "DummyClassifier"),
    ({"classes": [0, 3, 7]}, "not EMS-98 grades"),
])
def test_edited_or_foreign_models_are_refused(pair, tmp_path, capsys, edit, match):
    from sklearn.dummy import DummyClassifier

    from quakescan.learning.model import ModelError, load_model

    path = tmp_path / "m.skops"
    if "radius_m" in edit:
        tiny_model(path, radius_m=edit["radius_m"])
    elif "estimator" in edit:
        tiny_model(path, estimator=DummyClassifier())
    elif "classes" in edit:
        tiny_model(path, grades=edit["classes"])
    else:
        tiny_model(path, split_edit=edit)
    with pytest.raises(ModelError, match=match):
        load_model(path)
    code, _, err = run(["classify", "--pre", pair / "pre.las", "--post", pair / "post.las", "--model", path,
                        "-o", tmp_path / "res"], capsys)
    assert code == 2 and str(path) in err


@pytest.mark.parametrize("key,value", [("provenance", "made by hand"), ("radius_m", "1.5"), ("split", "paper"),
                                       ("feature_names", [1, 2]), ("radius_m", float("nan"))])
def test_model_metadata_of_the_wrong_type_is_refused(tmp_path, key, value):
    import skops.io

    from quakescan.learning.model import ModelError, load_model

    path = tiny_model(tmp_path / "m.skops")
    doc = skops.io.load(path, trusted=skops.io.get_untrusted_types(file=path))
    doc["meta"][key] = value
    if key == "feature_names":
        doc["estimator"].fit(np.zeros((4, 2)), [0, 3, 4, 5])
    skops.io.dump(doc, path)
    with pytest.raises(ModelError, match=str(path)):
        load_model(path)


def test_a_model_with_settings_in_range_still_loads(tmp_path):
    from quakescan.learning.model import load_model

    assert load_model(tiny_model(tmp_path / "m.skops", radius_m=4.0, split_edit={"lod_height_m": 0.5})).radius_m == 4.0


def test_footprints_in_degrees_holding_projected_coordinates_are_refused(pair, tmp_path, capsys):
    fp = tmp_path / "fp.geojson"
    fp.write_text(json.dumps(footprint_doc(box_rings(), crs="EPSG:4326")))
    code, _, err = run(classify_args(pair, tmp_path / "res", "--footprints", fp), capsys)
    assert code == 2 and str(fp) in err and "EPSG:4326" in err and "wrong CRS" in err


def test_a_cloud_in_degrees_holding_projected_coordinates_is_refused(tmp_path, capsys):
    xyz, bid = town()
    bad = write_cloud(tmp_path / "deg.las", xyz, bid, crs="EPSG:4326")
    code, _, err = run(["features", bad, "-o", tmp_path / "f.las", "--radius", "1.5"], capsys)
    assert code == 2 and str(bad) in err and "EPSG:4326" in err


@pytest.mark.parametrize("defect,reason", [
    ("nan vertex", "not a finite number"),
    ("bow-tie", "Self-intersection"),
    ("no area", "no area"),
])
def test_a_broken_footprint_keeps_its_building_as_not_assessable(pair, tmp_path, capsys, caplog, defect, reason):
    rings = box_rings()
    b, ring = rings[1]
    if defect == "nan vertex":
        ring[1] = [float("nan"), ring[1][1]]
    elif defect == "bow-tie":
        ring[1], ring[2] = ring[2], ring[1]
    else:
        ring[:] = [ring[0], ring[1], [(ring[0][0] + ring[1][0]) / 2, ring[0][1]], ring[0]]  # on one line
    fp = tmp_path / "fp.geojson"
    fp.write_text(json.dumps(footprint_doc(rings)))  # NaN is written as the literal NaN
    code, _, err = run(classify_args(pair, tmp_path / "res", "--footprints", fp), capsys)
    assert code == 0, err
    rows = result_rows(tmp_path / "res")
    assert sorted(rows) == [1, 2, 3]
    assert rows[2]["assessable"] == "0" and rows[2]["predicted_grade"] == "" and reason in rows[2]["reason"]
    assert rows[1]["assessable"] == rows[3]["assessable"] == "1"
    gj = json.loads((tmp_path / "res" / "buildings.geojson").read_text())
    assert [f["id"] for f in gj["features"]] == [1, 2, 3]
    assert any(str(fp) in r.getMessage() and "building 2" in r.getMessage() for r in caplog.records
               if r.levelname == "WARNING")


def test_a_truth_csv_listing_a_building_twice_is_refused(pair, tmp_path, capsys):
    truth = tmp_path / "truth.csv"
    truth.write_text("building_id,grade\n1,0\n2,3\n1,5\n")
    result = tmp_path / "buildings.csv"
    result.write_text("building_id,assessable,predicted_grade\n1,1,0\n2,1,3\n")
    code, _, err = run(["evaluate", result, "--truth", truth], capsys)
    assert code == 2 and str(truth) in err and "building 1 is listed twice" in err and "line 4" in err
    code, _, err = run(["train", "--pre", pair / "pre.las", "--post", pair / "post.las", "--truth", truth,
                        "-o", tmp_path / "m.skops"], capsys)
    assert code == 2 and str(truth) in err and "building 1 is listed twice" in err


@pytest.mark.parametrize("rows,match", [
    ("1,1,\n", "line 2"),  # assessable without a grade
    ("1,1,0\n1,1,3\n", "building 1 is listed twice"),
    ("1,1,9\n", "predicted grade 9"),
])
def test_evaluate_names_the_bad_line_of_a_result(tmp_path, capsys, rows, match):
    truth = tmp_path / "truth.csv"
    truth.write_text("building_id,grade\n1,0\n")
    result = tmp_path / "buildings.csv"
    result.write_text("building_id,assessable,predicted_grade\n" + rows)
    code, _, err = run(["evaluate", result, "--truth", truth], capsys)
    assert code == 2 and str(result) in err and match in err


@pytest.mark.parametrize("which", ["result", "truth"])
def test_evaluate_names_a_table_that_is_not_text(pair, tmp_path, capsys, which):
    truth, result = tmp_path / "t.csv", tmp_path / "r.csv"
    truth.write_text("building_id,grade\n1,0\n")
    result.write_text("building_id,assessable,predicted_grade\n1,1,0\n")
    argv = {"result": ["evaluate", pair / "pre.las", "--truth", truth],
            "truth": ["evaluate", result, "--truth", pair / "pre.las"]}[which]
    code, _, err = run(argv, capsys)
    assert code == 2 and str(pair / "pre.las") in err


def test_evaluate_output_that_is_a_file_is_refused(tmp_path, capsys):
    truth = tmp_path / "truth.csv"
    truth.write_text("building_id,grade\n1,0\n")
    result = tmp_path / "buildings.csv"
    result.write_text("building_id,assessable,predicted_grade\n1,1,0\n")
    code, _, err = run(["evaluate", result, "--truth", truth, "-o", truth], capsys)
    assert code == 2 and "existing file" in err


# ---------------------------------------------------------------------------------- hangs

def test_identical_points_do_not_make_features_quadratic(tmp_path, capsys):
    from quakescan.change.features import compute_features

    xyz = np.tile(ORIGIN + [10.0, 10.0, 5.0], (200_000, 1))
    t0 = time.perf_counter()
    f = compute_features(xyz, 1.5, ("planarity", "num_neighbours", "z_rank", "roughness"))
    assert time.perf_counter() - t0 < 10.0
    assert np.all(f["num_neighbours"] == 200_000) and np.all(f["z_rank"] == 0.0)
    assert np.all(np.isnan(f["planarity"])) and np.all(np.isnan(f["roughness"]))  # no extent: NaN by the rule
    src = write_cloud(tmp_path / "pile.las", xyz)
    t0 = time.perf_counter()
    code, _, err = run(["features", src, "-o", tmp_path / "f.las", "--radius", "1.5"], capsys)
    assert code == 0, err
    assert time.perf_counter() - t0 < 30.0


def test_duplicates_give_the_reference_features():
    from quakescan.change._feature_reference import reference_features
    from quakescan.change.features import compute_features

    rng = np.random.default_rng(3)
    xyz = np.round(rng.random((1500, 3)) * [8.0, 8.0, 2.0], 3)
    xyz = np.vstack([xyz, xyz[:300], xyz[:40], xyz[:40]])
    fast, ref = compute_features(xyz, 1.0), reference_features(xyz, 1.0)
    for name in fast:
        np.testing.assert_allclose(fast[name], ref[name], rtol=1e-6, atol=1e-9, err_msg=name)
    sub = compute_features(xyz, 1.0, query_index=np.array([5, 1500 + 5, 1800 + 5, 7]))
    assert np.array_equal(sub["planarity"][:3], np.full(3, fast["planarity"][5]))


def test_points_are_grouped_only_where_a_position_holds_a_stack():
    """Grouping coincident points costs two sorts of every point (5 s for 8.6 M); a real scan's
    few coincident pairs cost the kernels nothing, so they group only when some position holds
    STACK_COPIES copies. 63 copies of one point among 1000: not grouped for the kernels, grouped
    exactly when asked for any duplicate; 64: grouped, and the features equal the reference."""
    from quakescan.change._feature_reference import reference_features
    from quakescan.change.features import STACK_COPIES, compute_features, duplicate_groups

    assert STACK_COPIES == 64
    rng = np.random.default_rng(4)
    base = np.round(rng.random((1000, 3)) * [8.0, 8.0, 2.0], 3)
    below = np.vstack([base, np.tile(base[:1], (62, 1))])  # 63 copies of base[0]
    assert duplicate_groups(below, STACK_COPIES) is None
    first, inverse = duplicate_groups(below)
    assert len(first) == 1000 and np.array_equal(below[first][inverse], below)
    stack = np.vstack([below, base[:1]])  # 64 copies
    first, inverse = duplicate_groups(stack, STACK_COPIES)
    assert len(first) == 1000 and np.array_equal(stack[first][inverse], stack)
    fast, ref = compute_features(stack, 1.0), reference_features(stack, 1.0)
    for name in fast:
        np.testing.assert_allclose(fast[name], ref[name], rtol=1e-6, atol=1e-9, err_msg=name)


def test_identical_queries_do_not_make_nearest_neighbours_quadratic():
    from quakescan.change.split import nearest_neighbours

    pre = np.tile([5.0, 5.0, 5.0], (200_000, 1))
    post = np.tile([5.0, 5.0, 5.01], (200_000, 1))
    t0 = time.perf_counter()
    i, d = nearest_neighbours(pre, post)
    assert time.perf_counter() - t0 < 10.0
    assert np.allclose(d, 0.01) and i.min() >= 0


def _inflating_zip(path, declared=2 << 30):
    """A small zip whose directory says its member inflates to `declared` bytes."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("schema.json", b"\0" * 1_000_000)
    data = bytearray(path.read_bytes())
    cd = data.rfind(b"PK\x01\x02")
    size = min(declared, 0xFFFFFFFE).to_bytes(4, "little")
    data[cd + 24:cd + 28] = size  # central directory: uncompressed size
    data[22:26] = size  # local header, for readers that look there
    path.write_bytes(bytes(data))
    return path


def test_a_model_that_would_inflate_to_gigabytes_is_refused_before_reading(tmp_path, capsys, monkeypatch):
    import skops.io

    from quakescan.learning.model import ModelError, load_model

    bomb = _inflating_zip(tmp_path / "bomb.skops")
    assert sum(i.file_size for i in zipfile.ZipFile(bomb).infolist()) > 1 << 30
    monkeypatch.setattr(skops.io, "get_untrusted_types", lambda **k: pytest.fail("the archive was read"))
    monkeypatch.setattr(skops.io, "load", lambda *a, **k: pytest.fail("the archive was read"))
    with pytest.raises(ModelError, match="would inflate to"):
        load_model(bomb)
    notzip = tmp_path / "text.skops"
    notzip.write_text("not a zip")
    with pytest.raises(ModelError, match="not a skops archive"):
        load_model(notzip)


# ------------------------------------------------------------------ errors that name the file

def test_align_with_too_few_stable_points_names_both_epochs(tmp_path, capsys):
    xyz, bid = town()
    keep = bid > 0  # buildings only: nothing stable to align on
    pre = write_cloud(tmp_path / "pre.las", xyz[keep], bid[keep])
    post = write_cloud(tmp_path / "post.las", xyz[keep] + [0.0, 0.0, 0.001], bid[keep])
    model = tiny_model(tmp_path / "m.skops")
    code, _, err = run(["classify", "--pre", pre, "--post", post, "--model", model, "--align", "-o",
                        tmp_path / "res"], capsys)
    assert code == 2 and "too few stable points" in err and str(pre) in err and str(post) in err


# ------------------------------------------------------------------------- caches elsewhere

def test_an_unreadable_experiment_cache_is_recomputed(pair, tmp_path, caplog):
    from quakescan.change.settings import PipelineSettings
    from quakescan.studies.experiment import _table

    settings = PipelineSettings()
    cache = tmp_path / "table"
    first = _table(pair / "pre.las", [(pair / "post.las", 0)], cache, settings, 1)
    (written,) = tmp_path.glob("table_*.npz")
    written.write_bytes(written.read_bytes()[:100])  # cut
    again = _table(pair / "pre.las", [(pair / "post.las", 0)], cache, settings, 1)
    assert np.array_equal(first["x"], again["x"]) and "unreadable cache" in caplog.text
    assert no_partials(tmp_path) == []


@pytest.mark.parametrize("case", ["other CRS", "10 km apart", "empty", "footprints in another CRS",
                                  "footprints 10 km away"])
def test_what_the_headers_can_refuse_is_refused_before_a_point_is_read(pair, tmp_path, capsys, monkeypatch, case):
    """CRS, extents and point counts come from the headers (and the footprints' file): a pair
    that cannot work is refused without reading either cloud, naming the file at fault."""
    import quakescan.formats.pair as pair_module

    def no_read(*a, **k):
        raise AssertionError("a cloud was read")

    xyz, bid = town(seed=1, noise=0.002)
    post, fp = pair / "post.las", None
    if case == "other CRS":
        post = write_cloud(tmp_path / "post.las", xyz, bid, crs="EPSG:32631")
    elif case == "10 km apart":
        post = write_cloud(tmp_path / "post.las", xyz + [10_000.0, 0.0, 0.0], bid)
    elif case == "empty":
        post = write_cloud(tmp_path / "post.las", xyz[:0], bid[:0])
    else:
        fp = tmp_path / "fp.geojson"
        shift = [10_000.0, 0.0] if case == "footprints 10 km away" else [0.0, 0.0]
        rings = [(i, [[x + shift[0], y + shift[1]] for x, y in ring]) for i, ring in box_rings()]
        fp.write_text(json.dumps(footprint_doc(rings, crs="EPSG:32631" if "CRS" in case else RD)))
    monkeypatch.setattr(pair_module, "read_epoch", no_read)
    code, _, err = run(classify_args(pair, tmp_path / "res", *(["--footprints", fp] if fp else []), post=post),
                       capsys)
    assert code == 2, err
    said = {"other CRS": ("differs", "EPSG:32631"), "10 km apart": ("no overlap", "headers"),
            "empty": ("empty", "counts no point"), "footprints in another CRS": ("reproject the footprints", "EPSG:32631"),
            "footprints 10 km away": ("no footprint contains a pre-event point", "wrong CRS?")}[case]
    assert all(s in err for s in said) and str(fp or post) in err, err


def test_a_header_without_an_extent_is_not_taken_for_one_apart():
    """Some writers leave a header's extent at zero: the overlap is then judged on the points."""
    from quakescan.formats.pointcloud import HeaderFacts, check_pair_headers

    def facts(lo, hi, crs="EPSG:28992"):
        return HeaderFacts(Path("a.las"), crs, 10, np.array(lo, float), np.array(hi, float))

    check_pair_headers(facts([0, 0, 0], [0, 0, 0]), facts([5e5, 5e6, 0], [5e5 + 10, 5e6 + 10, 5]))
    with pytest.raises(Exception, match="no overlap"):
        check_pair_headers(facts([0, 0, 0], [10, 10, 1]), facts([5e5, 5e6, 0], [5e5 + 10, 5e6 + 10, 5]))


def test_a_post_event_survey_that_misses_buildings_is_said_with_the_counts(pair, tmp_path, capsys, caplog):
    """Footprints reached by both epochs, by one, by none: counted in the summary, and said on
    stderr when the post-event survey does not cover every building."""
    xyz, bid = town(seed=1, noise=0.002)
    west = xyz[:, 0] < ORIGIN[0] + 20.0  # the first box and the ground beside it
    post = write_cloud(tmp_path / "post.las", xyz[west], bid[west])
    fp = tmp_path / "fp.geojson"
    rings = box_rings() + [(9, [[x + 200.0, y] for x, y in box_rings()[0][1]])]  # a fourth one off the clouds
    fp.write_text(json.dumps(footprint_doc(rings)))
    code, _, err = run(classify_args(pair, tmp_path / "res", "--footprints", fp, post=post), capsys)
    assert code == 0, err
    coverage = json.loads((tmp_path / "res" / "summary.json").read_text())["coverage"]
    assert coverage == {"footprints": 4, "both": 1, "pre_only": 2, "post_only": 0, "neither": 1}
    said = [r.getMessage() for r in caplog.records if r.levelname == "WARNING" and "footprints" in r.getMessage()]
    assert any(str(post) in m and "of 4 footprints, 1 hold points of both epochs, 2 of the pre-event epoch only" in m
               for m in said), said


def test_footprints_beyond_both_clouds_are_counted_but_not_warned_of(pair, tmp_path, capsys, caplog):
    fp = tmp_path / "fp.geojson"
    rings = box_rings() + [(9, [[x + 200.0, y] for x, y in box_rings()[0][1]])]  # off both clouds
    fp.write_text(json.dumps(footprint_doc(rings)))
    code, _, err = run(classify_args(pair, tmp_path / "res", "--footprints", fp), capsys)
    assert code == 0, err
    assert json.loads((tmp_path / "res" / "summary.json").read_text())["coverage"]["neither"] == 1
    assert not [r for r in caplog.records if r.levelname == "WARNING" and "footprints, " in r.getMessage()]
