//! The scripted PushT expert as a chunked policy: the noise-free reference of every aggregator
//! experiment.
//!
//! At each query the expert is asked, from the observation alone, what it would do for the
//! next `T_p - T_o + 1` control steps: the simulator state is rebuilt from the newest
//! observation, a fresh [`Expert`] (no memory of earlier plans) plans from it, and its targets
//! are rolled out in that private copy. The chunk is therefore a deterministic function of the
//! observations, with no sampling noise at all; whatever its consecutive chunks disagree on
//! comes from the task and the expert's discrete choices (which contact to push, for how
//! long), re-made from a newer state at every query. This is the limit a perfectly trained
//! Diffusion Policy imitating the expert approaches, minus the multimodality that sampling
//! adds; comparing aggregators on it separates what the task does to the mean from what a
//! learned policy's sampling does.
//!
//! Rebuilding the state: the block pose is fitted to the 16 keypoints (a 2-D Procrustes fit,
//! exact up to the observations' f32 rounding); the agent position is the robot state; the
//! agent velocity, which the observation does not carry, is estimated as the displacement
//! between the last two observations over one control period (zero at the first query); the
//! physics world's block is placed at the observed pose (the real world's is one substep
//! ahead, see [`mte_sim::env`]). The copy therefore differs slightly from the real
//! environment: the same expert acting in the real environment commits to its primitive,
//! this one re-plans at every query from an approximate state.
//!
//! Row `r` of a chunk is the action for control time `t - (T_o - 1) + r`: row 0 (the past
//! step, never executed) repeats the first planned target.

use std::str::FromStr;

use mte_policy::error::config_err;
use mte_policy::{ChunkPolicy, ObsNeeds, Observation, PolicyError};
use mte_sim::expert::{Expert, ExpertConfig};
use mte_sim::geometry::{BAR, CONTROL_HZ, STEM};
use mte_sim::{PhysicsConfig, Pose, PushT, Snapshot, State};
use rand::RngCore;

fn input_err(name: &'static str, reason: impl Into<String>) -> PolicyError {
    PolicyError::Input {
        name,
        reason: reason.into(),
    }
}

/// The policy name sweeps and `mte eval policy --checkpoint` accept for the expert.
pub const EXPERT_POLICY: &str = "expert:pusht";

/// The chunk geometry and expert settings of [`PushTExpertPolicy`].
#[derive(Clone, Debug, PartialEq)]
pub struct ExpertPolicyConfig {
    /// Rows per chunk (`T_p`); Diffusion Policy's PushT value by default.
    pub horizon: usize,
    /// Observations per query (`T_o`); the last two give the agent's velocity.
    pub n_obs_steps: usize,
    /// The expert's settings.
    pub expert: ExpertConfig,
}

impl Default for ExpertPolicyConfig {
    /// `T_p` 16 and `T_o` 2 (Diffusion Policy on PushT), and the expert as it made the
    /// demonstrations of every bundled PushT policy (`mte data generate --travel-step 20
    /// --push-step 6`; the other settings at their defaults) except that it resumes a push
    /// it finds itself in ([`ExpertConfig::resume_pushes`]): re-planning at every query, the
    /// demonstrating expert would back out of every push it had started and never finish one
    /// (measured: mean max coverage 0.11 on 13 seeds executing the newest chunk at h = 2).
    fn default() -> Self {
        Self {
            horizon: 16,
            n_obs_steps: 2,
            expert: ExpertConfig {
                travel_step: 20.0,
                push_step: 6.0,
                resume_pushes: true,
                ..ExpertConfig::default()
            },
        }
    }
}

/// The scripted PushT expert behind the [`ChunkPolicy`] seam (module docs).
#[derive(Clone, Debug)]
pub struct PushTExpertPolicy {
    config: ExpertPolicyConfig,
}

impl PushTExpertPolicy {
    /// The expert with `config`.
    ///
    /// # Errors
    /// [`PolicyError::Config`] for `T_o` outside `1..=T_p` or an invalid expert setting.
    pub fn new(config: ExpertPolicyConfig) -> Result<Self, PolicyError> {
        if config.n_obs_steps == 0 || config.n_obs_steps > config.horizon {
            return Err(config_err(
                "n_obs_steps",
                config.n_obs_steps,
                format!("between 1 and the horizon {}", config.horizon),
            ));
        }
        config
            .expert
            .validate()
            .map_err(|e| config_err("expert", &config.expert, e.to_string()))?;
        Ok(Self { config })
    }

    /// The configuration.
    pub fn config(&self) -> &ExpertPolicyConfig {
        &self.config
    }
}

impl FromStr for PushTExpertPolicy {
    type Err = PolicyError;

    /// [`EXPERT_POLICY`], optionally with settings after a `?`:
    /// `expert:pusht?travel_step=10&push_step=4&resume_pushes=false&horizon=16` (the expert's
    /// step sizes in px, [`ExpertConfig::resume_pushes`], the chunk's `T_p`); unnamed settings
    /// keep [`ExpertPolicyConfig::default`].
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let (name, query) = s.split_once('?').unwrap_or((s, ""));
        if name != EXPERT_POLICY {
            return Err(config_err(
                "policy",
                s,
                format!("`{EXPERT_POLICY}[?key=value&...]`"),
            ));
        }
        let mut config = ExpertPolicyConfig::default();
        for pair in query.split('&').filter(|p| !p.is_empty()) {
            let (key, value) = pair.split_once('=').unwrap_or((pair, ""));
            let number = |expected: &str| {
                value
                    .parse::<f64>()
                    .map_err(|_| config_err("policy", pair, expected.to_string()))
            };
            match key {
                "travel_step" => config.expert.travel_step = number("travel_step=<px>")?,
                "push_step" => config.expert.push_step = number("push_step=<px>")?,
                "resume_pushes" => {
                    config.expert.resume_pushes = value
                        .parse()
                        .map_err(|_| config_err("policy", pair, "resume_pushes=true|false"))?;
                }
                "horizon" => {
                    config.horizon = value
                        .parse()
                        .map_err(|_| config_err("policy", pair, "horizon=<rows>"))?;
                }
                _ => {
                    return Err(config_err(
                        "policy",
                        pair,
                        "one of travel_step, push_step, resume_pushes, horizon",
                    ));
                }
            }
        }
        Self::new(config)
    }
}

/// Whether `name` names the expert ([`EXPERT_POLICY`], with or without settings).
pub fn is_expert_policy(name: &str) -> bool {
    name.split_once('?').map_or(name, |(n, _)| n) == EXPERT_POLICY
}

/// The block pose whose keypoints best fit `kp` (least squares over the 8 vertices).
pub fn pose_from_keypoints(kp: &[f32]) -> Result<Pose, PolicyError> {
    if kp.len() != 16 || !kp.iter().all(|v| v.is_finite()) {
        return Err(input_err(
            "env_state",
            format!(
                "{} values {kp:?}: expected 16 finite block keypoints (px)",
                kp.len()
            ),
        ));
    }
    let body: Vec<[f64; 2]> = BAR.iter().chain(STEM.iter()).copied().collect();
    let world: Vec<[f64; 2]> = kp
        .chunks_exact(2)
        .map(|p| [f64::from(p[0]), f64::from(p[1])])
        .collect();
    let centre = |ps: &[[f64; 2]]| {
        let n = ps.len() as f64;
        let (x, y) = ps.iter().fold((0.0, 0.0), |(x, y), p| (x + p[0], y + p[1]));
        [x / n, y / n]
    };
    let (cb, cw) = (centre(&body), centre(&world));
    let (mut dot, mut cross) = (0.0, 0.0);
    for (b, w) in body.iter().zip(&world) {
        let (bx, by) = (b[0] - cb[0], b[1] - cb[1]);
        let (wx, wy) = (w[0] - cw[0], w[1] - cw[1]);
        dot += bx * wx + by * wy;
        cross += bx * wy - by * wx;
    }
    let theta = cross.atan2(dot);
    let (s, c) = theta.sin_cos();
    Ok(Pose {
        x: cw[0] - (c * cb[0] - s * cb[1]),
        y: cw[1] - (s * cb[0] + c * cb[1]),
        theta,
    })
}

/// The snapshot the expert plans from: the newest observation's state, the velocity from the
/// last two observations.
fn snapshot(history: &[Observation]) -> Result<Snapshot, PolicyError> {
    let newest = history
        .last()
        .ok_or_else(|| input_err("history", "empty: expected at least one observation"))?;
    let agent = |o: &Observation| -> Result<[f64; 2], PolicyError> {
        match o.state.as_slice() {
            [x, y] if x.is_finite() && y.is_finite() => Ok([f64::from(*x), f64::from(*y)]),
            other => Err(input_err(
                "state",
                format!("{other:?}: expected the agent position, 2 finite values (px)"),
            )),
        }
    };
    let kp = newest
        .env_state
        .as_deref()
        .ok_or_else(|| input_err("env_state", "missing: expected the 16 block keypoints"))?;
    let block = pose_from_keypoints(kp)?;
    let now = agent(newest)?;
    let period = 1.0 / CONTROL_HZ;
    let agent_vel = match history.len() {
        0 | 1 => [0.0; 2],
        n => {
            let before = agent(&history[n - 2])?;
            [(now[0] - before[0]) / period, (now[1] - before[1]) / period]
        }
    };
    Ok(Snapshot {
        state: State { agent: now, block },
        agent_vel,
        physics_block: block,
        steps: 0,
    })
}

impl ChunkPolicy for PushTExpertPolicy {
    fn horizon(&self) -> usize {
        self.config.horizon
    }

    fn n_obs_steps(&self) -> usize {
        self.config.n_obs_steps
    }

    fn action_dim(&self) -> usize {
        2
    }

    fn needs(&self) -> ObsNeeds {
        ObsNeeds {
            env_state: true,
            image: None,
            wrist_image: false,
        }
    }

    /// Plans from the rebuilt state and rolls the plan out for the executable rows. `rng` is
    /// not used: the expert has no randomness (its `action_noise` is 0 here unless set).
    fn predict_chunk(
        &self,
        history: &[Observation],
        rng: &mut dyn RngCore,
    ) -> Result<Vec<f32>, PolicyError> {
        let snap = snapshot(history)?;
        let sim = |e: mte_sim::SimError| input_err("state", format!("the expert's rollout: {e}"));
        let mut env = PushT::new(PhysicsConfig::default());
        env.restore(&snap).map_err(sim)?;
        let mut expert = Expert::new(self.config.expert.clone())
            .map_err(|e| config_err("expert", &self.config.expert, e.to_string()))?;
        let (t_p, t_o) = (self.config.horizon, self.config.n_obs_steps);
        let mut rows = Vec::with_capacity(t_p);
        for _ in 0..=t_p - t_o {
            let a = expert.act(&env, rng).map_err(sim)?;
            env.step(a).map_err(sim)?;
            rows.push([a[0] as f32, a[1] as f32]);
        }
        let mut chunk = Vec::with_capacity(2 * t_p);
        for _ in 0..t_o - 1 {
            chunk.extend_from_slice(&rows[0]);
        }
        for r in &rows {
            chunk.extend_from_slice(r);
        }
        Ok(chunk)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn obs(env: &PushT) -> Observation {
        let a = env.agent_pos();
        Observation {
            state: vec![a[0] as f32, a[1] as f32],
            env_state: Some(env.keypoints().iter().map(|&v| v as f32).collect()),
            image: None,
            wrist_image: None,
        }
    }

    #[test]
    fn the_keypoint_fit_recovers_the_pose() {
        for (x, y, theta) in [
            (256.0, 300.0, 0.0),
            (100.5, 420.25, 2.5),
            (400.0, 80.0, -1.2),
        ] {
            let p = Pose { x, y, theta };
            let kp: Vec<f32> = p.keypoints().iter().map(|&v| v as f32).collect();
            let q = pose_from_keypoints(&kp).unwrap();
            // f32 keypoints near 500 px carry ~3e-5 px of rounding.
            assert!(
                (q.x - x).abs() < 1e-3 && (q.y - y).abs() < 1e-3,
                "{q:?} vs {p:?}"
            );
            let dtheta = (q.theta - theta).sin().abs();
            assert!(dtheta < 1e-5, "{q:?} vs {p:?}");
        }
    }

    #[test]
    fn bad_keypoints_are_typed_errors() {
        assert!(pose_from_keypoints(&[0.0; 15]).is_err());
        let mut kp = [1.0f32; 16];
        kp[3] = f32::NAN;
        assert!(pose_from_keypoints(&kp).is_err());
    }

    /// At a reset the agent is still, so the rebuilt state is the real one up to rounding:
    /// the chunk's executable rows must be the targets the expert produces acting in the real
    /// environment.
    #[test]
    fn at_rest_the_chunk_is_what_the_expert_does() {
        let policy = PushTExpertPolicy::from_str(EXPERT_POLICY).unwrap();
        let mut env = PushT::new(PhysicsConfig::default());
        env.reset(100_003, mte_sim::ResetStream::Legacy).unwrap();
        let history = vec![obs(&env), obs(&env)];
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let chunk = policy.predict_chunk(&history, &mut rng).unwrap();
        assert_eq!(chunk.len(), 32);
        let mut expert = Expert::new(policy.config().expert.clone()).unwrap();
        for r in 1..16 {
            let a = expert.act(&env, &mut rng).unwrap();
            env.step(a).unwrap();
            let (cx, cy) = (f64::from(chunk[2 * r]), f64::from(chunk[2 * r + 1]));
            assert!(
                (cx - a[0]).abs() < 0.05 && (cy - a[1]).abs() < 0.05,
                "row {r}: chunk ({cx}, {cy}) vs expert {a:?}"
            );
        }
        assert_eq!(chunk[0..2], chunk[2..4], "row 0 repeats the first target");
    }

    #[test]
    fn sweeps_load_the_expert_by_name() {
        use crate::sweep::PolicySource as _;
        let p = crate::sweep::CheckpointSource.load(EXPERT_POLICY).unwrap();
        assert_eq!((p.horizon(), p.n_obs_steps(), p.action_dim()), (16, 2, 2));
        assert!(p.needs().env_state && p.needs().image.is_none());
        assert!(
            p.attackable().is_none(),
            "the expert has no gradient to attack"
        );
        assert!(
            crate::sweep::CheckpointSource
                .load("expert:pusht2")
                .is_err()
        );
    }

    #[test]
    fn settings_parse_and_bad_ones_are_named() {
        let p: PushTExpertPolicy =
            "expert:pusht?travel_step=10&push_step=4&horizon=12&resume_pushes=false"
                .parse()
                .unwrap();
        assert!(!p.config().expert.resume_pushes);
        assert!(
            PushTExpertPolicy::from_str(EXPERT_POLICY)
                .unwrap()
                .config()
                .expert
                .resume_pushes
        );
        assert_eq!(p.config().expert.travel_step, 10.0);
        assert_eq!(p.config().expert.push_step, 4.0);
        assert_eq!(p.config().horizon, 12);
        for bad in [
            "expert:pusht?travel_step=fast",
            "expert:pusht?speed=3",
            "expert:pusht?push_step=-1",
            "expert:pusht?horizon=1",
            "expert:pusht?resume_pushes=yes",
        ] {
            let e = bad.parse::<PushTExpertPolicy>().unwrap_err().to_string();
            assert!(e.contains("expected"), "{bad}: {e}");
        }
        assert!(is_expert_policy("expert:pusht?push_step=4"));
        assert!(!is_expert_policy("assets/policies/expert"));
    }

    #[test]
    fn only_the_reserved_name_parses() {
        assert!(PushTExpertPolicy::from_str("expert:other").is_err());
        assert!(
            PushTExpertPolicy::new(ExpertPolicyConfig {
                n_obs_steps: 0,
                ..ExpertPolicyConfig::default()
            })
            .is_err()
        );
    }
}
