"""Probabilities calibrated on damage in real points: one temperature fitted out of fold.

The shipped classifier's probabilities are calibrated on simulated rows (its sigmoid maps are
fitted on folds of whole simulated cities). Real archives differ from every simulator in ways
no training row shows, and a model sure of itself on simulated cities is over-sure on them: a
building reported "no damage" at p = 0.9 that is heavily damaged is the worst answer it gives.

The real-point rows (`quakescan.learning.realset`: damage injected into real archives, and their
no-change rescans) measure that. Every real pair is predicted by the chosen classifier fitted
without any of that pair's rows (out of fold: it never saw those buildings, nor their repeats),
on every row of the pair, also those whose damage the acquisition did not show (the rows the
training leaves out, which a user meets all the same). One temperature T then scales the
log-probabilities, p_k ∝ p_k^(1/T), chosen to minimise the log-loss of those predictions
(Guo et al. 2017, "On calibration of modern neural networks": one parameter, so a few hundred
buildings fit it without overfitting). T > 1 softens over-sure answers, T < 1 sharpens
under-sure ones; the argmax, and so every grade, is unchanged.
"""
from __future__ import annotations

import numpy as np

from .reliability import calibration_error, fit_temperature, log_loss, temper


def out_of_fold_real(table, full, config: dict, real_pairs, *, seed: int = 0, fit=None):
    """Out-of-fold probabilities of every real row (once per building, not per repeat).

    `table`: the rows the model is fitted on (real rows repeated); `full`: every row, also
    those left out of training; `real_pairs`: the real pairs' names in `table.pairs`. Each real
    pair is predicted by `config`'s classifier fitted on `table` without that pair's rows.
    Returns (proba (n, k), truth (n,) grades, classes (k,), pair names (n,))."""
    return _out_of_fold(table, full, config, real_pairs, seed=seed, fit=fit)[:4]


def _out_of_fold(table, full, config: dict, real_pairs, *, seed: int = 0, fit=None):
    """`out_of_fold_real` and the rows of `full` it predicted."""
    from .model_selection import cv_groups
    from .model import fit_classifier

    fit = fit or fit_classifier
    fit_args = {k: v for k, v in config.items() if k not in ("name", "rule")}
    probas, truths, where, rows = [], [], [], []
    classes = None
    for name in real_pairs:
        k_train = table.pairs.index(name)
        k_full = full.pairs.index(name)
        test = np.flatnonzero(full.pair == k_full)
        if not len(test):
            continue
        _, first = np.unique(full.building_id[test], return_index=True)
        test = test[np.sort(first)]  # one row per building: the repeats are copies
        train = table.subset(table.pair != k_train)
        groups = cv_groups(train) if fit_args.get("calibration") else None
        est = fit(train.x, train.y, seed=seed, groups=groups, **fit_args)
        if classes is None:
            classes = np.asarray(est.classes_)
        elif not np.array_equal(classes, est.classes_):
            raise ValueError(f"the fit without real pair {name} knows grades {list(est.classes_)}, not {list(classes)}")
        probas.append(est.predict_proba(full.x[test]))
        truths.append(full.y[test])
        where += [name] * len(test)
        rows.append(test)
    if not probas:
        raise ValueError("no real rows to calibrate on")
    return np.vstack(probas), np.concatenate(truths), classes, np.array(where), np.concatenate(rows)


def real_calibration(table, full, config: dict, real_pairs, *, seed: int = 0, fit=None) -> dict:
    """{"temperature", "rows", "pairs", log-loss and ECE before and after} of the real rows'
    out-of-fold probabilities (`out_of_fold_real`)."""
    proba, truth, classes, _, rows = _out_of_fold(table, full, config, real_pairs, seed=seed, fit=fit)
    known = np.isin(truth, classes)
    proba, truth, rows = proba[known], truth[known], rows[known]
    index = np.searchsorted(classes, truth)
    then = counting_unseen(full, rows, classes)
    counted = then is not None
    then = then or (lambda p: p)
    t = fit_temperature(proba, index, then)
    said = proba.argmax(axis=1)  # the grade given: the model's, whatever is counted (`predict_rows`)
    after, proba = then(temper(proba, t)), then(proba)

    def ece(p):
        return calibration_error(p[np.arange(len(p)), said], said == index)

    return {"temperature": round(t, 4), "rows": int(len(truth)), "pairs": list(real_pairs),
            "unseen_damage": counted,
            "log_loss_before": round(log_loss(proba, index), 4), "log_loss_after": round(log_loss(after, index), 4),
            "ece_before": round(ece(proba), 4), "ece_after": round(ece(after), 4),
            "how": "one temperature on the out-of-fold probabilities of every real-point row "
                   "(quakescan.learning.real_calibration)"
                   + (", counting the damage each row's data could not show (quakescan.learning.unseen_damage), "
                      "as classify reports them" if counted else "")}


def counting_unseen(full, rows: np.ndarray, classes):
    """p -> p with the unseen damage of `full`'s `rows` counted (`with_unseen_damage`), as
    `predict_rows` reports them, so the temperature is fitted to what the user reads; None
    where the table records no unseen shares (the model's own probabilities are fitted)."""
    from .realset import UNSEEN_GRADES
    from .unseen_damage import with_unseen_damage

    if getattr(full, "unseen", None) is None:
        return None
    q = np.nan_to_num(np.asarray(full.unseen)[rows], nan=0.0)
    shares = [dict(zip(UNSEEN_GRADES, map(float, r))) for r in q]
    return lambda p: with_unseen_damage(p, classes, shares)
