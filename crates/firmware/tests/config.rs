//! Configuration files: the examples load and equal the built-in examples; bad values are
//! refused with the field and the value named.
#![cfg(feature = "std")]

use std::path::Path;

use firmware::config::{Config, LoadError};
use kinematics::Effectiveness;

fn repo_file(name: &str) -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .join(name)
}

#[test]
fn example_files_match_the_built_in_examples() {
    let dji = Config::from_toml_file(&repo_file("config/dji_m3508.toml")).unwrap();
    assert_eq!(dji, Config::dji_m3508_example());
    let odrive = Config::from_toml_file(&repo_file("config/odrive.toml")).unwrap();
    assert_eq!(odrive, Config::odrive_example());
    let cia402 = Config::from_toml_file(&repo_file("config/cia402.toml")).unwrap();
    assert_eq!(cia402, Config::cia402_example());
}

/// The CiA 402 example with one line replaced.
fn cia402_with(from: &str, to: &str) -> Result<Config, String> {
    let text = std::fs::read_to_string(repo_file("config/cia402.toml")).unwrap();
    assert!(text.contains(from), "fixture line {from:?} missing");
    Config::from_toml_str(&text.replacen(from, to, 1)).map_err(|e| e.to_string())
}

#[test]
fn cia402_nodes_and_axes_are_checked_naming_the_wheel() {
    for (from, to, error) in [
        (
            "node_ids = [1, 1, 2, 2]",
            "node_ids = [1, 1, 2, 0]",
            "drive.node_ids[3] (RR) = 0: a CANopen node id in 1..=127",
        ),
        (
            "axes = [1, 2, 1, 2]",
            "axes = [1, 1, 1, 2]",
            "drive.axes[1] (FR) = 1: a different axis (1 or 2) of a node that drives two wheels; \
             0 only on a node that drives one",
        ),
        (
            "axes = [1, 2, 1, 2]",
            "axes = [0, 2, 1, 2]",
            "drive.axes[1] (FR) = 2: a different axis (1 or 2) of a node that drives two wheels; \
             0 only on a node that drives one",
        ),
        (
            "axes = [1, 2, 1, 2]",
            "axes = [1, 2, 1, 3]",
            "drive.axes[3] (RR) = 3: 0 (a single-axis drive) or 1, 2 (an axis of a dual-axis drive)",
        ),
        (
            "master_node = 127",
            "master_node = 2",
            "drive.master_node = 2: a node id in 1..=127 that no drive has",
        ),
        (
            "heartbeat_timeout_ms = 150",
            "heartbeat_timeout_ms = 50",
            "drive.heartbeat_timeout_ms = 50: a time longer than drive.heartbeat_ms",
        ),
        (
            "actual_rpm_per_unit = 0.1",
            "actual_rpm_per_unit = 0.0",
            "drive.actual_rpm_per_unit = 0: a finite number > 0",
        ),
    ] {
        let e = cia402_with(from, to).unwrap_err();
        assert!(e.ends_with(error), "{to}: {e}");
    }
    // Four single-axis nodes are a valid layout.
    let single = cia402_with("axes = [1, 2, 1, 2]", "axes = [0, 0, 0, 0]");
    assert!(single.is_err(), "nodes 1 and 2 drive two wheels each");
    let text = std::fs::read_to_string(repo_file("config/cia402.toml"))
        .unwrap()
        .replacen("node_ids = [1, 1, 2, 2]", "node_ids = [1, 2, 3, 4]", 1)
        .replacen("axes = [1, 2, 1, 2]", "axes = [0, 0, 0, 0]", 1);
    Config::from_toml_str(&text).expect("four single-axis drives");
}

#[test]
fn toml_round_trip() {
    for c in [
        Config::dji_m3508_example(),
        Config::odrive_example(),
        Config::cia402_example(),
    ] {
        assert_eq!(Config::from_toml_str(&c.to_toml_string()).unwrap(), c);
    }
}

/// The DJI example with one line replaced.
fn dji_with(from: &str, to: &str) -> String {
    let text = std::fs::read_to_string(repo_file("config/dji_m3508.toml")).unwrap();
    assert!(text.contains(from), "fixture line {from:?} missing");
    text.replacen(from, to, 1)
}

fn invalid(text: &str) -> String {
    match Config::from_toml_str(text) {
        Err(e @ LoadError::Invalid { .. }) => e.to_string(),
        other => panic!("expected a validation error, got {other:?}"),
    }
}

#[test]
fn out_of_range_values_name_field_and_value() {
    let cases = [
        (
            "esc_ids = [1, 2, 3, 4]",
            "esc_ids = [1, 2, 3, 9]",
            "drive.esc_ids[3] (RR) = 9",
        ),
        (
            "esc_ids = [1, 2, 3, 4]",
            "esc_ids = [1, 1, 3, 4]",
            "drive.esc_ids[1] (FR) = 1",
        ),
        (
            "wheel_radius = 0.076",
            "wheel_radius = -0.076",
            "geometry.wheel_radius = -0.076",
        ),
        ("lx = 0.20", "lx = nan", "geometry.lx = NaN"),
        (
            "max_current = 16.0",
            "max_current = 25.0",
            "limits.max_current = 25",
        ),
        (
            "max_wheel_speed = 45.0",
            "max_wheel_speed = 0.0",
            "limits.max_wheel_speed = 0",
        ),
        (
            "odometry_hz = 100",
            "odometry_hz = 300",
            "timing.odometry_hz = 300",
        ),
        (
            "command_timeout_ms = 100",
            "command_timeout_ms = 0",
            "timing.command_timeout_ms = 0",
        ),
        (
            "stale_periods = 3",
            "stale_periods = 1",
            "timing.stale_periods = 1",
        ),
        ("kp = 1.2", "kp = -1.0", "gains.kp = -1"),
        (
            "gear_ratio = ",
            "gear_ratio = 1e-43 #",
            "drive.gear_ratio = 0.0000000000000000000000000000000000000000001: a ratio in 0.01..=1000",
        ),
    ];
    for (from, to, want) in cases {
        let msg = invalid(&dji_with(from, to));
        assert!(msg.contains(want), "{to}: {msg}");
        assert!(msg.starts_with("<string>:"), "{msg}");
    }
}

#[test]
fn infinite_stop_deceleration_is_allowed() {
    let c = Config::from_toml_str(&dji_with(
        "stop_linear_decel = 8.0",
        "stop_linear_decel = inf",
    ))
    .unwrap();
    assert!(c.limits.stop_linear_decel.is_infinite());
}

#[test]
fn singular_layout_is_refused() {
    let msg = invalid(&dji_with("lx = 0.20", "lx = 0.0").replace("ly = 0.18", "ly = 0.0"));
    assert!(msg.contains("geometry"), "{msg}");
}

#[test]
fn syntax_unknown_fields_and_types_are_toml_errors_with_a_line() {
    for (from, to, want) in [
        ("kp = 1.2", "kp = 1.2\nkd = 0.1", "kd"),
        ("model = \"c620\"", "model = \"c999\"", "c999"),
        ("control_hz = 1000", "control_hz = \"fast\"", "control_hz"),
        ("[limits]", "[limits", "line"),
    ] {
        match Config::from_toml_str(&dji_with(from, to)) {
            Err(e @ LoadError::Toml { .. }) => {
                let msg = e.to_string();
                assert!(msg.contains(want), "{to}: {msg}");
                assert!(msg.contains("line"), "{to}: no line in {msg}");
            }
            other => panic!("{to}: expected a TOML error, got {other:?}"),
        }
    }
}

/// A TOML error's text, from a file's text with one line replaced.
fn toml_error(file: &str, from: &str, to: &str) -> String {
    let text = std::fs::read_to_string(repo_file(file)).unwrap();
    assert!(text.contains(from), "fixture line {from:?} missing");
    match Config::from_toml_str(&text.replacen(from, to, 1)) {
        Err(e @ LoadError::Toml { .. }) => e.to_string(),
        other => panic!("{to}: expected a TOML error, got {other:?}"),
    }
}

/// A value of the wrong type or length names its key path, the value and the rule, on the
/// key's line: inside `[geometry]` and `[drive]`, tables tagged by `layout` and `protocol`
/// (every variant), as in the plain tables.
#[test]
fn wrong_types_name_the_key_path_value_and_line() {
    for (file, from, to, want) in [
        (
            "config/dji_m3508.toml",
            "lx = 0.20",
            "lx = \"0.20\"",
            "geometry.lx = \"0.20\": invalid type: string \"0.20\", expected a number (f32)",
        ),
        (
            "config/dji_m3508.toml",
            "esc_ids = [1, 2, 3, 4]",
            "esc_ids = \"1,2,3,4\"",
            "drive.esc_ids = \"1,2,3,4\": invalid type: string \"1,2,3,4\", expected an array \
             of length 4",
        ),
        (
            "config/dji_m3508.toml",
            "esc_ids = [1, 2, 3, 4]",
            "esc_ids = [1, 2, 3]",
            "drive.esc_ids = [1, 2, 3]: invalid length 3, expected an array of length 4",
        ),
        (
            "config/dji_m3508.toml",
            "esc_ids = [1, 2, 3, 4]",
            "esc_ids = [1, 2, 3, 300]",
            "drive.esc_ids[3] = 300: invalid value: integer `300`, expected an integer in \
             0..=255 (u8)",
        ),
        (
            "config/dji_m3508.toml",
            "kp = 1.2",
            "kp = \"1.2\"",
            "gains.kp = \"1.2\": invalid type: string \"1.2\", expected a number (f32)",
        ),
        (
            "config/odrive.toml",
            "gear_ratio = 5.0",
            "gear_ratio = \"5:1\"",
            "drive.gear_ratio = \"5:1\": invalid type: string \"5:1\", expected a number (f32)",
        ),
        (
            "config/odrive.toml",
            "vel_ramp = false",
            "vel_ramp = 0",
            "drive.vel_ramp = 0: invalid type: integer `0`, expected a boolean",
        ),
        (
            "config/cia402.toml",
            "heartbeat_ms = 50",
            "heartbeat_ms = 50.5",
            "drive.heartbeat_ms = 50.5: invalid type: floating point `50.5`, expected an \
             integer in 0..=65535 (u16)",
        ),
        (
            "config/cia402.toml",
            "axes = [1, 2, 1, 2]",
            "axes = [1, 2, 1, -2]",
            "drive.axes[3] = -2: invalid value: integer `-2`, expected an integer in 0..=255 (u8)",
        ),
        (
            "config/dji_m3508_pods3.toml",
            "radius = 0.024 ",
            "radius = \"24 mm\" ",
            "odometry.pods[0].radius = \"24 mm\": invalid type: string \"24 mm\", expected a \
             number (f32)",
        ),
    ] {
        let msg = toml_error(file, from, to);
        assert!(msg.ends_with(want), "{to}: {msg}");
        let text = std::fs::read_to_string(repo_file(file)).unwrap();
        let line = text.lines().position(|l| l.starts_with(from)).unwrap() + 1;
        assert!(msg.contains(&format!("at line {line},")), "{to}: {msg}");
        assert!(msg.contains(&format!("{line} | {to}")), "{to}: {msg}");
    }
}

/// The tagged tables keep the derive's rules, wherever the tag stands: each variant takes its
/// own keys, a missing one is named, an unknown one is named at its line.
#[test]
fn tagged_tables_name_unknown_missing_and_foreign_keys() {
    for (file, from, to, want) in [
        (
            "config/dji_m3508.toml",
            "esc_ids = [1, 2, 3, 4]",
            "node_ids = [1, 2, 3, 4]",
            "drive: unknown field `node_ids`, expected one of `model`, `esc_ids`, \
             `gear_ratio`, `inverted`",
        ),
        (
            "config/odrive.toml",
            "vel_ramp = false",
            "vel_ramp = false\nmodel = \"c620\"",
            "drive: unknown field `model`, expected one of `node_ids`, `gear_ratio`, \
             `inverted`, `vel_ramp`",
        ),
        (
            "config/dji_m3508.toml",
            "protocol = \"dji\"",
            "protocol = \"dji\"\nvel_ramp = true",
            "drive.vel_ramp: unknown field `vel_ramp`, expected one of `model`, `esc_ids`, \
             `gear_ratio`, `inverted`",
        ),
        (
            "config/dji_m3508.toml",
            "layout = \"standard\"",
            "layout = \"general\"",
            "geometry.lx: unknown field `lx`, expected one of `wheels`, \
             `forward_effectiveness`, `lateral_effectiveness`, `yaw_effectiveness`",
        ),
        (
            "config/dji_m3508.toml",
            "ly = 0.18",
            "lz = 0.18",
            "geometry.lz: unknown field `lz`, expected one of `lx`, `ly`, `wheel_radius`, \
             `forward_effectiveness`, `lateral_effectiveness`, `yaw_effectiveness`",
        ),
        (
            "config/dji_m3508.toml",
            "esc_ids = [1, 2, 3, 4]",
            "esc_ids = [1, 2, 3, 4]\nesc_id = 5",
            "drive.esc_id: unknown field `esc_id`, expected one of `protocol`, `model`, \
             `esc_ids`, `gear_ratio`, `inverted`, `node_ids`, `vel_ramp`, `axes`, \
             `target_rpm_per_unit`, `actual_rpm_per_unit`, `master_node`, `heartbeat_ms`, \
             `heartbeat_timeout_ms`",
        ),
        (
            "config/dji_m3508.toml",
            "wheel_radius = 0.076",
            "",
            "geometry: missing field `wheel_radius`",
        ),
        (
            "config/cia402.toml",
            "protocol = \"cia402\"",
            "",
            "drive: missing field `protocol`",
        ),
        (
            "config/cia402.toml",
            "protocol = \"cia402\"",
            "protocol = \"canopen\"",
            "drive.protocol = \"canopen\": unknown variant `canopen`, expected one of `dji`, \
             `odrive`, `cia402`",
        ),
    ] {
        let msg = toml_error(file, from, to);
        assert!(msg.ends_with(want), "{to}: {msg}");
    }
    // The tag after the keys it selects.
    let text = std::fs::read_to_string(repo_file("config/cia402.toml"))
        .unwrap()
        .replacen("protocol = \"cia402\"\n", "", 1)
        .replacen(
            "heartbeat_timeout_ms = 150",
            "heartbeat_timeout_ms = 150\nprotocol = \"cia402\"",
            1,
        );
    assert_eq!(
        Config::from_toml_str(&text).unwrap(),
        Config::cia402_example()
    );
}

#[test]
fn missing_file_is_an_io_error_naming_it() {
    let e = Config::from_toml_file(Path::new("no/such/config.toml")).unwrap_err();
    assert!(matches!(e, LoadError::Io { .. }));
    assert!(e.to_string().contains("no/such/config.toml"));
}

#[test]
fn an_odrive_node_whose_ids_are_the_robot_protocols_is_refused() {
    let text = std::fs::read_to_string(repo_file("config/odrive.toml")).unwrap();
    let from = "node_ids = [0, 1, 2, 3]";
    assert!(text.contains(from));
    let msg = invalid(&text.replacen(from, "node_ids = [0, 1, 24, 3]", 1));
    assert!(msg.contains("drive.node_ids[2] (RL) = 24"), "{msg}");
    assert!(msg.contains("0x300..=0x31F"), "{msg}");
    // Its neighbours are fine.
    for n in [23, 25] {
        let ok = text.replacen(from, &format!("node_ids = [0, 1, {n}, 3]"), 1);
        Config::from_toml_str(&ok).unwrap();
    }
}

/// The DJI example with its three effectiveness lines removed (a configuration written before
/// they existed).
fn dji_without_effectiveness() -> String {
    let text = std::fs::read_to_string(repo_file("config/dji_m3508.toml")).unwrap();
    let kept: Vec<&str> = text
        .lines()
        .filter(|l| !l.contains("_effectiveness ="))
        .collect();
    assert_eq!(
        kept.len() + 3,
        text.lines().count(),
        "three effectiveness lines"
    );
    kept.join("\n")
}

#[test]
fn effectiveness_defaults_to_one_and_is_left_out_of_the_toml_at_one() {
    let c = Config::from_toml_str(&dji_without_effectiveness()).unwrap();
    assert_eq!(c, Config::dji_m3508_example());
    assert_eq!(
        c.geometry.effectiveness(),
        Effectiveness::new(1.0, 1.0, 1.0)
    );
    // What the logs carry: the same text as before the keys existed.
    let toml = c.to_toml_string();
    assert!(!toml.contains("effectiveness"), "{toml}");
    // A factor other than 1 is written, and reads back to the bit.
    let c = Config::from_toml_str(&dji_with(
        "lateral_effectiveness = 1.0",
        "lateral_effectiveness = 0.72",
    ))
    .unwrap();
    assert_eq!(
        c.geometry.effectiveness(),
        Effectiveness::new(1.0, 0.72, 1.0)
    );
    let toml = c.to_toml_string();
    assert!(toml.contains("lateral_effectiveness = 0.72"), "{toml}");
    assert!(!toml.contains("forward_effectiveness"), "{toml}");
    assert_eq!(Config::from_toml_str(&toml).unwrap(), c);
    assert_eq!(c.kinematics().unwrap().effectiveness().ky, 0.72);
}

#[test]
fn effectiveness_out_of_range_names_the_key_and_value() {
    for key in ["forward", "lateral", "yaw"] {
        for (value, shown) in [
            ("0.0", "= 0:"),
            ("-1.0", "= -1:"),
            ("1.6", "= 1.6:"),
            ("nan", "= NaN:"),
            ("inf", "= inf:"),
            ("1.5000001", "= 1.5000001:"),
        ] {
            let from = format!("{key}_effectiveness = 1.0");
            let msg = invalid(&dji_with(&from, &format!("{key}_effectiveness = {value}")));
            let want = format!("geometry.{key}_effectiveness {shown} a factor in (0, 1.5]");
            assert!(msg.contains(&want), "{value}: {msg}");
        }
        // The bounds are accepted.
        for value in ["1.5", "0.01", "0.72"] {
            let from = format!("{key}_effectiveness = 1.0");
            Config::from_toml_str(&dji_with(&from, &format!("{key}_effectiveness = {value}")))
                .unwrap();
        }
    }
    // In range but so small that the scaled wheel map overflows f32: still the key.
    let msg = invalid(&dji_with(
        "yaw_effectiveness = 1.0",
        "yaw_effectiveness = 1e-38",
    ));
    assert!(
        msg.contains("geometry.yaw_effectiveness = 0.00000000000000000000000000000000000001"),
        "{msg}"
    );
    assert!(msg.contains("fits f32"), "{msg}");
}

#[test]
fn a_general_layout_takes_the_effectiveness_keys_too() {
    let wheel = |x: f32, y: f32, roller: &str| {
        format!(
            "[[geometry.wheels]]\nx = {x}\ny = {y}\naxle_angle = 1.5707964\n\
             roller_angle = {roller}\nradius = 0.076\n"
        )
    };
    let text = std::fs::read_to_string(repo_file("config/dji_m3508.toml")).unwrap();
    let drive = &text[text.find("[drive]").unwrap()..];
    let general = format!(
        "[geometry]\nlayout = \"general\"\nlateral_effectiveness = 0.75\n{}{}{}{}\n{drive}",
        wheel(0.2, 0.18, "0.7853982"),
        wheel(0.2, -0.18, "-0.7853982"),
        wheel(-0.2, 0.18, "-0.7853982"),
        wheel(-0.2, -0.18, "0.7853982"),
    );
    let c = Config::from_toml_str(&general).unwrap();
    assert_eq!(
        c.geometry.effectiveness(),
        Effectiveness::new(1.0, 0.75, 1.0)
    );
    assert_eq!(c.kinematics().unwrap().effectiveness().ky, 0.75);
    let bad = general.replace("lateral_effectiveness = 0.75", "lateral_effectiveness = 0");
    let msg = invalid(&bad);
    assert!(msg.contains("geometry.lateral_effectiveness = 0:"), "{msg}");
}

#[test]
fn odometry_defaults_to_wheel_heading_and_is_left_out_of_the_toml_at_its_defaults() {
    use firmware::config::{HeadingMode, OdometryConfig};
    let d = OdometryConfig::default();
    assert_eq!(
        (
            d.heading_source,
            d.gyro_timeout_ms,
            d.gyro_standstill_ms,
            d.gyro_bias_estimation
        ),
        (HeadingMode::Wheels, 50, 50, true)
    );
    // A configuration written before the section existed loads with the defaults, and
    // writes the same text as before (no [odometry] at all).
    let text = std::fs::read_to_string(repo_file("config/dji_m3508.toml")).unwrap();
    let before = text.split("\n[odometry]").next().unwrap();
    let c = Config::from_toml_str(before).unwrap();
    assert_eq!(c, Config::dji_m3508_example());
    assert!(!c.to_toml_string().contains("[odometry]"));
    assert_eq!(
        c.to_toml_string(),
        Config::dji_m3508_example().to_toml_string()
    );
    assert!(!Config::odrive_example().to_toml_string().contains("gyro"));

    let gyro = Config::from_toml_file(&repo_file("config/dji_m3508_gyro.toml")).unwrap();
    assert_eq!(gyro.odometry.heading_source, HeadingMode::Gyro);
    assert_eq!(
        Config {
            odometry: OdometryConfig::default(),
            ..gyro
        },
        Config::dji_m3508_example()
    );
    let toml = gyro.to_toml_string();
    assert!(
        toml.contains("[odometry]") && toml.contains("heading_source = \"gyro\""),
        "{toml}"
    );
    assert_eq!(Config::from_toml_str(&toml).unwrap(), gyro);
    // One key alone: the others take their defaults.
    let c = Config::from_toml_str(&format!(
        "{before}\n[odometry]\nheading_source = \"gyro\"\ngyro_bias_estimation = false\n"
    ))
    .unwrap();
    assert_eq!(
        c.odometry,
        OdometryConfig {
            heading_source: HeadingMode::Gyro,
            gyro_bias_estimation: false,
            ..OdometryConfig::default()
        }
    );
}

#[test]
fn odometry_values_out_of_range_name_the_key_and_value() {
    for (from, to, want) in [
        (
            "gyro_timeout_ms = 50 ",
            "gyro_timeout_ms = 0 ",
            "odometry.gyro_timeout_ms = 0: a timeout in 1..=10000 ms",
        ),
        (
            "gyro_timeout_ms = 50 ",
            "gyro_timeout_ms = 10001 ",
            "odometry.gyro_timeout_ms = 10001: a timeout in 1..=10000 ms",
        ),
        (
            "gyro_standstill_ms = 50 ",
            "gyro_standstill_ms = 60001 ",
            "odometry.gyro_standstill_ms = 60001: a time in 0..=60000 ms",
        ),
    ] {
        let msg = invalid(&dji_with(from, to));
        assert!(msg.contains(want), "{to}: {msg}");
    }
    // 0 ms of standstill is allowed: every standstill reading counts.
    let c = Config::from_toml_str(&dji_with(
        "gyro_standstill_ms = 50 ",
        "gyro_standstill_ms = 0 ",
    ));
    assert_eq!(c.unwrap().odometry.gyro_standstill_ms, 0);
    // A source that does not exist, or a misspelt key: TOML errors naming the value or key
    // and the line.
    for (from, to, want) in [
        (
            "heading_source = \"wheels\"",
            "heading_source = \"compass\"",
            "unknown variant `compass`, expected `wheels` or `gyro`",
        ),
        (
            "gyro_timeout_ms = 50 ",
            "gyro_timeout = 50 ",
            "unknown field `gyro_timeout`",
        ),
        (
            "gyro_bias_estimation = true",
            "gyro_bias_estimation = 1",
            "invalid type",
        ),
    ] {
        let msg = match Config::from_toml_str(&dji_with(from, to)) {
            Err(e @ LoadError::Toml { .. }) => e.to_string(),
            other => panic!("{to}: {other:?}"),
        };
        assert!(msg.contains(want) && msg.contains("line"), "{to}: {msg}");
    }
}

/// Every example file and a configuration that sets what they leave at defaults (general
/// layout, C610, a velocity ramp, an infinite stop, gyro heading) reads back from its
/// encoding exactly, and no two of them share an id.
#[test]
fn encoding_reads_back_every_field_and_ids_tell_configurations_apart() {
    use firmware::config::{Drive, Geometry, HeadingMode, WheelConfig};
    use firmware::protocol::dji::EscModel;
    let mut configs: Vec<Config> = [
        "dji_m3508",
        "dji_m3508_gyro",
        "dji_m3508_pods3",
        "dji_m3508_pods2_gyro",
        "odrive",
    ]
    .iter()
    .map(|name| Config::from_toml_file(&repo_file(&format!("config/{name}.toml"))).unwrap())
    .collect();
    let mut general = Config::dji_m3508_example();
    let wheel = |x: f32, y: f32, roller: f32| WheelConfig {
        x,
        y,
        axle_angle: core::f32::consts::FRAC_PI_2,
        roller_angle: roller,
        radius: 0.076,
    };
    let q = core::f32::consts::FRAC_PI_4;
    general.geometry = Geometry::General {
        wheels: [
            wheel(0.2, 0.18, -q),
            wheel(0.2, -0.18, q),
            wheel(-0.2, 0.18, q),
            wheel(-0.2, -0.18, -q),
        ],
        forward_effectiveness: 0.97,
        lateral_effectiveness: 0.75,
        yaw_effectiveness: 0.9,
    };
    general.drive = Drive::Dji {
        model: EscModel::C610,
        esc_ids: [5, 6, 7, 8],
        gear_ratio: 36.0,
        inverted: [true, false, true, false],
    };
    general.limits.stop_linear_decel = f32::INFINITY;
    general.limits.max_current = 9.0;
    general.odometry.heading_source = HeadingMode::Gyro;
    general.odometry.gyro_bias_estimation = false;
    general.validate().unwrap();
    let mut ramp = Config::odrive_example();
    if let Drive::Odrive { vel_ramp, .. } = &mut ramp.drive {
        *vel_ramp = true;
    }
    configs.extend([general, ramp]);
    for c in &configs {
        assert_eq!(Config::decode(&c.encode()).as_ref(), Ok(c));
    }
    let mut ids: Vec<u16> = configs.iter().map(Config::id).collect();
    ids.sort_unstable();
    ids.dedup();
    assert_eq!(ids.len(), configs.len());
}

/// The pod configurations load, round-trip through TOML, and every wrong pod value or
/// layout is refused naming the field and why.
#[test]
fn tracking_pods_are_validated_naming_the_field_and_why() {
    use firmware::config::OdometryMode;
    let pods3 = Config::from_toml_file(&repo_file("config/dji_m3508_pods3.toml")).unwrap();
    assert_eq!(pods3.odometry.source, OdometryMode::Pods3);
    assert_eq!(pods3.odometry.pods.len(), 3);
    assert_eq!(
        Config::from_toml_str(&pods3.to_toml_string()).unwrap(),
        pods3
    );
    let pods2 = Config::from_toml_file(&repo_file("config/dji_m3508_pods2_gyro.toml")).unwrap();
    assert_eq!(pods2.odometry.source, OdometryMode::Pods2Gyro);
    assert_eq!(
        Config::from_toml_str(&pods2.to_toml_string()).unwrap(),
        pods2
    );
    assert_ne!(pods3.id(), pods2.id());

    let text = std::fs::read_to_string(repo_file("config/dji_m3508_pods3.toml")).unwrap();
    let with = |from: &str, to: &str| {
        assert!(text.contains(from), "fixture {from:?} missing");
        text.replacen(from, to, 1)
    };
    for (from, to, error) in [
        (
            "source = \"pods3\"",
            "source = \"pods2_gyro\"",
            "odometry.heading_source = 0: \"gyro\" with odometry.source = \"pods2_gyro\"",
        ),
        (
            "source = \"pods3\"",
            "source = \"wheels\"",
            "odometry.pods = 3: no pods with odometry.source = \"wheels\"",
        ),
        (
            "radius = 0.024                # m, the omni",
            "radius = 0.0                # m, the omni",
            "odometry.pods.radius[0] = 0: a radius in (0, 1] m",
        ),
        (
            "counts_per_turn = 2000        # quadrature",
            "counts_per_turn = 0        # quadrature",
            "odometry.pods.counts_per_turn[0] = 0",
        ),
        (
            "pod_timeout_ms = 50 ",
            "pod_timeout_ms = 0 ",
            "odometry.pod_timeout_ms = 0",
        ),
        // Pod 2 counting forward too: all three parallel, sideways motion unseen.
        (
            "direction_deg = 90.0",
            "direction_deg = 0.0",
            "odometry.pods.direction_deg = 0: three pods not all parallel",
        ),
        // Pod 2 on the centre line, counting leftwards, and the two forward pods moved onto
        // the x axis: all three lines meet at the origin, a spin about it is invisible.
        (
            "y = 0.11 ",
            "y = 0.0 ",
            "odometry.pods = NaN: three pods whose lines of action do not meet in one point",
        ),
    ] {
        let mut t = with(from, to);
        if from == "y = 0.11 " {
            t = t
                .replacen("y = -0.11", "y = 0.0", 1)
                .replacen("x = 0.12", "x = 0.0", 1);
        }
        let got = invalid(&t);
        assert!(got.contains(error), "{to:?}: got {got}, want {error}");
    }
    // Two pods counting along parallel lines.
    let text2 = std::fs::read_to_string(repo_file("config/dji_m3508_pods2_gyro.toml")).unwrap();
    let got = invalid(&text2.replacen("direction_deg = 90.0", "direction_deg = 180.0", 1));
    assert!(
        got.contains("odometry.pods.direction_deg[1] = -180: a direction not parallel"),
        "{got}"
    );
    // A fourth pod: POD_COUNTS carries three.
    let four = format!(
        "{text}\n[[odometry.pods]]\nx = 0.0\ny = 0.0\ndirection_deg = 45.0\nradius = 0.024\ncounts_per_turn = 2000\n"
    );
    let got = Config::from_toml_str(&four).unwrap_err().to_string();
    assert!(got.contains("at most 3 pods"), "{got}");
}
