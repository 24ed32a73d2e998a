//! Generation end to end: files numpy can read, exact statistics, determinism across thread
//! counts, and the windowed sampler over a generated dataset.

use mte_data::dataset::names;
use mte_data::{Dataset, GenerateConfig, ObsSet, WindowSampler, generate};

fn config() -> GenerateConfig {
    GenerateConfig {
        episodes: 3,
        seed: 7,
        obs: ObsSet {
            state: true,
            keypoints: true,
            pixels: true,
        },
        image_size: (24, 16),
        max_steps: 12,
        ..GenerateConfig::default()
    }
}

fn run_in_pool(threads: usize, dir: &std::path::Path) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("pool");
    let seen = std::sync::Mutex::new(Vec::new());
    pool.install(|| {
        generate(&config(), dir, &|m| {
            seen.lock().expect("lock").push(m.index)
        })
        .expect("generate")
    });
    assert_eq!(
        seen.into_inner().expect("lock"),
        vec![0, 1, 2],
        "reported in order"
    );
}

#[test]
fn generated_dataset_loads_and_is_thread_count_independent() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
    run_in_pool(1, &a);
    run_in_pool(2, &b);
    for f in [
        "info.json",
        "episodes.jsonl",
        "stats.json",
        "data/action.npy",
        "data/observation.image.npy",
    ] {
        let (x, y) = (
            std::fs::read(a.join(f)).expect("a"),
            std::fs::read(b.join(f)).expect("b"),
        );
        assert!(x == y, "{f} differs between 1 and 2 threads");
    }

    let d = Dataset::load(&a).expect("load");
    assert_eq!(d.episodes.len(), 3);
    let frames: usize = d.episodes.iter().map(|e| e.length).sum();
    assert_eq!(d.info.frames, frames);
    assert!(
        d.episodes.iter().all(|e| e.length == 12),
        "12-step limit, no early success"
    );
    assert_eq!(d.episodes[1].seed, 8);
    assert_eq!(
        d.images.as_ref().expect("images").len(),
        frames * 16 * 24 * 3
    );
    assert_eq!(d.feature(names::ENV_STATE).expect("kp").len(), frames * 16);

    // Statistics equal a direct computation over the stored actions.
    let act = d.feature(names::ACTION).expect("action");
    let xs: Vec<f64> = act.chunks(2).map(|r| f64::from(r[0])).collect();
    let mean = xs.iter().sum::<f64>() / xs.len() as f64;
    let st = &d.stats[names::ACTION];
    assert!((st.mean[0] - mean).abs() < 1e-9);
    assert_eq!(
        st.max[0],
        xs.iter().copied().fold(f64::NEG_INFINITY, f64::max)
    );

    // The last frame of each (truncated) episode is done; frame indices restart per episode.
    let done = d.feature(names::DONE).expect("done");
    let fi = d.feature(names::FRAME_INDEX).expect("frame index");
    for e in &d.episodes {
        assert_eq!(done[e.start + e.length - 1], 1.0);
        assert_eq!(fi[e.start], 0.0);
    }

    // The sampler covers every frame and never crosses an episode boundary.
    let s = WindowSampler::new(&d.episode_lengths(), 16, 2, 8).expect("sampler");
    assert_eq!(s.len(), 3 * (12 + 2 + 8 - 1 - 16));
    let ep = d.feature(names::EPISODE_INDEX).expect("episode index");
    for i in 0..s.len() {
        let w = s.window(i).expect("window");
        assert!(w.frames.iter().all(|&f| ep[f] as usize == w.episode));
    }

    // Writing into an existing dataset is refused rather than overwriting it.
    assert!(generate(&config(), &a, &|_| {}).is_err());
}

#[test]
fn obs_list_parses_and_rejects_unknown_names() {
    let o: ObsSet = "state, pixels".parse().expect("valid");
    assert!(o.state && o.pixels && !o.keypoints);
    let e = "state,depth"
        .parse::<ObsSet>()
        .expect_err("unknown")
        .to_string();
    assert!(e.contains("depth"), "{e}");
}

#[test]
fn concatenated_datasets_equal_one_generated_whole() {
    let tmp = tempfile::tempdir().expect("tmp");
    let make = |name: &str, seed: u64, episodes: usize| {
        let dir = tmp.path().join(name);
        let c = GenerateConfig {
            seed,
            episodes,
            ..config()
        };
        generate(&c, &dir, &|_| {}).expect("generate");
        Dataset::load(&dir).expect("load")
    };
    let whole = make("whole", 7, 3);
    let parts = vec![make("a", 7, 1), make("b", 8, 2)];
    let joined = Dataset::concat(parts).expect("same features");
    assert_eq!(joined.episodes, whole.episodes);
    assert_eq!(joined.floats, whole.floats);
    assert_eq!(joined.images, whole.images);
    assert_eq!(
        (joined.info.episodes, joined.info.frames),
        (whole.info.episodes, whole.info.frames)
    );
    for (name, s) in &whole.stats {
        let j = &joined.stats[name];
        assert_eq!(
            (&j.min, &j.max, j.count),
            (&s.min, &s.max, s.count),
            "{name}"
        );
        for (a, b) in j.mean.iter().zip(&s.mean).chain(j.std.iter().zip(&s.std)) {
            assert!((a - b).abs() < 1e-9 * (1.0 + b.abs()), "{name}: {a} vs {b}");
        }
    }
    // A part without images is refused, naming its position.
    let no_pixels = {
        let dir = tmp.path().join("kp");
        let c = GenerateConfig {
            obs: ObsSet {
                state: true,
                keypoints: true,
                pixels: false,
            },
            ..config()
        };
        generate(&c, &dir, &|_| {}).expect("generate");
        Dataset::load(&dir).expect("load")
    };
    let e = Dataset::concat(vec![whole, no_pixels])
        .expect_err("different features")
        .to_string();
    assert!(e.contains("dataset 1"), "{e}");
    assert!(Dataset::concat(Vec::new()).is_err());
}
