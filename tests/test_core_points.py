"""Approximate features: changes at every k-th pre-event point (PipelineSettings.core_point_step)."""
import numpy as np
import pytest

from quakescan.change.pipeline import describe_pair
from quakescan.change.settings import PipelineError, PipelineSettings
from quakescan.formats.pointcloud import read_epoch
from tests.scenes import scan_box_pair


@pytest.fixture(scope="module")
def collapse_pair(tmp_path_factory):
    """The box city of tests/test_pipeline.py: building 4 loses 9 of its 12 m, the others are rescanned."""
    folder = tmp_path_factory.mktemp("core_points")
    scan_box_pair(folder, (9.0, 12.0, 9.0, 3.0, 9.0, 12.0))
    pre = read_epoch(folder / "pre.las")
    return pre, read_epoch(folder / "post.las", origin=pre.origin)


def test_step_one_is_every_point_and_the_default(collapse_pair):
    pre, post = collapse_pair
    assert PipelineSettings().core_point_step == 1
    default = describe_pair(pre, post, PipelineSettings())
    explicit = describe_pair(pre, post, PipelineSettings(core_point_step=1))
    assert [(r.building_id, r.n_pre, r.n_post, r.assessable, r.descriptors) for r in default] == \
           [(r.building_id, r.n_pre, r.n_post, r.assessable, r.descriptors) for r in explicit]
    # the known answers of tests/test_pipeline.py hold unchanged
    rows = {r.building_id: r for r in default}
    assert all(rows[b].descriptors["share_changed"] == 0.0 for b in (1, 2, 3, 5, 6))
    assert rows[4].descriptors["height_median"] == pytest.approx(-9.0, abs=0.2)


def test_step_four_approximates_step_one(collapse_pair):
    """Every 4th point: the same buildings, counts and assessability (the full clouds decide
    those), and descriptors close to the exact ones.

    Tolerances: building 4 has several thousand pre-event points, ~1/4 of them remain, so the
    changed share (a proportion p ≈ 0.6–0.9) has a sampling error sqrt(p(1-p)/n) well below
    0.02: 0.05 is loose. The median height change is the roof drop (−9 m, range noise 1 cm),
    which any quarter of the roof points gives within centimetres: 0.1 m. Planarity of the
    post-event neighbourhoods is a median over hundreds of points of a feature in [0, 1]:
    0.05 absolute. Unchanged buildings stay exactly unchanged: their changes are all below
    the levels of detection, whichever points are looked at."""
    pre, post = collapse_pair
    exact = {r.building_id: r for r in describe_pair(pre, post, PipelineSettings())}
    approx = {r.building_id: r for r in describe_pair(pre, post, PipelineSettings(core_point_step=4))}
    assert sorted(approx) == sorted(exact)
    for bid, r in approx.items():
        e = exact[bid]
        assert (r.n_pre, r.n_post, r.assessable) == (e.n_pre, e.n_post, e.assessable)
        assert set(r.descriptors) == set(e.descriptors)
    for bid in (1, 2, 3, 5, 6):
        assert approx[bid].descriptors["share_changed"] == 0.0
    a, e = approx[4].descriptors, exact[4].descriptors
    assert a["share_changed"] == pytest.approx(e["share_changed"], abs=0.05)
    assert a["height_median"] == pytest.approx(e["height_median"], abs=0.1)
    assert a["planarity_median"] == pytest.approx(e["planarity_median"], abs=0.05)
    assert a["distance_median"] == pytest.approx(e["distance_median"], abs=0.2)


def test_a_step_larger_than_a_building_still_describes_it(collapse_pair):
    """Each building keeps at least one query point: no building silently disappears."""
    pre, post = collapse_pair
    rows = describe_pair(pre, post, PipelineSettings(core_point_step=10**9))
    assert [r.building_id for r in rows] == [1, 2, 3, 4, 5, 6] and all(r.assessable for r in rows)


@pytest.mark.parametrize("bad", [0, -4, 2.5, "4", True, None])
def test_a_bad_step_is_refused(bad):
    with pytest.raises(PipelineError, match=f"core point step.*{bad!r}".replace("(", r"\(")):
        PipelineSettings(core_point_step=bad)


def test_settings_json_round_trip_with_and_without_the_step():
    s = PipelineSettings(radius_m=2.5, core_point_step=16)
    d = s.to_json()
    assert d["core_point_step"] == 16
    assert PipelineSettings.from_json(d) == s
    old = {k: v for k, v in PipelineSettings(radius_m=2.5).to_json().items() if k != "core_point_step"}
    assert PipelineSettings.from_json(old) == PipelineSettings(radius_m=2.5)  # a model saved before the knob
    with pytest.raises(PipelineError, match="core point step"):
        PipelineSettings.from_json({**d, "core_point_step": 0})
    assert PipelineSettings(core_point_step=np.int64(3)).to_json()["core_point_step"] == 3  # numpy ints too


def test_a_model_trained_with_a_step_classifies_with_it():
    """The step is part of what a model stores; classification rebuilds it from the model."""
    from quakescan.learning.prediction import model_settings
    from quakescan.learning.model import DamageModel

    settings = PipelineSettings(core_point_step=4)
    model = DamageModel(estimator=None, feature_names=settings.descriptor_names(), radius_m=settings.radius_m,
                        split=settings.to_json())
    assert model_settings(model).core_point_step == 4
    older = {k: v for k, v in settings.to_json().items() if k != "core_point_step"}
    assert model_settings(DamageModel(None, settings.descriptor_names(), 1.5, split=older)).core_point_step == 1
