//! `hostsim`: simulate the mecanum drive, replay and summarise its logs, compute kinematics.
//! This file parses the command line and dispatches; each subcommand is a module of `cmd`.

mod cmd;

use std::process::ExitCode;

use clap::{Parser, Subcommand};

use crate::cmd::{EXIT_ERROR, SIGPIPE_STATUS};

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
    Run(cmd::run::Args),
    Replay(cmd::replay::Args),
    Plant(cmd::plant::Args),
    Check(cmd::check::Args),
    Sweep(cmd::sweep::Args),
    Summary(cmd::summary::Args),
    Calibrate(cmd::calibrate::Args),
    Plot(cmd::plot::Args),
    Kin(cmd::kin::Args),
}

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
    let result = match &cli.command {
        Cmd::Run(a) => cmd::run::execute(a),
        Cmd::Replay(a) => cmd::replay::execute(a),
        Cmd::Plant(a) => cmd::plant::execute(a),
        Cmd::Check(a) => cmd::check::execute(a),
        Cmd::Sweep(a) => cmd::sweep::execute(a),
        Cmd::Summary(a) => cmd::summary::execute(a),
        Cmd::Calibrate(a) => cmd::calibrate::execute(a),
        Cmd::Plot(a) => cmd::plot::execute(a),
        Cmd::Kin(a) => cmd::kin::execute(a),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            // Each cause once: most errors here already include their source's text.
            eprintln!("error: {}", mecanum_linux::error_line(e.as_ref()));
            ExitCode::from(EXIT_ERROR)
        }
    }
}
