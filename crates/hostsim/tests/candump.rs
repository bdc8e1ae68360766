//! candump logs in hostsim: the frame classification, the candump replay (a simulated run written as a candump log replays
//! identically; with real-time-like timing noise the odometry still agrees; a tampered
//! odometry frame is caught), and the `hostsim replay` / `hostsim plant` command lines
//! (exit status, JSON, errors naming the file and line).

mod common;

use std::path::{Path, PathBuf};

use common::hostsim;
use drivelog::candump::{Entry, Writer};
use embedded_can::StandardId;
use firmware::protocol::robot::{OdomPosition, Telemetry};
use firmware::{CanFrame, Config};
use hostsim::replay::{
    OdometryTolerance, TimedFrame, firmware_sends, mcap_playback, read_log, replay_candump,
    replay_split, split_candump,
};
use hostsim::scenario::Scenario;

// ---------------------------------------------------------------------------------------------
// Classification

fn frame(id: u16, data: &[u8]) -> CanFrame {
    CanFrame::standard(StandardId::new(id).unwrap(), data).unwrap()
}

#[test]
fn the_classification_follows_the_codecs_and_the_configuration() {
    let dji = Config::dji_m3508_example();
    let odrive = Config::odrive_example();
    // DJI current commands of the group its ESCs (1-4) are in; the other group's belong to
    // another board on the bus; feedback is received.
    assert!(firmware_sends(&dji, &frame(0x200, &[0; 8])));
    assert!(!firmware_sends(&dji, &frame(0x1FF, &[0; 8])));
    let mut dji_5_8 = dji;
    if let firmware::config::Drive::Dji { esc_ids, .. } = &mut dji_5_8.drive {
        *esc_ids = [5, 6, 7, 8];
    }
    assert!(firmware_sends(&dji_5_8, &frame(0x1FF, &[0; 8])));
    assert!(!firmware_sends(&dji_5_8, &frame(0x200, &[0; 8])));
    assert!(!firmware_sends(&dji, &frame(0x201, &[0; 8])));
    // A malformed 0x200 (DLC 2) is not something the firmware sends.
    assert!(!firmware_sends(&dji, &frame(0x200, &[0; 2])));
    // Telemetry is sent, host commands are received.
    let odom = Telemetry::OdomPosition(OdomPosition { x: 1.0, y: 2.0 }).to_can_frame();
    assert!(firmware_sends(&dji, &odom) && firmware_sends(&odrive, &odom));
    let twist = firmware::protocol::robot::Command::StatusRequest.to_can_frame();
    assert!(!firmware_sends(&dji, &twist));
    // ODrive: Set_Input_Vel to configured nodes 0-3 is sent; to node 9, or an encoder
    // estimate, is received. 0x200 is node 16's command 0 for ODrive, not a DJI command.
    let vel = |node: u16| frame(node << 5 | 0x0D, &[0; 8]);
    assert!(firmware_sends(&odrive, &vel(3)));
    assert!(!firmware_sends(&odrive, &vel(9)));
    assert!(!firmware_sends(&odrive, &frame(0x09, &[0; 8])));
    assert!(!firmware_sends(&odrive, &frame(0x200, &[0; 8])));
}

// ---------------------------------------------------------------------------------------------
// Replay

/// A file in cargo's scratch folder for integration tests (under the target directory).
fn scratch(name: &str) -> PathBuf {
    common::scratch("candump", name)
}

/// A 2 s drive (enable, then a twist with all three components), logged to MCAP; returns
/// the log's frames (received and sent, merged by time).
fn simulated_session(config: Config, name: &str) -> (PathBuf, Vec<TimedFrame>) {
    let text = common::driving(
        "name = \"candump-session\"\nduration_s = 2.0",
        [0.5, 0.2, 0.4],
        "",
    );
    let mut scenario = Scenario::from_toml(&text, Path::new("session.toml")).unwrap();
    scenario.config = config;
    let path = scratch(&format!("{name}.mcap"));
    common::logged_run(&scenario, &path);
    let content = read_log(&path).unwrap();
    (path, mcap_playback(&content, true, true))
}

const EPOCH_NS: u64 = 1_700_000_000_000_000_000;

fn write_candump(path: &Path, frames: &[TimedFrame]) {
    let mut w = Writer::new(Vec::new(), "vcan0").unwrap();
    for f in frames {
        w.write(EPOCH_NS + f.t_ns, &f.frame).unwrap();
    }
    std::fs::write(path, w.finish().unwrap()).unwrap();
}

fn entries(frames: &[TimedFrame]) -> Vec<Entry> {
    frames
        .iter()
        .map(|f| Entry {
            t_ns: EPOCH_NS + f.t_ns / 1000 * 1000,
            iface: "vcan0".into(),
            frame: f.frame,
            direction: None,
        })
        .collect()
}

#[test]
fn a_simulated_session_as_candump_replays_identically() {
    for (config, name) in [
        (Config::dji_m3508_example(), "dji"),
        (Config::odrive_example(), "odrive"),
    ] {
        let (_, frames) = simulated_session(config, name);
        let split = split_candump(&config, &entries(&frames));
        let r = replay_split(&config, &split, OdometryTolerance::default()).unwrap();
        assert!(r.identical, "{name}: {:?}", r.first_difference);
        assert_eq!(r.verdict(), "identical");
        assert_eq!(r.replayed, r.sent);
        // 2001 steps; DJI feedback at 1 kHz, ODrive encoder estimates at 100 Hz.
        assert!(r.sent > 2000 && r.received > 900, "{name}: {r:?}");
        let o = r.odometry.as_ref().unwrap();
        // The robot moved, and the replayed core is where the logged one said it was
        // (within the 0.1 mm / 0.0001 rad resolution of the frames).
        assert!(o.logged.x.hypot(o.logged.y) > 0.3, "{name}: {o:?}");
        assert!(
            o.position_error_m < 2e-4 && o.heading_error_rad < 2e-4,
            "{name}: {o:?}"
        );
        assert!(o.agrees);
        assert_eq!(r.rejected.unknown_id + r.rejected.wrong_dlc, 0);
    }
}

/// A small deterministic generator for the timing noise.
struct Lcg(u64);

impl Lcg {
    fn below(&mut self, n: u64) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (self.0 >> 33) % n
    }
}

#[test]
fn real_time_timing_noise_changes_the_frames_but_not_the_odometry() {
    let config = Config::dji_m3508_example();
    let (_, frames) = simulated_session(config, "noisy");
    // As a real runner's log: the capture starts 0.37 ms before the first step, received
    // frames arrive up to 0.6 ms later than in the simulation, sent frames leave up to
    // 0.15 ms after the step.
    let mut rng = Lcg(7);
    let mut noisy: Vec<TimedFrame> = frames
        .iter()
        .map(|f| {
            let jitter = if firmware_sends(&config, &f.frame) {
                rng.below(150_000)
            } else {
                rng.below(600_000)
            };
            TimedFrame {
                t_ns: f.t_ns + 370_000 + jitter,
                frame: f.frame,
            }
        })
        .collect();
    noisy.insert(
        0,
        TimedFrame {
            t_ns: 0,
            frame: frame(0x123, &[1, 2, 3]),
        },
    );
    let split = split_candump(&config, &entries(&noisy));
    let r = replay_split(&config, &split, OdometryTolerance::default()).unwrap();
    assert!(!r.identical, "the noise should move frames to other steps");
    let o = r.odometry.as_ref().unwrap();
    assert!(o.agrees, "{o:?}");
    assert!(o.position_error_m < 0.005, "{o:?}");
    assert_eq!(r.verdict(), "odometry_agrees");
    assert!(r.agrees());
    // The stray 0x123 frame was fed to the core, which ignored it as an unknown id.
    assert_eq!(r.rejected.unknown_id, 1);
}

#[test]
fn a_tampered_odometry_frame_is_a_difference() {
    let config = Config::dji_m3508_example();
    let (_, mut frames) = simulated_session(config, "tampered");
    let last = frames
        .iter()
        .rposition(|f| matches!(Telemetry::decode(&f.frame), Ok(Telemetry::OdomPosition(_))))
        .unwrap();
    let Ok(Telemetry::OdomPosition(p)) = Telemetry::decode(&frames[last].frame) else {
        unreachable!()
    };
    frames[last].frame = Telemetry::OdomPosition(OdomPosition {
        x: p.x + 0.05,
        y: p.y,
    })
    .to_can_frame();
    let path = scratch("tampered.log");
    write_candump(&path, &frames);
    let r = replay_candump(&path, &config, OdometryTolerance::default()).unwrap();
    assert!(!r.identical);
    let d = r.first_difference.as_ref().unwrap();
    assert!(
        d.logged.as_ref().unwrap().frame.starts_with("310#"),
        "{d:?}"
    );
    let o = r.odometry.unwrap();
    assert!((o.position_error_m - 0.05).abs() < 1e-3, "{o:?}");
    assert!(!o.agrees);
}

// ---------------------------------------------------------------------------------------------
// Command line

#[test]
fn replay_command_on_candump_and_mcap_logs() {
    let config = Config::dji_m3508_example();
    let (mcap, frames) = simulated_session(config, "cli");
    let log = scratch("cli.candump");
    write_candump(&log, &frames);
    let log_s = log.to_str().unwrap();

    // candump, JSON.
    let (code, out, err) = hostsim(["replay", log_s, "--json"]);
    assert_eq!(code, 0, "{out}{err}");
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v["format"], "candump");
    assert_eq!(v["verdict"], "identical");
    assert_eq!(v["identical"], true);
    assert_eq!(v["interfaces"], serde_json::json!(["vcan0"]));
    assert_eq!(v["odometry"]["agrees"], true);
    assert!(v["odometry"]["logged"]["x"].as_f64().unwrap() > 0.3);
    // candump, text.
    let (code, out, _) = hostsim(["replay", log_s]);
    assert_eq!(code, 0);
    assert!(out.contains("verdict: identical"), "{out}");
    assert!(out.contains("odometry agrees"), "{out}");
    // The wrong configuration (ODrive) classifies the DJI frames as received: it differs.
    let odrive_cfg = scratch("odrive.toml");
    std::fs::write(&odrive_cfg, Config::odrive_example().to_toml_string()).unwrap();
    let (code, out, err) = hostsim([
        "replay",
        log_s,
        "--json",
        "--config",
        odrive_cfg.to_str().unwrap(),
    ]);
    assert_eq!(code, 1, "{out}{err}");
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v["verdict"], "differs");

    // MCAP, JSON.
    let (code, out, err) = hostsim(["replay", mcap.to_str().unwrap(), "--json"]);
    assert_eq!(code, 0, "{out}{err}");
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(
        (v["format"].as_str(), v["identical"].as_bool()),
        (Some("mcap"), Some(true))
    );
    // With an MCAP log, --config is a what-if; another drive protocol is refused.
    let (code, _, err) = hostsim([
        "replay",
        mcap.to_str().unwrap(),
        "--config",
        odrive_cfg.to_str().unwrap(),
    ]);
    assert_eq!(code, 2);
    assert!(
        err.contains("drive.protocol differs (log: dji, what-if: odrive)"),
        "{err}"
    );
}

#[test]
fn bad_inputs_exit_2_naming_the_file_line_or_field() {
    let bad = scratch("bad.log");
    std::fs::write(
        &bad,
        "(1700000000.000100) vcan0 201#0000000000000000\n(1700000000.000200) vcan0 201#00GG\n",
    )
    .unwrap();
    let bad_s = bad.to_str().unwrap();
    let (code, _, err) = hostsim(["replay", bad_s]);
    assert_eq!(code, 2);
    assert!(err.contains(bad_s) && err.contains("line 2"), "{err}");
    assert!(err.contains("201#00GG"), "{err}");

    let fd = scratch("fd.log");
    std::fs::write(&fd, "(1.000000) vcan0 301##0112233\n").unwrap();
    let (code, _, err) = hostsim(["replay", fd.to_str().unwrap()]);
    assert_eq!(code, 2);
    assert!(err.contains("line 1: CAN FD"), "{err}");

    let empty = scratch("empty.log");
    std::fs::write(&empty, "\n").unwrap();
    let (code, _, err) = hostsim(["replay", empty.to_str().unwrap()]);
    assert_eq!(code, 2);
    assert!(err.contains("no frames"), "{err}");

    let (code, _, err) = hostsim(["replay", "/nonexistent/session.log"]);
    assert_eq!(code, 2);
    assert!(err.contains("/nonexistent/session.log"), "{err}");

    let bad_cfg = scratch("bad.toml");
    std::fs::write(&bad_cfg, "[geometry]\nkind = 3\n").unwrap();
    let good = scratch("good.log");
    std::fs::write(&good, "(1.000000) vcan0 201#0000000000000000\n").unwrap();
    let (code, _, err) = hostsim([
        "replay",
        good.to_str().unwrap(),
        "--config",
        bad_cfg.to_str().unwrap(),
    ]);
    assert_eq!(code, 2);
    assert!(err.contains(bad_cfg.to_str().unwrap()), "{err}");

    // Playback options need --iface; a bad speed is refused before the interface is opened.
    let (code, _, err) = hostsim(["replay", good.to_str().unwrap(), "--speed", "2"]);
    assert_eq!(code, 2);
    assert!(err.contains("--iface"), "{err}");
    let (code, _, err) = hostsim([
        "replay",
        good.to_str().unwrap(),
        "--iface",
        "nosuchcan9",
        "--speed",
        "0",
    ]);
    assert_eq!(code, 2);
    assert!(err.contains("--speed"), "{err}");
    let (code, _, err) = hostsim(["replay", good.to_str().unwrap(), "--iface", "nosuchcan9"]);
    assert_eq!(code, 2);
    assert!(err.contains("nosuchcan9"), "{err}");
    let (code, _, err) = hostsim(["plant", "--iface", "nosuchcan9", "--duration", "1"]);
    assert_eq!(code, 2);
    assert!(err.contains("nosuchcan9"), "{err}");
    let (code, _, err) = hostsim([
        "plant",
        "--iface",
        "nosuchcan9",
        "--config",
        bad_cfg.to_str().unwrap(),
    ]);
    assert_eq!(code, 2);
    assert!(err.contains(bad_cfg.to_str().unwrap()), "{err}");
    let (code, _, _) = hostsim(["plant", "--iface", "vcan0", "--duration", "-1"]);
    assert_eq!(code, 2);
}
