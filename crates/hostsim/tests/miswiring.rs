//! A miswired robot is caught, not driven: every single motor flip (4) and every drive-id
//! transposition (6) of the DJI example, and the ODrive example's, in lockstep with the real
//! firmware core.
//!
//! - Driving: the firmware's `WheelRunaway` fault stops the robot within its window, before
//!   the robot has moved 5 cm the wrong way, for every miswiring a wheel encoder can see.
//! - The bring-up check (on blocks, [`hostsim::analysis::bringup`]) names each miswiring and prints the
//!   exact configuration lines that fix it; with them the square runs clean.
//! - No false alarm: the runaway watch stays silent over every built-in and checked-in
//!   scenario and over drives with random frame drops (the test prints how many steps).
//!
//! `cargo test -p hostsim --test miswiring -- --nocapture` prints the figures.

use std::path::Path;

use firmware::Config;
use firmware::control::Fault;
use firmware::protocol::robot::RobotState;
use hostsim::analysis::bringup::{self, WHEEL_NAMES, Wiring, diagnose};
use hostsim::engine::{LogOptions, run_observed};
use hostsim::nodes::drives::SimDrives;
use hostsim::nodes::plant::PlantSpec;
use hostsim::scenario::Scenario;

/// The ten miswirings of one robot: each motor flipped, each pair of drives swapped.
fn miswirings() -> Vec<(String, PlantSpec)> {
    let mut v = Vec::new();
    for (w, name) in WHEEL_NAMES.iter().enumerate() {
        v.push((
            format!("flip {name}"),
            PlantSpec {
                flip: vec![w],
                ..PlantSpec::default()
            },
        ));
    }
    for (a, first) in WHEEL_NAMES.iter().enumerate() {
        for (b, second) in WHEEL_NAMES.iter().enumerate().skip(a + 1) {
            v.push((
                format!("swap {first}-{second}"),
                PlantSpec {
                    swap: vec![[a, b]],
                    ..PlantSpec::default()
                },
            ));
        }
    }
    v
}

/// The wiring of the plant `spec` builds for `config`: what a right configuration says.
fn true_wiring(config: &Config, spec: &PlantSpec) -> Wiring {
    let c = Wiring::of(config);
    Wiring {
        ids: spec.wired_ids(c.ids),
        inverted: spec.wired_inverted(c.inverted),
        ..c
    }
}

/// What a drive did: the first fault, when, and how far the body had moved by then (and in
/// all).
#[derive(Debug, Clone, Copy)]
struct Drove {
    fault: Option<(Fault, u64)>,
    /// Start of the interval, running at the fault, in which the currents' residual was at
    /// or above the fight threshold at every step (the oracle, from the firmware's own
    /// currents and the configuration's kinematics), µs.
    fight_onset_us: Option<u64>,
    moved_at_fault_m: f64,
    moved_max_m: f64,
    steps: u64,
}

fn drive(s: &Scenario) -> Drove {
    use firmware::control::FIGHT_CURRENT_FRACTION;
    let mut plant = hostsim::engine::plant_for(s).unwrap();
    let kin = s.config.kinematics().unwrap();
    let threshold = FIGHT_CURRENT_FRACTION * s.config.limits.max_current;
    let mut d = Drove {
        fault: None,
        fight_onset_us: None,
        moved_at_fault_m: 0.0,
        moved_max_m: 0.0,
        steps: 0,
    };
    // The currents the motors act on at a step are those of the step before.
    let mut acting = [0.0f32; 4];
    run_observed(s, &mut plant, None, LogOptions::default(), |v| {
        d.steps += 1;
        let moved = v.truth[0].hypot(v.truth[1]);
        d.moved_max_m = d.moved_max_m.max(moved);
        let snap = v.controller.snapshot();
        if d.fault.is_none() {
            let (_, residual) = kin.forward_with_residual(&kinematics::WheelSpeeds(acting));
            if residual.rms() >= threshold {
                d.fight_onset_us.get_or_insert(v.t_us);
            } else {
                d.fight_onset_us = None;
            }
        }
        if d.fault.is_none() && snap.state == RobotState::Fault {
            d.fault = Some((snap.fault, v.t_us));
            d.moved_at_fault_m = moved;
        }
        acting = snap.currents;
    })
    .unwrap();
    d
}

/// Enable, then drive `twist` from 0.1 s for 1.5 s, then stand.
fn leg(config: Config, spec: &PlantSpec, twist: [f32; 3]) -> Scenario {
    let mut s = Scenario::from_toml("duration_s = 2.0\nseed = 5", Path::new("leg.toml")).unwrap();
    s.config = config;
    s.plant = spec.clone();
    s.actions = vec![
        hostsim::scenario::Action {
            enable: true,
            ..hostsim::scenario::Action::at(0.05)
        },
        hostsim::scenario::Action::twist(0.1, twist[0], twist[1], twist[2]),
        hostsim::scenario::Action::twist(1.6, 0.0, 0.0, 0.0),
    ];
    s
}

/// Driving a robot with one motor mounted the other way: forward, strafe and spin from
/// rest. Each faults `WheelFight` exactly its window after the wheels' currents began to
/// fight (the oracle: their residual above the threshold), before the robot has moved
/// 5 cm. With no torque it then coasts on (the figures are printed).
#[test]
fn driving_with_a_flipped_motor_faults_before_the_robot_moves_5_cm() {
    use firmware::control::FIGHT_WINDOW_US;
    let config = Config::dji_m3508_example();
    let (mut worst_moved, mut worst_after_twist, mut worst_coast) = (0.0f64, 0u64, 0.0f64);
    for (name, spec) in miswirings().into_iter().filter(|(_, s)| !s.flip.is_empty()) {
        for twist in [[0.5, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 1.5]] {
            let d = drive(&leg(config, &spec, twist));
            let (fault, at_us) = d
                .fault
                .unwrap_or_else(|| panic!("{name} {twist:?}: no fault"));
            assert_eq!(fault, Fault::WheelFight, "{name} {twist:?}");
            let onset = d.fight_onset_us.expect("the currents fought");
            assert!(
                (FIGHT_WINDOW_US..=FIGHT_WINDOW_US + 2_000).contains(&(at_us - onset)),
                "{name} {twist:?}: {} µs after the onset",
                at_us - onset
            );
            // The twist starts at 0.1 s.
            let after_twist = at_us - 100_000;
            println!(
                "{name} {twist:?}: WheelFight {:.0} ms after the twist, the body {:.1} mm from \
                 rest then, {:.1} mm at most (coasting)",
                after_twist as f64 / 1e3,
                d.moved_at_fault_m * 1e3,
                d.moved_max_m * 1e3
            );
            assert!(
                d.moved_at_fault_m < 0.05,
                "{name} {twist:?}: {} m",
                d.moved_at_fault_m
            );
            worst_moved = worst_moved.max(d.moved_at_fault_m);
            worst_after_twist = worst_after_twist.max(after_twist);
            worst_coast = worst_coast.max(d.moved_max_m);
        }
    }
    println!(
        "flipped motors: at most {:.1} mm moved and {:.0} ms from the twist at the fault; \
         {:.1} mm at most after coasting",
        worst_moved * 1e3,
        worst_after_twist as f64 / 1e3,
        worst_coast * 1e3
    );
}

/// The bring-up check of `config` on a robot wired as `spec`: its diagnosis must be the
/// plant's true wiring, and the lines must say exactly what changes.
fn check_names_the_fix(config: &Config, name: &str, spec: &PlantSpec) -> Wiring {
    let runs = bringup::run_check(config, spec, 3.0, 1000).unwrap();
    let configured = Wiring::of(config);
    let d = diagnose(&configured, runs.map(|r| r.seen));
    let report = bringup::Report::new(name.to_string(), (3.0, 1000), &configured, &runs, &d);
    println!("{report}");
    let truth = true_wiring(config, spec);
    assert_eq!(d.fixed, Some(truth), "{name}: {runs:#?}");
    assert_eq!(d.is_right(), spec.is_empty(), "{name}");
    for r in &runs {
        // On blocks: the body stays, the firmware ends every test as planned.
        assert!(
            r.body_moved_m < 1e-3,
            "{name}: body moved {} m",
            r.body_moved_m
        );
        let result = r.result.expect("a WHEEL_TEST_RESULT");
        assert_eq!(
            result.outcome,
            firmware::protocol::robot::TestOutcome::Done,
            "{name}"
        );
        // One wheel turned, about 3 rad (1 s at 3 rad/s; a DJI wheel on blocks coasts on
        // after the test for the 0.4 s the run lasts); the others stayed.
        let seen = r.seen.expect("a wheel turned");
        let angle = r.turned[seen.wheel].abs();
        assert!((2.5..4.5).contains(&angle), "{name}: {angle} rad");
        for (w, a) in r.turned.iter().enumerate() {
            assert!(w == seen.wheel || a.abs() < 0.05, "{name}: {w} turned {a}");
        }
    }
    let lines = d.fix_lines(&configured);
    let expect_ids = truth.ids != configured.ids;
    let expect_inv = truth.inverted != configured.inverted;
    assert_eq!(
        lines.len(),
        usize::from(expect_ids) + usize::from(expect_inv),
        "{lines:?}"
    );
    truth
}

/// The square with the firmware configured as `firmware` on the robot that `spec` builds
/// from `config` (wired as it says): no fault, the body back where it began, and the
/// odometry's drift.
fn square_is_clean(firmware: &Config, config: &Config, spec: &PlantSpec) -> f64 {
    let mut s = Scenario::builtin("square").unwrap();
    s.config = *firmware;
    let mut plant = SimDrives::with_spec(config, spec).unwrap();
    let summary =
        hostsim::engine::run(&s, &mut plant, None, LogOptions::default(), |_| {}).unwrap();
    assert!(
        summary
            .transitions
            .iter()
            .all(|(_, state, _)| state != "FAULT"),
        "{:?}",
        summary.transitions
    );
    // The square ends where it began (the right robot's ends 21 mm off).
    assert!(
        summary.truth[0].hypot(summary.truth[1]) < 0.05,
        "{:?}",
        summary.truth
    );
    summary.max_position_error
}

#[test]
fn the_bring_up_check_names_every_dji_miswiring_and_its_fix_makes_the_square_clean() {
    let config = Config::dji_m3508_example();
    let reference = square_is_clean(&config, &config, &PlantSpec::default());
    check_names_the_fix(&config, "as configured", &PlantSpec::default());
    for (name, spec) in miswirings() {
        let fixed = check_names_the_fix(&config, &name, &spec);
        let drift = square_is_clean(&fixed.apply(&config), &config, &spec);
        println!(
            "{name}: square with the fix: max drift {drift:.4} m (right robot {reference:.4})"
        );
        // The same robot under the same firmware: the same run, but for the encoders'
        // quantization (a motor turning the other way rounds its angle the other way; 5 µm
        // of drift measured for a flipped FL).
        assert!(
            (drift - reference).abs() < 1e-4,
            "{name}: {drift} vs {reference}"
        );
    }
}

#[test]
fn the_bring_up_check_names_every_odrive_miswiring_and_its_fix() {
    let config = Config::odrive_example();
    check_names_the_fix(&config, "odrive as configured", &PlantSpec::default());
    for (name, spec) in miswirings() {
        check_names_the_fix(&config, &format!("odrive {name}"), &spec);
    }
}

/// The runaway and fight watches over drives of a right robot: every built-in and
/// checked-in scenario (their own faults included: stuck encoders, offline motors, bus
/// faults), the square with 5 % and 20 % of all frames dropped at random (10 seeds each),
/// and legs into translations, spins and strafe-and-turn combinations. No `WheelRunaway`,
/// no `WheelFight`. (The fault matrix, `tests/fault_matrix.rs`, with its 1,000 random
/// dropouts, checks that every run ends in its specified state, which neither is.)
#[test]
fn no_false_runaway_or_fight_over_the_scenarios_and_random_drops() {
    let mut runs: Vec<(String, Scenario)> = Scenario::BUILTINS
        .iter()
        .map(|n| ((*n).to_string(), Scenario::builtin(n).unwrap()))
        .collect();
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenarios");
    let mut files: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    files.sort();
    for p in files {
        let s = Scenario::from_file(&p).unwrap();
        runs.push((p.file_name().unwrap().to_string_lossy().into_owned(), s));
    }
    for rate in [0.05, 0.2] {
        for seed in 0..10 {
            let text = format!(
                "duration_s = 9.1\nseed = {seed}\n[[faults]]\nkind = \"drop\"\nfrom_s = 0.0\n\
                 until_s = 9.1\nrate = {rate}"
            );
            let mut s = Scenario::from_toml(&text, Path::new("drops.toml")).unwrap();
            s.actions = Scenario::builtin("square").unwrap().actions;
            runs.push((format!("square, {rate} dropped, seed {seed}"), s));
        }
    }
    // Legs of a right robot from 0.6 m/s forward into translations, spins and strafe-and-
    // turn combinations (up to 1 m/s with 2 rad/s), the matrix of the fight watch's figures.
    let config = Config::dji_m3508_example();
    for t in [
        [0.5, 0.0, 0.0],
        [0.0, 0.5, 0.0],
        [0.0, 0.0, 1.5],
        [0.4, 0.2, 1.0],
        [0.3, -0.2, 0.6],
        [0.5, 0.5, 0.0],
        [0.4, 0.0, 0.6],
        [1.5, 0.0, 0.0],
        [0.0, 1.0, 2.0],
        [-1.0, -1.0, 0.0],
        [0.0, 0.0, -4.0],
    ] {
        let mut s = leg(config, &PlantSpec::default(), [0.6, 0.0, 0.0]);
        s.duration_s = 2.5;
        s.actions
            .insert(2, hostsim::scenario::Action::twist(0.6, t[0], t[1], t[2]));
        runs.push((format!("leg {t:?}"), s));
    }
    let mut steps = 0;
    for (name, s) in &runs {
        let d = drive(s);
        steps += d.steps;
        let fault = d.fault.map(|f| f.0);
        assert!(
            !matches!(fault, Some(Fault::WheelRunaway | Fault::WheelFight)),
            "{name}: {:?}",
            d.fault
        );
    }
    println!(
        "runaway and fight watches: {} runs, {steps} firmware steps, no WheelRunaway or WheelFight",
        runs.len()
    );
    assert!(steps > 200_000, "{steps}");
}
