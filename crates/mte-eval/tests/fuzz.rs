//! Property-based fuzzing, on stable Rust, of every parser a user hands mte input through:
//! replay streams, sweep specs, run-directory JSONL (through to the report), policy
//! `config.json` and safetensors files. Each takes arbitrary bytes and structured mutations
//! of a valid input (byte edits, and for JSON a random leaf replaced by a random value or
//! removed); the property is that nothing panics or aborts: every input is parsed or
//! refused with an error. Memory stays bounded because every size a parser allocates by is
//! bounded before allocation (replay: by the chunk window; sweeps: `MAX_SEEDS`; configs:
//! `DiffusionConfig::validate`'s size bounds).

use std::path::Path;

use mte_ensemble::Aggregator;
use mte_eval::replay::{read_stream, replay};
use mte_eval::report::{ReportOptions, build};
use mte_eval::store::{read_lines, read_manifest};
use mte_eval::sweep::SweepSpec;
use proptest::prelude::*;

/// Byte edits of `base`: `(position, kind, byte)` triples; kind 0 overwrites, 1 inserts,
/// 2 deletes.
fn mutate_bytes(base: &[u8], edits: &[(usize, u8, u8)]) -> Vec<u8> {
    let mut v = base.to_vec();
    for &(pos, kind, byte) in edits {
        let at = if v.is_empty() { 0 } else { pos % (v.len() + 1) };
        match kind % 3 {
            0 if at < v.len() => v[at] = byte,
            1 => v.insert(at, byte),
            2 if at < v.len() => {
                v.remove(at);
            }
            _ => v.push(byte),
        }
    }
    v
}

/// A random leaf of `v` (chosen by `pick`) replaced by `with`, or removed when `with` is
/// null inside an object.
fn mutate_json(v: &mut serde_json::Value, pick: &mut u64, with: &serde_json::Value) {
    use serde_json::Value;
    match v {
        Value::Object(map) if !map.is_empty() => {
            let keys: Vec<String> = map.keys().cloned().collect();
            let k = &keys[(*pick % keys.len() as u64) as usize];
            *pick /= keys.len() as u64 + 1;
            let child = map.get_mut(k).expect("key");
            if child.is_object() || child.is_array() {
                mutate_json(child, pick, with);
            } else if with.is_null() {
                map.remove(k);
            } else {
                *child = with.clone();
            }
        }
        Value::Array(items) if !items.is_empty() => {
            let i = (*pick % items.len() as u64) as usize;
            *pick /= items.len() as u64 + 1;
            if items[i].is_object() || items[i].is_array() {
                mutate_json(&mut items[i], pick, with);
            } else {
                items[i] = with.clone();
            }
        }
        _ => *v = with.clone(),
    }
}

/// Values a mutation plants: extremes of every JSON type.
fn hostile_value() -> impl Strategy<Value = serde_json::Value> {
    use serde_json::json;
    prop_oneof![
        Just(json!(null)),
        Just(json!(0)),
        Just(json!(-1)),
        Just(json!(u64::MAX)),
        Just(json!(1e300)),
        Just(json!(-1e-300)),
        Just(json!(1_000_000_000u64)),
        Just(json!("")),
        Just(json!("median")),
        Just(json!([])),
        Just(json!({})),
        Just(json!(true)),
        any::<i64>().prop_map(|n| json!(n)),
        any::<f64>()
            .prop_filter("finite", |x| x.is_finite())
            .prop_map(|x| json!(x)),
    ]
}

const STREAM: &str = "{\"t\": 0, \"chunk\": [[0.0, 1.0], [1.0, 2.0], [2.0, 3.0]]}\n\
                      {\"t\": 2, \"chunk\": [[2.0, 1.0], [3.0, 2.0], [4.0, 3.0]], \"corrupted\": true}\n\
                      {\"t\": 9, \"chunk\": [[9.0, 1.0], [9.5, 2.0], [9.9, 3.0]]}\n";

/// Parses and, when the stream is valid, replays it with every `t_o` that could fit.
fn replay_any(bytes: &[u8]) {
    if let Ok(stream) = read_stream(bytes) {
        for t_o in 1..=stream.t_p.min(3) {
            if let Ok(steps) = replay(&stream, t_o, Aggregator::MEDIAN) {
                // One record per covered time, one per uncovered run: bounded by the window.
                assert!(steps.len() <= stream.records.len() * (2 * stream.t_p + 1));
            }
        }
    }
}

const SPEC: &str = "name = \"x\"\npolicies = [\"p\"]\narms = [\"ewm:0.01\", \"median\"]\n\
                    h = [2, 8]\nseeds = { first = 100000, count = 3 }\nmax_steps = 300\n\
                    [[corruptions]]\nfault = { kind = \"occluder\", size = 24 }\nq = [0, 1, 2]\n\
                    [[corruptions]]\nfault = { kind = \"pgd\", iterations = 5 }\nq = [1]\n";

fn spec_any(text: &str) {
    if let Ok(spec) = SweepSpec::from_toml(text) {
        let cells = spec.cells();
        assert!(!cells.is_empty());
        assert!(spec.to_toml().is_ok());
    }
}

fn fixture() -> &'static Path {
    Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/fixtures/run_small"
    ))
}

/// Writes `text` as a cell file of the fixture run, reads it back and builds the report.
fn report_any(text: &[u8]) {
    let dir = tempfile::tempdir().expect("tmp");
    let path = dir.path().join("cell.jsonl");
    std::fs::write(&path, text).expect("write");
    let Ok(lines) = read_lines(&path) else { return };
    let manifest = read_manifest(fixture()).expect("fixture manifest");
    if let Ok(report) = build(&manifest, &lines, &ReportOptions::default()) {
        assert!(!report.markdown().is_empty());
    }
}

fn fixture_lines() -> String {
    let mut all = String::new();
    for e in std::fs::read_dir(fixture().join("cells")).expect("cells") {
        all.push_str(&std::fs::read_to_string(e.expect("entry").path()).expect("cell"));
    }
    all
}

fn bundled_config() -> String {
    std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../assets/policies/pusht_keypoints_cpu/config.json"
    ))
    .expect("bundled config")
}

fn config_any(text: &[u8]) {
    let dir = tempfile::tempdir().expect("tmp");
    let path = dir.path().join("config.json");
    std::fs::write(&path, text).expect("write");
    if let Ok(c) = mte_policy::DiffusionConfig::from_file(&path) {
        // Valid configs are small enough to build: validate bounds every size.
        assert!(c.horizon <= 1024 && c.down_dims.len() <= 6);
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    #[test]
    fn replay_streams_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..400)) {
        replay_any(&bytes);
    }

    #[test]
    fn mutated_replay_streams_never_panic(
        edits in prop::collection::vec((any::<usize>(), any::<u8>(), any::<u8>()), 1..8),
    ) {
        replay_any(&mutate_bytes(STREAM.as_bytes(), &edits));
    }

    #[test]
    fn replay_streams_with_hostile_values_never_panic(
        pick in any::<u64>(), with in hostile_value(), line in 0usize..3,
    ) {
        let mut lines: Vec<String> = STREAM.lines().map(String::from).collect();
        let mut v: serde_json::Value = serde_json::from_str(&lines[line]).expect("json");
        let mut p = pick;
        mutate_json(&mut v, &mut p, &with);
        lines[line] = v.to_string();
        replay_any(lines.join("\n").as_bytes());
    }

    #[test]
    fn sweep_specs_never_panic(text in ".{0,300}") {
        spec_any(&text);
    }

    #[test]
    fn mutated_sweep_specs_never_panic(
        edits in prop::collection::vec((any::<usize>(), any::<u8>(), any::<u8>()), 1..8),
    ) {
        let bytes = mutate_bytes(SPEC.as_bytes(), &edits);
        spec_any(&String::from_utf8_lossy(&bytes));
    }

    #[test]
    fn sweep_specs_with_hostile_values_never_panic(pick in any::<u64>(), with in hostile_value()) {
        let mut v: toml::Value = toml::from_str(SPEC).expect("spec");
        let mut j = serde_json::to_value(&v).expect("json");
        let mut p = pick;
        mutate_json(&mut j, &mut p, &with);
        if let Ok(t) = serde_json::from_value::<toml::Value>(j) {
            v = t;
        }
        if let Ok(text) = toml::to_string(&v) {
            spec_any(&text);
        }
    }

    #[test]
    fn run_files_never_panic_the_reader_or_the_report(
        bytes in prop::collection::vec(any::<u8>(), 0..300),
    ) {
        report_any(&bytes);
    }

    #[test]
    fn run_files_with_hostile_values_never_panic_the_report(
        picks in prop::collection::vec((any::<u64>(), hostile_value()), 1..4),
        line in any::<usize>(),
    ) {
        let text = fixture_lines();
        let mut lines: Vec<String> = text.lines().map(String::from).collect();
        let i = line % lines.len();
        let mut v: serde_json::Value = serde_json::from_str(&lines[i]).expect("json");
        for (pick, with) in &picks {
            let mut p = *pick;
            mutate_json(&mut v, &mut p, with);
        }
        lines[i] = v.to_string();
        report_any((lines.join("\n") + "\n").as_bytes());
    }

    #[test]
    fn policy_configs_never_panic(
        picks in prop::collection::vec((any::<u64>(), hostile_value()), 1..4),
        edits in prop::collection::vec((any::<usize>(), any::<u8>(), any::<u8>()), 0..3),
    ) {
        let mut v: serde_json::Value = serde_json::from_str(&bundled_config()).expect("json");
        for (pick, with) in &picks {
            let mut p = *pick;
            mutate_json(&mut v, &mut p, with);
        }
        config_any(&mutate_bytes(v.to_string().as_bytes(), &edits));
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    /// A checkpoint whose weights file is arbitrary bytes (or a mutated real header) is a
    /// typed error, never a panic or an unbounded allocation.
    #[test]
    fn safetensors_files_never_panic(
        edits in prop::collection::vec((0usize..64, any::<u8>(), any::<u8>()), 0..6),
        header_len in prop_oneof![Just(u64::MAX), Just(1u64 << 40), 0u64..512],
        tail in prop::collection::vec(any::<u8>(), 0..200),
    ) {
        let dir = tempfile::tempdir().expect("tmp");
        let bundled = Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../assets/policies/pusht_keypoints_cpu"
        ));
        for f in ["config.json", mte_policy::checkpoint::PRE_STATS, mte_policy::checkpoint::POST_STATS] {
            std::fs::copy(bundled.join(f), dir.path().join(f)).expect("copy");
        }
        let mut bytes = header_len.to_le_bytes().to_vec();
        bytes.extend_from_slice(br#"{"a":{"dtype":"F32","shape":[2],"data_offsets":[0,8]}}"#);
        bytes.extend_from_slice(&tail);
        let bytes = mutate_bytes(&bytes, &edits);
        std::fs::write(dir.path().join(mte_policy::checkpoint::WEIGHTS), bytes).expect("write");
        prop_assert!(mte_policy::load_policy(dir.path()).is_err());
    }
}
