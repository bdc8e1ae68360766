//! `hostsim calibrate`: the geometry (and the tracking pods) that make a log's odometry match
//! its reference.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result};
use serde::Serialize;

use super::*;

/// Fit the wheel radius, lx + ly and lateral effectiveness that make a log's odometry
/// match a reference pose, and each tracking pod's radius, direction and lever.
///
/// The odometry is recomputed from the logged wheel angles (/joint_states) with the
/// logged configuration (else the firmware's /odom); the reference is the simulator's
/// ground truth (/ground_truth/odom) or --reference TOPIC, e.g. an external tracker's
/// geometry_msgs/msg/PoseStamped or nav_msgs/msg/Odometry recorded into the same MCAP
/// (its body frame the robot's), interpolated at the odometry's log times. Body-frame
/// increments over consecutive windows (SE(2) log of the relative pose) are regressed per
/// axis. Convention: the radius is the effective one with forward_effectiveness = 1,
/// lx + ly the effective one with yaw_effectiveness = 1 (lx and ly keep their ratio),
/// lateral_effectiveness relative to that radius; they refine the logged values, so a log
/// recorded with the calibrated configuration gives corrections of 1.
///
/// A robot with tracking pods ([[odometry.pods]]) also has each pod fitted: its logged
/// wheel angle (/joint_states pod0, pod1, pod2) over each window against the reference's
/// body increment (dx, dy, dθ), Δα = (cos φ dx + sin φ dy + m dθ) / r, by least squares:
/// the radius r, the direction φ and the lever m = x sin φ − y cos φ (the distance of the
/// pod's line of action from the origin; where along that line it touches the floor is
/// unobservable). A straight leg along the pod gives its radius, motion across it its
/// direction, a spin its lever.
///
/// Prints each correction and value with its standard error, the RMS of the per-window
/// residuals, and the [geometry] lines to paste (and the [[odometry.pods]] tables, their
/// contact point moved across the line of action to the fitted lever); --write FILE
/// writes the logged configuration with them. The loop: `hostsim run calibration`,
/// `hostsim calibrate out/calibration.mcap --write cal.toml`, `hostsim run calibration
/// --config cal.toml`.
///
/// Exit status: 0, 2 if the log is refused (its motion cannot determine a value: it
/// needs 0.5 m of forward and of sideways travel and a full turn, and each pod 0.5 m of
/// travel along and across its direction; no configuration or reference in it) or FILE
/// cannot be written, 3 if the log is damaged (the fit used its complete part).
#[derive(Debug, clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    /// A log (MCAP) of `hostsim run`, `mecanum-runner --log` or `hostsim plant --log`.
    pub log: PathBuf,
    /// The reference pose topic.
    #[arg(long, value_name = "TOPIC", default_value = crate::analysis::calibrate::GROUND_TRUTH)]
    pub reference: String,
    /// Window length, s.
    #[arg(long, value_name = "SECONDS", default_value_t = 0.1)]
    pub window: f64,
    /// Write the logged configuration with the fitted [geometry] (and pods) to FILE.
    #[arg(long, value_name = "FILE")]
    pub write: Option<PathBuf>,
    /// Print the report as JSON (one object on stdout).
    #[arg(long)]
    pub json: bool,
}

/// `hostsim calibrate`.
pub fn execute(a: &Args) -> Result<ExitCode> {
    calibrate(
        &a.log,
        a.reference.clone(),
        a.window,
        a.write.as_deref(),
        a.json,
    )
}

/// `calibrate LOG`: the fitted geometry, printed and optionally written.
fn calibrate(
    path: &Path,
    reference: String,
    window_s: f64,
    write: Option<&Path>,
    json: bool,
) -> Result<ExitCode> {
    let options = crate::analysis::calibrate::Options {
        reference,
        window_s,
    };
    if let Some(file) = write {
        // Now, not after the fit: a path that cannot be written fails first. (Its temporary
        // file only: the last calibration there stays until the new one is whole.)
        drivelog::Staged::create(file).context("cannot write the calibration")?;
    }
    let c = crate::analysis::calibrate::calibrate(path, &options)
        .with_context(|| format!("cannot calibrate from {}", path.display()))?;
    warn_if_damaged(path, &c.read, "the fit used its complete part");
    if let Some(file) = write {
        let text = format!(
            "# The configuration of {}, [geometry]{} calibrated by hostsim calibrate \
             (reference {}).\n{}",
            path.display(),
            if c.pods.is_empty() {
                ""
            } else {
                " and [[odometry.pods]]"
            },
            c.reference,
            c.config.to_toml_string()
        );
        drivelog::output::write_whole(file, text.as_bytes())
            .context("cannot write the calibration")?;
    }
    let report = Report {
        geometry_lines: c.geometry_lines(),
        pod_lines: (!c.pods.is_empty()).then(|| c.pod_lines()),
        complete: c.read.is_complete(),
        calibration: &c,
        log: path,
        written: write,
    };
    print_report(&report, json)?;
    Ok(if c.read.is_complete() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(EXIT_DAMAGED)
    })
}

/// What `calibrate` reports: the fit (SI units; directions in degrees) with the lines to
/// paste, as text or (`--json`) as one JSON object.
#[derive(Debug, Serialize)]
struct Report<'a> {
    /// The fit.
    #[serde(flatten)]
    calibration: &'a crate::analysis::calibrate::Calibration,
    /// The `[geometry]` lines to paste.
    geometry_lines: String,
    /// The `[[odometry.pods]]` tables to paste, with pods.
    #[serde(skip_serializing_if = "Option::is_none")]
    pod_lines: Option<String>,
    /// The log was read whole (else the fit used its complete part).
    complete: bool,
    /// The log: text only.
    #[serde(skip)]
    log: &'a Path,
    /// The file `--write` wrote: text only.
    #[serde(skip)]
    written: Option<&'a Path>,
}

impl std::fmt::Display for Report<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(f, "calibration from {}", self.log.display())?;
        write!(f, "{}", self.calibration)?;
        if let Some(file) = self.written {
            write!(f, "\nwritten: {}", file.display())?;
        }
        Ok(())
    }
}
