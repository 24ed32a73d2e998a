//! Corrective demonstrations: the expert's frames start exactly where the policy left the
//! episode, the dataset does not depend on the thread count, and bad settings are refused.

use mte_data::{Dataset, GenerateConfig, ObsSet};
use mte_eval::corruption::CorruptionSpec;
use mte_eval::environment::PushTEnv;
use mte_eval::episode::NoObserver;
use mte_eval::expert_policy::PushTExpertPolicy;
use mte_eval::pusht::{EpisodeSpec, Sampling, run_episode_in};
use mte_eval::takeover::{TakeoverConfig, TakeoverEpisode, TakeoverError, generate_takeover};
use mte_policy::ChunkPolicy;

fn policy() -> PushTExpertPolicy {
    "expert:pusht".parse().expect("the expert as a policy")
}

fn config() -> TakeoverConfig {
    TakeoverConfig {
        record: GenerateConfig {
            episodes: 3,
            seed: 40,
            obs: ObsSet {
                state: true,
                keypoints: true,
                pixels: true,
                wrist: false,
            },
            image_size: (16, 16),
            max_steps: 50,
            ..GenerateConfig::default()
        },
        execution: "ewm:0.01".parse().expect("arm"),
        h: 2,
        switch: (5, 30),
        noise_seed: 9,
    }
}

fn run(threads: usize, dir: &std::path::Path) -> Vec<TakeoverEpisode> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("pool");
    let seen = std::sync::Mutex::new(Vec::new());
    let p = policy();
    pool.install(|| {
        generate_takeover(&p, "expert:pusht", &config(), dir, &|e| {
            seen.lock().expect("lock").push(e.clone())
        })
    })
    .expect("takeover");
    seen.into_inner().expect("lock")
}

#[test]
fn the_expert_records_from_the_state_the_policy_reached() {
    let tmp = tempfile::tempdir().expect("tmp");
    let (one, two) = (tmp.path().join("one"), tmp.path().join("two"));
    let episodes = run(1, &one);
    assert_eq!(episodes, run(2, &two), "reported alike");
    for f in [
        "info.json",
        "episodes.jsonl",
        "stats.json",
        "data/action.npy",
    ] {
        let read = |d: &std::path::Path| std::fs::read(d.join(f)).expect("file");
        assert!(
            read(&one) == read(&two),
            "{f} differs between 1 and 2 threads"
        );
    }
    let c = config();
    let d = Dataset::load(&one).expect("load");
    let recorded: Vec<&TakeoverEpisode> = episodes.iter().filter(|e| e.frames > 0).collect();
    assert!(
        !recorded.is_empty(),
        "the policy finished every episode early"
    );
    assert_eq!(d.episodes.len(), recorded.len());
    let agent = d.feature("observation.state").expect("state");
    let keypoints = d.feature("observation.environment_state").expect("kp");
    let p = policy();
    for (meta, e) in d.episodes.iter().zip(&recorded) {
        assert_eq!(e.index, (e.seed - c.record.seed) as usize);
        assert_eq!(e.switch, c.switch_of(e.index), "the drawn switch step");
        assert!((c.switch.0..=c.switch.1).contains(&e.switch));
        assert_eq!(meta.length, e.frames);
        assert!(e.frames <= c.record.max_steps - e.switch);
        // The same policy episode, stopped at the switch: its last state is the first frame.
        let spec = EpisodeSpec {
            needs: p.needs(),
            seed: e.seed,
            stream: c.record.stream,
            h: c.h,
            max_steps: e.switch,
            execution: c.execution,
            corruption: &CorruptionSpec::CLEAN,
            noise_seed: c.noise_seed,
            sampling: Sampling::Independent,
            monitors: &[],
            span: None,
        };
        let mut env = PushTEnv::new(c.record.stream);
        let r = run_episode_in(&mut env, &p, &spec, &mut NoObserver).expect("episode");
        assert_eq!((r.steps, r.success), (e.switch, false));
        let sim = env.into_sim();
        let s = sim.state_obs();
        let f0 = meta.start;
        assert_eq!(agent[2 * f0..2 * f0 + 2], [s[0] as f32, s[1] as f32]);
        let kp: Vec<f32> = sim.keypoints().iter().map(|&v| v as f32).collect();
        assert_eq!(keypoints[16 * f0..16 * f0 + 16], kp[..]);
        assert!((e.coverage_at_switch - sim.coverage()).abs() < 1e-12);
        assert!(e.max_coverage >= e.coverage_at_switch);
    }
}

#[test]
fn switch_steps_outside_the_episode_are_refused() {
    let tmp = tempfile::tempdir().expect("tmp");
    for (switch, h) in [((0, 10), 2), ((20, 10), 2), ((5, 50), 2), ((5, 10), 0)] {
        let c = TakeoverConfig {
            switch,
            h,
            ..config()
        };
        let e =
            generate_takeover(&policy(), "expert", &c, tmp.path(), &|_| {}).expect_err("refused");
        assert!(matches!(e, TakeoverError::Config { .. }), "{e}");
        let text = e.to_string();
        assert!(
            text.contains(if h == 0 { "`h`" } else { "`switch`" }),
            "{text}"
        );
    }
    assert!(
        !tmp.path().join("info.json").exists(),
        "nothing written for a refused configuration"
    );
}
