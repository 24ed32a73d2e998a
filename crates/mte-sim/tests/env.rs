//! Behaviour of the environment that gym-pusht users rely on.

use mte_sim::{PhysicsConfig, Pose, PushT, ResetStream, SimError, State, VecEnv};
use proptest::prelude::*;

/// Actions that keep pushing the block: towards its centre of gravity plus a seeded wobble.
fn pushing_actions(env: &PushT, t: usize) -> [f64; 2] {
    let c = env.block_pose().cog();
    let w = (t as f64 * 0.7).sin() * 40.0;
    [c[0] + w, c[1] - w * 0.5]
}

fn trajectory(config: PhysicsConfig, seed: u64, steps: usize) -> Vec<State> {
    let mut env = PushT::new(config);
    env.reset(seed, ResetStream::Legacy).expect("reset");
    (0..steps)
        .map(|t| {
            let a = pushing_actions(&env, t);
            env.step(a).expect("step");
            env.state()
        })
        .collect()
}

#[test]
fn same_seed_same_trajectory() {
    let a = trajectory(PhysicsConfig::default(), 100_003, 60);
    let b = trajectory(PhysicsConfig::default(), 100_003, 60);
    assert_eq!(a, b);
    // And the block really moved (the test would be vacuous otherwise).
    assert!((a[0].block.x - a[59].block.x).abs() + (a[0].block.y - a[59].block.y).abs() > 5.0);
}

#[test]
fn skipping_contact_free_substeps_changes_nothing() {
    for seed in [0, 5, 100_010] {
        let fast = trajectory(PhysicsConfig::default(), seed, 80);
        let slow = trajectory(
            PhysicsConfig {
                skip_free_flight: false,
                ..Default::default()
            },
            seed,
            80,
        );
        assert_eq!(fast, slow, "seed {seed}");
    }
}

#[test]
fn non_finite_actions_are_rejected_and_leave_the_state_unchanged() {
    let mut env = PushT::default();
    env.reset(1, ResetStream::Pcg64).expect("reset");
    env.step([200.0, 200.0]).expect("step");
    let before = env.snapshot();
    for bad in [
        [f64::NAN, 1.0],
        [1.0, f64::INFINITY],
        [f64::NEG_INFINITY, f64::NAN],
    ] {
        let e = env.step(bad).expect_err("non-finite");
        assert!(matches!(e, SimError::NonFiniteAction { .. }));
        assert!(e.to_string().contains("not finite"));
        assert_eq!(env.snapshot(), before);
    }
    let e = env
        .reset_to(State::from_array([1.0, 2.0, f64::NAN, 4.0, 0.0]))
        .expect_err("nan");
    assert!(matches!(e, SimError::NonFiniteState { .. }));
}

#[test]
fn out_of_range_targets_are_accepted_unclipped() {
    let mut env = PushT::default();
    env.reset_to(State {
        agent: [256.0, 480.0],
        block: Pose {
            x: 256.0,
            y: 100.0,
            theta: 0.0,
        },
    })
    .expect("reset");
    for _ in 0..10 {
        env.step([256.0, 700.0]).expect("out of range is fine");
    }
    // The kinematic agent follows its PD target through the wall at y = 506, as in gym-pusht.
    assert!(env.agent_pos()[1] > 600.0, "{:?}", env.agent_pos());
}

#[test]
fn state_round_trips_through_reset_to_pose() {
    let mut env = PushT::default();
    env.reset(100_020, ResetStream::Legacy).expect("reset");
    for t in 0..30 {
        let a = pushing_actions(&env, t);
        env.step(a).expect("step");
    }
    let s = env.state();
    let mut other = PushT::default();
    other.reset_to_pose(s).expect("finite");
    assert_eq!(other.state(), s);
    // reset_to takes gym-pusht's position-then-angle semantics instead: the body origin moves
    // unless the angle is zero.
    other.reset_to(s).expect("finite");
    let moved = other.state().block;
    let expect = Pose::from_cog(
        Pose {
            theta: 0.0,
            ..s.block
        }
        .cog(),
        s.block.theta,
    );
    assert!((moved.x - expect.x).abs() < 1e-9 && (moved.y - expect.y).abs() < 1e-9);
}

#[test]
fn snapshot_restore_is_deterministic() {
    let mut env = PushT::default();
    env.reset(100_030, ResetStream::Legacy).expect("reset");
    for t in 0..10 {
        let a = pushing_actions(&env, t);
        env.step(a).expect("step");
    }
    let snap = env.snapshot();
    let run = |env: &mut PushT| {
        env.restore(&snap).expect("restore");
        (10..40)
            .map(|t| {
                let a = pushing_actions(env, t);
                env.step(a).expect("step").block_pose
            })
            .collect::<Vec<_>>()
    };
    let a = run(&mut env);
    let b = run(&mut PushT::default());
    assert_eq!(a, b);
}

#[test]
fn step_info_matches_gym_pusht_semantics() {
    let mut env = PushT::default();
    // Block on the goal: success (coverage 1 > 0.95), reward 1.
    env.reset_to_pose(State {
        agent: [50.0, 50.0],
        block: mte_sim::GOAL,
    })
    .expect("reset");
    let info = env.step([50.0, 50.0]).expect("step");
    assert!(info.is_success && info.reward == 1.0 && (info.coverage - 1.0).abs() < 1e-12);
    assert_eq!(info.steps, 1);
    assert_eq!(info.n_contacts, 0);
    assert!(!info.truncated);
    for _ in 1..300 {
        env.step([50.0, 50.0]).expect("step");
    }
    assert!(env.step([50.0, 50.0]).expect("step").truncated);
}

#[test]
fn vec_env_is_independent_of_thread_count() {
    // More environments than `PARALLEL_MIN_ENVS`, so the pool runs them.
    let seeds: Vec<u64> = (100_000..100_020).collect();
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("pool");
        pool.install(|| {
            let mut v = VecEnv::new(seeds.len(), PhysicsConfig::default());
            v.reset(&seeds, ResetStream::Legacy).expect("reset");
            let mut out = Vec::new();
            for t in 0..25 {
                let actions: Vec<[f64; 2]> = v.observe(|e| pushing_actions(e, t));
                out.push(v.step(&actions).expect("step"));
            }
            out
        })
    };
    let one = run(1);
    assert_eq!(one, run(3));
    assert_eq!(one, run(2));
    // A small batch runs on the calling thread and gives the same steps.
    let small = {
        let mut v = VecEnv::new(4, PhysicsConfig::default());
        v.reset(&seeds[..4], ResetStream::Legacy).expect("reset");
        let mut out = Vec::new();
        for t in 0..25 {
            let actions: Vec<[f64; 2]> = v.observe(|e| pushing_actions(e, t));
            out.push(v.step(&actions).expect("step"));
        }
        out
    };
    for (t, (a, b)) in small.iter().zip(&one).enumerate() {
        assert_eq!(a[..], b[..4], "step {t}");
    }
    let mut v = VecEnv::new(2, PhysicsConfig::default());
    assert!(matches!(
        v.step(&[[1.0, 1.0]]),
        Err(SimError::BatchSize {
            actions: 1,
            envs: 2
        })
    ));
}

/// Worker blocks keep the environments' order in resets, observations and mutable access,
/// and a tick after the workers have parked (idle past `WORKER_SPIN`) wakes them and gives
/// the steps a plain loop gives.
#[test]
fn vec_env_workers_keep_order_and_wake_from_parking() {
    let seeds: Vec<u64> = (200..212).collect();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(3)
        .build()
        .expect("pool");
    let mut v = pool.install(|| VecEnv::new(seeds.len(), PhysicsConfig::default()));
    assert_eq!(v.threads(), 3);
    assert_eq!(VecEnv::new(4, PhysicsConfig::default()).threads(), 1);
    let mut plain: Vec<PushT> = seeds.iter().map(|_| PushT::default()).collect();
    let states = v.reset(&seeds, ResetStream::Pcg64).expect("reset");
    for (e, (&seed, s)) in plain.iter_mut().zip(seeds.iter().zip(&states)) {
        assert_eq!(&e.reset(seed, ResetStream::Pcg64).expect("reset"), s);
    }
    assert_eq!(
        v.observe(|e| e.state_obs()),
        plain.iter().map(PushT::state_obs).collect::<Vec<_>>()
    );
    let mut order = Vec::new();
    v.for_each_mut(|i, _| order.push(i));
    assert_eq!(order, (0..seeds.len()).collect::<Vec<_>>());
    for t in 0..6 {
        if t == 3 {
            std::thread::sleep(mte_sim::vec_env::WORKER_SPIN * 20);
        }
        let actions: Vec<[f64; 2]> = v.observe(|e| pushing_actions(e, t));
        let got = v.step(&actions).expect("step");
        let want: Vec<_> = plain
            .iter_mut()
            .zip(&actions)
            .map(|(e, &a)| e.step(a).expect("step"))
            .collect();
        assert_eq!(got, want, "tick {t}");
    }
    assert!(matches!(
        v.reset(&seeds[1..], ResetStream::Pcg64),
        Err(SimError::BatchSize {
            actions: 11,
            envs: 12
        })
    ));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]
    /// Whatever the (finite) actions, the state stays finite and coverage in [0, 1].
    #[test]
    fn random_actions_keep_the_state_finite(seed in 0u64..1000,
                                           actions in proptest::collection::vec((-200.0f64..700.0, -200.0f64..700.0), 1..30)) {
        let mut env = PushT::default();
        env.reset(seed, ResetStream::Pcg64).expect("reset");
        for (x, y) in actions {
            let info = env.step([x, y]).expect("finite action");
            prop_assert!(env.state().to_array().iter().all(|v| v.is_finite()));
            prop_assert!((0.0..=1.0).contains(&info.coverage));
        }
    }
}
