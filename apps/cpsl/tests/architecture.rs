//! Imports only point downwards: every workspace crate's `[dependencies]` on other cpsl crates
//! must be listed as allowed in the table of ARCHITECTURE.md (between the `imports` markers),
//! every crate in the workspace must appear in that table, and a crate imports only crates of
//! its own stage or earlier ones (`crates/<n>-<stage>/`, numbered in pipeline order).

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

/// Every crate's manifest with its stage number: `crates/<n>-<stage>/<crate>/` in pipeline
/// order, the apps after all of them.
fn manifests() -> Vec<(u32, PathBuf)> {
    let dirs = |p: PathBuf| -> Vec<PathBuf> {
        let mut v: Vec<PathBuf> = std::fs::read_dir(p)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.is_dir())
            .collect();
        v.sort();
        v
    };
    let mut out = Vec::new();
    for stage in dirs(root().join("crates")) {
        let name = stage.file_name().unwrap().to_string_lossy().into_owned();
        let n: u32 = name
            .split('-')
            .next()
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("crates/{name}: stage folders are named <n>-<stage>"));
        out.extend(dirs(stage).into_iter().map(|c| (n, c.join("Cargo.toml"))));
    }
    out.extend(
        dirs(root().join("apps"))
            .into_iter()
            .map(|c| (u32::MAX, c.join("Cargo.toml"))),
    );
    out
}

#[test]
fn imports_point_downwards() {
    let allowed = allowed();
    let mut seen = BTreeSet::new();
    let mut stages = BTreeMap::new();
    let mut imports = Vec::new();
    for (stage, manifest) in manifests() {
        let text = std::fs::read_to_string(&manifest)
            .unwrap_or_else(|e| panic!("{}: {e}", manifest.display()));
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
        let ok = allowed
            .get(&name)
            .unwrap_or_else(|| panic!("{name} is missing from the ARCHITECTURE.md imports table"));
        let bad: Vec<_> = deps.difference(ok).collect();
        assert!(
            bad.is_empty(),
            "{name} imports {bad:?}, which ARCHITECTURE.md does not allow"
        );
        stages.insert(name.clone(), stage);
        imports.extend(deps.into_iter().map(|d| (name.clone(), d)));
        seen.insert(name);
    }
    for (from, to) in imports {
        assert!(
            stages[&to] <= stages[&from],
            "{from} (stage {}) imports {to} from a later stage ({})",
            stages[&from],
            stages[&to]
        );
    }
    let listed: BTreeSet<String> = allowed.keys().cloned().collect();
    assert_eq!(
        listed, seen,
        "ARCHITECTURE.md lists crates that do not exist (or misses some)"
    );
}
