//! Per-step latency (insert + action) with divan: every aggregator at the headline
//! configurations, and the median and the exp-weighted mean over the full grid
//! (`T_p` 16/100, `d` 2/7/14, `h` 1/2/8).
//!
//! `running_sums` times the means served from per-time running sums beside the same means
//! gathered at every step (and beside a step whose candidates are then read, as an
//! evaluation's observer does).
//!
//! Run: `cargo bench -p mte-ensemble --bench step`. For p50/p99 per step over the full
//! aggregator grid, see the `latency` bench.

mod common;

use common::{CHUNKS, Config, DIMS, Loop, STRIDES};
use mte_ensemble::{Aggregator, Gathered};

fn main() {
    divan::main();
}

fn headline() -> Vec<Config> {
    let mut v = Vec::new();
    for agg in Aggregator::catalogue() {
        v.push(Config {
            agg,
            t_p: 16,
            d: 7,
            h: 2,
        }); // DP PushT at h = 2: M = 7/8
        v.push(Config {
            agg,
            t_p: 100,
            d: 14,
            h: 1,
        }); // ACT bimanual: M = 100
    }
    v
}

fn grid() -> Vec<Config> {
    let mut v = Vec::new();
    for agg in [Aggregator::MEDIAN, Aggregator::default()] {
        for t_p in CHUNKS {
            for d in DIMS {
                for h in STRIDES {
                    v.push(Config { agg, t_p, d, h });
                }
            }
        }
    }
    v
}

#[divan::bench(args = headline())]
fn every_aggregator(bencher: divan::Bencher, cfg: &Config) {
    let mut l = Loop::new(*cfg);
    bencher.bench_local(|| l.step());
}

#[divan::bench(args = grid())]
fn median_and_ewm_grid(bencher: divan::Bencher, cfg: &Config) {
    let mut l = Loop::new(*cfg);
    bencher.bench_local(|| l.step());
}

fn means() -> Vec<Config> {
    let mut v = Vec::new();
    for agg in [Aggregator::default(), Aggregator::Mean] {
        v.push(Config {
            agg,
            t_p: 16,
            d: 7,
            h: 2,
        });
        v.push(Config {
            agg,
            t_p: 100,
            d: 14,
            h: 1,
        });
    }
    v
}

/// The means from running sums (the default for `ewm` and `mean`).
#[divan::bench(args = means())]
fn running_sums(bencher: divan::Bencher, cfg: &Config) {
    let mut l = Loop::new(*cfg);
    bencher.bench_local(|| l.step());
}

/// The same means gathered at every step (the path before running sums, and the one every
/// other aggregator takes).
#[divan::bench(args = means())]
fn running_sums_gathered(bencher: divan::Bencher, cfg: &Config) {
    let mut l = Loop::with(*cfg, Gathered(cfg.agg));
    bencher.bench_local(|| l.step());
}

/// Running sums, then the step's candidates read (`last_candidates`), as the evaluation
/// runner's observer does at every step.
#[divan::bench(args = means())]
fn running_sums_then_candidates(bencher: divan::Bencher, cfg: &Config) {
    let mut l = Loop::new(*cfg);
    bencher.bench_local(|| {
        let a = l.step();
        a + l.ens.last_candidates().0.values()[0]
    });
}
