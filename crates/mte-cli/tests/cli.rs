//! End-to-end tests of the `mte` binary.
#![allow(clippy::unwrap_used)]

use std::fs;

use assert_cmd::Command;
use predicates::prelude::*;

/// Run `cmd`, require success, and parse its stdout as one JSON document.
fn json_stdout(cmd: &mut Command) -> serde_json::Value {
    let out = cmd.assert().success().get_output().stdout.clone();
    serde_json::from_slice(&out).unwrap()
}

fn mte() -> Command {
    let mut c = Command::cargo_bin("mte").unwrap();
    c.arg("--no-progress");
    c
}

#[test]
fn synthetic_json_shows_the_median_beating_the_mean_under_bursts() {
    let v = json_stdout(
        mte()
            .args([
                "synthetic",
                "--episodes",
                "4",
                "--steps",
                "80",
                "--format",
                "json",
            ])
            .args(["--aggregators", "ewm:0.01,median"]),
    );
    let cells = v["cells"].as_array().unwrap();
    assert_eq!(cells.len(), 4 * 2);
    let rmse = |q: u64, agg: &str| {
        cells
            .iter()
            .find(|c| c["q"] == q && c["aggregator"] == agg)
            .map(|c| c["rmse"].as_f64().unwrap())
            .unwrap()
    };
    for q in 1..=3 {
        assert!(rmse(q, "median") < rmse(q, "ewm:0.01"), "q={q}");
    }
    assert_eq!(v["comparisons"].as_array().unwrap().len(), 4);
}

#[test]
fn synthetic_text_prints_the_tables() {
    mte()
        .args([
            "synthetic",
            "--episodes",
            "2",
            "--steps",
            "60",
            "--q",
            "0,3",
        ])
        .assert()
        .success()
        .stdout(predicate::str::contains("| q | ewm:0.01 | median |"))
        .stdout(predicate::str::contains("| median (q=3) | 2q<M |"))
        .stdout(predicate::str::contains("Distribution of M(tau)"));
}

#[test]
fn bad_flags_exit_2_naming_the_value() {
    mte()
        .args(["synthetic", "--q", "9"])
        .assert()
        .code(2)
        .stderr(
            predicate::str::contains("q_values = 9").and(predicate::str::contains("M_min = 7")),
        );
    mte()
        .args(["synthetic", "--aggregators", "medain"])
        .assert()
        .code(2)
        .stderr(predicate::str::contains("unknown aggregator \"medain\""));
    mte()
        .args(["synthetic", "--t-o", "0"])
        .assert()
        .code(2)
        .stderr(predicate::str::contains("t_o = 0"));
}

#[test]
fn replay_writes_one_line_per_control_time() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("stream.jsonl");
    let mut text = String::new();
    for t in (0..20).step_by(2) {
        let rows: Vec<String> = (0..6).map(|r| format!("[{}.0, 1.0]", t + r)).collect();
        let corrupted = t % 6 == 0;
        text.push_str(&format!(
            "{{\"t\": {t}, \"chunk\": [{}], \"corrupted\": {corrupted}}}\n",
            rows.join(", ")
        ));
    }
    fs::write(&input, text).unwrap();
    let out = dir.path().join("actions.jsonl");
    mte()
        .args(["ensemble", "replay"])
        .arg(&input)
        .args(["--aggregator", "median", "--t-o", "2", "--out"])
        .arg(&out)
        .assert()
        .success()
        .stderr(predicate::str::contains(
            "replayed 10 queries (t_p = 6, d = 2)",
        ));
    let lines: Vec<serde_json::Value> = fs::read_to_string(&out)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    // Queries at 0..=18 each cover 5 control times: tau 0..=22.
    assert_eq!(lines.len(), 23);
    assert_eq!(lines[0]["tau"], 0);
    // Row r of the query at t is for time t - 1 + r and holds t + r: the action at tau is
    // tau + 1 in coordinate 0 whichever query supplies it.
    for l in &lines {
        let tau = l["tau"].as_f64().unwrap();
        assert_eq!(l["action"][0].as_f64().unwrap(), tau + 1.0, "{l}");
        assert_eq!(l["action"][1].as_f64().unwrap(), 1.0);
    }
    assert_eq!(lines[6]["report"]["m"], 3);
}

#[test]
fn malformed_replay_input_names_the_line_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("bad.jsonl");
    fs::write(
        &input,
        "{\"t\": 0, \"chunk\": [[1.0], [2.0]]}\n{\"t\": 1, \"chunk\": [[1.0]]}\n",
    )
    .unwrap();
    let out = dir.path().join("actions.jsonl");
    mte()
        .args(["ensemble", "replay"])
        .arg(&input)
        .arg("--out")
        .arg(&out)
        .assert()
        .code(2)
        .stderr(predicate::str::contains(
            "line 2: chunk is 1 x 1, expected 2 x 1",
        ));
    assert!(!out.exists());
    mte()
        .args(["ensemble", "replay", "/nonexistent/stream.jsonl"])
        .assert()
        .code(2)
        .stderr(predicate::str::contains(
            "opening chunk stream /nonexistent/stream.jsonl",
        ));
}

#[test]
fn replay_reads_standard_input() {
    mte()
        .args(["-q", "ensemble", "replay", "-", "--aggregator", "mean"])
        .write_stdin(
            "{\"t\": 0, \"chunk\": [[1.0], [3.0]]}\n{\"t\": 1, \"chunk\": [[5.0], [7.0]]}\n",
        )
        .assert()
        .success()
        .stdout(predicate::str::contains("{\"tau\":1,\"action\":[4.0]"))
        .stderr(predicate::str::is_empty());
}

#[test]
fn sim_render_writes_a_png_of_the_reset_state() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("frame.png");
    let v = json_stdout(
        mte()
            .args([
                "sim", "render", "--seed", "100000", "--format", "json", "--out",
            ])
            .arg(&out),
    );
    // The Diffusion Policy test seed 100000 (legacy stream) starts with the agent at (235, 124).
    assert_eq!(v["state"][0], 235.0);
    assert_eq!(v["state"][1], 124.0);
    let bytes = fs::read(&out).unwrap();
    assert_eq!(&bytes[1..4], b"PNG");
    let decoder = png::Decoder::new(std::io::Cursor::new(bytes));
    let reader = decoder.read_info().unwrap();
    assert_eq!((reader.info().width, reader.info().height), (96, 96));
}

#[test]
fn sim_rollout_writes_an_animated_gif_and_reports_success() {
    let dir = tempfile::tempdir().unwrap();
    let gif = dir.path().join("out.gif");
    let v = json_stdout(
        mte()
            .args([
                "sim", "rollout", "--policy", "expert", "--seed", "100007", "--format", "json",
            ])
            .args(["--gif-size", "64", "--gif"])
            .arg(&gif),
    );
    let ep = &v["episodes"][0];
    let steps = ep["steps"].as_u64().unwrap();
    assert!(ep["max_coverage"].as_f64().unwrap() > 0.5);
    let bytes = fs::read(&gif).unwrap();
    assert_eq!(&bytes[..6], b"GIF89a");
    // One frame for the reset plus one per step: count image descriptors via the decoder.
    let mut opts = gif::DecodeOptions::new();
    opts.set_color_output(gif::ColorOutput::Indexed);
    let mut dec = opts.read_info(std::io::Cursor::new(bytes)).unwrap();
    let mut frames = 0;
    while dec.read_next_frame().unwrap().is_some() {
        frames += 1;
    }
    assert_eq!(frames as u64, steps + 1);
}

#[test]
fn data_generate_writes_a_loadable_dataset_and_refuses_to_overwrite() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("demos");
    mte()
        .args([
            "data",
            "generate",
            "--episodes",
            "2",
            "--seed",
            "3",
            "--max-steps",
            "15",
        ])
        .args([
            "--obs",
            "state,keypoints,pixels",
            "--image-size",
            "32",
            "--out",
        ])
        .arg(&out)
        .assert()
        .success()
        .stdout(predicate::str::contains("2 episodes"));
    let info: serde_json::Value =
        serde_json::from_str(&fs::read_to_string(out.join("info.json")).unwrap()).unwrap();
    assert_eq!(info["format"], "mte-demo-v1");
    assert_eq!(
        info["features"]["observation.image"]["shape"],
        serde_json::json!([32, 32, 3])
    );
    assert!(out.join("data/observation.environment_state.npy").exists());
    mte()
        .args(["data", "generate", "--episodes", "1", "--out"])
        .arg(&out)
        .assert()
        .code(2)
        .stderr(predicate::str::contains("already holds a dataset"));
}

#[test]
fn bad_sim_flags_are_clear_errors() {
    mte()
        .args(["data", "generate", "--obs", "state,depth", "--out", "x"])
        .assert()
        .code(2)
        .stderr(predicate::str::contains("depth"));
    mte()
        .args(["sim", "rollout", "--episodes", "0"])
        .assert()
        .code(2)
        .stderr(predicate::str::contains("--episodes"));
}

/// The bundled policy, from the repository root.
fn bundled() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../assets/policies/pusht_keypoints_cpu")
}

/// Every bundled image policy (four U-Nets, v4 with four observations, and four Diffusion
/// Transformers) loads from a fresh clone and drives PushT from pixels: a short episode runs,
/// and its coverage is a valid fraction.
#[test]
fn bundled_image_policies_run_an_episode() {
    for name in [
        "pusht_image_cpu",
        "pusht_image_cpu_v2",
        "pusht_image_cpu_v3",
        "pusht_image_cpu_v4",
        "pusht_image_dit_cpu",
        "pusht_image_dit_cpu_v2",
        "pusht_image_dit_cpu_v3",
        "pusht_image_dit_cpu_v4",
    ] {
        let ckpt = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../assets/policies")
            .join(name);
        let v = json_stdout(
            mte()
                .args(["--format", "json", "eval", "policy", "--episodes", "1"])
                .args(["--max-steps", "40", "--checkpoint"])
                .arg(&ckpt),
        );
        let c = v["mean_max_coverage"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&c), "{name}: {v}");
        assert_eq!(
            v["episodes"].as_array().map(Vec::len),
            Some(1),
            "{name}: {v}"
        );
    }
}

/// `eval policy --corruption` runs the episode under the corruption (its candidate
/// statistics then measure corrupted candidates against clean ones, and the JSON names it);
/// malformed JSON, a bad field and a burst longer than its period are refused by name.
#[test]
fn eval_policy_takes_a_corruption_and_refuses_bad_ones() {
    // An episode of 40 steps at h = 2 under the median, with `corruption` if given.
    let eval = |corruption: Option<&str>| {
        let mut c = mte();
        c.args(["--format", "json", "eval", "policy", "--episodes", "1"])
            .args([
                "--max-steps",
                "40",
                "--stride",
                "2",
                "--execution",
                "median",
            ]);
        if let Some(json) = corruption {
            c.args(["--corruption", json]);
        }
        c.arg("--checkpoint").arg(bundled());
        c
    };
    let blank =
        r#"{"fault": {"kind": "blank"}, "schedule": {"kind": "burst", "q": 2, "phase": 3}}"#;
    let v = json_stdout(&mut eval(Some(blank)));
    assert_eq!(v["corruption"]["fault"]["kind"], "blank", "{v}");
    let steps = v["candidates"]["corrupted_steps"]
        .as_u64()
        .expect("counted");
    assert!(steps > 0, "a blank burst in 40 steps at h = 2: {v}");
    // The one episode's own statistics are the run's.
    assert_eq!(v["candidates_by_episode"][0], v["candidates"], "{v}");
    let out = v["candidates"]["corrupted_outside_bracket"]
        .as_f64()
        .expect("fraction");
    assert!((0.0..=1.0).contains(&out), "{v}");
    let clean = json_stdout(&mut eval(None));
    assert_eq!(clean["candidates"]["corrupted_steps"], 0, "{clean}");
    for (bad, needle) in [
        ("{not json", "expected a corruption as JSON"),
        (
            r#"{"fault": {"kind": "blank"}, "schedule": {"kind": "burst", "q": 99}}"#,
            "burst period 7",
        ),
        (
            r#"{"fault": {"kind": "blank"}, "schedule": {"kind": "bernoulli", "p": 2.0}}"#,
            "schedule.p",
        ),
    ] {
        eval(Some(bad))
            .assert()
            .failure()
            .stderr(predicate::str::contains(needle));
    }
}

/// `--device` is parsed into a device or refused with the accepted names, the JSON says where
/// the policy ran, and a CUDA device in a build without the `cuda` feature is an error that
/// says how to get one (nothing falls back to the CPU silently).
#[test]
fn eval_policy_names_its_device_and_refuses_unknown_ones() {
    let eval = |device: &str| {
        let mut c = mte();
        c.args(["--format", "json", "eval", "policy", "--episodes", "1"])
            .args(["--max-steps", "5", "--device", device, "--checkpoint"])
            .arg(bundled());
        c
    };
    let v = json_stdout(&mut eval("cpu"));
    assert_eq!(v["device"], "cpu", "{v}");
    eval("gpu")
        .assert()
        .failure()
        .stderr(predicates::str::contains("cpu, cuda or cuda:N"));
    if !cfg!(feature = "cuda") {
        eval("cuda:0")
            .assert()
            .failure()
            .stderr(predicates::str::contains("device cuda:0"))
            .stderr(predicates::str::contains("`cuda` feature"));
    }
}

#[test]
fn demo_runs_pairs_resumes_and_reports() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("demo");
    let run = |episodes: &str| {
        mte()
            .args([
                "demo",
                "--episodes",
                episodes,
                "--q",
                "0,3",
                "--workers",
                "2",
                "--out",
            ])
            .arg(&out)
            .arg("--policy")
            .arg(bundled())
            .assert()
            .success()
    };
    let first = String::from_utf8(run("1").get_output().stdout.clone()).unwrap();
    assert!(
        first.contains("2 cells: 4 episodes run, 0 already done, 0 errors"),
        "{first}"
    );
    assert!(first.contains("Main table"), "{first}");
    assert!(first.contains("blank-burst-q3"), "{first}");
    for f in ["report.md", "report.html", "manifest.json", "spec.toml"] {
        assert!(out.join(f).exists(), "{f}");
    }
    let cells: Vec<_> = fs::read_dir(out.join("cells")).unwrap().collect();
    assert_eq!(cells.len(), 2);
    // Every line is one finished (arm, seed).
    let lines: usize = cells
        .iter()
        .map(|c| {
            fs::read_to_string(c.as_ref().unwrap().path())
                .unwrap()
                .lines()
                .count()
        })
        .sum();
    assert_eq!(lines, 4);
    let again = String::from_utf8(run("1").get_output().stdout.clone()).unwrap();
    assert!(again.contains("0 episodes run, 4 already done"), "{again}");
    // The report alone, from the files, as JSON.
    let json = mte()
        .args(["report", "--format", "json"])
        .arg(&out)
        .assert()
        .success();
    let v: serde_json::Value = serde_json::from_slice(&json.get_output().stdout).unwrap();
    assert!(v["markdown"].as_str().unwrap().contains("median"));
    // --only: the named cell alone (tables and Holm families); an unknown name is a
    // typed error that lists the cells.
    let manifest: serde_json::Value =
        serde_json::from_str(&fs::read_to_string(out.join("manifest.json")).unwrap()).unwrap();
    let ids: Vec<&str> = manifest["cells"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["id"].as_str().unwrap())
        .collect();
    let corrupted = ids.iter().find(|id| id.contains("blank")).unwrap();
    let clean = ids.iter().find(|id| id.contains("clean")).unwrap();
    let only = mte()
        .args(["report", "--format", "json", "--only", corrupted, "--out"])
        .arg(dir.path().join("only"))
        .arg(&out)
        .assert()
        .success();
    let v: serde_json::Value = serde_json::from_slice(&only.get_output().stdout).unwrap();
    let md = v["markdown"].as_str().unwrap();
    assert!(md.contains("1 cells (1 corrupted)"), "{md}");
    assert!(md.contains(corrupted) && !md.contains(clean), "{md}");
    mte()
        .args(["report", "--only", "nope"])
        .arg(&out)
        .assert()
        .code(2)
        .stderr(
            predicate::str::contains("cell `nope` is not a cell of the runs")
                .and(predicate::str::contains(*clean)),
        );
    // More seeds grow the run: only the new ones run.
    let grown = String::from_utf8(run("2").get_output().stdout.clone()).unwrap();
    assert!(grown.contains("4 episodes run, 4 already done"), "{grown}");
    // A different grid in the same directory is refused, naming the way out.
    mte()
        .args(["demo", "--episodes", "2", "--q", "0,2", "--out"])
        .arg(&out)
        .arg("--policy")
        .arg(bundled())
        .assert()
        .code(2)
        .stderr(predicate::str::contains("another --out"));
}

#[test]
fn sweep_flags_and_specs_are_checked() {
    let dir = tempfile::tempdir().unwrap();
    let spec = dir.path().join("s.toml");
    fs::write(
        &spec,
        "name = \"x\"\npolicies = [\"p\"]\narms = [\"medain\"]\nh = [2]\nseeds = [1]\n\
         [[corruptions]]\nfault = { kind = \"blank\" }\nq = [1]\n",
    )
    .unwrap();
    mte()
        .arg("sweep")
        .arg(&spec)
        .arg("--out")
        .arg(dir.path().join("r"))
        .assert()
        .code(2)
        .stderr(predicate::str::contains("`arms` = medain"));
    mte()
        .args(["sweep", "--shard", "3/2", "--out"])
        .arg(dir.path().join("r"))
        .arg(&spec)
        .assert()
        .code(2);
    mte()
        .args(["report"])
        .arg(dir.path())
        .assert()
        .code(2)
        .stderr(predicate::str::contains("not an mte run directory"));
}

#[test]
fn attack_calibrate_reports_clean_and_attacked_rows() {
    let out = mte()
        .args([
            "attack",
            "calibrate",
            "--episodes",
            "1",
            "--iterations",
            "1",
            "--max-steps",
            "6",
        ])
        .args(["--format", "json", "--policy"])
        .arg(bundled())
        .assert()
        .success();
    let v: serde_json::Value = serde_json::from_slice(&out.get_output().stdout).unwrap();
    let rows = v["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 2);
    assert_eq!(rows[0]["iterations"], 0);
    assert_eq!(rows[1]["iterations"], 1);
    mte()
        .args(["attack", "calibrate", "--arm", "medain", "--policy"])
        .arg(bundled())
        .assert()
        .code(2)
        .stderr(predicate::str::contains("--arm"));
}

/// The patch pipeline end to end on a tiny image policy: train a patch, fine-tune the
/// encoder against it, probe the two encoders; files and figures are checked.
#[test]
fn patch_finetune_and_probe_run_end_to_end() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    let json = |n: &str| -> serde_json::Value {
        serde_json::from_str(&fs::read_to_string(p(n)).unwrap()).unwrap()
    };
    mte()
        .args(["data", "generate", "--episodes", "2", "--max-steps", "20"])
        .args(["--obs", "state,keypoints,pixels", "--out"])
        .arg(p("demos"))
        .assert()
        .success();
    let tiny = p("tiny.json");
    fs::write(
        &tiny,
        r#"{"down_dims": [8, 16], "n_groups": 4, "diffusion_step_embed_dim": 8, "spatial_softmax_num_keypoints": 4}"#,
    )
    .unwrap();
    // The encoder warm start (on the demonstrations given twice: several datasets pool),
    // then a policy on top of it with the encoder frozen.
    mte()
        .args(["--format", "json", "train", "encoder", "--steps", "2"])
        .args(["--batch-size", "4", "--data"])
        .arg(p("demos"))
        .arg("--data")
        .arg(p("demos"))
        .arg("--config")
        .arg(&tiny)
        .arg("--out")
        .arg(p("enc"))
        .assert()
        .success()
        .stdout(predicate::str::contains("\"heldout_mae\""));
    let pre = json("enc/pretrain.json");
    assert_eq!(pre["report"]["steps"], 2);
    assert!(pre["report"]["final_loss"].as_f64().unwrap().is_finite());
    mte()
        .args(["train", "diffusion", "--obs", "image", "--steps", "2"])
        .args([
            "--batch-size",
            "4",
            "--checkpoint-every",
            "0",
            "--freeze-encoder",
        ])
        .arg("--init")
        .arg(p("enc/encoder.safetensors"))
        .arg("--data")
        .arg(p("demos"))
        .arg("--config")
        .arg(&tiny)
        .arg("--out")
        .arg(p("policy"))
        .assert()
        .success();
    mte()
        .args([
            "--quiet",
            "attack",
            "patch",
            "--epochs",
            "2",
            "--batches-per-epoch",
            "1",
        ])
        .args([
            "--batch-size",
            "4",
            "--side",
            "12",
            "--center",
            "100,400",
            "--policy",
        ])
        .arg(p("policy"))
        .arg("--data")
        .arg(p("demos"))
        .arg("--out")
        .arg(p("patch"))
        .assert()
        .success()
        .stdout(predicate::str::contains("patch 12x12 at world (100, 400)"));
    let meta = json("patch/patch.json");
    assert_eq!(meta["format"], "mte-patch-v1");
    // 100 / 512 * 96 - 6 = 12.75 -> 13; 400 / 512 * 96 - 6 = 69.
    assert_eq!(meta["origin"], serde_json::json!([13, 69]));
    assert_eq!(meta["epoch_loss"].as_array().unwrap().len(), 2);
    assert!(p("patch/patch.png").exists());
    // Its control: the same square and place, uniform.
    mte()
        .args(["attack", "control", "--patch"])
        .arg(p("patch"))
        .arg("--out")
        .arg(p("grey"))
        .assert()
        .success()
        .stdout(predicate::str::contains("12 px at world (100, 400)"));
    let grey = json("grey/patch.json");
    assert_eq!(
        (&grey["origin"], &grey["epochs"]),
        (&meta["origin"], &serde_json::json!(0))
    );
    // `defend finetune` of the tiny policy against the patch, writing to `out`.
    let finetune = |out: &str| {
        let mut c = mte();
        c.args(["defend", "finetune", "--policy"])
            .arg(p("policy"))
            .arg("--data")
            .arg(p("demos"))
            .arg("--patch")
            .arg(p("patch"))
            .arg("--out")
            .arg(p(out))
            .args(["--quiet", "--steps", "2", "--batch-size", "4"]);
        c
    };
    finetune("tuned")
        .args([
            "--lr",
            "1e-3",
            "--clean-features",
            "1",
            "--checkpoint-every",
            "1",
        ])
        .assert()
        .success()
        .stdout(predicate::str::contains("for 2 steps"));
    assert!(p("tuned/model.safetensors").exists() && p("tuned/finetune.json").exists());
    // A checkpoint after step 1, none after the last (that is the output itself).
    assert!(p("tuned/step-1/model.safetensors").exists() && !p("tuned/step-2").exists());
    let ft = json("tuned/finetune.json");
    assert_eq!(ft["config"]["clean_features"], serde_json::json!(1.0));
    assert!(
        ft["report"]["last_clean_drift"].as_f64().unwrap() >= 0.0,
        "{ft}"
    );
    assert!(
        !p("tuned/patch").exists(),
        "a fixed patch is not saved again"
    );
    // Regenerating: the final patch is saved beside the encoder, in the same place as the
    // patch it started from, and differs from it.
    finetune("regen")
        .args(["--regenerate", "--regenerate-step", "0.05"])
        .assert()
        .success();
    let regen = json("regen/patch/patch.json");
    assert_eq!(
        (&regen["origin"], &regen["side"], &regen["center"]),
        (&meta["origin"], &meta["side"], &meta["center"])
    );
    assert_eq!(regen["regenerated"]["steps"], serde_json::json!(2));
    assert_eq!(regen["regenerated"]["step"], serde_json::json!(0.05));
    assert!(
        regen["regenerated"]["last_loss"].as_f64().unwrap() > 0.0,
        "{regen}"
    );
    assert_ne!(
        fs::read(p("regen/patch/patch.png")).unwrap(),
        fs::read(p("patch/patch.png")).unwrap(),
        "regeneration moved the patch"
    );
    let ft = json("regen/finetune.json");
    assert_eq!(ft["config"]["regenerate_step"], serde_json::json!(0.05));
    finetune("regen0")
        .args(["--regenerate-step", "0.05"])
        .assert()
        .code(2)
        .stderr(predicate::str::contains("--regenerate"));
    finetune("tuned0")
        .args(["--checkpoint-every", "0"])
        .assert()
        .code(2)
        .stderr(predicate::str::contains("--checkpoint-every 0"));
    let out = mte()
        .args([
            "--format",
            "json",
            "defend",
            "probe",
            "--batches",
            "1",
            "--batch-size",
            "2",
        ])
        .arg("--original")
        .arg(p("policy"))
        .arg("--tuned")
        .arg(p("tuned"))
        .arg("--data")
        .arg(p("demos"))
        .arg("--patch")
        .arg(p("patch"))
        .assert()
        .success();
    let r: serde_json::Value = serde_json::from_slice(&out.get_output().stdout).unwrap();
    let cos = r["cosine"].as_f64().unwrap();
    assert!((-1.0..=1.0 + 1e-9).contains(&cos), "{r}");
    assert!(r["grad_norm_ratio"].as_f64().unwrap() > 0.0, "{r}");
    // The encoder's activity on the demonstration frames, clean and at a random start.
    let out = mte()
        .args([
            "--format", "json", "attack", "activity", "--eps", "0", "--eps", "0.1",
        ])
        .arg("--policy")
        .arg(p("policy"))
        .arg("--data")
        .arg(p("demos"))
        .assert()
        .success();
    let rows: serde_json::Value = serde_json::from_slice(&out.get_output().stdout).unwrap();
    let rows = rows.as_array().unwrap();
    assert_eq!(rows.len(), 2, "{rows:?}");
    for (row, eps) in rows.iter().zip([0.0, 0.1]) {
        assert!((row["eps"].as_f64().unwrap() - eps).abs() < 1e-6, "{row}");
        assert_eq!(row["features"], 8, "{row}");
        let frames = row["frames"].as_u64().unwrap();
        assert!(
            frames > 0 && row["dead_frames"].as_u64().unwrap() <= frames,
            "{row}"
        );
    }
    mte()
        .args(["attack", "activity", "--eps=-1", "--policy"])
        .arg(p("policy"))
        .arg("--data")
        .arg(p("demos"))
        .assert()
        .code(2)
        .stderr(predicate::str::contains("eps"));
    // A keypoint policy cannot carry a patch: a clear error, exit 2.
    mte()
        .args(["attack", "patch", "--policy"])
        .arg(
            std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../../assets/policies/pusht_keypoints_cpu"),
        )
        .arg("--data")
        .arg(p("demos"))
        .arg("--out")
        .arg(p("nope"))
        .assert()
        .code(2)
        .stderr(predicate::str::contains("image policy"));
}

/// Inputs a hostile or careless user hands mte: each is a clear error (exit 2, naming the
/// value and what was expected) or, for a legal but extreme stream, bounded work.
#[test]
fn hostile_inputs_are_clear_errors_or_bounded_work() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    // A stream jumping from t = 0 to t = 10^12: one gap record, not 10^12 lines.
    fs::write(
        p("jump.jsonl"),
        "{\"t\": 0, \"chunk\": [[0.0], [1.0]]}\n{\"t\": 1000000000000, \"chunk\": [[2.0], [3.0]]}\n",
    )
    .unwrap();
    mte()
        .args(["ensemble", "replay"])
        .arg(p("jump.jsonl"))
        .args(["--t-o", "1", "--out"])
        .arg(p("jump.out"))
        .assert()
        .success();
    let lines = fs::read_to_string(p("jump.out")).unwrap();
    assert_eq!(lines.lines().count(), 5, "{lines}");
    assert!(lines.contains("\"through\":999999999999"), "{lines}");
    // t = 2^64 - 1 would overflow t + span.
    fs::write(
        p("max.jsonl"),
        format!("{{\"t\": {}, \"chunk\": [[0.0]]}}\n", u64::MAX),
    )
    .unwrap();
    mte()
        .args(["ensemble", "replay"])
        .arg(p("max.jsonl"))
        .assert()
        .code(2)
        .stderr(predicate::str::contains("is too large: expected t <="));
    // A config.json asking for a billion-step horizon.
    let ckpt = p("huge");
    fs::create_dir(&ckpt).unwrap();
    for f in fs::read_dir(bundled()).unwrap() {
        let f = f.unwrap().path();
        if f.is_file() {
            fs::copy(&f, ckpt.join(f.file_name().unwrap())).unwrap();
        }
    }
    let cfg = fs::read_to_string(ckpt.join("config.json")).unwrap();
    let mut v: serde_json::Value = serde_json::from_str(&cfg).unwrap();
    v["horizon"] = serde_json::json!(1_000_000_000u64);
    fs::write(ckpt.join("config.json"), v.to_string()).unwrap();
    mte()
        .args(["eval", "policy", "--episodes", "1", "--checkpoint"])
        .arg(&ckpt)
        .assert()
        .code(2)
        .stderr(predicate::str::contains("horizon").and(predicate::str::contains("at most 1024")));
    // Zero steps, zero episodes: refused at parse time.
    for flag in ["--max-steps", "--episodes", "--stride"] {
        mte()
            .args(["eval", "policy", flag, "0", "--checkpoint"])
            .arg(bundled())
            .assert()
            .code(2)
            .stderr(predicate::str::contains(">= 1"));
    }
    // Typed arguments: a bad arm, fault or point is refused at parse time, listing what is
    // accepted, before any policy loads.
    for (flag, value, needle) in [
        (
            "--aggregators",
            "ewm:0.01,medain",
            "expected one of mean, latest, median",
        ),
        ("--fault", "kind = \"blnk\"", "blnk"),
        ("--fault", "kind = \"occluder\", size = 0", "size"),
    ] {
        mte()
            .args(["demo", flag, value, "--out"])
            .arg(p("typed"))
            .assert()
            .code(2)
            .stderr(predicate::str::contains(needle));
    }
    assert!(!p("typed").exists(), "nothing was written");
    // A burst longer than its period (M_min = 7 at T_p 16, T_o 2, h 2).
    mte()
        .args(["demo", "--episodes", "1", "--q", "99", "--out"])
        .arg(p("q99"))
        .arg("--policy")
        .arg(bundled())
        .assert()
        .code(2)
        .stderr(
            predicate::str::contains("`q` = 99").and(predicate::str::contains("burst period 7")),
        );
    // A misspelt key inside a fault table.
    fs::write(
        p("typo.toml"),
        "name = \"x\"\npolicies = [\"p\"]\narms = [\"median\"]\nh = [2]\nseeds = [1]\n\
         [[corruptions]]\nfault = { kind = \"occluder\", size = 8, sise = 3 }\nq = [1]\n",
    )
    .unwrap();
    mte()
        .arg("sweep")
        .arg(p("typo.toml"))
        .arg("--out")
        .arg(p("typo"))
        .assert()
        .code(2)
        .stderr(predicate::str::contains("unknown field `sise`"));
}

/// A sweep whose cells recorded errors exits 2 after its summary, naming the cells.
#[test]
fn a_sweep_with_failed_cells_exits_non_zero() {
    let dir = tempfile::tempdir().unwrap();
    let spec = dir.path().join("s.toml");
    fs::write(
        &spec,
        "name = \"x\"\npolicies = [\"no/such/policy\"]\narms = [\"median\"]\nh = [2]\n\
         seeds = [1]\n[[corruptions]]\nfault = { kind = \"blank\" }\nq = [1]\n",
    )
    .unwrap();
    let out = mte()
        .arg("sweep")
        .arg(&spec)
        .arg("--out")
        .arg(dir.path().join("r"))
        .assert()
        .code(2)
        .stderr(predicate::str::contains(
            "1 error record(s) in 1 cell(s): policy-blank",
        ));
    let stdout = String::from_utf8(out.get_output().stdout.clone()).unwrap();
    assert!(stdout.contains("1 errors"), "{stdout}");
}

/// `mte film` draws one episode twice; bad panel sizes and unknown McNemar tests are
/// rejected with exit 2 naming the value and what is accepted.
#[test]
fn film_writes_both_figures_and_bad_values_exit_2() {
    let dir = tempfile::tempdir().unwrap();
    let policy = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../assets/policies/pusht_keypoints_cpu"
    );
    let v = json_stdout(
        mte()
            .args(["--format", "json", "film", "--policy", policy])
            .args(["--max-steps", "12", "--size", "32", "--q", "2", "--out"])
            .arg(dir.path()),
    );
    let films = v["films"].as_array().unwrap();
    assert_eq!(films.len(), 2);
    assert_eq!(
        (films[0]["arm"].as_str(), films[1]["arm"].as_str()),
        (Some("ewm:0.01"), Some("median"))
    );
    assert!(dir.path().join("figure2.gif").exists());
    assert!(dir.path().join("figure2-strip.png").exists());
    mte()
        .args(["film", "--policy", policy, "--size", "8", "--out"])
        .arg(dir.path())
        .assert()
        .code(2)
        .stderr(predicate::str::contains(
            "`size` = 8: expected 32..=1024 px",
        ));
    mte()
        .args(["report", "--mcnemar", "chi3"])
        .arg(dir.path())
        .assert()
        .code(2)
        .stderr(predicate::str::contains("expected `exact` or `chi2-cc`"));
}

/// A sweep with monitors records every query's scores; `mte monitor calibrate` makes
/// thresholds from its clean cell (and says when a rule can never fire), `mte monitor
/// evaluate` reports firing rates and AUROC against the clean cell.
#[test]
fn monitors_record_calibrate_and_evaluate() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    let spec = format!(
        r#"
name = "monitors"
policies = ["{}"]
arms = ["ewm:0.01", "median"]
h = [2]
seeds = {{ first = 100000, count = 4 }}
max_steps = 30
monitors = ["tide", "acc"]

[[corruptions]]
fault = {{ kind = "blank" }}
q = [0, 3]
"#,
        bundled().display()
    );
    fs::write(p("spec.toml"), spec).unwrap();
    mte()
        .args(["sweep"])
        .arg(p("spec.toml"))
        .arg("--out")
        .arg(p("run"))
        .assert()
        .success();
    // Every episode carries both traces, one score per query after the first.
    let cells = p("run").join("cells");
    let mut seen = 0;
    for entry in fs::read_dir(&cells).unwrap() {
        for line in fs::read_to_string(entry.unwrap().path()).unwrap().lines() {
            let r: serde_json::Value = serde_json::from_str(line).unwrap();
            let queries = r["queries"].as_u64().unwrap();
            for m in ["tide", "acc"] {
                let t = &r["monitors"][m];
                assert_eq!(t["first_query"], 1, "{r}");
                let n = t["scores"].as_array().unwrap().len() as u64;
                assert_eq!(n, queries - 1, "{m}: {r}");
            }
            seen += 1;
        }
    }
    assert_eq!(seen, 16, "2 cells x 4 seeds x 2 arms");
    // Calibrate on every clean episode (a 30-step episode rarely succeeds).
    let out = json_stdout(
        mte()
            .args(["--format", "json", "monitor", "calibrate"])
            .arg(p("run"))
            .arg("--all-episodes")
            .arg("--out")
            .arg(p("thresholds.json")),
    );
    let tide = &out["monitors"]["tide"];
    // Pooled: every scored query of the 4 clean ewm episodes (at most 14 each); with fewer
    // than 999 scores k = ceil((n + 1) 0.999) = n + 1 > n: alpha = 0.001 cannot be met.
    let n = tide["n"].as_u64().unwrap();
    assert!((4..=56).contains(&n), "{out}");
    assert_eq!(tide["k"].as_u64(), Some(n + 1), "{out}");
    assert!(tide["value"].is_null(), "{out}");
    let acc = &out["monitors"]["acc"];
    assert_eq!(
        (acc["n"].as_u64(), acc["k"].as_u64()),
        (Some(4), Some(4)),
        "{out}"
    );
    assert!(acc["value"].as_f64().unwrap() > 0.0, "{out}");
    let text = mte()
        .args(["monitor", "calibrate"])
        .arg(p("run"))
        .args(["--all-episodes", "--out"])
        .arg(p("t2.json"))
        .assert()
        .success();
    let text = String::from_utf8(text.get_output().stdout.clone()).unwrap();
    assert!(text.contains("can never fire"), "{text}");
    // Evaluate: one row per cell x arm x monitor, AUROC only for the corrupted cell.
    let ev = json_stdout(
        mte()
            .args(["--format", "json", "monitor", "evaluate"])
            .arg(p("run"))
            .arg("--thresholds")
            .arg(p("thresholds.json"))
            .arg("--plots")
            .arg(p("roc")),
    );
    // ROC plots: one per monitor and arm, each a curve of the corrupted cell.
    for m in ["tide", "acc"] {
        for arm in ["ewm_0.01", "median"] {
            let svg = fs::read_to_string(p("roc").join(format!("roc-{m}-{arm}.svg"))).unwrap();
            assert!(svg.contains("<svg") && svg.contains("AUROC"), "{m} {arm}");
        }
    }
    let rows = ev["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 8, "{ev}");
    for r in rows {
        let clean = r["reference"].is_null();
        assert_eq!(r["auroc"].is_null(), clean, "{r}");
        if r["monitor"] == "tide" {
            assert_eq!(
                r["fired"], 0,
                "a threshold that can never fire never fires: {r}"
            );
        }
        if let Some(a) = r["auroc"].as_f64() {
            assert!((0.0..=1.0).contains(&a), "{r}");
            let roc = r["roc"].as_array().unwrap();
            assert_eq!(roc.first().unwrap(), &serde_json::json!([0.0, 0.0]), "{r}");
            assert_eq!(roc.last().unwrap(), &serde_json::json!([1.0, 1.0]), "{r}");
        }
    }
    // Bad input: a corrupted cell cannot calibrate; a missing file is named.
    mte()
        .args(["monitor", "calibrate"])
        .arg(p("run"))
        .args(["--cell", "nope", "--out"])
        .arg(p("t3.json"))
        .assert()
        .code(2)
        .stderr(predicate::str::contains("--cell nope"));
    mte()
        .args(["monitor", "evaluate"])
        .arg(p("run"))
        .arg("--thresholds")
        .arg(p("missing.json"))
        .assert()
        .code(2)
        .stderr(predicate::str::contains("missing.json"));
}

/// `mte attack alignment --fault blank` measures blank frames' displacements; `--fault
/// patch` without `--patch` is refused, naming the flag; `train act --config` with a key ACT
/// does not have is refused, naming the key.
#[test]
fn alignment_of_blank_frames_and_refused_arguments() {
    let v = json_stdout(
        mte()
            .args([
                "--format",
                "json",
                "attack",
                "alignment",
                "--fault",
                "blank",
            ])
            .args(["--episodes", "1", "--max-steps", "30", "--policy"])
            .arg(bundled()),
    );
    assert!(
        v["alignment"]["attacked_queries"].as_u64().unwrap() > 0,
        "{v}"
    );
    assert!(v["alignment"]["mean_norm"].as_f64().unwrap() > 0.0, "{v}");
    mte()
        .args(["attack", "alignment", "--fault", "patch", "--policy"])
        .arg(bundled())
        .assert()
        .failure()
        .stderr(predicate::str::contains("--patch"));
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("c.json");
    fs::write(&cfg, r#"{"chunk_sise": 20}"#).unwrap();
    mte()
        .args([
            "train", "act", "--data", "unused", "--steps", "1", "--config",
        ])
        .arg(&cfg)
        .arg("--out")
        .arg(dir.path().join("o"))
        .assert()
        .failure()
        .stderr(predicate::str::contains("chunk_sise"));
}

/// `mte report --control` takes `ATTACK:CONTROL`; anything else is refused with the form.
#[test]
fn report_control_pairs_need_two_cell_ids() {
    let dir = tempfile::tempdir().unwrap();
    for bad in ["nocolon", ":grey", "a:b:c"] {
        mte()
            .arg("report")
            .arg(dir.path())
            .args(["--control", bad])
            .assert()
            .failure()
            .stderr(predicate::str::contains("ATTACK:CONTROL"));
    }
}

/// The bundled ACT checkpoint loads from a fresh clone through the policy seam and drives
/// PushT under both aggregators: its chunk is 20 actions, and each coverage is a fraction.
#[test]
fn bundled_act_policy_runs_ensembled_episodes() {
    let ckpt = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../assets/policies/pusht_keypoints_act_cpu");
    let config: serde_json::Value =
        serde_json::from_str(&fs::read_to_string(ckpt.join("config.json")).unwrap()).unwrap();
    assert_eq!(
        (config["type"].as_str(), config["chunk_size"].as_u64()),
        (Some("act"), Some(20))
    );
    for arm in ["ewm:0.01", "median"] {
        let v = json_stdout(
            mte()
                .args(["--format", "json", "eval", "policy", "--episodes", "1"])
                .args(["--max-steps", "30", "--stride", "2", "--execution", arm])
                .arg("--checkpoint")
                .arg(&ckpt),
        );
        let c = v["mean_max_coverage"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&c), "{arm}: {v}");
    }
}

/// Corrective episodes from a policy, trained on beside the demonstrations: with
/// `--normalization-from` the new checkpoint keeps the warm start's statistics, without it
/// they are pooled over both datasets.
#[test]
fn takeover_episodes_train_beside_demonstrations() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    mte()
        .args(["data", "generate", "--episodes", "2", "--max-steps", "20"])
        .arg("--out")
        .arg(p("demos"))
        .assert()
        .success();
    let v = json_stdout(
        mte()
            .args([
                "--format",
                "json",
                "data",
                "takeover",
                "--checkpoint",
                "expert:pusht",
            ])
            .args(["--switch", "2..12", "--episodes", "3", "--max-steps", "30"])
            .arg("--out")
            .arg(p("fixes")),
    );
    assert_eq!(v["episodes"], 3);
    let recorded = v["recorded"].as_u64().unwrap();
    assert!(recorded >= 1, "{v}");
    let info: serde_json::Value =
        serde_json::from_str(&fs::read_to_string(p("fixes/info.json")).unwrap()).unwrap();
    assert_eq!(info["episodes"].as_u64(), Some(recorded));
    assert_eq!(info["generator"]["takeover"]["execution"], "ewm:0.01");
    mte()
        .args(["data", "takeover", "--checkpoint", "expert:pusht"])
        .args(["--switch", "12..2", "--out"])
        .arg(p("bad"))
        .assert()
        .code(2)
        .stderr(predicate::str::contains("FIRST must not exceed LAST"));

    let tiny = p("tiny.json");
    fs::write(
        &tiny,
        r#"{"down_dims": [8, 16], "n_groups": 4, "diffusion_step_embed_dim": 8}"#,
    )
    .unwrap();
    let train_with = |config: &std::path::Path, out: &str, data: &[&str], extra: &[&str]| {
        let mut c = mte();
        c.args(["train", "diffusion", "--steps", "1", "--batch-size", "4"])
            .args(["--checkpoint-every", "0", "--config"])
            .arg(config);
        for d in data {
            c.arg("--data").arg(p(d));
        }
        c.args(extra).arg("--out").arg(p(out)).assert()
    };
    let train = |out: &str, data: &[&str], extra: &[&str]| {
        train_with(&tiny, out, data, extra).success();
    };
    let stats = |ckpt: &str| {
        fs::read(p(ckpt).join("policy_preprocessor_step_3_normalizer_processor.safetensors"))
            .unwrap()
    };
    train("first", &["demos"], &[]);
    let init = p("first/model.safetensors");
    let init = init.to_str().unwrap();
    let from = p("first");
    let from = from.to_str().unwrap();
    train(
        "kept",
        &["demos", "fixes"],
        &["--init", init, "--normalization-from", from],
    );
    train("pooled", &["demos", "fixes"], &["--init", init]);
    assert_eq!(stats("kept"), stats("first"), "the warm start's statistics");
    assert_ne!(
        stats("pooled"),
        stats("first"),
        "statistics of both datasets"
    );

    // A longer observation history from the same warm start (`--init-n-obs-steps`): the
    // policy trains on 4 observations; without the flag the init's narrower conditioning is
    // refused, naming the layer.
    let tiny4 = p("tiny4.json");
    fs::write(
        &tiny4,
        r#"{"down_dims": [8, 16], "n_groups": 4, "diffusion_step_embed_dim": 8, "n_obs_steps": 4}"#,
    )
    .unwrap();
    let wide = |out: &str, extra: &[&str]| {
        let init = [&["--init", init][..], extra].concat();
        train_with(&tiny4, out, &["demos"], &init)
    };
    wide("wide", &["--init-n-obs-steps", "2"]).success();
    let config: serde_json::Value =
        serde_json::from_str(&fs::read_to_string(p("wide/config.json")).unwrap()).unwrap();
    assert_eq!(config["n_obs_steps"], 4);
    wide("narrow", &[])
        .failure()
        .stderr(predicate::str::contains("cond_encoder.1.weight"));

    // `--config` sets the Diffusion Transformer's own fields (width, depth) on top of the
    // transformer's preset, which used to overwrite them.
    let dit = p("dit.json");
    fs::write(
        &dit,
        r#"{"transformer": {"n_layer": 1, "n_head": 2, "n_emb": 8, "p_drop_emb": 0.0,
            "p_drop_attn": 0.0, "causal_attn": true, "n_cond_layers": 0}}"#,
    )
    .unwrap();
    train_with(&dit, "dit", &["demos"], &["--backbone", "transformer"]).success();
    let config: serde_json::Value =
        serde_json::from_str(&fs::read_to_string(p("dit/config.json")).unwrap()).unwrap();
    assert_eq!(config["transformer"]["n_emb"], 8, "{config}");
    assert_eq!(config["transformer"]["n_layer"], 1, "{config}");
    assert_eq!(
        config["horizon"], 16,
        "the transformer preset's keypoint horizon"
    );
}
