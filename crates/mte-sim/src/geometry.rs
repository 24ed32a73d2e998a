//! PushT geometry and physical constants, in gym-pusht's units and conventions.
//!
//! Units: world units are pixels of the 512 x 512 canvas; **y points down** (pymunk coordinates
//! drawn directly, as gym-pusht and Diffusion Policy do). Angles are radians, positive from +x
//! towards +y (clockwise on screen). Time is seconds. Every value here is from
//! `shared/reference/peer-facts.md` section 1 (verified against gym-pusht 0.1.8 / pymunk 6.11).

/// Side of the square world and of the full-resolution canvas (px).
pub const WORLD_SIZE: f64 = 512.0;
/// Radius of the agent's circle (px).
pub const AGENT_RADIUS: f64 = 15.0;
/// Proportional gain of the agent's PD controller (1/s^2).
pub const KP: f64 = 100.0;
/// Derivative gain of the agent's PD controller (1/s).
pub const KV: f64 = 20.0;
/// Physics time step (s): `sim_hz = 100`.
pub const DT: f64 = 0.01;
/// Physics substeps per control step: control runs at 10 Hz.
pub const SUBSTEPS: usize = 10;
/// Control rate (Hz).
pub const CONTROL_HZ: f64 = 10.0;
/// Block mass (pymunk mass units; only ratios matter, the agent is kinematic).
pub const BLOCK_MASS: f64 = 1.0;
/// Block moment of inertia about its centre of gravity, as gym-pusht passes it (twice the bar's
/// own moment about the body origin; the stem's is never used).
pub const BLOCK_MOMENT: f64 = 3000.0;
/// Block centre of gravity in body coordinates: the unweighted mean of the two box centroids.
pub const BLOCK_COG: [f64; 2] = [0.0, 45.0];
/// The T's bar (120 x 30) in body coordinates, in pymunk's `get_vertices()` order.
pub const BAR: [[f64; 2]; 4] = [[-60.0, 0.0], [60.0, 0.0], [60.0, 30.0], [-60.0, 30.0]];
/// The T's stem (30 x 90) in body coordinates, in pymunk's `get_vertices()` order.
pub const STEM: [[f64; 2]; 4] = [[-15.0, 30.0], [15.0, 30.0], [15.0, 120.0], [-15.0, 120.0]];
/// Area of the T (px^2): 120*30 + 30*90.
pub const T_AREA: f64 = 6300.0;
/// Radius of the wall segments (px).
pub const WALL_RADIUS: f64 = 2.0;
/// The four static walls, as segment end points (px), in gym-pusht's order.
pub const WALLS: [[[f64; 2]; 2]; 4] = [
    [[5.0, 506.0], [5.0, 5.0]],
    [[5.0, 5.0], [506.0, 5.0]],
    [[506.0, 5.0], [506.0, 506.0]],
    [[5.0, 506.0], [506.0, 506.0]],
];
/// Coverage above which an episode succeeds (strict inequality) and reward saturates.
pub const SUCCESS_THRESHOLD: f64 = 0.95;
/// gym-pusht's episode limit (control steps).
pub const MAX_EPISODE_STEPS: usize = 300;
/// Where the agent is created before a reset state is applied (px).
pub const AGENT_SPAWN: [f64; 2] = [256.0, 400.0];

/// A planar pose of the T's **body origin** (the midpoint of the bar's outer edge), not of its
/// centre of gravity: `x`, `y` in px, `theta` in radians.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Pose {
    /// Body origin x (px).
    pub x: f64,
    /// Body origin y (px, down).
    pub y: f64,
    /// Rotation (rad), unwrapped as the physics integrates it.
    pub theta: f64,
}

/// The goal pose (256, 256, pi/4).
pub const GOAL: Pose = Pose {
    x: 256.0,
    y: 256.0,
    theta: std::f64::consts::FRAC_PI_4,
};

impl Pose {
    /// Body coordinates to world coordinates: rotate by `theta`, then translate.
    #[inline]
    pub fn apply(&self, p: [f64; 2]) -> [f64; 2] {
        let (s, c) = self.theta.sin_cos();
        [self.x + c * p[0] - s * p[1], self.y + s * p[0] + c * p[1]]
    }

    /// World coordinates to body coordinates: the inverse of [`Pose::apply`].
    #[inline]
    pub fn to_body(&self, p: [f64; 2]) -> [f64; 2] {
        let (s, c) = self.theta.sin_cos();
        let (dx, dy) = (p[0] - self.x, p[1] - self.y);
        [c * dx + s * dy, -s * dx + c * dy]
    }

    /// World position of the centre of gravity.
    #[inline]
    pub fn cog(&self) -> [f64; 2] {
        self.apply(BLOCK_COG)
    }

    /// The pose whose centre of gravity is at `cog` with rotation `theta`.
    #[inline]
    pub fn from_cog(cog: [f64; 2], theta: f64) -> Self {
        let (s, c) = theta.sin_cos();
        let [gx, gy] = BLOCK_COG;
        Pose {
            x: cog[0] - (c * gx - s * gy),
            y: cog[1] - (s * gx + c * gy),
            theta,
        }
    }

    /// The T's two boxes in world coordinates (bar first), vertices in [`BAR`]/[`STEM`] order.
    pub fn polygons(&self) -> [[[f64; 2]; 4]; 2] {
        [BAR.map(|v| self.apply(v)), STEM.map(|v| self.apply(v))]
    }

    /// The 8 block vertices (bar's 4 then stem's 4) flattened to 16 numbers `x0, y0, x1, ...`:
    /// gym-pusht's `environment_state`.
    pub fn keypoints(&self) -> [f64; 16] {
        let mut out = [0.0; 16];
        for (i, v) in BAR.iter().chain(STEM.iter()).enumerate() {
            let w = self.apply(*v);
            out[2 * i] = w[0];
            out[2 * i + 1] = w[1];
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn from_cog_inverts_cog() {
        let p = Pose {
            x: 12.0,
            y: -3.0,
            theta: 2.3,
        };
        let q = Pose::from_cog(p.cog(), p.theta);
        assert!((p.x - q.x).abs() < 1e-12 && (p.y - q.y).abs() < 1e-12);
    }

    #[test]
    fn to_body_inverts_apply() {
        let p = Pose {
            x: 12.0,
            y: -3.0,
            theta: 2.3,
        };
        let b = p.to_body(p.apply([7.5, -40.0]));
        assert!(
            (b[0] - 7.5).abs() < 1e-12 && (b[1] + 40.0).abs() < 1e-12,
            "{b:?}"
        );
    }

    #[test]
    fn areas_add_up() {
        let area = |poly: &[[f64; 2]; 4]| {
            let mut a = 0.0;
            for i in 0..4 {
                let (p, q) = (poly[i], poly[(i + 1) % 4]);
                a += p[0] * q[1] - q[0] * p[1];
            }
            a.abs() / 2.0
        };
        assert_eq!(area(&BAR) + area(&STEM), T_AREA);
    }
}
