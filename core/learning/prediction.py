"""A model applied to a pair's descriptor rows: one grade, its probabilities and its
confidence per building.

The paper's rule decides a building without changed points ("no damage") without asking
the model, unless the model was trained on every row; the probabilities count the damage a
building's data could not have shown (`quakescan.learning.unseen_damage`). `model_settings`
gives the pipeline settings a model's rows must be described with.
"""
from __future__ import annotations

import logging

import numpy as np

from ..change.descriptors import DESCRIPTOR_VERSION
from ..change.detectability import of_building
from ..change.pipeline import descriptor_matrix
from ..change.settings import PipelineSettings, settings_for_descriptors
from ..errors import QuakeScanError
from ..results.building_result import BuildingResult
from .model import DamageModel, ModelError, changed_share
from .unseen_damage import prior_weights, unseen_shares, with_prior, with_unseen_damage

log = logging.getLogger(__name__)


def model_settings(model: DamageModel, source: str = "model") -> PipelineSettings:
    """The pipeline settings the model was trained with; refuses a model for other features."""
    stored = model.split if isinstance(model.split, dict) else {}
    try:
        settings = settings_for_descriptors(model.feature_names, model.radius_m, stored.get("split"), stored,
                                            min_points_pre=int(stored.get("min_points_pre", 50)),
                                            min_points_post=int(stored.get("min_points_post", 10)),
                                            tile_m=float(stored.get("tile_m", 150.0)),
                                            core_point_step=int(stored.get("core_point_step", 1)))
    except (QuakeScanError, TypeError, ValueError, KeyError, AttributeError) as e:  # settings out of range or of the wrong type
        raise ModelError(f"{source}: the model's settings are invalid ({e}): an edited or foreign file; "
                         "retrain it with `quakescan train`") from None
    version = (model.provenance or {}).get("descriptor_version")
    if settings.surface is not None and version is not None:
        if version != DESCRIPTOR_VERSION:
            log.warning("%s: trained on surface descriptors of version %s, this QuakeScan computes version %s: "
                        "retrain it (blender_scripts/make_default_model.py) for results it was measured on",
                        source, version, DESCRIPTOR_VERSION)
    if settings.descriptor_names() != list(model.feature_names):
        raise ModelError(f"{source}: the model's descriptor columns are not in the order this QuakeScan "
                         f"computes them ({model.feature_names[:4]}...): retrain it with `quakescan train`")
    return settings


def predict_rows(rows, model: DamageModel, rule: bool | None = None, unseen_damage: bool = True,
                 prior: dict | None = None) -> list:
    """BuildingResults: not assessable stays so; no changed points → no damage by rule;
    else the model. `confidence`: the model's probability of the grade it gives, 1.0 for a
    grade given by rule, None when not assessable.

    rule: decide buildings without changed points without asking the model (the paper's
    rule); None: as the model was trained (`model.no_change_rule`; True for every model
    file written before the switch existed). Every assessed building carries what its data
    could resolve (`quakescan.change.detectability.of_building`), where its row says.

    unseen_damage: the probabilities, and so the confidence of the grade, count the damage the
    building's data could not have shown (`quakescan.learning.unseen_damage`): "no damage"
    under an airborne laser that resolves no wall holes is not said with a drone's confidence.
    The grade is the model's either way (what the data show). False: the model's own
    probabilities (damage assumed to show). `prior` {grade: share}: the mix of grades the user
    expects, for the equal one the model's probabilities carry (`unseen_damage.with_prior`);
    the grades stay the model's."""
    rule = model.no_change_rule if rule is None else bool(rule)
    classes = model.classes
    grades = sorted(set(classes) | ({0} if rule else set()))
    if prior is not None:
        prior_weights(prior, grades)  # a prior that cannot be used is refused before any row
    out, ask = [], []
    for r in rows:
        if not r.assessable:
            out.append(BuildingResult(r.building_id, r.n_pre, r.n_post, False, r.reason))
            continue
        share = changed_share(r.descriptors)  # the rule's column, as training reads it
        res = BuildingResult(r.building_id, r.n_pre, r.n_post, True, "", share_changed=share)
        seen = of_building(r.quality)
        if seen is not None:
            res.detectable_grade, res.min_opening_m2, res.min_lowering_m = (seen.detectable_grade,
                                                                            seen.min_opening_m2, seen.min_lowering_m)
            res.walls_resolved, res.min_wall_opening_m2 = seen.walls_resolved, seen.min_wall_opening_m2
        if rule and share == 0.0:
            p = np.array([[float(c == 0) for c in grades]])
            if unseen_damage:
                p = with_unseen_damage(p, grades, [unseen_shares(seen, grades)])
            p = with_prior(p, grades, prior)
            res.grade = 0
            res.probabilities = {c: float(v) for c, v in zip(grades, p[0])}
            res.decided_by = "no change"
            res.confidence = res.probabilities[0]
        else:
            ask.append((res, r, seen))
        out.append(res)
    if ask:
        proba = model.predict_proba_matrix(descriptor_matrix([r for _, r, _ in ask], model.feature_names))
        # the grade is what the data show (the model's own answer); its probabilities, and so
        # its confidence, count what they could not show
        said = np.argmax(proba, axis=1)
        if unseen_damage:
            proba = with_unseen_damage(proba, classes, [unseen_shares(seen, classes) for _, _, seen in ask])
        proba = with_prior(proba, classes, prior)
        for (res, _, _), p, k in zip(ask, proba, said):
            res.probabilities = {c: 0.0 for c in grades}
            res.probabilities.update({c: float(v) for c, v in zip(classes, p)})
            res.grade = int(classes[int(k)])
            res.decided_by = "model"
            res.confidence = float(p[k])
    return out
