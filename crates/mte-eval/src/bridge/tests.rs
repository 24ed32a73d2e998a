//! The bridge against its own worker, with the worker's pure-Python `toy:` target: needs a
//! `python3` (>= 3.9) on PATH, or `MTE_PYTHON`, and nothing else.

use std::time::Instant;

use mte_policy::{ChunkPolicy, ObsNeeds, Observation, PolicyError};
use rand::RngCore;

use super::*;
use crate::corruption::CorruptionSpec;
use crate::pusht::{EpisodeSpec, Execution, RolloutError, run_episode_in};

const STATE: ObsNeeds = ObsNeeds {
    env_state: false,
    image: None,
    wrist_image: false,
};

fn toy(options: &str, needs: ObsNeeds, timeout_s: f64) -> Result<BridgeEnv, EnvError> {
    let target: Target = format!("toy:{options}").parse().expect("toy target");
    let opts = BridgeOptions {
        timeout_s,
        ..BridgeOptions::default()
    };
    BridgeEnv::spawn(&target, needs, &opts)
}

#[test]
fn targets_parse_and_print_back() {
    for s in [
        "toy:",
        "toy:crash-at=3",
        "gym:gym_pusht/PushT-v0",
        "gym:gym_pusht/PushT-v0?obs_type=state&observation_width=96",
        "gym:a.b/C-v1",
        "robomimic:lift",
        "robomimic:can",
        "robomimic:square",
    ] {
        let t: Target = s.parse().unwrap_or_else(|e| panic!("{s}: {e}"));
        assert_eq!(t.to_string(), s);
    }
    for bad in [
        "pusht",
        "gym:PushT-v0",
        "gym:/X",
        "gym:m/",
        "robomimic:tool_hang",
        "mujoco:x",
    ] {
        let e = bad.parse::<Target>().expect_err(bad);
        assert!(e.to_string().contains(bad), "{e}");
    }
    assert_eq!(
        Target::Robomimic(RobomimicTask::Can).setup_name(),
        Some("robomimic")
    );
    assert_eq!(
        "gym:m/E".parse::<Target>().map(|t| t.setup_name()),
        Ok(None)
    );
}

#[test]
fn a_missing_setup_names_the_command() {
    let opts = BridgeOptions {
        python: None,
        ..BridgeOptions::default()
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let e = opts
        .interpreter_in(&Target::Robomimic(RobomimicTask::Lift), None, dir.path())
        .expect_err("no environment there");
    let text = e.to_string();
    assert!(text.contains("tools/env-setup robomimic"), "{text}");
    assert!(matches!(e, BridgeError::NotSetUp { .. }));
    // MTE_PYTHON wins over the setup's environment; an explicit option over both.
    let p = opts
        .interpreter_in(
            &Target::Robomimic(RobomimicTask::Lift),
            Some("/x/python".into()),
            dir.path(),
        )
        .expect("MTE_PYTHON");
    assert_eq!(p, PathBuf::from("/x/python"));
    let explicit = BridgeOptions {
        python: Some("/y/python".into()),
        ..opts
    };
    let p = explicit
        .interpreter_in(
            &Target::Robomimic(RobomimicTask::Lift),
            Some("/x/python".into()),
            dir.path(),
        )
        .expect("explicit");
    assert_eq!(p, PathBuf::from("/y/python"));
}

#[test]
fn the_toy_resets_observes_and_steps_through_the_worker() -> Result<(), EnvError> {
    let needs = ObsNeeds {
        env_state: true,
        image: Some((3, 2)),
        wrist_image: false,
    };
    let mut env = toy("", needs, 30.0)?;
    assert_eq!(env.action_dim(), 1);
    let s0 = env.reset(3)?;
    assert!(
        (s0 - (1.0 - (3.0f64 / 7.0 - 0.9).abs())).abs() < 1e-12,
        "{s0}"
    );
    let o = env.observe(needs)?;
    assert_eq!(o.state, vec![(3.0f64 / 7.0) as f32]);
    assert_eq!(o.env_state, Some(vec![0.9, 0.0]));
    let level = (255.0 * (3.0f64 / 7.0)) as u8;
    assert_eq!(o.image, Some(vec![level; 2 * 3 * 3]));
    let out = env.step(&[0.9])?;
    assert!(!out.success);
    let x = (3.0f64 / 7.0) + 0.5 * (0.9 - 3.0f64 / 7.0);
    assert!(
        (out.score - (1.0 - (x - 0.9).abs())).abs() < 1e-6,
        "{out:?}"
    );
    // A request of the wrong shape is refused before it reaches the worker.
    assert!(matches!(
        env.step(&[0.1, 0.2]),
        Err(EnvError::ActionShape {
            got: 2,
            expected: 1
        })
    ));
    // Observing with other needs than the worker was started for is a protocol error.
    let e = env.observe(STATE).expect_err("other needs");
    assert!(e.to_string().contains("started for"), "{e}");
    // Seeded resets repeat.
    env.reset(5)?;
    let a = env.observe(needs)?;
    env.step(&[0.2])?;
    env.reset(5)?;
    assert_eq!(env.observe(needs)?, a);
    Ok(())
}

#[test]
fn the_toys_expert_solves_it_through_the_worker() -> Result<(), EnvError> {
    let mut env = toy("", STATE, 30.0)?;
    let ep = run_expert(&mut env, 2, 50, STATE)?;
    assert!(
        ep.success && ep.steps == ep.frames.len() && ep.steps < 50,
        "{ep:?}"
    );
    assert!(
        ep.frames
            .iter()
            .all(|(o, a)| o.state.len() == 1 && a == &[0.9])
    );
    // From x = 2/7, halving the distance to 0.9 each step: within 0.01 after 6 steps.
    assert_eq!(ep.steps, 6);
    Ok(())
}

#[test]
fn a_crashed_worker_is_a_typed_error_with_its_stderr() -> Result<(), EnvError> {
    let mut env = toy("crash-at=2", STATE, 30.0)?;
    env.reset(0)?;
    env.step(&[0.5])?;
    let e = env.step(&[0.5]).expect_err("crashes at step 2");
    let text = e.to_string();
    assert!(
        matches!(e, EnvError::Bridge(BridgeError::Exited { .. })),
        "{text}"
    );
    assert!(text.contains("crashing at step 2 as asked"), "{text}");
    assert!(text.contains("exit status: 3"), "{text}");
    // Every later call reports the failure instead of talking to a dead process.
    let again = env.reset(0).expect_err("dead");
    assert!(again.to_string().contains("failed earlier"), "{again}");
    Ok(())
}

#[test]
fn a_hung_worker_is_killed_after_the_timeout() -> Result<(), EnvError> {
    let mut env = toy("hang-at=1", STATE, 1.0)?;
    env.reset(0)?;
    let t = Instant::now();
    let e = env.step(&[0.5]).expect_err("hangs");
    assert!(t.elapsed().as_secs_f64() < 30.0, "waited {:?}", t.elapsed());
    let text = e.to_string();
    assert!(
        matches!(e, EnvError::Bridge(BridgeError::Hung { .. })),
        "{text}"
    );
    assert!(text.contains("hanging at step 1 as asked"), "{text}");
    Ok(())
}

#[test]
fn a_refused_request_carries_the_workers_message() {
    let target: Target = "gym:no_such_module_mte/X-v0".parse().expect("target");
    let e = BridgeEnv::spawn(&target, STATE, &BridgeOptions::default()).expect_err("no module");
    let text = e.to_string();
    assert!(
        matches!(e, EnvError::Bridge(BridgeError::Refused { .. })),
        "{text}"
    );
    assert!(
        text.contains("No module named") || text.contains("no_such_module_mte"),
        "{text}"
    );
}

#[test]
fn the_wrist_camera_comes_through_the_worker_or_is_refused() -> Result<(), EnvError> {
    let needs = ObsNeeds {
        env_state: false,
        image: Some((3, 2)),
        wrist_image: true,
    };
    let mut env = toy("", needs, 30.0)?;
    env.reset(3)?;
    let o = env.observe(needs)?;
    let level = (255.0 * (3.0f64 / 7.0)) as u8;
    assert_eq!(o.image, Some(vec![level; 2 * 3 * 3]));
    assert_eq!(o.wrist_image, Some(vec![255 - level; 2 * 3 * 3]));
    // Without the wrist camera, the reply carries none.
    let mut env = toy(
        "",
        ObsNeeds {
            wrist_image: false,
            ..needs
        },
        30.0,
    )?;
    env.reset(3)?;
    let o = env.observe(ObsNeeds {
        wrist_image: false,
        ..needs
    })?;
    assert_eq!(o.wrist_image, None);
    // A wrist camera without frames to size it, or on a target without one: refused at hello.
    let e = toy(
        "",
        ObsNeeds {
            image: None,
            ..needs
        },
        30.0,
    )
    .expect_err("no image size");
    assert!(
        matches!(e, EnvError::Bridge(BridgeError::Refused { .. })),
        "{e}"
    );
    assert!(e.to_string().contains("ask for image too"), "{e}");
    let gym: Target = "gym:gym_pusht/PushT-v0".parse().expect("target");
    let e = BridgeEnv::spawn(&gym, needs, &BridgeOptions::default()).expect_err("gym");
    assert!(e.to_string().contains("has no wrist camera"), "{e}");
    Ok(())
}

/// Heads for 0.9 in every row of its chunk.
struct GoToGoal;

impl ChunkPolicy for GoToGoal {
    fn horizon(&self) -> usize {
        4
    }
    fn n_obs_steps(&self) -> usize {
        1
    }
    fn action_dim(&self) -> usize {
        1
    }
    fn needs(&self) -> ObsNeeds {
        STATE
    }
    fn predict_chunk(
        &self,
        _: &[Observation],
        _: &mut dyn RngCore,
    ) -> Result<Vec<f32>, PolicyError> {
        Ok(vec![0.9; 4])
    }
}

fn episode(execution: Execution) -> EpisodeSpec<'static> {
    EpisodeSpec {
        needs: STATE,
        seed: 1,
        stream: Default::default(),
        h: 2,
        max_steps: 50,
        execution,
        corruption: &CorruptionSpec::CLEAN,
        noise_seed: 0,
        sampling: Default::default(),
        monitors: &[],
        span: None,
    }
}

#[test]
fn the_runner_runs_episodes_in_a_worker_and_records_a_crash_as_a_failed_episode() {
    let mut env = toy("", STATE, 30.0).expect("toy");
    let arm = Execution::Ensemble("median".parse().expect("median"));
    let rec = run_episode_in(
        &mut env,
        &GoToGoal,
        &episode(arm),
        &mut crate::episode::NoObserver,
    )
    .expect("episode");
    assert!(rec.success, "{rec:?}");
    assert!(rec.steps < 50 && rec.max_coverage > 0.99, "{rec:?}");
    let mut env = toy("crash-at=3", STATE, 30.0).expect("toy");
    let e = run_episode_in(
        &mut env,
        &GoToGoal,
        &episode(arm),
        &mut crate::episode::NoObserver,
    )
    .expect_err("crash");
    assert!(
        matches!(
            e,
            RolloutError::Env(EnvError::Bridge(BridgeError::Exited { .. }))
        ),
        "{e}"
    );
}

#[test]
fn expert_demonstrations_become_a_dataset_in_seed_order() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("demos");
    let config = expert::DemoConfig {
        target: "toy:".parse().expect("toy"),
        episodes: 5,
        first_seed: 10,
        max_steps: 50,
        image: None,
        wrist_image: false,
        successes_only: true,
        workers: 2,
    };
    let info =
        expert::generate(&config, &out, &BridgeOptions::default(), &|_| {}).expect("generate");
    assert_eq!(info.episodes, 5);
    let ds = mte_data::Dataset::load(&out).expect("load");
    let seeds: Vec<u64> = ds.episodes.iter().map(|e| e.seed).collect();
    assert_eq!(
        seeds,
        vec![10, 11, 12, 13, 14],
        "seed order whichever worker ran each"
    );
    assert!(ds.episodes.iter().all(|e| e.success));
    assert_eq!(ds.info.features["observation.state"].shape, vec![1]);
    assert_eq!(
        ds.info.features["observation.environment_state"].shape,
        vec![2]
    );
    assert_eq!(ds.info.features["action"].shape, vec![1]);
    let actions = ds.feature("action").expect("action");
    assert!(actions.iter().all(|&a| a == 0.9), "the toy's expert");
    let frames: usize = ds.episodes.iter().map(|e| e.length).sum();
    assert_eq!(actions.len(), frames);
    // Only the last frame of an episode is done, with reward 1 (all succeeded).
    let done = ds.feature("next.done").expect("done");
    assert_eq!(done.iter().filter(|&&d| d == 1.0).count(), 5);
    // Zero episodes is refused with the field named.
    let e = expert::generate(
        &expert::DemoConfig {
            episodes: 0,
            ..config
        },
        &dir.path().join("x"),
        &BridgeOptions::default(),
        &|_| {},
    )
    .expect_err("zero");
    assert!(e.to_string().contains("`episodes` = 0"), "{e}");
}

#[test]
fn expert_demonstrations_record_the_wrist_camera_beside_the_frames() {
    let dir = tempfile::tempdir().expect("tempdir");
    let config = expert::DemoConfig {
        target: "toy:".parse().expect("toy"),
        episodes: 2,
        first_seed: 3,
        max_steps: 50,
        image: Some((3, 2)),
        wrist_image: true,
        successes_only: false,
        workers: 1,
    };
    let out = dir.path().join("demos");
    expert::generate(&config, &out, &BridgeOptions::default(), &|_| {}).expect("generate");
    let ds = mte_data::Dataset::load(&out).expect("load");
    let wrist = mte_data::dataset::names::WRIST_IMAGE;
    assert_eq!(ds.info.features[wrist].shape, vec![2, 3, 3]);
    let frames: usize = ds.episodes.iter().map(|e| e.length).sum();
    let (image, wrist_px) = (ds.images.expect("frames"), &ds.other_images[wrist]);
    assert_eq!(wrist_px.len(), frames * 2 * 3 * 3);
    // The toy's wrist camera is the negative of its frame, frame by frame.
    assert!(image.iter().zip(wrist_px).all(|(a, b)| *a == 255 - *b));
    assert!(ds.stats.contains_key(wrist), "per-channel statistics");
    // The wrist camera without frames to size it is refused with the field named.
    let e = expert::generate(
        &expert::DemoConfig {
            image: None,
            ..config
        },
        &dir.path().join("x"),
        &BridgeOptions::default(),
        &|_| {},
    )
    .expect_err("no image");
    assert!(e.to_string().contains("`wrist_image`"), "{e}");
}

#[test]
fn a_two_camera_policy_trains_on_toy_demos_and_drives_the_worker() {
    use mte_policy::config::{DiffusionConfig, ObsKind};
    let dir = tempfile::tempdir().expect("tempdir");
    let demos = dir.path().join("demos");
    let config = expert::DemoConfig {
        target: "toy:".parse().expect("toy"),
        episodes: 2,
        first_seed: 3,
        max_steps: 50,
        image: Some((40, 40)),
        wrist_image: true,
        successes_only: false,
        workers: 1,
    };
    expert::generate(&config, &demos, &BridgeOptions::default(), &|_| {}).expect("generate");
    let mut policy_config = DiffusionConfig::cpu(ObsKind::Image)
        .with_wrist_camera()
        .with_overrides(&serde_json::json!({
            "down_dims": [8, 16], "n_groups": 4, "diffusion_step_embed_dim": 8,
            "spatial_softmax_num_keypoints": 4, "num_inference_steps": 2, "crop_shape": [32, 32],
            "horizon": 4, "n_action_steps": 2
        }))
        .expect("config");
    crate::train_data::fit_shapes(
        &mut policy_config,
        &mte_data::Info::read(&demos).expect("info"),
    );
    policy_config.validate().expect("fitted");
    assert_eq!(
        policy_config.input_features["observation.images.wrist"].shape,
        vec![3, 40, 40]
    );
    let data = crate::train_data::load(&demos, &policy_config, Default::default()).expect("data");
    assert!(data.wrist_images.is_some());
    // Trained end to end, and with the encoder frozen (each frame's two cameras cached).
    for freeze_encoder in [false, true] {
        let out = dir.path().join(format!("policy-{freeze_encoder}"));
        let train = mte_policy::train::TrainConfig {
            steps: 2,
            batch_size: 4,
            checkpoint_every: 100,
            freeze_encoder,
            ..Default::default()
        };
        let report = mte_policy::train::train(
            &policy_config,
            &train,
            &data,
            &out,
            &candle_core::Device::Cpu,
            &|_, _, _| {},
        )
        .expect("train");
        assert!(report.final_loss.is_some_and(f32::is_finite), "{report:?}");
        let policy = mte_policy::checkpoint::load(&out, &candle_core::Device::Cpu).expect("load");
        assert!(policy.needs().wrist_image);
        let mut env = toy("", policy.needs(), 30.0).expect("toy with both cameras");
        let spec = EpisodeSpec {
            needs: policy.needs(),
            max_steps: 6,
            ..episode(Execution::Ensemble("median".parse().expect("median")))
        };
        let rec = run_episode_in(&mut env, &policy, &spec, &mut crate::episode::NoObserver)
            .expect("an episode on both cameras");
        assert_eq!(rec.steps, 6, "{rec:?}");
    }
    // Demonstrations without the wrist camera cannot feed this policy: named, with the option.
    let plain = dir.path().join("plain");
    let config = expert::DemoConfig {
        wrist_image: false,
        ..config
    };
    expert::generate(&config, &plain, &BridgeOptions::default(), &|_| {}).expect("generate");
    let e = crate::train_data::load(&plain, &policy_config, Default::default())
        .expect_err("no wrist frames");
    assert!(e.to_string().contains("--obs pixels,wrist"), "{e}");
}
