//! How aligned an attack's displacements are across the candidates that cover the same
//! control time: the quantity behind the common-mode boundary (a perfectly aligned
//! corruption is common-mode, invisible to translation-invariant monitors and unremovable by
//! equivariant aggregators; the paper measures a median pairwise cosine of 0.712 under PGD).
//!
//! The displacement of an attacked query is its executed chunk minus the chunk the policy
//! gives the same window with the same sampling noise, unattacked (the "twin": the attack's
//! sampling-stream words are recorded and the executed chunk's share replayed on the clean
//! window, which assumes the attack draws its reference chunk and then the executed one
//! from that stream, as `mte_policy::attack` does). For every
//! pair of attacked queries whose chunks both cover a control time, the cosine between their
//! displacement rows at that time is one sample; the summary is their median and quartiles.
//! Nothing in the runner changes: a wrapper policy answers each attacked query twice and an
//! observer pairs the displacements with their query times.

use std::collections::VecDeque;
use std::sync::Mutex;

use mte_policy::{AttackablePolicy, ChunkPolicy, ObsNeeds, Observation, PgdConfig, PolicyError};
use rand::RngCore;
use serde::{Deserialize, Serialize};

use crate::episode::{EpisodeObserver, QueryEvent};
use crate::pusht::{EpisodeSpec, RolloutError, run_episode_observed};

/// A policy that also answers every attacked query without the attack, from a copy of the
/// same sampling stream, and queues the difference.
struct Twin<'p> {
    inner: &'p (dyn ChunkPolicy + Sync),
    displacements: Mutex<VecDeque<Vec<f32>>>,
}

impl ChunkPolicy for Twin<'_> {
    fn horizon(&self) -> usize {
        self.inner.horizon()
    }
    fn n_obs_steps(&self) -> usize {
        self.inner.n_obs_steps()
    }
    fn action_dim(&self) -> usize {
        self.inner.action_dim()
    }
    fn needs(&self) -> ObsNeeds {
        self.inner.needs()
    }
    fn predict_chunk(
        &self,
        history: &[Observation],
        rng: &mut dyn RngCore,
    ) -> Result<Vec<f32>, PolicyError> {
        self.inner.predict_chunk(history, rng)
    }
    fn attackable(&self) -> Option<&dyn AttackablePolicy> {
        Some(self)
    }
}

/// A stream that replays recorded words from `at` on (zeros past the end).
struct Replay<'a> {
    words: &'a [u64],
    at: usize,
}

impl RngCore for Replay<'_> {
    fn next_u32(&mut self) -> u32 {
        self.next_u64() as u32
    }
    fn next_u64(&mut self) -> u64 {
        let w = self.words.get(self.at).copied().unwrap_or(0);
        self.at += 1;
        w
    }
    fn fill_bytes(&mut self, dst: &mut [u8]) {
        fill_from_words(self, dst);
    }
}

/// Bytes from whole words, little-endian (both streams here hand out words only).
fn fill_from_words(rng: &mut impl RngCore, dst: &mut [u8]) {
    for chunk in dst.chunks_mut(8) {
        let w = rng.next_u64().to_le_bytes();
        chunk.copy_from_slice(&w[..chunk.len()]);
    }
}

/// A stream that records every word it hands out.
struct Recording<'a> {
    inner: &'a mut dyn RngCore,
    words: Vec<u64>,
}

impl RngCore for Recording<'_> {
    fn next_u32(&mut self) -> u32 {
        self.next_u64() as u32
    }
    fn next_u64(&mut self) -> u64 {
        let w = self.inner.next_u64();
        self.words.push(w);
        w
    }
    fn fill_bytes(&mut self, dst: &mut [u8]) {
        fill_from_words(self, dst);
    }
}

impl AttackablePolicy for Twin<'_> {
    fn predict_chunk_attacked(
        &self,
        history: &[Observation],
        pgd: &PgdConfig,
        attack_rng: &mut dyn RngCore,
        sample_rng: &mut dyn RngCore,
    ) -> Result<Vec<f32>, PolicyError> {
        // The attack draws its reference chunk from the sampling stream first (the clean
        // chunk with the first noise), then the executed chunk (from the perturbed
        // observation, with the noise that follows). The twin is the clean chunk with the
        // executed chunk's noise: record the words, replay the reference chunk's sampling to
        // find where its share ends, and sample the clean window again from there.
        let mut rec = Recording {
            inner: sample_rng,
            words: Vec::new(),
        };
        let attacked = mte_policy::attackable(self.inner)?
            .predict_chunk_attacked(history, pgd, attack_rng, &mut rec)?;
        let mut first = Replay {
            words: &rec.words,
            at: 0,
        };
        self.inner.predict_chunk(history, &mut first)?;
        let clean = self.inner.predict_chunk(
            history,
            &mut Replay {
                words: &rec.words,
                at: first.at,
            },
        )?;
        let d: Vec<f32> = attacked.iter().zip(&clean).map(|(a, c)| a - c).collect();
        if let Ok(mut q) = self.displacements.lock() {
            q.push_back(d);
        }
        Ok(attacked)
    }
}

/// Pairs each attacked query's displacement with its query time.
struct Collect<'t, 'p> {
    twin: &'t Twin<'p>,
    attacked: Vec<(u64, Vec<f32>)>,
}

impl EpisodeObserver for Collect<'_, '_> {
    fn on_query(&mut self, e: &QueryEvent<'_>) {
        if !e.corrupted {
            return;
        }
        if let Some(d) = self
            .twin
            .displacements
            .lock()
            .ok()
            .and_then(|mut q| q.pop_front())
        {
            self.attacked.push((e.t, d));
        }
    }
}

/// Cosine samples of one episode's attacked queries: every pair covering a control time.
pub fn pair_cosines(attacked: &[(u64, Vec<f32>)], t_p: usize, t_o: usize, d: usize) -> Vec<f64> {
    let span = (t_p - t_o) as u64;
    let row = |t: u64, c: &[f32], tau: u64| -> Option<Vec<f64>> {
        let age = tau.checked_sub(t)?;
        (age <= span).then(|| {
            let r = age as usize + t_o - 1;
            c[r * d..(r + 1) * d]
                .iter()
                .map(|&v| f64::from(v))
                .collect()
        })
    };
    let mut out = Vec::new();
    for (i, (ti, ci)) in attacked.iter().enumerate() {
        for (tj, cj) in &attacked[i + 1..] {
            for tau in *tj..=ti + span {
                let (Some(a), Some(b)) = (row(*ti, ci, tau), row(*tj, cj, tau)) else {
                    continue;
                };
                let dot: f64 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
                let na = a.iter().map(|x| x * x).sum::<f64>().sqrt();
                let nb = b.iter().map(|x| x * x).sum::<f64>().sqrt();
                if na > 0.0 && nb > 0.0 {
                    out.push(dot / (na * nb));
                }
            }
        }
    }
    out
}

/// The alignment of an attack over episodes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Alignment {
    /// Episodes run.
    pub episodes: usize,
    /// Attacked queries.
    pub attacked_queries: usize,
    /// Cosine samples (pairs of attacked candidates x shared control times).
    pub pairs: usize,
    /// Median pairwise cosine.
    pub median: Option<f64>,
    /// Quartiles (25%, 75%).
    pub quartiles: Option<(f64, f64)>,
    /// Mean displacement norm per candidate row (action units).
    pub mean_norm: Option<f64>,
}

/// Runs `specs` (attacked episodes; their fault must be a query attack) and measures the
/// alignment of the attack's displacements.
///
/// # Errors
/// An episode's own errors.
pub fn alignment(
    policy: &(dyn ChunkPolicy + Sync),
    specs: &[EpisodeSpec<'_>],
) -> Result<Alignment, RolloutError> {
    let twin = Twin {
        inner: policy,
        displacements: Mutex::new(VecDeque::new()),
    };
    let (t_p, t_o, d) = (policy.horizon(), policy.n_obs_steps(), policy.action_dim());
    let (mut cos, mut norms, mut attacked) = (Vec::new(), Vec::new(), 0);
    for spec in specs {
        let mut obs = Collect {
            twin: &twin,
            attacked: Vec::new(),
        };
        run_episode_observed(&twin, spec, &mut obs)?;
        attacked += obs.attacked.len();
        cos.extend(pair_cosines(&obs.attacked, t_p, t_o, d));
        for (_, c) in &obs.attacked {
            norms.extend(
                c.chunks(d)
                    .map(|r| r.iter().map(|&v| f64::from(v).powi(2)).sum::<f64>().sqrt()),
            );
        }
    }
    cos.sort_by(f64::total_cmp);
    let q = |p: f64| cos[((cos.len() - 1) as f64 * p).round() as usize];
    Ok(Alignment {
        episodes: specs.len(),
        attacked_queries: attacked,
        pairs: cos.len(),
        median: (!cos.is_empty()).then(|| q(0.5)),
        quartiles: (!cos.is_empty()).then(|| (q(0.25), q(0.75))),
        mean_norm: (!norms.is_empty()).then(|| norms.iter().sum::<f64>() / norms.len() as f64),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn aligned_displacements_have_cosine_one_and_opposed_minus_one() {
        // T_p 4, T_o 1, d 2: queries at 0 and 2 share control times 2 and 3.
        let same = vec![1.0, 2.0, 1.0, 2.0, 1.0, 2.0, 1.0, 2.0];
        let opposed: Vec<f32> = same.iter().map(|v| -v).collect();
        let c = pair_cosines(&[(0, same.clone()), (2, same.clone())], 4, 1, 2);
        assert_eq!(c.len(), 2);
        assert!(c.iter().all(|v| (v - 1.0).abs() < 1e-12), "{c:?}");
        let c = pair_cosines(&[(0, same), (2, opposed)], 4, 1, 2);
        assert!(c.iter().all(|v| (v + 1.0).abs() < 1e-12), "{c:?}");
        // No shared control time: no sample.
        assert!(pair_cosines(&[(0, vec![1.0; 8]), (9, vec![1.0; 8])], 4, 1, 2).is_empty());
    }
}
