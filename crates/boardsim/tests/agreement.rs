//! One engine, two firmware nodes: every built-in scenario on the flashed image (the DJI
//! example configuration, as the built-ins) makes the in-process core's state changes at the
//! same control steps, and ends with its odometry within 1 mm and 0.05° of the core's. The
//! image logs each change at the step that made it (`step N: state S fault F`).

use boardsim::run::Harness;
use hostsim::engine::LogOptions;
use hostsim::scenario::Scenario;

mod common;
use common::board_run;

fn agree(name: &str) {
    let scenario = Scenario::builtin(name).unwrap();
    let mut plant = hostsim::engine::plant_for(&scenario).unwrap();
    let core =
        hostsim::engine::run(&scenario, &mut plant, None, LogOptions::default(), |_| {}).unwrap();
    let board = board_run(&scenario, Harness::default());
    eprintln!("{name}: core  {:?}", core.transitions);
    eprintln!("{name}: board {:?}", board.state_changes);
    assert_eq!(
        board.state_changes, core.transitions,
        "{name}: state changes"
    );
    let (pose, t) = board.odometry.expect("odometry from the board");
    let [x, y, h] = core.odometry;
    let dxy = (pose[0] - x).hypot(pose[1] - y);
    let dh = (pose[2] - h).abs().to_degrees();
    eprintln!(
        "{name}: odometry at {t:.3} s: board ({:.5}, {:.5}, {:.5}), core ({x:.5}, {y:.5}, \
         {h:.5}): {:.3} mm, {dh:.4}°; truth board {:?}, core {:?}",
        pose[0],
        pose[1],
        pose[2],
        dxy * 1e3,
        board.truth,
        core.truth
    );
    assert!(dxy < 1e-3, "{name}: {} mm", dxy * 1e3);
    assert!(dh < 0.05, "{name}: {dh}°");
}

/// One test a built-in, so that the test harness runs them side by side.
macro_rules! builtins {
    ($($test:ident => $name:literal),* $(,)?) => {
        $(#[test]
        fn $test() {
            agree($name);
        })*

        #[test]
        fn every_builtin_is_here() {
            let mut here = [$($name),*];
            let mut all = Scenario::BUILTINS;
            here.sort_unstable();
            all.sort_unstable();
            assert_eq!(here, all);
        }
    };
}

builtins! {
    square => "square",
    circle => "circle",
    strafe => "strafe",
    spin => "spin",
    figure_eight => "figure-eight",
    compass => "compass",
    watchdog => "watchdog",
    calibration => "calibration",
}
