//! Faults on the board: the flashed image against the in-process core in the same scenarios,
//! the drives silent, the host silent, an e-stop, a host stuck on one twist frame, a motor
//! mounted the other way round. The board must make the core's state changes and, from the
//! core's reaction on (its first state change after the onset), stop the motors (an all-zero
//! current command) within 2 ms of when the core does: its loop runs on its own timer and its
//! frames leave through its mailboxes. (Before the reaction the two may differ in a single
//! step: a command that rounds to zero in one loop's phase and not in the other's.)
//!
//! Then what only a board has: a stalled loop and its watchdog, a flood on the bus and an
//! overrun of its receive FIFO.

use std::path::Path;

use boardsim::lockstep::WireFault;
use boardsim::run::Harness;
use embedded_can::{Frame, Id, StandardId};
use firmware::control::Fault;
use firmware::protocol::robot::RobotState;
use hostsim::engine::{LogOptions, run_observed};
use hostsim::scenario::Scenario;

mod common;
use common::{board_run, print_lines};

/// The DJI current command of motors 1-4.
fn is_zero_current(frame: &firmware::CanFrame) -> bool {
    frame.id() == Id::Standard(StandardId::new(0x200).unwrap())
        && frame.data().iter().all(|&b| b == 0)
}

/// Enable at 0.05 s, 0.5 m/s forward from 0.1 s, then `rest` (TOML) from 0.5 s.
fn scenario(rest: &str) -> Scenario {
    let text = format!(
        "duration_s = 1.2\nseed = 5\n[[actions]]\nat_s = 0.05\nenable = true\n\
         [[actions]]\nat_s = 0.1\ntwist = [0.5, 0.0, 0.0]\n{rest}"
    );
    Scenario::from_toml(&text, Path::new("faults.toml")).unwrap()
}

/// What a run showed: its state changes (s, state, fault) and its first zero-current command.
type Seen = (Vec<(f64, String, String)>, Option<f64>);

/// The core's and the board's state changes, and the first all-zero current command of each
/// from the core's first state change at or after `onset_s` on, in s.
fn both(s: &Scenario, onset_s: f64) -> [Seen; 2] {
    let mut plant = hostsim::engine::plant_for(s).unwrap();
    let mut zeros = Vec::new();
    let core = run_observed(s, &mut plant, None, LogOptions::default(), |step| {
        if step.sent.iter().any(is_zero_current) {
            zeros.push(step.t_us as f64 * 1e-6);
        }
    })
    .unwrap();
    let reaction = core
        .transitions
        .iter()
        .map(|(t, ..)| *t)
        .find(|&t| t >= onset_s)
        .expect("the core reacts");
    let core_zero = zeros.into_iter().find(|&t| t >= reaction - 1e-9);
    let run = board_run(s, Harness::default());
    let board_zero = run
        .sent
        .iter()
        .map(|&(t, f)| (t as f64 * 1e-9, f))
        .find(|(t, f)| *t >= reaction - 2e-3 && is_zero_current(f))
        .map(|(t, _)| t);
    // The board's first STATUS reports its initial state; the core lists changes only.
    let board_states = run.transitions[1..]
        .iter()
        .map(|(t, st, f)| (*t, st.to_string(), f.to_string()))
        .collect();
    [(core.transitions, core_zero), (board_states, board_zero)]
}

fn check(name: &str, s: &Scenario, onset_s: f64, final_state: (&str, &str)) {
    let [(core, core_zero), (board, board_zero)] = both(s, onset_s);
    eprintln!("{name}: core {core:?}, zero current at {core_zero:?} s");
    eprintln!("{name}: board {board:?}, zero current at {board_zero:?} s");
    let states = |v: &[(f64, String, String)]| {
        v.iter()
            .map(|(_, s, f)| (s.clone(), f.clone()))
            .collect::<Vec<_>>()
    };
    assert_eq!(states(&board), states(&core), "{name}: state changes");
    let last = core.last().unwrap();
    assert_eq!((last.1.as_str(), last.2.as_str()), final_state, "{name}");
    for ((tb, ..), (tc, ..)) in board.iter().zip(&core) {
        // STATUS goes out at 10 Hz: the change shows at the next one.
        assert!(
            (0.0..0.11).contains(&(tb - tc)),
            "{name}: core {tc} s, board {tb} s"
        );
    }
    let (c, b) = (core_zero.unwrap(), board_zero.unwrap());
    eprintln!(
        "{name}: the board's zero currents {:+.3} ms from the core's",
        (b - c) * 1e3
    );
    assert!((b - c).abs() < 2e-3, "{name}: core {c} s, board {b} s");
}

#[test]
fn drives_silent_fault_the_board_as_the_core() {
    let offline: String = (0..4)
        .map(|w| {
            format!(
                "[[faults]]\nkind = \"motor_offline\"\nwheel = {w}\nfrom_s = 0.5\nuntil_s = 1.2\n"
            )
        })
        .collect();
    check(
        "drives silent",
        &scenario(&offline),
        0.5,
        ("FAULT", "MOTOR_STALE"),
    );
}

#[test]
fn a_silent_host_trips_the_boards_watchdog() {
    let s = scenario("[[actions]]\nat_s = 0.5\nsilence = true\n");
    check("host silent", &s, 0.5, ("DISABLED", "WATCHDOG"));
}

#[test]
fn an_estop_latches_on_the_board() {
    let s = scenario("[[actions]]\nat_s = 0.5\nestop = true\n");
    check("e-stop", &s, 0.5, ("ESTOP", "NONE"));
}

#[test]
fn a_host_stuck_on_one_twist_frame_is_stopped_by_the_board() {
    let s = scenario("[[faults]]\nkind = \"repeated_twist\"\nfrom_s = 0.5\nuntil_s = 1.2\n");
    check("stuck sender", &s, 0.5, ("DISABLED", "WATCHDOG"));
}

#[test]
fn a_stalled_loop_is_reset_by_the_watchdog_and_the_robot_stays_disabled() {
    // Driving at 0.5 m/s; from 0.5 s the harness withholds the TIM2 interrupt: the loop
    // waits on its timer for ever, nothing feeds the independent watchdog (50 ms).
    let s = scenario("");
    let harness = Harness {
        stall_timer_at_ns: Some(500_000_000),
        ..Harness::default()
    };
    let run = board_run(&s, harness);
    print_lines(&run, "");
    assert_eq!(run.board.stats().watchdog_resets, 1);
    let reset = run
        .lines
        .iter()
        .find(|l| l.text.contains("reset by the independent watchdog"))
        .map(|l| run.line_time_s(l))
        .expect("the rebooted image logs the watchdog reset");
    // The loop limps on for a while: frames arriving still wake it, and embassy's clock
    // reads TIM2's counter directly, so its ticker fires until the count of half-overflows,
    // which only the interrupt advances, makes time stand still (at most 65.5 ms). The
    // watchdog then resets the board 50 ms after the last step fed it (each step sends a
    // motor command), the reboot logging within 1 ms.
    let dji = |f: &firmware::CanFrame| f.id() == Id::Standard(StandardId::new(0x200).unwrap());
    let last_step = run
        .sent
        .iter()
        .rev()
        .find(|(t, f)| dji(f) && (*t as f64 * 1e-9) < reset)
        .map(|(t, _)| *t as f64 * 1e-9)
        .unwrap();
    eprintln!("last step's command at {last_step:.6} s, reset logged at {reset:.6} s");
    assert!(
        (0.049..0.0515).contains(&(reset - last_step)),
        "reset {:.3} ms after the last step",
        (reset - last_step) * 1e3
    );
    assert!(
        (0.5..0.5 + 0.066 + 0.0515).contains(&reset),
        "reset logged at {reset} s"
    );
    let after: Vec<&(u64, firmware::CanFrame)> = run
        .sent
        .iter()
        .filter(|(t, f)| dji(f) && *t as f64 * 1e-9 > reset)
        .collect();
    // The loop runs again at 1 kHz from the reboot to the end (1.2 s).
    let due = ((1.2 - reset) * 1e3) as usize;
    assert!(
        after.len() + 2 >= due,
        "{} motor commands after the reset, {due} due",
        after.len()
    );
    assert!(
        after.iter().all(|(_, f)| is_zero_current(f)),
        "a motor driven after the reset"
    );
    let states: Vec<String> = run
        .transitions
        .iter()
        .map(|(t, s, f)| format!("{t:.3} {s} {f}"))
        .collect();
    eprintln!("{states:?}");
    let (t, state, fault) = *run.transitions.last().unwrap();
    assert!(t > reset, "{states:?}");
    assert_eq!(
        (state.to_string(), fault.to_string()),
        ("DISABLED".into(), "NONE".into())
    );
}

#[test]
fn a_flipped_motor_faults_the_board_as_the_core() {
    // The front-right motor mounted the other way round: it fights the other three as soon
    // as the robot drives.
    let s = scenario("[plant]\nflip = [1]\n");
    check("flipped motor", &s, 0.1, ("FAULT", "WHEEL_FIGHT"));
}

/// The board's last once-a-second report: its counter `name` (`rx`, `overruns`, ...).
fn reported(run: &boardsim::run::BoardRun, name: &str) -> u64 {
    let line = run
        .lines
        .iter()
        .rev()
        .find(|l| l.text.starts_with("steps "))
        .expect("a report line");
    let key = format!(" {name} ");
    // The last occurrence: the legend before the counters names "motor stale" too.
    let at = line.text.rfind(&key).expect("the counter") + key.len();
    line.text[at..]
        .split(|c: char| !c.is_ascii_digit())
        .next()
        .and_then(|n| n.parse().ok())
        .expect("a number")
}

/// The board's odometry at the end, and how far it is from `other`'s, mm.
fn odometry_apart_mm(a: &boardsim::run::BoardRun, b: &boardsim::run::BoardRun) -> f64 {
    let ((p, _), (q, _)) = (a.odometry.unwrap(), b.odometry.unwrap());
    (p[0] - q[0]).hypot(p[1] - q[1]) * 1e3
}

/// A flood at the bus's full rate (8-byte frames of an unknown id, 0x7FF, filling every bit
/// the other nodes leave idle, from 0.3 s to 1.1 s): the board reads every frame (FIFO 0
/// never overruns), counts them as unknown, and drives on as without the flood.
#[test]
fn a_flood_at_the_full_bus_rate_is_read_and_the_robot_drives_on() {
    let s = scenario("");
    let quiet = board_run(&s, Harness::default());
    let flood = Harness {
        flood_ns: Some((300_000_000, 1_100_000_000)),
        ..Harness::default()
    };
    let run = board_run(&s, flood);
    let flooded = run.frames_received - quiet.frames_received;
    let apart = odometry_apart_mm(&run, &quiet);
    eprintln!(
        "flood: {flooded} more frames to the board; overruns {:?} (model), {} (board's report); rx {} (report); odometry {apart:.3} mm from the quiet run's",
        run.board.can1().overruns,
        reported(&run, "overruns"),
        reported(&run, "rx"),
    );
    // The drives and the board take some 65 % of the bus (five 8-byte frames a
    // millisecond); the flood fills the rest: 0.8 s x 35 % / 126 µs, some 2,200 frames, and
    // its backlog after 1.1 s (measured: 2,671).
    assert!(flooded > 2_000, "{flooded} frames");
    assert_eq!(run.board.can1().overruns, [0, 0]);
    assert_eq!(reported(&run, "overruns"), 0);
    let states = |r: &boardsim::run::BoardRun| {
        r.transitions
            .iter()
            .map(|&(_, s, f)| (s, f))
            .collect::<Vec<_>>()
    };
    assert_eq!(states(&run), states(&quiet));
    assert!(apart < 1.0, "{apart} mm");
}

/// The same flood with the board's RX interrupt withheld for 2 ms (a CPU busy elsewhere):
/// FIFO 0 overruns, the board counts it, and it is not fatal: no fault, the robot drives on.
#[test]
fn a_fifo_overrun_is_counted_and_not_fatal() {
    let s = scenario("");
    let quiet = board_run(&s, Harness::default());
    let run = board_run(
        &s,
        Harness {
            flood_ns: Some((300_000_000, 1_100_000_000)),
            hold_can_rx_ns: Some((600_000_000, 602_000_000)),
            ..Harness::default()
        },
    );
    let apart = odometry_apart_mm(&run, &quiet);
    eprintln!(
        "RX held 2 ms in the flood: overruns {:?} (model), {} (board's report); states {:?}; odometry {apart:.3} mm from the quiet run's",
        run.board.can1().overruns,
        reported(&run, "overruns"),
        run.transitions
    );
    assert!(run.board.can1().overruns[0] >= 1);
    // The hardware keeps one flag: the board counts at least one overrun for each time it
    // found the flag set (each of its reads clears it).
    assert!((1..=run.board.can1().overruns[0]).contains(&reported(&run, "overruns")));
    assert!(
        run.transitions
            .iter()
            .all(|&(_, _, f)| f == firmware::control::Fault::None),
        "{:?}",
        run.transitions
    );
    assert_eq!(
        run.transitions.last().map(|&(_, s, _)| s),
        Some(firmware::protocol::robot::RobotState::Enabled)
    );
    assert!(apart < 1.0, "{apart} mm");
}

/// A fault on the board's wire from 0.5 s to 0.7 s while driving; the host goes on sending
/// its twist, then resets at 0.9 s and enables at 0.95 s. The board must: fault (its drives
/// silent to it) and send no motor command from before the outage once the bus is back,
/// recover on its own (ABOM after a bus-off), report the fault at its first STATUS after the
/// outage, hold the motors at zero current until the host's reset and enable, and drive again
/// after them. Returns the run and the bus time of the first non-zero current after 0.7 s.
fn wire_fault(fault: WireFault) -> (boardsim::run::BoardRun, f64) {
    let s = scenario(
        "[[actions]]\nat_s = 0.9\nreset = true\n[[actions]]\nat_s = 0.95\nenable = true\n\
         [[actions]]\nat_s = 0.96\ntwist = [0.5, 0.0, 0.0]\n",
    );
    let run = board_run(
        &s,
        Harness {
            wire_fault_ns: Some((fault, 500_000_000, 700_000_000)),
            ..Harness::default()
        },
    );
    for l in run.lines.iter().filter(|l| l.level != "info") {
        eprintln!("{:.6} {} {}", run.line_time_s(l), l.level, l.text);
    }
    let commands: Vec<(f64, bool)> = run
        .sent
        .iter()
        .filter(|(_, f)| is_dji(f))
        .map(|&(t, f)| (t as f64 * 1e-9, is_zero_current(&f)))
        .collect();
    let back = commands
        .iter()
        .find(|(t, _)| *t >= 0.7)
        .expect("commands after");
    let driven = commands
        .iter()
        .find(|(t, zero)| *t >= 0.7 && !zero)
        .map(|(t, _)| *t)
        .expect("driven again");
    let can = run.board.can1();
    eprintln!(
        "{fault:?}: states {:?}; first motor command after the outage at {:.6} s (zero: {}), first non-zero at {driven:.6} s; highest TEC {}, bus-offs {}, TEC/REC at the end {:?}; stale frames dropped {}",
        run.transitions,
        back.0,
        back.1,
        can.max_tec,
        can.bus_offs,
        can.error_counters(),
        reported(&run, "stale")
    );
    let states: Vec<_> = run.transitions.iter().map(|&(_, s, f)| (s, f)).collect();
    assert_eq!(
        states,
        [
            (RobotState::Disabled, Fault::None),
            (RobotState::Enabled, Fault::None),
            (RobotState::Fault, Fault::MotorStale),
            (RobotState::Enabled, Fault::None),
        ],
        "{fault:?}"
    );
    // The fault is on the bus with the board's first STATUS after the outage.
    let faulted = run.transitions[2].0;
    assert!(
        (0.7..0.71).contains(&faulted),
        "{fault:?}: FAULT seen at {faulted} s"
    );
    // Zero current from the first command after the outage until the enable (0.95 s, its
    // command delivered some 0.13 ms later and applied at the next step).
    assert!(
        back.1,
        "{fault:?}: a motor command from before the outage at {} s",
        back.0
    );
    assert!(
        (0.95..0.953).contains(&driven),
        "{fault:?}: driven at {driven} s"
    );
    assert_eq!(can.error_counters().0, 0, "{fault:?}: TEC after recovery");
    assert!(reported(&run, "stale") > 0);
    (run, driven)
}

fn is_dji(frame: &firmware::CanFrame) -> bool {
    frame.id() == Id::Standard(StandardId::new(0x200).unwrap())
}

#[test]
fn unplugged_the_board_is_error_passive_faults_and_stays_stopped_until_reset_and_enable() {
    let (run, _) = wire_fault(WireFault::NoAck);
    // ACK errors take an error-passive sender no further (ISO 11898-1): never bus-off.
    let can = run.board.can1();
    assert_eq!((can.max_tec, can.bus_offs), (128, 0));
}

#[test]
fn a_corrupted_bus_puts_the_board_bus_off_it_recovers_and_stays_stopped_until_reset_and_enable() {
    let (run, _) = wire_fault(WireFault::BitErrors);
    // Bit errors: 8 a frame, bus-off at the 32nd; ABOM recovers after 128 x 11 recessive bits
    // (1.4 ms) and the errors go on: bus-off again and again through the outage.
    let can = run.board.can1();
    assert_eq!(can.max_tec, 255);
    assert!(can.bus_offs >= 2, "{} bus-offs", can.bus_offs);
}
