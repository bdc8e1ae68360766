//! `hostsim check`: the bring-up check on a simulated robot on blocks.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result, bail};

use super::*;

/// The bring-up check on a simulated robot on blocks: which wheel turns, which way.
///
/// Each configured wheel in turn is driven by the firmware's WHEEL_TEST (only a disabled
/// robot runs it: a quarter of the current limit, --duration-ms long, then disabled
/// again), on a fresh simulated robot with its wheels off the ground; the plant's ground
/// truth says which wheel turned and which way, as the person watching a real robot
/// does for `mecanum-drive check`. Prints per wheel what turned and the firmware's own
/// result, and the [drive] lines (esc_ids or node_ids, inverted) that fix the
/// configuration. --flip and --swap build the robot miswired on purpose.
///
/// Exit status: 0 if the robot is wired as configured, 3 if the check found a
/// miswiring (the fix is printed; as `mecanum-drive check`), 2 for an error.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Drive configuration TOML (as config/dji_m3508.toml or config/odrive.toml).
    /// Default: the built-in DJI example.
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// `--flip` and `--swap` (flattened: clap takes the help from their own docs).
    #[command(flatten)]
    pub wiring: WiringArgs,
    /// Wheel speed of each test, rad/s at the wheel (robot-forward; |speed| <= 10).
    #[arg(long, value_name = "RAD_S", default_value_t = 3.0)]
    pub speed: f32,
    /// Length of each test, ms (1-3000).
    #[arg(long, value_name = "MS", default_value_t = 1000)]
    pub duration_ms: u16,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

/// What `check` starts from: the configuration, its description and the robot's wiring.
pub struct Prepared {
    /// The drive configuration.
    pub config: firmware::Config,
    /// Where it came from, for the report.
    pub source: String,
    /// The simulated robot's wiring (`--flip`, `--swap`).
    pub spec: crate::nodes::plant::PlantSpec,
}

/// `hostsim check`'s checks before the first test: `--speed` and `--duration-ms` in range,
/// the configuration loads.
///
/// # Errors
/// The first of those that fails, naming the option or the file.
pub fn prepare(args: &Args) -> Result<Prepared> {
    if !(args.speed.is_finite() && args.speed.abs() <= 10.0 && args.speed != 0.0) {
        bail!(
            "--speed {}: expected a wheel speed in [-10, 10] rad/s, not 0",
            args.speed
        );
    }
    if !(1..=3000).contains(&args.duration_ms) {
        bail!("--duration-ms {}: expected 1-3000 ms", args.duration_ms);
    }
    let (config, source) = load_config(args.config.as_deref())?;
    let spec = args.wiring.spec();
    Ok(Prepared {
        config,
        source,
        spec,
    })
}

/// `hostsim check`: the bring-up check on a simulated robot on blocks.
pub fn execute(args: &Args) -> Result<ExitCode> {
    use crate::analysis::bringup::{Report, Wiring, diagnose, run_check};
    let Prepared {
        config,
        source,
        spec,
    } = prepare(args)?;
    let runs = run_check(&config, &spec, args.speed, args.duration_ms)
        .with_context(|| format!("configuration {source}"))?;
    let configured = Wiring::of(&config);
    let d = diagnose(&configured, runs.map(|r| r.seen));
    let report = Report::new(
        source,
        (args.speed, args.duration_ms),
        &configured,
        &runs,
        &d,
    );
    print_report(&report, args.json)?;
    Ok(if d.is_right() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(EXIT_MISWIRED)
    })
}
