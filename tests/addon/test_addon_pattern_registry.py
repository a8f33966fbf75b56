"""A new damage pattern is one function and one registration line: a toy pattern registered
with `register_pattern` is in the catalogue, applied by name, drawn for its grade, and gone
again after `unregister_pattern`."""
import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
import bmesh  # noqa: E402

from addon import ems98  # noqa: E402
from addon.geometry import mesh as gm  # noqa: E402
from addon.geometry import patterns as gp  # noqa: E402
from addon.geometry.shell import ShellSpec, build_shell, rect_footprint  # noqa: E402

BID = 7
TOY = ems98.Pattern("roof_dent", "Roof dent", (ems98.MASONRY,), (3,),
                    {"drop": ems98.Param(0.5, 1.5, "float", "m", "how far the roof's top sinks")})


def roof_dent(bm, spec, rng, building_id, drop):
    """The toy: every vertex at the roof's top sinks by `drop` (a flat roof: the whole roof)."""
    top = max(v.co.z for v in bm.verts)
    moved = [v for v in bm.verts if v.co.z >= top - 1e-6]
    for v in moved:
        v.co.z -= drop
    return {"drop": drop, "vertices": len(moved)}


@pytest.fixture
def toy():
    names, primary = ems98.PATTERN_NAMES, {k: list(v) for k, v in ems98.PRIMARY.items()}
    gp.register_pattern(TOY, roof_dent, primary=1.0)
    try:
        yield TOY
    finally:
        gp.unregister_pattern(TOY.name)
    assert ems98.PATTERN_NAMES == names and ems98.PRIMARY == primary and TOY.name not in gp.FUNCTIONS


def flat_masonry():
    return ShellSpec(footprint=rect_footprint(10, 8), storeys=2, storey_height=3.0, roof="flat", material="masonry")


def test_a_registered_pattern_is_in_the_catalogue_and_applied_by_name(toy):
    assert toy.name in ems98.PATTERN_NAMES and ems98.default_params(toy.name) == {"drop": 1.0}
    drawn = ems98.sample_params(toy.name, np.random.default_rng(0))
    assert 0.5 <= drawn["drop"] <= 1.5
    spec = flat_masonry()
    bm = bmesh.new()
    build_shell(bm, spec, BID)
    top = gm.arrays(bm)[0][:, 2].max()
    record = gp.apply_pattern(bm, spec, toy.name, None, np.random.default_rng(0), BID)
    after = gm.arrays(bm)[0][:, 2].max()
    bm.free()
    assert record["name"] == toy.name and record["params"]["drop"] == 1.0 and record["params"]["vertices"] > 0
    assert after == pytest.approx(top - 1.0, abs=1e-5)  # the flat roof sank by the default drop, exactly


def test_a_registered_pattern_is_drawn_for_its_grade_and_material(toy):
    entries = dict(ems98.candidates(3, ems98.MASONRY, {"storeys>=2"}))
    assert entries[toy.name] == 1.0
    assert toy.name not in dict(ems98.candidates(3, ems98.RC, {"storeys>=2"}))
    drawn = set()
    for seed in range(60):
        drawn |= {p for p, _ in ems98.choose_patterns(3, ems98.MASONRY, {"storeys>=2"}, np.random.default_rng(seed))}
    assert toy.name in drawn


def test_a_pattern_is_refused_twice_or_with_a_function_that_lacks_its_parameters(toy):
    with pytest.raises(ValueError, match="already in the catalogue"):
        gp.register_pattern(TOY, roof_dent)
    other = ems98.Pattern("roof_dent_b", "b", (ems98.MASONRY,), (3,), {"depth": ems98.Param(1, 2)})
    with pytest.raises(ValueError, match=r"takes no parameter\(s\) \['depth'\]"):
        gp.register_pattern(other, roof_dent)
    assert "roof_dent_b" not in ems98.PATTERN_NAMES
