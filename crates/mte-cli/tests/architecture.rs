//! ARCHITECTURE.md stays true: every workspace crate is in its crate map, and its
//! dependency table lists exactly the workspace edges `cargo metadata` reports.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::process::Command;

type Edges = BTreeMap<String, BTreeSet<String>>;

fn root() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))
}

/// Workspace crates and their normal dependencies on each other, from `cargo metadata`.
fn metadata_edges() -> Edges {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .args([
            "metadata",
            "--format-version",
            "1",
            "--no-deps",
            "--offline",
        ])
        .current_dir(root())
        .output()
        .expect("cargo metadata runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("metadata json");
    let packages = v["packages"].as_array().expect("packages");
    let names: BTreeSet<String> = packages
        .iter()
        .map(|p| p["name"].as_str().expect("name").to_string())
        .collect();
    packages
        .iter()
        .map(|p| {
            let deps = p["dependencies"]
                .as_array()
                .expect("dependencies")
                .iter()
                .filter(|d| d["kind"].is_null()) // normal, not dev or build
                .filter_map(|d| d["name"].as_str())
                .filter(|n| names.contains(*n))
                .map(String::from)
                .collect();
            (p["name"].as_str().expect("name").to_string(), deps)
        })
        .collect()
}

/// The rows of the markdown table under `heading` whose first cell is a code span.
fn table_rows(doc: &str, heading: &str) -> Vec<Vec<String>> {
    let start = doc
        .find(heading)
        .unwrap_or_else(|| panic!("no `{heading}` section"));
    doc[start..]
        .lines()
        .skip_while(|l| !l.starts_with('|'))
        .take_while(|l| l.starts_with('|'))
        .map(|l| {
            l.trim_matches('|')
                .split('|')
                .map(|c| c.trim().to_string())
                .collect::<Vec<_>>()
        })
        .filter(|cells| cells[0].starts_with('`'))
        .collect()
}

/// `mte-cli` (binary `mte`) -> mte-cli.
fn crate_name(cell: &str) -> String {
    cell.split('`').nth(1).unwrap_or_default().to_string()
}

#[test]
fn the_crate_map_names_every_workspace_crate() {
    let doc = std::fs::read_to_string(root().join("ARCHITECTURE.md")).expect("ARCHITECTURE.md");
    let listed: BTreeSet<String> = table_rows(&doc, "## Crate map")
        .iter()
        .map(|r| crate_name(&r[0]))
        .collect();
    let actual: BTreeSet<String> = metadata_edges().into_keys().collect();
    assert_eq!(
        listed, actual,
        "ARCHITECTURE.md's crate map against the workspace"
    );
}

#[test]
fn the_dependency_table_matches_cargo_metadata() {
    let doc = std::fs::read_to_string(root().join("ARCHITECTURE.md")).expect("ARCHITECTURE.md");
    let drawn: Edges = table_rows(&doc, "## Dependency direction")
        .iter()
        .map(|r| {
            let deps = r
                .get(1)
                .map(|c| {
                    c.split(',')
                        .map(crate_name)
                        .filter(|n| !n.is_empty())
                        .collect()
                })
                .unwrap_or_default();
            (crate_name(&r[0]), deps)
        })
        .collect();
    assert_eq!(
        drawn,
        metadata_edges(),
        "ARCHITECTURE.md's dependency table against cargo metadata"
    );
}
