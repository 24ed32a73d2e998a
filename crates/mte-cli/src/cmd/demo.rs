//! `mte demo`: the PushT blank-frame burst experiment with the bundled policy.

use std::path::PathBuf;

use anyhow::{Context, Result, ensure};
use mte_eval::corruption::Fault;
use mte_eval::report::ReportOptions;
use mte_eval::sweep::{CorruptionEntry, Seeds, Shard, SweepSpec};
use mte_sim::ResetStream;

use crate::args::{Cli, DemoArgs};

/// Where the bundled policy lives in the repository.
const BUNDLED: &str = "assets/policies/pusht_keypoints_cpu_v4";

/// The bundled policy: relative to the working directory, else to the source tree.
fn bundled_policy() -> PathBuf {
    let here = PathBuf::from(BUNDLED);
    if here.exists() {
        return here;
    }
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .join(BUNDLED)
}

/// `mte demo`
pub fn run(cli: &Cli, a: &DemoArgs) -> Result<()> {
    ensure!(a.episodes >= 1, "--episodes must be at least 1");
    let policy = a.policy.clone().unwrap_or_else(bundled_policy);
    ensure!(
        policy.join("config.json").exists(),
        "no policy checkpoint at {} (expected config.json and model.safetensors); pass --policy DIR",
        policy.display()
    );
    let fault: Fault = a.fault.clone();
    let spec = SweepSpec {
        name: "demo".into(),
        policies: vec![policy.to_string_lossy().into_owned()],
        arms: a.aggregators.clone(),
        h: vec![a.stride],
        seeds: Seeds::Range {
            first: 100_000,
            count: a.episodes,
        },
        max_steps: 300,
        noise_seed: 0,
        stream: ResetStream::Legacy,
        corruptions: vec![CorruptionEntry {
            fault,
            q: a.q.clone(),
            phase: 0,
            schedules: Vec::new(),
        }],
        monitors: Vec::new(),
        env: Default::default(),
        span: Vec::new(),
    };
    spec.validate().context("check the demo flags")?;
    let t0 = std::time::Instant::now();
    let resume = a.out.join("manifest.json").exists();
    let s = super::sweep::execute(
        cli,
        &spec,
        &a.out,
        resume,
        Shard::default(),
        super::sweep::options(a.workers, a.batch)?,
        mte_policy::ComputeDevice::Cpu,
    )
    .map_err(|e| {
        let other_grid = e
            .downcast_ref::<mte_eval::store::StoreError>()
            .is_some_and(|s| matches!(s, mte_eval::store::StoreError::Mismatch { .. }));
        if other_grid {
            let out = a.out.display();
            e.context(format!("{out} holds a different run: pass another --out"))
        } else {
            e
        }
    })?;
    super::sweep::print_summary(cli, &s, &a.out, t0.elapsed().as_secs_f64())?;
    super::report::write_and_print(
        cli,
        std::slice::from_ref(&a.out),
        &[],
        &a.out,
        &ReportOptions::default(),
        true,
    )?;
    super::sweep::fail_on_errors(&s, &a.out)
}
