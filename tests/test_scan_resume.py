"""An interrupted scan resumes from its finished flight lines and writes the same bytes."""
import json

import pytest

from quakescan.acquisition.pulses import pulse_count
from quakescan.acquisition.raycast import ground_level
from quakescan.acquisition.scan import scan
from quakescan.acquisition.survey import plan_flight, preset
from quakescan.formats.scene import write_scene
from quakescan.formats.synthetic import box_city

# 60° FOV at 50 m: 23 m between lines, five lines over a 3 × 2 box city
SURVEY = preset("paper").replace(pulse_rate_hz=50_000.0, altitude_agl_m=50.0, fov_deg=60.0, sweep_deg=180.0)
BATCH = 4_000  # several batches per line


class Stop(Exception):
    pass


def _stop_after(pulses):
    def progress(done, total):
        if done >= pulses:
            raise Stop

    return progress


def _line_ends(scene):
    plan = plan_flight(SURVEY, scene.bounds(), ground_level(scene))
    ends, total = [], 0
    for ln in plan.lines:
        total += pulse_count(SURVEY, ln)
        ends.append(total)
    return ends


@pytest.mark.parametrize("suffix", ["las", "laz"])
def test_a_scan_stopped_after_k_lines_resumes_and_writes_the_same_bytes(tmp_path, suffix):
    scene = box_city(rows=3, cols=2)
    ends = _line_ends(scene)
    assert len(ends) >= 4
    whole = scan(scene, SURVEY, tmp_path / f"whole.{suffix}", seed=5, batch_rays=BATCH)
    out, ck = tmp_path / f"part.{suffix}", tmp_path / f"part.{suffix}.lines"
    k = 2
    with pytest.raises(Stop):  # stopped in the middle of line k + 1
        scan(scene, SURVEY, out, seed=5, batch_rays=BATCH, checkpoint=ck, fingerprint="f",
             progress=_stop_after(ends[k - 1] + 1))
    assert not out.exists() and not (tmp_path / f"part.{suffix}.part").exists()
    if suffix == "laz":  # a LAZ cannot be cut by points: the finished lines' records are kept
        assert sorted(p.name for p in ck.glob("line_*")) == [f"line_{i:06d}.{e}" for i in range(k)
                                                             for e in ("bin", "json")]
    else:  # a LAS's partial file holds them: no second copy
        assert sorted(p.name for p in ck.glob("line_*")) == [f"line_{i:06d}.json" for i in range(k)]
        assert (ck / "partial.las").is_file()
    resumed = scan(scene, SURVEY, out, seed=5, batch_rays=BATCH, checkpoint=ck, fingerprint="f", workers=1)
    assert resumed.lines_resumed == k
    assert out.read_bytes() == (tmp_path / f"whole.{suffix}").read_bytes()
    assert not ck.exists()  # removed once the output is complete
    for name in ("points", "pulses_emitted", "pulses_swept", "rays_cast", "points_by_return", "points_by_building",
                 "points_by_surface"):
        assert getattr(resumed, name) == getattr(whole, name), name


def test_a_checkpoint_of_another_scan_or_a_cut_line_is_not_used(tmp_path):
    scene = box_city(rows=3, cols=2)
    ends = _line_ends(scene)
    whole = tmp_path / "whole.las"
    scan(scene, SURVEY, whole, seed=5, batch_rays=BATCH)
    out, ck = tmp_path / "part.las", tmp_path / "part.las.lines"
    with pytest.raises(Stop):  # lines of seed 6; no fingerprint from the caller: the key has the seed
        scan(scene, SURVEY, out, seed=6, batch_rays=BATCH, checkpoint=ck, fingerprint="",
             progress=_stop_after(ends[1]))
    assert len(list(ck.glob("line_*.json"))) == 2
    r = scan(scene, SURVEY, out, seed=5, batch_rays=BATCH, checkpoint=ck, fingerprint="")
    assert r.lines_resumed == 0 and out.read_bytes() == whole.read_bytes()
    # a line whose points were cut (a full disk, a copy stopped half-way) is scanned again,
    # and so is one whose record was cut short; the lines between are still taken
    with pytest.raises(Stop):
        scan(scene, SURVEY, out, seed=5, batch_rays=BATCH, checkpoint=ck, fingerprint="",
             progress=_stop_after(ends[2]))
    partial = ck / "partial.las"
    partial.write_bytes(partial.read_bytes()[:-10])
    (ck / "line_000000.json").write_text("{\"line\": 0, \"byt")
    r = scan(scene, SURVEY, out, seed=5, batch_rays=BATCH, checkpoint=ck, fingerprint="")
    assert r.lines_resumed == 1 and out.read_bytes() == whole.read_bytes()  # line 1 only


def test_a_killed_scan_resumes_from_the_file_it_left(tmp_path):
    """kill -9 leaves OUT.las.lines/writing.las (its header never finished) and the finished lines' records."""
    scene = box_city(rows=3, cols=2)
    ends = _line_ends(scene)
    whole = tmp_path / "whole.las"
    scan(scene, SURVEY, whole, seed=5, batch_rays=BATCH)
    out, ck = tmp_path / "part.las", tmp_path / "part.las.lines"
    with pytest.raises(Stop):
        scan(scene, SURVEY, out, seed=5, batch_rays=BATCH, checkpoint=ck, progress=_stop_after(ends[1] + 1))
    # what a killed writer leaves: its temporary file, no header counts, a point half-written
    import laspy

    data = (ck / "partial.las").read_bytes()
    (ck / "partial.las").unlink()
    line1 = json.loads((ck / "line_000001.json").read_text())
    with laspy.open(whole) as f:
        start, size = f.header.offset_to_point_data, f.header.point_format.size
    end = start + (line1["first_point"] + sum(b["points"] for b in line1["batches"])) * size
    assert len(data) >= end
    left = bytearray(data[:end] + bytes(size // 2))  # and half of a next point
    left[107:111] = bytes(4)  # legacy point count 0
    (ck / "writing.las").write_bytes(bytes(left))
    r = scan(scene, SURVEY, out, seed=5, batch_rays=BATCH, checkpoint=ck)
    assert r.lines_resumed == 2 and out.read_bytes() == whole.read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["part.las", "whole.las"]


def test_a_cut_laz_line_is_scanned_again(tmp_path):
    scene = box_city(rows=3, cols=2)
    ends = _line_ends(scene)
    whole = tmp_path / "whole.laz"
    scan(scene, SURVEY, whole, seed=5, batch_rays=BATCH)
    out, ck = tmp_path / "part.laz", tmp_path / "part.laz.lines"
    with pytest.raises(Stop):
        scan(scene, SURVEY, out, seed=5, batch_rays=BATCH, checkpoint=ck, progress=_stop_after(ends[1]))
    data = ck / "line_000001.bin"
    data.write_bytes(data.read_bytes()[:-10])
    r = scan(scene, SURVEY, out, seed=5, batch_rays=BATCH, checkpoint=ck)
    assert r.lines_resumed == 1 and out.read_bytes() == whole.read_bytes()


def test_the_command_resumes_an_interrupted_scan(tmp_path, capsys, monkeypatch):
    from quakescan import cli
    import quakescan.acquisition.scan

    scene = box_city(rows=3, cols=2)
    ends = _line_ends(scene)
    write_scene(scene, tmp_path / "scene")
    (tmp_path / "survey.json").write_text(json.dumps({"format": "quakescan-survey", "version": 1,
                                                      **{k: getattr(SURVEY, k) for k in
                                                         ("pulse_rate_hz", "altitude_agl_m", "fov_deg", "sweep_deg")}}))
    args = ["scan", str(tmp_path / "scene"), "-o", str(tmp_path / "a.las"), "--survey", str(tmp_path / "survey.json"),
            "--seed", "3"]
    assert cli.main(args[:3] + [str(tmp_path / "ref.las")] + args[4:]) == 0
    real_scan = quakescan.acquisition.scan.scan

    def interrupted(*a, **kw):
        kw["progress"] = _stop_after(ends[2])
        return real_scan(*a, **kw)

    monkeypatch.setattr(quakescan.acquisition.scan, "scan", interrupted)
    with pytest.raises(Stop):
        cli.main(args)
    monkeypatch.setattr(quakescan.acquisition.scan, "scan", real_scan)
    assert (tmp_path / "a.las.lines").is_dir() and not (tmp_path / "a.las").exists()
    capsys.readouterr()
    assert cli.main(args) == 0
    assert "resumed: 3 of" in capsys.readouterr().out
    assert (tmp_path / "a.las").read_bytes() == (tmp_path / "ref.las").read_bytes()
    assert not (tmp_path / "a.las.lines").exists()
