//! `mecanum-runner`: the firmware's control core on a Linux SocketCAN interface, at a fixed
//! rate (see `--help`). The loop itself is `mecanum_linux::run`; this crate is the command
//! line, signal handling and reporting around it. It is a package of its own, not a binary
//! of `firmware`, so that it can write its log through `drivelog` (which depends on
//! `firmware`).

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::AtomicUsize;

use anyhow::{Context as _, Result};
use clap::Parser;
use firmware::config::Drive;
use firmware::{Config, Controller};
use mecanum_linux::{self as linux, MonotonicClock, Report, RunOptions, SocketCanBus, StopReason};
use mecanum_runner::params::{Found, ParamFile};
use mecanum_runner::{Console, McapRecorder};

/// Exit status for a startup error (bad arguments, configuration or interface).
const EXIT_STARTUP: u8 = 2;
/// The CAN link was lost and `--exit-on-link-loss` asked to stop.
const EXIT_LINK_LOST: u8 = 3;

const ABOUT: &str = "\
Runs the mecanum drive's control core on a SocketCAN interface at a fixed rate: it reads the
motor feedback and the robot's commands from the bus, and sends the motor commands, odometry,
status and heartbeat.";

const LONG_ABOUT: &str = "\
Runs the mecanum drive's control core on a SocketCAN interface at a fixed rate (the
configuration's timing.control_hz, 1000 Hz in the examples): it reads the motor feedback and
the robot's commands from the bus, and sends the motor commands, odometry, status and
heartbeat. The same core runs on the motor-controller MCU and in the simulator.

Robot protocol (dbc/mecanum_robot.dbc; CAN 2.0A, little-endian, ids 0x300-0x31F):
  host -> robot   0x300 ESTOP (magic 0xE5)    0x301 TWIST_CMD (vx, vy, wz, seq: +1 each)
                  0x302 MODE_CMD (0 disable, 1 enable, 2 reset)    0x303 STATUS_REQ
                  0x305 WHEEL_TEST (the bring-up check, one wheel at a time)
  IMU -> robot    0x304 IMU_YAW_RATE (f32 rad/s, seq), optional: [odometry] heading_source
  pods -> robot   0x306 POD_COUNTS (three u16 counts, seq), optional: [odometry] source
  robot -> host   0x310 ODOM_POSITION, 0x311 ODOM_VELOCITY (timing.odometry_hz, 100 Hz),
                  0x315 ODOM_SLIP (with pods: the slip estimate, the odometry source)
                  0x312 STATUS, 0x313 STATUS_COUNTERS, 0x31F HEARTBEAT (timing.status_hz,
                  10 Hz)
                  0x314 WHEEL_TEST_RESULT (after a WHEEL_TEST)
Motor side: DJI C620/C610 current commands on 0x200 (ESC 1-4) / 0x1FF (ESC 5-8) every
period, feedback on 0x201-0x208; or ODrive CAN Simple (node << 5 | command); or CANopen
CiA 402 drives (NMT, SDO configuration, SYNC, RPDO targets, TPDO status, heartbeats).
The robot starts disabled: send MODE_CMD enable, then TWIST_CMD at least every
timing.command_timeout_ms (100 ms), or it ramps to a stop and disables itself. TWIST_CMD.seq
is an alive counter: a twist with the seq of the last accepted one is a repeat, not applied
and not fed to the watchdog (counted in STATUS_COUNTERS), so increment it in every frame.

The CAN link: if the interface goes down or away (link set down, adapter unplugged, cable
fault), the runner keeps stepping the core at its rate (its watchdog and state machine see
the silence: without motor feedback it faults, and stays faulted until a reset and a new
enable), sends nothing, reopens the interface with back-off (10 ms doubling to 200 ms) and
resumes when it is back, without a restart. Each loss and recovery is printed as it happens
(and logged on /rosout with --log); the statistics count send and receive errors by kind and
the gaps. --exit-on-link-loss stops instead.

Live: with --live (and --log) the log is served to Foxglove or Lichtblick as it is written
(Foxglove WebSocket protocol, every channel with its schema; docs/live.md). The loop never
waits on a client: a slow one loses messages, counted on /diagnostics and in the statistics.

Exit: on SIGINT or SIGTERM (or when --duration has elapsed) the runner stops the loop,
sends the frames that leave the motors safe (DJI: zero current; ODrive: zero velocity, then
the idle state), prints statistics to stderr (loop jitter p50/p99/max, frame counts, bus
errors, the controller's state, rejected-frame and repeated-twist counters) and exits 0. A second SIGINT or
SIGTERM during that shutdown exits at once with status 1.
Exit status: 0 after a clean stop; 1 if the shutdown frames could not all be sent or the
statistics or the log could not be written; 2 for a startup error (bad arguments, a configuration file
that cannot be read or is invalid, a CAN interface that is missing or down); 3 when the CAN link
was lost and --exit-on-link-loss was given.";

#[derive(Debug, Parser)]
#[command(name = "mecanum-runner", version, about = ABOUT, long_about = LONG_ABOUT)]
struct Args {
    /// SocketCAN interface to run on, e.g. vcan0 or can0. It must exist and be up.
    #[arg(long, value_name = "IFACE")]
    iface: String,

    /// Drive configuration (TOML, as config/dji_m3508.toml or config/odrive.toml). Default:
    /// the built-in DJI example, 4 x M3508 motors on C620 ESCs 1-4 at 1000 Hz (the same as
    /// config/dji_m3508.toml).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,

    /// Stop after this many seconds (then shut down as on SIGINT). Default: run until
    /// SIGINT/SIGTERM.
    #[arg(long, value_name = "SECONDS", value_parser = mecanum_linux::parse_seconds, allow_hyphen_values = true)]
    duration: Option<f64>,

    /// Write the final statistics as JSON to FILE (created at startup, written on exit).
    #[arg(long, value_name = "FILE")]
    stats_json: Option<PathBuf>,

    /// Busy-wait the last MICROS before each deadline instead of sleeping: lower jitter, more
    /// CPU. Default 0 (sleep only); at most 10000.
    #[arg(long, value_name = "MICROS", default_value_t = 0,
          value_parser = clap::value_parser!(u64).range(0..=mecanum_linux::MAX_SPIN_US))]
    spin_us: u64,

    /// Record the run in FILE (an MCAP log, a ROS 2 bag in the simulator's format: every
    /// frame received and sent with the times the core saw, its step times, odometry, wheel
    /// states, diagnostics and state changes; `hostsim replay FILE` replays it bit for bit).
    /// The loop never waits for the disk: if it falls behind, messages are dropped and
    /// counted.
    /// With --log-max-mb, FILE is a directory (created if missing) of numbered files
    /// runner-000001.mcap, runner-000002.mcap, ...
    #[arg(long, value_name = "FILE")]
    log: Option<PathBuf>,

    /// Rotate the log: start the next file of the --log directory once the current one has
    /// reached MB megabytes (10^6 bytes; it ends a little past that, at a hand-over to the
    /// writer). Each file is a complete log with the same metadata; the first replays bit
    /// for bit, a later one starts with the core's state at that point, which replay from an
    /// empty core does not have. Default: no rotation, one file.
    #[arg(long, value_name = "MB", requires = "log", value_parser = parse_megabytes, allow_hyphen_values = true)]
    log_max_mb: Option<f64>,

    /// With --log-max-mb, keep the newest K files and remove older ones (K >= 1).
    #[arg(long, value_name = "K", requires = "log_max_mb", default_value_t = 10, value_parser = parse_keep)]
    log_keep: usize,

    /// Stop on a CAN link loss (the interface set down, the adapter unplugged: ENETDOWN,
    /// ENODEV, ENXIO) with exit status 3, instead of the default: keep stepping the core,
    /// reopen the interface with back-off and resume when it is back.
    #[arg(long)]
    exit_on_link_loss: bool,

    /// Keep the parameters a host saves over CAN (`mecanum-drive param save`, CiA 301 0x1010)
    /// in FILE: written to FILE.part, synced and renamed over FILE, so a power cut leaves the
    /// old set or the new one. At start the set in FILE runs if it was saved for this
    /// --config's configuration (else the configuration file's, reported); a restore (0x1011)
    /// puts the configuration file's set back and saves it. Without --params a save is
    /// refused (SDO abort 0x08000020). FILE must be a saved set or not exist.
    #[arg(long, value_name = "FILE")]
    params: Option<PathBuf>,

    /// Print only errors (no start line, no statistics on stderr).
    #[arg(long, short)]
    quiet: bool,

    #[command(flatten)]
    live: live::LiveArgs,
}

fn parse_megabytes(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v > 0.0 && v < 1e9 => Ok(v),
        Ok(v) => Err(format!("--log-max-mb {v}: expected megabytes > 0")),
        Err(e) => Err(format!(
            "--log-max-mb {s:?}: expected a number of megabytes: {e}"
        )),
    }
}

fn parse_keep(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(0) => Err("--log-keep 0: at least 1 file must be kept".to_string()),
        Ok(v) => Ok(v),
        Err(e) => Err(format!("--log-keep {s:?}: expected a number of files: {e}")),
    }
}

/// What `main` needs from the startup: everything is checked before the loop starts.
struct Setup {
    controller: Controller,
    /// `--params`.
    params: Option<ParamFile>,
    bus: SocketCanBus,
    stats: Option<(PathBuf, drivelog::Staged)>,
    log: Option<McapRecorder>,
    server: Option<live::LiveServer>,
    stop: Arc<AtomicUsize>,
    summary: String,
}

fn main() -> ExitCode {
    // clap exits with status 2 on bad arguments and 0 for --help / --version.
    let args = Args::parse();
    let setup = match startup(&args) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("mecanum-runner: {}", linux::error_line(e.as_ref()));
            return ExitCode::from(EXIT_STARTUP);
        }
    };
    let Setup {
        mut controller,
        mut params,
        mut bus,
        stats,
        mut log,
        server,
        stop,
        summary,
    } = setup;
    if !args.quiet {
        eprintln!("mecanum-runner: {summary}; stop with Ctrl-C (SIGINT) or SIGTERM");
    }
    if let Some(server) = &server {
        if let Some(warning) = server.exposure_warning() {
            eprintln!("mecanum-runner: {warning}");
        }
        if !args.quiet {
            eprintln!("{}", server.banner());
        }
    }
    let options = RunOptions {
        duration_us: args.duration.map(|s| (s * 1e6).round() as u64),
        exit_on_link_loss: args.exit_on_link_loss,
        ..RunOptions::default()
    };
    let clock = MonotonicClock::new(args.spin_us);
    let report = {
        let mut recorder = Console::new(&args.iface, log.as_mut());
        let store: &mut dyn linux::ParamStore = match params.as_mut() {
            Some(file) => file,
            None => &mut (),
        };
        linux::run_recorded(
            &mut controller,
            &mut bus,
            &clock,
            &options,
            &stop,
            &mut recorder,
            store,
        )
    };
    if let Some(e) = params.as_ref().and_then(ParamFile::last_error) {
        eprintln!("mecanum-runner: the last parameter save failed: {e}");
    }
    let log_stats = log.as_ref().map(|l| (l.messages(), l.dropped()));
    let log_result = log.map(McapRecorder::finish);
    // After the log: its last messages are queued for the clients before they are let go.
    let live = server.map(live::LiveServer::stop);

    // The statistics first, and stderr without a panic: a stderr pipe that closed with the
    // same Ctrl-C (`... 2>&1 | tee log`) must not cost the report file or the exit status.
    let mut status = ExitCode::SUCCESS;
    let say = |line: std::fmt::Arguments<'_>| {
        let _ = writeln!(std::io::stderr(), "mecanum-runner: {line}");
    };
    if let Some((path, file)) = stats
        && let Err(e) = write_stats(
            &path,
            file,
            &report,
            log_stats,
            args.log.as_deref(),
            live.as_ref(),
        )
    {
        say(format_args!("{}", linux::error_line(e.as_ref())));
        status = ExitCode::FAILURE;
    }
    if !args.quiet {
        say(format_args!("{report}"));
        if let (Some((messages, dropped)), Some(path)) = (log_stats, &args.log) {
            say(format_args!(
                "log {}: {messages} messages, {dropped} dropped (writer behind)",
                path.display()
            ));
        }
        if let Some(live) = &live {
            say(format_args!("live: {live}"));
        }
    }
    if let Some(Err(e)) = log_result {
        say(format_args!("log: {}", linux::error_line(&e)));
        status = ExitCode::FAILURE;
    }
    if report.stop == StopReason::LinkLost {
        say(format_args!(
            "{}: CAN link lost ({}); stopped as --exit-on-link-loss asks",
            args.iface,
            report.link_error.as_deref().unwrap_or("no error recorded")
        ));
        return ExitCode::from(EXIT_LINK_LOST);
    }
    if report.node.shutdown.failed > 0 {
        say(format_args!(
            "{} of {} shutdown frames NOT sent ({}): the motors may still be commanded",
            report.node.shutdown.failed,
            report.node.shutdown.frames,
            report.errors.last.as_deref().unwrap_or("no error recorded")
        ));
        status = ExitCode::FAILURE;
    }
    status
}

fn startup(args: &Args) -> Result<Setup> {
    let (config, source) = match &args.config {
        Some(path) => (
            // The error names the file, and the line or the field.
            Config::from_toml_file(path)?,
            path.display().to_string(),
        ),
        None => (
            Config::dji_m3508_example(),
            "built-in DJI M3508/C620 example".to_string(),
        ),
    };
    let mut controller = Controller::new(&config)
        .with_context(|| format!("configuration {source} rejected by the controller"))?;
    let (params, params_note) = match &args.params {
        Some(path) => {
            let (file, found) = ParamFile::open(path, &config)?;
            let shown = path.display();
            let note = match found {
                Found::Missing => format!("parameters: {shown} (none saved yet)"),
                Found::Saved { config: saved, seq } => {
                    controller = controller.with_saved(&saved, seq).with_context(|| {
                        format!("--params {shown}: the saved set is refused by the controller")
                    })?;
                    format!("parameters: the set saved in {shown} (record {seq})")
                }
                Found::Other { base_id } => format!(
                    "parameters: {shown} holds a set saved for another configuration (id 0x{base_id:04x}); running {source}'s, the next save replaces it"
                ),
                Found::Damaged => format!(
                    "parameters: {shown} is damaged (its CRC fails); running {source}'s, the next save replaces it"
                ),
            };
            (Some(file), Some(note))
        }
        None => (None, None),
    };

    if args.live.live.is_some() && args.log.is_none() {
        anyhow::bail!("--live serves the log as it is written: give --log FILE too");
    }
    // Signals before the socket: from here on SIGINT/SIGTERM stop the loop cleanly (a second
    // one exits at once).
    let stop = linux::stop_on_signals()?;

    let bus = SocketCanBus::open(&args.iface)?;

    // Before the log: an address that cannot be served fails before a file is made. Its
    // clients' parameter requests go on the bus to this runner's own service, as any host's.
    let params_link = match args.live.live {
        Some(_) => {
            let node = firmware::params::service_node(&config);
            let link = linux::SdoClient::open(&args.iface, node)?;
            Some(Box::new(link) as Box<dyn live::ParamLink>)
        }
        None => None,
    };
    let server = args.live.serve(
        format!("mecanum-runner --iface {}", args.iface),
        params_link,
    )?;
    let mut log = match (&args.log, args.log_max_mb) {
        (Some(dir), Some(mb)) => Some(McapRecorder::rotating(
            dir,
            &controller,
            ((mb * 1e6).round() as u64).max(1),
            args.log_keep,
        )?),
        (Some(path), None) => Some(McapRecorder::create(path, &controller)?),
        (None, _) => None,
    };
    if let (Some(server), Some(log)) = (&server, log.as_mut()) {
        let tap = server.tap_maker();
        log.serve(
            Arc::new(move || Box::new(tap()) as Box<dyn drivelog::MessageTap>),
            live::FLUSH_INTERVAL,
        );
    }

    // The statistics file is created before the loop starts (and after everything else
    // checked), so a bad path fails now and not after a long run.
    let stats = match &args.stats_json {
        Some(path) => {
            // Renamed into place once written: a run that fails keeps the last report.
            let file = drivelog::Staged::create(path).context("cannot create --stats-json file")?;
            Some((path.clone(), file))
        }
        None => None,
    };
    let drive = match config.drive {
        Drive::Dji { model, esc_ids, .. } => format!("DJI {model:?} ESCs {esc_ids:?}"),
        Drive::Odrive { node_ids, .. } => format!("ODrive nodes {node_ids:?}"),
        Drive::Cia402(cia402) => {
            format!("CiA 402 nodes {:?} axes {:?}", cia402.node_ids, cia402.axes)
        }
    };
    let mut summary = format!(
        "{} at {} Hz ({} µs period), {drive}, configuration: {source} (id 0x{:04x})",
        args.iface,
        config.timing.control_hz,
        controller.period_micros(),
        controller.config_id()
    );
    if let Some(note) = params_note {
        summary = format!("{summary}; {note}");
    }
    Ok(Setup {
        controller,
        params,
        bus,
        stats,
        log,
        server,
        stop,
        summary,
    })
}

/// What `--stats-json` holds: the loop's report, the live server's and the log's figures.
#[derive(serde::Serialize)]
struct Stats<'a> {
    #[serde(flatten)]
    report: &'a Report,
    /// With `--live`.
    #[serde(skip_serializing_if = "Option::is_none")]
    live: Option<serde_json::Value>,
    /// With `--log`.
    #[serde(skip_serializing_if = "Option::is_none")]
    log: Option<LogStats>,
}

/// The log's figures in [`Stats`].
#[derive(serde::Serialize)]
struct LogStats {
    path: Option<String>,
    messages: u64,
    dropped: u64,
}

fn write_stats(
    path: &Path,
    mut file: drivelog::Staged,
    report: &Report,
    log: Option<(u64, u64)>,
    log_path: Option<&Path>,
    live: Option<&live::LiveReport>,
) -> Result<()> {
    let stats = Stats {
        report,
        live: live.map(live::LiveReport::to_json),
        log: log.map(|(messages, dropped)| LogStats {
            path: log_path.map(|p| p.display().to_string()),
            messages,
            dropped,
        }),
    };
    linux::write_stats_json(&mut file, &stats)
        .map_err(anyhow::Error::from)
        .and_then(|()| Ok(file.commit()?))
        .with_context(|| format!("cannot write --stats-json file {}", path.display()))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use linux::testing::{ScriptedBus, ScriptedClock};

    use super::*;

    /// `--stats-json` is the report's JSON with the log's figures added: the report's keys
    /// at the top level, sorted by name, pretty-printed, a newline at the end.
    #[test]
    fn the_statistics_are_the_report_with_the_log() {
        let clock = ScriptedClock::new(7_000_000, [], 0);
        let mut bus = ScriptedBus::new(&clock, []);
        let mut controller = Controller::new(&Config::dji_m3508_example()).unwrap();
        let options = RunOptions {
            duration_us: Some(10_000),
            ..RunOptions::default()
        };
        let stop = AtomicUsize::new(0);
        let report = linux::run(&mut controller, &mut bus, &*clock, &options, &stop);
        let stats = Stats {
            report: &report,
            live: None,
            log: Some(LogStats {
                path: Some("run.mcap".into()),
                messages: 12,
                dropped: 3,
            }),
        };
        let mut out = Vec::new();
        linux::write_stats_json(&mut out, &stats).unwrap();
        let mut expected = serde_json::to_value(&report).unwrap();
        expected["log"] = serde_json::json!({"path": "run.mcap", "messages": 12, "dropped": 3});
        let expected = serde_json::to_string_pretty(&expected).unwrap() + "\n";
        assert_eq!(String::from_utf8(out).unwrap(), expected);
    }
}
