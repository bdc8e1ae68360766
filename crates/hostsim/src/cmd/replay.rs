//! `hostsim replay`: a log through a fresh core (MCAP, candump), a what-if, or onto a bus.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use mecanum_linux::{MonotonicClock, SocketCanBus};
use serde::Serialize;

use crate::realtime::{PlayOptions, play_frames};
use crate::replay::whatif::{OPEN_LOOP_NOTE, what_if_mcap};
use crate::replay::{
    CandumpReplayError, LogFormat, OdometryTolerance, ReportFrame, detect_format, mcap_playback,
    replay_candump, replay_mcap, split_candump,
};

use super::*;

/// Replay a log through a fresh firmware core and compare, try another configuration on
/// it (what-if, open loop), or play it onto a CAN bus.
///
/// Without --iface: the log's inbound frames go through a fresh firmware core and its
/// outbound frames are compared with the logged ones. An MCAP log (hostsim's) carries its
/// configuration and must match bit for bit, step for step. A candump log (`candump -L`,
/// detected by a .log/.candump extension or its content) has every frame on the bus mixed:
/// the firmware codecs of --config classify them. Sent by the firmware: the drive's
/// command frames (DJI current commands 0x200/0x1FF; ODrive commands to the configured
/// nodes) and the robot telemetry (ODOM_POSITION 0x310, ODOM_VELOCITY 0x311, STATUS 0x312,
/// HEARTBEAT 0x31F). Everything else was received and is fed, at its time relative to the
/// first frame, to a core stepping on the period grid anchored at the first frame. The
/// report gives the frame-stream comparison (time ignored; the first difference if any)
/// and the odometry: the last logged ODOM_POSITION/ODOM_VELOCITY against the replayed
/// core's pose at that time. All interfaces in a candump log are taken as one bus.
///
/// What-if (an MCAP log with --config FILE): the same recorded inbound frames, at the
/// same recorded times and steps, go through a core built from FILE instead of the logged
/// configuration, to see what a gain or limit change would have sent. OPEN LOOP: the
/// motors' feedback is what was recorded; the plant's reaction to the changed outputs is
/// not simulated (for that, run the scenario again with `run --config`). The report
/// (--json: one object) gives the changed fields, the first differing frame (time, logged
/// and what-if frame), frames logged / sent / differing per arbitration id, the drive
/// setpoints per wheel (FL FR RL RR) decoded with the firmware's codecs (DJI current, A;
/// ODrive velocity, rev/s, and torque feed-forward, Nm): max |setpoint| of each side, max
/// |what-if - logged| with its time and the RMS difference, and the state changes in the
/// STATUS frames of each side (e.g. a fault only in the what-if). FILE must describe the
/// same drives: the same protocol, ESC model and ESC ids (DJI) or node ids (ODrive), and
/// for a runner's log (recorded step times) the same timing.control_hz; else it is refused
/// naming the field and both values.
///
/// A damaged MCAP log (cut short by a killed run, or corrupt) is replayed up to shortly
/// before the time of the last message in its last complete, intact chunk (less the
/// longest a sent frame waited on the bus); a warning on stderr names the byte offset of
/// the damage and what was read before it. A log in the JSON layout of earlier versions
/// is refused.
///
/// Exit status: 0 if the frames match (candump: or the odometry agrees within the
/// tolerances), 1 if not, 2 for a bad log (nothing readable, no configuration, no
/// firmware frames to compare, as in a `plant` log or one cut before its first step, a
/// time line with a gap over 60 s), configuration or argument, 3 if the frames of a
/// damaged log's complete part match (the log is damaged: see the warning). What-if: 0
/// when it ran, whether or not the frames differ (that is the answer, not a failure); 2
/// if FILE does not load, is refused by the firmware or describes other drives; 3 if it
/// ran on a damaged log's complete part.
///
/// With --iface: plays the log's frames onto a SocketCAN interface in real time (each at
/// its logged time relative to the first, divided by --speed) and reports frames sent
/// and ENOBUFS retries. By default only the frames the firmware received (what the host
/// and the drives sent) are played, so a live mecanum-runner on the interface can be fed
/// the logged session. Stops early on SIGINT/SIGTERM. Exit status 1 if a frame could not
/// be sent (dropped after 100 ms of ENOBUFS retries, or another error), else 3 if the
/// MCAP log is damaged (its complete part was played).
#[derive(Debug, clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    /// A hostsim MCAP log, or a candump log (.log / .candump).
    pub log: PathBuf,
    /// Drive configuration TOML. candump log: used to classify and replay it (default:
    /// the built-in DJI example, as config/dji_m3508.toml). MCAP log: a what-if, the
    /// logged session replayed open loop through a core built from FILE instead of the
    /// logged configuration (see above).
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Print the report as JSON (one object on stdout).
    #[arg(long)]
    pub json: bool,
    /// candump replay: largest position difference for the odometry to agree, m.
    #[arg(long, value_name = "M", default_value_t = 0.01)]
    pub position_tolerance: f64,
    /// candump replay: largest heading difference for the odometry to agree, rad.
    #[arg(long, value_name = "RAD", default_value_t = 0.01)]
    pub heading_tolerance: f64,
    /// Play the frames onto this SocketCAN interface (e.g. vcan0) in real time instead
    /// of replaying them through a core.
    #[arg(long, value_name = "IFACE")]
    pub iface: Option<String>,
    /// With --iface: time scale (2 plays twice as fast). Default 1.
    #[arg(long, value_name = "FACTOR")]
    pub speed: Option<f64>,
    /// With --iface: which frames to play. rx (default): the frames the firmware
    /// received (host commands, motor feedback; MCAP /can/rx), to feed a live runner;
    /// tx: the frames the firmware sent (MCAP /can/tx); all: both, merged by time.
    #[arg(long, value_enum, value_name = "WHICH")]
    pub only: Option<Only>,
}

/// Which logged frames `replay --iface` plays.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Only {
    /// The frames the firmware received (from the host and the drives).
    Rx,
    /// The frames the firmware sent.
    Tx,
    /// Every frame.
    All,
}

/// What `replay` does with its log, its options checked.
#[derive(Debug, Clone, PartialEq)]
pub enum Mode {
    /// Through a fresh core (or a what-if), with these odometry tolerances (candump logs).
    Replay(OdometryTolerance),
    /// Onto a CAN interface.
    Play {
        /// The interface.
        iface: String,
        /// The time scale, finite and > 0.
        speed: f64,
        /// Which frames.
        only: Only,
    },
}

/// `hostsim replay`'s checks before it reads the log: `--speed` and `--only` only with
/// `--iface`, the speed or the tolerances in range.
///
/// # Errors
/// The first option out of place or out of range, naming it.
pub fn prepare(a: &Args) -> Result<Mode> {
    match &a.iface {
        Some(iface) => {
            let speed = a.speed.unwrap_or(1.0);
            if !(speed.is_finite() && speed > 0.0) {
                bail!("--speed must be a finite number > 0, got {speed}");
            }
            Ok(Mode::Play {
                iface: iface.clone(),
                speed,
                only: a.only.unwrap_or(Only::Rx),
            })
        }
        None => {
            if a.speed.is_some() || a.only.is_some() {
                bail!("--speed and --only need --iface (they control the playback)");
            }
            let tolerance = OdometryTolerance {
                position_m: a.position_tolerance,
                heading_rad: a.heading_tolerance,
            };
            for (name, value) in [
                ("--position-tolerance", tolerance.position_m),
                ("--heading-tolerance", tolerance.heading_rad),
            ] {
                if !(value.is_finite() && value >= 0.0) {
                    bail!("{name} must be a finite number >= 0, got {value}");
                }
            }
            Ok(Mode::Replay(tolerance))
        }
    }
}

/// `hostsim replay`.
pub fn execute(a: &Args) -> Result<ExitCode> {
    match prepare(a)? {
        Mode::Play { iface, speed, only } => {
            play(&a.log, a.config.as_deref(), &iface, speed, only, a.json)
        }
        Mode::Replay(tolerance) => replay(&a.log, a.config.as_deref(), tolerance, a.json),
    }
}

fn replay(
    path: &Path,
    config: Option<&Path>,
    tolerance: OdometryTolerance,
    json: bool,
) -> Result<ExitCode> {
    match detect_format(path)? {
        LogFormat::Mcap => match config {
            Some(config) => what_if_log(path, config, json),
            None => replay_mcap_log(path, json),
        },
        LogFormat::Candump => replay_candump_log(path, config, tolerance, json),
    }
}

fn replay_mcap_log(path: &Path, json: bool) -> Result<ExitCode> {
    let report = replay_mcap(path)?;
    let damaged = report.read.as_ref().filter(|r| !r.is_complete());
    if let Some(read) = damaged {
        warn_if_damaged(
            path,
            read,
            "replaying its complete part, up to the last message read",
        );
    }
    let code = if !report.identical() {
        ExitCode::from(EXIT_FAILED)
    } else if damaged.is_some() {
        ExitCode::from(EXIT_DAMAGED)
    } else {
        ExitCode::SUCCESS
    };
    let frame = |f: &Option<crate::replay::TimedFrame>| {
        f.map(|f| ReportFrame {
            t_s: format!("{:.6}", f.t_ns as f64 * 1e-9),
            frame: f.frame.to_string(),
        })
    };
    let report = McapReplay {
        log: path.display().to_string(),
        format: LogFormat::Mcap,
        steps: report.steps,
        fed: report.fed,
        compared: report.compared,
        identical: report.identical(),
        verdict: if report.identical() {
            "identical"
        } else {
            "differs"
        },
        first_difference: report.difference.as_ref().map(|d| McapDifference {
            index: d.index,
            t_s: format!("{:.6}", d.t_ns as f64 * 1e-9),
            logged: frame(&d.logged),
            replayed: frame(&d.replayed),
        }),
        complete: damaged.is_none(),
        damage: damaged.map(ToString::to_string),
        damage_offset: damaged.and_then(|r| r.damage.as_ref()).map(|d| d.offset),
    };
    print_report(&report, json)?;
    Ok(code)
}

/// What the replay of an MCAP log reports: the comparison, and the damage if the log is
/// damaged.
#[derive(Debug, Serialize)]
struct McapReplay {
    log: String,
    format: LogFormat,
    steps: u64,
    fed: usize,
    compared: usize,
    identical: bool,
    /// `identical` or `differs`.
    verdict: &'static str,
    first_difference: Option<McapDifference>,
    complete: bool,
    damage: Option<String>,
    /// The byte offset of the damage.
    damage_offset: Option<u64>,
}

/// A frame of a difference with its time, or `nothing` where the stream had ended.
fn shown(f: Option<&ReportFrame>) -> String {
    f.map_or_else(
        || "nothing".to_string(),
        |f| format!("{} at {} s", f.frame, f.t_s),
    )
}

/// The first outbound frame that differs: its index, the step's time, both frames.
#[derive(Debug, Serialize)]
struct McapDifference {
    index: usize,
    t_s: String,
    logged: Option<ReportFrame>,
    replayed: Option<ReportFrame>,
}

impl std::fmt::Display for McapReplay {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "replayed {} steps, fed {} inbound frames, compared {} outbound frames",
            self.steps, self.fed, self.compared
        )?;
        match &self.first_difference {
            None => write!(f, "outbound frames are bit-identical"),
            Some(d) => write!(
                f,
                "first difference at outbound frame {} ({} s): log has {}, replay sent {}",
                d.index,
                d.t_s,
                shown(d.logged.as_ref()),
                shown(d.replayed.as_ref())
            ),
        }
    }
}

/// `replay LOG.mcap --config FILE`: the what-if of another configuration on a logged session.
fn what_if_log(path: &Path, config: &Path, json: bool) -> Result<ExitCode> {
    let r = what_if_mcap(path, config)?;
    let damaged = r.read.as_ref().filter(|r| !r.is_complete());
    if let Some(read) = damaged {
        warn_if_damaged(
            path,
            read,
            "replaying its complete part, up to the last message read",
        );
    }
    // It ran: different or not is the answer, not a failure.
    let code = if damaged.is_some() {
        ExitCode::from(EXIT_DAMAGED)
    } else {
        ExitCode::SUCCESS
    };
    let report = WhatIf {
        note: OPEN_LOOP_NOTE,
        log: path.display().to_string(),
        format: LogFormat::Mcap,
        config: config.display().to_string(),
        verdict: if r.identical {
            "no_difference"
        } else {
            "differs"
        },
        complete: damaged.is_none(),
        damage: damaged.map(ToString::to_string),
        report: &r,
    };
    print_report(&report, json)?;
    Ok(code)
}

/// What a what-if reports: the comparison of [`crate::replay::whatif::WhatIfReport`], the log and
/// the configuration.
#[derive(Debug, Serialize)]
struct WhatIf<'a> {
    #[serde(flatten)]
    report: &'a crate::replay::whatif::WhatIfReport,
    /// [`OPEN_LOOP_NOTE`].
    note: &'static str,
    log: String,
    format: LogFormat,
    /// The what-if configuration's file.
    config: String,
    /// `no_difference` or `differs`.
    verdict: &'static str,
    complete: bool,
    damage: Option<String>,
}

impl std::fmt::Display for WhatIf<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let r = self.report;
        writeln!(f, "{}", self.note)?;
        writeln!(f, "log {}, what-if configuration {}", self.log, self.config)?;
        if r.changes.is_empty() {
            writeln!(
                f,
                "changes: none (the what-if configuration equals the logged one)"
            )?;
        } else {
            let show = |v: &Option<String>| v.as_deref().unwrap_or("(absent)").to_string();
            let changes: Vec<String> = r
                .changes
                .iter()
                .map(|c| format!("{} {} -> {}", c.field, show(&c.logged), show(&c.what_if)))
                .collect();
            writeln!(f, "changes: {}", changes.join(", "))?;
        }
        writeln!(
            f,
            "replayed {} steps, fed {} inbound frames; the log has {} outbound frames, the \
             what-if core sent {}",
            r.steps, r.fed, r.logged_frames, r.what_if_frames
        )?;
        match &r.first_difference {
            None => writeln!(
                f,
                "outbound frames are bit-identical: the change makes no difference on this log"
            )?,
            Some(d) => {
                // A frame's own time only where it is not the step's.
                let show = |f: &Option<ReportFrame>| match f {
                    None => "nothing".to_string(),
                    Some(f) if f.t_s == d.t_s => f.frame.clone(),
                    Some(f) => format!("{} at {} s", f.frame, f.t_s),
                };
                writeln!(
                    f,
                    "first difference at {} s (outbound frame {}): log has {}, what-if sent {}",
                    d.t_s,
                    d.index,
                    show(&d.logged),
                    show(&d.what_if)
                )?;
            }
        }
        writeln!(f, "outbound frames by arbitration id:")?;
        writeln!(
            f,
            "  {:<10} {:<28} {:>8} {:>8} {:>8}",
            "id", "message", "logged", "what-if", "differ"
        )?;
        for c in &r.by_id {
            writeln!(
                f,
                "  {:<10} {:<28} {:>8} {:>8} {:>8}",
                c.id,
                c.message,
                c.logged,
                c.what_if,
                c.differ()
            )?;
        }
        for q in &r.setpoints {
            writeln!(
                f,
                "{} setpoints, {} (difference = what-if - logged, each held between its \
                 commands):",
                q.quantity, q.unit
            )?;
            writeln!(
                f,
                "  {:<5} {:>11} {:>12} {:>11} {:>10} {:>11}",
                "wheel", "max|logged|", "max|what-if|", "max|diff|", "at (s)", "rms diff"
            )?;
            for w in &q.wheels {
                let d = &w.difference;
                writeln!(
                    f,
                    "  {:<5} {:>11.4} {:>12.4} {:>11.4} {:>10} {:>11.4}",
                    w.wheel,
                    w.max_abs_logged,
                    w.max_abs_what_if,
                    d.max_abs_difference,
                    d.t_max_difference_s.as_deref().unwrap_or("-"),
                    d.rms_difference
                )?;
            }
        }
        let list = |changes: &[crate::replay::whatif::StateChange]| {
            if changes.is_empty() {
                "none".to_string()
            } else {
                changes
                    .iter()
                    .map(ToString::to_string)
                    .collect::<Vec<_>>()
                    .join(", ")
            }
        };
        let s = &r.states;
        writeln!(f, "state changes in the STATUS frames:")?;
        writeln!(f, "  logged:               {}", list(&s.logged))?;
        writeln!(f, "  what-if:              {}", list(&s.what_if))?;
        writeln!(f, "  only in the log:      {}", list(&s.only_logged))?;
        writeln!(f, "  only in the what-if:  {}", list(&s.only_what_if))?;
        writeln!(f, "  what-if core (exact): {}", list(&s.what_if_core))?;
        write!(f, "verdict: {}", self.verdict)
    }
}

fn replay_candump_log(
    path: &Path,
    config: Option<&Path>,
    tolerance: OdometryTolerance,
    json: bool,
) -> Result<ExitCode> {
    let (config, source) = load_config(config)?;
    let r = replay_candump(path, &config, tolerance).map_err(|e| match e {
        CandumpReplayError::Refused(e) => anyhow::anyhow!("configuration {source}: {e}"),
        other => other.into(),
    })?;
    let code = if r.agrees() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(EXIT_FAILED)
    };
    let report = CandumpReport {
        log: path.display().to_string(),
        format: LogFormat::Candump,
        config: source,
        verdict: r.verdict(),
        report: &r,
    };
    print_report(&report, json)?;
    Ok(code)
}

/// What the replay of a candump log reports: [`crate::replay::CandumpReplay`], the log and
/// the configuration.
#[derive(Debug, Serialize)]
struct CandumpReport<'a> {
    #[serde(flatten)]
    report: &'a crate::replay::CandumpReplay,
    log: String,
    format: LogFormat,
    /// Where the configuration came from.
    config: String,
    verdict: &'static str,
}

impl std::fmt::Display for CandumpReport<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let r = self.report;
        writeln!(
            f,
            "candump log {}: {} frames on {} over {:.3} s; configuration: {}",
            self.log,
            r.frames,
            r.interfaces.join(", "),
            r.duration_s,
            self.config
        )?;
        writeln!(
            f,
            "firmware received {} frames (fed), sent {} (compared); replay ran {} steps of {} \
             µs and sent {}",
            r.received, r.sent, r.steps, r.period_us, r.replayed
        )?;
        match &r.first_difference {
            None => writeln!(f, "outbound frames are identical (time ignored)")?,
            Some(d) => {
                writeln!(
                    f,
                    "outbound frames differ (time ignored) at frame {} ({} matched): log has \
                     {}, replay sent {}",
                    d.index,
                    r.matching_prefix,
                    shown(d.logged.as_ref()),
                    shown(d.replayed.as_ref())
                )?;
            }
        }
        match &r.odometry {
            None => writeln!(f, "odometry: the log has no ODOM_POSITION frame to compare")?,
            Some(o) => {
                let pose = |p: &crate::replay::OdometryReading| {
                    format!(
                        "x {:+.4} m  y {:+.4} m  heading {:+.2}° at {:.3} s",
                        p.x,
                        p.y,
                        p.heading.to_degrees(),
                        p.t_s
                    )
                };
                writeln!(f, "odometry logged   {}", pose(&o.logged))?;
                writeln!(f, "odometry replayed {}", pose(&o.replayed))?;
                writeln!(
                    f,
                    "odometry {}: position {:.1} mm (tolerance {:.1} mm), heading {:.4} rad \
                     (tolerance {:.4} rad), velocity {:.4}",
                    if o.agrees { "agrees" } else { "DIFFERS" },
                    o.position_error_m * 1000.0,
                    o.tolerance.position_m * 1000.0,
                    o.heading_error_rad,
                    o.tolerance.heading_rad,
                    o.velocity_error
                )?;
            }
        }
        let e = &r.rejected;
        let rejected = e.extended_id + e.remote + e.wrong_dlc + e.non_finite + e.out_of_range;
        writeln!(
            f,
            "replayed core rejected {rejected} received frames, ignored {} with unknown ids",
            e.unknown_id
        )?;
        write!(f, "verdict: {}", self.verdict)
    }
}

/// `replay LOG --iface IFACE`: plays the log's frames onto the interface in real time.
fn play(
    path: &Path,
    config: Option<&Path>,
    iface: &str,
    speed: f64,
    only: Only,
    json: bool,
) -> Result<ExitCode> {
    let (rx, tx) = match only {
        Only::Rx => (true, false),
        Only::Tx => (false, true),
        Only::All => (true, true),
    };
    let mut damaged = false;
    let frames = match detect_format(path)? {
        LogFormat::Mcap => {
            if config.is_some() {
                bail!(
                    "--config applies to candump logs; {} is an MCAP log, whose /can/rx and \
                     /can/tx topics give the direction",
                    path.display()
                );
            }
            let content = crate::replay::read_log(path)?;
            warn_if_damaged(path, &content.read, "playing its complete part");
            if content.undecodable.total() > 0 {
                bail!("{}: {}: not played", path.display(), content.undecodable);
            }
            damaged = !content.read.is_complete();
            mcap_playback(&content, rx, tx)
        }
        LogFormat::Candump => {
            let (config, _) = load_config(config)?;
            let entries = drivelog::candump::read_file(path)?;
            let split = split_candump(&config, &entries);
            match only {
                Only::Rx => split.rx,
                Only::Tx => split.tx,
                Only::All => split.all,
            }
        }
    };
    // A corrupt timestamp would make the playback sleep for years.
    crate::replay::check_time_gaps(&frames)
        .with_context(|| format!("{}: cannot play", path.display()))?;
    let stop = mecanum_linux::stop_on_signals()?;
    let mut bus = SocketCanBus::open(iface)?;
    let clock = MonotonicClock::new(0);
    if !json {
        eprintln!(
            "playing {} frames ({only:?}) of {} onto {iface} at {speed}x; stop with Ctrl-C",
            frames.len(),
            path.display()
        );
    }
    let options = PlayOptions {
        speed,
        ..PlayOptions::default()
    };
    let report = play_frames(&frames, &mut bus, &clock, &options, &stop);
    print_report(&report, json)?;
    Ok(if report.failed > 0 {
        ExitCode::from(EXIT_FAILED)
    } else if damaged {
        ExitCode::from(EXIT_DAMAGED)
    } else {
        ExitCode::SUCCESS
    })
}
