//! Whole episodes driven without a learned policy (the scripted expert or uniform random
//! targets), and the environment's throughput as `mte sim bench` measures it.
//!
//! Units: actions are target positions in pixels of the 512 x 512 workspace; a step is one
//! 10 Hz control step.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::render::Renderer;
use crate::{Expert, PushT, ResetStream, SimError};

/// What drives the agent.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Driver {
    /// The scripted push-primitive MPC expert ([`Expert`]).
    Expert,
    /// Uniform random targets in `[0, 512]^2` (the peer benchmark's workload).
    Random,
}

/// How one episode ended.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct RolloutOutcome {
    /// Reset seed.
    pub seed: u64,
    /// Whether coverage reached the success threshold.
    pub success: bool,
    /// Control steps taken.
    pub steps: usize,
    /// Highest coverage seen, the reset state included.
    pub max_coverage: f64,
}

/// Runs one episode from `seed` for at most `max_steps` steps. `on_state` sees the
/// environment after the reset (action `None`) and after every step (the action taken);
/// its error ends the episode. The driver's randomness is seeded from `seed`.
pub fn rollout<E, F>(
    env: &mut PushT,
    expert: &mut Expert,
    driver: Driver,
    seed: u64,
    stream: ResetStream,
    max_steps: usize,
    mut on_state: F,
) -> Result<RolloutOutcome, E>
where
    E: From<SimError>,
    F: FnMut(&PushT, Option<[f64; 2]>) -> Result<(), E>,
{
    env.reset(seed, stream)?;
    expert.reset();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut out = RolloutOutcome {
        seed,
        success: false,
        steps: 0,
        max_coverage: env.coverage(),
    };
    on_state(env, None)?;
    while out.steps < max_steps && !out.success {
        let action = match driver {
            Driver::Expert => expert.act(env, &mut rng)?,
            Driver::Random => [rng.random_range(0.0..512.0), rng.random_range(0.0..512.0)],
        };
        let info = env.step(action)?;
        out.steps += 1;
        out.max_coverage = out.max_coverage.max(info.coverage);
        out.success = info.is_success;
        on_state(env, Some(action))?;
    }
    Ok(out)
}

/// A failure while measuring throughput.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// The simulator failed.
    #[error(transparent)]
    Sim(#[from] SimError),
    /// The renderer failed.
    #[error(transparent)]
    Render(#[from] crate::render::RenderError),
}

/// Steps per second of one environment on one thread under uniform random targets, a reset
/// every 300 steps (one gym-pusht episode), rendering a 96 x 96 observation per step when
/// `pixels`. The actions are drawn before the clock starts.
pub fn steps_per_second(steps: usize, pixels: bool) -> Result<f64, BenchError> {
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let actions: Vec<[f64; 2]> = (0..steps)
        .map(|_| [rng.random_range(0.0..512.0), rng.random_range(0.0..512.0)])
        .collect();
    let mut env = PushT::default();
    let mut r = Renderer::new(env.goal());
    let mut img = vec![0u8; 96 * 96 * 3];
    let mut seed = 0;
    let t0 = std::time::Instant::now();
    for (i, act) in actions.iter().enumerate() {
        if i % 300 == 0 {
            seed += 1;
            env.reset(seed, ResetStream::Pcg64)?;
        }
        env.step(*act)?;
        if pixels {
            r.observation_with_contacts_into(
                &env.scene(),
                env.contact_segments(),
                96,
                96,
                &mut img,
            )?;
        }
    }
    Ok(steps as f64 / t0.elapsed().as_secs_f64())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ExpertConfig;

    #[test]
    fn a_rollout_reports_every_state_and_is_seeded() {
        let run = |driver| {
            let (mut env, mut expert) = (
                PushT::default(),
                Expert::new(ExpertConfig::default()).expect("expert"),
            );
            let mut seen = Vec::new();
            let out = rollout::<SimError, _>(
                &mut env,
                &mut expert,
                driver,
                5,
                ResetStream::Legacy,
                20,
                |_, a| {
                    seen.push(a);
                    Ok(())
                },
            )
            .expect("rollout");
            (out, seen)
        };
        let (out, seen) = run(Driver::Random);
        assert_eq!(seen.len(), out.steps + 1, "the reset and every step");
        assert_eq!(seen[0], None);
        assert!(out.steps <= 20 && (out.success || out.steps == 20));
        assert!((0.0..=1.0).contains(&out.max_coverage));
        assert_eq!(run(Driver::Random), (out, seen), "same seed, same episode");
        let (e, _) = run(Driver::Expert);
        assert!(e.steps >= 1 && e.seed == 5);
    }
}
