//! The built-in square with the flashed image in place of the in-process core, once with the
//! image built for `config/dji_m3508.toml` and once for `config/odrive.toml`: the image carries
//! that configuration (its id in the boot log and every `HEARTBEAT`), makes the same state
//! changes as the core with it, and ends with odometry within 1 mm and 0.05° of the core's.

use boardsim::run::Harness;
use hostsim::engine::LogOptions;
use hostsim::scenario::Scenario;

mod common;
use common::{board_run_on, elf_for, heartbeat_config_ids, print_lines};

#[test]
fn the_square_on_the_dji_image_matches_the_in_process_core() {
    square_on("dji_m3508");
}

#[test]
fn the_square_on_the_odrive_image_matches_the_in_process_core() {
    square_on("odrive");
}

fn square_on(config: &str) {
    let mut scenario = Scenario::builtin("square").unwrap();
    let file = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join(format!("../../config/{config}.toml"));
    scenario.config = firmware::Config::from_toml_file(&file).unwrap();
    let id = scenario.config.id();
    let mut plant = hostsim::engine::plant_for(&scenario).unwrap();
    let core =
        hostsim::engine::run(&scenario, &mut plant, None, LogOptions::default(), |_| {}).unwrap();

    let run = board_run_on(&elf_for(config), &scenario, Harness::default());
    print_lines(&run, "board ");
    let line = format!("drive configuration {config}.toml, id {id:#06x}");
    assert!(
        run.lines.iter().any(|l| l.text == line),
        "no boot line {line:?}: is the image built for config/{config}.toml?"
    );
    let ids = heartbeat_config_ids(&run);
    // One HEARTBEAT per STATUS period (10 Hz) from the first step on.
    assert!(
        ids.len() as f64 >= run.simulated_s * 10.0 - 1.0,
        "{} heartbeats in {} s",
        ids.len(),
        run.simulated_s
    );
    assert!(
        ids.iter().all(|&i| i == id),
        "HEARTBEAT.config_id {ids:?}, config {id:#06x}"
    );
    let core_states: Vec<(String, String)> = core
        .transitions
        .iter()
        .map(|(_, s, f)| (s.clone(), f.clone()))
        .collect();
    let board_states: Vec<(String, String)> = run
        .transitions
        .iter()
        .map(|(_, s, f)| (s.to_string(), f.to_string()))
        .collect();
    eprintln!("core  {:?}", core.transitions);
    eprintln!("board {:?}", run.transitions);
    // The board's first STATUS reports its initial state (the core's list starts at the first
    // change).
    assert_eq!(&board_states[1..], &core_states[..], "state changes");
    for ((tb, ..), (tc, ..)) in run.transitions[1..].iter().zip(&core.transitions) {
        // Seen at the next STATUS (10 Hz) after the core's change.
        assert!(
            (0.0..0.11).contains(&(tb - tc)),
            "core {tc} s, board {tb} s"
        );
    }
    eprintln!("truth: board {:?}, core {:?}", run.truth, core.truth);
    let (pose, t) = run.odometry.expect("odometry from the board");
    let [x, y, h] = core.odometry;
    let dx = ((pose[0] - x).powi(2) + (pose[1] - y).powi(2)).sqrt();
    let dh = (pose[2] - h).abs().to_degrees();
    eprintln!(
        "final odometry at {t:.3} s: board ({:.5}, {:.5}, {:.5}), core ({x:.5}, {y:.5}, {h:.5}): {:.3} mm, {dh:.4}°",
        pose[0],
        pose[1],
        pose[2],
        dx * 1e3
    );
    assert!(dx < 1e-3, "{} mm", dx * 1e3);
    assert!(dh < 0.05, "{dh}°");
    let s = run.board.stats();
    eprintln!(
        "{:.1} s simulated: {} instructions ({} per ms), {} exceptions, asleep {:.1} %",
        run.simulated_s,
        s.instructions,
        s.instructions as f64 / (run.simulated_s * 1e3),
        s.exceptions,
        100.0 * s.sleep_cycles as f64 / (run.simulated_s * boardsim::CPU_HZ as f64)
    );
}

/// The ODrive image with the DJI scenario: refused at its first HEARTBEAT, both ids named.
#[test]
fn an_image_built_for_another_configuration_is_refused() {
    use boardsim::run::RunError;
    let scenario = Scenario::builtin("square").unwrap();
    let e = common::try_board_run_on(&elf_for("odrive"), &scenario, Harness::default())
        .expect_err("refused");
    let (image, wanted) = (
        firmware::Config::odrive_example().id(),
        scenario.config.id(),
    );
    assert!(
        matches!(e, RunError::ConfigMismatch { image: i, scenario: s } if (i, s) == (image, wanted)),
        "{e}"
    );
    assert!(e.to_string().contains("MECANUM_CONFIG"), "{e}");
}
