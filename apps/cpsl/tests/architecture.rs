//! Imports only point downwards: every workspace crate's `[dependencies]` on other cpsl crates
//! must be listed as allowed in the table of ARCHITECTURE.md (between the `imports` markers),
//! and every crate in the workspace must appear in that table.

use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// crate name -> allowed cpsl imports, parsed from ARCHITECTURE.md.
fn allowed() -> BTreeMap<String, BTreeSet<String>> {
    let doc = std::fs::read_to_string(root().join("ARCHITECTURE.md")).unwrap();
    let table = doc
        .split("<!-- imports:begin -->")
        .nth(1)
        .and_then(|t| t.split("<!-- imports:end -->").next())
        .expect("ARCHITECTURE.md has an imports table");
    let code = |cell: &str| -> Vec<String> {
        cell.split('`')
            .skip(1)
            .step_by(2)
            .map(str::to_string)
            .collect()
    };
    table
        .lines()
        .filter(|l| l.starts_with("| `"))
        .map(|l| {
            let cells: Vec<&str> = l.split('|').collect();
            (
                code(cells[1])[0].clone(),
                code(cells[3]).into_iter().collect(),
            )
        })
        .collect()
}

#[test]
fn imports_point_downwards() {
    let allowed = allowed();
    let mut seen = BTreeSet::new();
    for group in ["crates", "apps"] {
        for entry in std::fs::read_dir(root().join(group)).unwrap() {
            let manifest = entry.unwrap().path().join("Cargo.toml");
            let Ok(text) = std::fs::read_to_string(&manifest) else {
                continue;
            };
            let doc: toml::Table = text.parse().unwrap();
            let name = doc["package"]["name"].as_str().unwrap().to_string();
            let deps: BTreeSet<String> = doc
                .get("dependencies")
                .and_then(|d| d.as_table())
                .map(|t| {
                    t.keys()
                        .filter(|k| k.starts_with("cpsl"))
                        .cloned()
                        .collect()
                })
                .unwrap_or_default();
            let ok = allowed.get(&name).unwrap_or_else(|| {
                panic!("{name} is missing from the ARCHITECTURE.md imports table")
            });
            let bad: Vec<_> = deps.difference(ok).collect();
            assert!(
                bad.is_empty(),
                "{name} imports {bad:?}, which ARCHITECTURE.md does not allow"
            );
            seen.insert(name);
        }
    }
    let listed: BTreeSet<String> = allowed.keys().cloned().collect();
    assert_eq!(
        listed, seen,
        "ARCHITECTURE.md lists crates that do not exist (or misses some)"
    );
}
