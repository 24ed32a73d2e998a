//! Episodes in lockstep: many episodes advance one control step at a time together, and at
//! each step the policy is called once for every episode that queries then (PGD once for
//! every attacked query), instead of once per episode.
//!
//! Nothing about an episode changes: each keeps its own environment, history, corruption
//! schedule, ensembler and per-query streams ([`crate::pusht::query_rng`]), built and
//! advanced by the same stage methods as [`crate::pusht::run_episode_in`]. The policy's
//! batched answer is, by the contract of [`ChunkPolicy::predict_chunks`], what each query
//! gets alone (the Diffusion Policy's network is batch-invariant: `mte_policy::kernels`),
//! so an episode's record is the same whichever episodes share its batches; only the
//! timings differ (a batch's time is shared equally by its queries). Tests run a small
//! sweep both ways and compare every record.
//!
//! Memory grows with the number of episodes run together (their histories, ensemblers,
//! and the policy's activations for one batch); callers bound it by the group size they
//! pass ([`crate::sweep::RunOptions::batch`]).

use std::time::Instant;

use mte_policy::{AttackedQuery, ChunkPolicy, PgdConfig, PolicyError, Query};
use rand_chacha::ChaCha8Rng;

use crate::environment::{Environment, PushTEnv};
use crate::episode::{EpisodeObserver, NoObserver};
use crate::pusht::{Episode, EpisodeSpec, Pending, RolloutError, Watchers};
use crate::record::EpisodeRecord;

/// Where finished episodes go: `(index into the specs, its record or its error)`, called as
/// each finishes (so a caller can append and flush it at once).
pub type OnDone<'a> = dyn FnMut(usize, Result<EpisodeRecord, RolloutError>) + 'a;

/// Runs the PushT episodes `specs` in lockstep on native environments, telling `on_done`
/// each record as its episode ends.
pub fn run_lockstep(policy: &dyn ChunkPolicy, specs: &[EpisodeSpec<'_>], on_done: &mut OnDone<'_>) {
    let mut envs: Vec<PushTEnv> = specs.iter().map(|s| PushTEnv::new(s.stream)).collect();
    let mut quiet = vec![NoObserver; specs.len()];
    let envs: Vec<&mut dyn Environment> =
        envs.iter_mut().map(|e| e as &mut dyn Environment).collect();
    let observers: Vec<&mut dyn EpisodeObserver> = quiet
        .iter_mut()
        .map(|o| o as &mut dyn EpisodeObserver)
        .collect();
    run_lockstep_in(envs, policy, specs, observers, on_done);
}

/// [`run_lockstep`] in any environments, episode `i` in `envs[i]` told to `observers[i]`.
/// Extra environments or observers beyond `specs.len()` are unused; a spec without both
/// finishes at once with an error.
pub fn run_lockstep_in<'e>(
    envs: Vec<&'e mut dyn Environment>,
    policy: &dyn ChunkPolicy,
    specs: &'e [EpisodeSpec<'e>],
    observers: Vec<&'e mut dyn EpisodeObserver>,
    on_done: &mut OnDone<'_>,
) {
    let mut envs = envs.into_iter();
    let mut observers = observers.into_iter();
    let mut live: Vec<Slot<'e>> = Vec::with_capacity(specs.len());
    for (index, spec) in specs.iter().enumerate() {
        let (Some(env), Some(obs)) = (envs.next(), observers.next()) else {
            on_done(index, Err(missing(index)));
            continue;
        };
        let t_start = Instant::now();
        let mut w = Watchers::new(obs);
        match Episode::new(env, policy, spec, &mut w) {
            Ok(ep) => live.push(Slot {
                index,
                ep,
                w,
                busy_s: t_start.elapsed().as_secs_f64(),
                pending: None,
                error: None,
            }),
            Err(e) => on_done(index, Err(e)),
        }
    }
    retire(&mut live, on_done);
    while !live.is_empty() {
        for s in &mut live {
            s.observe_and_prepare();
        }
        let chunks = answer(policy, &mut live);
        for (s, chunk) in live.iter_mut().zip(chunks) {
            s.accept_and_act(chunk);
        }
        retire(&mut live, on_done);
    }
}

fn missing(index: usize) -> RolloutError {
    RolloutError::Config {
        field: "lockstep",
        value: format!("episode {index}"),
        expected: "an environment and an observer for every spec".into(),
    }
}

/// One live episode with its observers and the query it has open this step.
struct Slot<'e> {
    index: usize,
    ep: Episode<'e, 'e>,
    w: Watchers<'e>,
    /// Wall time of this episode's own work so far (s): its stages, and its share of the
    /// batched policy calls. The episode's record reports this as its total, not the time
    /// since it started, which would count the other episodes of the lockstep batch.
    busy_s: f64,
    pending: Option<Pending>,
    error: Option<RolloutError>,
}

impl Slot<'_> {
    /// Stages *observe* and *corrupt*.
    fn observe_and_prepare(&mut self) {
        let t = Instant::now();
        let r = self
            .ep
            .observe(&mut self.w)
            .and_then(|()| self.ep.prepare(&mut self.w));
        match r {
            Ok(p) => self.pending = p,
            Err(e) => self.error = Some(e),
        }
        self.busy_s += t.elapsed().as_secs_f64();
    }

    /// The rest of the step, given the answer to this step's query (if it had one).
    fn accept_and_act(&mut self, chunk: Option<Result<Vec<f32>, RolloutError>>) {
        if self.error.is_some() {
            return;
        }
        let t = Instant::now();
        let r = (|| {
            if let (Some(p), Some(chunk)) = (self.pending.take(), chunk) {
                let event = self.ep.accept(&p, chunk?, &mut self.w)?;
                self.w.on_query(&event);
            }
            self.ep.act(&mut self.w)
        })();
        if let Err(e) = r {
            self.error = Some(e);
        }
        self.busy_s += t.elapsed().as_secs_f64();
    }
}

/// Hands every finished episode (over, or failed) to `on_done`.
fn retire(live: &mut Vec<Slot<'_>>, on_done: &mut OnDone<'_>) {
    let mut k = 0;
    while k < live.len() {
        if live[k].error.is_some() || live[k].ep.over() {
            let s = live.remove(k);
            let result = match s.error {
                Some(e) => Err(e),
                None => Ok(s.ep.record(s.w, s.busy_s)),
            };
            on_done(s.index, result);
        } else {
            k += 1;
        }
    }
}

/// The policy's answers to this step's open queries, one batch for the plain queries and
/// one per PGD setting for the attacked ones; `None` for a slot without a query.
fn answer(
    policy: &dyn ChunkPolicy,
    live: &mut [Slot<'_>],
) -> Vec<Option<Result<Vec<f32>, RolloutError>>> {
    let mut out: Vec<Option<Result<Vec<f32>, RolloutError>>> =
        (0..live.len()).map(|_| None).collect();
    let mut groups: Vec<(Option<PgdConfig>, Vec<usize>)> = Vec::new();
    for (k, s) in live.iter().enumerate() {
        let Some(p) = &s.pending else { continue };
        let key = p.attack().cloned();
        match groups.iter_mut().find(|(c, _)| *c == key) {
            Some((_, members)) => members.push(k),
            None => groups.push((key, vec![k])),
        }
    }
    for (attack, members) in groups {
        let pending: Vec<&Pending> = members
            .iter()
            .filter_map(|&k| live[k].pending.as_ref())
            .collect();
        let t = Instant::now();
        let answers = batch(policy, &pending, attack.as_ref());
        let share = t.elapsed().as_secs_f64() / members.len() as f64;
        let stage = pending[0].stage();
        for (&k, a) in members.iter().zip(answers) {
            live[k].w.on_stage(stage, share);
            live[k].busy_s += share;
            out[k] = Some(a);
        }
    }
    out
}

/// One batched call for `pending` (all plain, or all attacked with `attack`); if the batch
/// fails as a whole, each query is asked alone from the same streams, so the error lands on
/// the episode that caused it.
fn batch(
    policy: &dyn ChunkPolicy,
    pending: &[&Pending],
    attack: Option<&PgdConfig>,
) -> Vec<Result<Vec<f32>, RolloutError>> {
    let mut streams: Vec<(ChaCha8Rng, ChaCha8Rng)> = pending.iter().map(|p| p.streams()).collect();
    let together: Result<Vec<Vec<f32>>, PolicyError> = match attack {
        Some(cfg) => mte_policy::attackable(policy).and_then(|a| {
            let mut qs: Vec<AttackedQuery<'_>> = pending
                .iter()
                .zip(streams.iter_mut())
                .map(|(p, (c, s))| AttackedQuery {
                    history: p.window(),
                    attack_rng: c,
                    sample_rng: s,
                })
                .collect();
            a.predict_chunks_attacked(&mut qs, cfg)
        }),
        None => {
            let mut qs: Vec<Query<'_>> = pending
                .iter()
                .zip(streams.iter_mut())
                .map(|(p, (_, s))| Query {
                    history: p.window(),
                    rng: s,
                })
                .collect();
            policy.predict_chunks(&mut qs)
        }
    };
    match together {
        Ok(chunks) if chunks.len() == pending.len() => chunks.into_iter().map(Ok).collect(),
        _ => pending
            .iter()
            .map(|p| p.answer_alone(policy).map_err(RolloutError::from))
            .collect(),
    }
}
