//! The subcommands of `hostsim`, one module each: its arguments (`Args`, whose doc is the
//! subcommand's `--help`), `execute`, and what it prints. `main.rs` parses and dispatches;
//! the exit statuses are the constants here.

pub mod calibrate;
pub mod check;
pub mod kin;
pub mod plant;
pub mod plot;
pub mod replay;
pub mod run;
pub mod summary;
pub mod sweep;

use std::path::Path;

use anyhow::Result;
use hostsim::scenario::Scenario;

pub use mecanum_linux::parse_seconds;

/// Exit status of a command that ran and found a failure: frames that differ, a frame that
/// could not be sent, a run that did not pass.
pub const EXIT_FAILED: u8 = 1;
/// Exit status of an error before or instead of the work: bad arguments, files, interfaces.
pub const EXIT_ERROR: u8 = 2;
/// Exit status of `check` when it found a miswiring (the fix is printed), as
/// `mecanum-drive check`.
pub const EXIT_MISWIRED: u8 = 3;
/// Exit status of a `sweep` stopped by Ctrl-C (the rows finished are written), as a shell
/// reports a SIGINT death.
pub const EXIT_INTERRUPTED: u8 = 128 + 2;
/// Exit status of `replay` and `summary` for a damaged log whose complete part was used.
pub const EXIT_DAMAGED: u8 = 3;

/// The exit status of a process killed by SIGPIPE, as a shell reports it.
pub const SIGPIPE_STATUS: u8 = 128 + 13;

/// Warns on stderr that the log at `path` is damaged, if it is: where, what, what was read.
pub fn warn_if_damaged(path: &Path, read: &hostsim::log::ReadReport, doing: &str) {
    if !read.is_complete() {
        eprintln!("warning: {} is {read}; {doing}", path.display());
    }
}

/// Warns on stderr that messages of the log at `path` did not decode, and what `doing` does
/// about them; whether there were any.
pub fn warn_if_undecodable(
    path: &Path,
    undecodable: &hostsim::log::Undecodable,
    doing: &str,
) -> bool {
    let any = undecodable.total() > 0;
    if any {
        eprintln!("warning: {}: {undecodable}: {doing}", path.display());
    }
    any
}

/// A scenario file, or else a built-in of that name (`square` if none); `config` replaces
/// its configuration.
pub fn load_scenario(arg: Option<&str>, config: Option<firmware::Config>) -> Result<Scenario> {
    Ok(Scenario::load(arg.unwrap_or("square"), config)?)
}

/// The drive configuration of `--config`, or the built-in DJI example; with a description.
pub fn load_config(path: Option<&Path>) -> Result<(firmware::Config, String)> {
    match path {
        // The error names the file, and the line or the field.
        Some(p) => Ok((
            firmware::Config::from_toml_file(p)?,
            p.display().to_string(),
        )),
        None => Ok((
            firmware::Config::dji_m3508_example(),
            "built-in DJI M3508/C620 example".to_string(),
        )),
    }
}

/// A simulated robot wired otherwise than its configuration says (`check`, `plant`).
#[derive(Debug, Clone, clap::Args)]
pub struct WiringArgs {
    /// Mount this wheel's motor the other way than the configuration's `inverted` says
    /// (FL, FR, RL, RR or 0-3; repeatable).
    #[arg(long, value_name = "WHEEL", value_parser = parse_wheel)]
    flip: Vec<usize>,
    /// Wire these two wheels' drives to each other's ids (`esc_ids`/`node_ids`), e.g.
    /// `--swap FL,RL` (repeatable, applied in order).
    #[arg(long, value_name = "WHEEL,WHEEL", value_parser = parse_wheel_pair)]
    swap: Vec<[usize; 2]>,
}

impl WiringArgs {
    /// The plant's wiring as a scenario's `[plant]` table would give it.
    pub fn spec(&self) -> hostsim::scenario::PlantSpec {
        hostsim::scenario::PlantSpec {
            flip: self.flip.clone(),
            swap: self.swap.clone(),
            ..hostsim::scenario::PlantSpec::default()
        }
    }
}

/// A wheel by name (FL, FR, RL, RR, any case) or index 0-3.
pub fn parse_wheel(s: &str) -> Result<usize, String> {
    let t = s.trim();
    hostsim::bringup::WHEEL_NAMES
        .iter()
        .position(|n| n.eq_ignore_ascii_case(t))
        .or_else(|| t.parse::<usize>().ok().filter(|&i| i < 4))
        .ok_or_else(|| format!("{s:?} is not a wheel: FL, FR, RL, RR or 0-3"))
}

/// Two different wheels, `A,B`.
pub fn parse_wheel_pair(s: &str) -> Result<[usize; 2], String> {
    let (a, b) = s
        .split_once(',')
        .ok_or_else(|| format!("{s:?}: expected two wheels, e.g. FL,RL"))?;
    let (a, b) = (parse_wheel(a)?, parse_wheel(b)?);
    if a == b {
        return Err(format!("{s:?}: a wheel cannot swap with itself"));
    }
    Ok([a, b])
}
