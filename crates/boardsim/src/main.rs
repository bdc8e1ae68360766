//! `boardsim`: the flashed board image under emulation. See the crate's README.

use std::path::PathBuf;

use anyhow::Context as _;
use clap::{Parser, Subcommand};

use boardsim::lockstep::{Lockstep, run_with_drives};
use boardsim::{Board, CPU_HZ, Image};
use hostsim::bus::{Bus, Node};
use hostsim::drives::SimDrives;

/// The STM32F407 board image, exactly as flashed, on the simulated robot's CAN bus.
#[derive(Parser, Debug)]
#[command(version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
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

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Command::Boot { elf, seconds } => boot(&elf, seconds),
    }
}

fn boot(elf: &std::path::Path, seconds: f64) -> anyhow::Result<()> {
    if !(seconds.is_finite() && seconds > 0.0) {
        anyhow::bail!("--seconds {seconds}: must be a positive number of seconds");
    }
    let image = Image::read(elf)?;
    let board = Board::new(image).context("setting up the board")?;
    let config = firmware::Config::dji_m3508_example();
    let mut drives = SimDrives::new(&config).map_err(|e| anyhow::anyhow!("{e}"))?;
    let mut ls = Lockstep::new(board, Bus::new(1_000_000, Vec::new(), 0));
    let wall = std::time::Instant::now();
    let until_ns = (seconds * 1e9) as u64;
    let result = run_with_drives(&mut ls, &mut drives, until_ns, 100_000);
    for line in ls.board.take_lines() {
        println!(
            "{:10.6} {:5} {}",
            line.at as f64 / CPU_HZ as f64,
            line.level,
            line.text
        );
    }
    for u in ls.board.unknown_registers() {
        eprintln!("boardsim: {u}");
    }
    let s = ls.board.stats();
    let wall = wall.elapsed().as_secs_f64();
    let from_board = ls
        .completed
        .iter()
        .filter(|t| t.from == Node::Controller)
        .count();
    eprintln!(
        "boardsim: {:.3} s simulated in {wall:.3} s ({:.2}x real time); {} instructions, {} slices, {} exceptions, {} MMIO accesses, asleep {:.1} %; {} frames from the board, {} in all",
        ls.board.now() as f64 / CPU_HZ as f64,
        ls.board.now() as f64 / CPU_HZ as f64 / wall,
        s.instructions,
        s.slices,
        s.exceptions,
        s.mmio,
        100.0 * s.sleep_cycles as f64 / ls.board.now().max(1) as f64,
        from_board,
        ls.completed.len(),
    );
    result.map_err(|e| anyhow::anyhow!("the board stopped: {e}"))
}
