//! The simulated tracking-pod node (`[pods]`) in lockstep runs: its frames on the bus, their
//! counts against the ground truth, its seed, its silence, and the scenario's checks.

mod common;

use std::f64::consts::TAU;
use std::path::Path;

use firmware::Config;
use firmware::config::{OdometryMode, PodConfig, Pods};
use firmware::protocol::robot::Command;
use hostsim::bus::{Fate, Node};
use hostsim::engine::{LogOptions, RunSummary, StepView, run_observed};
use hostsim::scenario::{Scenario, ScenarioError};

const R: f32 = 0.024;
const CPT: u32 = 2000;

/// The DJI example with three pods: forward-counting ones left and right, a leftward-counting
/// one at the back.
fn pods_config() -> Config {
    let pod = |x, y, direction_deg| PodConfig {
        x,
        y,
        direction_deg,
        radius: R,
        counts_per_turn: CPT,
    };
    let mut config = Config::dji_m3508_example();
    config.odometry.source = OdometryMode::Pods3;
    config.odometry.pods = Pods::new(&[
        pod(0.05, 0.15, 0.0),
        pod(0.05, -0.15, 0.0),
        pod(-0.12, 0.02, 90.0),
    ])
    .unwrap();
    config
}

fn scenario_with(config: Config, rest: &str) -> Result<Scenario, ScenarioError> {
    let text = common::driving("duration_s = 2.0\nseed = 11", [0.4, 0.2, 0.6], rest);
    Scenario::from_toml_with_config(&text, Path::new("pods.toml"), Some(config))
}

fn scenario(rest: &str) -> Scenario {
    scenario_with(pods_config(), rest).unwrap()
}

/// [`scenario`] with the pod node silent from `from_s` to `until_s`.
fn pods_silent(from_s: f64, until_s: f64) -> Scenario {
    scenario(&format!(
        "[pods]\n[[faults]]\nkind = \"pods_silent\"\nfrom_s = {from_s:?}\nuntil_s = {until_s:?}"
    ))
}

/// A run's pod frames `(sample time ns, counts, seq, fate)` and the ground-truth pose at every
/// step `(t µs, [x, y, heading])`.
struct Observed {
    summary: RunSummary,
    pods: Vec<(u64, [u16; 3], u8, Fate)>,
    truth: Vec<(u64, [f64; 3])>,
}

fn observe(s: &Scenario) -> Observed {
    let mut plant = hostsim::engine::plant_for(s).unwrap();
    let (mut pods, mut truth) = (Vec::new(), Vec::new());
    let summary = run_observed(
        s,
        &mut plant,
        None,
        LogOptions::default(),
        |v: &StepView| {
            truth.push((v.t_us, v.truth));
            for tx in v.delivered.iter().filter(|tx| tx.from == Node::Pods) {
                let Ok(Command::PodCounts(c)) = Command::decode(&tx.sent) else {
                    panic!("not POD_COUNTS: {:?}", tx.sent);
                };
                pods.push((tx.queued_ns, c.counts, c.seq, tx.fate));
            }
        },
    )
    .unwrap();
    Observed {
        summary,
        pods,
        truth,
    }
}

/// The counts unwrapped: the sum of the signed 16-bit differences from 0.
fn unwrapped(frames: &[(u64, [u16; 3], u8, Fate)], pod: usize) -> f64 {
    let mut last = 0u16;
    let mut total = 0i64;
    for f in frames {
        total += i64::from(f.1[pod].wrapping_sub(last) as i16);
        last = f.1[pod];
    }
    total as f64
}

/// `∫(vx, vy, ω) dt` up to `until_us` from the ground-truth poses of the steps: each step's
/// world displacement turned into the body frame at its middle heading (exact to `(ω h)²/24`
/// of the step's travel).
fn body_travel(truth: &[(u64, [f64; 3])], until_us: u64) -> [f64; 3] {
    let mut t = [0.0; 3];
    for w in truth.windows(2).take_while(|w| w[1].0 <= until_us) {
        let ([x0, y0, h0], [x1, y1, h1]) = (w[0].1, w[1].1);
        let dh = kinematics::wrap_angle(h1 - h0);
        let (s, c) = (h0 + dh / 2.0).sin_cos();
        let (dx, dy) = (x1 - x0, y1 - y0);
        t[0] += c * dx + s * dy;
        t[1] += -s * dx + c * dy;
        t[2] += dh;
    }
    t
}

/// The counts a pod at `(x, y)` counting along `direction_deg` on a wheel of `radius` shows
/// after the body travel `t`.
fn counts_for(t: [f64; 3], x: f64, y: f64, direction_deg: f64, radius: f64) -> f64 {
    let (s, c) = direction_deg.to_radians().sin_cos();
    let travel = c * (t[0] - y * t[2]) + s * (t[1] + x * t[2]);
    travel / (TAU * radius) * f64::from(CPT)
}

#[test]
fn the_pods_count_the_true_motion_of_the_chassis() {
    let s = scenario(
        r#"
        [pods]
        [[pods.pod]]
        [[pods.pod]]
        radius_error = 0.02
        misalignment_deg = 3.0
        offset_x = 0.01
        offset_y = -0.02
        "#,
    );
    let o = observe(&s);
    // 200 Hz from 5 ms, every one delivered, seq counting; the firmware took them all.
    let last_ns = o.pods.last().unwrap().0;
    assert_eq!(o.pods.len() as u64, last_ns / 5_000_000);
    assert!(o.pods.iter().enumerate().all(|(i, f)| {
        f.0 == (i as u64 + 1) * 5_000_000 && f.2 == i as u8 && f.3 == Fate::Delivered
    }));
    // The body moved and turned (the twist has a rotation): every pod counted much.
    let t = body_travel(&o.truth, last_ns / 1000);
    assert!(t[2] > 0.9 && t[0] > 0.6, "travel {t:?}");
    let r = f64::from(R);
    for (pod, want) in [
        (0, counts_for(t, 0.05, 0.15, 0.0, r)),
        // The second pod is its true self: 2 % larger, turned by 3°, moved.
        (1, counts_for(t, 0.05 + 0.01, -0.15 - 0.02, 3.0, r * 1.02)),
        (2, counts_for(t, -0.12, 0.02, 90.0, r)),
    ] {
        let got = unwrapped(&o.pods, pod);
        assert!(got.abs() > 1000.0, "pod {pod}: {got}");
        assert!(
            (got - want).abs() <= 1.0,
            "pod {pod}: {got} counts, want {want:.2}"
        );
    }
    assert!(o.summary.rx_frames > o.pods.len() as u64);
}

#[test]
fn the_same_seed_gives_the_same_pod_frames_and_another_seed_other_noise() {
    let noisy = "[pods]\nnoise = 0.002\n";
    let a = observe(&scenario(noisy));
    let b = observe(&scenario(noisy));
    assert_eq!(a.pods, b.pods);
    assert_eq!(a.summary.tx_hash, b.summary.tx_hash);
    let mut other = scenario(noisy);
    other.seed = 12;
    let c = observe(&other);
    assert_ne!(a.pods, c.pods);
    // Without noise the counts are the truth's, whatever the seed; the noise moves them.
    let quiet = observe(&scenario("[pods]\n"));
    let mut quiet_other = scenario("[pods]\n");
    quiet_other.seed = 12;
    // (The seed also draws nothing else here: no bus faults, no IMU.)
    assert_eq!(quiet.pods, observe(&quiet_other).pods);
    assert_ne!(quiet.pods, a.pods);
}

#[test]
fn a_silent_pod_node_is_absent_from_the_bus_and_leaves_the_run_as_without_pods() {
    let without = observe(&scenario(""));
    assert!(without.pods.is_empty());
    // Silent for the whole run: the node samples at the plant's period boundaries (200 Hz
    // on the 1 ms grid), which do not change the physics, and sends nothing.
    let silent = observe(&pods_silent(0.0, 10.0));
    assert!(silent.pods.is_empty());
    assert_eq!(silent.summary.tx_hash, without.summary.tx_hash);
    assert_eq!(silent.summary.bus.frames, without.summary.bus.frames);
    assert_eq!(
        silent.summary.truth.map(f64::to_bits),
        without.summary.truth.map(f64::to_bits)
    );
    // Silent for a while: the frames of the window are missing, seq and counts went on.
    let gap = observe(&pods_silent(0.5, 0.75));
    let before = gap.pods.iter().rfind(|f| f.0 < 500_000_000).unwrap();
    let after = gap.pods.iter().find(|f| f.0 >= 500_000_000).unwrap();
    assert_eq!((before.0, after.0), (495_000_000, 750_000_000));
    assert_eq!(after.2, before.2.wrapping_add(51));
    // A `burst` on the sender `pods` drops them on the wire instead.
    let burst = observe(&scenario(
        r#"
        [pods]
        [[faults]]
        kind = "burst"
        sender = "pods"
        from_s = 0.5
        until_s = 0.75
        "#,
    ));
    assert!(
        burst
            .pods
            .iter()
            .filter(|f| f.3 == Fate::Dropped)
            .all(|f| (500_000_000..750_000_000).contains(&f.0))
    );
    assert_eq!(
        burst.pods.iter().filter(|f| f.3 == Fate::Dropped).count(),
        50
    );
}

#[test]
fn the_scenario_checks_name_the_key_and_the_value() {
    let error = |config: Config, rest: &str| match scenario_with(config, rest) {
        Ok(_) => panic!("accepted: {rest}"),
        Err(e) => e.to_string(),
    };
    for (rest, wanted) in [
        ("[pods]\nrate_hz = 0.0\n", "pods.rate_hz = 0"),
        ("[pods]\nrate_hz = 2500.0\n", "pods.rate_hz = 2500"),
        ("[pods]\nnoise = -1.0\n", "pods.noise = -1"),
        (
            "[pods]\n[[pods.pod]]\n[[pods.pod]]\nradius_error = 0.7\n",
            "pods.pod[1].radius_error = 0.7",
        ),
        (
            "[pods]\n[[pods.pod]]\nmisalignment_deg = 190.0\n",
            "pods.pod[0].misalignment_deg = 190",
        ),
        (
            "[pods]\n[[pods.pod]]\n[[pods.pod]]\n[[pods.pod]]\n[[pods.pod]]\n",
            "pods.pod = 4 tables for 3 configured pods",
        ),
        (
            "[[faults]]\nkind = \"pods_silent\"\nfrom_s = 0.5\nuntil_s = 1.0\n",
            "faults[0].kind = \"pods_silent\"",
        ),
        (
            "[[faults]]\nkind = \"pods_silent\"\nfrom_s = 0.5\nuntil_s = 1.0\nsender = \"pods\"\n",
            "faults[0].sender",
        ),
        ("[pods]\nrate = 100.0\n", "unknown field `rate`"),
        (
            "[pods]\n[[pods.pod]]\nradius = 0.03\n",
            "unknown field `radius`",
        ),
    ] {
        let e = error(pods_config(), rest);
        assert!(e.contains(wanted), "{rest}: {e}");
    }
    // A robot without pods cannot have simulated ones.
    let e = error(Config::dji_m3508_example(), "[pods]\n");
    assert!(
        e.contains("pods = (a table)") && e.contains("[[odometry.pods]]"),
        "{e}"
    );
    // The defaults, and a sender of bus faults.
    let s = scenario(
        "[pods]\n[[faults]]\nkind = \"drop\"\nrate = 0.5\nsender = \"pods\"\nfrom_s = 0.5\nuntil_s = 1.0\n",
    );
    let p = s.pods.unwrap();
    assert_eq!((p.rate_hz, p.noise, p.pod.len()), (200.0, 0.0, 0));
    assert_eq!(s.bus_faults[0].sender, Some(Node::Pods));
}

#[test]
fn the_scenario_pages_pods_example_parses_as_written() {
    let source = include_str!("../../../docs/scenarios.md");
    let block: String = source
        .split("```toml\n")
        .find(|b| b.starts_with("[pods]"))
        .and_then(|b| b.split("```").next())
        .unwrap()
        .to_owned();
    let s = scenario(&block);
    let p = s.pods.unwrap();
    assert_eq!((p.rate_hz, p.noise), (200.0, 0.0));
    assert_eq!((p.radius_error, p.misalignment_deg), (0.01, 0.5));
    assert_eq!(p.pod.len(), 1);
    assert_eq!(p.pod[0].radius_error, 0.002);
    assert_eq!((p.pod[0].offset_x, p.pod[0].offset_y), (0.002, -0.001));
    // The first pod's errors in all: the block's and its own; the others the block's.
    let (first, second) = (p.errors(0), p.errors(1));
    assert_eq!(first.radius_error, 0.01 + 0.002);
    assert_eq!(first.misalignment_deg, 0.5 - 0.1);
    assert_eq!((second.radius_error, second.offset_x), (0.01, 0.0));
}
