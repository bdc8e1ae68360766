//! `boardsim`: the flashed board image under emulation. See the crate's README.

use std::path::PathBuf;

use anyhow::Context as _;
use clap::{Parser, Subcommand};

use boardsim::rtt::LogLine;
use boardsim::run::{Harness, run_scenario};
use boardsim::{Board, CPU_HZ, Image};
use hostsim::engine::LogOptions;
use hostsim::scenario::Scenario;

/// The STM32F407 board image, exactly as flashed, on the simulated robot's CAN bus.
#[derive(Parser, Debug)]
#[command(version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Runs a scenario with the image as the firmware node: hostsim's host, drives, plant and
    /// bus faults, the board in their virtual time. Writes `<out>/<name>.mcap` (hostsim's
    /// channels, the board's odometry and state as its frames report them, its log lines on
    /// /rosout) and `<out>/<name>.png`, and prints a summary.
    ///
    /// SCENARIO is a scenario TOML file or a built-in (square, circle, strafe, spin,
    /// figure-eight, compass, watchdog, calibration), as for `hostsim run`.
    Run {
        /// A scenario TOML file, or the name of a built-in.
        #[arg(default_value = "square")]
        scenario: String,
        /// The board ELF, as `cargo build --release` in boards/stm32f407 makes it.
        #[arg(long)]
        elf: PathBuf,
        /// The drive configuration the image was built with (the simulated drives follow it;
        /// default: the scenario's).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Output folder for `<name>.mcap` and `<name>.png`.
        #[arg(long, default_value = "out")]
        out: PathBuf,
        /// Do not write the MCAP log.
        #[arg(long)]
        no_log: bool,
        /// Do not draw the plot.
        #[arg(long)]
        no_plot: bool,
        /// Print the summary as JSON on stdout.
        #[arg(long)]
        json: bool,
    },
    /// Boots the image with the example robot's four C620 ESCs on the bus, prints the
    /// board's log and what the board and the bus did.
    Boot {
        /// The board ELF (`boards/stm32f407/target/thumbv7em-none-eabihf/release/board-stm32f407`).
        #[arg(long)]
        elf: PathBuf,
        /// Simulated seconds.
        #[arg(long, default_value_t = 2.0)]
        seconds: f64,
    },
}

fn main() -> std::process::ExitCode {
    let result = match Cli::parse().command {
        Command::Boot { elf, seconds } => boot(&elf, seconds),
        Command::Run {
            scenario,
            elf,
            config,
            out,
            no_log,
            no_plot,
            json,
        } => run(
            &scenario,
            &elf,
            config.as_deref(),
            &out,
            !no_log,
            !no_plot,
            json,
        ),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            // One line, as the other programs print an error (no backtrace for bad input).
            eprintln!("boardsim: error: {}", mecanum_linux::error_line(e.as_ref()));
            std::process::ExitCode::from(2)
        }
    }
}

fn boot(elf: &std::path::Path, seconds: f64) -> anyhow::Result<()> {
    if !(seconds.is_finite() && seconds > 0.0) {
        anyhow::bail!("--seconds {seconds}: must be a positive number of seconds");
    }
    // A scenario of nothing but time: the example robot's drives answer, no host acts.
    let scenario = Scenario::from_toml(
        &format!("duration_s = {seconds}"),
        std::path::Path::new("boot.toml"),
    )?;
    let board = Board::new(Image::read(elf)?).context("setting up the board")?;
    let wall = std::time::Instant::now();
    let result = run_scenario(
        &scenario,
        board,
        None,
        LogOptions::default(),
        Harness::default(),
        |_| {},
    );
    let wall = wall.elapsed().as_secs_f64();
    let run = match result {
        Ok(run) => run,
        Err(e) => {
            print_lines(e.lines());
            return Err(e.into());
        }
    };
    print_lines(&run.lines);
    for u in run.board.unknown_registers() {
        eprintln!("boardsim: {u}");
    }
    let s = run.board.stats();
    eprintln!(
        "boardsim: {:.3} s simulated in {wall:.3} s ({:.2}x real time); {} instructions, {} slices, {} exceptions, {} MMIO accesses, asleep {:.1} %; {} frames from the board, {} to it",
        run.simulated_s,
        run.simulated_s / wall,
        s.instructions,
        s.slices,
        s.exceptions,
        s.mmio,
        100.0 * s.sleep_cycles as f64 / (run.simulated_s * CPU_HZ as f64),
        run.sent.len(),
        run.frames_received,
    );
    Ok(())
}

/// The board's log lines on stdout, stamped with their simulated time.
fn print_lines(lines: &[LogLine]) {
    for line in lines {
        println!(
            "{:10.6} {:5} {}",
            line.at as f64 / CPU_HZ as f64,
            line.level,
            line.text
        );
    }
}

fn run(
    scenario: &str,
    elf: &std::path::Path,
    config: Option<&std::path::Path>,
    out: &std::path::Path,
    log: bool,
    plot: bool,
    json: bool,
) -> anyhow::Result<()> {
    let config = config
        .map(firmware::Config::from_toml_file)
        .transpose()
        .context("--config")?;
    let scenario = Scenario::load(scenario, config)?;
    let image = Image::read(elf)?;
    std::fs::create_dir_all(out).with_context(|| format!("--out {}", out.display()))?;
    // The scenario's name, made a file name that stays in `out`.
    let stem = drivelog::file_stem(&scenario.name);
    let log_path = out.join(format!("{stem}.mcap"));
    let mut mcap = if log {
        Some(drivelog::McapLog::create(
            &log_path,
            &boardsim::run::run_metadata(&scenario, &image),
        )?)
    } else {
        None
    };
    let board = Board::new(image).context("setting up the board")?;
    let wall = std::time::Instant::now();
    let duration = scenario.duration_us() as f64 * 1e-6;
    let result = run_scenario(
        &scenario,
        board,
        mcap.as_mut(),
        LogOptions::default(),
        Harness::default(),
        |t_us| {
            if !json && t_us % 1_000_000 == 0 && t_us > 0 {
                eprint!(
                    "\rboardsim: {:.0} of {duration:.0} s simulated",
                    t_us as f64 * 1e-6
                );
            }
        },
    );
    if !json {
        eprintln!();
    }
    let run = match result {
        Ok(run) => run,
        Err(e) => {
            if !json {
                print_lines(e.lines());
            }
            // The log stays a `.part`: the last good one is as it was.
            let partial = mcap
                .as_ref()
                .and_then(|l| l.part())
                .map(|p| p.display().to_string());
            let err = anyhow::Error::from(e);
            return Err(match partial {
                Some(part) => err.context(format!("the run failed; what it logged is in {part}")),
                None => err,
            });
        }
    };
    if let Some(l) = mcap {
        l.finish()?;
    }
    let wall = wall.elapsed().as_secs_f64();
    if plot && !run.track.is_empty() {
        let png = out.join(format!("{stem}.png"));
        hostsim::analysis::plot::plot_run(
            &png,
            &format!("{} (board image)", scenario.name),
            &run.track,
        )
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    if json {
        println!("{:#}", json_summary(&scenario.name, elf, &run, wall));
        return Ok(());
    }
    print_summary(&scenario.name, elf, &run, wall);
    if log {
        println!("log {}", log_path.display());
    }
    Ok(())
}

/// What `run --json` prints: the run's figures and the board's log.
fn json_summary(
    name: &str,
    elf: &std::path::Path,
    run: &boardsim::run::BoardRun,
    wall: f64,
) -> serde_json::Value {
    let s = run.board.stats();
    let (odometry, error) = (run.odometry.map(|(p, _)| p), odometry_error(run));
    serde_json::json!({
        "scenario": name,
        "elf": elf.display().to_string(),
        "simulated_s": run.simulated_s,
        "wall_s": wall,
        "real_time_factor": run.simulated_s / wall,
        "transitions": run.state_changes.iter().map(|(t, st, f)| serde_json::json!({"t": t, "state": st, "fault": f})).collect::<Vec<_>>(),
        "odometry": odometry,
        "truth": run.truth,
        "final_position_error": error.map(|e| e.0),
        "frames_sent": run.sent.len(),
        "frames_received": run.frames_received,
        "instructions": s.instructions,
        "instructions_per_ms": s.instructions as f64 / (run.simulated_s * 1e3),
        "exceptions": s.exceptions,
        "board_log": run.lines.iter().map(|l| format!("{:.6} {} {}", l.at as f64 / CPU_HZ as f64, l.level, l.text)).collect::<Vec<_>>(),
    })
}

/// What `run` prints: the state changes, the odometry against the truth, the board's figures.
fn print_summary(name: &str, elf: &std::path::Path, run: &boardsim::run::BoardRun, wall: f64) {
    let s = run.board.stats();
    let (odometry, error) = (run.odometry.map(|(p, _)| p), odometry_error(run));
    println!("scenario {} on the board image {}", name, elf.display());
    for (t, st, f) in &run.state_changes {
        println!("  {t:8.3} s  state {st}, fault {f}");
    }
    if let (Some(p), Some((dxy, dh))) = (odometry, error) {
        println!(
            "odometry ({:.4}, {:.4}, {:.4}), truth ({:.4}, {:.4}, {:.4}): {:.1} mm, {:.3} deg off",
            p[0],
            p[1],
            p[2],
            run.truth[0],
            run.truth[1],
            run.truth[2],
            dxy * 1e3,
            dh.to_degrees()
        );
    }
    println!(
        "frames: {} from the board, {} to it; {} instructions ({:.0} per ms), {} exceptions",
        run.sent.len(),
        run.frames_received,
        s.instructions,
        s.instructions as f64 / (run.simulated_s * 1e3),
        s.exceptions
    );
    println!(
        "{:.3} s simulated in {wall:.3} s ({:.2}x real time)",
        run.simulated_s,
        run.simulated_s / wall
    );
}

/// The board's last odometry against the ground truth: position (m) and heading (rad) off.
fn odometry_error(run: &boardsim::run::BoardRun) -> Option<(f64, f64)> {
    run.odometry.map(|(p, _)| {
        (
            (p[0] - run.truth[0]).hypot(p[1] - run.truth[1]),
            p[2] - run.truth[2],
        )
    })
}
