//! Faults on the board: the flashed image against the in-process core in the same scenarios,
//! the drives silent, the host silent, an e-stop, a host stuck on one twist frame. The board
//! must make the core's state changes and, from the core's reaction on (its first state
//! change after the onset), stop the motors (an all-zero current command) within 2 ms of when
//! the core does: its loop runs on its own timer, started 0.95 ms after reset, and its frames
//! leave through its mailboxes. (Before the reaction the two may differ in a single step: a
//! command that rounds to zero in one loop's phase and not in the other's.)

use std::path::Path;

use boardsim::run::Harness;
use embedded_can::{Frame, Id, StandardId};
use hostsim::drives::SimDrives;
use hostsim::scenario::Scenario;
use hostsim::sim::{LogOptions, run_observed};

mod common;
use common::board_run;

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
    let mut plant = SimDrives::for_scenario(s).unwrap();
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
        .map(|(t, st, f)| (*t, format!("{st:?}"), format!("{f:?}")))
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
        ("Fault", "MotorStale"),
    );
}

#[test]
fn a_silent_host_trips_the_boards_watchdog() {
    let s = scenario("[[actions]]\nat_s = 0.5\nsilence = true\n");
    check("host silent", &s, 0.5, ("Disabled", "Watchdog"));
}

#[test]
fn an_estop_latches_on_the_board() {
    let s = scenario("[[actions]]\nat_s = 0.5\nestop = true\n");
    check("e-stop", &s, 0.5, ("Estop", "None"));
}

#[test]
fn a_host_stuck_on_one_twist_frame_is_stopped_by_the_board() {
    let s = scenario("[[faults]]\nkind = \"repeated_twist\"\nfrom_s = 0.5\nuntil_s = 1.2\n");
    check("stuck sender", &s, 0.5, ("Disabled", "Watchdog"));
}

#[test]
fn a_stalled_loop_is_reset_by_the_watchdog_and_the_robot_stays_disabled() {
    // Driving at 0.5 m/s; from 0.5 s the harness withholds the TIM2 interrupt: the loop
    // waits on its timer for ever, nothing feeds the independent watchdog (50 ms).
    let s = scenario("");
    let harness = Harness {
        stall_timer_at_ns: Some(500_000_000),
    };
    let run = board_run(&s, harness);
    for l in &run.lines {
        eprintln!(
            "{:.6} {} {}",
            l.at as f64 / boardsim::CPU_HZ as f64,
            l.level,
            l.text
        );
    }
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
        .map(|(t, s, f)| format!("{t:.3} {s:?} {f:?}"))
        .collect();
    eprintln!("{states:?}");
    let (t, state, fault) = *run.transitions.last().unwrap();
    assert!(t > reset, "{states:?}");
    assert_eq!(
        (format!("{state:?}"), format!("{fault:?}")),
        ("Disabled".into(), "None".into())
    );
}
