//! A scripted PushT expert: sampling-based model-predictive control over push primitives,
//! using the simulator itself as the model.
//!
//! A **push primitive** is: leave the block's neighbourhood radially, travel around it on a
//! circle, come in radially to a pre-contact point `c + n (r + clearance)` outside a point `c`
//! of the T's outline with outward normal `n`, then push along `-n` until the agent's centre
//! is `length` px past first touch, and hold. Candidates are every outline point at
//! `contact_spacing` px times every push length. Each candidate is rolled out in a copy of
//! the environment from the current [`Snapshot`]; the one whose final block pose is closest
//! to the goal (position error of the centre of gravity plus `angle_weight` x angle error,
//! squared, plus `step_cost` per step) is executed; then the expert plans again.
//!
//! The expert is deterministic: the same state gives the same plan (no randomness at all
//! unless `action_noise` > 0, which draws from the RNG passed in, for demonstration
//! diversity).

use std::collections::VecDeque;

use rand::Rng;

use crate::env::{PhysicsConfig, PushT, Snapshot};
use crate::error::SimError;
use crate::geometry::{AGENT_RADIUS, Pose};

/// The T's outline in body coordinates (counter-clockwise on screen, y down), the union of
/// the bar and the stem.
const OUTLINE: [[f64; 2]; 8] = [
    [-60.0, 0.0],
    [60.0, 0.0],
    [60.0, 30.0],
    [15.0, 30.0],
    [15.0, 120.0],
    [-15.0, 120.0],
    [-15.0, 30.0],
    [-60.0, 30.0],
];

/// Expert settings. Defaults are the ones the success figures in `BENCHMARKS.md` were measured
/// with.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ExpertConfig {
    /// Spacing of candidate contact points along the outline (px).
    pub contact_spacing: f64,
    /// Push lengths past first touch (px).
    pub push_lengths: Vec<f64>,
    /// Gap between agent and block at the pre-contact point (px).
    pub clearance: f64,
    /// Radius of the travel circle around the block's centre of gravity (px): larger than the
    /// T's bounding radius (76.5) plus the agent's (15).
    pub orbit_radius: f64,
    /// Largest target displacement per control step while travelling (px).
    pub travel_step: f64,
    /// Target displacement per control step while pushing (px).
    pub push_step: f64,
    /// Control steps to hold the final push target.
    pub hold_steps: usize,
    /// Weight of the angle error (px per rad) in the pose cost.
    pub angle_weight: f64,
    /// Cost per executed control step (px^2), so equal outcomes prefer shorter plans.
    pub step_cost: f64,
    /// Standard deviation of uniform noise added to executed targets (px); 0 = none.
    pub action_noise: f64,
    /// Whether a plan made while the agent is already inside a contact's push corridor (within
    /// half a `contact_spacing` of the push line, between the pre-contact point and the
    /// longest push's end) continues that push from where the agent is, instead of backing
    /// out to approach again. Off for the demonstrations (the expert commits to each
    /// primitive and re-plans only when it ends, so it never plans mid-push); on for an
    /// expert that re-plans at every query from the observation alone.
    #[serde(default)]
    pub resume_pushes: bool,
}

impl Default for ExpertConfig {
    fn default() -> Self {
        ExpertConfig {
            contact_spacing: 7.5,
            push_lengths: vec![2.0, 6.0, 15.0, 35.0],
            clearance: 4.0,
            orbit_radius: 100.0,
            travel_step: 45.0,
            push_step: 8.0,
            hold_steps: 2,
            angle_weight: 60.0,
            step_cost: 0.5,
            action_noise: 0.0,
            resume_pushes: false,
        }
    }
}

/// A rejected [`ExpertConfig`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ExpertConfigError {
    /// A field outside its valid range.
    #[error("expert config field `{field}` = {value}: expected {expected}")]
    Field {
        /// Field name.
        field: &'static str,
        /// Offending value.
        value: f64,
        /// What was expected.
        expected: &'static str,
    },
}

impl ExpertConfig {
    /// Check every field.
    pub fn validate(&self) -> Result<(), ExpertConfigError> {
        let pos = |field, value: f64| {
            if value.is_finite() && value > 0.0 {
                Ok(())
            } else {
                Err(ExpertConfigError::Field {
                    field,
                    value,
                    expected: "a finite number > 0",
                })
            }
        };
        pos("contact_spacing", self.contact_spacing)?;
        pos("orbit_radius", self.orbit_radius)?;
        pos("travel_step", self.travel_step)?;
        pos("push_step", self.push_step)?;
        pos("angle_weight", self.angle_weight)?;
        if self.push_lengths.is_empty() {
            return Err(ExpertConfigError::Field {
                field: "push_lengths",
                value: 0.0,
                expected: "at least one push length",
            });
        }
        for &l in &self.push_lengths {
            pos("push_lengths", l)?;
        }
        for (field, v) in [
            ("clearance", self.clearance),
            ("step_cost", self.step_cost),
            ("action_noise", self.action_noise),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(ExpertConfigError::Field {
                    field,
                    value: v,
                    expected: "a finite number >= 0",
                });
            }
        }
        Ok(())
    }
}

/// The pose error the expert minimises: squared distance of the centres of gravity plus
/// (`angle_weight` x wrapped angle difference)^2, in px^2.
pub fn pose_cost(block: &Pose, goal: &Pose, angle_weight: f64) -> f64 {
    let (b, g) = (block.cog(), goal.cog());
    let da = wrap_angle(block.theta - goal.theta);
    (b[0] - g[0]).powi(2) + (b[1] - g[1]).powi(2) + (angle_weight * da).powi(2)
}

fn wrap_angle(a: f64) -> f64 {
    let t = (a + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU);
    t - std::f64::consts::PI
}

/// A candidate contact: point and outward normal in body coordinates.
#[derive(Clone, Copy, Debug)]
struct Contact {
    point: [f64; 2],
    normal: [f64; 2],
}

fn contacts(spacing: f64) -> Vec<Contact> {
    let mut out = Vec::new();
    for i in 0..OUTLINE.len() {
        let a = OUTLINE[i];
        let b = OUTLINE[(i + 1) % OUTLINE.len()];
        let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
        let len = dx.hypot(dy);
        // Outline runs clockwise in the math sense (y down, listed left-to-right along the top),
        // so the outward normal is (dy, -dx) / len.
        let normal = [dy / len, -dx / len];
        // Keep away from the corners by half a spacing; at least one point per edge.
        let n = ((len / spacing).floor() as usize).max(1);
        for k in 0..n {
            let t = (k as f64 + 0.5) / n as f64;
            out.push(Contact {
                point: [a[0] + t * dx, a[1] + t * dy],
                normal,
            });
        }
    }
    out
}

/// The scripted expert. Call [`Expert::act`] once per control step.
pub struct Expert {
    config: ExpertConfig,
    contacts: Vec<Contact>,
    plan: VecDeque<[f64; 2]>,
    model: PushT,
    scratch: Vec<[f64; 2]>,
}

impl Expert {
    /// A new expert; the configuration is validated.
    pub fn new(config: ExpertConfig) -> Result<Self, ExpertConfigError> {
        config.validate()?;
        let contacts = contacts(config.contact_spacing);
        Ok(Expert {
            config,
            contacts,
            plan: VecDeque::new(),
            model: PushT::new(PhysicsConfig::default()),
            scratch: Vec::new(),
        })
    }

    /// The configuration.
    pub fn config(&self) -> &ExpertConfig {
        &self.config
    }

    /// The targets of the plan in progress still to execute, next first (empty when the next
    /// [`Expert::act`] plans anew). Its last target is where the committed primitive ends.
    pub fn planned(&self) -> impl ExactSizeIterator<Item = &[f64; 2]> {
        self.plan.iter()
    }

    /// Forget the current plan (call after a reset).
    pub fn reset(&mut self) {
        self.plan.clear();
    }

    /// The next agent target for `env`. `rng` is used only when `action_noise` > 0.
    pub fn act<R: Rng + ?Sized>(&mut self, env: &PushT, rng: &mut R) -> Result<[f64; 2], SimError> {
        if self.plan.is_empty() {
            self.replan(env)?;
        }
        let mut a = self.plan.pop_front().unwrap_or_else(|| env.agent_pos());
        if self.config.action_noise > 0.0 {
            let s = self.config.action_noise;
            a[0] += rng.random_range(-s..=s);
            a[1] += rng.random_range(-s..=s);
        }
        Ok(a)
    }

    /// Plan the best primitive from the current state.
    fn replan(&mut self, env: &PushT) -> Result<(), SimError> {
        let snap = env.snapshot();
        let goal = env.goal();
        let mut best: Option<(f64, Vec<[f64; 2]>)> = None;
        let lengths = self.config.push_lengths.clone();
        for ci in 0..self.contacts.len() {
            let contact = self.contacts[ci];
            // Approach once, then branch the push lengths from its end state.
            let mut approach = std::mem::take(&mut self.scratch);
            approach.clear();
            let resumed = self.resumed_depth(&snap, contact);
            if resumed.is_none() {
                self.approach_targets(&snap, contact, &mut approach);
            }
            let start = resumed.unwrap_or(self.config.clearance + AGENT_RADIUS);
            self.model.restore(&snap)?;
            for a in &approach {
                self.model.step(*a)?;
            }
            let after_approach = self.model.snapshot();
            let block = after_approach.state.block;
            for &len in &lengths {
                if AGENT_RADIUS - len >= start {
                    continue; // a resumed push already past this length
                }
                let mut targets = approach.clone();
                self.push_targets(&block, contact, start, len, &mut targets);
                self.model.restore(&after_approach)?;
                let mut success = false;
                for a in &targets[approach.len()..] {
                    if self.model.step(*a)?.is_success {
                        success = true;
                        break;
                    }
                }
                let mut cost = pose_cost(&self.model.block_pose(), &goal, self.config.angle_weight)
                    + self.config.step_cost * targets.len() as f64;
                if success {
                    cost = -1.0 / targets.len() as f64;
                }
                if best.as_ref().is_none_or(|(c, _)| cost < *c) {
                    best = Some((cost, targets));
                }
            }
            self.scratch = approach;
        }
        if let Some((_, targets)) = best {
            self.plan.extend(targets);
        }
        Ok(())
    }

    /// Targets that bring the agent from where it is to the pre-contact point of `contact`
    /// without crossing the block: out to the orbit circle, around it, and in.
    fn approach_targets(&self, snap: &Snapshot, contact: Contact, out: &mut Vec<[f64; 2]>) {
        let block = snap.state.block;
        let cog = block.cog();
        let pre_body = [
            contact.point[0] + contact.normal[0] * (AGENT_RADIUS + self.config.clearance),
            contact.point[1] + contact.normal[1] * (AGENT_RADIUS + self.config.clearance),
        ];
        let pre = block.apply(pre_body);
        let agent = snap.state.agent;
        let r = self.config.orbit_radius;
        let ang = |p: [f64; 2]| (p[1] - cog[1]).atan2(p[0] - cog[0]);
        let dist = |p: [f64; 2]| (p[0] - cog[0]).hypot(p[1] - cog[1]);
        let on_circle = |a: f64| [cog[0] + r * a.cos(), cog[1] + r * a.sin()];
        let step = self.config.travel_step;
        let mut at = agent;
        let mut go = |out: &mut Vec<[f64; 2]>, to: [f64; 2]| {
            let d = (to[0] - at[0]).hypot(to[1] - at[1]);
            let n = (d / step).ceil().max(1.0) as usize;
            for k in 1..=n {
                let t = k as f64 / n as f64;
                out.push([at[0] + t * (to[0] - at[0]), at[1] + t * (to[1] - at[1])]);
            }
            at = to;
        };
        // Straight in when the agent is already on the pre-contact side and close.
        let (a0, a1) = (ang(agent), ang(pre));
        let da = wrap_angle(a1 - a0);
        let direct = (agent[0] - pre[0]).hypot(agent[1] - pre[1]) < 1.0
            || (da.abs() < 0.35 && dist(agent) >= dist(pre));
        if !direct {
            if dist(agent) < r {
                go(out, on_circle(a0));
            }
            // Around the circle in arcs of at most `step` px.
            let arc_steps = ((da.abs() * r) / step).ceil() as usize;
            for k in 1..=arc_steps {
                let a = a0 + da * k as f64 / arc_steps as f64;
                go(out, on_circle(a));
            }
        }
        go(out, pre);
    }

    /// With [`ExpertConfig::resume_pushes`], the agent's offset along `contact`'s outward
    /// normal (px from the outline, the agent's centre) when it is inside that contact's push
    /// corridor; `None` otherwise.
    fn resumed_depth(&self, snap: &Snapshot, contact: Contact) -> Option<f64> {
        if !self.config.resume_pushes {
            return None;
        }
        let local = snap.state.block.to_body(snap.state.agent);
        let rel = [local[0] - contact.point[0], local[1] - contact.point[1]];
        let depth = rel[0] * contact.normal[0] + rel[1] * contact.normal[1];
        let lateral = rel[0] * contact.normal[1] - rel[1] * contact.normal[0];
        let longest = self.config.push_lengths.iter().copied().fold(0.0, f64::max);
        let inside = lateral.abs() <= 0.5 * self.config.contact_spacing
            && depth <= self.config.clearance + AGENT_RADIUS
            && depth > AGENT_RADIUS - longest;
        inside.then_some(depth)
    }

    /// Push targets: from offset `start` (px along the outward normal; the pre-contact point
    /// unless a push is resumed) along `-normal` until the agent's centre is `len` px past
    /// first touch, in `push_step` increments, then hold.
    fn push_targets(
        &self,
        block: &Pose,
        contact: Contact,
        start: f64,
        len: f64,
        out: &mut Vec<[f64; 2]>,
    ) {
        let end = AGENT_RADIUS - len;
        let n = ((start - end) / self.config.push_step).ceil().max(1.0) as usize;
        let mut last = [0.0; 2];
        for k in 1..=n {
            let off = start + (end - start) * k as f64 / n as f64;
            let p = [
                contact.point[0] + contact.normal[0] * off,
                contact.point[1] + contact.normal[1] * off,
            ];
            last = block.apply(p);
            out.push(last);
        }
        for _ in 0..self.config.hold_steps {
            out.push(last);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An agent touching the stem's right side next to a contact point, the block at the goal.
    fn touching(resume_pushes: bool) -> (Expert, Snapshot, Contact) {
        let expert = Expert::new(ExpertConfig {
            resume_pushes,
            ..ExpertConfig::default()
        })
        .expect("valid");
        let contact = *expert
            .contacts
            .iter()
            .find(|c| c.normal == [1.0, 0.0] && (c.point[1] - 75.0).abs() < 4.0)
            .expect("a contact on the stem's right side");
        let block = crate::geometry::GOAL;
        let body = [contact.point[0] + AGENT_RADIUS, contact.point[1] + 1.0];
        let mut env = PushT::new(PhysicsConfig::default());
        env.reset_to_pose(crate::env::State {
            agent: block.apply(body),
            block,
        })
        .expect("reset");
        (expert, env.snapshot(), contact)
    }

    #[test]
    fn a_push_is_resumed_only_from_inside_its_corridor() {
        let (expert, snap, contact) = touching(true);
        let depth = expert
            .resumed_depth(&snap, contact)
            .expect("inside the corridor");
        assert!((depth - AGENT_RADIUS).abs() < 0.5, "depth {depth}");
        let (off, _, _) = touching(false);
        assert_eq!(off.resumed_depth(&snap, contact), None, "off by default");
        // Far from the block: no corridor.
        let mut away = snap;
        away.state.agent = [20.0, 20.0];
        assert_eq!(expert.resumed_depth(&away, contact), None);
        // Beside the corridor (a full contact spacing along the edge).
        let mut beside = snap;
        let p = snap
            .state
            .block
            .apply([contact.point[0] + AGENT_RADIUS, contact.point[1] + 8.0]);
        beside.state.agent = p;
        assert_eq!(expert.resumed_depth(&beside, contact), None);
    }

    #[test]
    fn a_resumed_push_starts_where_the_agent_is_and_moves_inward() {
        let (expert, snap, contact) = touching(true);
        let depth = expert.resumed_depth(&snap, contact).expect("inside");
        let block = snap.state.block;
        let mut out = Vec::new();
        expert.push_targets(&block, contact, depth, 15.0, &mut out);
        let agent = snap.state.agent;
        let first = (out[0][0] - agent[0]).hypot(out[0][1] - agent[1]);
        assert!(
            first <= expert.config.push_step + 1.5,
            "first target {first} px away"
        );
        // Each target deeper along -normal than the last, until the hold.
        let n = out.len() - expert.config.hold_steps;
        // Body x: the stem's right side has normal +x.
        let along = |p: [f64; 2]| block.to_body(p)[0];
        for w in out[..n].windows(2) {
            assert!(along(w[1]) < along(w[0]), "{w:?}");
        }
        assert!((along(out[n - 1]) - (contact.point[0] + AGENT_RADIUS - 15.0)).abs() < 1e-9);
    }
}
