//! What is bit-identical (README, "Reproducibility"): on one machine, a run's records do not
//! depend on the thread count of the neural-network kernels nor on the sweep's worker count.
//! (Across CPU models they may differ in their last bits; that is stated, not tested here.)
//!
//! Each check runs the real binary twice and compares every record field except timings,
//! bit for bit: a closed-loop coverage compounds any difference in any chunk, so equal
//! coverages over tens of steps and several queries mean equal chunks.

use std::fs;
use std::path::{Path, PathBuf};

use assert_cmd::Command;

fn mte() -> Command {
    let mut c = Command::cargo_bin("mte").expect("the mte binary is built");
    c.env("NO_COLOR", "1").env_remove("RAYON_NUM_THREADS");
    c
}

fn policy(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../assets/policies")
        .join(name)
}

/// `mte eval policy` as JSON with the kernels on `threads` threads, timings removed.
fn eval_with_threads(name: &str, threads: usize) -> serde_json::Value {
    let out = mte()
        .env("RAYON_NUM_THREADS", threads.to_string())
        .args(["--format", "json", "eval", "policy", "--episodes", "2"])
        .args([
            "--max-steps",
            "24",
            "--stride",
            "4",
            "--execution",
            "median",
        ])
        .arg("--checkpoint")
        .arg(policy(name))
        .assert()
        .success();
    let mut v: serde_json::Value =
        serde_json::from_slice(&out.get_output().stdout).expect("json output");
    strip_timings(&mut v);
    v
}

/// Removes every field whose name says it is a duration (they are the only fields that may
/// differ between two runs of the same experiment).
fn strip_timings(v: &mut serde_json::Value) {
    match v {
        serde_json::Value::Object(map) => {
            map.retain(|k, _| !is_timing(k));
            map.values_mut().for_each(strip_timings);
        }
        serde_json::Value::Array(items) => items.iter_mut().for_each(strip_timings),
        _ => {}
    }
}

fn is_timing(key: &str) -> bool {
    key == "times"
        || key.ends_with("_s")
        || key.ends_with("_ms")
        || key.ends_with("_us")
        || key.contains("per_s")
        || key.contains("seconds")
}

#[test]
fn policy_rollouts_do_not_depend_on_the_kernel_thread_count() {
    for name in ["pusht_keypoints_cpu", "pusht_image_cpu"] {
        let one = eval_with_threads(name, 1);
        let episodes = one["episodes"].as_array().expect("episodes");
        assert_eq!(episodes.len(), 2, "{one}");
        for threads in [2, 3] {
            assert_eq!(
                one,
                eval_with_threads(name, threads),
                "{name}: 1 thread against {threads}"
            );
        }
    }
}

/// Every episode line of a run directory without its timings, sorted.
fn records(run: &Path) -> Vec<String> {
    let mut lines = Vec::new();
    for entry in fs::read_dir(run.join("cells")).expect("cells") {
        let text = fs::read_to_string(entry.expect("entry").path()).expect("cell file");
        for line in text.lines() {
            let mut v: serde_json::Value = serde_json::from_str(line).expect("json line");
            assert_eq!(v["kind"], "episode", "{line}");
            strip_timings(&mut v);
            lines.push(v.to_string());
        }
    }
    lines.sort();
    lines
}

#[test]
fn sweep_records_do_not_depend_on_the_worker_count() {
    let dir = tempfile::tempdir().expect("tempdir");
    let spec = dir.path().join("grid.toml");
    fs::write(
        &spec,
        format!(
            "name = \"workers\"\npolicies = [{:?}]\narms = [\"ewm:0.01\", \"median\"]\n\
             h = [2]\nseeds = {{ first = 100000, count = 3 }}\nmax_steps = 16\n\
             [[corruptions]]\nfault = {{ kind = \"blank\" }}\nq = [2]\n\
             [[corruptions]]\nfault = {{ kind = \"pgd\", iterations = 2 }}\nq = [1]\n",
            policy("pusht_keypoints_cpu").display().to_string()
        ),
    )
    .expect("spec");
    let run = |workers: &str| {
        let out = dir.path().join(format!("w{workers}"));
        mte()
            .args(["--no-progress", "sweep"])
            .arg(&spec)
            .args(["--workers", workers, "--out"])
            .arg(&out)
            .assert()
            .success();
        records(&out)
    };
    let one = run("1");
    // 2 cells x 2 arms x 3 seeds.
    assert_eq!(one.len(), 12, "{one:?}");
    assert_eq!(one, run("2"), "1 worker against 2");
    assert_eq!(one, run("3"), "1 worker against 3");
}

#[test]
fn a_run_manifest_names_the_machine() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("demo");
    mte()
        .args([
            "--no-progress",
            "-q",
            "demo",
            "--episodes",
            "1",
            "--q",
            "0",
            "--out",
        ])
        .arg(&out)
        .arg("--policy")
        .arg(policy("pusht_keypoints_cpu"))
        .assert()
        .success();
    let m: serde_json::Value =
        serde_json::from_str(&fs::read_to_string(out.join("manifest.json")).expect("manifest"))
            .expect("json");
    let machines = m["machines"].as_array().expect("machines");
    assert_eq!(machines.len(), 1, "{m}");
    assert!(
        machines[0]["cpu_model"]
            .as_str()
            .is_some_and(|s| !s.is_empty()),
        "{m}"
    );
    assert!(
        machines[0]["logical_cpus"].as_u64().is_some_and(|n| n >= 1),
        "{m}"
    );
    let report = fs::read_to_string(out.join("report.md")).expect("report");
    assert!(
        report.contains(&format!(
            "machine: {}",
            machines[0]["cpu_model"].as_str().unwrap_or_default()
        )),
        "{report}"
    );
}
