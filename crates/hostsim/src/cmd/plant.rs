//! `hostsim plant`: the simulated drives on a real SocketCAN interface, in real time.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use mecanum_linux::{MonotonicClock, SocketCanBus};

use crate::realtime::{PlantLog, PlantOptions, run_plant, run_plant_observed};
use crate::replay::PLANT_PROGRAM;
use drivelog::McapLog;

use super::*;

/// Run the simulated drives on a SocketCAN interface in real time, for a firmware runner.
///
/// The drives of --config (DJI C620/M3508 or ODrive, on a 20 kg chassis) answer the
/// motor commands they see on --iface with their feedback, in real time: a 1 kHz loop
/// with absolute deadlines reads the commands, advances the physics by the elapsed
/// simulated period and sends the due feedback frames. Point `mecanum-runner --iface`
/// at the same interface (with the same configuration) and send it MODE_CMD/TWIST_CMD
/// (e.g. `hostsim replay LOG --iface`, or cansend) to drive the simulated robot.
///
/// On SIGINT/SIGTERM or after --duration: prints the ground-truth pose and velocity on
/// stdout and the loop statistics (ticks, overruns, jitter, frames) on stderr, and writes
/// both as JSON to --stats-json. A second SIGINT/SIGTERM exits at once with status 1.
/// Exit status: 0 after a clean stop, 1 if the statistics or the log could not be
/// written, 2 for a startup error (bad arguments, configuration, interface).
///
/// With --live (and --log) the log is served to Foxglove or Lichtblick as it is written
/// (docs/live.md): the frames on the bus, the ground truth against the firmware's odometry.
#[derive(Debug, clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    /// SocketCAN interface, e.g. vcan0 or can0. It must exist and be up.
    #[arg(long, value_name = "IFACE")]
    pub iface: String,
    /// Drive configuration TOML (as config/dji_m3508.toml or config/odrive.toml).
    /// Default: the built-in DJI example. Use the runner's configuration.
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Stop after this many seconds. Default: run until SIGINT/SIGTERM.
    #[arg(long, value_name = "SECONDS", value_parser = parse_seconds)]
    pub duration: Option<f64>,
    /// Write the final statistics and ground truth as JSON to FILE (created at startup).
    #[arg(long, value_name = "FILE")]
    pub stats_json: Option<PathBuf>,
    /// Busy-wait the last MICROS before each deadline instead of sleeping: lower jitter,
    /// more CPU. Default 0; at most 10000.
    #[arg(long, value_name = "MICROS", default_value_t = 0,
          value_parser = clap::value_parser!(u64).range(0..=mecanum_linux::MAX_SPIN_US))]
    pub spin_us: u64,
    /// Write an MCAP log (a ROS 2 bag) of the run to FILE: every frame on the interface
    /// once, as the firmware sees it (/can/rx: the drives' feedback and the host's commands;
    /// /can/tx: the rest), the host's twist commands (/cmd_vel), the firmware's odometry and
    /// the plant's ground truth every 10 ms (/odom, /ground_truth/odom, /tf). A chunk ends at
    /// least every half second. `hostsim summary FILE` reads it.
    #[arg(long, value_name = "FILE")]
    pub log: Option<PathBuf>,
    /// Print only errors (no start line, no statistics on stderr).
    #[arg(long, short)]
    pub quiet: bool,
    /// Put an IMU node on the interface too: it sends IMU_YAW_RATE (0x304) from the plant's
    /// true yaw rate at 200 Hz with white noise (0.005 °/s/√Hz, seed 0) and a constant bias,
    /// for a runner configured with [odometry] heading_source = "gyro".
    #[arg(long)]
    pub imu: bool,
    /// With --imu: the gyro's bias, °/s. Default 0.1.
    #[arg(long, value_name = "DEG_S", requires = "imu")]
    pub imu_bias_deg_s: Option<f64>,
    /// Put the tracking pods of --config's [[odometry.pods]] on the interface too: a node
    /// that sends POD_COUNTS (0x306) at 200 Hz from the chassis's true travel, the pods as
    /// configured, for a runner configured with [odometry] source = "pods2_gyro" or "pods3"
    /// (with "pods2_gyro", give --imu too).
    #[arg(long)]
    pub pods: bool,
    /// `--flip` and `--swap` (flattened: clap takes the help from their own docs).
    #[command(flatten)]
    pub wiring: WiringArgs,
    /// The robot on blocks: no wheel touches the ground (for `mecanum-drive check`).
    #[arg(long)]
    pub lifted: bool,
    /// `--live` and its caps (flattened: clap takes the help from their own docs).
    #[command(flatten)]
    pub live: live::LiveArgs,
}

/// What `plant` starts from: the configuration and the nodes built from it.
pub struct Prepared {
    /// The drive configuration.
    pub config: firmware::Config,
    /// Where it came from, for the messages.
    pub source: String,
    /// The simulated drives and chassis, wired and lifted as asked.
    pub drives: crate::nodes::drives::SimDrives,
    /// The IMU node's parameters (`--imu`).
    pub imu: Option<crate::nodes::imu::ImuParams>,
    /// The tracking pods' node (`--pods`).
    pub pods: Option<crate::nodes::pods::PodNode>,
}

/// `hostsim plant`'s checks before it touches the interface: `--live` has a log to serve,
/// the configuration loads and the plant models it, the IMU's bias is in range, `--pods`
/// has pods to count.
///
/// # Errors
/// The first of those that fails, naming the option or the file.
pub fn prepare(args: &Args) -> Result<Prepared> {
    if args.live.live.is_some() && args.log.is_none() {
        bail!("--live serves the log as it is written: give --log FILE too");
    }
    let (config, source) = load_config(args.config.as_deref())?;
    let spec = crate::nodes::plant::PlantSpec {
        lifted: args.lifted,
        ..args.wiring.spec()
    };
    let drives = crate::nodes::drives::SimDrives::with_spec(&config, &spec)
        .with_context(|| format!("configuration {source}: the plant cannot model it"))?;
    let imu = args.imu.then(|| crate::nodes::imu::ImuParams {
        bias_deg_s: args.imu_bias_deg_s.unwrap_or(0.1),
        ..crate::nodes::imu::ImuParams::default()
    });
    if let Some((key, value, expected)) = imu.as_ref().and_then(|i| i.invalid()) {
        bail!(
            "--imu-{}: {value}: expected {expected}",
            key.replace('_', "-")
        );
    }
    let nominal = config.odometry.pods;
    if args.pods && nominal.is_empty() {
        bail!(
            "--pods: configuration {source} has no [[odometry.pods]]: the pod node counts the \
             configured pods"
        );
    }
    let pods = args.pods.then(|| {
        crate::nodes::pods::PodNode::new(
            &crate::nodes::pods::PodsParams::default(),
            nominal.as_slice(),
            0,
        )
    });
    Ok(Prepared {
        config,
        source,
        drives,
        imu,
        pods,
    })
}

/// `hostsim plant`: the simulated drives on the interface in real time.
pub fn execute(args: &Args) -> Result<ExitCode> {
    let (iface, quiet) = (args.iface.as_str(), args.quiet);
    let (stats_json, log) = (args.stats_json.as_deref(), args.log.as_deref());
    let Prepared {
        config,
        source,
        mut drives,
        imu,
        pods,
    } = prepare(args)?;
    let mut drives = crate::nodes::imu::WithImu::new(&mut drives, imu.as_ref(), 0);
    let mut drives = crate::nodes::pods::WithPods::new(&mut drives, pods);
    let stop = mecanum_linux::stop_on_signals()?;
    let mut bus = SocketCanBus::open(iface)?;
    // Created before the loop starts, so a bad path fails now and not after a long run.
    let stats = match stats_json {
        Some(p) => Some((
            p,
            // Renamed into place once written: a run that fails keeps the last report.
            drivelog::Staged::create(p).context("cannot create --stats-json file")?,
        )),
        None => None,
    };
    // Before the log: an address that cannot be served fails before a file is made.
    // Its clients' parameter requests go on the bus to the robot's service (a runner's, a
    // board's), as any host's.
    let params_link = match args.live.live {
        Some(_) => Some(Box::new(mecanum_linux::SdoClient::open(
            iface,
            firmware::params::service_node(&config),
        )?) as Box<dyn live::ParamLink>),
        None => None,
    };
    let server = args
        .live
        .serve(format!("hostsim plant --iface {iface}"), params_link)?;
    let mut plant_log = match log {
        Some(path) => Some(open_log(path, &config, iface, server.as_ref())?),
        None => None,
    };
    let options = PlantOptions {
        duration_us: args.duration.map(|s| (s * 1e6).round() as u64),
        ..PlantOptions::default()
    };
    if !quiet {
        eprintln!(
            "hostsim plant: simulated drives on {iface} at {} Hz, configuration: {source}; \
             stop with Ctrl-C (SIGINT) or SIGTERM",
            1_000_000 / options.period_us
        );
    }
    if let Some(server) = &server {
        if let Some(warning) = server.exposure_warning() {
            eprintln!("{warning}");
        }
        if !quiet {
            eprintln!("{}", server.banner());
        }
    }
    let clock = MonotonicClock::new(args.spin_us);
    let report = match plant_log.as_mut() {
        Some(observer) => {
            run_plant_observed(&mut drives, &mut bus, &clock, &options, &stop, observer)
        }
        None => run_plant(&mut drives, &mut bus, &clock, &options, &stop),
    };
    let status = match (plant_log, log) {
        (Some(observer), Some(path)) => finish_log(observer, path, quiet),
        _ => ExitCode::SUCCESS,
    };
    // After the log: its last messages are queued for the clients before they are let go.
    let live = server.map(live::LiveServer::stop);
    if let (Some(report), false) = (&live, quiet) {
        eprintln!("live: {report}");
    }
    // The ground truth always goes out, on stdout; the statistics on stderr.
    println!(
        "ground truth: x {:+.4} m  y {:+.4} m  heading {:+.2}°  (vx {:+.4} m/s  vy {:+.4} m/s  \
         wz {:+.4} rad/s)",
        report.node.truth.x,
        report.node.truth.y,
        report.node.truth.heading.to_degrees(),
        report.node.velocity.vx,
        report.node.velocity.vy,
        report.node.velocity.wz
    );
    if !quiet {
        eprintln!("hostsim plant: {report}");
    }
    if let Some((path, file)) = stats
        && let Err(e) = write_stats(file, &report, live.as_ref())
    {
        eprintln!(
            "error: cannot write --stats-json file {}: {e:#}",
            path.display()
        );
        return Ok(ExitCode::from(EXIT_FAILED));
    }
    Ok(status)
}

/// The `--log` file at `path`, its metadata the run's (`config`, the interface), served to
/// the `--live` clients as it is written.
fn open_log(
    path: &std::path::Path,
    config: &firmware::Config,
    iface: &str,
    server: Option<&live::LiveServer>,
) -> Result<PlantLog> {
    let start_unix_ns = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos());
    let metadata = std::collections::BTreeMap::from([
        ("config".to_string(), config.to_toml_string()),
        ("program".to_string(), PLANT_PROGRAM.to_string()),
        (
            "source".to_string(),
            format!("hostsim plant --iface {iface}"),
        ),
        ("start_unix_ns".to_string(), start_unix_ns.to_string()),
        (
            "hostsim_version".to_string(),
            env!("CARGO_PKG_VERSION").to_string(),
        ),
    ]);
    let mut log = McapLog::create(path, &metadata)?;
    if let Some(server) = server {
        log.set_tap(Box::new(server.tap()));
        log.set_flush_interval(live::FLUSH_INTERVAL);
    }
    Ok(PlantLog::new(log))
}

/// Finishes the log at `path`: failure if it cannot be written whole.
fn finish_log(observer: PlantLog, path: &std::path::Path, quiet: bool) -> ExitCode {
    match observer.finish() {
        Ok(n) if !quiet => {
            eprintln!("hostsim plant: {n} messages logged to {}", path.display());
            ExitCode::SUCCESS
        }
        Ok(_) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: log {}: {e}", path.display());
            ExitCode::from(EXIT_FAILED)
        }
    }
}

/// Writes `--stats-json`: the plant's report and, with `--live`, the live server's.
fn write_stats(
    mut file: drivelog::Staged,
    report: &crate::realtime::PlantReport,
    live: Option<&live::LiveReport>,
) -> Result<()> {
    let stats = Stats {
        report,
        live: live.map(live::LiveReport::to_json),
    };
    mecanum_linux::write_stats_json(&mut file, &stats)?;
    file.commit()?;
    Ok(())
}

/// What `--stats-json` holds: the plant's report and, with `--live`, the live server's.
#[derive(serde::Serialize)]
struct Stats<'a> {
    #[serde(flatten)]
    report: &'a crate::realtime::PlantReport,
    #[serde(skip_serializing_if = "Option::is_none")]
    live: Option<serde_json::Value>,
}
