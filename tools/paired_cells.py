"""Paired comparison of two cells of one run, arm by arm: mean max coverage of each, the
paired difference (second - first) with its standard error, and the two-sided Wilcoxon
signed-rank p-value (scipy's rules) over the seeds both cells ran.

    python tools/paired_cells.py RUN CELL_A CELL_B [CELL_C ...]   # every cell against CELL_A

A cell written `OTHER_RUN::CELL` is read from another run directory (runs of one policy on the
same seeds and noise seed pair by seed across runs, as within one).

Needs numpy and scipy (tools/reference/requirements-stats.txt).
"""
import json
import pathlib
import sys

import numpy as np
from scipy import stats


def load(run, cell):
    if "::" in cell:
        run, cell = cell.split("::", 1)
    out = {}
    for line in (pathlib.Path(run) / "cells" / f"{cell}.jsonl").read_text().splitlines():
        r = json.loads(line)
        if r.get("kind") == "episode":
            out.setdefault(r["arm"], {})[r["seed"]] = r["max_coverage"]
    return out


def main(run, base, *others):
    a = load(run, base)
    print(f"| arm | cell | n | {base} | cell | Δ ± paired SE | Wilcoxon p |\n|---|---|--:|--:|--:|--:|--:|")
    for cell in others:
        b = load(run, cell)
        for arm in sorted(a):
            seeds = sorted(set(a[arm]) & set(b.get(arm, {})))
            x = np.array([a[arm][s] for s in seeds])
            y = np.array([b[arm][s] for s in seeds])
            d = y - x
            p = stats.wilcoxon(y, x).pvalue if np.any(d != 0) else 1.0
            se = d.std(ddof=1) / np.sqrt(len(d))
            print(f"| `{arm}` | `{cell}` | {len(seeds)} | {x.mean():.3f} | {y.mean():.3f} | {d.mean():+.3f} ± {se:.3f} | {p:.2g} |")


if __name__ == "__main__":
    main(*sys.argv[1:])
