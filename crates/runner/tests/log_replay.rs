//! The runner's loop with its log on, against a bus and a clock in memory (late wake-ups, an
//! overrun), then `hostsim`'s replay of that log: bit-identical outbound frames.

use std::collections::VecDeque;

use firmware::protocol::robot::Command;
use firmware::{CanFrame, Config, Controller};

mod common;
use common::{T0, bus, clock, enable_at, esc_feedback, run_for, std_frame, twists};
use mecanum_runner::McapRecorder;

/// 600 ms: the four ESCs report every millisecond (wheels turning); the host enables at
/// 10 ms, drives from 20 ms to 300 ms, then falls silent (the watchdog stops the robot); a
/// TWIST_CMD of the wrong length at 350 ms; an e-stop at 450 ms.
fn session() -> VecDeque<(u64, CanFrame)> {
    let mut frames = esc_feedback(0..600);
    frames.push(enable_at(10));
    frames.extend(twists(20..300));
    frames.push((T0 + 350_000, std_frame(0x301, &[1, 2, 3])));
    frames.push((T0 + 450_000, Command::Estop.to_can_frame()));
    frames.sort_by_key(|f| f.0);
    frames.into()
}

#[test]
fn a_runner_log_replays_bit_for_bit_at_its_recorded_steps() {
    let config = Config::dji_m3508_example();
    let path = std::path::PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("runner_log.mcap");
    // Wake-ups late by 0 to 290 µs, and one 2.5 ms overrun at step 200 (re-anchored).
    let clock = clock(
        (0..600u64).map(|k| if k == 200 { 2500 } else { (k * 53) % 300 }),
        0,
    );
    let mut bus = bus(&clock, session());
    let mut recorder = McapRecorder::create(&path, &Controller::new(&config).unwrap()).unwrap();
    let report = run_for(&config, &clock, &mut bus, 600_000, &mut recorder);
    assert_eq!(report.overruns, 1);
    assert_eq!(report.node.controller.state_at_stop, "ESTOP");
    assert_eq!(report.node.controller.rx_errors.wrong_dlc, 1);
    assert_eq!(recorder.dropped(), 0);
    recorder.finish().unwrap();

    // What the log holds: every frame, every step and the shutdown, off the period grid.
    let content = hostsim::replay::read_log(&path).unwrap();
    assert!(content.read.is_complete());
    assert_eq!(content.program.as_deref(), Some("mecanum-runner"));
    assert_eq!(content.rx.len() as u64, report.frames_received);
    assert_eq!(content.tx.len(), bus.sent.len());
    assert_eq!(content.steps.len() as u64, report.steps + 1);
    assert!(content.steps.last().unwrap().shutdown);
    let off_grid = content
        .steps
        .iter()
        .filter(|s| s.t_ns % 1_000_000 != 0)
        .count();
    assert!(off_grid > 400, "{off_grid} steps off the grid");
    let rosout = content.topics.get("/rosout").copied().unwrap_or(0);
    // Disabled, Enabled, the watchdog's stop, Estop (and the shutdown's state, unchanged).
    assert!(rosout >= 4, "{rosout} state changes");
    assert_eq!(content.topics["/odom"], report.steps.div_ceil(10) + 1);

    // Replay at the recorded steps: bit-identical, every frame compared.
    let replay = hostsim::replay::replay_mcap(&path).unwrap();
    assert!(replay.identical(), "{:?}", replay.difference);
    assert_eq!(replay.compared, bus.sent.len());
    assert_eq!(replay.fed as u64, report.frames_received);
    assert_eq!(replay.steps, report.steps + 1);

    // On the simulator's grid instead, the same frames do not replay: the step times matter.
    let (rx, tx, steps) = hostsim::replay::complete_part(&content);
    let grid = hostsim::replay::replay_frames(&config, &rx, &tx).unwrap();
    assert!(!grid.identical());

    // A what-if steps at the recorded steps too: the logged configuration changes nothing,
    // a doubled velocity gain changes only the current commands.
    use hostsim::replay::whatif::what_if_frames;
    let same = what_if_frames(&config, &config, &rx, &tx, &steps).unwrap();
    assert!(same.identical, "{:?}", same.first_difference);
    assert_eq!(same.steps, report.steps + 1);
    let mut stiffer = config;
    stiffer.gains.kp *= 2.0;
    let r = what_if_frames(&config, &stiffer, &rx, &tx, &steps).unwrap();
    assert_eq!(
        (r.steps, r.what_if_frames),
        (report.steps + 1, r.logged_frames)
    );
    let first = r.first_difference.as_ref().unwrap();
    assert!(
        first.what_if.as_ref().unwrap().frame.starts_with("200#"),
        "{first:?}"
    );
    for c in &r.by_id {
        assert_eq!(c.differ() > 0, c.id == "0x200", "{c:?}");
    }
}
