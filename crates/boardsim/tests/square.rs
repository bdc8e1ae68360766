//! The built-in square with the flashed image in place of the in-process core: the same state
//! changes, and the final odometry within 1 mm and 0.05° of the core's.

use boardsim::run::Harness;
use hostsim::drives::SimDrives;
use hostsim::scenario::Scenario;
use hostsim::sim::LogOptions;

mod common;
use common::board_run;

#[test]
fn the_square_on_the_board_matches_the_in_process_core() {
    let scenario = Scenario::builtin("square").unwrap();
    let mut plant = SimDrives::for_scenario(&scenario).unwrap();
    let core =
        hostsim::sim::run(&scenario, &mut plant, None, LogOptions::default(), |_| {}).unwrap();

    let run = board_run(&scenario, Harness::default());
    for l in &run.lines {
        eprintln!(
            "board {:.6} {} {}",
            l.at as f64 / boardsim::CPU_HZ as f64,
            l.level,
            l.text
        );
    }
    let core_states: Vec<(String, String)> = core
        .transitions
        .iter()
        .map(|(_, s, f)| (s.clone(), f.clone()))
        .collect();
    let board_states: Vec<(String, String)> = run
        .transitions
        .iter()
        .map(|(_, s, f)| (format!("{s:?}"), format!("{f:?}")))
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
