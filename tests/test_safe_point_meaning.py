"""What the points say, read as they mean it (issue 45): ASPRS noise (classes 7 and 18) is no
surface (left out of every building, counted; a cloud of nothing but noise refused), and a
post-event file dated before its pre-event file is said to be so."""
import datetime
import json
import logging

import laspy
import numpy as np
import pytest

from quakescan.change.align import stable_mask
from quakescan.formats.pointcloud import PointCloudError, acquisition_start, epoch_order_warning, read_epoch
from quakescan.assessment.run import classify
from tests.safe_folder_pair import pair  # noqa: F401  (a fixture)


def with_noise(src, dst, building: int, n: int, noise_class: int, seed: int):
    """`src` with `n` returns of class `noise_class` 30-60 m above `building`'s points appended
    (they keep that building's ID in the file, as a classifier that only flags noise leaves it)."""
    las = laspy.read(src)
    rng = np.random.default_rng(seed)
    idx = rng.choice(np.flatnonzero(np.asarray(las.building_id) == building), n)
    out = laspy.LasData(las.header, points=las.points[np.concatenate([np.arange(len(las.points)), idx])].copy())
    raw_z = np.asarray(out.points["Z"]).copy()  # integer counts of the header's scale
    raw_z[-n:] += np.round(rng.uniform(30.0, 60.0, n) / las.header.scales[2]).astype(raw_z.dtype)
    out.points["Z"] = raw_z
    cls = np.asarray(out.classification).copy()
    cls[-n:] = noise_class
    out.classification = cls
    out.write(dst)
    return dst


def test_noise_above_a_roof_changes_no_building_and_is_counted(pair, tmp_path):  # noqa: F811
    pre = with_noise(pair / "pre.las", tmp_path / "pre_noisy.las", 1, 40, 18, seed=1)
    post = with_noise(pair / "post.las", tmp_path / "post_noisy.las", 1, 300, 7, seed=2)
    clean = classify(pair / "pre.las", pair / "post.las", tmp_path / "clean", model_path=pair / "model.skops")
    noisy = classify(pre, post, tmp_path / "noisy", model_path=pair / "model.skops")
    assert (tmp_path / "noisy" / "buildings.csv").read_bytes() == (tmp_path / "clean" / "buildings.csv").read_bytes()
    assert noisy["noise_points"] == {"pre": 40, "post": 300}
    assert clean["noise_points"] == {"pre": 0, "post": 0}
    assert json.loads((tmp_path / "noisy" / "summary.json").read_text())["noise_points"] == {"pre": 40, "post": 300}
    graded = laspy.read(tmp_path / "noisy" / "post_grades.las")  # every point kept, noise in no building
    assert len(graded.points) == noisy["points"]["post"] == clean["points"]["post"] + 300
    noise = np.asarray(graded.classification) == 7
    assert noise.sum() == 300
    assert (np.asarray(graded.building_id)[noise] == 0).all()
    assert (np.asarray(graded.predicted_grade)[noise] == 255).all()


def test_a_cloud_of_nothing_but_noise_is_refused(pair, tmp_path):  # noqa: F811
    las = laspy.read(pair / "post.las")
    las.classification = np.full(len(las.points), 7, np.uint8)
    las.write(tmp_path / "all_noise.las")
    with pytest.raises(PointCloudError, match=r"all_noise.las: every one of its \d+ points is classified as noise"):
        classify(pair / "pre.las", tmp_path / "all_noise.las", tmp_path / "out", model_path=pair / "model.skops")
    assert not (tmp_path / "out" / "buildings.csv").exists()


def test_noise_is_never_stable_ground_for_the_registration():
    cls = np.array([2, 7, 18, 1, 6, 3])
    ids = np.array([0, 0, 0, 0, 0, 0])
    assert stable_mask(cls, ids).tolist() == [True, False, False, True, False, False]


@pytest.mark.slow
def test_the_dask_path_leaves_noise_out_as_one_process_does(pair, tmp_path):  # noqa: F811
    from quakescan.distributed.engine import classify_distributed
    from quakescan.distributed.cluster import dask_client

    post = with_noise(pair / "post.las", tmp_path / "post_noisy.las", 1, 300, 7, seed=2)
    one = classify(pair / "pre.las", post, tmp_path / "one", model_path=pair / "model.skops")
    with dask_client(1, memory_limit="1GB") as client:
        dist = classify_distributed(pair / "pre.las", post, tmp_path / "dask", client, model_path=pair / "model.skops")
    assert dist["noise_points"] == one["noise_points"] == {"pre": 0, "post": 300}
    assert (tmp_path / "dask" / "buildings.csv").read_bytes() == (tmp_path / "one" / "buildings.csv").read_bytes()
    epoch = read_epoch(tmp_path / "dask" / "post_grades.las")
    assert (epoch.building_id[epoch.classification == 7] == 0).all()


def redated(src, dst, date: str, gps_shift_s: float):
    las = laspy.read(src)
    las.header.creation_date = datetime.date.fromisoformat(date)
    las.gps_time = np.asarray(las.gps_time) + gps_shift_s
    las.write(dst)
    return dst


def test_a_post_event_file_dated_before_the_pre_event_one_is_warned_about(pair, tmp_path, caplog):  # noqa: F811
    early = redated(pair / "post.las", tmp_path / "post_2019.las", "2019-05-01", -3600.0)
    assert acquisition_start(pair / "pre.las") == {"date": "2020-01-01", "gps_start": pytest.approx(
        float(np.asarray(laspy.read(pair / "pre.las").gps_time[:10_000]).min()))}
    warning = epoch_order_warning(pair / "pre.las", early)
    assert "dated 2019-05-01, the pre-event file 2020-01-01" in warning
    assert "GPS time starts 3600 s before" in warning and "swapped" in warning
    with caplog.at_level(logging.WARNING):
        summary = classify(pair / "pre.las", early, tmp_path / "out", model_path=pair / "model.skops", write_las=False)
    assert summary["warnings"] == [warning] and warning in caplog.text
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["warnings"] == [warning]


def test_epochs_in_order_or_in_gps_week_time_are_not_warned_about(pair, tmp_path):  # noqa: F811
    assert epoch_order_warning(pair / "pre.las", pair / "post.las") is None  # one date, one start
    later = redated(pair / "post.las", tmp_path / "post_2021.las", "2021-05-01", 3600.0)
    assert epoch_order_warning(pair / "pre.las", later) is None
    # one survey in two halves, or a photo flight's first images: seconds apart either way
    close = redated(pair / "post.las", tmp_path / "post_close.las", "2020-01-01", -300.0)
    assert epoch_order_warning(pair / "pre.las", close) is None
    week = laspy.read(pair / "post.las")  # GPS week time repeats every week: it orders nothing
    week.header.global_encoding.gps_time_type = laspy.header.GpsTimeType.WEEK_TIME
    week.gps_time = np.asarray(week.gps_time) - 3600.0
    week.write(tmp_path / "post_week.las")
    assert acquisition_start(tmp_path / "post_week.las")["gps_start"] is None
    assert epoch_order_warning(pair / "pre.las", tmp_path / "post_week.las") is None
