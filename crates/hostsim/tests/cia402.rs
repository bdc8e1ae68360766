//! The core as the CANopen master of simulated CiA 402 drives (`config/cia402.toml`): each
//! node configured, started and enabled on the bit-timed bus, the robot driving its square,
//! and the bus load of the cycle the configuration sets.

mod common;

use drivelog::for_each_message;
use drivelog::msg::{self, decode};
use embedded_can::Frame;
use firmware::Config;
use firmware::protocol::canopen::{self, Message, NmtCommand};
use firmware::protocol::robot::{self, RobotState};
use hostsim::bus::Node;
use hostsim::engine::{LogOptions, RunSummary, run, run_observed};
use hostsim::nodes::drives::SimDrives;
use hostsim::scenario::Scenario;

fn cia402() -> Config {
    Config::from_toml_file(std::path::Path::new("../../config/cia402.toml")).unwrap()
}

fn square(config: Config) -> Scenario {
    let mut s = Scenario::builtin("square").unwrap();
    s.config = config;
    s
}

fn simulate(s: &Scenario) -> RunSummary {
    let mut plant = SimDrives::new(&s.config).unwrap();
    run(s, &mut plant, None, LogOptions::default(), |_| {}).unwrap()
}

#[test]
fn the_square_drives_on_cia402_drives_and_the_odometry_closes() {
    let r = simulate(&square(cia402()));
    assert_eq!(r.last.state, RobotState::Enabled, "{:?}", r.transitions);
    assert_eq!(r.last.rx_errors.total(), 0);
    assert_eq!(r.last.motors_online, 0b1111);
    // As the ODrive and DJI robots on the same square: the odometry ends within 2 cm of the
    // truth (the strafing legs slip, as the chassis model makes every mecanum robot slip).
    assert!(
        r.final_position_error < 0.02,
        "{} m",
        r.final_position_error
    );
    assert!(
        r.truth[0].abs() < 0.05 && r.truth[1].abs() < 0.05,
        "{:?}",
        r.truth
    );
}

/// Times (µs) at which a node is started and reaches operation enabled, and when the master
/// sent its first frame: read from the frames on the bus.
#[derive(Debug, Default, Clone, Copy)]
struct Trace {
    start: Option<u64>,
    enabled: Option<u64>,
}

#[test]
fn each_node_is_configured_started_and_enabled_in_simulated_milliseconds() {
    let s = square(cia402());
    let mut plant = SimDrives::new(&s.config).unwrap();
    let mut traces = [Trace::default(); 2];
    let mut enable_sent = None;
    run_observed(&s, &mut plant, None, LogOptions::default(), |step| {
        for tx in step.delivered {
            let t = tx.delivered_ns / 1000;
            match canopen::decode(&tx.frame) {
                Ok(Message::Nmt {
                    command: NmtCommand::Start,
                    node: Some(n),
                }) if tx.from == Node::Controller => {
                    traces[usize::from(n.get() - 1)].start.get_or_insert(t);
                }
                Ok(Message::Tpdo1 {
                    node, statusword, ..
                }) if statusword & 0x6F == 0x27 => {
                    traces[usize::from(node.get() - 1)].enabled.get_or_insert(t);
                }
                _ => {}
            }
            let mode_cmd = embedded_can::Id::Standard(
                embedded_can::StandardId::new(robot::layout::MODE_CMD.id).unwrap(),
            );
            if tx.frame.id() == mode_cmd && tx.frame.data() == [1] && enable_sent.is_none() {
                enable_sent = Some(t);
            }
        }
    })
    .unwrap();
    let enable_sent = enable_sent.expect("the host enabled the robot");
    for (i, t) in traces.iter().enumerate() {
        let start = t.start.expect("started");
        let enabled = t.enabled.expect("enabled") - enable_sent;
        eprintln!(
            "node {}: started {:.1} ms after boot, operation enabled {:.1} ms after the host's enable",
            i + 1,
            start as f64 / 1e3,
            enabled as f64 / 1e3
        );
        // 37 SDO transfers, one per 1 ms step; then three enable steps, each answered by the
        // next SYNC (4 ms).
        assert!(
            (37_000..=43_000).contains(&start),
            "node {}: {start} µs",
            i + 1
        );
        assert!(enabled <= 20_000, "node {}: {enabled} µs", i + 1);
    }
}

#[test]
fn the_cycle_sets_the_bus_load_and_a_1_khz_cycle_nearly_fills_the_bus() {
    let load = |hz: u32| {
        let mut c = cia402();
        c.timing.setpoint_hz = hz;
        let r = simulate(&square(c));
        assert!(
            r.last.state == RobotState::Enabled,
            "{hz} Hz: {:?}",
            r.transitions
        );
        r.bus_load
    };
    let (l250, l1000) = (load(250), load(1000));
    // Two dual-axis nodes: SYNC, two RPDO1, two RPDO3, two TPDO1, two TPDO2 a cycle, beside
    // the robot's own frames.
    assert!((0.20..0.30).contains(&l250), "250 Hz: {l250}");
    assert!(l1000 > 0.80, "1 kHz: {l1000}");
}

#[test]
fn the_reboot_scenario_faults_reconfigures_and_drives_again_after_the_hosts_reset() {
    let s =
        Scenario::from_file(std::path::Path::new("../../scenarios/cia402_reboot.toml")).unwrap();
    let path = common::scratch("cia402", "reboot.mcap");
    let r = common::logged_run(&s, &path);
    // The log's status line says what the bus said.
    let bytes = std::fs::read(&path).unwrap();
    let mut lines = Vec::new();
    for_each_message(
        &bytes,
        |m| {
            if m.topic == "/rosout" {
                lines.push(decode::<msg::Log>(m.data).unwrap().msg);
            }
        },
        |_, _| {},
    )
    .unwrap();
    let line = "state FAULT, fault DRIVE_REBOOTED (node 1: booted again, configured anew)";
    assert!(lines.iter().any(|l| l == line), "{lines:?}");
    let states: Vec<(&str, &str)> = r
        .transitions
        .iter()
        .map(|(_, s, f)| (s.as_str(), f.as_str()))
        .collect();
    assert_eq!(
        states,
        [
            ("ENABLED", "NONE"),
            ("FAULT", "DRIVE_REBOOTED"),
            ("DISABLED", "NONE"),
            ("ENABLED", "NONE")
        ],
        "{:?}",
        r.transitions
    );
    let fault_at = r.transitions[1].0;
    assert!((0.602..0.605).contains(&fault_at), "{fault_at} s");
    assert_eq!(r.last.motors_online, 0b1111);
    // Driving forward again at the end: 0.4 m/s for about a second.
    assert!(r.truth[0] > 0.5, "{:?}", r.truth);
}

#[test]
fn canopen_faults_are_refused_for_other_drives() {
    let mut s =
        Scenario::from_file(std::path::Path::new("../../scenarios/cia402_reboot.toml")).unwrap();
    s.config = Config::dji_m3508_example();
    let e = hostsim::engine::plant_for(&s).unwrap_err().to_string();
    assert!(e.contains("faults[].kind") && e.contains("cia402"), "{e}");
    // Where the scenario is loaded with such a configuration, the file, the fault and its
    // kind are named.
    let path = std::path::Path::new("../../scenarios/cia402_reboot.toml");
    let text = std::fs::read_to_string(path).unwrap();
    let e = Scenario::from_toml_with_config(&text, path, Some(Config::dji_m3508_example()))
        .unwrap_err()
        .to_string();
    for says in [
        "cia402_reboot.toml",
        "faults[0].kind",
        "\"drive_reboot\"",
        "cia402",
    ] {
        assert!(e.contains(says), "{says}: {e}");
    }
}

/// A disable while driving at 0.4 m/s: the master's configuration sets 0x605B = 1 (shutdown
/// option code: slow down on the slow down ramp), so each drive keeps its axes powered at a
/// zero target and reports operation enabled until they are at rest, and only then ready to
/// switch on; the torque goes when the wheels have stopped, not at the shutdown.
#[test]
fn a_disable_while_driving_slows_down_powered_before_the_drive_function_goes() {
    let text = r#"
name = "disable_while_driving"
duration_s = 1.2
seed = 1
command_hz = 50.0
[[actions]]
at_s = 0.1
enable = true
[[actions]]
at_s = 0.15
twist = [0.4, 0.0, 0.0]
[[actions]]
at_s = 0.7
disable = true
"#;
    let s = Scenario::from_toml_with_config(
        text,
        std::path::Path::new("disable_while_driving.toml"),
        Some(cia402()),
    )
    .unwrap();
    let mut plant = SimDrives::new(&s.config).unwrap();
    // Node 1, axis 1, from its TPDO1s after the shutdown: (µs, statusword, velocity actual).
    let mut shutdown = None;
    let mut after = Vec::new();
    run_observed(&s, &mut plant, None, LogOptions::default(), |step| {
        for tx in step.delivered {
            let t = tx.delivered_ns / 1000;
            match canopen::decode(&tx.frame) {
                Ok(Message::Rpdo1 {
                    node, controlword, ..
                }) if node.get() == 1 && controlword == 0x06 && t > 600_000 => {
                    shutdown.get_or_insert(t);
                }
                Ok(Message::Tpdo1 {
                    node,
                    statusword,
                    velocity,
                }) if node.get() == 1 && shutdown.is_some() => {
                    after.push((t, statusword, velocity));
                }
                _ => {}
            }
        }
    })
    .unwrap();
    let shutdown = shutdown.expect("the master shut node 1 down");
    let moving = after[0].2.unsigned_abs();
    let rest = after
        .iter()
        .position(|&(_, sw, _)| sw & 0x6F == 0x21)
        .expect("ready to switch on in the end");
    let (t_rest, _, v_rest) = after[rest];
    eprintln!(
        "node 1: {moving} raw at the shutdown, ready to switch on {:.1} ms later at {v_rest} raw",
        (t_rest - shutdown) as f64 / 1e3
    );
    assert!(moving > 100, "moving at the shutdown: {after:?}");
    // Operation enabled (powered) all the way down, the speed falling.
    assert!(
        after[..rest].iter().all(|&(_, sw, _)| sw & 0x6F == 0x27),
        "{after:?}"
    );
    assert!(rest >= 3, "the slow down took {rest} cycles: {after:?}");
    assert!(v_rest.unsigned_abs() * 10 < moving, "{after:?}");
    assert!(t_rest - shutdown < 200_000, "{} µs", t_rest - shutdown);
}
