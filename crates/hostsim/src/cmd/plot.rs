//! `hostsim plot`: logged runs side by side in one PNG.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Result;

use super::{EXIT_DAMAGED, warn_if_damaged, warn_if_undecodable};

/// Draw logged runs side by side in one PNG, e.g. before and after `calibrate`.
///
/// A panel per run with its ground truth and odometry seen from above (the same axes for
/// all), then one of every run's position error over time; the legends give each run's
/// largest drift. Give two logs to compare them, e.g. a run before and after `calibrate`: `hostsim plot
/// out/calibration.mcap recal/calibration.mcap`. Each needs /odom and /ground_truth/odom
/// (a `hostsim run` or `hostsim plant --log` log). Exit status 2 if a log cannot be read
/// or the PNG written.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// One or more MCAP logs (up to 3), each labelled by its path.
    #[arg(required = true, num_args = 1..=3)]
    pub logs: Vec<PathBuf>,
    /// The PNG to write. Default: beside the first log, its name with `.png` (one log) or
    /// `-vs-<second log's name>.png` (more).
    #[arg(long, value_name = "FILE")]
    pub out: Option<PathBuf>,
}

/// `hostsim plot`.
pub fn execute(a: &Args) -> Result<ExitCode> {
    plot_logs(&a.logs, a.out.clone())
}

/// `plot LOG...`: the runs in one figure.
fn plot_logs(logs: &[PathBuf], out: Option<PathBuf>) -> Result<ExitCode> {
    let stem = |p: &Path| {
        p.file_stem()
            .map_or_else(String::new, |s| s.to_string_lossy().into_owned())
    };
    let out = out.unwrap_or_else(|| {
        let mut name = stem(&logs[0]);
        if let Some(second) = logs.get(1) {
            name = format!("{name}-vs-{}", stem(second));
        }
        logs[0].with_file_name(format!("{name}.png"))
    });
    let logged = logs
        .iter()
        .map(|p| crate::analysis::plot::track_from_log(p).map_err(anyhow::Error::msg))
        .collect::<Result<Vec<_>>>()?;
    // Drawn all the same, from what could be read; said, and the exit status says it too.
    let mut damaged = false;
    for (path, l) in logs.iter().zip(&logged) {
        if !l.read.is_complete() {
            warn_if_damaged(path, &l.read, "the plot draws its complete part");
            damaged = true;
        }
        damaged |= warn_if_undecodable(path, &l.undecodable, "the plot leaves them out");
    }
    let tracks: Vec<Vec<crate::engine::TrackPoint>> =
        logged.into_iter().map(|l| l.points).collect();
    let labels: Vec<String> = logs.iter().map(|p| p.display().to_string()).collect();
    let runs: Vec<(&str, &[crate::engine::TrackPoint])> = labels
        .iter()
        .zip(&tracks)
        .map(|(l, t)| (l.as_str(), t.as_slice()))
        .collect();
    let title = stem(&logs[0]);
    crate::analysis::plot::plot_runs(&out, &title, &runs)?;
    for (label, track) in labels.iter().zip(&tracks) {
        println!(
            "{label}: max drift {:.1} mm",
            crate::analysis::plot::max_drift(track) * 1000.0
        );
    }
    println!("plot:  {}", out.display());
    Ok(if damaged {
        ExitCode::from(EXIT_DAMAGED)
    } else {
        ExitCode::SUCCESS
    })
}
