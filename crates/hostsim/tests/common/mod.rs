//! Set-up shared by the integration tests: a logged run of a scenario, a scratch folder.

// Each test crate uses its own part of this module.
#![allow(dead_code)]

use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::Command;

use drivelog::McapLog;
use hostsim::analysis::calibrate::{Calibration, Options, calibrate};
use hostsim::engine::{LogOptions, RunSummary, run, run_metadata};
use hostsim::scenario::Scenario;

/// Runs `scenario` on the simulated drives, logging every message into `log`, which is left
/// open (the caller finishes it, or drops it to leave a log cut short).
pub fn run_into(scenario: &Scenario, log: &mut McapLog) -> RunSummary {
    let mut plant = hostsim::engine::plant_for(scenario).unwrap();
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

/// Runs the `hostsim` binary with `args`: its exit code (-1 if a signal ended it), stdout and
/// stderr.
pub fn hostsim<S: AsRef<OsStr>>(args: impl IntoIterator<Item = S>) -> (i32, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_hostsim"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// The calibration of the log at `path` with the default options.
pub fn fit(path: &Path) -> Calibration {
    calibrate(path, &Options::default()).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Prints a calibration's report under `what`, indented.
pub fn print_fit(what: &str, c: &Calibration) {
    println!("{what}:");
    for line in c.to_string().lines() {
        println!("  {line}");
    }
}

/// The [`SimPlant`](hostsim::nodes::SimPlant) methods of a test plant around `self.drives` (a
/// [`SimDrives`](hostsim::nodes::drives::SimDrives)) that pass through to them, the plant's time kept in `self.now_ns`:
/// `advance`, `advance_ns`, `truth`, `truth_velocity` and `set_faults`. Used inside the
/// plant's `impl SimPlant`.
#[allow(unused_macros)] // as `dead_code` above: not every test crate has such a plant
macro_rules! pass_to_drives {
    () => {
        fn advance(&mut self, dt: f64) {
            self.advance_ns((dt * 1e9).round() as u64);
        }
        fn advance_ns(&mut self, dt_ns: u64) {
            self.now_ns += dt_ns;
            self.drives.advance_ns(dt_ns);
        }
        fn truth(&self) -> [f64; 3] {
            self.drives.truth()
        }
        fn truth_velocity(&self) -> [f64; 3] {
            self.drives.truth_velocity()
        }
        fn set_faults(&mut self, at_ns: u64, stuck: [bool; 4], offline: [bool; 4]) {
            self.drives.set_faults(at_ns, stuck, offline);
        }
    };
}
#[allow(unused_imports)]
pub(crate) use pass_to_drives;

/// A scenario's TOML that enables the robot at 50 ms and commands `twist` from 100 ms on:
/// `head` (the top-level keys, `duration_s` and any other), the two actions, then `tables`
/// (faults, `[pods]`, ...).
pub fn driving(head: &str, twist: [f64; 3], tables: &str) -> String {
    format!(
        "{head}\n[[actions]]\nat_s = 0.05\nenable = true\n[[actions]]\nat_s = 0.1\n\
         twist = {twist:?}\n{tables}"
    )
}

/// `name` in a scratch folder `group` under Cargo's temporary directory for integration
/// tests (kept after the run, for a look at a failure).
pub fn scratch(group: &str, name: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(group);
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}
