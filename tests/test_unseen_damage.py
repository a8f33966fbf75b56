"""Probabilities that count the damage a building's data could not show (closed forms)."""
import numpy as np
import pytest

from quakescan.change import detectability as D
from quakescan.change.pipeline import BuildingRow
from quakescan.learning.unseen_damage import unseen_shares, with_unseen_damage

CLASSES = [0, 3, 4, 5]
W3, W4 = D.WALLS_ONLY_SHARE[3], D.WALLS_ONLY_SHARE[4]


def _seen(grade, walls):
    return D.Detectability(1.0, 0.3, grade, 5.0 if walls is not None else None, walls)


def test_walls_only_shares_are_the_add_ons_pattern_weights():
    from addon import ems98  # pure Python: no bpy needed

    for g in (3, 4, 5):
        shares = []
        for material in (ems98.MASONRY, ems98.RC):
            forms = ems98.PRIMARY[(g, material)]
            total = sum(w for _, w in forms)
            shares.append(sum(w for name, w in forms if name in D.WALLS_ONLY_PATTERNS) / total)
        assert D.WALLS_ONLY_SHARE[g] == pytest.approx(np.mean(shares), abs=1e-12), g
    known = {name for forms in ems98.PRIMARY.values() for name, _ in forms}
    assert set(D.WALLS_ONLY_PATTERNS) <= known


def test_shares_from_what_the_roof_and_the_walls_resolve():
    assert unseen_shares(_seen(3, True), CLASSES) == {0: 0.0, 3: 0.0, 4: 0.0, 5: 0.0}
    assert unseen_shares(_seen(3, False), CLASSES) == {0: 0.0, 3: W3, 4: W4, 5: 0.0}
    # the roof resolves grade 4 at best: heavy roof forms unseen too; walls unseen: nothing of 3 shows
    assert unseen_shares(_seen(4, True), CLASSES) == pytest.approx({0: 0.0, 3: 1 - W3, 4: 0.0, 5: 0.0})
    assert unseen_shares(_seen(4, False), CLASSES) == pytest.approx({0: 0.0, 3: 1.0, 4: W4, 5: 0.0})
    assert unseen_shares(_seen(None, False), CLASSES) == pytest.approx({0: 0.0, 3: 1.0, 4: 1.0, 5: 1.0})
    # walls not measured (a building too low for a facade band) are not seen walls
    assert unseen_shares(_seen(3, None), CLASSES) == {0: 0.0, 3: W3, 4: W4, 5: 0.0}
    # no detectability at all (a model without surface descriptors): the model's probabilities
    assert unseen_shares(None, CLASSES) == {0: 0.0, 3: 0.0, 4: 0.0, 5: 0.0}


def test_nothing_unseen_leaves_the_model_s_probabilities():
    p = np.random.default_rng(0).dirichlet(np.ones(4), 50)
    out = with_unseen_damage(p, CLASSES, [unseen_shares(_seen(3, True), CLASSES)] * 50)
    np.testing.assert_allclose(out, p, rtol=1e-12)


def test_no_damage_seen_under_blind_walls_is_bounded_in_closed_form():
    q = unseen_shares(_seen(3, False), CLASSES)
    (p,) = with_unseen_damage(np.array([[1.0, 0.0, 0.0, 0.0]]), CLASSES, [q])
    # P(0) = 1 / (1 + q3 + q4): about 0.62, below the 0.8 of a confident answer
    assert p[0] == pytest.approx(1 / (1 + W3 + W4)) and p[0] < 0.8
    assert p[1:] == pytest.approx([W3 / (1 + W3 + W4), W4 / (1 + W3 + W4), 0.0])
    # nothing resolvable at all: the prior, every grade alike (ties go to "no damage seen")
    (p,) = with_unseen_damage(np.array([[1.0, 0.0, 0.0, 0.0]]), CLASSES, [unseen_shares(_seen(None, False), CLASSES)])
    assert p == pytest.approx([0.25] * 4) and int(np.argmax(p)) == 0


def test_unseen_damage_only_takes_confidence_from_no_damage():
    rng = np.random.default_rng(1)
    p = rng.dirichlet(np.full(4, 0.5), 2000)
    shares = [unseen_shares(_seen(g, w), CLASSES) for g, w in
              zip(rng.choice([3, 4, 5], 2000), rng.choice([True, False], 2000))]
    out = with_unseen_damage(p, CLASSES, shares)
    assert np.allclose(out.sum(axis=1), 1.0) and (out >= 0).all()
    # every row is divided by 1 + sum_g q_g P(0) >= 1, and grade g gains q_g P(0) before it
    z = 1 + np.array([sum(s[g] for g in (3, 4, 5)) for s in shares]) * p[:, 0]
    np.testing.assert_allclose(out[:, 0], p[:, 0] / z, rtol=1e-12)
    assert (out[:, 0] <= p[:, 0] + 1e-15).all()
    q3 = np.array([s[3] for s in shares])
    np.testing.assert_allclose(out[:, 1], (p[:, 1] + q3 * p[:, 0]) / z, rtol=1e-12)


def test_bad_shapes_and_shares_are_named():
    with pytest.raises(ValueError, match="4 classes"):
        with_unseen_damage(np.ones((2, 3)) / 3, CLASSES, [{}, {}])
    with pytest.raises(ValueError, match="1 rows of unseen shares for 2"):
        with_unseen_damage(np.ones((2, 4)) / 4, CLASSES, [{}])
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        with_unseen_damage(np.ones((1, 4)) / 4, CLASSES, [{3: 1.5}])
    p = np.ones((1, 3)) / 3  # a model without grade 0: nothing to mix
    np.testing.assert_array_equal(with_unseen_damage(p, [3, 4, 5], [{3: 0.5}]), p)


class _Model:  # a model sure of "no damage" for every building it is asked about
    no_change_rule = False
    classes = [0, 3, 4, 5]
    feature_names = ["share_changed"]

    @staticmethod
    def predict_proba_matrix(x):
        return np.tile([0.97, 0.01, 0.01, 0.01], (len(x), 1))

    @staticmethod
    def confidence(proba):
        return np.asarray(proba).max(axis=1)


def _row(bid, wall_density):
    quality = {"density_pre": 4.0, "density_post": 4.0, "area_m2": 200.0, "lowering_lod_m": 0.3,
               "wall_density_pre": wall_density, "wall_density_post": wall_density, "facade_m2": 300.0}
    return BuildingRow(bid, 800, 800, True, descriptors={"share_changed": 0.0}, quality=quality)


@pytest.mark.parametrize("rule", [False, True])
def test_predict_rows_counts_unseen_damage_by_default(rule):
    from quakescan.learning.prediction import predict_rows

    # an airborne laser's walls (0.3 returns per m² of facade) beside a drone's (20)
    rows = [_row(1, 0.3), _row(2, 20.0)]
    blind, seeing = predict_rows(rows, _Model(), rule=rule)
    assert blind.walls_resolved is False and seeing.walls_resolved is True
    assert blind.grade == seeing.grade == 0  # the grade is what the data show
    sure = 1.0 if rule else 0.97
    assert seeing.confidence == pytest.approx(sure)
    assert blind.confidence == pytest.approx(sure / (1 + (W3 + W4) * sure)) and blind.confidence < 0.8
    assert blind.probabilities[3] == pytest.approx(((1 - sure) / 3 + W3 * sure) / (1 + (W3 + W4) * sure))
    assert sum(blind.probabilities.values()) == pytest.approx(1.0)
    own = predict_rows(rows, _Model(), rule=rule, unseen_damage=False)
    assert [r.confidence for r in own] == pytest.approx([sure, sure])


def test_a_prior_reweights_every_probability_in_closed_form():
    from quakescan.learning.unseen_damage import with_prior

    p = np.array([[0.5, 0.2, 0.2, 0.1]])
    (out,) = with_prior(p, CLASSES, {0: 70, 3: 10, 4: 10, 5: 10})
    w = np.array([0.7, 0.1, 0.1, 0.1]) * p[0]
    assert out == pytest.approx(w / w.sum())
    np.testing.assert_array_equal(with_prior(p, CLASSES, None), p)
    # equal shares of any scale: the model's own prior, nothing changes
    np.testing.assert_allclose(with_prior(p, CLASSES, {0: 3, 3: 3, 4: 3, 5: 3}), p)
    # with unseen damage counted first: the posterior pi_g (p_g + q_g p_0), pi_0 p_0
    q = unseen_shares(_seen(3, False), CLASSES)
    (both,) = with_prior(with_unseen_damage(p, CLASSES, [q]), CLASSES, {0: 70, 3: 10, 4: 10, 5: 10})
    raw = np.array([0.7 * 0.5, 0.1 * (0.2 + W3 * 0.5), 0.1 * (0.2 + W4 * 0.5), 0.1 * 0.1])
    assert both == pytest.approx(raw / raw.sum())


@pytest.mark.parametrize("text, message", [
    ("0:70,3:10,4:10", "no share for grade\\(s\\) \\[5\\]"),
    ("0:70,3:10,4:10,5:10,2:5", "grade\\(s\\) \\[2\\] the model does not know"),
    ("0:70,3:0,4:10,5:10", "grade 3 must be a finite number > 0"),
    ("0:70,3:nan,4:10,5:10", "grade 3 must be a finite number > 0"),
    ("0:70;3:10", "is not GRADE:SHARE"),
    ("0:70,0:10", "grade 0 is given twice"),
])
def test_a_prior_that_cannot_be_used_is_named(text, message):
    from quakescan.learning.unseen_damage import PriorError, parse_prior, prior_weights

    with pytest.raises(PriorError, match=message):
        prior_weights(parse_prior(text), CLASSES)


def test_predict_rows_takes_a_prior_and_keeps_the_model_s_grades():
    from quakescan.learning.prediction import predict_rows
    from quakescan.learning.unseen_damage import PriorError

    rows = [_row(1, 0.3), _row(2, 20.0)]
    blind, seeing = predict_rows(rows, _Model(), prior={0: 80, 3: 10, 4: 5, 5: 5})
    assert blind.grade == seeing.grade == 0
    z = 0.8 * 0.97 + 0.1 * (0.01 + W3 * 0.97) + 0.05 * (0.01 + W4 * 0.97) + 0.05 * 0.01
    assert blind.confidence == pytest.approx(0.8 * 0.97 / z)
    assert seeing.confidence == pytest.approx(0.8 * 0.97 / (0.8 * 0.97 + 0.2 * 0.01))
    with pytest.raises(PriorError, match="grade\\(s\\) \\[5\\]"):
        predict_rows(rows, _Model(), prior={0: 80, 3: 10, 4: 10})


def test_classify_refuses_a_prior_before_reading_the_clouds(tmp_path):
    from quakescan.learning.unseen_damage import PriorError
    from quakescan.assessment.run import classify

    pre, post = tmp_path / "pre.las", tmp_path / "post.las"
    pre.write_bytes(b"not read"), post.write_bytes(b"not read")
    with pytest.raises(PriorError, match="grade\\(s\\) \\[9\\]"):
        classify(pre, post, tmp_path / "out", prior={0: 1, 3: 1, 4: 1, 5: 1, 9: 1})
    assert not (tmp_path / "out").exists()
