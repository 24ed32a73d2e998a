//! Shared set-up of the ensembler benchmarks: one configuration, a pre-generated stream.

use std::fmt;

use mte_ensemble::{Aggregate, Aggregator, ChunkGeometry, QueryMeta, TemporalEnsembler};

/// One benchmark configuration: aggregator, chunk length `t_p`, action dim `d`, stride `h`.
/// `t_o` is 2 for `t_p = 16` (Diffusion Policy) and 1 for `t_p = 100` (ACT).
#[derive(Clone, Copy, Debug)]
pub struct Config {
    pub agg: Aggregator,
    pub t_p: usize,
    pub d: usize,
    pub h: usize,
}

impl Config {
    pub fn geometry(&self) -> ChunkGeometry {
        let t_o = if self.t_p >= 100 { 1 } else { 2 };
        ChunkGeometry::new(self.t_p, t_o, self.h).expect("benchmark geometries are valid")
    }
}

impl fmt::Display for Config {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let g = self.geometry();
        write!(
            f,
            "{} T_p={} d={} h={} M={}",
            self.agg,
            self.t_p,
            self.d,
            self.h,
            g.m_max()
        )
    }
}

/// A control loop over pre-generated chunks: `step` does what a controller does at one
/// control time (insert the chunk when a query fires, then ask for the action).
pub struct Loop<A: Aggregate = Aggregator> {
    pub ens: TemporalEnsembler<A>,
    chunks: Vec<Vec<f32>>,
    h: u64,
    tau: u64,
    next_query: u64,
    next_chunk: usize,
}

impl Loop {
    pub fn new(cfg: Config) -> Self {
        Loop::with(cfg, cfg.agg)
    }
}

impl<A: Aggregate> Loop<A> {
    /// The loop of `cfg`'s geometry with `agg` in place of `cfg.agg`.
    pub fn with(cfg: Config, agg: A) -> Self {
        let g = cfg.geometry();
        let ens = TemporalEnsembler::new(g, cfg.d, agg).expect("valid ensembler");
        // 64 distinct chunks of smooth values plus deterministic jitter.
        let chunks = (0..64)
            .map(|k| {
                (0..cfg.t_p * cfg.d)
                    .map(|i| ((i * 7 + k * 13) as f32 * 0.173).sin() + (k as f32) * 0.01)
                    .collect()
            })
            .collect();
        let mut l = Self {
            ens,
            chunks,
            h: cfg.h as u64,
            tau: 0,
            next_query: 0,
            next_chunk: 0,
        };
        for _ in 0..(4 * cfg.t_p) {
            l.step(); // reach steady state: M(tau) at its periodic values
        }
        l
    }

    #[inline]
    pub fn step(&mut self) -> f32 {
        let tau = self.tau;
        if tau == self.next_query {
            // Counters rather than `tau % h`: a 64-bit division would cost more than some
            // aggregators.
            self.ens
                .insert(tau, &self.chunks[self.next_chunk], QueryMeta::CLEAN)
                .expect("insert");
            self.next_query += self.h;
            self.next_chunk = if self.next_chunk + 1 == self.chunks.len() {
                0
            } else {
                self.next_chunk + 1
            };
        }
        self.tau += 1;
        self.ens.action(tau).expect("action").action[0]
    }
}

pub const CHUNKS: [usize; 2] = [16, 100];
pub const DIMS: [usize; 3] = [2, 7, 14];
pub const STRIDES: [usize; 3] = [1, 2, 8];
