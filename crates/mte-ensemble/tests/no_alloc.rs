//! `insert` and `action` never touch the heap after construction, for every aggregator, nor
//! do the monitors' `observe`, proven with a counting global allocator.
//!
//! This file holds a single test so that no other test thread allocates while counting.
#![allow(clippy::unwrap_used)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

use mte_ensemble::{
    Aggregator, ChunkGeometry, EnsemblerOptions, MonitorKind, QueryMeta, TemporalEnsembler,
    WeightOrder,
};

struct Counting;

thread_local! {
    static ALLOCATIONS: Cell<u64> = const { Cell::new(0) };
}

// SAFETY: forwards to the system allocator; only counts calls on the current thread.
#[allow(unsafe_code)]
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.with(|c| c.set(c.get() + 1));
        // SAFETY: same contract as the caller's.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: same contract as the caller's.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        ALLOCATIONS.with(|c| c.set(c.get() + 1));
        // SAFETY: same contract as the caller's.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn allocations() -> u64 {
    ALLOCATIONS.with(Cell::get)
}

#[test]
fn steady_state_steps_do_not_allocate() {
    let mut aggs = Aggregator::catalogue();
    aggs.push(Aggregator::ExpWeightedMean {
        m: -0.5,
        order: WeightOrder::NewestFirst,
    });
    aggs.push(Aggregator::RecencyMedian { m: -0.2 });
    let setups = [(16, 2, 2, 7), (100, 1, 1, 14), (10, 2, 3, 2), (64, 2, 1, 3)];
    // The allocator must really be counting, or the assertions below prove nothing.
    let before = allocations();
    let probe: Box<[u8]> = Box::new([1u8; 16]);
    assert!(allocations() > before && probe[0] == 1);

    for (t_p, t_o, h, d) in setups {
        let g = ChunkGeometry::new(t_p, t_o, h).unwrap();
        for &agg in &aggs {
            for bracket_diagnostics in [false, true] {
                let opts = EnsemblerOptions {
                    bracket_diagnostics,
                    ..Default::default()
                };
                let mut ens = TemporalEnsembler::with_options(g, d, agg, opts).unwrap();
                let chunk: Vec<f32> = (0..t_p * d).map(|i| (i as f32 * 0.37).sin()).collect();
                let mut bad = chunk.clone();
                bad[t_o * d] = f32::NAN;
                let mut out = vec![0.0f32; d];
                let start = allocations();
                for episode in 0..3u64 {
                    ens.reset();
                    for tau in 0..300u64 {
                        if tau % h as u64 == 0 {
                            let meta = QueryMeta {
                                corrupted: (tau / h as u64) % 3 == episode,
                            };
                            let c = if tau % 7 == 0 && tau > t_p as u64 {
                                &bad
                            } else {
                                &chunk
                            };
                            ens.insert(tau, c, meta).unwrap();
                        }
                        let step = ens.action(tau).unwrap();
                        assert!(step.action.iter().all(|v| v.is_finite()));
                        ens.action_into(tau, &mut out).unwrap();
                    }
                    // Error paths must not allocate either.
                    assert!(ens.action(10_000).is_err());
                    assert!(ens.insert(5, &chunk, QueryMeta::CLEAN).is_err());
                }
                let n = allocations() - start;
                assert_eq!(
                    n, 0,
                    "{agg} t_p={t_p} h={h} d={d}: {n} allocations in 900 steps"
                );
            }
        }
        // The monitors, per query, including their error paths.
        let chunk: Vec<f32> = (0..t_p * d).map(|i| (i as f32 * 0.37).sin()).collect();
        for kind in [MonitorKind::Tide, MonitorKind::Acc] {
            let mut m = kind.build(g, d, 1e-3).unwrap();
            let start = allocations();
            for _ in 0..3 {
                m.reset();
                for tau in (0..300u64).step_by(h) {
                    let _ = m.observe(tau, &chunk).unwrap();
                }
                assert!(m.observe(0, &chunk).is_err());
                assert!(m.observe(10_000, &chunk[1..]).is_err());
            }
            let n = allocations() - start;
            assert_eq!(n, 0, "{kind} t_p={t_p} h={h} d={d}: {n} allocations");
        }
    }
}
