//! Lockstep execution gives the records one-episode-at-a-time execution gives: a small
//! sweep with the bundled keypoint and image policies (clean, blank bursts, PGD, a
//! candidate fault; ensembled and open-loop arms) is run alone (`batch = 1`), in lockstep
//! groups of 3 and in one group per cell, and every record but its timings must agree bit
//! for bit. Groups of 3 mix seeds and arms differently from whole cells, so a result that
//! depended on its batch-mates would show.

use std::collections::BTreeMap;
use std::path::Path;

use mte_eval::Silent;
use mte_eval::record::Line;
use mte_eval::store::{RunDir, read_lines};
use mte_eval::sweep::{CheckpointSource, RunOptions, Shard, SweepSpec, run};

type TestResult = Result<(), Box<dyn std::error::Error>>;

/// Record text (timings zeroed) by (cell, arm, seed).
type Records = BTreeMap<(String, String, u64), String>;

fn spec(policy: &str, faults: &str) -> Result<SweepSpec, Box<dyn std::error::Error>> {
    let assets = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/policies");
    let text = format!(
        r#"
name = "lockstep"
policies = ["{}"]
arms = ["ewm:0.01", "median", "open-loop"]
h = [2]
seeds = {{ first = 100000, count = 3 }}
max_steps = 24
{faults}
"#,
        assets.join(policy).display()
    );
    Ok(SweepSpec::from_toml(&text)?)
}

/// `spec` run with `options` into a new run directory (inside the returned temporary
/// directory, which removes it when dropped), no episode failing.
fn run_in_tempdir(
    spec: &SweepSpec,
    options: RunOptions,
) -> Result<(tempfile::TempDir, RunDir), Box<dyn std::error::Error>> {
    let dir = tempfile::tempdir()?;
    let manifest = spec.manifest(None, 0);
    let rd = RunDir::create(&dir.path().join("run"), &spec.to_toml()?, &manifest, false)?;
    let s = run(
        spec,
        &manifest,
        &rd,
        Shard::default(),
        options,
        &CheckpointSource,
        &Silent,
    )?;
    assert_eq!(s.errors, 0, "{s:?}");
    Ok((dir, rd))
}

/// Every episode record of a run of `spec` with `options`, timings zeroed, by (cell, arm,
/// seed); errors as their text.
fn records(spec: &SweepSpec, options: RunOptions) -> Result<Records, Box<dyn std::error::Error>> {
    let (_dir, rd) = run_in_tempdir(spec, options)?;
    let mut out = BTreeMap::new();
    for cell in spec.cells() {
        for line in read_lines(&rd.cell_path(&cell.id))? {
            let Line::Episode(mut e) = line else {
                return Err(format!("an error line in {}", cell.id).into());
            };
            e.times = Default::default();
            out.insert(
                (e.cell.clone(), e.arm.clone(), e.seed),
                serde_json::to_string(&e)?,
            );
        }
    }
    Ok(out)
}

fn same_records_every_way(spec: &SweepSpec, episodes: usize) -> TestResult {
    let alone = records(
        spec,
        RunOptions {
            workers: 2,
            batch: 1,
        },
    )?;
    assert_eq!(alone.len(), episodes);
    for batch in [3, 64] {
        let together = records(spec, RunOptions { workers: 2, batch })?;
        assert_eq!(together.len(), alone.len());
        for (key, rec) in &alone {
            assert_eq!(together.get(key), Some(rec), "batch {batch}: {key:?}");
        }
    }
    // The corruption did something, so equal records are not trivially equal.
    let corrupted = alone
        .values()
        .filter(|r| r.contains("\"corrupted_queries\":0"))
        .count();
    assert!(
        corrupted < alone.len(),
        "some episode had corrupted queries"
    );
    Ok(())
}

#[test]
fn keypoint_policy_lockstep_equals_alone() -> TestResult {
    let s = spec(
        "pusht_keypoints_cpu",
        r#"
[[corruptions]]
fault = { kind = "blank" }
q = [0, 2]

[[corruptions]]
fault = { kind = "pgd", iterations = 2 }
q = [2]

[[corruptions]]
fault = { kind = "common-mode", magnitude = 30.0, angle_deg = 45.0 }
q = [1]
"#,
    )?;
    // 4 cells x 3 seeds x 3 arms.
    same_records_every_way(&s, 36)
}

#[test]
fn image_policy_lockstep_equals_alone() -> TestResult {
    let s = spec(
        "pusht_image_cpu",
        r#"
[[corruptions]]
fault = { kind = "blank" }
q = [2]
"#,
    )?;
    same_records_every_way(&s, 9)
}

/// The alignment of `fault` in bursts of q = 3 over one 40-step episode of the bundled
/// keypoint policy at h = 2, executed by `arm`.
fn align(
    fault: mte_eval::corruption::Fault,
    arm: &str,
) -> Result<mte_eval::alignment::Alignment, Box<dyn std::error::Error>> {
    use mte_eval::corruption::{CorruptionSpec, Schedule};
    use mte_eval::pusht::EpisodeSpec;
    use mte_eval::sweep::PolicySource as _;
    let assets = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/policies");
    let policy = CheckpointSource.load(&assets.join("pusht_keypoints_cpu").to_string_lossy())?;
    let corruption = CorruptionSpec {
        fault,
        schedule: Schedule::Burst {
            q: 3,
            period: None,
            phase: 0,
        },
    };
    let spec = EpisodeSpec {
        needs: policy.needs(),
        seed: 100_000,
        stream: Default::default(),
        h: 2,
        max_steps: 40,
        execution: arm.parse()?,
        corruption: &corruption,
        noise_seed: 0,
        sampling: Default::default(),
        monitors: &[],
        span: None,
    };
    Ok(mte_eval::alignment::alignment(policy.as_ref(), &[spec])?)
}

/// The alignment twin replays the executed chunk's sampling noise on the clean window: with
/// a zero-radius PGD the attacked chunk is the clean one, so every displacement is exactly
/// zero; with a real radius they are not.
#[test]
fn alignment_twins_share_the_executed_noise() -> TestResult {
    use mte_eval::corruption::{Fault, QueryAttack};
    let pgd = |eps: f64| {
        Fault::Query(QueryAttack::Pgd(mte_policy::PgdConfig {
            eps,
            iterations: 2,
            ..mte_policy::PgdConfig::default()
        }))
    };
    let zero = align(pgd(0.0), "open-loop")?;
    assert!(zero.attacked_queries > 0, "{zero:?}");
    assert_eq!(zero.mean_norm, Some(0.0), "{zero:?}");
    assert_eq!(
        zero.pairs, 0,
        "zero displacements have no direction: {zero:?}"
    );
    let real = align(pgd(0.5), "open-loop")?;
    assert_eq!(real.attacked_queries, zero.attacked_queries);
    assert!(real.mean_norm.unwrap_or(0.0) > 0.0, "{real:?}");
    assert!(real.pairs > 0, "{real:?}");
    let m = real.median.ok_or("median")?;
    assert!((-1.0..=1.0).contains(&m), "{real:?}");
    Ok(())
}

/// For a sensor fault the twin is the clean window's chunk with the query's own sampling
/// noise: a zero-sigma noise fault leaves the window as it was, so every displacement is
/// exactly zero; blank keypoints and real noise displace the chunks.
#[test]
fn sensor_fault_twins_share_the_query_noise() -> TestResult {
    use mte_eval::corruption::{Fault, SensorFault};
    let none = align(
        Fault::Sensor(SensorFault::GaussianNoise { sigma: 0.0 }),
        "median",
    )?;
    assert!(none.attacked_queries > 0, "{none:?}");
    assert_eq!(none.mean_norm, Some(0.0), "{none:?}");
    assert_eq!(none.pairs, 0, "{none:?}");
    for fault in [
        SensorFault::Blank,
        SensorFault::GaussianNoise { sigma: 20.0 },
    ] {
        let r = align(Fault::Sensor(fault.clone()), "median")?;
        assert_eq!(r.attacked_queries, none.attacked_queries, "{fault}");
        assert!(r.mean_norm.unwrap_or(0.0) > 0.0, "{fault}: {r:?}");
        assert!(r.pairs > 0, "{fault}: {r:?}");
    }
    Ok(())
}

/// In lockstep an episode's total time is its own work (its stages and its share of the
/// batched policy calls), not the wall time from its start to its end, which would count
/// every other episode of the batch: on one worker the totals add up to at most the run's
/// wall time, and each covers the episode's own stages.
#[test]
fn lockstep_totals_count_only_the_episodes_own_work() -> TestResult {
    let spec = spec(
        "pusht_keypoints_cpu",
        "[[corruptions]]\nfault = { kind = \"none\" }\nq = [0]",
    )?;
    let t = std::time::Instant::now();
    let options = RunOptions {
        workers: 1,
        batch: 64,
    };
    let (_dir, rd) = run_in_tempdir(&spec, options)?;
    let wall = t.elapsed().as_secs_f64();
    let mut sum = 0.0;
    let mut n = 0;
    for line in read_lines(&rd.cell_path(&spec.cells()[0].id))? {
        let Line::Episode(e) = line else {
            return Err("an error line".into());
        };
        let own = e.times.policy_s + e.times.sim_s + e.times.render_s + e.times.corruption_s;
        assert!(e.times.total_s >= own, "{:?}", e.times);
        sum += e.times.total_s;
        n += 1;
    }
    assert_eq!(n, 9, "3 seeds x 3 arms");
    assert!(sum <= wall, "episode totals {sum} s over a run of {wall} s");
    Ok(())
}
