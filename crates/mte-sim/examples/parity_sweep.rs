//! Measure block-pose divergence from gym-pusht under recorded actions for solver variants:
//! `cargo run --release -p mte-sim --example parity_sweep`.
#![allow(clippy::print_stdout, clippy::unwrap_used, clippy::expect_used)]
use mte_sim::{PhysicsConfig, Pose, PushT, ResetStream};
use serde::Deserialize;

#[derive(Deserialize)]
struct Trajectories {
    episodes: Vec<Episode>,
}
#[derive(Deserialize)]
struct Episode {
    stream: String,
    seed: u64,
    actions: Vec<[f64; 2]>,
    steps: Vec<Step>,
}
#[derive(Deserialize)]
struct Step {
    block_pose: [f64; 3],
}

fn wrap(a: f64) -> f64 {
    (a + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI
}

fn main() {
    let t: Trajectories =
        serde_json::from_str(include_str!("../tests/fixtures/pusht_trajectories.json")).unwrap();
    let base = PhysicsConfig::default();
    let mut variants: Vec<(String, PhysicsConfig)> = vec![("default".into(), base)];
    let arg = std::env::args().nth(1).unwrap_or_default();
    if arg == "sweep" {
        for it in [1, 2, 4, 8, 10] {
            variants.push((
                format!("iters {it}"),
                PhysicsConfig {
                    solver_iterations: it,
                    ..base
                },
            ));
        }
        for st in [0, 2] {
            variants.push((
                format!("stab {st}"),
                PhysicsConfig {
                    stabilization_iterations: st,
                    ..base
                },
            ));
        }
        for (f, z) in [
            (30.0, 5.0),
            (39.4, 5.0),
            (60.0, 19.0),
            (25.0, 19.0),
            (39.4, 50.0),
        ] {
            variants.push((
                format!("soft {f}/{z}"),
                PhysicsConfig {
                    contact_frequency: f,
                    contact_damping_ratio: z,
                    ..base
                },
            ));
        }
        for p in [0.2, 1.0, 0.001] {
            variants.push((
                format!("pred {p}"),
                PhysicsConfig {
                    prediction_distance: p,
                    ..base
                },
            ));
        }
        for p in [0.01, 0.5] {
            variants.push((
                format!("slop {p}"),
                PhysicsConfig {
                    allowed_penetration: p,
                    ..base
                },
            ));
        }
        variants.push((
            "noskip".into(),
            PhysicsConfig {
                skip_free_flight: false,
                ..base
            },
        ));
    }
    if arg == "grid" {
        for f in [45.0, 60.0, 80.0, 120.0, 200.0] {
            for z in [8.0, 19.0, 40.0] {
                for it in [4, 10] {
                    variants.push((
                        format!("{f}/{z}/{it}"),
                        PhysicsConfig {
                            contact_frequency: f,
                            contact_damping_ratio: z,
                            solver_iterations: it,
                            ..base
                        },
                    ));
                }
            }
        }
    }
    let at = [1usize, 2, 5, 10, 20, 50, 100];
    for (name, cfg) in variants {
        let mut per_step: Vec<Vec<f64>> = vec![Vec::new(); at.len()];
        let mut per_step_a: Vec<Vec<f64>> = vec![Vec::new(); at.len()];
        for ep in &t.episodes {
            let mut env = PushT::new(cfg);
            env.reset(ep.seed, ep.stream.parse::<ResetStream>().unwrap())
                .unwrap();
            for (i, (a, s)) in ep.actions.iter().zip(&ep.steps).enumerate() {
                env.step(*a).unwrap();
                if let Some(k) = at.iter().position(|&x| x == i + 1) {
                    let theirs = Pose {
                        x: s.block_pose[0],
                        y: s.block_pose[1],
                        theta: s.block_pose[2],
                    };
                    let (c0, c1) = (env.block_pose().cog(), theirs.cog());
                    per_step[k].push((c0[0] - c1[0]).hypot(c0[1] - c1[1]));
                    per_step_a[k].push(wrap(env.block_pose().theta - theirs.theta).abs());
                }
            }
        }
        let mut line = format!("{name:16}");
        for (k, step) in at.iter().enumerate() {
            let v = &mut per_step[k];
            v.sort_by(f64::total_cmp);
            let mean_a = per_step_a[k].iter().sum::<f64>() / per_step_a[k].len() as f64;
            line += &format!(
                " | @{step}: med {:.2} max {:.1} a {:.3}",
                v[v.len() / 2],
                v[v.len() - 1],
                mean_a
            );
        }
        println!("{line}");
    }
}
