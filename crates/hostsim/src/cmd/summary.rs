//! `hostsim summary`: what a log says, in numbers.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Result, bail};

use super::*;

/// Summarise a log: odometry drift against ground truth, bus load, state changes and
/// faults, messages per topic.
///
/// A damaged log (cut short by a killed run, or corrupt) is summarised up to its last
/// complete, intact chunk, and a warning on stderr names the byte offset of the damage
/// and what was read before it.
///
/// Exit status: 0 for an intact log, 2 if the file cannot be read or nothing in it is
/// readable (not MCAP, or an intact log without messages), 3 if the log is damaged (the
/// summary of its complete part is printed; for a log cut before its first chunk, a
/// summary without messages).
#[derive(Debug, clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    /// A hostsim MCAP log.
    pub log: PathBuf,
}

/// `hostsim summary`.
pub fn execute(a: &Args) -> Result<ExitCode> {
    summary(&a.log)
}

fn summary(path: &Path) -> Result<ExitCode> {
    let s = crate::analysis::summary::summarize(path).map_err(anyhow::Error::msg)?;
    let damaged = !s.read.is_complete();
    if s.topics.is_empty() && !damaged {
        bail!("{}: no messages", path.display());
    }
    println!("log {} ({:.2} s)", path.display(), s.duration_s);
    if let Some(name) = &s.scenario {
        println!("scenario: {name}");
    }
    if let (Some(o), Some(g), Some((last, max))) = (s.odometry, s.truth, s.drift) {
        println!(
            "odometry x {:+.4} y {:+.4} heading {:+.2}°; ground truth x {:+.4} y {:+.4} heading {:+.2}°",
            o[0],
            o[1],
            o[2].to_degrees(),
            g[0],
            g[1],
            g[2].to_degrees()
        );
        println!(
            "odometry drift: final {:.1} mm, max {:.1} mm",
            last * 1000.0,
            max * 1000.0
        );
    }
    if let Some(load) = s.bus_load {
        let fates: Vec<String> = s.fates.iter().map(|(k, v)| format!("{v} {k}")).collect();
        println!(
            "bus load {:.1} %; frames: {}",
            load * 100.0,
            fates.join(", ")
        );
    }
    for (t, level, text) in &s.events {
        let tag = match *level {
            l if l >= drivelog::msg::Log::ERROR => "FAULT",
            // An e-stop; other warnings (a silent gyro, a lost CAN link) do not stop.
            l if l >= drivelog::msg::Log::WARN && text.starts_with("state") => "STOP ",
            l if l >= drivelog::msg::Log::WARN => "WARN ",
            _ => "     ",
        };
        println!("  {tag} {t:9.3} s  {text}");
    }
    for (topic, n) in &s.topics {
        println!("  {topic:24} {n:>9} messages");
    }
    println!("read: {}", s.read);
    println!("decoded: {}", s.undecodable);
    if damaged {
        warn_if_damaged(path, &s.read, "the summary covers its complete part");
    }
    let undecodable = warn_if_undecodable(path, &s.undecodable, "the summary leaves them out");
    Ok(if damaged || undecodable {
        ExitCode::from(EXIT_DAMAGED)
    } else {
        ExitCode::SUCCESS
    })
}
