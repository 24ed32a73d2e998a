//! The scale-out scripts in `deploy/`, run locally: the Slurm array job's script once per
//! array index (as Slurm would, with `SLURM_ARRAY_TASK_ID` and `SLURM_ARRAY_TASK_COUNT`),
//! then the merge script; the merged run must equal the same spec run unsharded. The
//! Kubernetes Indexed Job runs the same `deploy/sweep-shard` with `JOB_COMPLETION_INDEX`.

use std::collections::BTreeSet;
use std::fs;
use std::path::{Path, PathBuf};
use std::process::Command;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Every episode line of a run's (or a set of shard runs') cell files, without its
/// timings (wall-clock seconds differ between any two runs).
fn episodes(runs: &[PathBuf]) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    for run in runs {
        for f in fs::read_dir(run.join("cells")).expect("cells") {
            let text = fs::read_to_string(f.expect("entry").path()).expect("cell file");
            for line in text.lines() {
                let mut v: serde_json::Value = serde_json::from_str(line).expect("json line");
                if let Some(o) = v.as_object_mut() {
                    o.remove("times");
                }
                out.insert(v.to_string());
            }
        }
    }
    out
}

fn run(cmd: &mut Command) {
    let out = cmd.output().expect("starts");
    assert!(
        out.status.success(),
        "{cmd:?}: {}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn the_slurm_array_run_locally_then_merged_equals_the_unsharded_run() {
    let dir = tempfile::tempdir().expect("tempdir");
    let policy = root().join("assets/policies/pusht_keypoints_cpu");
    let spec = dir.path().join("sweep.toml");
    fs::write(
        &spec,
        format!(
            "name = \"deploy\"\npolicies = [{:?}]\narms = [\"ewm:0.01\", \"median\"]\nh = [2]\n\
             seeds = [100000, 100001]\nmax_steps = 24\n[[corruptions]]\nfault = {{ kind = \"blank\" }}\n\
             q = [0, 1, 2]\n",
            policy.display().to_string()
        ),
    )
    .expect("spec");
    let mte = env!("CARGO_BIN_EXE_mte");
    let sharded = dir.path().join("sharded");
    let n = 3;
    // Array task `i` of `n`, as Slurm starts it: the script with its index in the environment.
    let task = |i: usize| {
        let mut c = Command::new("bash");
        c.arg("deploy/slurm/sweep.sbatch")
            .arg(&spec)
            .arg(&sharded)
            .current_dir(root())
            .env("MTE", mte)
            .env("SLURM_ARRAY_TASK_ID", i.to_string())
            .env("SLURM_ARRAY_TASK_COUNT", n.to_string())
            .env("SLURM_CPUS_PER_TASK", "1");
        c
    };
    for i in 0..n {
        run(&mut task(i));
    }
    // A requeued task resumes its shard: nothing is run twice.
    run(&mut task(0));
    run(Command::new("bash")
        .arg("deploy/slurm/merge.sbatch")
        .arg(&sharded)
        .current_dir(root())
        .env("MTE", mte));
    let single = dir.path().join("single");
    run(Command::new(mte)
        .args(["--no-progress", "sweep"])
        .arg(&spec)
        .arg("--out")
        .arg(&single)
        .args(["--workers", "1"]));
    run(Command::new(mte)
        .args(["--no-progress", "report"])
        .arg(&single)
        .arg("--out")
        .arg(dir.path().join("single-report")));

    let shards: Vec<PathBuf> = (0..n).map(|i| sharded.join(format!("shard-{i}"))).collect();
    for s in &shards {
        let cells = fs::read_dir(s.join("cells")).expect("cells").count();
        assert_eq!(
            cells,
            1,
            "{}: one of the three cells per shard",
            s.display()
        );
    }
    let (merged, alone) = (episodes(&shards), episodes(std::slice::from_ref(&single)));
    assert_eq!(
        merged.len(),
        3 * 2 * 2,
        "3 cells x 2 seeds x 2 arms, none repeated"
    );
    assert_eq!(
        merged, alone,
        "the shards' episodes are the unsharded run's"
    );
    let report = |p: PathBuf| -> serde_json::Value {
        serde_json::from_str(&fs::read_to_string(p).expect("report.json")).expect("json")
    };
    let (m, s) = (
        report(sharded.join("report/report.json")),
        report(dir.path().join("single-report/report.json")),
    );
    for key in [
        "main",
        "mcnemar",
        "clean_cells",
        "corrupted_cells",
        "episodes",
    ] {
        assert!(!m[key].is_null(), "report.json has {key:?}");
        assert_eq!(m[key], s[key], "report.json[{key:?}] of the merged shards");
    }
}
