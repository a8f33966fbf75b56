"""The descriptor registry (core/change/descriptors.py): one place names every change
descriptor, says whether it transfers across sensors and how it reads in words, and takes a
new family with one registration line that a run then computes."""
import numpy as np
import pytest

from quakescan.change import descriptors as registry
from quakescan.change.pipeline import describe_pair
from quakescan.change.settings import PipelineError, PipelineSettings, settings_for_descriptors
from quakescan.change.surface import NOISE_FREE_DESCRIPTORS, SURFACE_DESCRIPTORS, SurfaceSettings
from quakescan.learning.default_model import MODEL_DESCRIPTORS
from tests.test_surface import epoch, scene


def test_the_built_in_families_are_the_surface_columns_in_their_order():
    assert registry.names() == SURFACE_DESCRIPTORS
    assert [f.name for f in registry.families()] == ["raster", "interior", "core", "openings"]
    # the shipped model reads what transfers: every built-in one but the sensor's noise
    assert MODEL_DESCRIPTORS == NOISE_FREE_DESCRIPTORS == registry.transferring()
    assert set(SURFACE_DESCRIPTORS) - set(MODEL_DESCRIPTORS) == {
        "m_distance_p10", "m_distance_median", "m_distance_p90", "m_lod_median"}
    assert registry.code_versions() == {"descriptors": registry.DESCRIPTOR_VERSION,
                                        "openings": registry.OPENINGS_VERSION}


def test_every_descriptor_reads_in_words_with_its_unit():
    for name in registry.names():
        d = registry.get(name)
        assert d.meaning and d.unit in registry.UNITS
    assert registry.get("s_lowered_storey").wording(0.384) == "38 % of the footprint lowered by more than a storey"
    assert registry.get("m_distance_median").wording(-1.234).startswith("-1.23 m ")
    assert registry.get("s_height_ratio_mean").wording(0.5).startswith("0.50 of its height")


def _roof_heights(view: registry.BuildingView) -> dict:
    """The toy family: the building's pre-event roof top and what stands over its cells after,
    above its ground."""
    post = view.post_over()
    return {"t_roof_m": float(view.own[:, 2].max() - view.ground),
            "t_post_top_m": float(post[:, 2].max() - view.ground) if len(post) else 0.0}


TOY = registry.Family("toy", (registry.Descriptor("t_roof_m", "m", "high before the event"),
                              registry.Descriptor("t_post_top_m", "m", "high after it")), version=1,
                      compute=_roof_heights)


@pytest.fixture
def toy():
    registry.register(TOY)
    yield TOY
    registry.unregister("toy")


def test_a_registered_family_is_computed_by_a_run_that_asks_for_it(toy):
    """A 10 x 10 x 6 m box whose every part came down to 1 m, on a ground at 0 m: before 6 m,
    after 1 m, to the noise of the points: the top of thousands of N(0, 1 cm) heights lies
    about 4 sigma up and the ground (their 10th percentile) 1.3 sigma down."""
    rng = np.random.default_rng(3)
    pre, post = scene(rng, 60, False), scene(rng, 60, False)
    post_xyz = post[0].copy()
    on_building = post[1] == 1
    post_xyz[on_building, 2] = np.minimum(post_xyz[on_building, 2], 1.0)
    settings = settings_for_descriptors(["s_lowered_1m", "t_roof_m", "t_post_top_m"], 1.5)
    row = describe_pair(epoch(pre), epoch((post_xyz, post[1], post[2])), settings, workers=1)[0]
    assert row.assessable
    assert row.descriptors["t_roof_m"] == pytest.approx(6.0, abs=0.08)
    assert row.descriptors["t_post_top_m"] == pytest.approx(1.0, abs=0.08)
    assert row.descriptors["s_lowered_1m"] > 0.9
    assert registry.code_versions(["t_roof_m"])["toy"] == 1
    assert "toy" not in registry.code_versions(["s_lowered_1m"])  # not asked for: no cache key of it


def test_a_family_not_asked_for_is_not_computed(toy, monkeypatch):
    calls = []
    monkeypatch.setattr(registry, "_FAMILIES", {**registry._FAMILIES, "toy": registry.Family(
        "toy", TOY.descriptors, 1, compute=lambda view: calls.append(1) or _roof_heights(view))})
    rng = np.random.default_rng(4)
    pre = scene(rng, 40, False)
    describe_pair(epoch(pre), epoch(pre), PipelineSettings(surface=SurfaceSettings(), paper_descriptors=False,
                                                          surface_descriptors=("s_lowered_1m",)), workers=1)
    assert calls == []


def test_registration_refuses_what_would_be_ambiguous(toy):
    with pytest.raises(registry.DescriptorError, match="registered already"):
        registry.register(TOY)
    with pytest.raises(registry.DescriptorError, match="taken"):
        registry.register(registry.Family("other", (registry.Descriptor("s_raised", "share", "x"),), 1,
                                          compute=_roof_heights))
    with pytest.raises(registry.DescriptorError, match="compute"):
        registry.register(registry.Family("lazy", (registry.Descriptor("t_x", "share", "x"),), 1))
    with pytest.raises(registry.DescriptorError, match="built in"):
        registry.unregister("raster")
    with pytest.raises(registry.DescriptorError, match="lower-case identifier"):
        registry.Descriptor("T x", "share", "x")
    with pytest.raises(registry.DescriptorError, match="unit"):
        registry.Descriptor("t_x", "pts", "x")


def test_a_family_that_computes_other_names_or_non_finite_values_is_named(toy):
    with pytest.raises(registry.DescriptorError, match="'toy' returned"):
        registry.checked(TOY, {"t_roof_m": 1.0})
    with pytest.raises(registry.DescriptorError, match="t_post_top_m = nan is not finite"):
        registry.checked(TOY, {"t_roof_m": 1.0, "t_post_top_m": float("nan")})
    assert registry.checked(TOY, {"t_roof_m": np.float32(2), "t_post_top_m": 1}) == {"t_roof_m": 2.0,
                                                                                     "t_post_top_m": 1.0}


def test_unknown_names_are_refused_until_registered():
    with pytest.raises(PipelineError, match="unknown surface descriptors"):
        PipelineSettings(surface=SurfaceSettings(), surface_descriptors=("t_roof_m",))
    registry.register(TOY)
    try:
        PipelineSettings(surface=SurfaceSettings(), surface_descriptors=("t_roof_m",))
    finally:
        registry.unregister("toy")
