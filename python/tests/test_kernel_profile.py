"""tools/kernel_profile.py (kernels per forward from an Nsight Compute CSV, BENCHMARKS.md's
H200 section) on synthetic CSVs: the period of a repeated launch sequence, the busy time and
shares over one period, and its refusals."""

import gzip

import pytest

import repo_script

HEADER = ('"ID","Process ID","Process Name","Host Name","Kernel Name","Context","Stream",'
          '"Block Size","Grid Size","Device","CC","Section Name","Metric Name","Metric Unit",'
          '"Metric Value"')


def load_tool():
    return repo_script.load("tools/kernel_profile.py")


def write_csv(path, launches, metric="gpu__time_duration.sum"):
    lines = ["==PROF== Connected to process 1", HEADER]
    for i, (name, ns, grid) in enumerate(launches):
        lines.append(f'"{i}","1","bench","host","{name}","1","7","(1024, 1, 1)","{grid}","0",'
                     f'"9.0","Command line profiler metrics","{metric}","ns","{ns:,}"')
    text = "\n".join(lines) + "\n"
    if str(path).endswith(".gz"):
        with gzip.open(path, "wt") as f:
            f.write(text)
    else:
        path.write_text(text)


# One "forward": 7 launches, 3 of them multi-block; durations in ns.
FORWARD = [("ucopy_f32", 2000, "(1, 1, 1)"), ("badd_f32", 3000, "(1, 1, 1)"),
           ("sgemm", 10000, "(8, 1, 1)"), ("ucopy_f32", 2000, "(1, 1, 1)"),
           ("fast_sum_f32", 4000, "(2, 1, 1)"), ("bmul_f32", 1500, "(1, 1, 1)"),
           ("sgemm", 12000, "(8, 1, 1)")]


@pytest.mark.parametrize("name", ["ncu.csv", "ncu.csv.gz"])
def test_period_busy_time_and_shares(tmp_path, name):
    tool = load_tool()
    path = tmp_path / name
    # Start mid-forward, as a profiling window does, and run four forwards.
    write_csv(path, (FORWARD * 5)[3:3 + 4 * len(FORWARD)])
    s = tool.summary(tool.read_rows(str(path)), 2, 20, 3)
    assert s["kernels_per_period"] == 7
    assert s["name_match_share"] == pytest.approx(1.0)
    assert s["busy_us"] == pytest.approx(34.5)  # 34,500 ns per forward, wherever it starts
    assert s["mean_us"] == pytest.approx(34.5 / 7)
    assert s["single_block_share"] == pytest.approx(4 / 7)
    assert s["top"][0] == ("sgemm", 2, pytest.approx(22.0))


def test_refuses_a_csv_without_header_or_with_another_metric(tmp_path):
    tool = load_tool()
    bare = tmp_path / "bare.csv"
    bare.write_text("no profile here\n")
    with pytest.raises(ValueError, match="no ncu CSV header"):
        tool.read_rows(str(bare))
    other = tmp_path / "other.csv"
    write_csv(other, FORWARD, metric="sm__throughput.avg.pct_of_peak_sustained_elapsed")
    with pytest.raises(ValueError, match="gpu__time_duration.sum"):
        tool.read_rows(str(other))


def test_refuses_fewer_than_two_periods(tmp_path):
    tool = load_tool()
    path = tmp_path / "short.csv"
    write_csv(path, FORWARD)
    with pytest.raises(ValueError, match="too few"):
        tool.summary(tool.read_rows(str(path)), 5, 20, 3)
