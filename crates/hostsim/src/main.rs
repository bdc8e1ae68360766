//! `hostsim`: simulate the mecanum drive, replay and summarise its logs, compute kinematics.

use std::fs::File;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use hostsim::log::McapLog;
use hostsim::plot::plot_run;
use hostsim::realtime::{
    PlantLog, PlantOptions, PlayOptions, play_frames, run_plant, run_plant_observed,
};
use hostsim::replay::PLANT_PROGRAM;
use hostsim::replay::{
    CandumpReplayError, LogFormat, OdometryTolerance, detect_format, mcap_playback, replay_candump,
    replay_mcap, split_candump,
};
use hostsim::scenario::Scenario;
use hostsim::sim::{LogOptions, RunSummary, run_metadata};
use hostsim::whatif::{OPEN_LOOP_NOTE, what_if_mcap};
use indicatif::{ProgressBar, ProgressStyle};
use mecanum_linux::{MonotonicClock, SocketCanBus};

/// Host simulator of the mecanum drive stack.
///
/// The real firmware core runs in lockstep with a simulated plant (DJI C620/M3508 or ODrive
/// drives, a 20 kg chassis on mecanum rollers with friction-limited slip) over a simulated
/// 1 Mbit/s CAN bus, in simulated time. Runs are deterministic: the same scenario and seed
/// give the same frames, bit for bit.
#[derive(Debug, Parser)]
#[command(name = "hostsim", version, about, long_about)]
struct Cli {
    #[command(subcommand)]
    command: Cmd,
}

#[derive(Debug, Subcommand)]
enum Cmd {
    /// Run a scenario: writes an MCAP log and a PNG plot, prints a summary.
    ///
    /// With no argument runs the built-in `square`. Built-ins: square, circle, strafe, spin,
    /// figure-eight, compass, watchdog, calibration (seed 1; DJI C620 + M3508 drives on a
    /// 20 kg chassis; see `calibrate`).
    ///
    /// A scenario file (TOML; examples in scenarios/, the format in the hostsim crate's
    /// `scenario` module docs) sets duration_s, and optionally name (default: the file's
    /// stem), seed (default 0), command_hz (default 50), config (a drive configuration, relative
    /// to the file; default the DJI example), [[actions]] (at_s and one or more of enable,
    /// disable, reset, estop, status_request, twist = [vx, vy, wz], silence, resume,
    /// wheel_test = { wheel, speed, duration_ms }) and
    /// [[faults]] (kind = drop | burst | delay | corrupt | stuck_encoder | motor_offline |
    /// non_finite_twist, from_s, until_s, and the kind's fields: rate, delay_ms, sender,
    /// wheel), [plant] (the simulated robot where it differs from the configuration:
    /// wheel_radius, lx, ly, roller_drag, and a miswiring: flip = [wheel indices], swap =
    /// [[a, b], ...], lifted = true; kept when --config replaces the configuration) and
    /// [imu] (an IMU node sending IMU_YAW_RATE for gyro heading: rate_hz, bias_deg_s,
    /// noise_density in °/s/√Hz, enabled). Every error names the file, the field and the
    /// value.
    Run {
        /// A scenario TOML file, or the name of a built-in.
        scenario: Option<String>,
        /// Output folder for `<name>.mcap` and `<name>.png`.
        #[arg(long, default_value = "out")]
        out: PathBuf,
        /// Drive configuration TOML (overrides the scenario's).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Seed for the bus faults (overrides the scenario's).
        #[arg(long)]
        seed: Option<u64>,
        /// Set a field, KEY=VALUE: of the drive configuration as its TOML names it
        /// (gains.kp, limits.max_current, ...) or of the plant (plant.mass_kg, ...), as a
        /// `sweep` row prints it. Repeatable.
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
        /// Do not write the MCAP log.
        #[arg(long)]
        no_log: bool,
        /// Do not draw the plot.
        #[arg(long)]
        no_plot: bool,
        /// Print the summary as JSON instead of text.
        #[arg(long)]
        json: bool,
        /// Print `progress <simulated seconds>` on stderr every 100 ms of simulated time, one
        /// line each, after that time's messages went to the log: for scripts that watch a
        /// run (the progress bar is drawn only on a terminal).
        #[arg(long)]
        progress_lines: bool,
    },
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
    #[command(verbatim_doc_comment)]
    Replay {
        /// A hostsim MCAP log, or a candump log (.log / .candump).
        log: PathBuf,
        /// Drive configuration TOML. candump log: used to classify and replay it (default:
        /// the built-in DJI example, as config/dji_m3508.toml). MCAP log: a what-if, the
        /// logged session replayed open loop through a core built from FILE instead of the
        /// logged configuration (see above).
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
        /// Print the report as JSON (one object on stdout).
        #[arg(long)]
        json: bool,
        /// candump replay: largest position difference for the odometry to agree, m.
        #[arg(long, value_name = "M", default_value_t = 0.01)]
        position_tolerance: f64,
        /// candump replay: largest heading difference for the odometry to agree, rad.
        #[arg(long, value_name = "RAD", default_value_t = 0.01)]
        heading_tolerance: f64,
        /// Play the frames onto this SocketCAN interface (e.g. vcan0) in real time instead
        /// of replaying them through a core.
        #[arg(long, value_name = "IFACE")]
        iface: Option<String>,
        /// With --iface: time scale (2 plays twice as fast). Default 1.
        #[arg(long, value_name = "FACTOR")]
        speed: Option<f64>,
        /// With --iface: which frames to play. rx (default): the frames the firmware
        /// received (host commands, motor feedback; MCAP /can/rx), to feed a live runner;
        /// tx: the frames the firmware sent (MCAP /can/tx); all: both, merged by time.
        #[arg(long, value_enum, value_name = "WHICH")]
        only: Option<Only>,
    },
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
    #[command(verbatim_doc_comment)]
    Plant(PlantArgs),
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
    Check(CheckArgs),
    /// Many runs of one scenario at once, on every core: seeds and parameter values.
    ///
    /// The runs are every seed of --seeds with every combination of the --set grids
    /// (`--set gains.kp=0.8,1.0,1.2`); a --set range (`--set plant.mass_kg=18..24`) is drawn
    /// at random for each run, from a generator seeded by the run's index. Names: a field of
    /// the drive configuration as its TOML names it (gains.kp, limits.max_current,
    /// timing.command_timeout_ms, ...) or plant.wheel_radius, plant.lx, plant.ly,
    /// plant.roller_drag, plant.mass_kg; every name and value is checked before the first
    /// run. No logs (--log-worst N writes the N worst runs' logs afterwards).
    ///
    /// Writes OUT/sweep.csv and OUT/sweep.jsonl (one row per run: index, seed, the values,
    /// final state, first fault and when, time from it until the body stood, odometry drift
    /// at the end and at most, RMS of the commanded minus the measured speed, steps) and
    /// OUT/sweep.png (the largest drift of each run against the first swept parameter, or
    /// the seed), and prints percentiles and the worst runs, each with the command that runs
    /// it alone. The table is the same on any number of threads. Ctrl-C stops starting runs
    /// and writes the rows finished (exit status 130); a second Ctrl-C exits at once.
    Sweep(SweepArgs),
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
    #[command(verbatim_doc_comment)]
    Summary {
        /// A hostsim MCAP log.
        log: PathBuf,
    },
    /// Fit the wheel radius, lx + ly and lateral effectiveness that make a log's odometry
    /// match a reference pose.
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
    /// Prints each correction and value with its standard error, the RMS of the per-window
    /// residuals, and the [geometry] lines to paste; --write FILE writes the logged
    /// configuration with them. The loop: `hostsim run calibration`, `hostsim calibrate
    /// out/calibration.mcap --write cal.toml`, `hostsim run calibration --config cal.toml`.
    ///
    /// Exit status: 0, 2 if the log is refused (its motion cannot determine a value: it
    /// needs 0.5 m of forward and of sideways travel and a full turn; no configuration or
    /// reference in it) or FILE cannot be written, 3 if the log is damaged (the fit used its
    /// complete part).
    #[command(verbatim_doc_comment)]
    Calibrate {
        /// A log (MCAP) of `hostsim run`, `mecanum-runner --log` or `hostsim plant --log`.
        log: PathBuf,
        /// The reference pose topic.
        #[arg(long, value_name = "TOPIC", default_value = hostsim::calibrate::GROUND_TRUTH)]
        reference: String,
        /// Window length, s.
        #[arg(long, value_name = "SECONDS", default_value_t = 0.1)]
        window: f64,
        /// Write the logged configuration with the fitted [geometry] to FILE.
        #[arg(long, value_name = "FILE")]
        write: Option<PathBuf>,
        /// Print the report as JSON (one object on stdout).
        #[arg(long)]
        json: bool,
    },
    /// Draw logged runs side by side in one PNG, e.g. before and after `calibrate`.
    ///
    /// A panel per run with its ground truth and odometry seen from above (the same axes for
    /// all), then one of every run's position error over time; the legends give each run's
    /// largest drift. Give two logs to compare them, e.g. a run before and after `calibrate`: `hostsim plot
    /// out/calibration.mcap recal/calibration.mcap`. Each needs /odom and /ground_truth/odom
    /// (a `hostsim run` or `hostsim plant --log` log). Exit status 2 if a log cannot be read
    /// or the PNG written.
    Plot {
        /// One or more MCAP logs (up to 3), each labelled by its path.
        #[arg(required = true, num_args = 1..=3)]
        logs: Vec<PathBuf>,
        /// The PNG to write. Default: beside the first log, its name with `.png` (one log) or
        /// `-vs-<second log's name>.png` (more).
        #[arg(long, value_name = "FILE")]
        out: Option<PathBuf>,
    },
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
    #[command(verbatim_doc_comment)]
    Kin,
}

/// Exit status of `replay` and `summary` for a damaged log whose complete part was used.
const EXIT_DAMAGED: u8 = 3;

/// Warns on stderr that the log at `path` is damaged, if it is: where, what, what was read.
fn warn_if_damaged(path: &Path, read: &hostsim::log::ReadReport, doing: &str) {
    if !read.is_complete() {
        eprintln!("warning: {} is {read}; {doing}", path.display());
    }
}

/// The arguments of `hostsim plant`.
#[derive(Debug, clap::Args)]
struct PlantArgs {
    /// SocketCAN interface, e.g. vcan0 or can0. It must exist and be up.
    #[arg(long, value_name = "IFACE")]
    iface: String,
    /// Drive configuration TOML (as config/dji_m3508.toml or config/odrive.toml).
    /// Default: the built-in DJI example. Use the runner's configuration.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Stop after this many seconds. Default: run until SIGINT/SIGTERM.
    #[arg(long, value_name = "SECONDS", value_parser = parse_seconds)]
    duration: Option<f64>,
    /// Write the final statistics and ground truth as JSON to FILE (created at startup).
    #[arg(long, value_name = "FILE")]
    stats_json: Option<PathBuf>,
    /// Busy-wait the last MICROS before each deadline instead of sleeping: lower jitter,
    /// more CPU. Default 0.
    #[arg(long, value_name = "MICROS", default_value_t = 0)]
    spin_us: u64,
    /// Write an MCAP log (a ROS 2 bag) of the run to FILE: every frame on the interface
    /// once, as the firmware sees it (/can/rx: the drives' feedback and the host's commands;
    /// /can/tx: the rest), the host's twist commands (/cmd_vel), the firmware's odometry and
    /// the plant's ground truth every 10 ms (/odom, /ground_truth/odom, /tf). A chunk ends at
    /// least every half second. `hostsim summary FILE` reads it.
    #[arg(long, value_name = "FILE")]
    log: Option<PathBuf>,
    /// Print only errors (no start line, no statistics on stderr).
    #[arg(long, short)]
    quiet: bool,
    /// Put an IMU node on the interface too: it sends IMU_YAW_RATE (0x304) from the plant's
    /// true yaw rate at 200 Hz with white noise (0.005 °/s/√Hz, seed 0) and a constant bias,
    /// for a runner configured with [odometry] heading_source = "gyro".
    #[arg(long)]
    imu: bool,
    /// With --imu: the gyro's bias, °/s. Default 0.1.
    #[arg(long, value_name = "DEG_S", requires = "imu")]
    imu_bias_deg_s: Option<f64>,
    #[command(flatten)]
    wiring: WiringArgs,
    /// The robot on blocks: no wheel touches the ground (for `mecanum-drive check`).
    #[arg(long)]
    lifted: bool,
}

/// A simulated robot wired otherwise than its configuration says (`check`, `plant`).
#[derive(Debug, Clone, clap::Args)]
struct WiringArgs {
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
    fn spec(&self) -> hostsim::scenario::PlantSpec {
        hostsim::scenario::PlantSpec {
            flip: self.flip.clone(),
            swap: self.swap.clone(),
            ..hostsim::scenario::PlantSpec::default()
        }
    }
}

/// A wheel by name (FL, FR, RL, RR, any case) or index 0-3.
fn parse_wheel(s: &str) -> Result<usize, String> {
    let t = s.trim();
    hostsim::bringup::WHEEL_NAMES
        .iter()
        .position(|n| n.eq_ignore_ascii_case(t))
        .or_else(|| t.parse::<usize>().ok().filter(|&i| i < 4))
        .ok_or_else(|| format!("{s:?} is not a wheel: FL, FR, RL, RR or 0-3"))
}

/// Two different wheels, `A,B`.
fn parse_wheel_pair(s: &str) -> Result<[usize; 2], String> {
    let (a, b) = s
        .split_once(',')
        .ok_or_else(|| format!("{s:?}: expected two wheels, e.g. FL,RL"))?;
    let (a, b) = (parse_wheel(a)?, parse_wheel(b)?);
    if a == b {
        return Err(format!("{s:?}: a wheel cannot swap with itself"));
    }
    Ok([a, b])
}

/// The arguments of `hostsim sweep`.
#[derive(Debug, clap::Args)]
struct SweepArgs {
    /// A scenario TOML file, or the name of a built-in.
    scenario: String,
    /// Seeds: A..B (both included), or a list 1,5,9. Default: the scenario's own.
    #[arg(long, value_name = "SEEDS")]
    seeds: Option<String>,
    /// A parameter: KEY=V1,V2,... (a grid axis) or KEY=LO..HI (a random draw per run).
    /// Repeatable.
    #[arg(long = "set", value_name = "KEY=VALUES")]
    set: Vec<String>,
    /// Drive configuration TOML (overrides the scenario's).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Threads (default: one per core).
    #[arg(long, value_name = "N", default_value_t = 0)]
    jobs: usize,
    /// Output folder for sweep.csv, sweep.jsonl, sweep.png and the worst runs' logs.
    #[arg(long, default_value = "out")]
    out: PathBuf,
    /// How many of the worst runs (largest drift) to print.
    #[arg(long, value_name = "N", default_value_t = 5)]
    worst: usize,
    /// Run the N worst runs again with logs: OUT/sweep-<index>.mcap.
    #[arg(long, value_name = "N", default_value_t = 0)]
    log_worst: usize,
    /// Do not draw sweep.png.
    #[arg(long)]
    no_plot: bool,
}

/// The arguments of `hostsim check`.
#[derive(Debug, clap::Args)]
struct CheckArgs {
    /// Drive configuration TOML (as config/dji_m3508.toml or config/odrive.toml).
    /// Default: the built-in DJI example.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    #[command(flatten)]
    wiring: WiringArgs,
    /// Wheel speed of each test, rad/s at the wheel (robot-forward; |speed| <= 10).
    #[arg(long, value_name = "RAD_S", default_value_t = 3.0)]
    speed: f32,
    /// Length of each test, ms (1-3000).
    #[arg(long, value_name = "MS", default_value_t = 1000)]
    duration_ms: u16,
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
}

/// The exit status of a process killed by SIGPIPE, as a shell reports it.
const SIGPIPE_STATUS: u8 = 128 + 13;

/// Rust ignores SIGPIPE, so `println!` to a closed pipe (`hostsim run | head -1`) panics.
/// Behave like a Unix tool instead: end quietly with the status a SIGPIPE death gives.
fn exit_quietly_on_broken_pipe() {
    let default = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let payload = info.payload();
        let message = payload
            .downcast_ref::<String>()
            .map(String::as_str)
            .or_else(|| payload.downcast_ref::<&str>().copied())
            .unwrap_or("");
        if message.starts_with("failed printing to std") && message.contains("Broken pipe") {
            std::process::exit(i32::from(SIGPIPE_STATUS));
        }
        default(info);
    }));
}

fn main() -> ExitCode {
    exit_quietly_on_broken_pipe();
    let cli = Cli::parse();
    match dispatch(cli) {
        Ok(code) => code,
        Err(e) => {
            // Each cause once: most errors here already include their source's text.
            eprintln!("error: {}", mecanum_linux::error_line(e.as_ref()));
            ExitCode::from(2)
        }
    }
}

fn dispatch(cli: Cli) -> Result<ExitCode> {
    match cli.command {
        Cmd::Run {
            scenario,
            out,
            config,
            seed,
            set,
            no_log,
            no_plot,
            json,
            progress_lines,
        } => run(
            scenario.as_deref(),
            &out,
            config,
            seed,
            &set,
            RunOutputs {
                log: !no_log,
                plot: !no_plot,
                json,
                progress_lines,
            },
        ),
        Cmd::Replay {
            log,
            config,
            json,
            position_tolerance,
            heading_tolerance,
            iface,
            speed,
            only,
        } => {
            let tolerance = OdometryTolerance {
                position_m: position_tolerance,
                heading_rad: heading_tolerance,
            };
            match iface {
                Some(iface) => play(&log, config.as_deref(), &iface, speed, only, json),
                None => {
                    if speed.is_some() || only.is_some() {
                        bail!("--speed and --only need --iface (they control the playback)");
                    }
                    replay(&log, config.as_deref(), tolerance, json)
                }
            }
        }
        Cmd::Plant(args) => plant(&args),
        Cmd::Check(args) => check(&args),
        Cmd::Sweep(args) => sweep(&args),
        Cmd::Summary { log } => summary(&log),
        Cmd::Plot { logs, out } => plot_logs(&logs, out),
        Cmd::Calibrate {
            log,
            reference,
            window,
            write,
            json,
        } => calibrate(&log, reference, window, write.as_deref(), json),
        Cmd::Kin => {
            let stdin = std::io::stdin();
            match hostsim::kin::run(stdin.lock(), std::io::stdout().lock()) {
                Ok(()) => Ok(ExitCode::SUCCESS),
                // The reader went away (`hostsim kin | head -1`): end quietly, as on SIGPIPE.
                Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => {
                    Ok(ExitCode::from(SIGPIPE_STATUS))
                }
                Err(e) => Err(e).context("reading stdin / writing stdout"),
            }
        }
    }
}

/// A scenario file, or else a built-in of that name (`square` if none); `config` replaces
/// its configuration.
fn load_scenario(arg: Option<&str>, config: Option<firmware::Config>) -> Result<Scenario> {
    Ok(Scenario::load(arg.unwrap_or("square"), config)?)
}

/// What `run` writes besides the simulation itself.
#[derive(Debug, Clone, Copy)]
struct RunOutputs {
    log: bool,
    plot: bool,
    json: bool,
    progress_lines: bool,
}

fn run(
    scenario: Option<&str>,
    out: &Path,
    config: Option<PathBuf>,
    seed: Option<u64>,
    set: &[String],
    outputs: RunOutputs,
) -> Result<ExitCode> {
    let RunOutputs {
        log: write_log,
        plot: draw_plot,
        json,
        progress_lines,
    } = outputs;
    let config = config
        .map(|path| firmware::Config::from_toml_file(&path))
        .transpose()?;
    let mut scenario = load_scenario(scenario, config)?;
    if let Some(seed) = seed {
        scenario.seed = seed;
    }
    if !set.is_empty() {
        let mut values = Vec::new();
        for arg in set {
            let p = hostsim::sweep::Param::parse(arg)?;
            match p.values {
                hostsim::sweep::Values::List(v) if v.len() == 1 => values.push((p.key, v[0])),
                _ => bail!(
                    "--set {arg}: expected one value, KEY=VALUE (grids and ranges are for sweep)"
                ),
            }
        }
        scenario = hostsim::sweep::apply(&scenario, scenario.seed, &values)?;
    }
    std::fs::create_dir_all(out)
        .with_context(|| format!("cannot create the output folder {}", out.display()))?;
    let stem: String = scenario
        .name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect();
    let log_path = out.join(format!("{stem}.mcap"));
    let png_path = out.join(format!("{stem}.png"));
    if draw_plot {
        // Now, not after a long run: a path that cannot be written fails before simulating.
        std::fs::File::create(&png_path)
            .with_context(|| format!("cannot create the plot {}", png_path.display()))?;
    }
    let mut log = if write_log {
        Some(McapLog::create(&log_path, &run_metadata(&scenario))?)
    } else {
        None
    };
    let mut plant = hostsim::drives::SimDrives::for_scenario(&scenario)?;
    let bar = ProgressBar::new(scenario.duration_us() / 1000);
    bar.set_style(
        ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} ms simulated ({per_sec})")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.set_message(scenario.name.clone());
    let wall = std::time::Instant::now();
    let summary = hostsim::sim::run(
        &scenario,
        &mut plant,
        log.as_mut(),
        LogOptions::default(),
        |t_us| {
            bar.set_position(t_us / 1000);
            if progress_lines {
                // One write, so that a reader never sees half a line from a killed run.
                let line = format!("progress {:.3}\n", t_us as f64 * 1e-6);
                let _ = std::io::stderr().write_all(line.as_bytes());
            }
        },
    )?;
    bar.finish_and_clear();
    let wall_s = wall.elapsed().as_secs_f64();
    if let Some(log) = log {
        log.finish()?;
    }
    if draw_plot {
        plot_run(&png_path, &scenario.name, &summary.track)?;
    }
    if json {
        println!("{}", summary_json(&summary, wall_s));
    } else {
        print_summary(&summary, wall_s);
        if write_log {
            println!("log:   {}", log_path.display());
        }
        if draw_plot {
            println!("plot:  {}", png_path.display());
        }
    }
    Ok(ExitCode::SUCCESS)
}

fn print_summary(s: &RunSummary, wall_s: f64) {
    println!(
        "scenario {:?}: {:.2} s simulated in {:.3} s ({:.0}x real time)",
        s.scenario,
        s.duration_s,
        wall_s,
        s.duration_s / wall_s.max(1e-9)
    );
    println!(
        "ground truth  x {:+.4} m  y {:+.4} m  heading {:+.2}°",
        s.truth[0],
        s.truth[1],
        s.truth[2].to_degrees()
    );
    println!(
        "odometry      x {:+.4} m  y {:+.4} m  heading {:+.2}°",
        s.odometry[0],
        s.odometry[1],
        s.odometry[2].to_degrees()
    );
    println!(
        "odometry drift: final {:.1} mm, max {:.1} mm, heading {:.2}°",
        s.final_position_error * 1000.0,
        s.max_position_error * 1000.0,
        s.final_heading_error.to_degrees()
    );
    println!(
        "bus: {} frames, load {:.1} %, {} dropped, {} corrupted; firmware sent {}, received {}",
        s.bus.frames,
        s.bus_load * 100.0,
        s.bus.dropped,
        s.bus.corrupted,
        s.tx_frames,
        s.rx_frames
    );
    let e = s.last.rx_errors;
    println!(
        "firmware: final state {} (fault {}); rejected frames {}, unknown ids {}, repeated twists {}",
        s.last.state,
        s.last.fault,
        e.total() - e.unknown_id,
        e.unknown_id,
        s.last.repeated_seq
    );
    for (t, state, fault) in &s.transitions {
        println!("  {t:8.3} s  {state} ({fault})");
    }
    if s.last.heading_source != firmware::protocol::robot::HeadingSource::Wheels {
        println!(
            "gyro heading: final source {}, bias estimate {:+.4} °/s from {} standstill \
             samples; heading source changes:",
            s.last.heading_source,
            f64::from(s.last.gyro_bias).to_degrees(),
            s.last.gyro_bias_samples
        );
        for (t, source) in &s.heading_changes {
            println!("  {t:8.3} s  {source}");
        }
    }
    println!("outbound stream hash {:016x}", s.tx_hash);
}

fn summary_json(s: &RunSummary, wall_s: f64) -> String {
    serde_json::json!({
        "scenario": s.scenario,
        "duration_s": s.duration_s,
        "wall_s": wall_s,
        "steps": s.steps,
        "tx_frames": s.tx_frames,
        "rx_frames": s.rx_frames,
        "bus_frames": s.bus.frames,
        "bus_load": s.bus_load,
        "dropped": s.bus.dropped,
        "corrupted": s.bus.corrupted,
        "truth": s.truth,
        "odometry": s.odometry,
        "final_position_error": s.final_position_error,
        "max_position_error": s.max_position_error,
        "final_heading_error": s.final_heading_error,
        "state": s.last.state.as_str(),
        "fault": s.last.fault.as_str(),
        "transitions": s.transitions,
        "heading_changes": s.heading_changes,
        "tx_hash": format!("{:016x}", s.tx_hash),
    })
    .to_string()
}

/// Which logged frames `replay --iface` plays.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Only {
    /// The frames the firmware received (from the host and the drives).
    Rx,
    /// The frames the firmware sent.
    Tx,
    /// Every frame.
    All,
}

fn parse_seconds(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if (0.0..1e9).contains(&v) => Ok(v),
        Ok(v) => Err(format!(
            "expected a number of seconds in [0, 1e9) (about 31 years), got {v}"
        )),
        Err(e) => Err(format!("expected a number of seconds, got {s:?}: {e}")),
    }
}

/// The drive configuration of `--config`, or the built-in DJI example; with a description.
fn load_config(path: Option<&Path>) -> Result<(firmware::Config, String)> {
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

fn replay(
    path: &Path,
    config: Option<&Path>,
    tolerance: OdometryTolerance,
    json: bool,
) -> Result<ExitCode> {
    for (name, value) in [
        ("--position-tolerance", tolerance.position_m),
        ("--heading-tolerance", tolerance.heading_rad),
    ] {
        if !(value.is_finite() && value >= 0.0) {
            bail!("{name} must be a finite number >= 0, got {value}");
        }
    }
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
    let show = |f: &Option<hostsim::replay::TimedFrame>| {
        f.map_or_else(
            || "nothing".to_string(),
            |f| format!("{} at {:.6} s", f.frame, f.t_ns as f64 * 1e-9),
        )
    };
    let code = if !report.identical() {
        ExitCode::from(1)
    } else if damaged.is_some() {
        ExitCode::from(EXIT_DAMAGED)
    } else {
        ExitCode::SUCCESS
    };
    if json {
        let frame = |f: &Option<hostsim::replay::TimedFrame>| {
            f.map(|f| {
                serde_json::json!({
                    "t_s": format!("{:.6}", f.t_ns as f64 * 1e-9),
                    "frame": f.frame.to_string(),
                })
            })
        };
        let difference = report.difference.as_ref().map(|d| {
            serde_json::json!({
                "index": d.index,
                "t_s": format!("{:.6}", d.t_ns as f64 * 1e-9),
                "logged": frame(&d.logged),
                "replayed": frame(&d.replayed),
            })
        });
        let v = serde_json::json!({
            "log": path.display().to_string(),
            "format": LogFormat::Mcap,
            "steps": report.steps,
            "fed": report.fed,
            "compared": report.compared,
            "identical": report.identical(),
            "verdict": if report.identical() { "identical" } else { "differs" },
            "first_difference": difference,
            "complete": damaged.is_none(),
            "damage": damaged.map(ToString::to_string),
            "damage_offset": damaged.and_then(|r| r.damage.as_ref()).map(|d| d.offset),
        });
        println!("{v}");
        return Ok(code);
    }
    println!(
        "replayed {} steps, fed {} inbound frames, compared {} outbound frames",
        report.steps, report.fed, report.compared
    );
    match &report.difference {
        None => println!("outbound frames are bit-identical"),
        Some(d) => println!(
            "first difference at outbound frame {} ({:.6} s): log has {}, replay sent {}",
            d.index,
            d.t_ns as f64 * 1e-9,
            show(&d.logged),
            show(&d.replayed)
        ),
    }
    Ok(code)
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
    let verdict = if r.identical {
        "no_difference"
    } else {
        "differs"
    };
    if json {
        let mut v = serde_json::to_value(&r)?;
        if let Some(o) = v.as_object_mut() {
            o.insert("note".into(), OPEN_LOOP_NOTE.into());
            o.insert("log".into(), path.display().to_string().into());
            o.insert("format".into(), serde_json::to_value(LogFormat::Mcap)?);
            o.insert("config".into(), config.display().to_string().into());
            o.insert("verdict".into(), verdict.into());
            o.insert("complete".into(), damaged.is_none().into());
            o.insert("damage".into(), damaged.map(ToString::to_string).into());
        }
        println!("{v}");
        return Ok(code);
    }
    println!("{OPEN_LOOP_NOTE}");
    println!(
        "log {}, what-if configuration {}",
        path.display(),
        config.display()
    );
    if r.changes.is_empty() {
        println!("changes: none (the what-if configuration equals the logged one)");
    } else {
        let show = |v: &Option<String>| v.as_deref().unwrap_or("(absent)").to_string();
        let changes: Vec<String> = r
            .changes
            .iter()
            .map(|c| format!("{} {} -> {}", c.field, show(&c.logged), show(&c.what_if)))
            .collect();
        println!("changes: {}", changes.join(", "));
    }
    println!(
        "replayed {} steps, fed {} inbound frames; the log has {} outbound frames, the what-if \
         core sent {}",
        r.steps, r.fed, r.logged_frames, r.what_if_frames
    );
    match &r.first_difference {
        None => println!(
            "outbound frames are bit-identical: the change makes no difference on this log"
        ),
        Some(d) => {
            // A frame's own time only where it is not the step's.
            let show = |f: &Option<hostsim::replay::ReportFrame>| match f {
                None => "nothing".to_string(),
                Some(f) if f.t_s == d.t_s => f.frame.clone(),
                Some(f) => format!("{} at {} s", f.frame, f.t_s),
            };
            println!(
                "first difference at {} s (outbound frame {}): log has {}, what-if sent {}",
                d.t_s,
                d.index,
                show(&d.logged),
                show(&d.what_if)
            );
        }
    }
    println!("outbound frames by arbitration id:");
    println!(
        "  {:<10} {:<28} {:>8} {:>8} {:>8}",
        "id", "message", "logged", "what-if", "differ"
    );
    for c in &r.by_id {
        println!(
            "  {:<10} {:<28} {:>8} {:>8} {:>8}",
            c.id,
            c.message,
            c.logged,
            c.what_if,
            c.differ()
        );
    }
    for q in &r.setpoints {
        println!(
            "{} setpoints, {} (difference = what-if - logged, each held between its commands):",
            q.quantity, q.unit
        );
        println!(
            "  {:<5} {:>11} {:>12} {:>11} {:>10} {:>11}",
            "wheel", "max|logged|", "max|what-if|", "max|diff|", "at (s)", "rms diff"
        );
        for w in &q.wheels {
            let d = &w.difference;
            println!(
                "  {:<5} {:>11.4} {:>12.4} {:>11.4} {:>10} {:>11.4}",
                w.wheel,
                w.max_abs_logged,
                w.max_abs_what_if,
                d.max_abs_difference,
                d.t_max_difference_s.as_deref().unwrap_or("-"),
                d.rms_difference
            );
        }
    }
    let list = |changes: &[hostsim::whatif::StateChange]| {
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
    println!("state changes in the STATUS frames:");
    println!("  logged:               {}", list(&s.logged));
    println!("  what-if:              {}", list(&s.what_if));
    println!("  only in the log:      {}", list(&s.only_logged));
    println!("  only in the what-if:  {}", list(&s.only_what_if));
    println!("  what-if core (exact): {}", list(&s.what_if_core));
    println!("verdict: {verdict}");
    Ok(code)
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
        ExitCode::from(1)
    };
    if json {
        let mut v = serde_json::to_value(&r)?;
        if let Some(o) = v.as_object_mut() {
            o.insert("log".into(), path.display().to_string().into());
            o.insert("format".into(), serde_json::to_value(LogFormat::Candump)?);
            o.insert("config".into(), source.into());
            o.insert("verdict".into(), r.verdict().into());
        }
        println!("{v}");
        return Ok(code);
    }
    println!(
        "candump log {}: {} frames on {} over {:.3} s; configuration: {source}",
        path.display(),
        r.frames,
        r.interfaces.join(", "),
        r.duration_s
    );
    println!(
        "firmware received {} frames (fed), sent {} (compared); replay ran {} steps of {} µs \
         and sent {}",
        r.received, r.sent, r.steps, r.period_us, r.replayed
    );
    match &r.first_difference {
        None => println!("outbound frames are identical (time ignored)"),
        Some(d) => {
            let show = |f: &Option<hostsim::replay::ReportFrame>| {
                f.as_ref().map_or_else(
                    || "nothing".to_string(),
                    |f| format!("{} at {} s", f.frame, f.t_s),
                )
            };
            println!(
                "outbound frames differ (time ignored) at frame {} ({} matched): log has {}, \
                 replay sent {}",
                d.index,
                r.matching_prefix,
                show(&d.logged),
                show(&d.replayed)
            );
        }
    }
    match &r.odometry {
        None => println!("odometry: the log has no ODOM_POSITION frame to compare"),
        Some(o) => {
            let pose = |p: &hostsim::replay::OdometryReading| {
                format!(
                    "x {:+.4} m  y {:+.4} m  heading {:+.2}° at {:.3} s",
                    p.x,
                    p.y,
                    p.heading.to_degrees(),
                    p.t_s
                )
            };
            println!("odometry logged   {}", pose(&o.logged));
            println!("odometry replayed {}", pose(&o.replayed));
            println!(
                "odometry {}: position {:.1} mm (tolerance {:.1} mm), heading {:.4} rad \
                 (tolerance {:.4} rad), velocity {:.4}",
                if o.agrees { "agrees" } else { "DIFFERS" },
                o.position_error_m * 1000.0,
                o.tolerance.position_m * 1000.0,
                o.heading_error_rad,
                o.tolerance.heading_rad,
                o.velocity_error
            );
        }
    }
    let e = &r.rejected;
    let rejected = e.extended_id + e.remote + e.wrong_dlc + e.non_finite + e.out_of_range;
    println!(
        "replayed core rejected {rejected} received frames, ignored {} with unknown ids",
        e.unknown_id
    );
    println!("verdict: {}", r.verdict());
    Ok(code)
}

/// `replay LOG --iface IFACE`: plays the log's frames onto the interface in real time.
fn play(
    path: &Path,
    config: Option<&Path>,
    iface: &str,
    speed: Option<f64>,
    only: Option<Only>,
    json: bool,
) -> Result<ExitCode> {
    let speed = speed.unwrap_or(1.0);
    if !(speed.is_finite() && speed > 0.0) {
        bail!("--speed must be a finite number > 0, got {speed}");
    }
    let only = only.unwrap_or(Only::Rx);
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
            let content = hostsim::replay::read_log(path)?;
            warn_if_damaged(path, &content.read, "playing its complete part");
            damaged = !content.read.is_complete();
            mcap_playback(&content, rx, tx)
        }
        LogFormat::Candump => {
            let (config, _) = load_config(config)?;
            let entries = hostsim::candump::read_file(path)?;
            let split = split_candump(&config, &entries);
            match only {
                Only::Rx => split.rx,
                Only::Tx => split.tx,
                Only::All => split.all,
            }
        }
    };
    // A corrupt timestamp would make the playback sleep for years.
    hostsim::replay::check_time_gaps(&frames)
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
    if json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        println!("{report}");
    }
    Ok(if report.failed > 0 {
        ExitCode::from(1)
    } else if damaged {
        ExitCode::from(EXIT_DAMAGED)
    } else {
        ExitCode::SUCCESS
    })
}

/// `sweep SCENARIO`: many runs at once.
fn sweep(args: &SweepArgs) -> Result<ExitCode> {
    use hostsim::sweep::{self as sw, Param};
    let config = args
        .config
        .as_deref()
        .map(firmware::Config::from_toml_file)
        .transpose()?;
    let base = load_scenario(Some(&args.scenario), config)?;
    let seeds = match &args.seeds {
        Some(s) => sw::parse_seeds(s)?,
        None => vec![base.seed],
    };
    let params: Vec<Param> = args
        .set
        .iter()
        .map(|a| Param::parse(a))
        .collect::<Result<_, _>>()?;
    let runs = sw::expand(&seeds, &params);
    // Every name and value (and both ends of each range), before the first run.
    sw::check(&base, &runs, &params)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create the output folder {}", args.out.display()))?;
    let csv_path = args.out.join("sweep.csv");
    let jsonl_path = args.out.join("sweep.jsonl");
    let png_path = args.out.join("sweep.png");
    let mut csv =
        File::create(&csv_path).with_context(|| format!("cannot create {}", csv_path.display()))?;
    let mut jsonl = File::create(&jsonl_path)
        .with_context(|| format!("cannot create {}", jsonl_path.display()))?;
    let threads = if args.jobs == 0 {
        std::thread::available_parallelism().map_or(1, std::num::NonZero::get)
    } else {
        args.jobs
    };
    eprintln!(
        "sweep of {:?}: {} runs ({} seeds x {} values) on {threads} threads",
        base.name,
        runs.len(),
        seeds.len(),
        runs.len() / seeds.len().max(1)
    );
    let signal = mecanum_linux::stop_on_signals()?;
    let bar = ProgressBar::new(runs.len() as u64);
    bar.set_style(
        ProgressStyle::with_template("[{bar:40}] {pos}/{len} runs, {elapsed} elapsed, ETA {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let stop = || signal.load(std::sync::atomic::Ordering::Relaxed) != 0;
    let wall = std::time::Instant::now();
    let rows = sw::run_all(&base, &runs, threads, &stop, |_| bar.inc(1))?;
    bar.finish_and_clear();
    let interrupted = rows.len() < runs.len();
    let keys: Vec<String> = params.iter().map(|p| p.key.clone()).collect();
    writeln!(csv, "{}", sw::csv_header(&keys))?;
    for r in &rows {
        writeln!(csv, "{}", r.csv())?;
        writeln!(jsonl, "{}", r.json())?;
    }
    let secs = wall.elapsed().as_secs_f64();
    let simulated: f64 =
        rows.iter().map(|r| r.steps as f64).sum::<f64>() / f64::from(base.config.timing.control_hz);
    println!(
        "{} of {} runs in {secs:.1} s on {threads} threads ({:.0}x real time in all){}",
        rows.len(),
        runs.len(),
        simulated / secs.max(1e-9),
        if interrupted {
            "; INTERRUPTED: the rows finished are written"
        } else {
            ""
        }
    );
    let column = |f: fn(&sw::Row) -> f64| rows.iter().map(f).collect::<Vec<f64>>();
    for (name, unit, values) in [
        ("drift, largest", "m", column(|r| r.drift_max_m)),
        ("drift, final", "m", column(|r| r.drift_final_m)),
        ("tracking error RMS", "m/s", column(|r| r.tracking_rms_m_s)),
        ("stop after a fault", "s", column(|r| r.stop_after_fault_s)),
    ] {
        if values.iter().all(|v| !v.is_finite()) {
            println!("{name:20} -");
            continue;
        }
        println!(
            "{name:20} p50 {:.4}  p90 {:.4}  p99 {:.4}  max {:.4} {unit}",
            sw::percentile(&values, 50.0),
            sw::percentile(&values, 90.0),
            sw::percentile(&values, 99.0),
            sw::percentile(&values, 100.0)
        );
    }
    let mut faults: std::collections::BTreeMap<&str, usize> = std::collections::BTreeMap::new();
    for r in &rows {
        *faults.entry(r.fault.as_str()).or_default() += 1;
    }
    let faults: Vec<String> = faults.iter().map(|(k, n)| format!("{k} {n}")).collect();
    println!("faults: {}", faults.join(", "));
    let mut worst: Vec<&sw::Row> = rows.iter().collect();
    worst.sort_by(|a, b| {
        b.drift_max_m
            .total_cmp(&a.drift_max_m)
            .then(a.index.cmp(&b.index))
    });
    println!("worst runs (largest drift):");
    for r in worst.iter().take(args.worst) {
        println!(
            "  #{} drift {:.4} m, fault {}: {}",
            r.index,
            r.drift_max_m,
            r.fault,
            r.reproduce(&args.scenario)
        );
    }
    for r in worst.iter().take(args.log_worst) {
        let s = sw::apply(&base, r.seed, &r.values)?;
        let path = args.out.join(format!("sweep-{}.mcap", r.index));
        let mut log = McapLog::create(&path, &run_metadata(&s))?;
        let mut plant = hostsim::drives::SimDrives::for_scenario(&s)?;
        hostsim::sim::run(
            &s,
            &mut plant,
            Some(&mut log),
            LogOptions::default(),
            |_| {},
        )?;
        log.finish()?;
        println!("  log of #{}: {}", r.index, path.display());
    }
    if !args.no_plot && !rows.is_empty() {
        let (label, xs): (String, Vec<f64>) = match keys.first() {
            Some(k) => (k.clone(), rows.iter().map(|r| r.values[0].1).collect()),
            #[allow(clippy::cast_precision_loss)]
            None => ("seed".into(), rows.iter().map(|r| r.seed as f64).collect()),
        };
        let ys = column(|r| r.drift_max_m);
        hostsim::plot::scatter(
            &png_path,
            &format!("sweep of {}", base.name),
            &label,
            "largest drift, m",
            &xs,
            &ys,
        )?;
    }
    println!("table: {} and {}", csv_path.display(), jsonl_path.display());
    Ok(if interrupted {
        ExitCode::from(130)
    } else {
        ExitCode::SUCCESS
    })
}

/// `check`: the bring-up check on a simulated robot on blocks.
fn check(args: &CheckArgs) -> Result<ExitCode> {
    use hostsim::bringup::{Wiring, diagnose, report, run_check};
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
    let runs = run_check(&config, &spec, args.speed, args.duration_ms)
        .with_context(|| format!("configuration {source}"))?;
    let configured = Wiring::of(&config);
    let d = diagnose(&configured, runs.map(|r| r.seen));
    if args.json {
        let wheels: Vec<serde_json::Value> = runs
            .iter()
            .zip(d.verdicts)
            .map(|(r, v)| {
                serde_json::json!({
                    "wheel": hostsim::bringup::WHEEL_NAMES[r.wheel],
                    "id": configured.ids[r.wheel],
                    "turned": r.seen.map(|s| hostsim::bringup::WHEEL_NAMES[s.wheel]),
                    "forward": r.seen.map(|s| s.forward),
                    "angles_rad": r.turned,
                    "verdict": hostsim::bringup::verdict_text(r.wheel, v),
                    "firmware": r.result.map(|t| serde_json::json!({
                        "outcome": t.outcome.as_str(),
                        "angle_rad": t.angle,
                        "peak_current_a": t.peak_current,
                    })),
                    "fault": r.fault.as_str(),
                })
            })
            .collect();
        let out = serde_json::json!({
            "configuration": source,
            "right": d.is_right(),
            "wheels": wheels,
            "fix": d.fix_lines(&configured),
            "unresolved": d.unresolved,
        });
        println!("{out}");
    } else {
        println!(
            "bring-up check of {source} on a simulated robot on blocks, each wheel at {} rad/s \
             for {} ms:",
            args.speed, args.duration_ms
        );
        print!("{}", report(&configured, &runs, &d));
    }
    Ok(if d.is_right() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(3)
    })
}

/// `plant --iface IFACE`: the simulated drives on the interface in real time.
fn plant(args: &PlantArgs) -> Result<ExitCode> {
    let (iface, quiet) = (args.iface.as_str(), args.quiet);
    let (stats_json, log) = (args.stats_json.as_deref(), args.log.as_deref());
    let (config, source) = load_config(args.config.as_deref())?;
    let spec = hostsim::scenario::PlantSpec {
        lifted: args.lifted,
        ..args.wiring.spec()
    };
    let mut drives = hostsim::drives::SimDrives::with_spec(&config, &spec)
        .with_context(|| format!("configuration {source}: the plant cannot model it"))?;
    let imu = args.imu.then(|| hostsim::imu::ImuParams {
        bias_deg_s: args.imu_bias_deg_s.unwrap_or(0.1),
        ..hostsim::imu::ImuParams::default()
    });
    if let Some((key, value, expected)) = imu.as_ref().and_then(|i| i.invalid()) {
        bail!(
            "--imu-{}: {value}: expected {expected}",
            key.replace('_', "-")
        );
    }
    let mut drives = hostsim::imu::WithImu::new(&mut drives, imu.as_ref(), 0);
    let stop = mecanum_linux::stop_on_signals()?;
    let mut bus = SocketCanBus::open(iface)?;
    // Created before the loop starts, so a bad path fails now and not after a long run.
    let stats = match stats_json {
        Some(p) => Some((
            p,
            File::create(p)
                .with_context(|| format!("cannot create --stats-json file {}", p.display()))?,
        )),
        None => None,
    };
    let mut plant_log = match log {
        Some(path) => {
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
            Some(PlantLog::new(McapLog::create(path, &metadata)?))
        }
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
    let clock = MonotonicClock::new(args.spin_us);
    let report = match plant_log.as_mut() {
        Some(observer) => {
            run_plant_observed(&mut drives, &mut bus, &clock, &options, &stop, observer)
        }
        None => run_plant(&mut drives, &mut bus, &clock, &options, &stop),
    };
    let mut status = ExitCode::SUCCESS;
    if let (Some(observer), Some(path)) = (plant_log, log) {
        match observer.finish() {
            Ok(n) if !quiet => {
                eprintln!("hostsim plant: {n} messages logged to {}", path.display())
            }
            Ok(_) => {}
            Err(e) => {
                eprintln!("error: log {}: {e}", path.display());
                status = ExitCode::FAILURE;
            }
        }
    }
    // The ground truth always goes out, on stdout; the statistics on stderr.
    println!(
        "ground truth: x {:+.4} m  y {:+.4} m  heading {:+.2}°  (vx {:+.4} m/s  vy {:+.4} m/s  \
         wz {:+.4} rad/s)",
        report.truth.x,
        report.truth.y,
        report.truth.heading.to_degrees(),
        report.velocity.vx,
        report.velocity.vy,
        report.velocity.wz
    );
    if !quiet {
        eprintln!("hostsim plant: {report}");
    }
    if let Some((path, mut file)) = stats {
        let written = serde_json::to_writer_pretty(&mut file, &report)
            .map_err(anyhow::Error::from)
            .and_then(|()| Ok(file.write_all(b"\n")?));
        if let Err(e) = written {
            eprintln!(
                "error: cannot write --stats-json file {}: {e:#}",
                path.display()
            );
            return Ok(ExitCode::FAILURE);
        }
    }
    Ok(status)
}

fn summary(path: &Path) -> Result<ExitCode> {
    let s = hostsim::summary::summarize(path).map_err(anyhow::Error::msg)?;
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
            l if l >= hostsim::log::msg::Log::ERROR => "FAULT",
            // An e-stop; other warnings (a silent gyro, a lost CAN link) do not stop.
            l if l >= hostsim::log::msg::Log::WARN && text.starts_with("state") => "STOP ",
            l if l >= hostsim::log::msg::Log::WARN => "WARN ",
            _ => "     ",
        };
        println!("  {tag} {t:9.3} s  {text}");
    }
    for (topic, n) in &s.topics {
        println!("  {topic:24} {n:>9} messages");
    }
    println!("read: {}", s.read);
    if damaged {
        warn_if_damaged(path, &s.read, "the summary covers its complete part");
        return Ok(ExitCode::from(EXIT_DAMAGED));
    }
    Ok(ExitCode::SUCCESS)
}

/// `calibrate LOG`: the fitted geometry, printed and optionally written.
fn calibrate(
    path: &Path,
    reference: String,
    window_s: f64,
    write: Option<&Path>,
    json: bool,
) -> Result<ExitCode> {
    let options = hostsim::calibrate::Options {
        reference,
        window_s,
    };
    let c = hostsim::calibrate::calibrate(path, &options)
        .with_context(|| format!("cannot calibrate from {}", path.display()))?;
    warn_if_damaged(path, &c.read, "the fit used its complete part");
    if let Some(file) = write {
        let text = format!(
            "# The configuration of {}, [geometry] calibrated by hostsim calibrate (reference \
             {}).\n{}",
            path.display(),
            c.reference,
            c.config.to_toml_string()
        );
        std::fs::write(file, text).with_context(|| format!("cannot write {}", file.display()))?;
    }
    if json {
        println!("{}", c.to_json());
    } else {
        println!("calibration from {}", path.display());
        print!("{c}");
        if let Some(file) = write {
            println!("written: {}", file.display());
        }
    }
    Ok(if c.read.is_complete() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(EXIT_DAMAGED)
    })
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
    let tracks = logs
        .iter()
        .map(|p| hostsim::plot::track_from_log(p).map_err(anyhow::Error::msg))
        .collect::<Result<Vec<_>>>()?;
    let labels: Vec<String> = logs.iter().map(|p| p.display().to_string()).collect();
    let runs: Vec<(&str, &[hostsim::plot::TrackPoint])> = labels
        .iter()
        .zip(&tracks)
        .map(|(l, t)| (l.as_str(), t.as_slice()))
        .collect();
    let title = stem(&logs[0]);
    hostsim::plot::plot_runs(&out, &title, &runs)?;
    for (label, track) in labels.iter().zip(&tracks) {
        println!(
            "{label}: max drift {:.1} mm",
            hostsim::plot::max_drift(track) * 1000.0
        );
    }
    println!("plot:  {}", out.display());
    Ok(ExitCode::SUCCESS)
}
