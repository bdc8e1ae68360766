//! The scenario format: what parses, what is refused and how the refusal reads.
use super::*;
use crate::bus::{FaultKind, Node};
use crate::nodes::host::{HostFault, HostFaultKind};
use crate::nodes::plant::ChassisParams;

#[test]
fn builtins_exist_and_end_after_their_last_action() {
    for name in Scenario::BUILTINS {
        let s = Scenario::builtin(name).unwrap();
        let last = s.actions.last().unwrap().at_s;
        assert!(s.duration_s >= last, "{name}");
    }
    let e = Scenario::builtin("nope").unwrap_err().to_string();
    assert!(e.contains("square") && e.contains("nope"), "{e}");
}

/// Scenario texts the format refuses, each with what the refusal must name.
const REFUSED: &[(&str, &str)] = &[
    ("duration_s = -1.0", "duration_s"),
    // Positive but a period past u64 microseconds: it wrapped the host's command clock.
    (
        "duration_s = 1.0\ncommand_hz = 1e-300",
        "command_hz = 1e-300: a rate in [0.01, 1000] Hz",
    ),
    (
        "duration_s = 1.0\ncommand_hz = 0.001",
        "command_hz = 0.001: a rate in [0.01, 1000] Hz",
    ),
    (
        "duration_s = 1.0\ncommand_hz = 1000.5",
        "command_hz = 1000.5: a rate in [0.01, 1000] Hz",
    ),
    ("name = \" \"\nduration_s = 1.0", "name = \" \": a name"),
    (
        "duration_s = 1.0\n[[faults]]\nkind = \"drop\"\nfrom_s = 0.0\nuntil_s = 1.0",
        "faults[0].rate = (missing): a probability",
    ),
    (
        "duration_s = 1.0\n[[faults]]\nkind = \"corrupt\"\nrate = 2.0\nfrom_s = 0.0\nuntil_s = 1.0",
        "faults[0].rate = 2: a probability",
    ),
    (
        "duration_s = 1.0\n[[faults]]\nkind = \"motor_offline\"\nwheel = 4\nfrom_s = 0.0\nuntil_s = 1.0",
        "faults[0].wheel = 4: a wheel index",
    ),
    (
        "duration_s = 1.0\n[[faults]]\nkind = \"delay\"\ndelay_ms = -5.0\nfrom_s = 0.0\nuntil_s = 1.0",
        "faults[0].delay_ms = -5: a delay",
    ),
    (
        "duration_s = 1.0\n[[faults]]\nkind = \"burst\"\nfrom_s = 2.0\nuntil_s = 1.0",
        "from_s",
    ),
    ("duration_s = 1.0\n[[actions]]\nat_s = -0.5", "at_s"),
    (
        "duration_s = 1.0\n[[actions]]\nat_s = 1.0\nenable = true",
        "actions[0].at_s = 1: a time before duration_s",
    ),
    (
        "duration_s = 1.0\n[[actions]]\nat_s = 0.5",
        "actions[0] = {}: at least one of",
    ),
    (
        "duration_s = 1.0\n[[actions]]\nat_s = 0.5\nenable = true\ndisable = true",
        "actions[0] = {enable, disable}",
    ),
    (
        "duration_s = 1.0\n[[faults]]\nkind = \"burst\"\nfrom_s = 1.5\nuntil_s = 2.0",
        "faults[0].from_s = 1.5: a time before duration_s",
    ),
    (
        "duration_s = 1.0\n[[faults]]\nkind = \"drop\"\nrate = 0.5\nwheel = 2\nfrom_s = 0.0\nuntil_s = 1.0",
        "faults[0].wheel = 2: not used by a \"drop\" fault (it takes rate, sender)",
    ),
    (
        "duration_s = 1.0\n[[faults]]\nkind = \"stuck_encoder\"\nwheel = 1\nrate = 0.5\nfrom_s = 0.0\nuntil_s = 1.0",
        "faults[0].rate = 0.5: not used by a \"stuck_encoder\" fault (it takes wheel)",
    ),
    (
        "duration_s = 1.0\n[[faults]]\nkind = \"repeated_twist\"\nwheel = 1\nfrom_s = 0.0\nuntil_s = 1.0",
        "faults[0].wheel = 1: not used by a \"repeated_twist\" fault (it takes no other field)",
    ),
];

#[test]
fn toml_scenario_parses_and_validates() {
    let text = r#"
        duration_s = 3.0
        seed = 9
        [[actions]]
        at_s = 0.1
        enable = true
        [[actions]]
        at_s = 0.2
        twist = [0.5, 0.0, 0.1]
        [[faults]]
        kind = "drop"
        rate = 0.25
        from_s = 1.0
        until_s = 2.0
        sender = "drives"
        [[faults]]
        kind = "stuck_encoder"
        wheel = 2
        from_s = 0.5
        until_s = 0.7
        [[faults]]
        kind = "non_finite_twist"
        from_s = 1.5
        until_s = 1.6
        [[faults]]
        kind = "repeated_twist"
        from_s = 2.0
        until_s = 2.5
    "#;
    let s = Scenario::from_toml(text, Path::new("x.toml")).unwrap();
    assert_eq!((s.name.as_str(), s.seed, s.actions.len()), ("x", 9, 2));
    assert_eq!(s.bus_faults[0].kind, FaultKind::Drop { rate: 0.25 });
    assert_eq!(s.bus_faults[0].sender, Some(Node::Drives));
    assert_eq!(
        (s.wheel_faults[0].wheel, s.wheel_faults[0].from_us),
        (2, 500_000)
    );
    assert_eq!(
        s.host_faults,
        [
            HostFault {
                kind: HostFaultKind::NonFiniteTwist,
                from_us: 1_500_000,
                until_us: 1_600_000
            },
            HostFault {
                kind: HostFaultKind::RepeatedTwist,
                from_us: 2_000_000,
                until_us: 2_500_000
            }
        ]
    );
    assert!(s.host_faults[1].active(2_000_000) && !s.host_faults[1].active(2_500_000));
    assert_eq!(s.bus_faults.len(), 1);

    for &(bad, field) in REFUSED {
        let e = Scenario::from_toml(bad, Path::new("bad.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains(field) && e.contains("bad.toml"), "{bad}: {e}");
    }
    let e = Scenario::from_toml("duration_s = 1.0\nwarp = 9", Path::new("w.toml"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("warp"), "{e}");
}

#[test]
fn a_wheel_test_action_parses_and_its_ranges_are_checked() {
    let text = "duration_s = 2.0\n[[actions]]\nat_s = 0.1\n\
                wheel_test = { wheel = 2, speed = -3.0, duration_ms = 500 }";
    let s = Scenario::from_toml(text, Path::new("t.toml")).unwrap();
    let t = s.actions[0].wheel_test.unwrap();
    assert_eq!((t.wheel, t.speed, t.duration_ms), (2, -3.0, 500));
    for (table, needle) in [
        (
            "wheel = 4, speed = 3.0, duration_ms = 500",
            "actions[0].wheel_test.wheel = 4",
        ),
        (
            "wheel = 0, speed = 11.0, duration_ms = 500",
            "actions[0].wheel_test.speed = 11",
        ),
        (
            "wheel = 0, speed = 3.0, duration_ms = 0",
            "actions[0].wheel_test.duration_ms = 0",
        ),
    ] {
        let text = format!("duration_s = 2.0\n[[actions]]\nat_s = 0.1\nwheel_test = {{ {table} }}");
        let e = Scenario::from_toml(&text, Path::new("t.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains(needle), "{table}: {e}");
    }
}

#[test]
fn plant_wiring_parses_and_a_bad_wheel_is_named() {
    let text = "duration_s = 1.0\n[plant]\nflip = [1]\nswap = [[0, 2], [2, 3]]\nlifted = true";
    let s = Scenario::from_toml(text, Path::new("w.toml")).unwrap();
    assert_eq!((s.plant.flip.as_slice(), s.plant.lifted), (&[1][..], true));
    // FL <-> RL, then RL <-> RR: RL is on FL's id... applied in order.
    assert_eq!(s.plant.wired_ids([1u8, 2, 3, 4]), [3, 2, 4, 1]);
    assert_eq!(
        s.plant.wired_inverted([false, true, false, true]),
        [false, false, false, true]
    );
    for (table, needle) in [
        ("flip = [4]", "plant.flip = 4: a wheel index 0..=3"),
        ("flip = [1, 1]", "plant.flip = 1: each wheel at most once"),
        ("swap = [[2, 2]]", "plant.swap = 2: two different wheels"),
        ("swap = [[0, 7]]", "plant.swap = 7: a wheel index 0..=3"),
    ] {
        let text = format!("duration_s = 1.0\n[plant]\n{table}");
        let e = Scenario::from_toml(&text, Path::new("w.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains(needle), "{table}: {e}");
    }
}

#[test]
fn plant_table_parses_validates_and_changes_only_the_robot() {
    let text = "duration_s = 1.0\n[plant]\nwheel_radius = 0.0775\nlx = 0.194\nroller_drag = 0.2";
    let s = Scenario::from_toml(text, Path::new("p.toml")).unwrap();
    assert_eq!(
        s.plant,
        PlantSpec {
            wheel_radius: Some(0.0775),
            lx: Some(0.194),
            ly: None,
            roller_drag: Some(0.2),
            ..PlantSpec::default()
        }
    );
    let mut chassis = ChassisParams::from_config(&s.config);
    s.plant.apply(&mut chassis).unwrap();
    let xs: Vec<[f64; 3]> = chassis
        .wheels
        .iter()
        .map(|w| [w.x, w.y, w.radius])
        .collect();
    // ly stays the configuration's (an f32).
    let ly = f64::from(0.18f32);
    assert_eq!(
        xs,
        [
            [0.194, ly, 0.0775],
            [0.194, -ly, 0.0775],
            [-0.194, ly, 0.0775],
            [-0.194, -ly, 0.0775]
        ]
    );
    assert_eq!(chassis.roller_drag, 0.2);
    // The firmware's configuration is the file's (the DJI example), untouched.
    assert_eq!(s.config, Config::dji_m3508_example());

    for (bad, want) in [
        (
            "wheel_radius = 0.0",
            "plant.wheel_radius = 0: a radius in (0, 1] m",
        ),
        ("lx = -0.2", "plant.lx = -0.2: a distance in (0, 5] m"),
        ("ly = nan", "plant.ly = NaN: a distance in (0, 5] m"),
        (
            "roller_drag = 1.0",
            "plant.roller_drag = 1: a roller drag in [0, 1)",
        ),
        ("mass = 3.0", "unknown field `mass`"),
    ] {
        let text = format!("duration_s = 1.0\n[plant]\n{bad}");
        let e = Scenario::from_toml(&text, Path::new("bad.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains(want) && e.contains("bad.toml"), "{bad}: {e}");
    }

    // lx and ly are the standard layout's: another layout is refused, naming the field.
    let mut general = ChassisParams::default();
    general.wheels[0].x = 0.3;
    let e = PlantSpec {
        ly: Some(0.2),
        ..PlantSpec::default()
    }
    .apply(&mut general)
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("plant.ly = 0.2") && e.contains("standard layout"),
        "{e}"
    );

    // The calibration built-in fixes its robot to the example's.
    let c = Scenario::builtin("calibration").unwrap();
    assert_eq!(c.plant, PlantSpec::dji_m3508_example());
    assert_eq!(c.plant.lx, Some(f64::from(0.20f32)));
    assert!(Scenario::builtin("square").unwrap().plant.is_empty());
}

#[test]
fn fault_names_are_the_ones_a_file_uses() {
    use FaultName::*;
    for kind in [
        Drop,
        Burst,
        Delay,
        Corrupt,
        StuckEncoder,
        MotorOffline,
        NonFiniteTwist,
        RepeatedTwist,
        DriveSilent,
        DriveReboot,
        DriveFault,
        EnableRefused,
        SdoAbort,
        DriveBusOff,
        PodsSilent,
        RunnerRestart,
    ] {
        let parsed: FaultName =
            serde::de::Deserialize::deserialize(serde::de::value::StrDeserializer::<
                serde::de::value::Error,
            >::new(kind.as_str()))
            .unwrap();
        assert_eq!(parsed, kind);
    }
}
