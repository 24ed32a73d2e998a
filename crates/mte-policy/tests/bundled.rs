//! Every checkpoint bundled under `assets/policies/` loads through the policy seam and
//! declares the shapes its config file gives (a checkpoint added without its processor files,
//! or with a config its weights do not match, fails here rather than at an evaluation).

use mte_policy::load_policy;

#[test]
fn every_bundled_checkpoint_loads_with_its_configured_shapes() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/policies");
    let mut dirs: Vec<_> = std::fs::read_dir(&root)
        .expect("assets/policies")
        .map(|e| e.expect("entry").path())
        .filter(|p| p.join("config.json").is_file())
        .collect();
    dirs.sort();
    assert!(dirs.len() >= 10, "found only {} checkpoints", dirs.len());
    for dir in dirs {
        let text = std::fs::read_to_string(dir.join("config.json")).expect("config");
        let c: serde_json::Value = serde_json::from_str(&text).expect("JSON");
        let p = load_policy(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
        let horizon = if c["type"] == "act" {
            "chunk_size"
        } else {
            "horizon"
        };
        let action = c["output_features"]["action"]["shape"][0].as_u64();
        let name = dir.display();
        assert_eq!(
            p.horizon() as u64,
            c[horizon].as_u64().expect("horizon"),
            "{name}"
        );
        assert_eq!(
            p.action_dim() as u64,
            action.expect("action shape"),
            "{name}"
        );
        assert_eq!(
            p.n_obs_steps() as u64,
            c["n_obs_steps"].as_u64().expect("n_obs"),
            "{name}"
        );
    }
}
