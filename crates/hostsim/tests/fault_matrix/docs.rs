//! The tables in `docs/reliability.md`: the matrix's, the current figures' line, and the
//! check (or, with `UPDATE_FAULT_MATRIX` set, the rewrite) of a block there.

use std::fmt::Write as _;
use std::path::Path;

use super::rows::Row;

pub(super) fn table(rows: &[Row]) -> String {
    let mut t = String::from(
        "| fault | onset | expected | budget | measured | detail | pass |\n|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        writeln!(
            t,
            "| {} | {} | {} | {} | {} | {} | {} |",
            r.fault,
            r.onset,
            r.expected,
            r.budget,
            r.measured,
            r.detail,
            if r.pass { "yes" } else { "**NO**" }
        )
        .unwrap();
    }
    t
}

fn doc_path() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/reliability.md")
}

/// Checks (or, with `UPDATE_FAULT_MATRIX` set, rewrites) the block between
/// `<!-- {name}:begin -->` and `<!-- {name}:end -->` in docs/reliability.md. One test at a
/// time reads and writes the file.
pub(super) fn keep_in_docs(name: &str, block: &str) {
    static DOC: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _one_at_a_time = DOC
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let path = doc_path();
    let doc = std::fs::read_to_string(&path).unwrap();
    let (begin, end) = (
        format!("<!-- {name}:begin -->\n"),
        format!("<!-- {name}:end -->"),
    );
    let (Some(b), Some(e)) = (doc.find(&begin), doc.find(&end)) else {
        panic!("{} has no {begin:?} ... {end:?} block", path.display());
    };
    let current = &doc[b + begin.len()..e];
    if current == block {
        return;
    }
    if std::env::var_os("UPDATE_FAULT_MATRIX").is_some() {
        let updated = format!("{}{block}{}", &doc[..b + begin.len()], &doc[e..]);
        std::fs::write(&path, updated).unwrap();
    } else {
        panic!(
            "docs/reliability.md ({name}) is out of date; rerun with UPDATE_FAULT_MATRIX=1 to \
             rewrite it. Now:\n{block}"
        );
    }
}

/// The fault matrix's line of the current figures at the top of docs/reliability.md.
pub(super) fn current_figures(rows: &[Row]) -> String {
    let faults: std::collections::BTreeSet<&str> = rows
        .iter()
        .map(|r| r.fault.split(',').next().unwrap_or(&r.fault))
        .collect();
    let stops = rows
        .iter()
        .filter(|r| r.expected.contains("zero current") || r.expected.contains("zero targets"))
        .count();
    let mut t = String::new();
    writeln!(t, "| fault matrix (the simulator, lockstep) | rows | kinds of fault | rows that must stop the motors | in their specified state within budget |").unwrap();
    writeln!(t, "|---|---|---|---|---|").unwrap();
    writeln!(
        t,
        "| `cargo test -p hostsim --test fault_matrix` | {} | {} | {stops} | {} of {} |",
        rows.len(),
        faults.len(),
        rows.iter().filter(|r| r.pass).count(),
        rows.len()
    )
    .unwrap();
    t
}
