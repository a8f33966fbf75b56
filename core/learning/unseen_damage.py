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

A responder who expects another mix of grades (most buildings of a city stand after an
earthquake of intensity VIII; EMS-98's own tables give "few", "many", "most" per grade and
vulnerability class) gives it as a prior: every probability is reweighted by π_g
(`with_prior`), the unseen share included, as the formula says for π_g / π_0 other than 1.

The grade stays the model's (`quakescan.learning.prediction.predict_rows`): it says what
the data show, and the probabilities what that answer is worth given what they cannot show.
Unseen damage could only ever be guessed from the prior, and a guess is not a grade: taken as
one it would call the undamaged buildings of every airborne archive damaged.

q_g comes from closed-form sampling (`quakescan.change.detectability`), not from fitting: the
catalogue's forms of grade g confined to walls (`detectability.WALLS_ONLY_SHARE`) are unseen
unless `walls_resolved` is True (False: too sparse; None: not measured, a building too low
for a facade band), its roof forms where the roof resolves no grade up to g (`detectable_grade`
None or above g). A row without any detectability (a model without surface descriptors)
counts as seen: its probabilities are the model's.
"""
from __future__ import annotations

import numpy as np

from ..change.detectability import WALLS_ONLY_SHARE, Detectability
from ..errors import QuakeScanError

class PriorError(QuakeScanError, ValueError):
    """A prior over the grades that cannot be used."""


def unseen_shares(seen: Detectability | None, grades) -> dict[int, float]:
    """{grade: q_g}, the share of each damaged grade's catalogue forms this building's data
    could not show (0 for grade 0, and for every grade where `seen` is None)."""
    out = {}
    for g in (int(v) for v in grades):
        if g <= 0 or seen is None:
            out[g] = 0.0
            continue
        walls = float(WALLS_ONLY_SHARE.get(g, 0.0))
        roof_unseen = seen.detectable_grade is None or int(seen.detectable_grade) > g
        # walls count as seen only where they resolve heavy damage: unresolved, or not measured
        # at all (too low for a facade band: `walls_resolved` None), their forms are unseen
        q = (1.0 - walls if roof_unseen else 0.0) + (0.0 if seen.walls_resolved is True else walls)
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
    # π_g / π_0 = 1: the model's classes are weighted inversely to their frequency in training
    # (`fit_classifier`, class_weight "balanced"); another prior is `with_prior`'s
    mixed = p + q * p[:, [zero]]
    total = mixed.sum(axis=1, keepdims=True)
    return np.divide(mixed, total, out=np.array(p, copy=True), where=total > 0)


def with_prior(proba, classes, prior: dict | None) -> np.ndarray:
    """(n, k) probabilities for another prior over the grades than the equal one the model's
    carry: p_g ∝ π_g p_g (Saerens, Latinne & Decaestecker 2002, "Adjusting the outputs of a
    classifier to new a priori probabilities"). `prior` {grade: share}, any positive scale,
    one share for every class; None: the equal prior, `proba` as it is. With unseen damage
    counted first (`with_unseen_damage`) this is the module's posterior for prior π."""
    p = np.asarray(proba, dtype=np.float64)
    if prior is None or not len(p):
        return p
    weights = prior_weights(prior, classes)
    out = p * weights[None, :]
    total = out.sum(axis=1, keepdims=True)
    return np.divide(out, total, out=np.array(p, copy=True), where=total > 0)


def prior_weights(prior: dict, classes) -> np.ndarray:
    """The prior's shares for `classes`, in their order, summing to 1."""
    classes = [int(c) for c in classes]
    missing = [c for c in classes if c not in prior]
    if missing:
        raise PriorError(f"the prior gives no share for grade(s) {missing} (it needs one for each of {classes})")
    extra = sorted(set(int(g) for g in prior) - set(classes))
    if extra:
        raise PriorError(f"the prior gives shares for grade(s) {extra} the model does not know (its grades: {classes})")
    w = np.array([float(prior[c]) for c in classes])
    if not np.all(np.isfinite(w)) or np.any(w <= 0):
        raise PriorError(f"every share of the prior must be a finite number > 0, got {dict(zip(classes, w.tolist()))}")
    return w / w.sum()


def parse_prior(text: str) -> dict[int, float]:
    """"0:70,3:10,4:10,5:10" → {0: 70.0, 3: 10.0, 4: 10.0, 5: 10.0} (shares of any scale)."""
    out: dict[int, float] = {}
    for part in str(text).split(","):
        grade, sep, share = part.partition(":")
        try:
            if not sep:
                raise ValueError
            g, v = int(grade.strip()), float(share.strip())
        except ValueError:
            raise PriorError(f"prior {text!r}: {part.strip()!r} is not GRADE:SHARE (e.g. 0:70,3:10,4:10,5:10)") from None
        if g in out:
            raise PriorError(f"prior {text!r}: grade {g} is given twice")
        if not (np.isfinite(v) and v > 0):
            raise PriorError(f"prior {text!r}: the share of grade {g} must be a finite number > 0, got {share.strip()!r}")
        out[g] = v
    return out


__all__ = ["PriorError", "parse_prior", "prior_weights", "unseen_shares", "with_prior",
           "with_unseen_damage"]
