"""Kernels per forward pass from an Nsight Compute CSV (`ncu --csv --print-units base
--metrics gpu__time_duration.sum ...`), for a benchmark that repeats one forward pass.

The kernel-name sequence of a repeated forward is periodic; the period (the lag in
[--min, --max] at which the most names match their successor one lag later) is the number of
kernels one forward launches. Over the first full period it prints the GPU time the kernels
were busy (the sum of their durations, in microseconds), the mean per kernel, the share of
single-block launches (grid (1, 1, 1)), and the kernels that took the most time.

    python tools/kernel_profile.py ncu.csv[.gz] [--min 50] [--max 2000] [--top 10]
"""
import argparse
import collections
import csv
import gzip
import sys


def read_rows(path):
    """(kernel name, duration in ns, grid size) per profiled launch, in launch order."""
    opener = gzip.open if path.endswith(".gz") else open
    with opener(path, "rt") as f:
        lines = f.read().splitlines()
    start = next((i for i, line in enumerate(lines) if line.startswith('"ID"')), None)
    if start is None:
        raise ValueError(f"{path}: no ncu CSV header (a line starting with \"ID\")")
    rows = []
    for r in csv.DictReader(lines[start:]):
        if r["Metric Name"] != "gpu__time_duration.sum" or r["Metric Unit"] != "ns":
            raise ValueError(f"{path}: expected gpu__time_duration.sum in ns, got "
                             f"{r['Metric Name']} in {r['Metric Unit']}")
        rows.append((r["Kernel Name"], float(r["Metric Value"].replace(",", "")), r["Grid Size"]))
    return rows


def period(names, lo, hi):
    """The lag in [lo, hi] with the highest share of names equal to the name one lag later,
    and that share."""
    best = (0.0, None)
    for p in range(lo, min(hi, len(names) // 2) + 1):
        share = sum(a == b for a, b in zip(names, names[p:])) / (len(names) - p)
        if share > best[0]:
            best = (share, p)
    if best[1] is None:
        raise ValueError(f"{len(names)} launches: too few for a period in [{lo}, {hi}] "
                         "(at least two periods are needed)")
    return best[1], best[0]


def summary(rows, lo, hi, top):
    p, share = period([n for n, _, _ in rows], lo, hi)
    one = rows[:p]
    busy = sum(t for _, t, _ in one)
    counts, times = collections.Counter(), collections.Counter()
    for name, t, _ in one:
        counts[name] += 1
        times[name] += t
    return {
        "kernels_per_period": p,
        "name_match_share": share,
        "busy_us": busy / 1e3,
        "mean_us": busy / p / 1e3,
        "single_block_share": sum(g == "(1, 1, 1)" for _, _, g in one) / p,
        "top": [(name, counts[name], times[name] / 1e3) for name, _ in times.most_common(top)],
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("csv")
    ap.add_argument("--min", type=int, default=50)
    ap.add_argument("--max", type=int, default=2000)
    ap.add_argument("--top", type=int, default=10)
    a = ap.parse_args(argv)
    s = summary(read_rows(a.csv), a.min, a.max, a.top)
    print(f"kernels per forward {s['kernels_per_period']} (names matching one period later: "
          f"{s['name_match_share']:.3f})")
    print(f"GPU busy {s['busy_us']:.1f} us, mean {s['mean_us']:.2f} us per kernel, "
          f"single-block launches {s['single_block_share']:.1%}")
    for name, n, us in s["top"]:
        print(f"{n:5d} launches {us:9.1f} us  {name[:70]}")


if __name__ == "__main__":
    sys.exit(main())
