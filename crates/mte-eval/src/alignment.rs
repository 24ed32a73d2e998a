//! How aligned a corruption's displacements are across the candidates that cover the same
//! control time: the quantity behind the common-mode boundary (a perfectly aligned
//! corruption is common-mode, invisible to translation-invariant monitors and unremovable by
//! equivariant aggregators; the paper measures a median pairwise cosine of 0.712 under PGD).
//!
//! The displacement of a corrupted query is its executed chunk minus the chunk the policy
//! gives the clean window with the same sampling noise (the "twin"). For a sensor fault
//! (blank frames, the patch, ...) the twin is the policy's answer to the window as the
//! sensors gave it, from a copy of the query's sampling stream. For PGD the attack's
//! sampling-stream words are recorded and the executed chunk's share replayed on the clean
//! window, which assumes the attack draws its reference chunk and then the executed one
//! from that stream, as `mte_policy::attack` does. For every pair of corrupted queries whose
//! chunks both cover a control time, the cosine between their displacement rows at that
//! time is one sample; the summary is their median and quartiles. The episodes run through
//! the runner's own stages, so the executed chunks are the ones a sweep would execute.

use mte_policy::{ChunkPolicy, Observation, PolicyError};
use rand::RngCore;
use serde::{Deserialize, Serialize};

use crate::environment::{Environment, PushTEnv};
use crate::episode::NoObserver;
use crate::pusht::{Episode, EpisodeSpec, Pending, RolloutError, Watchers};

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

/// The chunk `p` executes and, when the schedule corrupted it, its displacement from the
/// twin (the clean window's chunk with the same sampling noise).
fn answer_with_twin(
    policy: &dyn ChunkPolicy,
    p: &Pending,
    clean_window: &[Observation],
) -> Result<(Vec<f32>, Option<Vec<f32>>), PolicyError> {
    if !p.corrupted() {
        return Ok((p.answer_alone(policy)?, None));
    }
    let (mut crng, mut srng) = p.streams();
    let (executed, clean) = match p.attack() {
        Some(cfg) => {
            // The attack draws its reference chunk from the sampling stream first (the
            // clean chunk with the first noise), then the executed chunk (from the perturbed
            // window, with the noise that follows): record the words, replay the reference
            // chunk's sampling to find where its share ends, and sample again from there.
            let mut rec = Recording {
                inner: &mut srng,
                words: Vec::new(),
            };
            let executed = mte_policy::attackable(policy)?.predict_chunk_attacked(
                p.window(),
                cfg,
                &mut crng,
                &mut rec,
            )?;
            let mut first = Replay {
                words: &rec.words,
                at: 0,
            };
            policy.predict_chunk(clean_window, &mut first)?;
            let mut rest = Replay {
                words: &rec.words,
                at: first.at,
            };
            (executed, policy.predict_chunk(clean_window, &mut rest)?)
        }
        None => {
            let executed = policy.predict_chunk(p.window(), &mut srng.clone())?;
            (executed, policy.predict_chunk(clean_window, &mut srng)?)
        }
    };
    let d = executed.iter().zip(&clean).map(|(a, c)| a - c).collect();
    Ok((executed, Some(d)))
}

/// One episode of `spec` through the runner's stages; the corrupted queries' times and
/// displacements.
fn episode_displacements(
    env: &mut dyn Environment,
    policy: &dyn ChunkPolicy,
    spec: &EpisodeSpec<'_>,
) -> Result<Vec<(u64, Vec<f32>)>, RolloutError> {
    let mut quiet = NoObserver;
    let mut w = Watchers::new(&mut quiet);
    let mut ep = Episode::new(env, policy, spec, &mut w)?;
    let mut out = Vec::new();
    while !ep.over() {
        ep.observe(&mut w)?;
        if let Some(p) = ep.prepare(&mut w)? {
            let (chunk, displacement) = answer_with_twin(policy, &p, ep.clean_window())?;
            let t = ep.accept(&p, chunk, &mut w)?.t;
            if let Some(d) = displacement {
                out.push((t, d));
            }
        }
        ep.act(&mut w)?;
    }
    Ok(out)
}

/// Cosine samples of one episode's corrupted queries: every pair covering a control time.
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

/// The alignment of a corruption over episodes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Alignment {
    /// Episodes run.
    pub episodes: usize,
    /// Corrupted queries (attacked, or fed a faulty window).
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

/// Runs `specs` (corrupted episodes: PGD, or a sensor fault) in PushT and measures the
/// alignment of the corruption's displacements.
///
/// # Errors
/// An episode's own errors.
pub fn alignment(
    policy: &(dyn ChunkPolicy + Sync),
    specs: &[EpisodeSpec<'_>],
) -> Result<Alignment, RolloutError> {
    let (t_p, t_o, d) = (policy.horizon(), policy.n_obs_steps(), policy.action_dim());
    let (mut cos, mut norms, mut attacked) = (Vec::new(), Vec::new(), 0);
    for spec in specs {
        let mut env = PushTEnv::new(spec.stream);
        let displaced = episode_displacements(&mut env, policy, spec)?;
        attacked += displaced.len();
        cos.extend(pair_cosines(&displaced, t_p, t_o, d));
        for (_, c) in &displaced {
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
