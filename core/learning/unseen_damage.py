"""Probabilities that count the damage a building's data could not have shown.

The classifier is trained on damage its data showed (`quakescan.learning.default_model.
visible_damage`: damaged rows where no change was seen are left out), so its probabilities
answer "which grade, given that whatever damage there is shows in these points". Where a
building's data cannot show some forms of a grade at all — wall holes and blown-out infill
under an airborne laser that puts a return on a wall every few square metres, roof openings
below the smallest opening its density resolves — that question is not the user's. A building
with such damage looks exactly like an undamaged one, and "no damage, p = 0.9" for it is the
confident wrong answer the responder cannot afford.

Bayes' rule with the share of each grade's forms its data could not show gives the user's
question. Let q_g be the share of grade g's catalogue forms this building's data cannot show
(`unseen_shares`); such damage gives the descriptors of no damage, L_0(x). The model is fitted
on class-balanced rows from which unseen damage was left out, so its probability P_m(g | x)
is proportional to the likelihood of x under the forms of g that show (weighted by the share
of them that showed in its own training rows, which the class weights make up for) and
P_m(0 | x) to L_0(x). With the equal priors the model's probabilities carry (π_g / π_0 = 1),
the posterior that also counts the unseen forms is

    P(0 | x) ∝ P_m(0 | x)
    P(g | x) ∝ P_m(g | x) + q_g (π_g / π_0) P_m(0 | x),   g = 3, 4, 5.

With every q_g = 0 (a drone flight whose walls and roof resolve every form) the model's
probabilities are unchanged. With walls unresolved, "no damage" under a model sure of it
gets 1 / (1 + Σ q_g): an airborne pair says "no damage seen" at about 0.62, not 0.9.

The grade stays the model's (`quakescan.learning.classification.predict_rows`): it says what
the data show, and the probabilities what that answer is worth given what they cannot show.
Unseen damage could only ever be guessed from the prior, and a guess is not a grade: taken as
one it would call the undamaged buildings of every airborne archive damaged.

q_g comes from closed-form sampling (`quakescan.change.detectability`), not from fitting: the
catalogue's forms of grade g confined to walls (`detectability.WALLS_ONLY_SHARE`) are unseen
where `walls_resolved` is False, its roof forms where the roof resolves no grade up to g
(`detectable_grade` None or above g). Unknown detectability (None) counts as seen: older rows
and models without surface descriptors keep their probabilities.
"""
from __future__ import annotations

import numpy as np

from ..change.detectability import WALLS_ONLY_SHARE, Detectability

# the model's classes are weighted inversely to their frequency in training (`fit_classifier`,
# class_weight "balanced"): its probabilities carry equal priors, π_g / π_0 = 1
PRIOR_RATIO = 1.0


def unseen_shares(seen: Detectability | None, grades) -> dict[int, float]:
    """{grade: q_g}, the share of each damaged grade's catalogue forms this building's data
    could not show (0 for grade 0 and where detectability is unknown)."""
    out = {}
    for g in (int(v) for v in grades):
        if g <= 0 or seen is None:
            out[g] = 0.0
            continue
        walls = float(WALLS_ONLY_SHARE.get(g, 0.0))
        roof_unseen = seen.detectable_grade is None or int(seen.detectable_grade) > g
        q = (1.0 - walls if roof_unseen else 0.0) + (walls if seen.walls_resolved is False else 0.0)
        out[g] = min(max(q, 0.0), 1.0)
    return out


def with_unseen_damage(proba, classes, shares: list[dict]) -> np.ndarray:
    """(n, k) probabilities over `classes` that count unseen damage: row i of `proba` mixed
    with `shares[i]` ({grade: q_g}, `unseen_shares`) as the module says. A model without
    grade 0 among its classes has nothing to mix: `proba` is returned as it is."""
    p = np.asarray(proba, dtype=np.float64)
    classes = [int(c) for c in classes]
    if p.ndim != 2 or p.shape[1] != len(classes):
        raise ValueError(f"probabilities of shape {p.shape} do not match {len(classes)} classes")
    if len(shares) != len(p):
        raise ValueError(f"{len(shares)} rows of unseen shares for {len(p)} rows of probabilities")
    if 0 not in classes or not len(p):
        return p
    zero = classes.index(0)
    q = np.array([[float(s.get(c, 0.0)) if c != 0 else 0.0 for c in classes] for s in shares])
    if np.any(~np.isfinite(q)) or np.any((q < 0) | (q > 1)):
        raise ValueError("unseen shares must lie in [0, 1]")
    mixed = p + q * PRIOR_RATIO * p[:, [zero]]
    total = mixed.sum(axis=1, keepdims=True)
    return np.divide(mixed, total, out=np.array(p, copy=True), where=total > 0)


__all__ = ["PRIOR_RATIO", "unseen_shares", "with_unseen_damage"]
