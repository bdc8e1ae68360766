//! `hostsim`: simulate the mecanum drive, replay and summarise its logs, compute kinematics.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use hostsim::log::McapLog;
use hostsim::plot::plot_run;
use hostsim::replay::{candump_text, replay_mcap};
use hostsim::scenario::Scenario;
use hostsim::sim::{LogOptions, RunSummary, run_metadata};
use indicatif::{ProgressBar, ProgressStyle};

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
    /// figure-eight, compass, watchdog.
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
        /// Do not write the MCAP log.
        #[arg(long)]
        no_log: bool,
        /// Do not draw the plot.
        #[arg(long)]
        no_plot: bool,
        /// Print the summary as JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Replay a log through a fresh firmware core and check the outbound frames are
    /// bit-identical; prints the first difference if not. Exit code 1 on a difference.
    Replay {
        /// A hostsim MCAP log.
        log: PathBuf,
    },
    /// Summarise a log: messages per topic, frames, the run's configuration.
    Summary {
        /// A hostsim MCAP log.
        log: PathBuf,
    },
    /// Kinematics calculator: JSON lines on stdin, one JSON line out per line.
    ///
    /// {"op":"inverse","lx":..,"ly":..,"r":..,"vx":..,"vy":..,"wz":..} gives
    /// {"fl":..,"fr":..,"rl":..,"rr":..} (rad/s); {"op":"forward",...,"fl":..,"fr":..,"rl":..,"rr":..}
    /// gives {"vx":..,"vy":..,"wz":..}. A bad line gives {"error":"..."} and the rest go on.
    Kin,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match dispatch(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
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
            no_log,
            no_plot,
            json,
        } => run(
            scenario.as_deref(),
            &out,
            config,
            seed,
            !no_log,
            !no_plot,
            json,
        ),
        Cmd::Replay { log } => replay(&log),
        Cmd::Summary { log } => summary(&log),
        Cmd::Kin => {
            let stdin = std::io::stdin();
            hostsim::kin::run(stdin.lock(), std::io::stdout().lock())
                .context("reading stdin / writing stdout")?;
            Ok(ExitCode::SUCCESS)
        }
    }
}

fn load_scenario(arg: Option<&str>) -> Result<Scenario> {
    let arg = arg.unwrap_or("square");
    let path = Path::new(arg);
    if path.extension().is_some_and(|e| e == "toml") || path.exists() {
        Ok(Scenario::from_file(path)?)
    } else {
        Ok(Scenario::builtin(arg)?)
    }
}

fn run(
    scenario: Option<&str>,
    out: &Path,
    config: Option<PathBuf>,
    seed: Option<u64>,
    write_log: bool,
    draw_plot: bool,
    json: bool,
) -> Result<ExitCode> {
    let mut scenario = load_scenario(scenario)?;
    if let Some(path) = config {
        scenario.config = firmware::Config::from_toml_file(&path)?;
    }
    if let Some(seed) = seed {
        scenario.seed = seed;
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
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
    let mut log = if write_log {
        Some(McapLog::create(&log_path, &run_metadata(&scenario))?)
    } else {
        None
    };
    let mut plant = hostsim::drives::SimDrives::new(&scenario.config)?;
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
        |t_us| bar.set_position(t_us / 1000),
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
        "firmware: final state {:?} (fault {:?}); rejected frames {}, unknown ids {}",
        s.last.state,
        s.last.fault,
        e.total() - e.unknown_id,
        e.unknown_id
    );
    for (t, state, fault) in &s.transitions {
        println!("  {t:8.3} s  {state} ({fault})");
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
        "state": format!("{:?}", s.last.state),
        "fault": format!("{:?}", s.last.fault),
        "transitions": s.transitions,
        "tx_hash": format!("{:016x}", s.tx_hash),
    })
    .to_string()
}

fn replay(path: &Path) -> Result<ExitCode> {
    let report = replay_mcap(path)?;
    if let Some(t) = &report.truncated {
        eprintln!("warning: log cut short: {t}; replaying what was complete");
    }
    println!(
        "replayed {} steps, fed {} inbound frames, compared {} outbound frames",
        report.steps, report.fed, report.compared
    );
    match &report.difference {
        None => {
            println!("outbound frames are bit-identical");
            Ok(ExitCode::SUCCESS)
        }
        Some(d) => {
            let show = |f: &Option<hostsim::replay::TimedFrame>| {
                f.map_or_else(
                    || "nothing".to_string(),
                    |f| {
                        format!(
                            "{} at {:.6} s",
                            candump_text(&f.frame),
                            f.t_ns as f64 * 1e-9
                        )
                    },
                )
            };
            println!(
                "first difference at outbound frame {} ({:.6} s): log has {}, replay sent {}",
                d.index,
                d.t_ns as f64 * 1e-9,
                show(&d.logged),
                show(&d.replayed)
            );
            Ok(ExitCode::from(1))
        }
    }
}

fn summary(path: &Path) -> Result<ExitCode> {
    let s = hostsim::summary::summarize(path).map_err(anyhow::Error::msg)?;
    if s.topics.is_empty() {
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
        let tag = if *level >= 4 { "FAULT" } else { "     " };
        println!("  {tag} {t:9.3} s  {text}");
    }
    for (topic, n) in &s.topics {
        println!("  {topic:24} {n:>9} messages");
    }
    if let Some(t) = &s.truncated {
        println!("cut short: {t}");
    }
    Ok(ExitCode::SUCCESS)
}
