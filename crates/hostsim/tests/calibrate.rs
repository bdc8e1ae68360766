//! `hostsim calibrate` on the simulator: the calibrated rerun's drift, the recovery of a robot
//! built unlike its configuration, the refusal of a log without the motion a value needs, a
//! tracker's poses as the reference, and the command line. Every figure is printed
//! (`cargo test -p hostsim --test calibrate -- --nocapture`).

mod common;

use std::collections::BTreeMap;
use std::ffi::OsStr;
use std::path::Path;

use common::{fit, hostsim, logged_run, print_fit, scratch};
use firmware::Config;
use firmware::config::Geometry;
use hostsim::analysis::calibrate::{CalibrateError, GeometryValues, Options, calibrate};
use hostsim::engine::RunSummary;
use hostsim::nodes::plant::PlantSpec;
use hostsim::nodes::plant::{Chassis, ChassisParams, WheelInput};
use hostsim::scenario::{Action, Scenario};
use kinematics::ChassisVelocity;

/// A scenario on the DJI example's robot (fixed: `[plant]`), run with `config`: after the
/// enable, each leg `(vx, vy, wz, seconds)` in turn, `stop_s` standing still after each
/// (none if 0), then 1 s standing still.
fn legs(name: &str, config: Config, legs: &[(f32, f32, f32, f64)], stop_s: f64) -> Scenario {
    let mut s = Scenario::builtin("square").unwrap();
    s.name = name.to_string();
    s.config = config;
    s.plant = PlantSpec::dji_m3508_example();
    s.actions.truncate(1); // the enable
    let mut t = 0.1;
    for &(vx, vy, wz, dur) in legs {
        s.actions.push(Action::twist(t, vx, vy, wz));
        t += dur;
        if stop_s > 0.0 {
            s.actions.push(Action::twist(t, 0.0, 0.0, 0.0));
            t += stop_s;
        }
    }
    s.actions.push(Action::twist(t, 0.0, 0.0, 0.0));
    s.duration_s = t + 1.0;
    s
}

/// The built-in square's legs: 1 m each way at 0.5 m/s without turning (4 m of path).
const SQUARE: [(f32, f32, f32, f64); 4] = [
    (0.5, 0.0, 0.0, 2.0),
    (0.0, 0.5, 0.0, 2.0),
    (-0.5, 0.0, 0.0, 2.0),
    (0.0, -0.5, 0.0, 2.0),
];

/// The built-in compass's legs: the eight directions at 0.5 m/s, 1.5 s each (6 m of path).
fn compass() -> Vec<(f32, f32, f32, f64)> {
    let s = std::f32::consts::FRAC_1_SQRT_2 * 0.5;
    [
        (0.5, 0.0),
        (s, -s),
        (0.0, -0.5),
        (-s, -s),
        (-0.5, 0.0),
        (-s, s),
        (0.0, 0.5),
        (s, s),
    ]
    .map(|(vx, vy)| (vx, vy, 0.0, 1.5))
    .to_vec()
}

/// Runs and logs `scenario` under `group`, returning the summary and the log's path.
fn run(group: &str, scenario: &Scenario) -> (RunSummary, std::path::PathBuf) {
    let path = scratch(group, &format!("{}.mcap", scenario.name));
    (logged_run(scenario, &path), path)
}

/// The log of the built-in `calibration` run, run once for every test here that needs it.
fn calibration_log() -> &'static Path {
    static LOG: std::sync::OnceLock<std::path::PathBuf> = std::sync::OnceLock::new();
    LOG.get_or_init(|| {
        run(
            "calibrate-shared",
            &Scenario::builtin("calibration").unwrap(),
        )
        .1
    })
}

/// The loop of the README on the simulator: run `calibration`, calibrate, rerun with the
/// fitted values (the robot stays the example's: `[plant]`).
///
/// Targets: a square with a 0.5 s stop at each corner within 1 % of its 4 m path, the compass
/// with stops within 1.5 % of its 6 m, a commanded 1 m strafe 1 m ± 2 % in ground truth, and a
/// calibration of the calibrated run giving corrections of 1 (± 0.2 %).
///
/// The built-in square and compass, which change direction without stopping, keep most of
/// their drift (measured: square 295 -> 230 mm, 5.7 % of the path; compass 507 -> 252 mm,
/// 4.2 %), and are held only to that improvement: at each corner the body slides on in its
/// old direction for a while, which no wheel sees. In the plant (`plant::chassis`), a
/// strafing robot's rollers spin, its contacts slide, and sliding contacts hold little against
/// a sideways slip: the slip left over from the forward leg decays with a time constant of
/// 0.17 s in a 0.5 m/s strafe, 0.5 s in the 0.67 m/s wheel strafe the calibrated
/// configuration commands for it, 1.5 s at 1 m/s (measured with the chassis alone). The
/// faster wheels of the calibrated strafe slide further (0.16 m against 0.08 m). With a stop
/// at each corner the slide is gone and what is left is what the calibration addresses.
#[test]
fn the_calibrated_rerun_meets_the_drift_targets() {
    let wall = std::time::Instant::now();
    let group = "calibrate-rerun";
    let first = fit(calibration_log());
    print_fit("calibration of the example robot", &first);
    let calibrated = first.config;

    // A calibration of a run with the calibrated configuration: corrections of 1.
    let mut again = Scenario::builtin("calibration").unwrap();
    again.name = "calibration-calibrated".into();
    again.config = calibrated;
    let (_, log) = run(group, &again);
    let second = fit(&log);
    print_fit("calibration of the calibrated run", &second);
    for a in &second.axes {
        assert!(
            (a.correction - 1.0).abs() < 2e-3,
            "{}: correction {} after calibration",
            a.axis,
            a.correction
        );
    }

    let drift = |name: &str, config: Config, l: &[(f32, f32, f32, f64)], stop_s: f64| {
        let (s, _) = run(group, &legs(name, config, l, stop_s));
        s.max_position_error
    };
    let example = Config::dji_m3508_example();
    println!("max drift of the odometry (before -> after calibration):");
    let compass = compass();
    // (scenario, legs, stop at the corners, path m, largest drift after, as a fraction of it)
    for (name, l, stop_s, path_m, limit) in [
        ("square-stops", &SQUARE[..], 0.5, 4.0, 0.01),
        ("compass-stops", &compass[..], 0.5, 6.0, 0.015),
        // The corner slide's: the improvement measured, not the targets.
        ("square", &SQUARE[..], 0.0, 4.0, 0.06),
        ("compass", &compass[..], 0.0, 6.0, 0.045),
    ] {
        let before = drift(&format!("{name}-before"), example, l, stop_s);
        let after = drift(&format!("{name}-after"), calibrated, l, stop_s);
        println!(
            "  {name:<14} {:6.1} mm ({:4.2} %) -> {:5.1} mm ({:4.2} %) of {path_m} m",
            before * 1e3,
            before / path_m * 100.0,
            after * 1e3,
            after / path_m * 100.0
        );
        assert!(after <= limit * path_m, "{name}: {after} m");
        assert!(before >= 0.06 * path_m, "{name}: {before} m before");
    }

    // A commanded 1 m strafe.
    for (what, config) in [("before", example), ("after", calibrated)] {
        let (s, _) = run(
            group,
            &legs(
                &format!("strafe-1m-{what}"),
                config,
                &[(0.0, 0.5, 0.0, 2.0)],
                0.0,
            ),
        );
        println!(
            "  1 m strafe {what}: ground truth y {:.4} m, x {:+.4} m",
            s.truth[1], s.truth[0]
        );
        if what == "after" {
            assert!((s.truth[1] - 1.0).abs() <= 0.02, "{:?}", s.truth);
        } else {
            assert!(s.truth[1] < 0.8, "{:?}", s.truth);
        }
    }
    println!("wall time {:.2} s", wall.elapsed().as_secs_f64());
}

/// The yaw effectiveness of a chassis: its yaw rate over the commanded one in a steady spin
/// at `wz` with every wheel held at its ideal speed (the chassis alone, no drives).
fn spin_effectiveness(params: ChassisParams, wz: f64) -> f64 {
    let k = params.kinematics().unwrap();
    let wheels = k.inverse(ChassisVelocity::new(0.0, 0.0, wz));
    let inputs = wheels.as_array().map(WheelInput::Speed);
    let mut chassis = Chassis::new(params).unwrap();
    chassis.step(3.0, &inputs).unwrap();
    chassis.state().velocity.wz / wz
}

/// A robot built unlike its configuration (wheel radius +2 %, lx and ly -3 %, roller drag
/// 3/17: a pure strafe makes 0.7 of the command) under the example configuration: the fit
/// recovers the radius and the lateral effectiveness within 0.5 %.
///
/// lx + ly: rotation spins the rollers too, so the plant's own yaw effectiveness `η` is below
/// 1 and the *effective* lx + ly the odometry needs is the geometric one over `η`. `η` is
/// measured with the chassis alone (a steady spin at held wheel speeds) and checked against
/// the plant's model: the torque balance of the contact forces in a pure spin of a standard
/// layout gives `η = (L² + ε L (ly − lx)) / (L² + ε (ly − lx)²)`, `L = lx + ly`, 1 for
/// lx = ly. The fit must give `L / η` within 0.5 %. Under the same model the geometric value
/// follows back from the fit, with `ε = (1 − k_y)/(1 + k_y)` from the fitted lateral
/// effectiveness: that is checked too, but it holds for this roller model only, so
/// `hostsim calibrate` reports the effective value.
#[test]
fn the_fit_recovers_a_robot_built_unlike_its_configuration() {
    let logged = GeometryValues::of(&Config::dji_m3508_example().geometry).unwrap();
    let (lx, ly, r) = (
        0.97 * logged.lx,
        0.97 * logged.ly,
        1.02 * logged.wheel_radius,
    );
    let eps = 3.0 / 17.0;
    let plant = PlantSpec {
        wheel_radius: Some(r),
        lx: Some(lx),
        ly: Some(ly),
        roller_drag: Some(eps),
        ..PlantSpec::default()
    };
    let mut s = Scenario::builtin("calibration").unwrap();
    s.name = "calibration-unlike".into();
    s.plant = plant;
    let (_, log) = run("calibrate-recovery", &s);
    let c = fit(&log);
    print_fit(
        "calibration of the robot built unlike its configuration",
        &c,
    );

    let mut params = ChassisParams::standard(lx, ly, r);
    params.roller_drag = eps;
    let eta = spin_effectiveness(params, 1.5);
    let l = lx + ly;
    let eta_model = (l * l + eps * l * (ly - lx)) / (l * l + eps * (ly - lx).powi(2));
    println!("plant yaw effectiveness: measured {eta:.6}, model {eta_model:.6}");
    assert!((eta - eta_model).abs() < 1e-4, "{eta} vs {eta_model}");

    let check = |what: &str, got: f64, want: f64| {
        let error = got / want - 1.0;
        println!(
            "  {what:<32} fitted {got:.6}, true {want:.6}: error {:+.3} %",
            error * 100.0
        );
        assert!(error.abs() <= 0.005, "{what}: {got} vs {want}");
    };
    println!("recovery:");
    check("wheel_radius (m)", c.wheel_radius.value, r);
    check("lateral_effectiveness", c.lateral_effectiveness.value, 0.7);
    check(
        "lx + ly effective, L / eta (m)",
        c.lx_plus_ly.value,
        l / eta,
    );
    let k_y = c.lateral_effectiveness.value;
    let eps_fit = (1.0 - k_y) / (1.0 + k_y);
    let (px, py) = (lx / l, ly / l);
    let eta_fit = (1.0 + eps_fit * (py - px)) / (1.0 + eps_fit * (py - px).powi(2));
    check(
        "lx + ly geometric, model (m)",
        c.lx_plus_ly.value * eta_fit,
        l,
    );
    println!(
        "  (the effective lx + ly is {:+.2} % off the geometric one: the yaw slip)",
        (c.lx_plus_ly.value / l - 1.0) * 100.0
    );
    // Standard errors small against the 0.5 %.
    for e in [c.wheel_radius, c.lx_plus_ly, c.lateral_effectiveness] {
        assert!(e.stderr / e.value < 1e-3, "{e:?}");
    }
}

/// A log of straight driving alone cannot give the lateral effectiveness or lx + ly: refused,
/// naming each missing motion, by the library and by the command line (exit status 2).
#[test]
fn a_straight_only_log_is_refused_naming_the_missing_motion() {
    let example = Config::dji_m3508_example();
    let s = legs(
        "straight-only",
        example,
        &[(0.5, 0.0, 0.0, 2.0), (-0.5, 0.0, 0.0, 2.0)],
        0.5,
    );
    let (_, log) = run("calibrate-refusal", &s);
    let e = calibrate(&log, &Options::default()).unwrap_err();
    let text = e.to_string();
    println!("refused: {text}");
    let CalibrateError::MissingMotion(missing) = &e else {
        panic!("{e:?}")
    };
    let what: Vec<(&str, &str)> = missing.iter().map(|m| (m.motion, m.value)).collect();
    assert_eq!(
        what,
        [("strafe", "lateral_effectiveness"), ("rotation", "lx + ly")]
    );
    assert!(missing.iter().all(|m| m.have < 0.01), "{missing:?}");
    assert!(
        text.contains(
            "no strafe in this log (0.00 m of lateral travel at a steady speed, needs >= \
             0.5 m): cannot fit lateral_effectiveness; drive sideways both ways"
        ) && text.contains("no rotation in this log (0.0° of turning")
            && text.contains("cannot fit lx + ly")
            && text.contains("hostsim run calibration"),
        "{text}"
    );

    let (code, stdout, stderr) = hostsim(["calibrate", log.to_str().unwrap()]);
    println!("command line: exit {code}, {stderr}");
    assert_eq!(code, 2, "{stderr}");
    assert!(stderr.contains("no strafe in this log"), "{stderr}");
    assert!(stdout.is_empty());
}

/// The built-in calibration run's log rewritten as a tracker would give it: metadata, wheels
/// (`/joint_states`) and `/cmd_vel` as they are, the ground truth as
/// `geometry_msgs/msg/PoseStamped` on `/tracker/pose` at 30 Hz, 4 ms late, with ±0.3 mm and
/// ±0.3 mrad of noise. Written to `tracker.mcap` in the scratch folder `group`.
fn tracker_log(group: &str) -> std::path::PathBuf {
    use drivelog::msg::{self, decode, encode};
    let bytes = std::fs::read(calibration_log()).unwrap();
    let path = scratch(group, "tracker.mcap");
    let mut w = mcap::WriteOptions::new()
        .profile(drivelog::PROFILE)
        .create(std::io::BufWriter::new(
            std::fs::File::create(&path).unwrap(),
        ))
        .unwrap();
    let channel = |w: &mut mcap::Writer<_>, def: &msg::MsgDef, topic: &str| {
        let schema = w
            .add_schema(def.name, "ros2msg", def.schema_text().as_bytes())
            .unwrap();
        w.add_channel(schema, topic, "cdr", &BTreeMap::new())
            .unwrap()
    };
    let joints = channel(&mut w, &msg::JOINT_STATE, "/joint_states");
    let cmd = channel(&mut w, &msg::TWIST_STAMPED, "/cmd_vel");
    let tracker = channel(&mut w, &msg::POSE_STAMPED, "/tracker/pose");
    let mut messages: Vec<(u64, u16, Vec<u8>)> = Vec::new();
    let mut metadata = BTreeMap::new();
    let mut noise = 0x2545_f491_4f6c_dd1d_u64;
    let mut next = move || {
        // xorshift64: deterministic noise in [-1, 1).
        noise ^= noise << 13;
        noise ^= noise >> 7;
        noise ^= noise << 17;
        (noise >> 11) as f64 / (1u64 << 52) as f64 - 1.0
    };
    drivelog::for_each_message(
        &bytes,
        |m| match m.topic {
            "/joint_states" => messages.push((m.log_time, joints, m.data.to_vec())),
            "/cmd_vel" => messages.push((m.log_time, cmd, m.data.to_vec())),
            "/ground_truth/odom" if (m.log_time / 10_000_000) % 3 == 0 => {
                let o = decode::<msg::Odometry>(m.data).unwrap();
                let [x, y, yaw] = o.pose.pose.to_planar();
                let t = m.log_time + 4_000_000;
                let pose = msg::PoseStamped {
                    header: msg::Header::new(t, "world"),
                    pose: msg::Pose::planar([
                        x + 3e-4 * next(),
                        y + 3e-4 * next(),
                        yaw + 3e-4 * next(),
                    ]),
                };
                let mut data = Vec::new();
                encode(&mut data, &pose);
                // The tracker's clock: its poses are 4 ms late against the wheels.
                messages.push((m.log_time + 4_000_000, tracker, data));
            }
            _ => {}
        },
        |name, kv| {
            if name == drivelog::METADATA_NAME {
                metadata = kv.clone();
            }
        },
    )
    .unwrap();
    w.write_metadata(&mcap::records::Metadata {
        name: drivelog::METADATA_NAME.into(),
        metadata,
    })
    .unwrap();
    messages.sort_by_key(|m| m.0);
    for (i, (t, channel_id, data)) in messages.iter().enumerate() {
        let header = mcap::records::MessageHeader {
            channel_id: *channel_id,
            sequence: i as u32,
            log_time: *t,
            publish_time: *t,
        };
        w.write_to_known_channel(&header, data).unwrap();
    }
    w.finish().unwrap();
    drop(w);
    path
}

/// The poses of a tracker: the ground truth as `geometry_msgs/msg/PoseStamped` on
/// `/tracker/pose` at 30 Hz, stamped 4 ms late with ±0.3 mm and ±0.3 mrad of noise, in a log
/// with the wheels (`/joint_states`) and the configuration but no ground truth. The fit
/// matches the ground truth's within 0.2 %; a missing or non-pose reference is refused,
/// naming the topics.
#[test]
fn a_tracker_pose_stamped_reference_gives_the_same_fit() {
    let group = "calibrate-tracker";
    let truth_fit = fit(calibration_log());

    let path = tracker_log(group);

    let options = Options {
        reference: "/tracker/pose".into(),
        ..Options::default()
    };
    let c = calibrate(&path, &options).unwrap();
    print_fit("calibration against the tracker", &c);
    assert_eq!(c.reference_type, "geometry_msgs/msg/PoseStamped");
    for (what, a, b) in [
        ("wheel_radius", c.wheel_radius, truth_fit.wheel_radius),
        ("lx + ly", c.lx_plus_ly, truth_fit.lx_plus_ly),
        (
            "lateral_effectiveness",
            c.lateral_effectiveness,
            truth_fit.lateral_effectiveness,
        ),
    ] {
        let d = a.value / b.value - 1.0;
        println!(
            "  {what:<22} tracker {:.6} ± {:.1e}, ground truth {:.6}: {:+.3} %",
            a.value,
            a.stderr,
            b.value,
            d * 100.0
        );
        assert!(d.abs() < 2e-3, "{what}: {a:?} vs {b:?}");
    }

    let e = calibrate(&path, &Options::default())
        .unwrap_err()
        .to_string();
    println!("default reference: {e}");
    assert!(
        e.contains("no topic \"/ground_truth/odom\"") && e.contains("/tracker/pose"),
        "{e}"
    );
    let bad = Options {
        reference: "/cmd_vel".into(),
        ..Options::default()
    };
    let e = calibrate(&path, &bad).unwrap_err().to_string();
    println!("/cmd_vel as reference: {e}");
    assert!(
        e.contains("\"/cmd_vel\" is a geometry_msgs/msg/TwistStamped, not a pose"),
        "{e}"
    );
}

/// The command line: `--json` gives the fit, `--write FILE` a configuration that loads and
/// holds the fitted values and the rest of the logged one.
#[test]
fn the_command_line_writes_a_configuration_that_loads() {
    let written = scratch("calibrate-cli", "calibrated.toml");
    let (code, stdout, stderr) = hostsim([
        "calibrate",
        calibration_log().to_str().unwrap(),
        "--write",
        written.to_str().unwrap(),
        "--json",
    ]);
    assert_eq!(code, 0, "{stderr}");
    let v: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    println!("{v:#}");
    let config = Config::from_toml_file(&written).unwrap();
    let Geometry::Standard {
        lx,
        ly,
        wheel_radius,
        forward_effectiveness,
        lateral_effectiveness,
        yaw_effectiveness,
    } = config.geometry
    else {
        panic!("{config:?}")
    };
    let fitted = &v["fitted"];
    for (key, value) in [
        ("lx", lx),
        ("ly", ly),
        ("wheel_radius", wheel_radius),
        ("forward_effectiveness", forward_effectiveness),
        ("lateral_effectiveness", lateral_effectiveness),
        ("yaw_effectiveness", yaw_effectiveness),
    ] {
        assert_eq!(fitted[key].as_f64().map(|x| x as f32), Some(value), "{key}");
        assert!(
            v["geometry_lines"]
                .as_str()
                .unwrap()
                .contains(&format!("\n{key} = {value:?}\n")),
            "{key}"
        );
    }
    // Everything but the geometry is the logged configuration's.
    let example = Config::dji_m3508_example();
    assert_eq!(
        Config {
            geometry: example.geometry,
            ..config
        },
        example
    );
    // A log cut short (its summary and last chunk lost, the motion all there): the fit of its
    // complete part, exit status 3 and a warning naming the damage.
    let bytes = std::fs::read(calibration_log()).unwrap();
    let cut = scratch("calibrate-cli", "cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() * 97 / 100]).unwrap();
    let (code, stdout, stderr) = hostsim(["calibrate", cut.to_str().unwrap()]);
    println!("cut log: exit {code}, {stderr}");
    assert_eq!(code, 3, "{stderr}");
    assert!(
        stderr.contains("cut.mcap is damaged") && stderr.contains("complete part"),
        "{stderr}"
    );
    assert!(stdout.contains("lateral_effectiveness = 0.7"), "{stdout}");
    for axis in v["axes"].as_array().unwrap() {
        let (c, se) = (
            axis["correction"].as_f64().unwrap(),
            axis["stderr"].as_f64().unwrap(),
        );
        assert!(c.is_finite() && se.is_finite() && se < 1e-3, "{axis}");
    }
}

/// `hostsim plot A B`: both runs in one PNG, a path panel each and the errors (1800 x 600),
/// each run's largest drift as the run measured it (within 1 mm: the log has every 10th
/// step); a log without odometry and ground truth is refused (exit status 2).
#[test]
fn the_plot_draws_two_runs_side_by_side() {
    let group = "calibrate-plot";
    let mut after = Config::dji_m3508_example();
    if let Geometry::Standard {
        lateral_effectiveness,
        ..
    } = &mut after.geometry
    {
        *lateral_effectiveness = 0.75;
    }
    let (before_run, before) = run(
        group,
        &legs("before", Config::dji_m3508_example(), &SQUARE, 0.5),
    );
    let (after_run, after) = run(group, &legs("after", after, &SQUARE, 0.5));
    for (path, summary) in [(&before, &before_run), (&after, &after_run)] {
        let track = hostsim::analysis::plot::track_from_log(path)
            .unwrap()
            .points;
        let drift = hostsim::analysis::plot::max_drift(&track);
        println!(
            "{}: max drift {:.1} mm from the log, {:.1} mm in the run",
            path.display(),
            drift * 1e3,
            summary.max_position_error * 1e3
        );
        assert!((drift - summary.max_position_error).abs() < 1e-3);
    }
    let png = scratch(group, "before-vs-after.png");
    let _ = std::fs::remove_file(&png);
    let (code, stdout, stderr) =
        hostsim([OsStr::new("plot"), before.as_os_str(), after.as_os_str()]);
    println!("{stdout}");
    assert_eq!(code, 0, "{stderr}");
    assert!(stdout.contains("before-vs-after.png"), "{stdout}");
    let bytes = std::fs::read(&png).unwrap();
    // PNG signature, then the IHDR chunk: width and height, big-endian.
    assert_eq!(&bytes[1..4], b"PNG");
    let size = |at: usize| u32::from_be_bytes(bytes[at..at + 4].try_into().unwrap());
    assert_eq!((size(16), size(20)), (1800, 600));

    let log = scratch(group, "no-odometry.mcap");
    std::fs::write(&log, b"not a log").unwrap();
    let (code, _, stderr) = hostsim([OsStr::new("plot"), log.as_os_str()]);
    assert_eq!(code, 2, "{stderr}");
    assert!(
        stderr.contains("no-odometry.mcap") && stderr.contains("not a readable MCAP"),
        "{stderr}"
    );
}
