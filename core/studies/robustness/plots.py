"""The robustness report's figures: robust features against the threshold per radius, and the
ULS-vs-DIM difference of every feature at every radius."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ...runtime.atomic import open_replacing
from .selection import THRESHOLDS, RobustnessResult


def _write_figure(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    try:
        with open_replacing(path, "wb") as fh:
            fig.savefig(fh, format="png")
    finally:
        plt.close(fig)


def plot_counts(result: RobustnessResult, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    ts = np.array(THRESHOLDS)
    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=120)
    cmap = plt.get_cmap("viridis")
    for k, r in enumerate(result.radii):
        counts = [len(result.robust_at(r, t)) for t in ts]
        best = r == result.best_radius
        ax.step(ts, counts, where="post", lw=3.0 if best else 1.2, color="black" if best else
                cmap(k / max(1, len(result.radii) - 1)), label=f"r = {r:g} m" + (" (selected)" if best else ""),
                zorder=3 if best else 2)
    ax.axvline(result.threshold_pct, color="red", ls="--", lw=1)
    ax.text(result.threshold_pct, 0.2, f" {result.threshold_pct:g} %", color="red", va="bottom")
    ax.set_xlabel("allowed difference in relative change, ULS vs DIM [percentage points]")
    ax.set_ylabel("number of robust change features" + (" (every stage)" if len(result.stages) > 1 else ""))
    ax.set_xlim(0, ts[-1])
    ax.set_ylim(0, len(result.features) + 0.5)
    ax.yaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    _write_figure(fig, path)


def plot_heatmap(result: RobustnessResult, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    m = np.array([[result.difference[r][f] for r in result.radii] for f in result.features], dtype=float)
    shown = np.clip(m, 0, 50)
    fig, ax = plt.subplots(figsize=(1.6 + 0.75 * len(result.radii), 1.4 + 0.28 * len(result.features)), dpi=120)
    im = ax.imshow(np.ma.masked_invalid(shown), cmap="magma_r", vmin=0, vmax=50, aspect="auto")
    for i in range(m.shape[0]):
        for j in range(m.shape[1]):
            v = m[i, j]
            txt = "n/a" if not math.isfinite(v) else (f"{v:.0f}" if v < 999 else ">999")
            ax.text(j, i, txt, ha="center", va="center", fontsize=6,
                    color="white" if math.isfinite(v) and v > 30 else "black")
    ax.set_xticks(range(len(result.radii)), [f"{r:g}" + (" *" if r == result.best_radius else "")
                                             for r in result.radii])
    ax.set_yticks(range(len(result.features)), result.features, fontsize=7)
    ax.set_xlabel("radius [m] (* selected)")
    worst = " (largest over the stages)" if len(result.stages) > 1 else ""
    ax.set_title(f"|relative change ULS - DIM| [percentage points]{worst}", fontsize=9)
    fig.colorbar(im, ax=ax, label="clipped at 50")
    fig.tight_layout()
    _write_figure(fig, path)
