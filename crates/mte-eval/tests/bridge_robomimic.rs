//! robomimic's lift through the environment bridge: seeded resets repeat whatever ran
//! before them in the worker, observations have robomimic's shapes, and the scripted expert
//! lifts the cube.
//!
//! Needs the environment `tools/env-setup robomimic` makes: `tools/bridge-tests` runs these
//! tests with `MTE_PYTHON` pointing at it (`cargo test --workspace --test bridge_robomimic
//! -- --ignored`).

use mte_eval::bridge::{BridgeEnv, BridgeOptions, Target, run_expert};
use mte_eval::environment::Environment;
use mte_policy::ObsNeeds;

fn lift(needs: ObsNeeds) -> BridgeEnv {
    assert!(
        std::env::var_os("MTE_PYTHON").is_some(),
        "set MTE_PYTHON to the Python of tools/env-setup robomimic (tools/bridge-tests does)"
    );
    let target: Target = "robomimic:lift".parse().expect("target");
    BridgeEnv::spawn(&target, needs, &BridgeOptions::default()).expect("robomimic worker")
}

#[test]
#[ignore = "needs robosuite: tools/bridge-tests runs it"]
fn lift_resets_repeat_and_the_expert_lifts_the_cube() {
    let needs = ObsNeeds {
        env_state: true,
        image: None,
        wrist_image: false,
    };
    let mut env = lift(needs);
    assert_eq!(env.action_dim(), 7, "OSC_POSE deltas and the gripper");
    env.reset(100_000).expect("reset");
    let first = env.observe(needs).expect("observe");
    assert_eq!(
        first.state.len(),
        9,
        "eef position, quaternion, gripper joints"
    );
    assert_eq!(
        first.env_state.as_ref().map(Vec::len),
        Some(10),
        "lift's object-state"
    );
    // An episode of another seed in the same worker, then the first seed again.
    let other = run_expert(&mut env, 100_001, 400, needs).expect("expert");
    assert!(
        other.success,
        "the expert lifts seed 100001's cube: {other:?}"
    );
    assert_ne!(
        other.frames[0].0, first,
        "another seed places the cube elsewhere"
    );
    env.reset(100_000).expect("reset");
    assert_eq!(
        env.observe(needs).expect("observe"),
        first,
        "a seeded reset repeats exactly"
    );
    let ep = run_expert(&mut env, 100_000, 400, needs).expect("expert");
    assert!(ep.success && ep.steps < 400, "{:?}", (ep.success, ep.steps));
    assert!(ep.max_score == 1.0);
    // The cube is up: robosuite's lift succeeds once the cube's centre is more than 4 cm
    // above the table offset (z = 0.8 m); resting, it sits at about 0.831 m.
    let z0 = ep.frames[0].0.env_state.as_ref().expect("object-state")[2];
    let end = env.observe(needs).expect("observe");
    let z1 = end.env_state.as_ref().expect("object-state")[2];
    assert!(z0 < 0.84 && z1 > 0.84, "cube z {z0} -> {z1}");
}

#[test]
#[ignore = "needs robosuite and EGL: tools/bridge-tests runs it"]
fn lift_frames_are_84_by_84_and_show_the_scene() {
    let needs = ObsNeeds {
        env_state: false,
        image: Some((84, 84)),
        wrist_image: false,
    };
    let mut env = lift(needs);
    env.reset(100_000).expect("reset");
    let o = env.observe(needs).expect("observe");
    let px = o.image.expect("image");
    assert_eq!(px.len(), 84 * 84 * 3);
    let distinct: std::collections::BTreeSet<u8> = px.iter().copied().collect();
    assert!(
        distinct.len() > 32,
        "a rendered scene, not a blank frame ({} values)",
        distinct.len()
    );
    // Other sizes are refused with the reason.
    let target: Target = "robomimic:lift".parse().expect("target");
    let bad = ObsNeeds {
        env_state: false,
        image: Some((96, 96)),
        wrist_image: false,
    };
    let e = BridgeEnv::spawn(&target, bad, &BridgeOptions::default()).expect_err("96 x 96");
    assert!(e.to_string().contains("84 x 84"), "{e}");
}

#[test]
#[ignore = "needs robosuite and EGL: tools/bridge-tests runs it"]
fn the_wrist_camera_sees_another_view_of_the_same_reset() {
    let needs = ObsNeeds {
        env_state: false,
        image: Some((84, 84)),
        wrist_image: true,
    };
    let mut env = lift(needs);
    env.reset(100_000).expect("reset");
    let a = env.observe(needs).expect("observe");
    let (top, wrist) = (a.image.expect("image"), a.wrist_image.expect("wrist"));
    assert_eq!(wrist.len(), 84 * 84 * 3);
    let distinct: std::collections::BTreeSet<u8> = wrist.iter().copied().collect();
    assert!(
        distinct.len() > 32,
        "a rendered view ({} values)",
        distinct.len()
    );
    assert_ne!(top, wrist, "two cameras, two views");
    // Seeded: the same reset shows the same wrist view.
    env.reset(100_000).expect("reset");
    let b = env.observe(needs).expect("observe");
    assert_eq!(b.wrist_image.as_deref(), Some(&wrist[..]));
    assert_eq!(b.image.as_deref(), Some(&top[..]));
    // Rendering the second camera leaves the agentview frame as a one-camera worker renders it.
    let one = ObsNeeds {
        wrist_image: false,
        ..needs
    };
    let mut alone = lift(one);
    alone.reset(100_000).expect("reset");
    let c = alone.observe(one).expect("observe");
    assert_eq!(c.image.as_deref(), Some(&top[..]));
    assert_eq!(c.wrist_image, None);
}
