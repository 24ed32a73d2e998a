//! Per-step latency percentiles (p50, p99) of insert + action, for every aggregator over the
//! grid `T_p` 16/100 x `d` 2/7/14 x `h` 1/2/8.
//!
//! Each step is timed individually with `Instant` and the timer's own median cost
//! (measured here, typically 20-30 ns on a VM) is subtracted, so single-step figures below
//! ~50 ns carry that much uncertainty; the mean is taken over untimed batches and is exact.
//! Output is a markdown table on stdout.
//!
//! Run: `cargo bench -p mte-ensemble --bench latency [-- FILTER]`.
//!
//! `-- --count N FILTER` instead runs exactly `N` untimed steps of each matching
//! configuration and prints nothing else: for instruction counts under
//! `valgrind --tool=callgrind`, which are repeatable on a busy machine.
#![allow(clippy::print_stdout)]

mod common;

use std::hint::black_box;
use std::time::{Duration, Instant};

use common::{CHUNKS, Config, DIMS, Loop, STRIDES};
use mte_ensemble::Aggregator;
use mte_ensemble::bracket::nearest_rank;

fn percentile(sorted: &[f64], q: f64) -> f64 {
    nearest_rank(sorted, q).unwrap_or(0.0)
}

fn timer_overhead() -> f64 {
    let mut v: Vec<f64> = (0..100_000)
        .map(|_| {
            let t0 = Instant::now();
            let t1 = Instant::now();
            (t1 - t0).as_nanos() as f64
        })
        .collect();
    v.sort_by(f64::total_cmp);
    percentile(&v, 0.5)
}

fn measure(cfg: Config, overhead: f64, budget: Duration) -> (f64, f64, f64, usize) {
    let mut l = Loop::new(cfg);
    // Mean over a batch, no per-step timer.
    let start = Instant::now();
    let mut n = 0usize;
    while start.elapsed() < budget / 2 || n < 1000 {
        for _ in 0..100 {
            black_box(l.step());
        }
        n += 100;
    }
    let mean = start.elapsed().as_nanos() as f64 / n as f64;
    // Individually timed steps.
    let mut samples = Vec::with_capacity(n.min(200_000));
    let start = Instant::now();
    while samples.len() < 200_000 && (start.elapsed() < budget / 2 || samples.len() < 1000) {
        let t0 = Instant::now();
        black_box(l.step());
        let dt = t0.elapsed().as_nanos() as f64;
        samples.push((dt - overhead).max(0.0));
    }
    samples.sort_by(f64::total_cmp);
    (
        mean,
        percentile(&samples, 0.5),
        percentile(&samples, 0.99),
        samples.len(),
    )
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let count: Option<usize> = args
        .iter()
        .position(|a| a == "--count")
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok());
    let filter: Option<String> = args
        .iter()
        .enumerate()
        .find(|(i, a)| !a.starts_with('-') && (*i == 0 || args[i - 1] != "--count"))
        .map(|(_, a)| a.clone());
    if let Some(n) = count {
        for agg in Aggregator::catalogue() {
            for t_p in CHUNKS {
                for d in DIMS {
                    for h in STRIDES {
                        let cfg = Config { agg, t_p, d, h };
                        if filter
                            .as_ref()
                            .is_some_and(|f| !cfg.to_string().contains(f.as_str()))
                        {
                            continue;
                        }
                        let mut l = Loop::new(cfg);
                        for _ in 0..n {
                            black_box(l.step());
                        }
                    }
                }
            }
        }
        return;
    }
    let overhead = timer_overhead();
    println!("timer overhead (median of Instant::now() pairs): {overhead:.0} ns\n");
    println!("| aggregator | T_p | d | h | M | mean ns | p50 ns | p99 ns | steps timed |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for agg in Aggregator::catalogue() {
        for t_p in CHUNKS {
            for d in DIMS {
                for h in STRIDES {
                    let cfg = Config { agg, t_p, d, h };
                    let label = cfg.to_string();
                    if filter.as_ref().is_some_and(|f| !label.contains(f.as_str())) {
                        continue;
                    }
                    let (mean, p50, p99, n) = measure(cfg, overhead, Duration::from_millis(120));
                    let m = cfg.geometry().m_max();
                    println!(
                        "| {agg} | {t_p} | {d} | {h} | {m} | {mean:.0} | {p50:.0} | {p99:.0} | {n} |"
                    );
                }
            }
        }
    }
}
