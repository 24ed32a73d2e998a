//! Exact coverage: area(goal T ∩ block T) / area(goal T).
//!
//! gym-pusht computes this with shapely on two-box MultiPolygons. The two boxes of a T do not
//! overlap, so the intersection area is exactly the sum of the four box-box intersection areas;
//! each is a convex-polygon clip (Sutherland-Hodgman) followed by the shoelace formula. No
//! sampling, no rasterisation: the result equals shapely's to rounding (about 1e-12 relative).

use crate::geometry::{Pose, T_AREA};

/// A convex polygon with at most 8 vertices (a quad clipped by a quad has at most 8).
#[derive(Clone, Copy)]
struct Poly {
    n: usize,
    v: [[f64; 2]; 8],
}

fn signed_area(poly: &[[f64; 2]]) -> f64 {
    let mut a = 0.0;
    for i in 0..poly.len() {
        let p = poly[i];
        let q = poly[(i + 1) % poly.len()];
        a += p[0] * q[1] - q[0] * p[1];
    }
    a / 2.0
}

/// Area of the intersection of two convex quadrilaterals (either winding).
pub fn convex_quad_intersection_area(a: &[[f64; 2]; 4], b: &[[f64; 2]; 4]) -> f64 {
    // Clip `a` by each edge of `b`; orient `b` counter-clockwise (in the math sense) first.
    let mut clip = *b;
    if signed_area(&clip) < 0.0 {
        clip.reverse();
    }
    let mut cur = Poly {
        n: 4,
        v: [[0.0; 2]; 8],
    };
    cur.v[..4].copy_from_slice(a);
    for i in 0..4 {
        let e0 = clip[i];
        let e1 = clip[(i + 1) % 4];
        let (ex, ey) = (e1[0] - e0[0], e1[1] - e0[1]);
        // Inside = left of the edge (cross >= 0).
        let side = |p: [f64; 2]| ex * (p[1] - e0[1]) - ey * (p[0] - e0[0]);
        let mut out = Poly {
            n: 0,
            v: [[0.0; 2]; 8],
        };
        for j in 0..cur.n {
            let p = cur.v[j];
            let q = cur.v[(j + 1) % cur.n];
            let (sp, sq) = (side(p), side(q));
            if sp >= 0.0 {
                push(&mut out, p);
            }
            if (sp >= 0.0) != (sq >= 0.0) {
                let t = sp / (sp - sq);
                push(
                    &mut out,
                    [p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])],
                );
            }
        }
        cur = out;
        if cur.n < 3 {
            return 0.0;
        }
    }
    signed_area(&cur.v[..cur.n]).abs()
}

fn push(poly: &mut Poly, p: [f64; 2]) {
    // A convex quad clipped by 4 half-planes has at most 8 vertices; guard anyway.
    if poly.n < poly.v.len() {
        poly.v[poly.n] = p;
        poly.n += 1;
    }
}

/// Area (px^2) of the intersection of the T at `block` with the T at `goal`.
pub fn intersection_area(block: &Pose, goal: &Pose) -> f64 {
    let b = block.polygons();
    let g = goal.polygons();
    let mut area = 0.0;
    for bp in &b {
        for gp in &g {
            area += convex_quad_intersection_area(bp, gp);
        }
    }
    area
}

/// Coverage in [0, 1]: intersection area over the goal T's area (6300 px^2).
pub fn coverage(block: &Pose, goal: &Pose) -> f64 {
    (intersection_area(block, goal) / T_AREA).clamp(0.0, 1.0)
}

/// gym-pusht's reward: clip(coverage / 0.95, 0, 1).
pub fn reward(coverage: f64) -> f64 {
    (coverage / crate::geometry::SUCCESS_THRESHOLD).clamp(0.0, 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::GOAL;

    #[test]
    fn identical_poses_cover_fully() {
        assert!((coverage(&GOAL, &GOAL) - 1.0).abs() < 1e-12);
        let p = Pose {
            x: 100.0,
            y: 80.0,
            theta: -2.0,
        };
        assert!((coverage(&p, &p) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn disjoint_poses_cover_nothing() {
        let p = Pose {
            x: 50.0,
            y: 50.0,
            theta: 0.0,
        };
        assert_eq!(coverage(&p, &GOAL), 0.0);
    }

    #[test]
    fn axis_aligned_shift_matches_hand_computation() {
        // Both at angle 0, block shifted right by 10: bar overlap 110*30, stem overlap 20*90.
        let g = Pose {
            x: 200.0,
            y: 200.0,
            theta: 0.0,
        };
        let b = Pose {
            x: 210.0,
            y: 200.0,
            theta: 0.0,
        };
        let expect = (110.0 * 30.0 + 20.0 * 90.0) / T_AREA;
        assert!((coverage(&b, &g) - expect).abs() < 1e-12);
        // A vertical shift of 15: bar 120*15, stem 30*75, plus the stem's top 15 rows inside
        // the goal's bar? The block stem spans y 245..335, the goal bar 200..230: no. The block
        // bar spans 215..245: overlaps goal bar 215..230 (120*15) and goal stem 230..245 (30*15).
        let b = Pose {
            x: 200.0,
            y: 215.0,
            theta: 0.0,
        };
        let expect = (120.0 * 15.0 + 30.0 * 15.0 + 30.0 * 75.0) / T_AREA;
        assert!((coverage(&b, &g) - expect).abs() < 1e-12);
    }

    #[test]
    fn rotation_by_pi_about_the_stem_axis_is_symmetric() {
        // The T is symmetric about its stem axis; a reflection is not a rotation, but winding
        // of the clip polygon must not matter: clip a CW quad against a CCW one.
        let a = [[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]];
        let mut b = [[5.0, 5.0], [15.0, 5.0], [15.0, 15.0], [5.0, 15.0]];
        assert!((convex_quad_intersection_area(&a, &b) - 25.0).abs() < 1e-12);
        b.reverse();
        assert!((convex_quad_intersection_area(&a, &b) - 25.0).abs() < 1e-12);
    }

    #[test]
    fn reward_clips() {
        assert_eq!(reward(0.95), 1.0);
        assert_eq!(reward(1.0), 1.0);
        assert!((reward(0.475) - 0.5).abs() < 1e-12);
    }
}
