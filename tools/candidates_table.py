"""Summarise `mte --format json eval policy` outputs (one file per arm and sampling mode)
as a Markdown table: coverage, success and the candidate-spread statistics.

    python3 tools/candidates_table.py runs/candidates/*.json
"""
import json
import sys


def row(path):
    d = json.load(open(path))
    c = d["candidates"]
    cov = [e["max_coverage"] for e in d["episodes"]]
    n = len(cov)
    m = sum(cov) / n
    se = (sum((x - m) ** 2 for x in cov) / (n - 1) / n) ** 0.5 if n > 1 else float("nan")
    ages = ", ".join(f"{x:.1f}" for x in c["by_age"][:7])
    return (f"| `{d['execution']}` | {d['sampling']} | {len(d['episodes'])} | "
            f"{m:.3f} ± {se:.3f} | {100 * d['success_rate']:.0f}% | "
            f"{c['spread']:.1f} | {c['newest_to_mean']:.1f} | {c['newest_to_median']:.1f} | "
            f"{c['mean_to_nearest']:.1f} | {c['median_to_nearest']:.1f} | "
            f"{100 * c['split_fraction']:.1f}% | {ages} | {d['seconds']:.0f} s |")


print("| arm | sampling | n | mean max coverage | success | spread (px) | newest to mean "
      "| newest to median | mean to nearest | median to nearest | split steps "
      "| distance from newest by age 1..7 (px) | wall |")
print("|:--|:--|--:|--:|--:|--:|--:|--:|--:|--:|--:|:--|--:|")
for p in sys.argv[1:]:
    try:
        print(row(p))
    except (ValueError, KeyError) as e:
        print(f"<!-- {p}: {e} -->")
