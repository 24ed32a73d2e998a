//! The PushT runner with a scripted chunk policy: geometry, schedules, faults, pairing,
//! the bracket guarantee end to end, and sweeps that resume.

use std::collections::HashSet;
use std::sync::Mutex;

use mte_ensemble::Regime;
use mte_eval::Silent;
use mte_eval::corruption::{
    BiasDirection, CandidateCorruption, CorruptionSpec, Fault, OracleMode, QueryAttack, Schedule,
    SensorFault,
};
use mte_eval::pusht::{EpisodeSpec, Execution, ObsNeeds, run_episode};
use mte_eval::record::{EpisodeRecord, Line};
use mte_eval::store::{RunDir, read_lines};
use mte_eval::sweep::{PolicySource, RunOptions, Shard, SweepSpec, run};
use mte_policy::{ChunkPolicy, Observation, PolicyError};
use mte_sim::ResetStream;
use rand::{Rng, RngCore};

/// Heads for the block's centre (mean of the keypoints) with a little sampling noise; a
/// blanked observation (all keypoints zero) makes it predict `wild` instead. Records what
/// every query saw.
struct Scripted {
    wild: f32,
    seen: Mutex<Vec<(bool, u32)>>,
}

impl Scripted {
    fn new(wild: f32) -> Self {
        Self {
            wild,
            seen: Mutex::new(Vec::new()),
        }
    }
}

impl ChunkPolicy for Scripted {
    fn horizon(&self) -> usize {
        16
    }
    fn needs(&self) -> ObsNeeds {
        NEEDS
    }
    fn n_obs_steps(&self) -> usize {
        2
    }
    fn action_dim(&self) -> usize {
        2
    }
    fn predict_chunk(
        &self,
        history: &[Observation],
        rng: &mut dyn RngCore,
    ) -> Result<Vec<f32>, PolicyError> {
        let kp = history[1].env_state.clone().unwrap_or_default();
        let blank = kp.iter().all(|&v| v == 0.0);
        let draw = rng.next_u32();
        if let Ok(mut s) = self.seen.lock() {
            s.push((blank, draw));
        }
        let (cx, cy) = if blank {
            (self.wild, self.wild)
        } else {
            let n = kp.len() as f32 / 2.0;
            let sx: f32 = kp.iter().step_by(2).sum();
            let sy: f32 = kp.iter().skip(1).step_by(2).sum();
            (sx / n, sy / n)
        };
        let mut out = Vec::with_capacity(32);
        for _ in 0..16 {
            out.push(cx + rng.random_range(-3.0..3.0));
            out.push(cy + rng.random_range(-3.0..3.0));
        }
        Ok(out)
    }
}

const NEEDS: ObsNeeds = ObsNeeds {
    env_state: true,
    image: None,
    wrist_image: false,
};

fn spec<'a>(execution: Execution, corruption: &'a CorruptionSpec, h: usize) -> EpisodeSpec<'a> {
    EpisodeSpec {
        needs: NEEDS,
        seed: 100_000,
        stream: ResetStream::Legacy,
        h,
        max_steps: 120,
        execution,
        corruption,
        noise_seed: 7,
        sampling: Default::default(),
        monitors: &[],
        span: None,
    }
}

fn blank_burst(q: usize) -> CorruptionSpec {
    CorruptionSpec {
        fault: SensorFault::Blank.into(),
        schedule: Schedule::Burst {
            q,
            phase: 0,
            period: None,
        },
    }
}

type TestResult = Result<(), Box<dyn std::error::Error>>;

#[test]
fn covering_counts_follow_the_geometry() -> TestResult {
    let p = Scripted::new(0.0);
    let r = run_episode(
        &p,
        &spec(
            Execution::Ensemble("median".parse()?),
            &CorruptionSpec::CLEAN,
            2,
        ),
    )?;
    assert_eq!(r.m_counts.iter().sum::<u64>(), r.steps as u64);
    // T_p = 16, T_o = 2, h = 2: M grows by one per query (two steps each) up to 7, then
    // alternates between 7 and 8 (the protocol's worked example).
    assert_eq!(&r.m_counts[..7], &[0, 2, 2, 2, 2, 2, 2], "{:?}", r.m_counts);
    assert_eq!(r.m_counts.len(), 9);
    let (m7, m8) = (r.m_counts[7], r.m_counts[8]);
    assert_eq!((m7 + m8) as usize, r.steps - 12);
    assert!(m7.abs_diff(m8) <= 2, "{m7} vs {m8}");
    assert_eq!(r.queries, r.steps.div_ceil(2));
    assert_eq!(r.q_counts, vec![r.steps as u64]);
    assert_eq!(r.bracket, None, "no diagnostics on clean cells");
    let t = r.times;
    assert!(t.ensemble_s > 0.0 && t.total_s > t.policy_s + t.sim_s + t.ensemble_s);
    assert!(t.overhead_s() >= t.ensemble_s * 0.5, "{t:?}");
    Ok(())
}

#[test]
fn blank_bursts_strike_exactly_the_scheduled_queries() -> TestResult {
    let p = Scripted::new(0.0);
    let c = blank_burst(3);
    let r = run_episode(&p, &spec(Execution::OpenLoop, &c, 2))?;
    let seen = p.seen.lock().map_err(|_| "poisoned")?.clone();
    assert_eq!(seen.len(), r.queries);
    for (i, (blank, _)) in seen.iter().enumerate() {
        assert_eq!(*blank, i % 7 < 3, "query {i} (M_min = 7)");
    }
    assert_eq!(
        r.corrupted_queries,
        (0..r.queries).filter(|i| i % 7 < 3).count()
    );
    Ok(())
}

#[test]
fn arms_share_seeds_noise_and_schedule() -> TestResult {
    let c = blank_burst(2);
    let draws = |arm: &str| -> Result<Vec<(bool, u32)>, Box<dyn std::error::Error>> {
        let p = Scripted::new(0.0);
        run_episode(&p, &spec(arm.parse()?, &c, 2))?;
        let s = p.seen.lock().map_err(|_| "poisoned")?.clone();
        Ok(s)
    };
    let (a, b) = (draws("ewm:0.01")?, draws("median")?);
    // The first query sees the same reset and draws the same noise in both arms; the
    // corruption pattern is the same at every query both arms made.
    assert_eq!(a[0], b[0]);
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.0, y.0);
    }
    // Same arm twice: identical.
    assert_eq!(draws("median")?, b);
    Ok(())
}

#[test]
fn the_median_stays_in_the_bracket_where_2q_lt_m_and_the_mean_does_not() -> TestResult {
    let c = blank_burst(3);
    let run = |arm: &str| -> Result<EpisodeRecord, Box<dyn std::error::Error>> {
        Ok(run_episode(
            &Scripted::new(5_000.0),
            &spec(arm.parse()?, &c, 2),
        )?)
    };
    let median = run("median")?;
    let mean = run("mean")?;
    let g = Regime::Guaranteed.index();
    let (bm, be) = (
        median.bracket.ok_or("median diagnostics")?,
        mean.bracket.ok_or("mean diagnostics")?,
    );
    assert!(bm.tallies[g].steps > 0);
    assert_eq!(bm.tallies[g].outside, 0, "the guarantee");
    assert!(be.tallies[g].outside > 0, "the mean is dragged out");
    // q(tau) is measured: bursts of 3 of every 7 queries reach q = 3 or 4 of 7-8.
    assert!(median.q_counts.len() >= 4, "{:?}", median.q_counts);
    Ok(())
}

#[test]
fn oracle_attacks_stay_inside_the_bracket_and_need_an_ensembler() -> TestResult {
    for mode in [OracleMode::Instant, OracleMode::Drift] {
        let c = CorruptionSpec {
            fault: CandidateCorruption::Oracle { mode }.into(),
            schedule: Schedule::Burst {
                q: 3,
                phase: 0,
                period: None,
            },
        };
        let r = run_episode(&Scripted::new(0.0), &spec("median".parse()?, &c, 2))?;
        let b = r.bracket.ok_or("diagnostics")?;
        let steps: u64 = b.tallies.iter().map(|t| t.steps).sum();
        assert!(steps > 0);
        assert_eq!(b.tallies.iter().map(|t| t.outside).sum::<u64>(), 0);
        assert!(run_episode(&Scripted::new(0.0), &spec(Execution::OpenLoop, &c, 2)).is_err());
    }
    Ok(())
}

#[test]
fn a_patch_needs_an_image_policy_and_an_existing_patch() {
    let c = CorruptionSpec {
        fault: Fault::Sensor(SensorFault::Patch {
            path: "no/such/patch".into(),
            step: None,
        }),
        schedule: mte_eval::corruption::Schedule::Dense { start: 0, end: 5 },
    };
    // NEEDS has no camera: refused before anything runs.
    let e = run_episode(&Scripted::new(0.0), &spec(Execution::OpenLoop, &c, 2))
        .expect_err("keypoint policy");
    assert!(e.to_string().contains("image policy"), "{e}");
    let s = EpisodeSpec {
        needs: ObsNeeds {
            image: Some((96, 96)),
            ..NEEDS
        },
        ..spec(Execution::OpenLoop, &c, 2)
    };
    let e = run_episode(&Scripted::new(0.0), &s).expect_err("missing patch directory");
    assert!(e.to_string().contains("no/such/patch"), "{e}");
}

#[test]
fn a_declared_patch_step_must_be_the_file_s() -> TestResult {
    use mte_eval::patch_file::{PatchMeta, save};
    use mte_policy::patch::{PatchConfig, PatchReport};
    let dir = tempfile::tempdir()?;
    let cfg = PatchConfig {
        step: 5e-4,
        ..PatchConfig::default()
    };
    let report = PatchReport {
        texture: vec![0.5; 3 * 4 * 4],
        side: 4,
        origin: (10, 20),
        initial_loss: 0.1,
        epoch_loss: vec![0.2],
    };
    let meta = PatchMeta::new(&cfg, &report, [112.0, 112.0], [96, 96], dir.path());
    save(dir.path(), &meta, &[128; 3 * 4 * 4])?;
    let run = |step: Option<f64>| {
        let c = CorruptionSpec {
            fault: Fault::Sensor(SensorFault::Patch {
                path: dir.path().to_path_buf(),
                step,
            }),
            schedule: Schedule::Dense { start: 0, end: 5 },
        };
        let s = EpisodeSpec {
            needs: ObsNeeds {
                image: Some((96, 96)),
                ..NEEDS
            },
            max_steps: 12,
            ..spec(Execution::OpenLoop, &c, 2)
        };
        run_episode(&Scripted::new(0.0), &s).map(|_| ())
    };
    let e = run(Some(1e-4)).expect_err("1e-4 declared, 5e-4 trained");
    let msg = e.to_string();
    assert!(
        msg.contains("fault.step") && msg.contains("0.0005"),
        "{msg}"
    );
    run(Some(5e-4))?;
    run(None)?;
    Ok(())
}

#[test]
fn bad_stride_is_a_typed_error() {
    let e = run_episode(
        &Scripted::new(0.0),
        &spec(Execution::OpenLoop, &CorruptionSpec::CLEAN, 16),
    );
    assert!(e.is_err_and(|e| e.to_string().contains("`h` = 16")));
}

/// The first `rows` rows of `Scripted`'s chunks: a policy that predicts fewer rows.
struct Shortened(Scripted, usize);

impl ChunkPolicy for Shortened {
    fn horizon(&self) -> usize {
        self.1
    }
    fn needs(&self) -> ObsNeeds {
        self.0.needs()
    }
    fn n_obs_steps(&self) -> usize {
        self.0.n_obs_steps()
    }
    fn action_dim(&self) -> usize {
        self.0.action_dim()
    }
    fn predict_chunk(
        &self,
        history: &[Observation],
        rng: &mut dyn RngCore,
    ) -> Result<Vec<f32>, PolicyError> {
        let mut c = self.0.predict_chunk(history, rng)?;
        c.truncate(self.1 * 2);
        Ok(c)
    }
}

#[test]
fn a_shorter_span_is_a_policy_predicting_fewer_rows() -> TestResult {
    let blank = blank_burst(2);
    for (execution, corruption) in [
        (
            Execution::Ensemble("ewm:0.01".parse()?),
            &CorruptionSpec::CLEAN,
        ),
        (Execution::Ensemble("median".parse()?), &blank),
        (Execution::OpenLoop, &CorruptionSpec::CLEAN),
    ] {
        let base = spec(execution, corruption, 2);
        let spanned = EpisodeSpec {
            span: Some(13),
            ..base
        };
        let a = run_episode(&Scripted::new(900.0), &spanned)?;
        let b = run_episode(&Shortened(Scripted::new(900.0), 14), &base)?;
        let key = |r: &EpisodeRecord| {
            let cov = r.max_coverage.to_bits();
            (cov, r.steps, r.m_counts.clone(), r.q_counts.clone())
        };
        assert_eq!(key(&a), key(&b), "{execution}");
        // The full span is the default.
        let full = EpisodeSpec {
            span: Some(15),
            ..base
        };
        let c = run_episode(&Scripted::new(900.0), &full)?;
        let d = run_episode(&Scripted::new(900.0), &base)?;
        assert_eq!(key(&c), key(&d), "{execution}");
        if execution != Execution::OpenLoop {
            // At h = 2, 13 rows give 6-7 candidates, 15 give 7-8.
            assert_eq!((a.m_counts.len(), d.m_counts.len()), (8, 9), "{execution}");
        }
    }
    for bad in [0, 16] {
        let s = EpisodeSpec {
            span: Some(bad),
            ..spec(Execution::OpenLoop, &CorruptionSpec::CLEAN, 2)
        };
        let e = run_episode(&Scripted::new(0.0), &s).expect_err("span out of range");
        let msg = e.to_string();
        assert!(
            msg.contains("`span`") && msg.contains(&bad.to_string()),
            "{msg}"
        );
        assert!(msg.contains("1..=15"), "{msg}");
    }
    let s = EpisodeSpec {
        span: Some(3),
        ..spec(Execution::OpenLoop, &CorruptionSpec::CLEAN, 4)
    };
    let e = run_episode(&Scripted::new(0.0), &s).expect_err("stride past the span");
    assert!(e.to_string().contains("`h` = 4"), "{e}");
    Ok(())
}

struct Source;

impl PolicySource for Source {
    fn load(&self, path: &str) -> Result<Box<dyn ChunkPolicy + Send + Sync>, PolicyError> {
        if path == "missing" {
            return Err(PolicyError::Input {
                name: "policy",
                reason: "no such policy: missing".into(),
            });
        }
        Ok(Box::new(Scripted::new(5_000.0)))
    }
}

const SPEC: &str = r#"
name = "t"
policies = ["scripted", "missing"]
arms = ["ewm:0.01", "median"]
h = [2]
seeds = { first = 100000, count = 2 }
max_steps = 40

[[corruptions]]
fault = { kind = "blank" }
q = [0, 2]
"#;

#[test]
fn a_sweep_s_span_names_its_cells_and_reaches_every_episode() -> TestResult {
    let text = SPEC.replace("max_steps = 40", "max_steps = 40\nspan = [13]");
    let spec = SweepSpec::from_toml(&text)?;
    let cells = spec.cells();
    assert!(
        cells
            .iter()
            .all(|c| c.id.ends_with("-h2-span13") && c.span == Some(13))
    );
    let manifest = spec.manifest(None, 0);
    let dir = tempfile::tempdir()?;
    let rd = RunDir::create(&dir.path().join("run"), &spec.to_toml()?, &manifest, false)?;
    run(
        &spec,
        &manifest,
        &rd,
        "0/1".parse()?,
        RunOptions::new(1),
        &Source,
        &Silent,
    )?;
    let lines = read_lines(&rd.cell_path(&cells[0].id))?;
    let m_lens: Vec<usize> = lines
        .iter()
        .filter_map(|l| match l {
            Line::Episode(e) => Some(e.m_counts.len()),
            Line::Error(_) => None,
        })
        .collect();
    assert_eq!(
        m_lens,
        vec![8; 4],
        "at most 7 candidates from 13 rows at h = 2"
    );
    let short = SweepSpec::from_toml(&SPEC.replace("max_steps = 40", "max_steps = 40\nspan = [1]"));
    let e = short.expect_err("a span shorter than the stride");
    assert!(e.to_string().contains("`span` = 1"), "{e}");
    let long = SweepSpec::from_toml(&text.replace("span = [13]", "span = [16]"))?;
    let m = long.manifest(None, 0);
    let rd = RunDir::create(&dir.path().join("long"), &long.to_toml()?, &m, false)?;
    let e = run(
        &long,
        &m,
        &rd,
        "0/1".parse()?,
        RunOptions::new(1),
        &Source,
        &Silent,
    );
    let e = e.expect_err("a span past the policy's executable rows");
    assert!(e.to_string().contains("1..=15"), "{e}");
    Ok(())
}

#[test]
fn sweeps_record_every_episode_resume_and_shard() -> TestResult {
    let spec = SweepSpec::from_toml(SPEC)?;
    let cells = spec.cells();
    assert_eq!(cells.len(), 4);
    let manifest = spec.manifest(None, 0);
    let dir = tempfile::tempdir()?;
    let root = dir.path().join("run");
    let rd = RunDir::create(&root, &spec.to_toml()?, &manifest, false)?;
    let s0 = run(
        &spec,
        &manifest,
        &rd,
        "0/2".parse()?,
        RunOptions::new(2),
        &Source,
        &Silent,
    )?;
    let s1 = run(
        &spec,
        &manifest,
        &rd,
        "1/2".parse()?,
        RunOptions::new(1),
        &Source,
        &Silent,
    )?;
    assert_eq!(s0.cells + s1.cells, 4);
    assert_eq!(
        s0.episodes_run + s1.episodes_run,
        8,
        "2 cells x 2 seeds x 2 arms"
    );
    assert_eq!(s0.errors + s1.errors, 8, "the missing policy's cells");
    let ok_cell = &cells[1];
    let lines = read_lines(&rd.cell_path(&ok_cell.id))?;
    let keys: HashSet<(String, u64)> = lines
        .iter()
        .filter_map(|l| match l {
            Line::Episode(e) => Some((e.arm.clone(), e.seed)),
            Line::Error(_) => None,
        })
        .collect();
    assert_eq!(keys.len(), 4);
    // Resume: nothing new to run in the good cells.
    let rd = RunDir::create(&root, "", &manifest, true)?;
    let again = run(
        &spec,
        &manifest,
        &rd,
        Shard::default(),
        RunOptions::new(2),
        &Source,
        &Silent,
    )?;
    assert_eq!(again.episodes_run, 0);
    assert_eq!(again.episodes_skipped, 8);
    // Drop the last finished episode: resume runs exactly that one.
    let path = rd.cell_path(&ok_cell.id);
    let text = std::fs::read_to_string(&path)?;
    let kept: Vec<&str> = text.lines().collect();
    std::fs::write(&path, format!("{}\n", kept[..kept.len() - 1].join("\n")))?;
    let again = run(
        &spec,
        &manifest,
        &rd,
        Shard::default(),
        RunOptions::new(2),
        &Source,
        &Silent,
    )?;
    assert_eq!(again.episodes_run, 1);
    assert!("2/2".parse::<Shard>().is_err());
    assert!(SweepSpec::from_toml(&SPEC.replace("median", "medain")).is_err());
    Ok(())
}

#[test]
fn pgd_cells_differing_only_in_radius_get_their_own_ids() -> TestResult {
    let two_radii = r#"
name = "t"
policies = ["p"]
arms = ["ewm:0.01"]
h = [2]
seeds = { first = 0, count = 1 }
[[corruptions]]
fault = { kind = "pgd", iterations = 20 }
q = [2]
[[corruptions]]
fault = { kind = "pgd", eps = 0.1, iterations = 20 }
q = [2, 0]
[[corruptions]]
fault = { kind = "blank" }
q = [0]
"#;
    let ids: Vec<String> = SweepSpec::from_toml(two_radii)?
        .cells()
        .into_iter()
        .map(|c| c.id)
        .collect();
    assert_eq!(
        ids,
        [
            "p-pgd-20-burst-q2-h2",
            "p-pgd-20-eps0.1-burst-q2-h2",
            "p-clean-h2"
        ],
        "the clean cell named twice is one cell"
    );
    // Two different patches whose files share a name would share a cell id.
    let clash = r#"
name = "t"
policies = ["p"]
arms = ["median"]
h = [2]
seeds = { first = 0, count = 1 }
[[corruptions]]
fault = { kind = "patch", path = "a/x.json" }
q = [2]
[[corruptions]]
fault = { kind = "patch", path = "b/x.json" }
q = [2]
"#;
    let e = SweepSpec::from_toml(clash).expect_err("two cells, one id");
    assert!(e.to_string().contains("p-patch-x.json-burst-q2-h2"), "{e}");
    Ok(())
}

#[test]
fn the_shipped_sweep_specs_parse() -> TestResult {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../sweeps");
    let mut n = 0;
    for entry in std::fs::read_dir(&dir)? {
        let path = entry?.path();
        if path.extension().is_some_and(|e| e == "toml") {
            let spec = SweepSpec::from_toml(&std::fs::read_to_string(&path)?)
                .map_err(|e| format!("{}: {e}", path.display()))?;
            assert!(!spec.cells().is_empty());
            n += 1;
        }
    }
    assert!(n >= 2);
    Ok(())
}

#[test]
fn pgd_bursts_attack_a_real_diffusion_policy_reproducibly() -> TestResult {
    use mte_policy::PgdConfig;
    let p = tiny_diffusion_policy()?;
    let pgd = CorruptionSpec {
        fault: Fault::Query(QueryAttack::Pgd(PgdConfig {
            iterations: 2,
            samples: 1,
            ..PgdConfig::default()
        })),
        schedule: Schedule::Burst {
            q: 2,
            phase: 0,
            period: None,
        },
    };
    let mut s = spec("median".parse()?, &pgd, 2);
    s.max_steps = 16;
    let a = run_episode(&p, &s)?;
    assert_eq!(
        a.corrupted_queries, 3,
        "queries 0, 1 and 7 of 0..8 (M_min = 7)"
    );
    assert!(a.times.corruption_s > 0.0);
    let b = run_episode(&p, &s)?;
    assert_eq!(
        (a.max_coverage, a.steps, &a.q_counts),
        (b.max_coverage, b.steps, &b.q_counts)
    );
    // A policy without an observation gradient refuses PGD with a typed error.
    let e = run_episode(&Scripted::new(0.0), &s);
    assert!(e.is_err_and(|e| e.to_string().contains("PGD")));
    Ok(())
}

#[test]
fn calibration_runs_budgets_in_order_and_stops_when_the_attack_stops_improving() -> TestResult {
    use mte_eval::calibrate::{CalibrationSpec, calibrate};
    let p = tiny_diffusion_policy()?;
    let spec = CalibrationSpec {
        seeds: vec![100_000, 100_001],
        iterations: vec![2, 1, 3],
        steps: vec![0.01],
        // A tolerance no attack can beat: the sweep stops at the second budget.
        tolerance: 10.0,
        max_steps: 12,
        ..CalibrationSpec::default()
    };
    let rows = calibrate(&p, NEEDS, &spec, &Silent)?;
    assert_eq!(rows.len(), 3, "clean, 1 and 2 iterations, then stop");
    assert_eq!(rows[0].iterations, 0);
    assert_eq!((rows[1].iterations, rows[2].iterations), (1, 2));
    assert!(!rows[1].stopped && rows[2].stopped);
    assert!(
        rows.iter()
            .all(|r| (0.0..=1.0).contains(&r.mean_coverage) && r.n == 2)
    );
    assert!(
        calibrate(
            &p,
            NEEDS,
            &CalibrationSpec {
                seeds: vec![],
                ..spec
            },
            &Silent
        )
        .is_err()
    );
    Ok(())
}

/// A randomly initialised (seeded) keypoint Diffusion Policy small enough for tests.
fn tiny_diffusion_policy() -> Result<mte_policy::DiffusionPolicy, Box<dyn std::error::Error>> {
    use mte_policy::config::{DiffusionConfig, ObsKind};
    use mte_policy::{Stats, StatsMap};
    let c = DiffusionConfig::cpu(ObsKind::Keypoints).with_overrides(&serde_json::json!({
        "down_dims": [8, 16], "n_groups": 4, "diffusion_step_embed_dim": 8,
        "num_inference_steps": 2
    }))?;
    let mm = |n: usize| Stats {
        min: vec![0.0; n],
        max: vec![512.0; n],
        mean: vec![256.0; n],
        std: vec![128.0; n],
    };
    let mut stats = StatsMap::new();
    stats.insert("observation.state".into(), mm(2));
    stats.insert("observation.environment_state".into(), mm(16));
    stats.insert("action".into(), mm(2));
    // The VarMap only registers the variables; the policy holds its own tensors.
    let vm = candle_nn::VarMap::new();
    let vb = mte_policy::init::seeded_var_builder(
        &vm,
        1,
        candle_core::DType::F32,
        &candle_core::Device::Cpu,
    );
    Ok(mte_policy::DiffusionPolicy::new(c, stats, vb)?)
}

/// One observed step: tau, m, q, the first candidate, the action.
type Seen = (u64, usize, usize, Vec<f32>, Vec<f32>);

/// Counts what an observer is told.
#[derive(Default)]
struct Watch {
    queries: Vec<(u64, bool, usize)>,
    steps: Vec<Seen>,
    stages: mte_eval::episode::StageTimer,
    stage_calls: [usize; 5],
}

impl mte_eval::episode::EpisodeObserver for Watch {
    fn on_query(&mut self, e: &mte_eval::episode::QueryEvent<'_>) {
        self.queries.push((e.t, e.corrupted, e.chunk.len()));
    }
    fn on_step(&mut self, e: &mte_eval::episode::StepEvent<'_>) {
        assert_eq!(e.candidates.len(), e.corrupted.len());
        let first: Vec<f32> = e.candidates.row(0).to_vec();
        self.steps.push((e.tau, e.m, e.q, first, e.action.to_vec()));
    }
    fn on_stage(&mut self, stage: mte_eval::episode::Stage, seconds: f64) {
        use mte_eval::episode::Stage;
        assert!(
            seconds >= 0.0 && seconds.is_finite(),
            "{stage:?}: {seconds}"
        );
        let k = match stage {
            Stage::Observe => 0,
            Stage::Corrupt => 1,
            Stage::Query => 2,
            Stage::Ensemble => 3,
            Stage::Step => 4,
        };
        self.stage_calls[k] += 1;
        self.stages.on_stage(stage, seconds);
    }
}

#[test]
fn observers_see_every_query_and_step_the_record_counts() -> TestResult {
    let corruption = blank_burst(2);
    for execution in [
        Execution::OpenLoop,
        Execution::Ensemble(mte_ensemble::Aggregator::MEDIAN),
    ] {
        let p = Scripted::new(400.0);
        let mut w = Watch::default();
        let s = spec(execution, &corruption, 2);
        let r = mte_eval::pusht::run_episode_observed(&p, &s, &mut w)?;
        assert_eq!(w.queries.len(), r.queries);
        assert_eq!(
            w.queries.iter().filter(|q| q.1).count(),
            r.corrupted_queries
        );
        assert!(
            w.queries
                .iter()
                .enumerate()
                .all(|(i, q)| q.0 == 2 * i as u64 && q.2 == 32)
        );
        assert_eq!(w.steps.len(), r.steps);
        let mut m_counts = vec![0u64; r.m_counts.len()];
        for (k, st) in w.steps.iter().enumerate() {
            assert_eq!(st.0, k as u64);
            m_counts[st.1] += 1;
        }
        assert_eq!(m_counts, r.m_counts);
        // The record's stage times are the sums of what observers were told, per stage.
        let (t, seen) = (r.times, w.stages.times);
        assert_eq!(
            (
                t.render_s,
                t.corruption_s,
                t.policy_s,
                t.ensemble_s,
                t.sim_s
            ),
            (
                seen.render_s,
                seen.corruption_s,
                seen.policy_s,
                seen.ensemble_s,
                seen.sim_s
            )
        );
        // Observe and step once per control step (and the reset), corrupt and query once
        // per query; the ensemble stage per query and per step.
        assert_eq!(w.stage_calls[0], r.steps);
        assert_eq!(w.stage_calls[4], r.steps + 1);
        assert_eq!((w.stage_calls[1], w.stage_calls[2]), (r.queries, r.queries));
        assert_eq!(w.stage_calls[3], r.queries + r.steps);
        assert!(t.total_s >= t.render_s + t.policy_s + t.sim_s);
        // The observed run is the unobserved run.
        let again = run_episode(&Scripted::new(400.0), &s)?;
        assert_eq!((again.max_coverage, again.steps), (r.max_coverage, r.steps));
    }
    Ok(())
}

/// Common-mode bias acts on the candidates: while the newest query is corrupted every
/// candidate the median sees is shifted, so the median moves by the bias (and the
/// candidates stay unflagged: no clean bracket exists).
#[test]
fn common_mode_bias_shifts_the_candidates_the_aggregator_sees() -> TestResult {
    let shifted = CorruptionSpec {
        fault: Fault::Candidates(CandidateCorruption::CommonMode {
            magnitude: 64.0,
            angle_deg: 0.0,
            direction: BiasDirection::Constant,
        }),
        schedule: Schedule::Dense { start: 0, end: 1 },
    };
    let p = Scripted::new(400.0);
    let mut w = Watch::default();
    let median = Execution::Ensemble(mte_ensemble::Aggregator::MEDIAN);
    let r = mte_eval::pusht::run_episode_observed(&p, &spec(median, &shifted, 2), &mut w)?;
    let clean = CorruptionSpec::CLEAN;
    let mut wc = Watch::default();
    mte_eval::pusht::run_episode_observed(
        &Scripted::new(400.0),
        &spec(median, &clean, 2),
        &mut wc,
    )?;
    // Query 0 (t = 0) is the only corrupted one; it is the newest at tau = 0 and 1.
    assert_eq!(r.corrupted_queries, 1);
    for tau in 0..2 {
        let (b, c) = (&w.steps[tau], &wc.steps[tau]);
        assert_eq!(b.3[0], c.3[0] + 64.0, "candidate at tau {tau}");
        assert_eq!(b.3[1], c.3[1], "the bias is along +x");
        assert_eq!(b.4[0], c.4[0] + 64.0, "action at tau {tau}");
        assert_eq!(b.2, 0, "common-mode candidates are not flagged");
    }
    Ok(())
}

/// The action shifts (x, y) of a median episode under common-mode bias, against the clean
/// episode of the same seed, at the control times `0..n` (the first query is corrupted
/// and newest there).
fn common_mode_shifts(
    direction: BiasDirection,
    seed: u64,
    execution: Execution,
    n: usize,
) -> Result<Vec<(f32, f32)>, Box<dyn std::error::Error>> {
    let shifted = CorruptionSpec {
        fault: Fault::Candidates(CandidateCorruption::CommonMode {
            magnitude: 64.0,
            angle_deg: 0.0,
            direction,
        }),
        schedule: Schedule::Dense { start: 0, end: 1 },
    };
    let run = |c: &CorruptionSpec| -> Result<Watch, Box<dyn std::error::Error>> {
        let mut w = Watch::default();
        let mut s = spec(execution, c, 2);
        s.seed = seed;
        mte_eval::pusht::run_episode_observed(&Scripted::new(400.0), &s, &mut w)?;
        Ok(w)
    };
    let (b, c) = (run(&shifted)?, run(&CorruptionSpec::CLEAN)?);
    Ok((0..n)
        .map(|t| {
            (
                b.steps[t].4[0] - c.steps[t].4[0],
                b.steps[t].4[1] - c.steps[t].4[1],
            )
        })
        .collect())
}

/// A drifting bias turns by its rate each control step; a random one keeps its length, is
/// the same for both arms of a seed and differs between seeds.
#[test]
fn common_mode_bias_drifts_or_is_drawn_per_episode() -> TestResult {
    let median = Execution::Ensemble(mte_ensemble::Aggregator::MEDIAN);
    let near = |a: f32, b: f32| (a - b).abs() < 1e-3;
    let drift = common_mode_shifts(
        BiasDirection::Drift { deg_per_step: 90.0 },
        100_000,
        median,
        2,
    )?;
    assert!(near(drift[0].0, 64.0) && near(drift[0].1, 0.0), "{drift:?}");
    assert!(near(drift[1].0, 0.0) && near(drift[1].1, 64.0), "{drift:?}");
    let mean = Execution::Ensemble(mte_ensemble::Aggregator::Mean);
    let a = common_mode_shifts(BiasDirection::Random, 100_000, median, 2)?;
    let b = common_mode_shifts(BiasDirection::Random, 100_000, mean, 2)?;
    let other = common_mode_shifts(BiasDirection::Random, 100_001, median, 2)?;
    for (x, y) in [a[0], a[1], other[0]] {
        assert!(near(x.hypot(y), 64.0), "length {}", x.hypot(y));
    }
    assert!(
        near(a[0].0, a[1].0) && near(a[0].1, a[1].1),
        "constant within the episode"
    );
    assert!(
        near(a[0].0, b[0].0) && near(a[0].1, b[0].1),
        "paired across arms"
    );
    assert!(!near(a[0].0, other[0].0), "another seed, another direction");
    Ok(())
}

/// A filmed episode is the runner's episode: the same record (but its timings), one frame
/// per control step, and the corrupted steps flagged as the schedule strikes.
#[test]
fn a_film_is_the_episode_with_one_flagged_frame_per_step() -> TestResult {
    let corruption = blank_burst(2);
    let s = spec(
        Execution::Ensemble(mte_ensemble::Aggregator::MEDIAN),
        &corruption,
        2,
    );
    let p = Scripted::new(400.0);
    let film = mte_eval::film::film(&p, &s, 48)?;
    let plain = run_episode(&p, &s)?;
    let strip_times = |mut r: EpisodeRecord| {
        r.times = Default::default();
        r
    };
    assert_eq!(strip_times(film.record.clone()), strip_times(plain.clone()));
    assert_eq!(film.shots.len(), plain.steps);
    assert!(film.shots.iter().all(|f| f.rgb.len() == 48 * 48 * 3));
    // Each corrupted query flags its h = 2 steps (the last query may be cut short).
    let flagged = film.shots.iter().filter(|f| f.corrupted).count();
    assert!(flagged <= 2 * plain.corrupted_queries && flagged + 1 >= 2 * plain.corrupted_queries);
    assert!(plain.corrupted_queries > 0);
    assert!(mte_eval::film::film(&p, &s, 8).is_err(), "panel too small");
    Ok(())
}

/// Fixed sampling gives every query of an episode the same noise stream; independent
/// sampling a different one per query (and the default is independent).
#[test]
fn fixed_sampling_repeats_the_noise_stream_at_every_query() -> TestResult {
    let draws = |sampling| -> Result<Vec<u32>, Box<dyn std::error::Error>> {
        let p = Scripted::new(0.0);
        let s = EpisodeSpec {
            sampling,
            ..spec(Execution::OpenLoop, &CorruptionSpec::CLEAN, 2)
        };
        run_episode(&p, &s)?;
        let seen = p.seen.lock().map_err(|_| "poisoned")?.clone();
        Ok(seen.into_iter().map(|(_, d)| d).collect())
    };
    let fixed = draws(mte_eval::pusht::Sampling::Fixed)?;
    assert!(
        fixed.len() > 2 && fixed.iter().all(|&d| d == fixed[0]),
        "{fixed:?}"
    );
    let independent = draws(mte_eval::pusht::Sampling::Independent)?;
    let distinct: HashSet<u32> = independent.iter().copied().collect();
    assert_eq!(distinct.len(), independent.len());
    assert_eq!(
        independent[0], fixed[0],
        "query 0 draws the same stream either way"
    );
    assert_eq!(
        mte_eval::pusht::Sampling::default(),
        mte_eval::pusht::Sampling::Independent
    );
    Ok(())
}

/// Heads for 0.9: the bridge's toy target (`toy:`) solves under it.
struct TowardsGoal;

impl ChunkPolicy for TowardsGoal {
    fn horizon(&self) -> usize {
        4
    }
    fn needs(&self) -> ObsNeeds {
        ObsNeeds {
            env_state: false,
            image: None,
            wrist_image: false,
        }
    }
    fn n_obs_steps(&self) -> usize {
        1
    }
    fn action_dim(&self) -> usize {
        1
    }
    fn predict_chunk(
        &self,
        _: &[Observation],
        _: &mut dyn RngCore,
    ) -> Result<Vec<f32>, PolicyError> {
        Ok(vec![0.9; 4])
    }
}

struct TowardsGoalSource;

impl PolicySource for TowardsGoalSource {
    fn load(&self, _: &str) -> Result<Box<dyn ChunkPolicy + Send + Sync>, PolicyError> {
        Ok(Box::new(TowardsGoal))
    }
}

/// A sweep whose `env` is a bridge target runs its episodes in workers (the toy target
/// needs only `python3`); a worker that crashes fails its episodes with the worker's
/// message, and the sweep goes on and reports them.
#[test]
fn bridged_sweeps_run_in_workers_and_record_crashes_as_failed_episodes() -> TestResult {
    for (env, crash) in [("toy:", false), ("toy:crash-at=3", true)] {
        let text = format!(
            "name = \"toy\"\npolicies = [\"toy\"]\narms = [\"ewm:0.01\", \"median\"]\nh = [2]\n\
             seeds = [1, 2, 3]\nmax_steps = 30\nenv = \"{env}\"\n[[corruptions]]\nfault = {{ kind = \"none\" }}\nq = [0]\n"
        );
        let spec = SweepSpec::from_toml(&text)?;
        assert_eq!(spec.env.to_string(), env);
        let manifest = spec.manifest(None, 0);
        let dir = tempfile::tempdir()?;
        let rd = RunDir::create(&dir.path().join("run"), &spec.to_toml()?, &manifest, false)?;
        let s = run(
            &spec,
            &manifest,
            &rd,
            Shard::default(),
            RunOptions::new(2),
            &TowardsGoalSource,
            &Silent,
        )?;
        let lines = read_lines(&rd.cell_path(&spec.cells()[0].id))?;
        assert_eq!(lines.len(), 6, "3 seeds x 2 arms, each recorded");
        if crash {
            assert_eq!((s.episodes_run, s.errors), (0, 6));
            for l in &lines {
                let Line::Error(e) = l else {
                    panic!("an episode survived the crash: {l:?}")
                };
                assert!(
                    e.error.contains("crashing at step 3 as asked"),
                    "{}",
                    e.error
                );
            }
        } else {
            assert_eq!((s.episodes_run, s.errors), (6, 0));
            for l in &lines {
                let Line::Episode(e) = l else { panic!("{l:?}") };
                assert!(e.success, "{e:?}");
            }
        }
    }
    Ok(())
}
