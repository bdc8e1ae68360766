//! `hostsim kin`: the kinematics calculator on stdin and stdout.

use std::process::ExitCode;

use anyhow::{Context, Result};

use super::*;

/// Kinematics calculator: JSON lines on stdin, one JSON line out per non-blank line.
///
/// {"op":"inverse","lx":..,"ly":..,"r":..,"vx":..,"vy":..,"wz":..} gives
/// {"fl":..,"fr":..,"rl":..,"rr":..}; {"op":"forward","lx":..,"ly":..,"r":..,
/// "fl":..,"fr":..,"rl":..,"rr":..} gives {"vx":..,"vy":..,"wz":..}.
///
/// The standard four-wheel layout: lx and ly are the distances in metres from the
/// centre to a wheel's contact point along x (forward) and y (left), i.e. half the
/// wheelbase and half the track, both > 0; r is the wheel radius in metres. Wheel speeds
/// in rad/s (positive rolls the robot forward), vx and vy in m/s, wz in rad/s
/// counter-clockwise.
///
/// A line that cannot be answered (not JSON or not UTF-8, a missing or bad field, a
/// result too large to be finite) gives {"error":"..."} naming the field and the value,
/// and the next lines are answered as usual. Blank lines get no answer.
#[derive(Debug, clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {}

/// `hostsim kin`.
pub fn execute(_: &Args) -> Result<ExitCode> {
    let stdin = std::io::stdin();
    match crate::analysis::kin::run(stdin.lock(), std::io::stdout().lock()) {
        Ok(()) => Ok(ExitCode::SUCCESS),
        // The reader went away (`hostsim kin | head -1`): end quietly, as on SIGPIPE.
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(ExitCode::from(SIGPIPE_STATUS)),
        Err(e) => Err(e).context("reading stdin / writing stdout"),
    }
}
