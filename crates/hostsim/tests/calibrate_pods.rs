//! `hostsim calibrate` on a robot with tracking pods: the pods' radius, direction and lever
//! recovered from the built-in `calibration` run when the true pods differ from the
//! configuration, the 60 s square before and after the calibrated pods, the refusal of a
//! log without the motion a pod needs, and the command line's pod output. Every figure is
//! printed (`cargo test --release -p hostsim --test calibrate_pods -- --nocapture`).

mod common;

use std::path::{Path, PathBuf};

use common::{fit, hostsim, logged_run, print_fit, scratch};
use firmware::Config;
use firmware::config::PodConfig;
use hostsim::analysis::calibrate::{CalibrateError, Options, calibrate};
use hostsim::engine::{LogOptions, run_observed};
use hostsim::nodes::pods::{PodErrors, PodsParams, TruePod};
use hostsim::scenario::{Action, Scenario};

fn repo_file(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .join(name)
}

fn pods3_config() -> Config {
    Config::from_toml_file(&repo_file("config/dji_m3508_pods3.toml")).unwrap()
}

/// The pods' errors of the recovery test: each pod's scale, misalignment and, for pods 0
/// and 2, the contact point moved across the line of action (pod 0 also 5 mm along it,
/// which changes no count).
const ERRORS: [PodErrors; 3] = [
    PodErrors {
        radius_error: 0.012,
        misalignment_deg: 0.4,
        offset_x: 0.005,
        offset_y: 0.003,
    },
    PodErrors {
        radius_error: -0.008,
        misalignment_deg: -0.3,
        offset_x: 0.0,
        offset_y: 0.0,
    },
    PodErrors {
        radius_error: 0.005,
        misalignment_deg: 0.6,
        offset_x: -0.002,
        offset_y: 0.0,
    },
];

/// The built-in `calibration` run on the pods3 configuration with the pods `pods` (the
/// square file's pod noise, 2e-5 m/s/√Hz, unless `pods` says otherwise).
fn calibration_run(name: &str, config: Config, pods: PodsParams) -> Scenario {
    let mut s = Scenario::builtin("calibration").unwrap();
    s.name = name.to_string();
    s.config = config;
    s.pods = Some(pods);
    s
}

fn run(group: &str, scenario: &Scenario) -> PathBuf {
    let path = scratch(group, &format!("{}.mcap", scenario.name));
    logged_run(scenario, &path);
    path
}

/// The true pods of `config` under `errors`.
fn true_pods(config: &Config, params: &PodsParams) -> Vec<TruePod> {
    config
        .odometry
        .pods
        .as_slice()
        .iter()
        .enumerate()
        .map(|(i, p)| TruePod::new(p, &params.errors(i)))
        .collect()
}

/// The pods of a pods3 robot that err as [`ERRORS`] say, on the `calibration` run: the fit
/// recovers each pod's radius within 0.1 %, direction within 0.05°, lever within 1 mm, each
/// true value within 4 of its standard errors; the refined tables' contact points lie on the
/// true lines of action (within 1 mm), and `--write` writes a configuration with them.
#[test]
fn the_fit_recovers_pods_built_unlike_their_configuration() {
    let config = pods3_config();
    let params = PodsParams {
        noise: 2e-5,
        pod: ERRORS.to_vec(),
        ..PodsParams::default()
    };
    let log = run(
        "calibrate-pods",
        &calibration_run("calibration-pods3", config, params),
    );
    let c = fit(&log);
    print_fit("calibration of the pods3 robot", &c);
    assert_eq!(c.pods.len(), 3);
    println!(
        "recovery (fitted - true; in standard errors):\n  pod  radius                  \
         direction                 lever"
    );
    let truth = PodsParams {
        pod: ERRORS.to_vec(),
        ..PodsParams::default()
    };
    for (f, t) in c.pods.iter().zip(true_pods(&config, &truth)) {
        let true_deg = t.direction.to_degrees();
        let true_lever = t.x * t.direction.sin() - t.y * t.direction.cos();
        let (dr, dd, dm) = (
            f.radius.value / t.radius - 1.0,
            f.direction_deg.value - true_deg,
            f.lever.value - true_lever,
        );
        let (zr, zd, zm) = (
            (f.radius.value - t.radius) / f.radius.stderr,
            dd / f.direction_deg.stderr,
            dm / f.lever.stderr,
        );
        println!(
            "  {}    {:+.4} % ({:+.2} s.e.)   {:+.4}° ({:+.2} s.e.)   {:+.4} mm ({:+.2} s.e.)",
            f.pod,
            dr * 100.0,
            zr,
            dd,
            zd,
            dm * 1e3,
            zm
        );
        assert!(dr.abs() < 1e-3, "pod {}: radius {dr}", f.pod);
        assert!(dd.abs() < 0.05, "pod {}: direction {dd}°", f.pod);
        assert!(dm.abs() < 1e-3, "pod {}: lever {dm} m", f.pod);
        for (what, z) in [("radius", zr), ("direction", zd), ("lever", zm)] {
            assert!(
                z.abs() < 4.0,
                "pod {}: {what} off by {z} standard errors",
                f.pod
            );
        }
        // The refined table: the fitted radius and direction as written, its point on the
        // true line of action.
        let (s, co) = f.fitted.direction_deg.to_radians().sin_cos();
        let refined_lever = f.fitted.x * s - f.fitted.y * co;
        assert!((refined_lever - true_lever).abs() < 1e-3, "{f:?}");
        assert!((f.fitted.radius / t.radius - 1.0).abs() < 1e-3, "{f:?}");
        assert_eq!(f.fitted.counts_per_turn, 2000);
    }
    // The configuration of the report (what --write writes) has the refined pods.
    let refined = c.config.odometry.pods;
    for (p, f) in refined.as_slice().iter().zip(&c.pods) {
        assert_eq!(f64::from(p.radius), f64::from(f.fitted.radius as f32));
        assert_eq!(
            f64::from(p.direction_deg),
            f64::from(f.fitted.direction_deg as f32)
        );
    }
    let text = c.pod_lines();
    assert_eq!(text.matches("[[odometry.pods]]").count(), 3, "{text}");
    let pasted = Config::from_toml_str(&format!(
        "{}\n{}",
        pods3_config()
            .to_toml_string()
            .split("[[odometry.pods]]")
            .next()
            .unwrap(),
        text
    ))
    .unwrap();
    assert_eq!(pasted.odometry.pods, refined);
}

/// The scenario errors that make the pods configured as `nominal` the true pods `truth`: a
/// run with a calibrated configuration keeps the robot's pods as they are.
fn errors_against(nominal: &[PodConfig], truth: &[TruePod]) -> Vec<PodErrors> {
    nominal
        .iter()
        .zip(truth)
        .map(|(n, t)| PodErrors {
            radius_error: t.radius / f64::from(n.radius) - 1.0,
            misalignment_deg: t.direction.to_degrees() - f64::from(n.direction_deg),
            offset_x: t.x - f64::from(n.x),
            offset_y: t.y - f64::from(n.y),
        })
        .collect()
}

/// How far the odometry strays on the square (`measure` of `tests/pod_odometry.rs`): the
/// largest growth of the position error within a lap over that lap's distance, the worst
/// whole lap; and the heading error at the end, rad.
fn per_lap(scenario: &Scenario) -> (f64, f64) {
    const FIRST_TWIST_S: f64 = 2.0;
    const LAP_S: f64 = 8.0;
    let mut plant = hostsim::engine::plant_for(scenario).unwrap();
    let mut distance = 0.0;
    let mut last: Option<[f64; 2]> = None;
    let laps = ((scenario.duration_s - FIRST_TWIST_S) / LAP_S) as usize;
    let mut lap: Vec<([f64; 2], f64, f64)> = Vec::new();
    let summary = run_observed(scenario, &mut plant, None, LogOptions::default(), |step| {
        let t = step.t_us as f64 * 1e-6;
        let pose = step.controller.pose();
        let [tx, ty, _] = step.truth;
        if let Some([x, y]) = last {
            distance += (tx - x).hypot(ty - y);
        }
        last = Some([tx, ty]);
        let e = [f64::from(pose.x) - tx, f64::from(pose.y) - ty];
        if t < FIRST_TWIST_S {
            return;
        }
        let index = ((t - FIRST_TWIST_S) / LAP_S) as usize;
        if index == lap.len() {
            lap.push((e, distance, 0.0));
        }
        let (start, _, grown) = &mut lap[index];
        *grown = grown.max((e[0] - start[0]).hypot(e[1] - start[1]));
    })
    .unwrap();
    lap.push(([0.0; 2], distance, 0.0));
    let worst = (0..laps.min(lap.len() - 1))
        .map(|k| lap[k].2 / (lap[k + 1].1 - lap[k].1))
        .fold(0.0, f64::max);
    (worst, summary.final_heading_error)
}

/// `scenarios/square_60s_pods.toml` on pods3 with each pod's scale off on its own (+1 %,
/// −1 %, +0.6 %; the file's 0.5° block misalignment): the parallel pods' scale difference
/// turns straight travel into rotation and the square fails its 1 % per lap; calibrated on
/// the `calibration` run of the same pods, the square holds 1 % per lap.
#[test]
fn the_calibrated_pods_keep_the_square_within_1_percent_per_lap() {
    let mut square = Scenario::from_file(&repo_file("scenarios/square_60s_pods.toml")).unwrap();
    let pods = square.pods.as_mut().unwrap();
    pods.radius_error = 0.0;
    pods.pod = [0.01, -0.01, 0.006]
        .map(|radius_error| PodErrors {
            radius_error,
            ..PodErrors::default()
        })
        .to_vec();
    let params = pods.clone();
    let (before, heading_before) = per_lap(&square);

    let log = run(
        "calibrate-pods-square",
        &calibration_run("calibration-square-pods", square.config, params),
    );
    let c = fit(&log);
    print_fit("calibration of the square's pods", &c);
    // The same robot (its true pods), the firmware with the calibrated pods.
    let truth = true_pods(&square.config, square.pods.as_ref().unwrap());
    let mut calibrated = square.clone();
    calibrated.config.odometry.pods = c.config.odometry.pods;
    calibrated.config.validate().unwrap();
    // The same true pods, as errors against the calibrated ones (each pod's whole error).
    *calibrated.pods.as_mut().unwrap() = PodsParams {
        pod: errors_against(calibrated.config.odometry.pods.as_slice(), &truth),
        radius_error: 0.0,
        misalignment_deg: 0.0,
        ..square.pods.clone().unwrap()
    };
    for (a, b) in truth.iter().zip(&true_pods(
        &calibrated.config,
        calibrated.pods.as_ref().unwrap(),
    )) {
        assert!((a.radius - b.radius).abs() < 1e-12 && (a.direction - b.direction).abs() < 1e-9);
        assert!((a.x - b.x).abs() < 1e-9 && (a.y - b.y).abs() < 1e-9);
    }
    let (after, heading_after) = per_lap(&calibrated);
    println!(
        "square at speed, pods3, largest error growth per lap: {:.2} % (heading at the end \
         {:.3}°) -> {:.2} % ({:.3}°) with the calibrated pods",
        before * 100.0,
        heading_before.to_degrees(),
        after * 100.0,
        heading_after.to_degrees()
    );
    assert!(before > 0.01, "before: {before}");
    assert!(after < 0.01, "after: {after}");
}

/// A log of straight forward and back driving on a pods3 robot: the wheels' strafe and
/// rotation are missing, and so are the forward pods' directions (nothing across them), the
/// sideways pod's radius (nothing along it) and every pod's lever (no turning): refused,
/// each named, by the library and the command line (exit status 2).
#[test]
fn a_straight_only_log_is_refused_naming_each_pod() {
    let mut s = calibration_run("straight-only-pods3", pods3_config(), PodsParams::default());
    s.actions = vec![
        Action {
            enable: true,
            ..Action::at(0.05)
        },
        Action::twist(0.1, 0.5, 0.0, 0.0),
        Action::twist(2.1, 0.0, 0.0, 0.0),
        Action::twist(2.6, -0.5, 0.0, 0.0),
        Action::twist(4.6, 0.0, 0.0, 0.0),
    ];
    s.duration_s = 5.6;
    let log = run("calibrate-pods-refusal", &s);
    let e = calibrate(&log, &Options::default()).unwrap_err();
    let text = e.to_string();
    println!("refused: {text}");
    let CalibrateError::MissingMotion(missing) = &e else {
        panic!("{e:?}")
    };
    let what: Vec<(Option<usize>, &str, &str)> =
        missing.iter().map(|m| (m.pod, m.motion, m.value)).collect();
    assert_eq!(
        what,
        [
            (None, "strafe", "lateral_effectiveness"),
            (None, "rotation", "lx + ly"),
            (Some(0), "strafe", "direction_deg"),
            (Some(0), "rotation", "lever"),
            (Some(1), "strafe", "direction_deg"),
            (Some(1), "rotation", "lever"),
            (Some(2), "strafe", "radius"),
            (Some(2), "rotation", "lever"),
        ]
    );
    assert!(
        text.contains(
            "pod 0: 0.00 m of travel across its direction at a steady speed in this log \
             (needs >= 0.5 m): cannot fit its direction_deg; drive sideways both ways"
        ) && text.contains(
            "pod 2: 0.00 m of travel along its direction at a steady speed in this log \
             (needs >= 0.5 m): cannot fit its radius; drive sideways both ways"
        ) && text.contains(
            "pod 1: 0.0° of turning at a steady speed in this log (needs >= 360°): cannot \
             fit its lever; spin on the spot both ways"
        ),
        "{text}"
    );
    let (code, _, stderr) = hostsim(["calibrate", log.to_str().unwrap()]);
    assert_eq!(code, 2, "{stderr}");
    assert!(stderr.contains("pod 2: 0.00 m of travel along"), "{stderr}");
}

/// The command line on a pods3 log: the text report has each pod's fit and the
/// `[[odometry.pods]]` tables, `--json` the same figures (`pods`, `pod_lines`), `--write` a
/// configuration with the refined pods; on a log without pods neither has anything of pods.
#[test]
fn the_command_line_reports_the_pods_only_for_a_robot_with_pods() {
    let group = "calibrate-pods-cli";
    let params = PodsParams {
        pod: ERRORS.to_vec(),
        ..PodsParams::default()
    };
    let log = run(
        group,
        &calibration_run("calibration-pods3-cli", pods3_config(), params),
    );
    let written = scratch(group, "calibrated.toml");
    // `hostsim calibrate ARGS`, which succeeds: its stdout.
    let calibrate_ok = |args: &[&str]| {
        let (code, stdout, stderr) = hostsim([&["calibrate"], args].concat());
        assert_eq!(code, 0, "{stderr}");
        stdout
    };
    let text = calibrate_ok(&[log.to_str().unwrap()]);
    println!("{text}");
    for needle in [
        "pods, from their angles in /joint_states",
        "  pod 2  radius ",
        "direction_deg  90.0000° -> 90.6",
        "unobservable",
        "[[odometry.pods]]  # pod 0\nx = ",
        "counts_per_turn = 2000\n",
    ] {
        assert!(text.contains(needle), "{needle:?} in {text}");
    }
    let json = calibrate_ok(&[
        log.to_str().unwrap(),
        "--json",
        "--write",
        written.to_str().unwrap(),
    ]);
    let v: serde_json::Value = serde_json::from_str(&json).unwrap();
    let pods = v["pods"].as_array().unwrap();
    assert_eq!(pods.len(), 3);
    for (p, key) in pods.iter().zip(["radius", "direction_deg", "lever"]) {
        assert!(p[key]["stderr"].as_f64().unwrap() > 0.0, "{p}");
    }
    assert!((pods[1]["scale"]["value"].as_f64().unwrap() - 0.992).abs() < 1e-3);
    let config = Config::from_toml_file(&written).unwrap();
    for (p, j) in config.odometry.pods.as_slice().iter().zip(pods) {
        assert_eq!(
            Some(f64::from(p.radius)),
            j["fitted"]["radius"].as_f64().map(|r| f64::from(r as f32))
        );
    }
    assert!(v["pod_lines"].as_str().unwrap().contains("radius = "));

    // Without pods: nothing of them.
    let mut plain = Scenario::builtin("calibration").unwrap();
    plain.name = "calibration-no-pods".into();
    let log = run(group, &plain);
    let text = calibrate_ok(&[log.to_str().unwrap()]);
    assert!(
        !text.contains("pods, from") && !text.contains("odometry.pods"),
        "{text}"
    );
    let json = calibrate_ok(&[log.to_str().unwrap(), "--json"]);
    let v: serde_json::Value = serde_json::from_str(&json).unwrap();
    assert!(
        v.get("pods").is_none() && v.get("pod_lines").is_none(),
        "{v}"
    );
}
