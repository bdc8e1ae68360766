//! What the tests share: where the board images are, and a run of a scenario on one.
// Each test binary uses a part of these helpers.
#![allow(dead_code)]

use std::path::PathBuf;

use boardsim::run::{BoardRun, Harness, RunError, run_scenario};
use boardsim::{Board, Image};
use firmware::protocol::robot::Telemetry;
use hostsim::engine::LogOptions;
use hostsim::scenario::Scenario;

/// The release image of `boards/stm32f407` built for `config/<config>.toml`, as
/// `scripts/test.sh` builds them before the Rust tests: `board-stm32f407` for the default
/// (`dji_m3508`; `BOARDSIM_ELF` overrides it), `board-stm32f407-<config>` for the others.
pub fn elf_for(config: &str) -> PathBuf {
    let release = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../boards/stm32f407/target/thumbv7em-none-eabihf/release");
    let path = match (config, std::env::var_os("BOARDSIM_ELF")) {
        ("dji_m3508", Some(path)) => PathBuf::from(path),
        ("dji_m3508", None) => release.join("board-stm32f407"),
        (other, _) => release.join(format!("board-stm32f407-{other}")),
    };
    assert!(
        path.exists(),
        "{}: no board image for config/{config}.toml; build it with `cd boards/stm32f407 && \
         MECANUM_CONFIG=../../config/{config}.toml cargo build --release` (scripts/test.sh \
         builds both the dji_m3508 and the odrive image)",
        path.display()
    );
    path
}

/// The default image (`config/dji_m3508.toml`).
pub fn elf() -> PathBuf {
    elf_for("dji_m3508")
}

/// `scenario` with the default board image as the firmware node, no log.
pub fn board_run(scenario: &Scenario, harness: Harness) -> BoardRun {
    board_run_on(&elf(), scenario, harness)
}

/// `scenario` with the board image `elf` as the firmware node, no log.
pub fn board_run_on(elf: &std::path::Path, scenario: &Scenario, harness: Harness) -> BoardRun {
    try_board_run_on(elf, scenario, harness).unwrap()
}

/// [`board_run_on`], its error returned.
pub fn try_board_run_on(
    elf: &std::path::Path,
    scenario: &Scenario,
    harness: Harness,
) -> Result<BoardRun, RunError> {
    let board = Board::new(Image::read(elf).unwrap()).unwrap();
    run_board(board, scenario, harness)
}

/// `scenario` with `board` (a board on a flash image of its own, say) as the firmware node, no
/// log.
pub fn run_board(
    board: Board,
    scenario: &Scenario,
    harness: Harness,
) -> Result<BoardRun, RunError> {
    run_scenario(
        scenario,
        board,
        None,
        LogOptions::default(),
        harness,
        |_| {},
    )
}

/// Prints the board's log lines, each after `prefix` and its time in seconds (shown when a
/// test fails).
pub fn print_lines(run: &BoardRun, prefix: &str) {
    for l in &run.lines {
        let t = l.at as f64 / boardsim::CPU_HZ as f64;
        eprintln!("{prefix}{t:.6} {} {}", l.level, l.text);
    }
}

/// The `config_id` of every `HEARTBEAT` the board sent.
pub fn heartbeat_config_ids(run: &BoardRun) -> Vec<u16> {
    run.sent
        .iter()
        .filter_map(|(_, f)| match Telemetry::decode(f) {
            Ok(Telemetry::Heartbeat(h)) => Some(h.config_id),
            _ => None,
        })
        .collect()
}
