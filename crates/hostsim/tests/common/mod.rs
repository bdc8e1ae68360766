//! Set-up shared by the integration tests: a logged run of a scenario, a scratch folder.

// Each test crate uses its own part of this module.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

use hostsim::drives::SimDrives;
use hostsim::log::McapLog;
use hostsim::scenario::Scenario;
use hostsim::sim::{LogOptions, RunSummary, run, run_metadata};

/// Runs `scenario` on the simulated drives, logging every message into `log`, which is left
/// open (the caller finishes it, or drops it to leave a log cut short).
pub fn run_into(scenario: &Scenario, log: &mut McapLog) -> RunSummary {
    let mut plant = SimDrives::for_scenario(scenario).unwrap();
    run(
        scenario,
        &mut plant,
        Some(log),
        LogOptions::default(),
        |_| {},
    )
    .unwrap()
}

/// Runs `scenario` and writes its complete log (with the run's metadata, as `hostsim run`
/// writes it) to `path`.
pub fn logged_run(scenario: &Scenario, path: &Path) -> RunSummary {
    let mut log = McapLog::create(path, &run_metadata(scenario)).unwrap();
    let summary = run_into(scenario, &mut log);
    log.finish().unwrap();
    summary
}

/// `name` in a scratch folder `group` under Cargo's temporary directory for integration
/// tests (kept after the run, for a look at a failure).
pub fn scratch(group: &str, name: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(group);
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}
