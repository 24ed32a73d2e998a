"""Paired comparison of two cells of one run, arm by arm, over the seeds both cells ran:
mean max coverage of each, the paired difference (second - first) with its standard error and
the two-sided Wilcoxon signed-rank p-value (scipy's rules); and the successes of each, the
discordant pairs (success lost : success gained from the first cell to the second) and the
two-sided exact McNemar p-value on them (binomial, p = 1/2, the same test as `mte report`).

    python tools/paired_cells.py RUN CELL_A CELL_B [CELL_C ...]   # every cell against CELL_A
    python tools/paired_cells.py --arms RUN CELL ARM_A ARM_B [...]  # within one cell: every arm against ARM_A

A cell written `OTHER_RUN::CELL` is read from another run directory (runs of one policy on the
same seeds and noise seed pair by seed across runs, as within one).

Needs numpy and scipy (tools/reference/requirements-stats.txt).
"""
import json
import pathlib
import sys

import numpy as np
from scipy import stats


class MissingArm(ValueError):
    """A cell has no records of an arm asked for; the message names the arm and the cell's arms."""


def load(run, cell):
    """`{arm: {seed: (max_coverage, success)}}` of a cell's episode records."""
    if "::" in cell:
        run, cell = cell.split("::", 1)
    out = {}
    for line in (pathlib.Path(run) / "cells" / f"{cell}.jsonl").read_text().splitlines():
        r = json.loads(line)
        if r.get("kind") == "episode":
            out.setdefault(r["arm"], {})[r["seed"]] = (r["max_coverage"], bool(r["success"]))
    return out


def mcnemar_exact(lost, gained):
    """Two-sided exact McNemar p-value of `lost : gained` discordant pairs (1.0 when none)."""
    if lost + gained == 0:
        return 1.0
    return stats.binomtest(lost, lost + gained, 0.5).pvalue


def row(arm, cell, a, b):
    seeds = sorted(set(a) & set(b))
    x = np.array([a[s][0] for s in seeds])
    y = np.array([b[s][0] for s in seeds])
    d = y - x
    p = stats.wilcoxon(y, x).pvalue if np.any(d != 0) else 1.0
    se = d.std(ddof=1) / np.sqrt(len(d)) if len(d) > 1 else float("nan")
    lost = sum(a[s][1] and not b[s][1] for s in seeds)
    gained = sum(b[s][1] and not a[s][1] for s in seeds)
    sa, sb = sum(a[s][1] for s in seeds), sum(b[s][1] for s in seeds)
    return (
        f"| `{arm}` | `{cell}` | {len(seeds)} | {x.mean():.3f} | {y.mean():.3f} | {d.mean():+.3f} ± {se:.3f} | {p:.2g} "
        f"| {sa} → {sb} | {lost}:{gained} | {mcnemar_exact(lost, gained):.2g} |"
    )


def header(base):
    return (
        f"| arm | cell | n | {base} | cell | Δ ± paired SE | Wilcoxon p | successes | lost:gained | McNemar p |\n"
        "|---|---|--:|--:|--:|--:|--:|--:|--:|--:|"
    )


def arms(run, cell, base, *others):
    """Arms of one cell against `base` on the seeds both ran (columns as for cells; the first
    column names the arm compared, the second the cell)."""
    a = load(run, cell)
    missing = [arm for arm in (base, *others) if arm not in a]
    if missing:
        raise MissingArm(f"cell {cell} has no arm {', '.join(missing)}; it has {', '.join(sorted(a))}")
    print(header(base))
    for arm in others:
        print(row(arm, cell, a[base], a[arm]))


def main(run, base, *others):
    a = load(run, base)
    print(header(base))
    for cell in others:
        b = load(run, cell)
        for arm in sorted(a):
            if arm in b:
                print(row(arm, cell, a[arm], b[arm]))


def cli(argv):
    """Runs the command line `argv` (without the program name); returns the exit status: 0, or 2
    with the usage on stderr for `-h`, `--help` or too few arguments, or with the missing file
    named for a cell that has no records, or with the arm named for an arm a cell lacks."""
    usage = __doc__.split("\n\n")[1]
    if argv[:1] in (["-h"], ["--help"]):
        print(usage, file=sys.stderr)
        return 0
    command, args, least = (arms, argv[1:], 4) if argv[:1] == ["--arms"] else (main, argv, 3)
    if len(args) < least:
        print(f"expected at least {least} arguments, got {len(args)}\n{usage}", file=sys.stderr)
        return 2
    try:
        command(*args)
    except FileNotFoundError as e:
        print(f"no records: {e.filename}", file=sys.stderr)
        return 2
    except MissingArm as e:
        print(e, file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(cli(sys.argv[1:]))
