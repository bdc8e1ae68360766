//! `hostsim run`: a scenario in lockstep, its log, plot and summary; with `--live`, served to
//! Foxglove as it runs, paced to the wall clock.

use std::io::Write as _;
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::Ordering;
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, Sender};
use std::time::Duration;

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;

use crate::analysis::plot::plot_run;
use crate::engine::{LogOptions, RunSummary, run_metadata};
use crate::scenario::Scenario;
use drivelog::McapLog;
use firmware::CanFrame;
use firmware::protocol::canopen::{self, NodeId};

use super::*;

/// Run a scenario: writes an MCAP log and a PNG plot, prints a summary.
///
/// With no argument runs the built-in `square`. Built-ins: square, circle, strafe, spin,
/// figure-eight, compass, watchdog, calibration (seed 1; DJI C620 + M3508 drives on a
/// 20 kg chassis; see `calibrate`).
///
/// A scenario file (TOML; examples in scenarios/) sets the run's length, the host's actions
/// and the faults on a timeline, and optionally the drive configuration, the simulated robot
/// where it differs from it (a miswiring too) and an IMU: the format is docs/scenarios.md
/// in the repository. Every error names the file, the field and the value.
///
/// With --live the run is served to Foxglove or Lichtblick as it goes (Foxglove WebSocket
/// protocol, every channel of the log with its schema), paced to the wall clock (--rate),
/// and Ctrl-C stops it cleanly: the log finished, exit status 130 (docs/live.md).
#[derive(Debug, clap::Args)]
pub struct Args {
    /// A scenario TOML file, or the name of a built-in.
    pub scenario: Option<String>,
    /// Output folder for `<name>.mcap` and `<name>.png`.
    #[arg(long, default_value = "out")]
    pub out: PathBuf,
    /// Drive configuration TOML (overrides the scenario's).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Seed for the bus faults (overrides the scenario's).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Set a field, KEY=VALUE: of the drive configuration as its TOML names it
    /// (gains.kp, limits.max_current, ...), of the plant (plant.mass_kg, ...), of the pod
    /// node (pods.radius_error, pods.pod[1].offset_x, ...) or of the IMU (imu.bias_deg_s),
    /// as a `sweep` row prints it. Repeatable.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
    /// Do not write the MCAP log.
    #[arg(long, conflicts_with = "live")]
    pub no_log: bool,
    /// Do not draw the plot.
    #[arg(long)]
    pub no_plot: bool,
    /// Print the summary as JSON instead of text.
    #[arg(long)]
    pub json: bool,
    /// Print `progress <simulated seconds>` on stderr every 100 ms of simulated time, one
    /// line each, after that time's messages went to the log: for scripts that watch a
    /// run (the progress bar is drawn only on a terminal).
    #[arg(long)]
    pub progress_lines: bool,
    /// `--live` and its caps (flattened: clap takes the help from their own docs).
    #[command(flatten)]
    pub live: live::LiveArgs,
    /// With --live: simulated seconds per wall-clock second (1: real time, 0.5: half speed,
    /// 4: four times), 0.001 to 1000. Without --live a run goes as fast as it can, and
    /// --rate is refused.
    #[arg(long, value_name = "X", requires = "live", value_parser = parse_rate)]
    pub rate: Option<f64>,
}

/// `--rate`: in [`live::Pacer::RATES`].
fn parse_rate(s: &str) -> Result<f64, String> {
    let rate: f64 = s
        .trim()
        .parse()
        .map_err(|_| format!("{s:?}: expected a number, e.g. 1 (real time) or 0.5"))?;
    live::Pacer::check_rate(rate)
}

/// How a live run serves (`--live`) and paces (`--rate`).
#[derive(Debug, Clone)]
struct LiveArgs {
    serve: live::LiveArgs,
    rate: f64,
}

/// What `run` starts from: the scenario with `--config`, `--seed` and `--set` applied, and
/// its plant.
pub struct Prepared {
    /// The scenario to run.
    pub scenario: crate::scenario::Scenario,
    /// Its simulated drives and chassis.
    pub plant: crate::nodes::drives::SimDrives,
}

/// `hostsim run`'s checks before any output: the configuration and scenario load, each
/// `--set` is one value the scenario takes, the plant can model the result.
///
/// # Errors
/// The first of those that fails, naming the file, key or value.
pub fn prepare(a: &Args) -> Result<Prepared> {
    let config = a
        .config
        .as_deref()
        .map(firmware::Config::from_toml_file)
        .transpose()?;
    let mut scenario = load_scenario(a.scenario.as_deref(), config)?;
    if let Some(seed) = a.seed {
        scenario.seed = seed;
    }
    if !a.set.is_empty() {
        let mut values = Vec::new();
        for arg in &a.set {
            let p = crate::analysis::sweep::Param::parse(arg)?;
            match p.values {
                crate::analysis::sweep::Values::List(v) if v.len() == 1 => {
                    values.push((p.key, v[0]))
                }
                _ => bail!(
                    "--set {arg}: expected one value, KEY=VALUE (grids and ranges are for sweep)"
                ),
            }
        }
        scenario = crate::analysis::sweep::apply(&scenario, scenario.seed, &values)?;
    }
    // The plant before any output: a scenario it refuses makes no file.
    let plant = crate::engine::plant_for(&scenario)?;
    Ok(Prepared { scenario, plant })
}

/// `hostsim run`.
pub fn execute(a: &Args) -> Result<ExitCode> {
    run(
        prepare(a)?,
        &a.out,
        RunOutputs {
            log: !a.no_log,
            plot: !a.no_plot,
            json: a.json,
            progress_lines: a.progress_lines,
        },
        a.live.live.is_some().then(|| LiveArgs {
            serve: a.live.clone(),
            rate: a.rate.unwrap_or(1.0),
        }),
    )
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
    prepared: Prepared,
    out: &Path,
    outputs: RunOutputs,
    live_args: Option<LiveArgs>,
) -> Result<ExitCode> {
    let RunOutputs {
        log: write_log,
        plot: draw_plot,
        json,
        progress_lines,
    } = outputs;
    let Prepared {
        scenario,
        mut plant,
    } = prepared;
    std::fs::create_dir_all(out)
        .with_context(|| format!("cannot create the output folder {}", out.display()))?;
    let stem = drivelog::file_stem(&scenario.name);
    let log_path = out.join(format!("{stem}.mcap"));
    let png_path = out.join(format!("{stem}.png"));
    if draw_plot {
        // Now, not after a long run: a path that cannot be written fails before simulating.
        // (Its temporary file only: the last good plot stays until the new one is whole.)
        drivelog::Staged::create(&png_path).context("cannot create the plot")?;
    }
    // Before the log: an address that cannot be served fails before a file is made.
    let (mut live, inbox) = match live_args {
        Some(args) => {
            let (live, inbox) = Live::start(args, &scenario)?;
            (Some(live), Some(inbox))
        }
        None => (None, None),
    };
    let mut log = if write_log {
        Some(McapLog::create(&log_path, &run_metadata(&scenario))?)
    } else {
        None
    };
    if let (Some(live), Some(log)) = (live.as_mut(), log.as_mut()) {
        live.attach(log);
    }
    let bar = ProgressBar::new(scenario.duration_us() / 1000);
    bar.set_style(
        ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} ms simulated ({per_sec})")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.set_message(scenario.name.clone());
    let wall = std::time::Instant::now();
    let partial = log.as_ref().and_then(|l| l.part()).map(Path::to_path_buf);
    let summary = crate::engine::run_live(
        &scenario,
        &mut plant,
        log.as_mut(),
        LogOptions::default(),
        inbox.as_ref(),
        |step| {
            let t_us = step.t_us;
            if t_us.is_multiple_of(100_000) {
                bar.set_position(t_us / 1000);
                if progress_lines {
                    // One write, so that a reader never sees half a line from a killed run.
                    let line = format!("progress {:.3}\n", t_us as f64 * 1e-6);
                    let _ = std::io::stderr().write_all(line.as_bytes());
                }
            }
            match live.as_mut() {
                Some(live) => live.step(t_us, step.sent),
                None => ControlFlow::Continue(()),
            }
        },
    )
    .with_context(|| match &partial {
        Some(part) => format!(
            "the run failed; what it logged is in {} (the last good outputs are as they were)",
            part.display()
        ),
        None => "the run failed (the last good outputs are as they were)".to_string(),
    })?;
    bar.finish_and_clear();
    let wall_s = wall.elapsed().as_secs_f64();
    if let Some(log) = log {
        log.finish()?;
    }
    // After the log: its last messages are queued for the clients before they are let go.
    let live = live.map(Live::finish);
    if draw_plot {
        plot_run(&png_path, &scenario.name, &summary.track)?;
    }
    let interrupted = live.as_ref().is_some_and(|l| l.interrupted);
    let report = Report::new(
        &summary,
        wall_s,
        live.as_ref(),
        write_log.then_some(log_path.as_path()),
        draw_plot.then_some(png_path.as_path()),
    );
    print_report(&report, json)?;
    if let Some(l) = &live {
        eprintln!("live: {}", l.report);
        eprintln!("live: {}", l.pacing);
        if l.interrupted {
            eprintln!(
                "live: INTERRUPTED at {:.3} s simulated: the log holds the run up to there",
                summary.duration_s
            );
        }
    }
    Ok(if interrupted {
        ExitCode::from(EXIT_INTERRUPTED)
    } else {
        ExitCode::SUCCESS
    })
}

/// A live run's server, pacer and stop flag, and the way of its clients' parameter requests
/// to the simulated robot ([`SimulatedBus`]).
struct Live {
    server: live::LiveServer,
    /// The robot's answers to the requests, for the server's [`SimulatedBus`].
    answers: Sender<CanFrame>,
    /// The id of those answers: `0x580` + the parameter service's node.
    answer_id: u16,
    rate: f64,
    /// Started at the run's first step.
    pacer: Option<live::Pacer>,
    /// SIGINT/SIGTERM: the number of the first one, 0 before.
    signal: std::sync::Arc<std::sync::atomic::AtomicUsize>,
}

/// What a live run did.
struct LiveEnd {
    report: live::LiveReport,
    pacing: live::PacingReport,
    interrupted: bool,
}

impl Live {
    /// Listens on `args.addr`, says where on stderr (and warns off loopback), and takes
    /// SIGINT/SIGTERM as "stop the run".
    /// The frames the server's clients send to the robot (their parameter requests) come on
    /// the receiver returned, for the run's host to send ([`crate::engine::run_live`]).
    fn start(args: LiveArgs, scenario: &Scenario) -> Result<(Self, Receiver<CanFrame>)> {
        let node = firmware::params::service_node(&scenario.config);
        let (requests, inbox) = mpsc::channel();
        let (answers, from_robot) = mpsc::channel();
        let port = SimulatedBus {
            requests,
            answers: from_robot,
        };
        let node_id = NodeId::new(node).context("the parameter service's node id")?;
        let link = mecanum_linux::SdoClient::new(port, node_id);
        let server = args
            .serve
            .serve(
                format!("hostsim run {}", scenario.name),
                Some(Box::new(link)),
            )?
            .context("--live: no address")?;
        if let Some(warning) = server.exposure_warning() {
            eprintln!("{warning}");
        }
        let signal = mecanum_linux::stop_on_signals()?;
        eprintln!(
            "{}, {}x real time; stop with Ctrl-C",
            server.banner(),
            args.rate
        );
        let live = Self {
            server,
            answers,
            answer_id: canopen::layout::SDO_RESPONSE.id + u16::from(node),
            rate: args.rate,
            pacer: None,
            signal,
        };
        Ok((live, inbox))
    }

    /// Serves what `log` writes, in batches every 50 ms of wall-clock time at most (also in
    /// slow motion).
    fn attach(&self, log: &mut McapLog) {
        log.set_tap(Box::new(self.server.tap()));
        let interval = live::FLUSH_INTERVAL.mul_f64(self.rate.min(1.0));
        log.set_flush_interval(interval.max(Duration::from_millis(5)));
    }

    /// After each step: hands the robot's answers among the frames it `sent` to the
    /// server, waits for the wall clock, and ends the run on a stop signal.
    fn step(&mut self, t_us: u64, sent: &[CanFrame]) -> ControlFlow<()> {
        for frame in sent
            .iter()
            .filter(|f| f.standard_id() == Some(self.answer_id))
        {
            // The server gone (the run ending): nobody to answer.
            let _ = self.answers.send(*frame);
        }
        let rate = self.rate;
        self.pacer
            .get_or_insert_with(|| live::Pacer::new(rate))
            .pace(t_us * 1000);
        if self.signal.load(Ordering::Relaxed) == 0 {
            ControlFlow::Continue(())
        } else {
            ControlFlow::Break(())
        }
    }

    fn finish(self) -> LiveEnd {
        LiveEnd {
            pacing: self
                .pacer
                .unwrap_or_else(|| live::Pacer::new(self.rate))
                .report(),
            interrupted: self.signal.load(Ordering::Relaxed) != 0,
            report: self.server.stop(),
        }
    }
}

/// The simulated bus as a live server's clients reach it: their requests go to the run's
/// host, which sends them at its next tick; the robot's answers come back from the steps.
struct SimulatedBus {
    requests: Sender<CanFrame>,
    answers: Receiver<CanFrame>,
}

impl mecanum_linux::FramePort for SimulatedBus {
    fn send(&mut self, frame: &CanFrame) -> std::io::Result<()> {
        self.requests
            .send(*frame)
            .map_err(|_| std::io::Error::other("the run has ended"))
    }

    fn recv_timeout(&mut self, timeout: Duration) -> std::io::Result<Option<CanFrame>> {
        match self.answers.recv_timeout(timeout) {
            Ok(frame) => Ok(Some(frame)),
            Err(RecvTimeoutError::Timeout) => Ok(None),
            Err(RecvTimeoutError::Disconnected) => Err(std::io::Error::other("the run has ended")),
        }
    }
}

impl LiveEnd {
    /// The live server's report with the pacing's figures.
    fn json(&self) -> serde_json::Value {
        let p = &self.pacing;
        let mut value = self.report.to_json();
        value["rate"] = p.rate.into();
        value["paced_steps"] = p.steps.into();
        value["late_mean_s"] = p.mean_late_s.into();
        value["late_p99_s"] = p.p99_late_s.into();
        value["late_max_s"] = p.max_late_s.into();
        value
    }
}

/// What `hostsim run` reports: the run's figures, printed as text or (`--json`) as one JSON
/// object. The text also gives the firmware's counters and gyro estimate and the files
/// written, which the JSON leaves out.
#[derive(Debug, Serialize)]
pub struct Report<'a> {
    /// Scenario name.
    scenario: &'a str,
    /// Simulated time, s.
    duration_s: f64,
    /// Wall-clock time of the run, s.
    wall_s: f64,
    /// Control steps run.
    steps: u64,
    /// Frames the firmware sent.
    tx_frames: u64,
    /// Frames the firmware received.
    rx_frames: u64,
    /// Frames on the bus.
    bus_frames: u64,
    /// Bus load over the run (0..1).
    bus_load: f64,
    /// Frames the bus dropped.
    dropped: u64,
    /// Frames the bus corrupted.
    corrupted: u64,
    /// Ground-truth pose `[x m, y m, heading rad]` at the last step.
    truth: [f64; 3],
    /// Final odometry pose, as `truth`.
    odometry: [f64; 3],
    /// Final position error of odometry against ground truth, m.
    final_position_error: f64,
    /// Largest position error during the run, m.
    max_position_error: f64,
    /// Final heading error, rad.
    final_heading_error: f64,
    /// The firmware's final state.
    state: &'static str,
    /// Its fault.
    fault: &'static str,
    /// State changes `(time s, state, fault)`.
    transitions: &'a [(f64, String, String)],
    /// Heading source changes `(time s, source)`.
    heading_changes: &'a [(f64, String)],
    /// The outbound stream hash, 16 hex digits.
    #[serde(serialize_with = "hex16")]
    tx_hash: u64,
    /// With `--live`: the server's and the pacing's figures.
    #[serde(skip_serializing_if = "Option::is_none")]
    live: Option<serde_json::Value>,
    /// With `--live`: whether Ctrl-C stopped the run.
    #[serde(skip_serializing_if = "Option::is_none")]
    interrupted: Option<bool>,
    /// The firmware's last snapshot (its counters and gyro estimate): text only.
    #[serde(skip)]
    last: &'a firmware::control::Snapshot,
    /// The log written: text only.
    #[serde(skip)]
    log: Option<&'a Path>,
    /// The plot drawn: text only.
    #[serde(skip)]
    plot: Option<&'a Path>,
}

fn hex16<S: serde::Serializer>(hash: &u64, s: S) -> Result<S::Ok, S::Error> {
    s.collect_str(&format_args!("{hash:016x}"))
}

impl<'a> Report<'a> {
    fn new(
        s: &'a RunSummary,
        wall_s: f64,
        live: Option<&LiveEnd>,
        log: Option<&'a Path>,
        plot: Option<&'a Path>,
    ) -> Self {
        Self {
            scenario: &s.scenario,
            duration_s: s.duration_s,
            wall_s,
            steps: s.steps,
            tx_frames: s.tx_frames,
            rx_frames: s.rx_frames,
            bus_frames: s.bus.frames,
            bus_load: s.bus_load,
            dropped: s.bus.dropped,
            corrupted: s.bus.corrupted,
            truth: s.truth,
            odometry: s.odometry,
            final_position_error: s.final_position_error,
            max_position_error: s.max_position_error,
            final_heading_error: s.final_heading_error,
            state: s.last.state.as_str(),
            fault: s.last.fault.as_str(),
            transitions: &s.transitions,
            heading_changes: &s.heading_changes,
            tx_hash: s.tx_hash,
            live: live.map(LiveEnd::json),
            interrupted: live.map(|l| l.interrupted),
            last: &s.last,
            log,
            plot,
        }
    }
}

impl std::fmt::Display for Report<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "scenario {:?}: {:.2} s simulated in {:.3} s ({:.0}x real time)",
            self.scenario,
            self.duration_s,
            self.wall_s,
            self.duration_s / self.wall_s.max(1e-9)
        )?;
        let (t, o) = (self.truth, self.odometry);
        writeln!(
            f,
            "ground truth  x {:+.4} m  y {:+.4} m  heading {:+.2}°",
            t[0],
            t[1],
            t[2].to_degrees()
        )?;
        writeln!(
            f,
            "odometry      x {:+.4} m  y {:+.4} m  heading {:+.2}°",
            o[0],
            o[1],
            o[2].to_degrees()
        )?;
        writeln!(
            f,
            "odometry drift: final {:.1} mm, max {:.1} mm, heading {:.2}°",
            self.final_position_error * 1000.0,
            self.max_position_error * 1000.0,
            self.final_heading_error.to_degrees()
        )?;
        writeln!(
            f,
            "bus: {} frames, load {:.1} %, {} dropped, {} corrupted; firmware sent {}, received {}",
            self.bus_frames,
            self.bus_load * 100.0,
            self.dropped,
            self.corrupted,
            self.tx_frames,
            self.rx_frames
        )?;
        let last = self.last;
        let e = last.rx_errors;
        writeln!(
            f,
            "firmware: final state {} (fault {}); rejected frames {}, unknown ids {}, repeated \
             twists {}",
            last.state,
            last.fault,
            e.total() - e.unknown_id,
            e.unknown_id,
            last.repeated_seq
        )?;
        for (t, state, fault) in self.transitions {
            writeln!(f, "  {t:8.3} s  {state} ({fault})")?;
        }
        if last.heading_source != firmware::protocol::robot::HeadingSource::Wheels {
            writeln!(
                f,
                "gyro heading: final source {}, bias estimate {:+.4} °/s from {} standstill \
                 samples; heading source changes:",
                last.heading_source,
                f64::from(last.gyro_bias).to_degrees(),
                last.gyro_bias_samples
            )?;
            for (t, source) in self.heading_changes {
                writeln!(f, "  {t:8.3} s  {source}")?;
            }
        }
        write!(f, "outbound stream hash {:016x}", self.tx_hash)?;
        if let Some(log) = self.log {
            write!(f, "\nlog:   {}", log.display())?;
        }
        if let Some(plot) = self.plot {
            write!(f, "\nplot:  {}", plot.display())?;
        }
        Ok(())
    }
}
