//! The `mecanum-runner` binary from the outside: `--help`, and the startup errors (exit
//! status 2, a message naming the file, field or interface, never a panic).
//!
//! `runs_on_vcan0` needs a virtual CAN interface and is ignored by default; run it where one
//! exists with `cargo test -p mecanum-runner --test cli -- --ignored`
//! after `ip link add dev vcan0 type vcan && ip link set up vcan0`.

use std::path::PathBuf;
use std::process::{Command, Output};

const RUNNER: &str = env!("CARGO_BIN_EXE_mecanum-runner");

fn runner(args: &[&str]) -> Output {
    Command::new(RUNNER)
        .args(args)
        .output()
        .expect("the runner binary starts")
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A file in the test's scratch folder with `text` in it.
fn scratch(name: &str, text: &str) -> PathBuf {
    let path = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(name);
    std::fs::write(&path, text).expect("scratch file written");
    path
}

/// The example DJI configuration with one line replaced.
fn dji_config_with(name: &str, from: &str, to: &str) -> PathBuf {
    let example = concat!(env!("CARGO_MANIFEST_DIR"), "/../../config/dji_m3508.toml");
    let text = std::fs::read_to_string(example).expect("example configuration");
    assert!(text.contains(from), "{from:?} not in the example");
    scratch(name, &text.replace(from, to))
}

/// Exit status 2 and a one-line-per-fact message, no panic.
fn assert_startup_error(out: &Output) -> String {
    let err = stderr(out);
    assert_eq!(out.status.code(), Some(2), "stderr: {err}");
    assert!(!err.contains("panicked"), "{err}");
    assert!(out.stdout.is_empty());
    err
}

#[test]
fn help_explains_the_protocol_and_the_exit() {
    let out = runner(&["--help"]);
    assert!(out.status.success());
    let help = String::from_utf8_lossy(&out.stdout);
    for needle in [
        "--iface <IFACE>",
        "--config <FILE>",
        "--duration <SECONDS>",
        "--stats-json <FILE>",
        "--quiet",
        "built-in DJI example",
        "0x300-0x31F",
        "0x301 TWIST_CMD",
        "0x312 STATUS",
        "0x31F HEARTBEAT",
        "0x306 POD_COUNTS",
        "0x315 ODOM_SLIP",
        "CiA 402",
        "--live [<ADDR>]",
        "SIGTERM",
        "zero current",
        "Exit status",
    ] {
        assert!(help.contains(needle), "--help lacks {needle:?}:\n{help}");
    }
}

#[test]
fn an_invalid_value_exits_2_naming_file_and_field() {
    let path = dji_config_with(
        "bad_value.toml",
        "max_wheel_speed = 45.0",
        "max_wheel_speed = -1.0",
    );
    let out = runner(&["--iface", "vcan0", "--config", path.to_str().unwrap()]);
    let err = assert_startup_error(&out);
    assert!(err.contains("limits.max_wheel_speed = -1"), "{err}");
    assert!(err.contains("bad_value.toml"), "{err}");
}

#[test]
fn an_unknown_field_exits_2_naming_the_line() {
    let path = dji_config_with("bad_field.toml", "max_wheel_speed =", "max_wheel_sped =");
    let out = runner(&["--iface", "vcan0", "--config", path.to_str().unwrap()]);
    let err = assert_startup_error(&out);
    assert!(err.contains("unknown field `max_wheel_sped`"), "{err}");
    let text = std::fs::read_to_string(&path).unwrap();
    let line = 1 + text
        .lines()
        .position(|l| l.starts_with("max_wheel_sped"))
        .unwrap();
    assert!(err.contains(&format!("line {line}")), "line {line}: {err}");
}

#[test]
fn a_missing_config_file_exits_2_naming_it() {
    let out = runner(&["--iface", "vcan0", "--config", "/no/such/dir/robot.toml"]);
    let err = assert_startup_error(&out);
    assert!(err.contains("/no/such/dir/robot.toml"), "{err}");
}

#[test]
fn a_missing_interface_exits_2_naming_it() {
    let out = runner(&["--iface", "nosuchcan7"]);
    let err = assert_startup_error(&out);
    assert!(err.contains("\"nosuchcan7\""), "{err}");
}

#[test]
fn bad_arguments_exit_2() {
    assert_startup_error(&runner(&[]));
    assert_startup_error(&runner(&["--iface", "vcan0", "--duration", "-1"]));
    assert_startup_error(&runner(&["--iface", "vcan0", "--duration", "soon"]));
}

#[test]
fn bad_rotation_values_exit_2_naming_option_and_value() {
    let log = ["--iface", "vcan0", "--log", "/tmp/unused-rotation-dir"];
    let with = |extra: &[&str]| runner(&[&log[..], extra].concat());
    let err = assert_startup_error(&with(&["--log-max-mb", "1", "--log-keep", "0"]));
    assert!(err.contains("--log-keep 0"), "{err}");
    let err = assert_startup_error(&with(&["--log-max-mb", "0"]));
    assert!(err.contains("--log-max-mb 0"), "{err}");
    let err = assert_startup_error(&with(&["--log-max-mb", "-3"]));
    assert!(err.contains("--log-max-mb -3"), "{err}");
    // --log-keep without --log-max-mb would silently do nothing: refused.
    assert_startup_error(&with(&["--log-keep", "3"]));
    assert!(!std::path::Path::new("/tmp/unused-rotation-dir").exists());
}

#[test]
fn a_failed_startup_writes_no_stats_file() {
    let stats = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("never_written.json");
    let _ = std::fs::remove_file(&stats);
    let out = runner(&[
        "--iface",
        "nosuchcan7",
        "--stats-json",
        stats.to_str().unwrap(),
    ]);
    assert_startup_error(&out);
    assert!(!stats.exists());
}

/// The runner on vcan0 for two seconds, watched by a second socket: the frames appear at
/// their rates, SIGTERM stops it with exit 0 after a zero-current frame, and the statistics
/// file has the counts.
#[test]
#[ignore = "needs vcan0 up: ip link add dev vcan0 type vcan && ip link set up vcan0"]
fn runs_on_vcan0() {
    use embedded_can::{Frame as _, Id};
    use socketcan::Socket as _;
    use std::collections::HashMap;
    use std::time::{Duration, Instant};

    let listener = socketcan::CanSocket::open("vcan0").expect("vcan0 exists and is up");
    // An unwritable statistics file is a startup error, found before the loop.
    let out = runner(&["--iface", "vcan0", "--stats-json", "/no/such/dir/s.json"]);
    let err = assert_startup_error(&out);
    assert!(err.contains("/no/such/dir/s.json"), "{err}");

    listener
        .set_read_timeout(Duration::from_millis(50))
        .unwrap();
    let stats = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("vcan0_stats.json");
    let mut child = Command::new(RUNNER)
        .args(["--iface", "vcan0", "--stats-json", stats.to_str().unwrap()])
        .spawn()
        .unwrap();

    let mut counts: HashMap<u16, u32> = HashMap::new();
    let mut last_motor = None;
    let watch = Instant::now();
    let mut signalled = false;
    while watch.elapsed() < Duration::from_secs(3) {
        if !signalled && watch.elapsed() >= Duration::from_secs(2) {
            let pid = child.id().to_string();
            assert!(
                Command::new("kill")
                    .args(["-TERM", &pid])
                    .status()
                    .unwrap()
                    .success()
            );
            signalled = true;
        }
        if let Ok(frame) = listener.read_frame()
            && let Id::Standard(id) = frame.id()
        {
            *counts.entry(id.as_raw()).or_default() += 1;
            if id.as_raw() == 0x200 {
                last_motor = Some(frame.data().to_vec());
            }
        }
    }
    let status = child.wait().unwrap();
    assert!(status.success(), "{status}");
    // Two seconds at 1000 / 100 / 10 Hz, within the slack of a start-up and a busy machine.
    let within = |id: u16, lo: u32, hi: u32| {
        let n = counts.get(&id).copied().unwrap_or(0);
        assert!((lo..=hi).contains(&n), "{id:#x}: {n} frames, {counts:?}");
    };
    within(0x200, 1500, 2100);
    within(0x310, 150, 210);
    within(0x311, 150, 210);
    within(0x312, 15, 21);
    within(0x31F, 15, 21);
    assert_eq!(last_motor.as_deref(), Some(&[0u8; 8][..]));

    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&stats).unwrap()).unwrap();
    assert_eq!(report["stop"], serde_json::json!({ "signal": 15 }));
    assert_eq!(report["shutdown"]["sent"], 1);
    assert_eq!(report["send_errors"], 0);
    assert!(report["jitter"]["p99_us"].as_u64().is_some());
}
