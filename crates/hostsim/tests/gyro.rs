//! Gyro heading on the simulator: the plant's IMU node sends `IMU_YAW_RATE` (bias, white
//! noise, seeded) and the firmware core, configured with `[odometry] heading_source =
//! "gyro"`, takes each odometry step's rotation from it. Measured against the plant's ground
//! truth with its default slip; the figures are printed (`cargo test -p hostsim --test gyro
//! -- --nocapture`).

mod common;

use std::path::Path;

use drivelog::for_each_message;
use drivelog::msg::{self, decode};
use drivelog::write::DIAGNOSTIC_NAME;
use firmware::CanFrame;
use firmware::config::{Config, HeadingMode};
use firmware::control::HeadingSource;
use firmware::protocol::robot::{self, RobotState, Telemetry};
use hostsim::bus::Node;
use hostsim::engine::{LogOptions, RunSummary, run_observed};
use hostsim::nodes::SimPlant;
use hostsim::nodes::drives::SimDrives;
use hostsim::replay::replay_mcap;
use hostsim::scenario::Scenario;

fn repo_file(name: &str) -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .join(name)
}

/// The 60 s figure-eight with a gyro (`scenarios/figure_eight_60s_gyro.toml`).
fn figure_eight_60s() -> Scenario {
    Scenario::from_file(&repo_file("scenarios/figure_eight_60s_gyro.toml")).unwrap()
}

/// A run's heading error against the ground truth, rad: at the end, and the largest at any
/// step.
#[derive(Debug, Clone, Copy)]
struct HeadingError {
    last: f64,
    max: f64,
}

fn heading_error(odometry: f64, truth: f64) -> f64 {
    kinematics::wrap_angle(odometry - truth)
}

/// Runs `scenario`, measuring the heading error at every step; also the STATUS frames the
/// core sent, with their time (µs).
fn measure(scenario: &Scenario) -> (RunSummary, HeadingError, Vec<(u64, robot::Status)>) {
    let mut plant = hostsim::engine::plant_for(scenario).unwrap();
    let mut max = 0.0f64;
    let mut statuses = Vec::new();
    let summary = run_observed(scenario, &mut plant, None, LogOptions::default(), |step| {
        let pose = step.controller.pose();
        max = max.max(heading_error(f64::from(pose.heading), step.truth[2]).abs());
        for f in step.sent {
            if let Ok(Telemetry::Status(s)) = Telemetry::decode(f) {
                statuses.push((step.t_us, s));
            }
        }
    })
    .unwrap();
    let last = summary.final_heading_error;
    (summary, HeadingError { last, max }, statuses)
}

/// A time in µs as the run reports it, s.
fn at(us: u64) -> f64 {
    us as f64 * 1e-6
}

fn with_odometry(mut s: Scenario, edit: impl FnOnce(&mut Config)) -> Scenario {
    edit(&mut s.config);
    s
}

#[test]
fn gyro_heading_after_the_60s_figure_eight_is_within_1_degree() {
    let gyro = figure_eight_60s();
    assert_eq!(gyro.config.odometry.heading_source, HeadingMode::Gyro);
    let imu = gyro.imu.expect("the scenario has an IMU");
    assert_eq!((imu.rate_hz, imu.bias_deg_s), (200.0, 0.1));
    let no_bias_estimate = with_odometry(gyro.clone(), |c| {
        c.odometry.gyro_bias_estimation = false;
    });
    let wheels = with_odometry(gyro.clone(), |c| {
        c.odometry.heading_source = HeadingMode::Wheels;
    });

    let (g, g_err, g_status) = measure(&gyro);
    let (n, n_err, _) = measure(&no_bias_estimate);
    let (w, w_err, w_status) = measure(&wheels);
    let deg = f64::to_degrees;
    println!(
        "60 s figure-eight ({:.1} s run, plant's default slip), heading error against the ground \
         truth, final / largest during the run:",
        gyro.duration_s
    );
    println!(
        "  gyro, bias estimated standing still: {:+.3}° / {:.3}°  (bias estimate {:+.4} °/s \
         from {} samples; true 0.1 °/s)",
        deg(g_err.last),
        deg(g_err.max),
        deg(f64::from(g.last.gyro_bias)),
        g.last.gyro_bias_samples
    );
    println!(
        "  gyro, no bias estimate:              {:+.3}° / {:.3}°  (0.1 °/s x {:.1} s = {:.2}°)",
        deg(n_err.last),
        deg(n_err.max),
        gyro.duration_s,
        0.1 * gyro.duration_s
    );
    println!(
        "  wheels only:                         {:+.3}° / {:.3}°",
        deg(w_err.last),
        deg(w_err.max)
    );
    println!(
        "  position error final / largest: gyro {:.1} / {:.1} mm, no bias estimate {:.1} / \
         {:.1} mm, wheels {:.1} / {:.1} mm",
        g.final_position_error * 1e3,
        g.max_position_error * 1e3,
        n.final_position_error * 1e3,
        n.max_position_error * 1e3,
        w.final_position_error * 1e3,
        w.max_position_error * 1e3
    );

    // With the bias learned in the 2 s standstill: within 1° all along.
    assert!(deg(g_err.max) <= 1.0, "gyro heading error {:?}", g_err);
    let bias = f64::from(g.last.gyro_bias).to_degrees();
    assert!((bias - 0.1).abs() < 0.01, "bias estimate {bias} °/s");
    // The learning window: from the settle time after the motors came online to the first
    // twist at 2 s, 200 frames a second.
    assert!((370..=400).contains(&g.last.gyro_bias_samples));
    // Without the estimate, the bias integrates: 0.1 °/s over the run, about 6°.
    let expected = 0.1 * gyro.duration_s;
    assert!(
        (deg(n_err.last) - expected).abs() < 0.5,
        "no bias estimate: {}° (expected about {expected}°)",
        deg(n_err.last)
    );
    assert_eq!(n.last.gyro_bias_samples, 0);
    // Wheel heading slips (the figure-eight's left and right loops cancel much of it by the
    // end, not during the run): worse than the gyro's.
    assert!(w_err.max > 2.0 * g_err.max, "{w_err:?} vs {g_err:?}");
    assert!(
        w_err.last.abs() > g_err.last.abs(),
        "{w_err:?} vs {g_err:?}"
    );
    // And the heading carries the position: the gyro's odometry ends far closer.
    assert!(g.final_position_error < 0.2 * w.final_position_error);

    // STATUS reports the source: the gyro after its first frame, and WHEELS without it.
    assert!(
        g_status
            .iter()
            .skip(1)
            .all(|(_, s)| s.heading_source == HeadingSource::Gyro)
    );
    assert!(
        w_status
            .iter()
            .all(|(_, s)| s.heading_source == HeadingSource::Wheels)
    );
    assert_eq!(
        g.heading_changes,
        [
            (0.0, "WHEELS_GYRO_SILENT".to_string()),
            (at(6_000), "GYRO".to_string())
        ]
    );
    assert!(w.heading_changes.is_empty());
}

/// A shorter gyro run: the figure-eight's first loop and a half.
fn short_gyro_run(extra: &str) -> Scenario {
    let text = format!(
        r#"
        duration_s = 15.0
        seed = 7
        config = "config/dji_m3508_gyro.toml"
        [imu]
        bias_deg_s = 0.1
        [[actions]]
        at_s = 0.5
        enable = true
        [[actions]]
        at_s = 1.0
        twist = [0.4, 0.0, 0.6283185]
        [[actions]]
        at_s = 11.0
        twist = [0.4, 0.0, -0.6283185]
        {extra}
    "#
    );
    Scenario::from_toml(&text, &repo_file("gyro-test.toml")).unwrap()
}

#[test]
fn a_silent_gyro_falls_back_to_the_wheels_with_the_reason_reported_and_comes_back() {
    // The IMU's frames are lost from 5 s to 7 s (a burst on its sender alone).
    let scenario = short_gyro_run(
        r#"
        [[faults]]
        kind = "burst"
        sender = "imu"
        from_s = 5.0
        until_s = 7.0
        "#,
    );
    let path = common::scratch("gyro", "silent.mcap");
    let SilentRun {
        summary: r,
        statuses,
        last_imu_us,
        back_us,
    } = silent_run(&scenario, &path);
    println!(
        "last IMU frame before the silence at {:.6} s, first after at {:.6} s; heading source \
         changes: {:?}",
        last_imu_us as f64 * 1e-6,
        back_us as f64 * 1e-6,
        r.heading_changes
    );
    // The first step more than gyro_timeout_ms (50 ms) after the last frame, and the first
    // step after the first frame back.
    let fell_back_us = (last_imu_us + 50_000) / 1000 * 1000 + 1000;
    let returned_us = back_us.div_ceil(1000) * 1000;
    assert_eq!(
        r.heading_changes,
        [
            (0.0, "WHEELS_GYRO_SILENT".to_string()),
            (at(6_000), "GYRO".to_string()),
            (at(fell_back_us), "WHEELS_GYRO_SILENT".to_string()),
            (at(returned_us), "GYRO".to_string()),
        ]
    );
    // A warning, not a fault: the robot drove on.
    assert_eq!(r.transitions.len(), 1, "{:?}", r.transitions);
    assert_eq!(
        (r.last.state, r.last.heading_source),
        (RobotState::Enabled, HeadingSource::Gyro)
    );
    // STATUS says so, at its 10 Hz.
    for (t, s) in &statuses {
        let want = if *t >= fell_back_us && *t < returned_us || *t < 6_000 {
            HeadingSource::WheelsGyroSilent
        } else {
            HeadingSource::Gyro
        };
        assert_eq!(s.heading_source, want, "STATUS at {t} µs");
        assert!(*t <= 500_000 || s.state == RobotState::Enabled);
    }
    assert_eq!(
        statuses
            .iter()
            .filter(|(_, s)| s.heading_source == HeadingSource::WheelsGyroSilent)
            .count(),
        21, // t = 0, and 5.1 .. 7.0 s
    );

    // The log: /rosout has the two changes of the silence (a warning with the reason, then
    // information), /diagnostics says WheelsGyroSilent at the WARN level meanwhile.
    check_silence_in_the_log(&path, fell_back_us, returned_us);
    // `hostsim summary` lists the changes among the events.
    let summary = hostsim::analysis::summary::summarize(&path).unwrap();
    let events: Vec<_> = summary
        .events
        .iter()
        .filter(|e| e.2.starts_with("heading source"))
        .collect();
    assert_eq!(events.len(), 4);
    // The log replays bit for bit: the IMU's frames are among the inbound ones.
    let replay = replay_mcap(&path).unwrap();
    assert!(replay.identical(), "{:?}", replay.difference);
}

/// What the silent-gyro run shows: its summary, every STATUS sent (step time, µs), the last
/// IMU frame delivered before the silence (at 5 s) and the first after it (µs).
struct SilentRun {
    summary: RunSummary,
    statuses: Vec<(u64, robot::Status)>,
    last_imu_us: u64,
    back_us: u64,
}

/// Runs `scenario` with its log at `path`, watching the IMU's deliveries and the STATUS
/// frames.
fn silent_run(scenario: &Scenario, path: &Path) -> SilentRun {
    let mut log =
        drivelog::McapLog::create(path, &hostsim::engine::run_metadata(scenario)).unwrap();
    let mut plant = hostsim::engine::plant_for(scenario).unwrap();
    let mut statuses = Vec::new();
    let mut last_imu_us = 0;
    let mut first_imu_after_us = None;
    let r = run_observed(
        scenario,
        &mut plant,
        Some(&mut log),
        LogOptions::default(),
        |step| {
            for tx in step.delivered {
                if tx.from == Node::Imu && tx.fate != hostsim::bus::Fate::Dropped {
                    let t = tx.delivered_ns / 1000;
                    if t < 5_000_000 {
                        last_imu_us = t;
                    } else if first_imu_after_us.is_none() {
                        first_imu_after_us = Some(t);
                    }
                }
            }
            for f in step.sent {
                if let Ok(Telemetry::Status(s)) = Telemetry::decode(f) {
                    statuses.push((step.t_us, s));
                }
            }
        },
    )
    .unwrap();
    log.finish().unwrap();
    SilentRun {
        summary: r,
        statuses,
        last_imu_us,
        back_us: first_imu_after_us.unwrap(),
    }
}

/// The log of the silent-gyro run: /rosout has the fallback at `fell_back_us` (a warning
/// with the reason) and the return at `returned_us`, /diagnostics says WHEELS_GYRO_SILENT
/// at the WARN level every 10 ms between them.
fn check_silence_in_the_log(path: &Path, fell_back_us: u64, returned_us: u64) {
    let bytes = std::fs::read(path).unwrap();
    let mut rosout = Vec::new();
    let mut silent_diagnostics = Vec::new();
    let mut gyro_diagnostics = 0;
    for_each_message(
        &bytes,
        |m| match m.topic {
            "/rosout" => {
                let l = decode::<msg::Log>(m.data).unwrap();
                if l.msg.starts_with("heading source") {
                    rosout.push((m.log_time / 1000, l.level, l.msg));
                }
            }
            "/diagnostics" => {
                let d = decode::<msg::DiagnosticArray>(m.data).unwrap();
                let status = &d.status[0];
                assert_eq!(status.name, DIAGNOSTIC_NAME);
                let value = |k: &str| {
                    status
                        .values
                        .iter()
                        .find(|kv| kv.key == k)
                        .map(|kv| kv.value.clone())
                };
                match value("heading_source").as_deref() {
                    Some("WHEELS_GYRO_SILENT") => silent_diagnostics.push((
                        m.log_time / 1000,
                        status.level,
                        status.message.clone(),
                    )),
                    Some("GYRO") => gyro_diagnostics += 1,
                    other => panic!("heading_source {other:?}"),
                }
                assert!(value("gyro_bias").is_some() && value("gyro_bias_samples").is_some());
            }
            _ => {}
        },
        |_, _| {},
    )
    .unwrap();
    assert_eq!(rosout.len(), 4, "{rosout:?}");
    let (t, level, text) = &rosout[2];
    assert_eq!((*t, *level), (fell_back_us, msg::Log::WARN));
    assert!(
        text.contains("WHEELS_GYRO_SILENT") && text.contains("no valid IMU_YAW_RATE for 50 ms"),
        "{text}"
    );
    assert_eq!((rosout[3].0, rosout[3].1), (returned_us, msg::Log::INFO));
    assert!(rosout[3].2.contains("GYRO"), "{}", rosout[3].2);
    // Every 10 ms from the fallback to the return (and the first step).
    let during: Vec<_> = silent_diagnostics.iter().filter(|d| d.0 > 0).collect();
    assert!(
        during
            .iter()
            .all(|d| d.0 >= fell_back_us && d.0 < returned_us)
    );
    assert_eq!(
        during.len() as u64,
        (returned_us.div_ceil(10_000) - fell_back_us.div_ceil(10_000))
    );
    assert!(during.iter().all(|d| d.1 == msg::DiagnosticStatus::WARN
        && d.2 == "ENABLED, heading from the wheels: gyro silent"));
    assert!(gyro_diagnostics > 1000);
}

/// The simulated drives, with an IMU of their own that sends malformed `IMU_YAW_RATE`
/// frames: one of each kind every 100 ms from 1 s to 14 s.
struct BadImu {
    drives: SimDrives,
    now_ns: u64,
    next_ns: u64,
    sent: [u32; 4],
}

impl BadImu {
    /// The last set of frames, ns.
    const LAST_NS: u64 = 14_000_000_000;
    const FRAMES: [(&'static str, usize, f32); 4] = [
        ("wrong_dlc", 7, 0.0),
        ("non_finite", 8, f32::NAN),
        ("non_finite", 8, f32::INFINITY),
        ("out_of_range", 8, 40.0),
    ];
}

impl SimPlant for BadImu {
    fn on_frame(&mut self, t_us: u64, frame: &CanFrame) {
        self.drives.on_frame(t_us, frame);
    }
    fn feedback(&mut self, until_ns: u64, out: &mut Vec<(u64, CanFrame)>) {
        self.drives.feedback(until_ns, out);
    }
    fn node_frames(&mut self, node: Node, until_ns: u64, out: &mut Vec<(u64, CanFrame)>) {
        if node != Node::Imu {
            return;
        }
        while self.next_ns <= until_ns.min(self.now_ns).min(Self::LAST_NS) {
            for (i, (_, dlc, rate)) in Self::FRAMES.into_iter().enumerate() {
                let mut data = [0u8; 8];
                data[..4].copy_from_slice(&rate.to_le_bytes());
                let id = embedded_can::StandardId::new(0x304).unwrap();
                out.push((self.next_ns, CanFrame::from_buffer(id, data, dlc as u8)));
                self.sent[i] += 1;
            }
            self.next_ns += 100_000_000;
        }
    }
    fn next_feedback_ns(&self) -> u64 {
        let mine = if self.next_ns <= Self::LAST_NS {
            self.next_ns
        } else {
            u64::MAX
        };
        self.drives.next_feedback_ns().min(mine)
    }
    common::pass_to_drives!();
}

#[test]
fn malformed_imu_frames_are_counted_by_kind_and_the_gyro_carries_on() {
    let scenario = short_gyro_run("");
    let mut plant = BadImu {
        drives: hostsim::engine::plant_for(&scenario).unwrap(),
        now_ns: 0,
        next_ns: 1_000_000_000,
        sent: [0; 4],
    };
    let mut counters = None;
    let r = run_observed(&scenario, &mut plant, None, LogOptions::default(), |step| {
        for f in step.sent {
            if let Ok(Telemetry::StatusCounters(c)) = Telemetry::decode(f) {
                counters = Some((step.t_us, c));
            }
        }
    })
    .unwrap();
    let [dlc, nan, inf, range] = plant.sent;
    println!(
        "sent {dlc} IMU_YAW_RATE frames with DLC 7, {nan} NaN, {inf} inf, {range} at 40 rad/s; \
         the core counted {:?}",
        r.last.rx_errors
    );
    assert_eq!(dlc, 131);
    let e = r.last.rx_errors;
    assert_eq!(
        (e.wrong_dlc, e.non_finite, e.out_of_range, e.unknown_id),
        (dlc, nan + inf, range, 0)
    );
    // The last STATUS_COUNTERS (at 15 s) counted them all.
    let (t, c) = counters.unwrap();
    assert_eq!(t, 15_000_000);
    assert_eq!(
        (
            u32::from(c.wrong_dlc),
            u32::from(c.non_finite),
            u32::from(c.out_of_range)
        ),
        (dlc, nan + inf, range)
    );
    // The valid frames kept the gyro the source all along.
    assert_eq!(r.heading_changes.len(), 2, "{:?}", r.heading_changes);
    assert_eq!(r.last.heading_source, HeadingSource::Gyro);
}

#[test]
fn the_same_seed_gives_the_same_imu_frames_and_outbound_stream() {
    let imu_frames = |scenario: &Scenario| {
        let mut plant = hostsim::engine::plant_for(scenario).unwrap();
        let mut frames = Vec::new();
        let r = run_observed(scenario, &mut plant, None, LogOptions::default(), |step| {
            frames.extend(
                step.delivered
                    .iter()
                    .filter(|tx| tx.from == Node::Imu)
                    .map(|tx| (tx.delivered_ns, tx.frame)),
            );
        })
        .unwrap();
        (r, frames)
    };
    let s = short_gyro_run("");
    let (a, fa) = imu_frames(&s);
    let (b, fb) = imu_frames(&s);
    // 15 s at 200 Hz; the last one reaches the core after its last step.
    assert_eq!(fa.len(), 2999);
    assert_eq!(fa, fb);
    assert_eq!(a.tx_hash, b.tx_hash);
    assert_eq!(a.odometry, b.odometry);
    let mut other = s.clone();
    other.seed = 8;
    let (c, fc) = imu_frames(&other);
    assert_ne!(fa, fc, "another seed, other noise");
    assert_ne!(a.tx_hash, c.tx_hash);
    println!(
        "seed 7: outbound hash {:016x} twice; seed 8: {:016x}",
        a.tx_hash, c.tx_hash
    );
}

#[test]
fn without_an_imu_table_a_scenario_runs_as_before_and_the_gyro_config_falls_back() {
    // The IMU is off by default: no IMU frames on the bus.
    let s = Scenario::builtin("figure-eight").unwrap();
    assert!(s.imu.is_none());
    // A gyro configuration without an IMU on the bus: wheel heading all along, and the
    // reason in every STATUS. (Its STATUS bytes differ, so do their stuff bits and the bus
    // timing of everything after them, and the closed loop drifts apart by a hair: the
    // odometry is the wheels' as closely as two such runs agree.)
    let gyro = with_odometry(s.clone(), |c| c.odometry.heading_source = HeadingMode::Gyro);
    let (g, g_err, statuses) = measure(&gyro);
    let (w, w_err, _) = measure(&s);
    assert!(
        statuses
            .iter()
            .all(|(_, st)| st.heading_source == HeadingSource::WheelsGyroSilent)
    );
    assert_eq!(g.heading_changes, [(0.0, "WHEELS_GYRO_SILENT".to_string())]);
    assert!(
        (g_err.last - w_err.last).abs() < 1e-3,
        "{g_err:?} vs {w_err:?}"
    );
    assert!(
        (g_err.max - w_err.max).abs() < 1e-3,
        "{g_err:?} vs {w_err:?}"
    );
    assert!((g.final_position_error - w.final_position_error).abs() < 1e-3);
}

#[test]
fn the_imu_table_parses_with_defaults_and_refuses_values_out_of_range() {
    let base = "duration_s = 1.0\n";
    let s = Scenario::from_toml(&format!("{base}[imu]\n"), Path::new("imu.toml")).unwrap();
    let imu = s.imu.unwrap();
    assert_eq!(
        (imu.enabled, imu.rate_hz, imu.bias_deg_s, imu.noise_density),
        (true, 200.0, 0.1, 0.005)
    );
    let s = Scenario::from_toml(
        &format!("{base}[imu]\nrate_hz = 100.0\nenabled = false\n"),
        Path::new("imu.toml"),
    )
    .unwrap();
    assert_eq!(s.imu.map(|i| (i.rate_hz, i.enabled)), Some((100.0, false)));
    // The IMU is a bus node of its own for faults.
    let s = Scenario::from_toml(
        &format!("{base}[[faults]]\nkind = \"drop\"\nrate = 0.5\nsender = \"imu\"\nfrom_s = 0.0\nuntil_s = 1.0\n"),
        Path::new("imu.toml"),
    )
    .unwrap();
    assert_eq!(s.bus_faults[0].sender, Some(Node::Imu));
    for (table, want) in [
        ("rate_hz = 0.0", "imu.rate_hz = 0: a rate in (0, 2000] Hz"),
        (
            "rate_hz = 5000.0",
            "imu.rate_hz = 5000: a rate in (0, 2000] Hz",
        ),
        (
            "bias_deg_s = inf",
            "imu.bias_deg_s = inf: a bias in [-100, 100] °/s",
        ),
        (
            "noise_density = -0.1",
            "imu.noise_density = -0.1: a rate noise density in [0, 10] °/s/√Hz",
        ),
        ("rate = 200.0", "unknown field `rate`"),
    ] {
        let e = Scenario::from_toml(&format!("{base}[imu]\n{table}\n"), Path::new("bad.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains(want) && e.contains("bad.toml"), "{table}: {e}");
    }
}
