//! What-if replays (`hostsim replay LOG.mcap --config FILE`): a simulated session replayed
//! open loop through a core with another configuration. The same configuration changes
//! nothing; a gain changes the currents; a lower limit caps them; a fault only the what-if
//! has is reported with its time; other drives and bad files are refused naming the field.

mod common;

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use common::hostsim;
use firmware::Config;
use hostsim::replay::whatif::{
    OPEN_LOOP_NOTE, WhatIfError, WhatIfReport, WhatIfRunError, what_if_frames, what_if_mcap,
};
use hostsim::replay::{StepTime, read_log, replay_mcap};
use hostsim::scenario::Scenario;

/// A logged 2.5 s of the built-in square (DJI C620/M3508): enable at 0.05 s, forward at
/// 0.5 m/s from 0.1 s, left from 2.1 s. Written once per test run.
fn dji_log() -> &'static Path {
    static LOG: OnceLock<PathBuf> = OnceLock::new();
    LOG.get_or_init(|| {
        let path = common::scratch("whatif", "square.mcap");
        let mut s = Scenario::builtin("square").unwrap();
        s.duration_s = 2.5;
        common::logged_run(&s, &path);
        path
    })
}

/// `config` as a TOML file `name` in the scratch folder.
fn config_file(name: &str, config: &Config) -> PathBuf {
    let path = common::scratch("whatif", name);
    std::fs::write(&path, config.to_toml_string()).unwrap();
    path
}

fn dji_with(edit: impl FnOnce(&mut Config)) -> Config {
    let mut c = Config::dji_m3508_example();
    edit(&mut c);
    c
}

fn seconds(t_s: &str) -> f64 {
    t_s.parse().unwrap()
}

#[test]
fn the_logged_configuration_makes_no_difference() {
    let log = dji_log();
    // The logged configuration itself, as the log stores it.
    let logged = read_log(log).unwrap().config.unwrap();
    let path = common::scratch("whatif", "same.toml");
    std::fs::write(&path, logged).unwrap();
    let r = what_if_mcap(log, &path).unwrap();
    assert!(r.identical, "{:?}", r.first_difference);
    assert_eq!(r.first_difference, None);
    assert!(r.changes.is_empty(), "{:?}", r.changes);
    // The same run as a plain replay: every step, every frame.
    let replay = replay_mcap(log).unwrap();
    assert_eq!((r.steps, r.fed), (replay.steps, replay.fed));
    assert_eq!(r.logged_frames, replay.compared);
    assert_eq!(r.what_if_frames, r.logged_frames);
    // 2.5 s at 1 kHz, steps at 0..=2.5 s; one 0x200 command per step.
    assert_eq!(r.steps, 2501);
    let cmd = r.by_id.iter().find(|c| c.id == "0x200").unwrap();
    assert_eq!(
        (cmd.message.as_str(), cmd.logged),
        ("CURRENT_CMD_1_4", 2501)
    );
    assert!(r.by_id.iter().all(|c| c.differ() == 0), "{:?}", r.by_id);
    let current = &r.setpoints[0];
    assert_eq!((current.quantity, current.unit), ("motor current", "A"));
    for w in &current.wheels {
        assert_eq!(w.difference.samples, 2501, "{}", w.wheel);
        assert_eq!(w.difference.max_abs_difference, 0.0, "{}", w.wheel);
        assert_eq!(w.difference.rms_difference, 0.0, "{}", w.wheel);
        assert_eq!(w.difference.t_max_difference_s, None, "{}", w.wheel);
        assert_eq!(w.max_abs_logged, w.max_abs_what_if, "{}", w.wheel);
        assert!(w.max_abs_logged > 1.0, "{}: the robot was driven", w.wheel);
    }
    assert!(r.states.only_logged.is_empty() && r.states.only_what_if.is_empty());
    assert_eq!(r.states.logged, r.states.what_if);
}

#[test]
fn a_higher_velocity_gain_changes_the_currents_and_nothing_else() {
    let log = dji_log();
    let path = config_file("kp.toml", &dji_with(|c| c.gains.kp = 2.4));
    let r = what_if_mcap(log, &path).unwrap();
    assert!(!r.identical);
    assert_eq!(r.changes.len(), 1, "{:?}", r.changes);
    let change = &r.changes[0];
    assert_eq!(
        (change.field.as_str(), change.logged.as_deref()),
        ("gains.kp", Some("1.2"))
    );
    assert_eq!(change.what_if.as_deref(), Some("2.4"));

    // The first difference: the first current command of the first step with a speed error
    // (the first twist arrives at 0.1 s), in both streams.
    let d = r.first_difference.as_ref().unwrap();
    let t = seconds(&d.t_s);
    assert!(t > 0.0 && (0.1..0.2).contains(&t), "{t}");
    let (logged, what_if) = (d.logged.as_ref().unwrap(), d.what_if.as_ref().unwrap());
    assert_eq!(
        (logged.t_s.as_str(), what_if.t_s.as_str()),
        (d.t_s.as_str(), d.t_s.as_str())
    );
    assert!(logged.frame.starts_with("200#") && what_if.frame.starts_with("200#"));
    assert_ne!(logged.frame, what_if.frame);

    // Open loop: the feedback is the recorded one, so the odometry and the status frames are
    // the logged ones; only the current commands change.
    for c in &r.by_id {
        if c.id == "0x200" {
            assert_eq!((c.logged, c.what_if), (2501, 2501));
            assert!(c.changed > 2000, "{c:?}");
            assert_eq!((c.only_logged, c.only_what_if), (0, 0));
        } else {
            assert_eq!(c.differ(), 0, "{c:?}");
            assert_eq!(c.logged, c.what_if, "{c:?}");
        }
    }
    for w in &r.setpoints[0].wheels {
        let d = &w.difference;
        assert!(
            d.max_abs_difference > 0.1 && d.max_abs_difference.is_finite(),
            "{}: {d:?}",
            w.wheel
        );
        assert!(d.rms_difference > 0.0 && d.rms_difference <= d.max_abs_difference);
        let t_max = seconds(d.t_max_difference_s.as_deref().unwrap());
        assert!(
            t_max >= t,
            "{}: max at {t_max} before the first difference",
            w.wheel
        );
        // A stiffer loop asks for more current.
        assert!(w.max_abs_what_if > w.max_abs_logged, "{w:?}");
    }
    assert!(r.states.only_what_if.is_empty(), "{:?}", r.states);
}

#[test]
fn a_lower_current_limit_caps_every_what_if_current() {
    let log = dji_log();
    let limit = 5.0;
    let path = config_file("current.toml", &dji_with(|c| c.limits.max_current = limit));
    let r = what_if_mcap(log, &path).unwrap();
    assert!(!r.identical);
    let mut binding = 0;
    for w in &r.setpoints[0].wheels {
        assert!(
            w.max_abs_what_if <= f64::from(limit),
            "{}: {} A over the {limit} A limit",
            w.wheel,
            w.max_abs_what_if
        );
        if w.max_abs_logged > f64::from(limit) {
            // The limit binds: the what-if sits on it (one C620 LSB is 20/16384 A).
            binding += 1;
            assert!(
                w.max_abs_what_if >= f64::from(limit) - 20.0 / 16384.0,
                "{w:?}"
            );
            assert!(w.difference.max_abs_difference > 0.5, "{w:?}");
        }
    }
    assert_eq!(binding, 4, "the square drives every wheel over {limit} A");
}

#[test]
fn a_fault_only_the_what_if_has_is_reported_with_its_time() {
    // The host sends a twist every 20 ms; a 10 ms command timeout stops the robot.
    let log = dji_log();
    let path = config_file(
        "timeout.toml",
        &dji_with(|c| c.timing.command_timeout_ms = 10),
    );
    let r = what_if_mcap(log, &path).unwrap();
    let watchdog = |changes: &[hostsim::replay::whatif::StateChange]| {
        changes
            .iter()
            .find(|c| c.fault == "WATCHDOG")
            .map(|c| (seconds(&c.t_s), c.state.clone()))
    };
    assert_eq!(watchdog(&r.states.logged), None, "{:?}", r.states.logged);
    let (t_status, _) = watchdog(&r.states.only_what_if).expect("only in the what-if");
    // The core stops 10 ms after the first twist (0.1 s) plus a step; STATUS frames go out
    // every 100 ms, so the frames show it at 0.2 s.
    let (t_core, state) = watchdog(&r.states.what_if_core).unwrap();
    assert!((0.110..0.115).contains(&t_core), "{t_core}");
    assert_eq!(state, "ENABLED", "stopping, not yet disabled");
    assert_eq!(t_status, 0.2);
    assert!(
        r.states
            .what_if_core
            .iter()
            .any(|c| c.state == "DISABLED" && c.fault == "WATCHDOG"),
        "{:?}",
        r.states.what_if_core
    );
}

#[test]
fn other_drives_are_refused_naming_what_differs() {
    let log = dji_log();
    let odrive = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../config/odrive.toml");
    let err = what_if_mcap(log, &odrive).unwrap_err();
    let WhatIfError::Incompatible { source, .. } = &err else {
        panic!("{err}")
    };
    assert_eq!(
        (
            source.field,
            source.logged.as_str(),
            source.what_if.as_str()
        ),
        ("drive.protocol", "dji", "odrive")
    );
    let text = err.to_string();
    assert!(
        text.contains("odrive.toml") && text.contains("square.mcap"),
        "{text}"
    );
    assert!(
        text.contains("drive.protocol differs (log: dji, what-if: odrive)"),
        "{text}"
    );

    let path = config_file(
        "ids.toml",
        &dji_with(|c| {
            if let firmware::config::Drive::Dji { esc_ids, .. } = &mut c.drive {
                *esc_ids = [5, 6, 7, 8];
            }
        }),
    );
    let err = what_if_mcap(log, &path).unwrap_err().to_string();
    assert!(
        err.contains("drive.esc_ids differs (log: [1, 2, 3, 4], what-if: [5, 6, 7, 8])"),
        "{err}"
    );
    let path = config_file(
        "c610.toml",
        &dji_with(|c| {
            c.limits.max_current = 10.0;
            if let firmware::config::Drive::Dji { model, .. } = &mut c.drive {
                *model = firmware::protocol::dji::EscModel::C610;
            }
        }),
    );
    let err = what_if_mcap(log, &path).unwrap_err().to_string();
    assert!(
        err.contains("drive.model differs (log: c620, what-if: c610)"),
        "{err}"
    );

    // A runner's log records its step times: the core's period must be the logged one.
    let logged = Config::dji_m3508_example();
    let slower = dji_with(|c| {
        c.timing.control_hz = 500;
        c.timing.setpoint_hz = 100;
    });
    let steps = [StepTime {
        t_ns: 0,
        shutdown: false,
    }];
    let err = what_if_frames(&logged, &slower, &[], &[], &steps).unwrap_err();
    let WhatIfRunError::Incompatible(e) = &err else {
        panic!("{err}")
    };
    assert_eq!(
        (e.field, e.logged.as_str(), e.what_if.as_str()),
        ("timing.control_hz", "1000", "500")
    );
    // On the simulator's grid (no step records) it steps on its own period.
    let r = what_if_frames(&logged, &slower, &[], &[], &[]).unwrap();
    assert_eq!(r.steps, 1);
    // A configuration the firmware refuses (built in code, so not checked by a loader).
    let refused = dji_with(|c| c.timing.control_hz = 500);
    let err = what_if_frames(&logged, &refused, &[], &[], &[]).unwrap_err();
    assert!(matches!(err, WhatIfRunError::Refused(_)), "{err}");
    assert!(
        err.to_string().contains("timing.setpoint_hz = 200"),
        "{err}"
    );
}

#[test]
fn a_bad_configuration_file_is_refused_naming_the_field() {
    let log = dji_log();
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../config/dji_m3508.toml"),
    )
    .unwrap();
    // Out of range.
    let negative = common::scratch("whatif", "negative-kp.toml");
    std::fs::write(&negative, text.replace("kp = 1.2", "kp = -1.0")).unwrap();
    let err = what_if_mcap(log, &negative).unwrap_err();
    assert!(matches!(err, WhatIfError::Config { .. }), "{err}");
    let err = err.to_string();
    assert!(
        err.contains("negative-kp.toml") && err.contains("gains.kp = -1"),
        "{err}"
    );
    // Misspelt.
    let typo = common::scratch("whatif", "typo.toml");
    std::fs::write(&typo, text.replace("kp = 1.2", "kpp = 1.2")).unwrap();
    let err = what_if_mcap(log, &typo).unwrap_err().to_string();
    assert!(err.contains("typo.toml") && err.contains("kpp"), "{err}");
    // Missing.
    let err = what_if_mcap(log, Path::new("no/such/config.toml"))
        .unwrap_err()
        .to_string();
    assert!(err.contains("no/such/config.toml"), "{err}");
}

#[test]
fn an_odrive_what_if_decodes_velocity_setpoints() {
    let log = common::scratch("whatif", "odrive-strafe.mcap");
    let mut s = Scenario::builtin("strafe").unwrap();
    s.config = Config::odrive_example();
    s.duration_s = 1.5;
    common::logged_run(&s, &log);
    // 0.5 m/s sideways on 50 mm wheels is 10 rad/s per wheel; allow 5.
    let mut slow = Config::odrive_example();
    slow.limits.max_wheel_speed = 5.0;
    let r = what_if_mcap(&log, &config_file("odrive-slow.toml", &slow)).unwrap();
    assert!(!r.identical);
    let quantities: Vec<_> = r.setpoints.iter().map(|q| (q.quantity, q.unit)).collect();
    assert_eq!(
        quantities,
        [("motor velocity", "rev/s"), ("torque feed-forward", "Nm")]
    );
    // Wheel speed limit in motor turns per second: 5 rad/s x 5:1 belt / 2 pi.
    let limit = 5.0 * 5.0 / std::f64::consts::TAU;
    for w in &r.setpoints[0].wheels {
        assert!(w.logged_commands > 250, "{w:?}");
        assert!(w.max_abs_logged > 7.0, "{w:?}");
        assert!(w.max_abs_what_if <= limit * (1.0 + 1e-6), "{w:?}");
        assert!(w.max_abs_what_if > limit * 0.99, "{w:?}");
    }
    let setpoint_ids: Vec<_> = r
        .by_id
        .iter()
        .filter(|c| c.message.starts_with("Set_Input_Vel") && c.changed > 0)
        .map(|c| c.id.as_str())
        .collect();
    // node << 5 | 0x0D for nodes 0-3.
    assert_eq!(setpoint_ids, ["0x00D", "0x02D", "0x04D", "0x06D"]);
}

#[test]
fn the_same_inputs_give_the_same_report() {
    let log = dji_log();
    let path = config_file("ki.toml", &dji_with(|c| c.gains.ki = 60.0));
    let a: WhatIfReport = what_if_mcap(log, &path).unwrap();
    let b = what_if_mcap(log, &path).unwrap();
    assert_eq!(a, b);
    assert_eq!(
        serde_json::to_string(&a).unwrap(),
        serde_json::to_string(&b).unwrap()
    );
}

#[test]
fn the_command_line_what_if() {
    let log = dji_log().to_str().unwrap();
    let kp = config_file("cli-kp.toml", &dji_with(|c| c.gains.kp = 2.4));
    let kp = kp.to_str().unwrap();

    // Text: open loop first, a difference is exit 0.
    let (code, out, err) = hostsim(["replay", log, "--config", kp]);
    assert_eq!(code, 0, "{out}{err}");
    assert_eq!(out.lines().next(), Some(OPEN_LOOP_NOTE));
    assert!(out.contains("changes: gains.kp 1.2 -> 2.4"), "{out}");
    assert!(out.contains("first difference at 0.101000 s"), "{out}");
    assert!(out.contains("0x200"), "{out}");
    assert!(out.contains("verdict: differs"), "{out}");
    // The same run twice prints the same report.
    assert_eq!(hostsim(["replay", log, "--config", kp]).1, out);

    // JSON.
    let (code, out, _) = hostsim(["replay", log, "--config", kp, "--json"]);
    assert_eq!(code, 0);
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v["verdict"], "differs");
    assert_eq!(v["open_loop"], true);
    assert_eq!(v["note"], OPEN_LOOP_NOTE);
    assert_eq!(v["complete"], true);
    assert_eq!(v["setpoints"][0]["wheels"][0]["wheel"], "FL");
    assert!(
        v["setpoints"][0]["wheels"][0]["max_abs_difference"]
            .as_f64()
            .unwrap()
            > 0.1
    );

    // No difference.
    let same = config_file("cli-same.toml", &Config::dji_m3508_example());
    let (code, out, _) = hostsim(["replay", log, "--config", same.to_str().unwrap()]);
    assert_eq!(code, 0);
    assert!(
        out.contains("the change makes no difference on this log"),
        "{out}"
    );
    assert!(out.contains("verdict: no_difference"), "{out}");

    // Refused: exit 2, naming the field.
    let odrive = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../config/odrive.toml");
    let (code, _, err) = hostsim(["replay", log, "--config", odrive.to_str().unwrap()]);
    assert_eq!(code, 2);
    assert!(err.contains("drive.protocol differs"), "{err}");
    let bad = common::scratch("whatif", "cli-bad.toml");
    std::fs::write(
        &bad,
        Config::dji_m3508_example()
            .to_toml_string()
            .replace("max_current = 16.0", "max_current = 25.0"),
    )
    .unwrap();
    let (code, _, err) = hostsim(["replay", log, "--config", bad.to_str().unwrap()]);
    assert_eq!(code, 2);
    assert!(
        err.contains("cli-bad.toml") && err.contains("limits.max_current = 25"),
        "{err}"
    );

    // The help says what it is and what it is not.
    let (_, help, _) = hostsim(["replay", "--help"]);
    assert!(help.contains("OPEN LOOP"), "{help}");
    assert!(help.contains("What-if: 0"), "{help}");
}

#[test]
fn a_damaged_log_runs_on_its_complete_part_and_exits_3() {
    let bytes = std::fs::read(dji_log()).unwrap();
    let cut = common::scratch("whatif", "cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let same = config_file("cut-same.toml", &Config::dji_m3508_example());
    let r = what_if_mcap(&cut, &same).unwrap();
    assert!(!r.read.as_ref().unwrap().is_complete());
    assert!(r.identical, "{:?}", r.first_difference);
    assert!(r.steps > 100 && r.steps < 2501, "{}", r.steps);
    let (code, out, err) = hostsim([
        "replay",
        cut.to_str().unwrap(),
        "--config",
        same.to_str().unwrap(),
    ]);
    assert_eq!(code, 3, "{out}{err}");
    assert!(err.contains("warning:"), "{err}");
    assert!(out.contains("verdict: no_difference"), "{out}");
}
