//! Chunked execution of a policy on PushT: the policy is queried every `h` control steps with
//! the last `T_o` observations (the first repeated at episode start, as Diffusion Policy
//! does), and its chunk is either executed open loop (`h` actions of the latest chunk, from
//! row `T_o - 1`: Diffusion Policy's and LeRobot's default) or fed to a `TemporalEnsembler`.
//! The evaluation runner with corruption, sweeps and reports builds on this (issue 6).

use mte_ensemble::{Aggregator, ChunkGeometry, EnsembleError, QueryMeta, TemporalEnsembler};
use mte_policy::{ChunkPolicy, Observation, PolicyError};
use mte_sim::render::Renderer;
use mte_sim::{PushT, ResetStream, SimError};
use rand::RngCore;

/// How chunks become actions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Execution {
    /// Execute `h` actions of the latest chunk.
    OpenLoop,
    /// Aggregate every covering chunk with an ensembler.
    Ensemble(Aggregator),
}

/// Which observations the policy reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ObsNeeds {
    /// The 16 keypoints.
    pub env_state: bool,
    /// Rendered frames of this (width, height).
    pub image: Option<(usize, usize)>,
}

/// One episode's outcome.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EpisodeOutcome {
    /// Reset seed.
    pub seed: u64,
    /// Coverage > 0.95 reached.
    pub success: bool,
    /// Maximum coverage over the episode (Diffusion Policy's score).
    pub max_coverage: f64,
    /// Control steps run.
    pub steps: usize,
}

/// Errors of a rollout.
#[derive(Debug, thiserror::Error)]
pub enum RolloutError {
    /// The simulator failed.
    #[error(transparent)]
    Sim(#[from] SimError),
    /// The policy failed.
    #[error(transparent)]
    Policy(#[from] PolicyError),
    /// The ensembler refused a chunk or a time.
    #[error(transparent)]
    Ensemble(#[from] EnsembleError),
    /// Rendering failed.
    #[error(transparent)]
    Render(#[from] mte_sim::render::RenderError),
    /// A bad setting.
    #[error("`{field}` = {value}: expected {expected}")]
    Config {
        /// Field.
        field: &'static str,
        /// Value.
        value: String,
        /// Expectation.
        expected: String,
    },
}

fn observe(
    env: &PushT,
    needs: ObsNeeds,
    renderer: &mut Option<Renderer>,
) -> Result<Observation, RolloutError> {
    let a = env.agent_pos();
    let image = match (needs.image, renderer.as_mut()) {
        (Some((w, h)), Some(r)) => {
            let mut px = vec![0u8; w * h * 3];
            r.observation_with_contacts_into(&env.scene(), env.contact_segments(), w, h, &mut px)?;
            Some(px)
        }
        _ => None,
    };
    Ok(Observation {
        state: vec![a[0] as f32, a[1] as f32],
        env_state: needs
            .env_state
            .then(|| env.keypoints().iter().map(|&v| v as f32).collect()),
        image,
    })
}

/// Run one episode from `seed`.
#[allow(clippy::too_many_arguments)]
pub fn run_episode(
    policy: &dyn ChunkPolicy,
    needs: ObsNeeds,
    seed: u64,
    stream: ResetStream,
    h: usize,
    max_steps: usize,
    execution: Execution,
    rng: &mut dyn RngCore,
) -> Result<EpisodeOutcome, RolloutError> {
    let (t_p, t_o, d) = (policy.horizon(), policy.n_obs_steps(), policy.action_dim());
    if h == 0 || h + t_o > t_p + 1 {
        return Err(RolloutError::Config {
            field: "h",
            value: h.to_string(),
            expected: format!("1..={} (T_p - T_o + 1)", t_p + 1 - t_o),
        });
    }
    let mut env = PushT::default();
    env.reset(seed, stream)?;
    let mut renderer = needs.image.map(|_| Renderer::new(env.goal()));
    let geometry = ChunkGeometry { t_p, t_o, h };
    let mut ens = match execution {
        Execution::Ensemble(a) => Some(TemporalEnsembler::new(geometry, d, a)?),
        Execution::OpenLoop => None,
    };
    let mut history: Vec<Observation> = Vec::with_capacity(t_o);
    let mut chunk = Vec::new();
    let mut max_coverage = env.coverage();
    for steps in 0..max_steps {
        // The history holds the last T_o control-rate observations, the first one repeated at
        // the start (Diffusion Policy's env wrapper records every step's observation).
        let o = observe(&env, needs, &mut renderer)?;
        if history.is_empty() {
            history = vec![o; t_o];
        } else {
            history.remove(0);
            history.push(o);
        }
        let k = steps % h;
        if k == 0 {
            chunk = policy.predict_chunk(&history, rng)?;
            if let Some(e) = ens.as_mut() {
                e.insert(steps as u64, &chunk, QueryMeta { corrupted: false })?;
            }
        }
        let action: [f64; 2] = match ens.as_mut() {
            Some(e) => {
                let s = e.action(steps as u64)?;
                [f64::from(s.action[0]), f64::from(s.action[1])]
            }
            None => {
                let r = t_o - 1 + k;
                [f64::from(chunk[r * d]), f64::from(chunk[r * d + 1])]
            }
        };
        let info = env.step(action)?;
        max_coverage = max_coverage.max(info.coverage);
        if info.is_success {
            return Ok(EpisodeOutcome {
                seed,
                success: true,
                max_coverage,
                steps: steps + 1,
            });
        }
    }
    let steps = max_steps;
    Ok(EpisodeOutcome {
        seed,
        success: false,
        max_coverage,
        steps,
    })
}
