//! The host side of the cross-target check: runs the scenario of `xtarget_scenario` and prints
//! the same report the Cortex-M4 build prints through semihosting.
//!
//! `xtarget-host [--every N]`: print every N-th outbound frame (default 100, as on the M4;
//! 1 prints them all).

use std::io::{self, Write as _};
use std::process::ExitCode;

use xtarget_scenario::{NoProbe, Options, run_all};

fn main() -> ExitCode {
    let mut opts = Options::default();
    let args: Vec<String> = std::env::args().skip(1).collect();
    match args.as_slice() {
        [] => {}
        [flag, n] if flag == "--every" => match n.parse() {
            Ok(n) => opts.frame_every = n,
            Err(e) => {
                eprintln!("xtarget-host: --every {n}: {e}");
                return ExitCode::from(2);
            }
        },
        _ => {
            eprintln!("usage: xtarget-host [--every N]");
            return ExitCode::from(2);
        }
    }
    let mut report = String::new();
    if run_all(&opts, &mut report, &mut NoProbe).is_err() {
        return ExitCode::FAILURE;
    }
    let mut stdout = io::stdout().lock();
    if stdout.write_all(report.as_bytes()).is_err() {
        return ExitCode::FAILURE;
    }
    ExitCode::SUCCESS
}
