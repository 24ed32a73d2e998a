"""tools/paired_cells.py (the cell-against-cell comparison of docs/experiments/patch_controls)
on a tiny synthetic run directory: its differences, standard errors and Wilcoxon p-values."""

import json

import numpy as np
from scipy import stats

import repo_script


def load_tool():
    return repo_script.load("tools/paired_cells.py")


def write_cell(run, cell, values):
    lines = []
    for arm, per_seed in values.items():
        for seed, cov in per_seed.items():
            lines.append(json.dumps({"kind": "episode", "cell": cell, "arm": arm, "seed": seed, "max_coverage": cov, "success": cov > 0.95}))
    (run / "cells" / f"{cell}.jsonl").write_text("\n".join(lines) + "\n")


def test_paired_difference_and_wilcoxon(tmp_path, capsys):
    (tmp_path / "cells").mkdir()
    rng = np.random.default_rng(0)
    a = {s: float(v) for s, v in zip(range(20), rng.uniform(0, 1, 20))}
    b = {s: a[s] - 0.1 + 0.01 * s for s in a}
    write_cell(tmp_path, "base", {"ewm": a})
    write_cell(tmp_path, "other", {"ewm": b})
    load_tool().main(str(tmp_path), "base", "other")
    row = [line for line in capsys.readouterr().out.splitlines() if "`other`" in line][0]
    d = np.array([b[s] - a[s] for s in range(20)])
    p = stats.wilcoxon(list(b.values()), list(a.values())).pvalue
    assert f"{d.mean():+.3f} ± {d.std(ddof=1) / np.sqrt(20):.3f}" in row
    assert f"{p:.2g}" in row
    assert "| 20 |" in row


def test_a_cell_of_another_run_pairs_by_seed(tmp_path, capsys):
    for run in ("one", "two"):
        (tmp_path / run / "cells").mkdir(parents=True)
    a = {s: 0.5 for s in range(6)}
    b = {s: 0.5 + 0.1 * (s % 2) for s in range(8)}
    write_cell(tmp_path / "one", "base", {"median": a})
    write_cell(tmp_path / "two", "other", {"median": b})
    load_tool().main(str(tmp_path / "one"), "base", f"{tmp_path / 'two'}::other")
    row = [line for line in capsys.readouterr().out.splitlines() if "other`" in line][0]
    assert "| 6 |" in row, "only the seeds both cells ran"
    assert "+0.050" in row


def test_exact_mcnemar_on_successes(tmp_path, capsys):
    (tmp_path / "cells").mkdir()
    seeds = range(12)
    # Success lost on seeds 0-7, gained on seed 8, unchanged elsewhere: 8:1 discordant pairs.
    a = {s: (1.0 if s < 8 or s == 10 else 0.2) for s in seeds}
    b = {s: (1.0 if s in (8, 10) else 0.2) for s in seeds}
    for name, values in (("base", a), ("other", b)):
        lines = [
            json.dumps({"kind": "episode", "arm": "median", "seed": s, "max_coverage": v, "success": v == 1.0})
            for s, v in values.items()
        ]
        (tmp_path / "cells" / f"{name}.jsonl").write_text("\n".join(lines) + "\n")
    tool = load_tool()
    tool.main(str(tmp_path), "base", "other")
    row = [line for line in capsys.readouterr().out.splitlines() if "`other`" in line][0]
    p = stats.binomtest(1, 9, 0.5).pvalue  # the exact McNemar test is this binomial test
    assert "| 9 → 2 | 8:1 |" in row
    assert f"| {p:.2g} |" in row
    assert tool.mcnemar_exact(0, 0) == 1.0
    assert tool.mcnemar_exact(3, 3) == 1.0
    assert abs(tool.mcnemar_exact(20, 0) - 2 * 0.5**20) < 1e-15


def test_arms_of_one_cell_pair_by_seed(tmp_path, capsys):
    (tmp_path / "cells").mkdir()
    rng = np.random.default_rng(1)
    base = {s: float(v) for s, v in zip(range(15), rng.uniform(0, 1, 15))}
    other = {s: base[s] + 0.05 * (s % 3) for s in range(12)}  # 12 seeds only
    write_cell(tmp_path, "c", {"open-loop": base, "median": other})
    load_tool().arms(str(tmp_path), "c", "open-loop", "median")
    row = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| `median`")][0]
    d = np.array([other[s] - base[s] for s in range(12)])
    p = stats.wilcoxon([other[s] for s in range(12)], [base[s] for s in range(12)]).pvalue
    assert "| 12 |" in row, "only the seeds both arms ran"
    assert f"{d.mean():+.3f} ± {d.std(ddof=1) / np.sqrt(12):.3f}" in row
    assert f"{p:.2g}" in row


def test_arms_names_a_missing_arm(tmp_path):
    (tmp_path / "cells").mkdir()
    write_cell(tmp_path, "c", {"ewm": {0: 0.5, 1: 0.6}})
    tool = load_tool()
    try:
        tool.arms(str(tmp_path), "c", "ewm", "median")
    except tool.MissingArm as e:
        assert "no arm median" in str(e) and "it has ewm" in str(e)
    else:
        raise AssertionError("a missing arm must stop the tool")


def test_the_command_line_explains_bad_arguments(tmp_path, capsys):
    tool = load_tool()
    assert tool.cli(["--help"]) == 0
    assert "paired_cells.py RUN CELL_A CELL_B" in capsys.readouterr().err
    assert tool.cli([str(tmp_path), "base"]) == 2
    assert "expected at least 3 arguments, got 2" in capsys.readouterr().err
    assert tool.cli(["--arms", str(tmp_path), "cell", "ewm"]) == 2
    assert "expected at least 4 arguments, got 3" in capsys.readouterr().err
    assert tool.cli([str(tmp_path), "base", "other"]) == 2
    assert "no records:" in capsys.readouterr().err
    (tmp_path / "cells").mkdir()
    write_cell(tmp_path, "base", {"ewm": {0: 0.5, 1: 0.7}})
    write_cell(tmp_path, "other", {"ewm": {0: 0.6, 1: 0.7}})
    assert tool.cli([str(tmp_path), "base", "other"]) == 0
    assert "`other`" in capsys.readouterr().out
    assert tool.cli(["--arms", str(tmp_path), "base", "ewm", "median"]) == 2
    assert "no arm median" in capsys.readouterr().err
