//! What the tests share: where the board image is, and a run of a scenario on it.

use std::path::PathBuf;

use boardsim::run::{BoardRun, Harness, run_scenario};
use boardsim::{Board, Image};
use hostsim::scenario::Scenario;
use hostsim::sim::LogOptions;

/// The board ELF: `BOARDSIM_ELF`, else the release build of `boards/stm32f407` (which
/// `scripts/test.sh` makes before the Rust tests).
pub fn elf() -> PathBuf {
    let path = std::env::var_os("BOARDSIM_ELF").map_or_else(
        || {
            PathBuf::from(env!("CARGO_MANIFEST_DIR"))
                .join("../../boards/stm32f407/target/thumbv7em-none-eabihf/release/board-stm32f407")
        },
        PathBuf::from,
    );
    assert!(
        path.exists(),
        "{}: no board image; build it with `cd boards/stm32f407 && cargo build --release` \
         (scripts/test.sh does) or set BOARDSIM_ELF",
        path.display()
    );
    path
}

/// `scenario` with the board image as the firmware node, no log.
pub fn board_run(scenario: &Scenario, harness: Harness) -> BoardRun {
    let board = Board::new(Image::read(&elf()).unwrap()).unwrap();
    run_scenario(
        scenario,
        board,
        None,
        LogOptions::default(),
        harness,
        |_| {},
    )
    .unwrap()
}
