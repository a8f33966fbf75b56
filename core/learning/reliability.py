"""Temperature scaling and the calibration error of probabilities: the numbers every model,
calibration and benchmark shares (`quakescan.learning.real_calibration` fits the temperature;
`quakescan.learning.model` applies it).

One temperature T scales the log-probabilities, p_k ∝ p_k^(1/T) (Guo et al. 2017, "On
calibration of modern neural networks"); T > 1 softens over-sure answers, T < 1 sharpens
under-sure ones; the argmax is unchanged.
"""
from __future__ import annotations

import math

import numpy as np

# The temperature is sought in [1/MAX_TEMPERATURE, MAX_TEMPERATURE] (log-uniform): beyond it
# the data would say the classifier knows nothing (or everything) on real points.
MAX_TEMPERATURE = 20.0
ECE_BINS = 10
PROBABILITY_FLOOR = 1e-12


def temper(proba: np.ndarray, temperature: float) -> np.ndarray:
    """Probabilities (n, k) scaled by `temperature`: p^(1/T), renormalised per row."""
    p = np.asarray(proba, dtype=np.float64)
    if temperature == 1.0 or p.size == 0:
        return p
    check_temperature(temperature)
    logp = np.log(np.clip(p, PROBABILITY_FLOOR, 1.0)) / float(temperature)
    logp -= logp.max(axis=1, keepdims=True)
    q = np.exp(logp)
    return q / q.sum(axis=1, keepdims=True)


def check_temperature(t) -> float:
    if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t) \
            or not (1.0 / MAX_TEMPERATURE <= t <= MAX_TEMPERATURE):
        raise ValueError(f"temperature must be a number in [{1 / MAX_TEMPERATURE:g}, {MAX_TEMPERATURE:g}], got {t!r}")
    return float(t)


def log_loss(proba: np.ndarray, truth_index: np.ndarray) -> float:
    p = np.asarray(proba)[np.arange(len(truth_index)), truth_index]
    return float(-np.mean(np.log(np.clip(p, PROBABILITY_FLOOR, 1.0))))


def expected_calibration_error(proba: np.ndarray, truth_index: np.ndarray, bins: int = ECE_BINS) -> float:
    """Top-label ECE: the row-weighted mean gap between confidence and accuracy over `bins`
    equal-width confidence bins."""
    p = np.asarray(proba)
    if len(p) == 0:
        return float("nan")
    return calibration_error(p.max(axis=1), p.argmax(axis=1) == np.asarray(truth_index), bins)


def calibration_error(confidence: np.ndarray, correct: np.ndarray, bins: int = ECE_BINS) -> float:
    """ECE of answers given at `confidence` ((n,) in [0, 1]) that were `correct` ((n,) bool)."""
    conf, correct = np.asarray(confidence, dtype=np.float64), np.asarray(correct, dtype=np.float64)
    if len(conf) == 0:
        return float("nan")
    k = np.minimum((conf * bins).astype(int), bins - 1)
    return float(sum((k == b).mean() * abs(correct[k == b].mean() - conf[k == b].mean())
                     for b in range(bins) if (k == b).any()))


def fit_temperature(proba: np.ndarray, truth_index: np.ndarray, then=None) -> float:
    """The temperature minimising the log-loss of `proba` (n, k) against the true classes'
    column indices (bounded search on log T); `then(p)`: what is done to the tempered
    probabilities before they are reported (e.g. `unseen_damage.with_unseen_damage`)."""
    from scipy.optimize import minimize_scalar

    proba, truth_index = np.asarray(proba, dtype=np.float64), np.asarray(truth_index)
    if len(proba) == 0:
        raise ValueError("no rows to fit a temperature on")
    bound = math.log(MAX_TEMPERATURE)
    then = then or (lambda p: p)
    res = minimize_scalar(lambda s: log_loss(then(temper(proba, math.exp(s))), truth_index), bounds=(-bound, bound),
                          method="bounded", options={"xatol": 1e-4})
    return float(math.exp(res.x))
