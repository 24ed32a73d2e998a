//! Cost of one monitor score per query (TIDE with the ensembled plan, ACC), at Diffusion
//! Policy's (T_p 16, T_o 2, h 8 and h 2) and ACT's (T_p 100, T_o 1, h 1) geometries and
//! d 2, 7, 14. Rewind-IL reports 37 µs per cycle for TIDE.
//!
//! `cargo bench -p mte-ensemble --bench monitor`

use mte_ensemble::{ChunkGeometry, MonitorKind};

fn main() {
    divan::main();
}

const SETUPS: [(usize, usize, usize, usize); 6] = [
    (16, 2, 8, 2),
    (16, 2, 2, 2),
    (16, 2, 2, 7),
    (100, 1, 1, 2),
    (100, 1, 1, 7),
    (100, 1, 1, 14),
];

fn run(bencher: divan::Bencher, kind: MonitorKind, setup: (usize, usize, usize, usize)) {
    let (t_p, t_o, h, d) = setup;
    let g = ChunkGeometry::new(t_p, t_o, h).expect("geometry");
    let mut m = kind.build(g, d, 1e-3).expect("monitor");
    let chunks: Vec<Vec<f32>> = (0..8)
        .map(|k| {
            (0..t_p * d)
                .map(|i| ((i + 31 * k) as f32 * 0.37).sin())
                .collect()
        })
        .collect();
    // Warm the ring so every query is scored against a full history (M_max chunks).
    let mut t = 0u64;
    for k in 0..g.m_max() + chunks.len() {
        m.observe(t, &chunks[k % chunks.len()]).expect("observe");
        t += h as u64;
    }
    bencher.bench_local(|| {
        let c = &chunks[(t / h as u64) as usize % chunks.len()];
        let s = m.observe(t, c).expect("observe");
        t += h as u64;
        s
    });
}

#[divan::bench(args = SETUPS)]
fn tide(bencher: divan::Bencher, setup: (usize, usize, usize, usize)) {
    run(bencher, MonitorKind::Tide, setup);
}

#[divan::bench(args = SETUPS)]
fn acc(bencher: divan::Bencher, setup: (usize, usize, usize, usize)) {
    run(bencher, MonitorKind::Acc, setup);
}
