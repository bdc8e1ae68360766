//! `hostsim`: simulate the mecanum drive, replay and summarise its logs, compute kinematics.
//! This file parses the command line and dispatches; the command line is the library's
//! `hostsim::cmd` (one module per subcommand), where the fuzz target `hostsim_args` reaches it.

use std::process::ExitCode;

use clap::Parser;
use hostsim::cmd::{Cli, EXIT_ERROR, SIGPIPE_STATUS};

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
    match cli.command.execute() {
        Ok(code) => code,
        Err(e) => {
            // Each cause once: most errors here already include their source's text.
            eprintln!("error: {}", mecanum_linux::error_line(e.as_ref()));
            ExitCode::from(EXIT_ERROR)
        }
    }
}
