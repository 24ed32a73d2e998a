//! The PushT environment: rapier2d physics arranged to reproduce gym-pusht's Chipmunk stepping.
//!
//! # Stepping, and how the quasi-static block is reproduced
//!
//! One control step runs [`SUBSTEPS`] substeps of [`DT`]. Each substep, as gym-pusht does:
//! the agent's velocity is updated by the PD law `v += (KP (target - p) - KV v) dt`, then the
//! physics steps. Chipmunk's step is: integrate positions with the velocities left by the
//! previous solve, detect contacts at the new positions, multiply velocities by
//! `damping^dt` (= 0: gym-pusht's `damping = 0` zeroes the block's velocity), apply contact
//! impulses. The block therefore carries no momentum: it moves, one substep later, by exactly
//! the velocity the contact impulses of one substep gave it.
//!
//! rapier's step detects contacts, solves and integrates positions in that order. We reproduce
//! Chipmunk's order with rapier as follows:
//! 1. the agent (a kinematic, velocity-based body) is moved by us to `p + v dt` before the
//!    rapier step, and its velocity `v` is given to the solver;
//! 2. the block's velocity is set to zero before every rapier step (the damping-0 effect);
//! 3. rapier solves the contacts at those positions and moves the block by the solved velocity.
//!
//! Step 3 moves the block at the end of substep k, where Chipmunk moves it at the start of
//! substep k+1: rapier's block is one substep ahead. The pose we report (and reward, and draw)
//! is therefore the block pose **before** the last rapier step, which is exactly the pose
//! Chipmunk reports; the displacement already made inside rapier is what Chipmunk would apply
//! first in the next step. The remaining differences from gym-pusht are the contact solvers
//! themselves (rapier's soft TGS against Chipmunk's PGS with bias); they are measured in
//! `BENCHMARKS.md` / the parity tests.
//!
//! Substeps where no contact is possible (agent farther from the block than its speed can
//! close, block clear of the walls) skip rapier entirely: the block cannot move and the agent
//! integrates analytically. The skip is exact: a test runs both paths and compares.

use rapier2d::prelude::*;

use crate::coverage;
use crate::error::SimError;
use crate::geometry::{
    AGENT_RADIUS, AGENT_SPAWN, BAR, BLOCK_COG, BLOCK_MASS, BLOCK_MOMENT, DT, GOAL, KP, KV,
    MAX_EPISODE_STEPS, Pose, STEM, SUBSTEPS, SUCCESS_THRESHOLD, WALL_RADIUS, WALLS,
};
use crate::render::{ContactSegment, Scene};
use crate::rng::ResetStream;

/// Largest distance from the block's centre of gravity to any of its vertices (px):
/// |(15, 120) - (0, 45)| = sqrt(15^2 + 75^2).
const BLOCK_BOUND_RADIUS: f64 = 76.485_292_703_891_77;
/// Extra clearance (px) before we call a substep contact-free; above rapier's prediction
/// distance (0.002 x length unit = 0.2 px) with a wide margin.
const SKIP_MARGIN: f64 = 4.0;
/// rapier's length unit (px): its tolerances (allowed penetration 0.001 x, prediction
/// distance 0.002 x) scale with it; 100 px puts the allowed penetration at 0.1 px, Chipmunk's
/// collision slop in gym-pusht.
const LENGTH_UNIT: f32 = 100.0;

/// The full simulator state that gym-pusht exposes and accepts: agent position and the block's
/// body-origin pose. `block.theta` is the raw (unwrapped) angle.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct State {
    /// Agent centre (px).
    pub agent: [f64; 2],
    /// Block body-origin pose.
    pub block: Pose,
}

impl State {
    /// gym-pusht's 5-vector `[agent_x, agent_y, block_x, block_y, block_angle]` with the raw
    /// angle (its `state` observation wraps the angle; see [`PushT::state_obs`]).
    pub fn to_array(&self) -> [f64; 5] {
        [
            self.agent[0],
            self.agent[1],
            self.block.x,
            self.block.y,
            self.block.theta,
        ]
    }

    /// Inverse of [`State::to_array`].
    pub fn from_array(a: [f64; 5]) -> Self {
        State {
            agent: [a[0], a[1]],
            block: Pose {
                x: a[2],
                y: a[3],
                theta: a[4],
            },
        }
    }

    fn check_finite(&self) -> Result<(), SimError> {
        if self.to_array().iter().all(|v| v.is_finite()) {
            Ok(())
        } else {
            Err(SimError::NonFiniteState {
                state: self.to_array(),
            })
        }
    }
}

/// What one control step reports: gym-pusht's reward, termination and `info` fields.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StepInfo {
    /// clip(coverage / 0.95, 0, 1).
    pub reward: f64,
    /// area(goal ∩ block) / area(goal), in [0, 1].
    pub coverage: f64,
    /// coverage > 0.95 (strict); gym-pusht's `terminated`.
    pub is_success: bool,
    /// Control steps taken since the last reset (1 after the first step).
    pub steps: usize,
    /// `steps >= 300`: the TimeLimit truncation gym-pusht is registered with.
    pub truncated: bool,
    /// Agent position (px), `info["pos_agent"]`.
    pub pos_agent: [f64; 2],
    /// Agent velocity (px/s), `info["vel_agent"]`.
    pub vel_agent: [f64; 2],
    /// Block pose with the raw angle, `info["block_pose"]`.
    pub block_pose: Pose,
    /// `info["n_contacts"]` as gym-pusht computes it: ceil(contact points summed over the
    /// substeps / 1000) (its divisor is `int(1 / dt * control_hz)`), so 1 iff any contact.
    pub n_contacts: u32,
    /// Contact points summed over the 10 substeps (the un-mangled count).
    pub contact_points: u32,
}

/// Physics tuning of the rapier solver. Defaults are chosen to behave like gym-pusht's
/// Chipmunk space (see the field docs) and are what the parity figures were measured with.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PhysicsConfig {
    /// rapier solver iterations per substep (Chipmunk's `iterations` is 10).
    pub solver_iterations: usize,
    /// rapier stabilisation iterations per solver iteration.
    pub stabilization_iterations: usize,
    /// Natural frequency of rapier's soft contacts (Hz). With `contact_damping_ratio` it sets
    /// the fraction of penetration removed per substep (rapier's ERP, 0.090 by default;
    /// Chipmunk's `1 - collision_bias^dt` is 0.061) and the constraint softness.
    /// The default (60 Hz, ratio 19) was picked by a grid search over frequency
    /// {45..200} x ratio {8, 19, 40} x iterations {4, 10} for the smallest divergence from the
    /// recorded gym-pusht trajectories (`examples/parity_sweep.rs`); rapier's own default
    /// (30 Hz, ratio 5) diverges about 3x more after 10 steps.
    pub contact_frequency: f64,
    /// Damping ratio of rapier's soft contacts; large values make the velocity constraint
    /// stiff, as Chipmunk's is.
    pub contact_damping_ratio: f64,
    /// Distance (px) at which rapier creates (speculative) contacts before shapes touch.
    /// Chipmunk has no speculative contacts, so the default is tiny.
    pub prediction_distance: f64,
    /// Penetration (px) left uncorrected: Chipmunk's `collision_slop` (0.1).
    pub allowed_penetration: f64,
    /// Largest velocity (px/s) used to push overlapping shapes apart.
    pub max_corrective_velocity: f64,
    /// Skip rapier on substeps where no contact is possible (exact; see the module docs).
    pub skip_free_flight: bool,
}

impl Default for PhysicsConfig {
    fn default() -> Self {
        PhysicsConfig {
            solver_iterations: 4,
            stabilization_iterations: 1,
            contact_frequency: 60.0,
            contact_damping_ratio: 19.0,
            prediction_distance: 0.01,
            allowed_penetration: 0.1,
            max_corrective_velocity: 1.0e4,
            skip_free_flight: true,
        }
    }
}

/// Everything needed to continue a trajectory exactly (unlike [`State`], which is what
/// gym-pusht's `reset_to_state` accepts and which drops velocities).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Snapshot {
    /// Observable state.
    pub state: State,
    /// Agent velocity (px/s).
    pub agent_vel: [f64; 2],
    /// Block pose inside the physics world (one substep ahead, see the module docs).
    pub physics_block: Pose,
    /// Control steps since reset.
    pub steps: usize,
}

/// The rapier world of one PushT.
struct World {
    pipeline: PhysicsPipeline,
    params: IntegrationParameters,
    islands: IslandManager,
    broad_phase: DefaultBroadPhase,
    narrow_phase: NarrowPhase,
    bodies: RigidBodySet,
    colliders: ColliderSet,
    impulse_joints: ImpulseJointSet,
    multibody_joints: MultibodyJointSet,
    ccd: CCDSolver,
    agent: RigidBodyHandle,
    block: RigidBodyHandle,
    /// The block pose in f64: the pose last set, plus the exact f64 differences of rapier's f32
    /// poses across each step. Poses that were set (resets) therefore read back bit for bit.
    block_pose: Pose,
}

impl World {
    fn new(config: &PhysicsConfig) -> Self {
        let mut bodies = RigidBodySet::new();
        let mut colliders = ColliderSet::new();

        let walls = bodies.insert(RigidBodyBuilder::fixed());
        for [a, b] in WALLS {
            let c = ColliderBuilder::capsule_from_endpoints(
                point![a[0] as f32, a[1] as f32],
                point![b[0] as f32, b[1] as f32],
                WALL_RADIUS as f32,
            )
            .friction(0.0)
            .restitution(0.0);
            colliders.insert_with_parent(c, walls, &mut bodies);
        }

        let agent = bodies.insert(
            RigidBodyBuilder::kinematic_velocity_based()
                .translation(vector![AGENT_SPAWN[0] as f32, AGENT_SPAWN[1] as f32])
                .can_sleep(false),
        );
        colliders.insert_with_parent(
            ColliderBuilder::ball(AGENT_RADIUS as f32)
                .friction(0.0)
                .restitution(0.0),
            agent,
            &mut bodies,
        );

        // Mass properties exactly as gym-pusht passes them to pymunk: mass 1, moment 3000
        // about the centre of gravity (0, 45); the colliders carry no mass of their own.
        let block = bodies.insert(
            RigidBodyBuilder::dynamic()
                .translation(vector![256.0, 300.0])
                .additional_mass_properties(MassProperties::new(
                    point![BLOCK_COG[0] as f32, BLOCK_COG[1] as f32],
                    BLOCK_MASS as f32,
                    BLOCK_MOMENT as f32,
                ))
                .can_sleep(false),
        );
        for poly in [BAR, STEM] {
            // Both boxes are axis-aligned in body coordinates: cuboids translated to their centre.
            let (x0, x1) = (poly[0][0].min(poly[2][0]), poly[0][0].max(poly[2][0]));
            let (y0, y1) = (poly[0][1].min(poly[2][1]), poly[0][1].max(poly[2][1]));
            let c = ColliderBuilder::cuboid(((x1 - x0) / 2.0) as f32, ((y1 - y0) / 2.0) as f32)
                .translation(vector![((x0 + x1) / 2.0) as f32, ((y0 + y1) / 2.0) as f32])
                .density(0.0)
                .friction(0.0)
                .restitution(0.0);
            colliders.insert_with_parent(c, block, &mut bodies);
        }

        let unit = LENGTH_UNIT;
        let params = IntegrationParameters {
            dt: DT as f32,
            length_unit: unit,
            num_solver_iterations: config.solver_iterations.max(1),
            num_internal_stabilization_iterations: config.stabilization_iterations,
            contact_softness: SpringCoefficients::new(
                config.contact_frequency as f32,
                config.contact_damping_ratio as f32,
            ),
            normalized_prediction_distance: config.prediction_distance as f32 / unit,
            normalized_allowed_linear_error: config.allowed_penetration as f32 / unit,
            normalized_max_corrective_velocity: config.max_corrective_velocity as f32 / unit,
            ..IntegrationParameters::default()
        };
        World {
            pipeline: PhysicsPipeline::new(),
            params,
            islands: IslandManager::new(),
            broad_phase: DefaultBroadPhase::new(),
            narrow_phase: NarrowPhase::new(),
            bodies,
            colliders,
            impulse_joints: ImpulseJointSet::new(),
            multibody_joints: MultibodyJointSet::new(),
            ccd: CCDSolver::new(),
            agent,
            block,
            block_pose: Pose {
                x: 256.0,
                y: 300.0,
                theta: 0.0,
            },
        }
    }

    fn block_pose(&self) -> Pose {
        self.block_pose
    }

    fn rapier_block_pose(&self) -> Pose {
        let iso = self.bodies[self.block].position();
        Pose {
            x: f64::from(iso.translation.x),
            y: f64::from(iso.translation.y),
            theta: f64::from(iso.rotation.angle()),
        }
    }

    fn set_block_pose(&mut self, pose: Pose) {
        self.block_pose = pose;
        let b = &mut self.bodies[self.block];
        b.set_position(
            Isometry::new(vector![pose.x as f32, pose.y as f32], pose.theta as f32),
            true,
        );
        b.set_linvel(vector![0.0, 0.0], true);
        b.set_angvel(0.0, true);
    }

    fn set_agent(&mut self, p: [f64; 2], v: [f64; 2]) {
        let a = &mut self.bodies[self.agent];
        a.set_translation(vector![p[0] as f32, p[1] as f32], true);
        a.set_linvel(vector![v[0] as f32, v[1] as f32], true);
    }

    /// One rapier step with the agent at `p` moving at `v`; returns the contact points.
    fn step(&mut self, p: [f64; 2], v: [f64; 2], segments: &mut Vec<ContactSegment>) -> u32 {
        segments.clear();
        self.set_agent(p, v);
        let b = &mut self.bodies[self.block];
        b.set_linvel(vector![0.0, 0.0], false);
        b.set_angvel(0.0, false);
        let before = self.rapier_block_pose();
        let before_iso = *self.bodies[self.block].position();
        self.pipeline.step(
            &vector![0.0, 0.0],
            &self.params,
            &mut self.islands,
            &mut self.broad_phase,
            &mut self.narrow_phase,
            &mut self.bodies,
            &mut self.colliders,
            &mut self.impulse_joints,
            &mut self.multibody_joints,
            &mut self.ccd,
            &(),
            &(),
        );
        let mut points = 0u32;
        for pair in self.narrow_phase.contact_pairs() {
            if pair.has_any_active_contact {
                for m in &pair.manifolds {
                    points += m.data.solver_contacts.len() as u32;
                    let n = m.data.normal;
                    let (nx, ny) = (f64::from(n.x), f64::from(n.y));
                    for c in &m.data.solver_contacts {
                        // rapier's solver point is the midpoint of the two surface points.
                        let h = f64::from(c.dist) / 2.0;
                        let (px, py) = (f64::from(c.point.x), f64::from(c.point.y));
                        let p1 = [px - nx * h, py - ny * h];
                        let p2 = [px + nx * h, py + ny * h];
                        segments.push([
                            [p1[0] - 2.0 * nx, p1[1] - 2.0 * ny],
                            [p2[0] + 2.0 * nx, p2[1] + 2.0 * ny],
                        ]);
                    }
                }
            }
        }
        if points == 0 {
            // No contact: the block's velocity was zero, so it cannot have moved; undo the
            // f32 rounding of rapier's integration about the centre of mass (about 1 ulp), so
            // that contact-free substeps are exact no-ops whether or not they are skipped.
            self.bodies[self.block].set_position(before_iso, false);
            return 0;
        }
        let after = self.rapier_block_pose();
        self.block_pose.x += after.x - before.x;
        self.block_pose.y += after.y - before.y;
        let dtheta = after.theta - before.theta;
        // rapier's angle() is in (-pi, pi]: unwrap the difference.
        self.block_pose.theta +=
            dtheta - std::f64::consts::TAU * (dtheta / std::f64::consts::TAU).round();
        points
    }
}

/// One PushT environment (gym-pusht `PushT-v0` semantics; see the module docs).
///
/// Actions are absolute agent targets in px; like gym-pusht, targets outside [0, 512]^2 are
/// accepted unclipped (the PD controller then drives the agent towards them; the agent, being
/// kinematic, passes through walls exactly as in gym-pusht). Non-finite actions are rejected
/// with [`SimError::NonFiniteAction`] and leave the state unchanged.
pub struct PushT {
    config: PhysicsConfig,
    world: World,
    goal: Pose,
    agent_pos: [f64; 2],
    agent_vel: [f64; 2],
    /// The block pose gym-pusht would report (see the module docs).
    block: Pose,
    steps: usize,
    last_action: Option<[f64; 2]>,
    /// Contact markers of the last physics substep (pymunk's debug-draw segments).
    contacts: Vec<ContactSegment>,
}

impl Default for PushT {
    fn default() -> Self {
        Self::new(PhysicsConfig::default())
    }
}

impl PushT {
    /// A fresh environment in gym-pusht's `_setup` configuration (agent at (256, 400), block at
    /// (256, 300) angle 0); call [`PushT::reset`] or [`PushT::reset_to`] before stepping.
    pub fn new(config: PhysicsConfig) -> Self {
        let world = World::new(&config);
        let block = world.block_pose();
        PushT {
            config,
            world,
            goal: GOAL,
            agent_pos: AGENT_SPAWN,
            agent_vel: [0.0; 2],
            block,
            steps: 0,
            last_action: None,
            contacts: Vec::new(),
        }
    }

    /// The physics configuration.
    pub fn config(&self) -> &PhysicsConfig {
        &self.config
    }

    /// Seeded reset: draws the initial state from `stream` exactly as gym-pusht / Diffusion
    /// Policy do for `seed`, then applies it with [`PushT::reset_to`].
    pub fn reset(&mut self, seed: u64, stream: ResetStream) -> Result<State, SimError> {
        let s = stream.sample(seed)?;
        self.reset_to(State::from_array(s))?;
        Ok(self.state())
    }

    /// gym-pusht's `reset(options={"reset_to_state": ...})`: a fresh world; the agent is placed,
    /// then the block's body origin is placed at `(block.x, block.y)` with angle 0, then the
    /// angle is set **about the centre of gravity** (which moves the origin), then one physics
    /// substep runs (resolving any overlap; the agent's velocity is zero).
    ///
    /// Consequently `reset_to(s)` reproduces `s` only when `s.block.theta` is 0 (or the pose
    /// came from [`PushT::reset_to_pose`]); use [`PushT::state`] to read the applied state.
    pub fn reset_to(&mut self, state: State) -> Result<(), SimError> {
        state.check_finite()?;
        // Position first (angle 0), then the angle about the CoG.
        let at_zero = Pose {
            x: state.block.x,
            y: state.block.y,
            theta: 0.0,
        };
        let pose = Pose::from_cog(at_zero.cog(), state.block.theta);
        self.reset_to_pose(State {
            agent: state.agent,
            block: pose,
        })
    }

    /// Like [`PushT::reset_to`], but `state.block` is taken as the final body-origin pose (no
    /// rotation about the centre of gravity): `reset_to_pose(s)` then `state()` gives `s` back
    /// unless the agent overlaps the block.
    pub fn reset_to_pose(&mut self, state: State) -> Result<(), SimError> {
        state.check_finite()?;
        self.world = World::new(&self.config);
        self.world.set_block_pose(state.block);
        self.agent_pos = state.agent;
        self.agent_vel = [0.0; 2];
        self.block = state.block;
        self.steps = 0;
        self.last_action = None;
        // gym-pusht's settling step: velocities are zero, so only overlaps are resolved.
        self.substep();
        Ok(())
    }

    /// The observable state (agent position, block pose with the raw angle).
    pub fn state(&self) -> State {
        State {
            agent: self.agent_pos,
            block: self.block,
        }
    }

    /// Everything needed to continue exactly from here (see [`PushT::restore`]).
    pub fn snapshot(&self) -> Snapshot {
        Snapshot {
            state: self.state(),
            agent_vel: self.agent_vel,
            physics_block: self.world.block_pose(),
            steps: self.steps,
        }
    }

    /// Continue from a [`Snapshot`]. The physics world is rebuilt (contact warm-start caches are
    /// cleared), so a restored environment is deterministic: the same snapshot and actions
    /// always give the same trajectory.
    pub fn restore(&mut self, snap: &Snapshot) -> Result<(), SimError> {
        snap.state.check_finite()?;
        self.world = World::new(&self.config);
        self.world.set_block_pose(snap.physics_block);
        self.agent_pos = snap.state.agent;
        self.agent_vel = snap.agent_vel;
        self.block = snap.state.block;
        self.steps = snap.steps;
        self.contacts.clear();
        Ok(())
    }

    /// gym-pusht's `state` observation: `[agent_x, agent_y, block_x, block_y, angle mod 2pi]`.
    pub fn state_obs(&self) -> [f64; 5] {
        let mut s = self.state().to_array();
        s[4] = s[4].rem_euclid(std::f64::consts::TAU);
        s
    }

    /// gym-pusht's `environment_state`: the 8 block vertices (bar then stem), 16 numbers.
    pub fn keypoints(&self) -> [f64; 16] {
        self.block.keypoints()
    }

    /// Agent position (px).
    pub fn agent_pos(&self) -> [f64; 2] {
        self.agent_pos
    }

    /// Agent velocity (px/s).
    pub fn agent_vel(&self) -> [f64; 2] {
        self.agent_vel
    }

    /// Block body-origin pose (raw angle).
    pub fn block_pose(&self) -> Pose {
        self.block
    }

    /// The contact markers gym-pusht draws (in red) for the contacts of the last physics
    /// substep: for each contact point, the segment from `p1 - 2n` to `p2 + 2n` (px), with
    /// `p1`, `p2` the surface points and `n` the contact normal. rapier's contacts stand in for
    /// Chipmunk's, so these agree only approximately.
    pub fn contact_segments(&self) -> &[ContactSegment] {
        &self.contacts
    }

    /// What the renderer draws: agent, block and goal.
    pub fn scene(&self) -> Scene {
        Scene {
            agent: self.agent_pos,
            block: self.block,
            goal: self.goal,
        }
    }

    /// Goal pose.
    pub fn goal(&self) -> Pose {
        self.goal
    }

    /// The last action passed to [`PushT::step`], if any since the reset.
    pub fn last_action(&self) -> Option<[f64; 2]> {
        self.last_action
    }

    /// Control steps since the last reset.
    pub fn steps(&self) -> usize {
        self.steps
    }

    /// Current coverage of the goal by the block.
    pub fn coverage(&self) -> f64 {
        coverage::coverage(&self.block, &self.goal)
    }

    /// One 10 Hz control step towards the absolute target `action` (px).
    pub fn step(&mut self, action: [f64; 2]) -> Result<StepInfo, SimError> {
        if !action.iter().all(|v| v.is_finite()) {
            return Err(SimError::NonFiniteAction { action });
        }
        self.last_action = Some(action);
        let mut contact_points = 0;
        for _ in 0..SUBSTEPS {
            for ((p, v), target) in self
                .agent_pos
                .iter_mut()
                .zip(&mut self.agent_vel)
                .zip(action)
            {
                *v += (KP * (target - *p) - KV * *v) * DT;
                *p += *v * DT;
            }
            contact_points += self.substep();
        }
        self.steps += 1;
        let coverage = self.coverage();
        Ok(StepInfo {
            reward: coverage::reward(coverage),
            coverage,
            is_success: coverage > SUCCESS_THRESHOLD,
            steps: self.steps,
            truncated: self.steps >= MAX_EPISODE_STEPS,
            pos_agent: self.agent_pos,
            vel_agent: self.agent_vel,
            block_pose: self.block,
            n_contacts: contact_points.div_ceil(1000),
            contact_points,
        })
    }

    /// The physics part of one substep, after the agent has been moved to `agent_pos`.
    fn substep(&mut self) -> u32 {
        self.block = self.world.block_pose();
        if self.config.skip_free_flight && self.contact_impossible(&self.block) {
            self.contacts.clear();
            return 0;
        }
        self.world
            .step(self.agent_pos, self.agent_vel, &mut self.contacts)
    }

    /// True when neither the agent nor a wall can touch the block during this substep.
    fn contact_impossible(&self, block: &Pose) -> bool {
        let cog = block.cog();
        let speed = self.agent_vel[0].hypot(self.agent_vel[1]);
        let reach = AGENT_RADIUS + BLOCK_BOUND_RADIUS + 2.0 * speed * DT + SKIP_MARGIN;
        let (dx, dy) = (self.agent_pos[0] - cog[0], self.agent_pos[1] - cog[1]);
        if dx * dx + dy * dy <= reach * reach {
            return false;
        }
        // Walls: inner faces at 7 and 504 (segments at 5 / 506, radius 2).
        let lo = 5.0 + WALL_RADIUS + SKIP_MARGIN;
        let hi = 506.0 - WALL_RADIUS - SKIP_MARGIN;
        cog[0] - BLOCK_BOUND_RADIUS > lo
            && cog[0] + BLOCK_BOUND_RADIUS < hi
            && cog[1] - BLOCK_BOUND_RADIUS > lo
            && cog[1] + BLOCK_BOUND_RADIUS < hi
    }
}
