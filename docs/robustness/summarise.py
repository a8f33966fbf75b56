"""Stability of the robust-feature selection across runs (seeds): best radius, robust set,
how often each feature is selected, against the paper's set.

    python docs/robustness/summarise.py out/robustness_b_s0 out/robustness_b_s1 out/robustness_b_s2 \\
        -o docs/robustness/stability.json
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from quakescan.studies.robustness.selection import PAPER_SET, REPORT_FEATURES


def summarise(runs: list[Path]) -> dict:
    res = []
    for r in runs:
        js = json.loads((r / "robustness.json").read_text())
        res.append({"run": str(r), "seed": js.get("seed"), "best_radius_m": js["best_radius_m"],
                    "robust": js["robust"], "n_robust": len(js["robust"]),
                    "paper_overlap": len(set(js["robust"]) & set(PAPER_SET)),
                    "jaccard_with_paper": js["comparison_with_paper"]["agreement"],
                    "robust_count_by_radius": {k: len(v) for k, v in js["robust_by_radius"].items()},
                    "wall_time_s": js["wall_time_s"]})
    n = len(res)
    freq = {f: sum(f in x["robust"] for x in res) for f in REPORT_FEATURES}
    always = [f for f in REPORT_FEATURES if freq[f] == n]
    never = [f for f in REPORT_FEATURES if freq[f] == 0]
    sets = [set(x["robust"]) for x in res]
    jac = [len(a & b) / len(a | b) if a | b else 1.0 for i, a in enumerate(sets) for b in sets[i + 1:]]
    return {"runs": res, "times_selected": freq, "selected_in_every_run": always, "never_selected": never,
            "pairwise_jaccard_between_runs": [round(j, 3) for j in jac],
            "best_radii": [x["best_radius_m"] for x in res], "paper_set": list(PAPER_SET)}


def markdown(s: dict) -> str:
    lines = ["| run | best radius [m] | robust | of the paper's 10 | Jaccard with paper |", "|---|---|---|---|---|"]
    for x in s["runs"]:
        lines.append(f"| {Path(x['run']).name} | {x['best_radius_m']:g} | {x['n_robust']} | {x['paper_overlap']} | "
                     f"{x['jaccard_with_paper']:.2f} |")
    n = len(s["runs"])
    lines += ["", "| feature | paper | selected in runs |", "|---|---|---|"]
    for f, c in s["times_selected"].items():
        lines.append(f"| {f} | {'yes' if f in s['paper_set'] else ''} | {c}/{n} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+")
    ap.add_argument("-o", "--output", required=True)
    a = ap.parse_args(argv)
    s = summarise([Path(r) for r in a.runs])
    Path(a.output).write_text(json.dumps(s, indent=1) + "\n")
    print(markdown(s))


if __name__ == "__main__":
    main()
