//! Odometry from tracking pods on the simulator, against the ground truth: the 60 s square
//! at speed (`scenarios/square_60s_pods.toml`) with pods that err (1 % scale, 0.5°), for
//! `pods3` and `pods2_gyro`, the wheels alone on the same run, the pods silent mid-run, a
//! replay, and a sweep over seeds and drawn pod errors. The measure is the largest position
//! error along the path, never only the final pose (a closed square cancels most of it).
//! Figures are printed (`cargo test --release -p hostsim --test pod_odometry -- --nocapture`).

mod common;

use std::path::Path;

use firmware::config::{Config, HeadingMode, OdometryMode};
use firmware::control::OdometrySource;
use hostsim::analysis::sweep::{self, Param};
use hostsim::engine::{LogOptions, run_observed};
use hostsim::replay::replay_mcap;
use hostsim::scenario::Scenario;
use rayon::prelude::*;

fn repo_file(name: &str) -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .join(name)
}

/// The square's first twist, s, and one lap (four 2 s sides), s.
const FIRST_TWIST_S: f64 = 2.0;
const LAP_S: f64 = 8.0;
/// The targets: the largest error at most this fraction of the distance driven.
const LIMIT: f64 = 0.01;
/// Heading within this at the end, rad (1°).
const HEADING_LIMIT: f64 = 0.017_453_292_519_943_295;

/// `scenarios/square_60s_pods.toml`: three pods.
fn pods3() -> Scenario {
    Scenario::from_file(&repo_file("scenarios/square_60s_pods.toml")).unwrap()
}

/// The same run with two pods and the gyro, as the command line runs it:
/// `--config config/dji_m3508_pods2_gyro.toml` (pods 0 and 2 of the three-pod layout).
fn pods2_gyro() -> Scenario {
    let config = Config::from_toml_file(&repo_file("config/dji_m3508_pods2_gyro.toml")).unwrap();
    let path = repo_file("scenarios/square_60s_pods.toml");
    let s = Scenario::load(path.to_str().unwrap(), Some(config)).unwrap();
    assert_eq!(s.config.odometry.source, OdometryMode::Pods2Gyro);
    assert_eq!(s.config.odometry.heading_source, HeadingMode::Gyro);
    s
}

/// The same run, odometry from the wheels (the plant keeps its slide).
fn wheels_only() -> Scenario {
    let mut s = pods3();
    s.config.odometry = Config::dji_m3508_example().odometry;
    s.pods = None;
    s
}

/// How far the odometry strayed from the ground truth along the path.
#[derive(Debug, Clone, Copy, Default)]
struct Accuracy {
    /// The largest growth of the position error within a lap (from the error at its start),
    /// over that lap's distance, the worst lap.
    per_lap: f64,
    /// The largest position error over the distance driven in the run.
    over_run: f64,
    /// The largest position error, m.
    max_m: f64,
    /// The distance driven, m.
    distance_m: f64,
    /// The heading error at the end, rad.
    heading: f64,
}

impl Accuracy {
    fn holds(&self) -> bool {
        self.per_lap <= LIMIT && self.over_run <= LIMIT && self.heading.abs() <= HEADING_LIMIT
    }
}

/// Runs `scenario` and measures the position error at every step: per lap (the growth of
/// the error vector since the lap began, over the lap's distance: the issue's "229.8 mm, 5.9 %
/// of 3.91 m") and over the run. Only whole laps count per lap.
fn measure(scenario: &Scenario) -> (Accuracy, Vec<(f64, OdometrySource)>) {
    let mut plant = hostsim::engine::plant_for(scenario).unwrap();
    let mut a = Accuracy::default();
    let mut last: Option<[f64; 2]> = None;
    let laps = ((scenario.duration_s - FIRST_TWIST_S) / LAP_S) as usize;
    // Per lap: the error at its start, the distance at its start, the largest growth.
    let mut lap: Vec<([f64; 2], f64, f64)> = Vec::new();
    let mut sources: Vec<(f64, OdometrySource)> = Vec::new();
    let summary = run_observed(scenario, &mut plant, None, LogOptions::default(), |step| {
        let t = step.t_us as f64 * 1e-6;
        let pose = step.controller.pose();
        let [tx, ty, _] = step.truth;
        if let Some([x, y]) = last {
            a.distance_m += (tx - x).hypot(ty - y);
        }
        last = Some([tx, ty]);
        let e = [f64::from(pose.x) - tx, f64::from(pose.y) - ty];
        a.max_m = a.max_m.max(e[0].hypot(e[1]));
        let source = step.controller.snapshot().odometry_source;
        if sources.last().is_none_or(|&(_, s)| s != source) {
            sources.push((t, source));
        }
        if t < FIRST_TWIST_S {
            return;
        }
        let index = ((t - FIRST_TWIST_S) / LAP_S) as usize;
        if index == lap.len() {
            lap.push((e, a.distance_m, 0.0));
        }
        let (start, _, grown) = &mut lap[index];
        *grown = grown.max((e[0] - start[0]).hypot(e[1] - start[1]));
    })
    .unwrap();
    lap.push(([0.0; 2], a.distance_m, 0.0));
    for k in 0..laps.min(lap.len() - 1) {
        let driven = lap[k + 1].1 - lap[k].1;
        a.per_lap = a.per_lap.max(lap[k].2 / driven);
    }
    a.over_run = a.max_m / a.distance_m;
    a.heading = summary.final_heading_error;
    (a, sources)
}

fn report(name: &str, a: &Accuracy) {
    println!(
        "{name}: largest error {:.1} mm over {:.2} m driven; per lap {:.2} %, over the run \
         {:.2} %; heading at the end {:.3}°",
        a.max_m * 1e3,
        a.distance_m,
        a.per_lap * 100.0,
        a.over_run * 100.0,
        a.heading.to_degrees()
    );
}

#[test]
fn pods_keep_the_square_at_speed_within_1_percent_and_the_wheels_do_not() {
    let runs = [
        ("pods3", pods3(), OdometrySource::Pods3),
        ("pods2_gyro", pods2_gyro(), OdometrySource::Pods2Gyro),
        ("wheels", wheels_only(), OdometrySource::Wheels),
    ];
    let results: Vec<_> = runs.par_iter().map(|(_, s, _)| measure(s)).collect();
    for ((name, _, source), (a, sources)) in runs.iter().zip(&results) {
        report(name, a);
        // The pods give the odometry from their first frame (the robot stands still then)
        // to the end.
        assert_eq!(
            sources.last().map(|s| s.1),
            Some(*source),
            "{name}: {sources:?}"
        );
        assert!(sources.len() <= 2, "{name}: {sources:?}");
        assert!(a.distance_m > 25.0, "{name}: drove {} m", a.distance_m);
    }
    let (p3, p2, wheels) = (&results[0].0, &results[1].0, &results[2].0);
    for (name, a) in [("pods3", p3), ("pods2_gyro", p2)] {
        assert!(a.per_lap <= LIMIT, "{name}: {a:?}");
        assert!(a.over_run <= LIMIT, "{name}: {a:?}");
        assert!(a.heading.abs() <= HEADING_LIMIT, "{name}: {a:?}");
    }
    // The wheels cannot see the slide at the corners.
    assert!(wheels.per_lap > 0.03, "wheels: {wheels:?}");
}

/// How a sweep draws each pod's scale error: one error common to the pods (a batch of
/// wheels, a worn tread) in ±`common`, plus each pod's own in ±`own`.
#[derive(Debug, Clone, Copy)]
struct ScaleDraw {
    common: f64,
    own: f64,
}

/// The sweep's `--set` arguments that draw a run's pod errors (docs/simulator.md, "Tracking
/// pods", gives the `hostsim sweep` command): the scale as `scale` says, the pod block's
/// misalignment uniform in ±0.5° plus each pod's own in ±0.1°, contact points off by up to
/// ±2 mm.
fn pod_draws(pods: usize, scale: ScaleDraw) -> Vec<String> {
    let range = |key: &str, half: f64| format!("{key}={}..{half}", -half);
    let mut sets = vec![
        range("pods.misalignment_deg", 0.5),
        range("pods.radius_error", scale.common),
    ];
    for i in 0..pods {
        sets.push(range(&format!("pods.pod[{i}].radius_error"), scale.own));
        sets.push(range(&format!("pods.pod[{i}].misalignment_deg"), 0.1));
        sets.push(range(&format!("pods.pod[{i}].offset_x"), 0.002));
        sets.push(range(&format!("pods.pod[{i}].offset_y"), 0.002));
    }
    sets
}

/// The runs of `hostsim sweep SCENARIO --seeds 1..RUNS` with [`pod_draws`]: each scenario as
/// the sweep runs it (the same draws, by the run's index).
fn drawn(base: &Scenario, runs: u64, scale: ScaleDraw) -> Vec<Scenario> {
    let params: Vec<Param> = pod_draws(base.config.odometry.pods.len(), scale)
        .iter()
        .map(|a| Param::parse(a).unwrap())
        .collect();
    let seeds: Vec<u64> = (1..=runs).collect();
    let specs = sweep::expand(&seeds, &params).unwrap();
    sweep::check(base, &specs, &params).unwrap();
    specs
        .iter()
        .map(|r| sweep::apply(base, r.seed, &r.values).unwrap())
        .collect()
}

/// Two pods and the gyro hold with every pod's scale drawn on its own (±1 %). Three pods
/// take their rotation from the difference of the two parallel pods, so a scale error
/// between those two turns straight travel into rotation (0.1 % between pods 0.22 m apart
/// is 0.26° a metre): they hold with a common scale error (±1 %) and pods that agree within
/// ±0.1 % each, as after the pods' calibration; with every scale drawn on its own (±1 %) only
/// 75 of the 200 runs held when this was measured (docs/simulator.md, "Tracking pods").
#[test]
fn over_200_seeds_and_drawn_pod_errors_95_percent_of_runs_hold() {
    const RUNS: u64 = 200;
    for (name, base, scale) in [
        (
            "pods2_gyro",
            pods2_gyro(),
            ScaleDraw {
                common: 0.0,
                own: 0.01,
            },
        ),
        (
            "pods3",
            pods3(),
            ScaleDraw {
                common: 0.01,
                own: 0.001,
            },
        ),
    ] {
        let results: Vec<Accuracy> = drawn(&base, RUNS, scale)
            .par_iter()
            .map(|s| measure(s).0)
            .collect();
        let held = results.iter().filter(|a| a.holds()).count();
        let worst = |f: fn(&Accuracy) -> f64| results.iter().map(f).fold(0.0, f64::max);
        println!(
            "{name} ({scale:?}): {held} of {RUNS} runs within 1 % (per lap and over the run) and \
             1°; worst per lap {:.2} %, over the run {:.2} %, heading {:.3}°",
            worst(|a| a.per_lap) * 100.0,
            worst(|a| a.over_run) * 100.0,
            worst(|a| a.heading.abs()).to_degrees()
        );
        assert!(held * 100 >= 95 * RUNS as usize, "{name}: {held} of {RUNS}");
    }
}

#[test]
fn silent_pods_hand_over_to_the_wheels_in_time_without_a_jump_and_come_back() {
    let mut s = pods3();
    s.duration_s = 20.0;
    s.actions.retain(|a| a.at_s < 20.0);
    // Silent from 9 s (mid-lap, strafing) to 11 s.
    s.node_faults.push(hostsim::scenario::NodeFault {
        kind: hostsim::scenario::FaultName::PodsSilent,
        from_us: 9_000_000,
        until_us: 11_000_000,
    });
    let mut plant = hostsim::engine::plant_for(&s).unwrap();
    let timeout_us = u64::from(s.config.odometry.pod_timeout_ms) * 1000;
    let mut changes: Vec<(u64, OdometrySource)> = Vec::new();
    let mut largest_step = 0.0f64;
    let mut previous: Option<(f64, f64)> = None;
    let mut last_frame_us = 0;
    run_observed(&s, &mut plant, None, LogOptions::default(), |step| {
        for tx in step.delivered {
            // The core takes a frame at its delivery time.
            if tx.from == hostsim::bus::Node::Pods && step.t_us < 9_100_000 {
                last_frame_us = tx.delivered_ns / 1000;
            }
        }
        let snap = step.controller.snapshot();
        if changes
            .last()
            .is_none_or(|&(_, src)| src != snap.odometry_source)
        {
            changes.push((step.t_us, snap.odometry_source));
        }
        let p = step.controller.pose();
        if let Some((x, y)) = previous {
            largest_step = largest_step.max((f64::from(p.x) - x).hypot(f64::from(p.y) - y));
        }
        previous = Some((f64::from(p.x), f64::from(p.y)));
    })
    .unwrap();
    println!("sources {changes:?}; last pod frame before the silence at {last_frame_us} µs");
    let silent = changes
        .iter()
        .find(|c| c.1 == OdometrySource::WheelsPodsSilent && c.0 > 1_000_000)
        .expect("the wheels took over");
    // The first step past the timeout after the last frame taken.
    assert!(silent.0 > last_frame_us + timeout_us, "{silent:?}");
    assert!(silent.0 <= last_frame_us + timeout_us + 1_000, "{silent:?}");
    let back = changes
        .iter()
        .find(|c| c.1 == OdometrySource::Pods3 && c.0 > silent.0)
        .expect("the pods came back");
    assert!(back.0 >= 11_000_000 && back.0 < 11_010_000, "{back:?}");
    // No jump: 0.5 m/s is 0.5 mm a step; the handover applies the wheels' last 50 ms at once
    // (25 mm at most).
    assert!(
        largest_step < 0.5 * 0.051 + 0.001,
        "largest step {largest_step} m"
    );
}

#[test]
fn a_pod_run_replays_bit_for_bit() {
    let mut s = pods2_gyro();
    s.duration_s = 12.0;
    s.actions.retain(|a| a.at_s < 12.0);
    let path = common::scratch("pod_odometry", "replay.mcap");
    let summary = common::logged_run(&s, &path);
    assert_eq!(summary.last.odometry_source, OdometrySource::Pods2Gyro);
    let replay = replay_mcap(&path).unwrap();
    assert!(replay.identical(), "{:?}", replay.difference);
}
