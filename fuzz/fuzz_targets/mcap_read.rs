//! The MCAP reading path of `hostsim replay` and `hostsim summary`: `log::for_each_message`,
//! `replay::read_log_bytes` (decoding every `/can/rx` and `/can/tx` message's CDR),
//! `summary::summarize`, and `replay::replay_frames` on what was read (with the log's own
//! configuration when it loads, else the example one) for logs spanning at most 0.5 s.
//! Garbage, truncated and corrupted files give errors, never a panic.
#![no_main]

use std::path::PathBuf;
use std::sync::OnceLock;

use firmware::config::Config;
use hostsim::replay::{self, TimedFrame};
use libfuzzer_sys::fuzz_target;

/// `summarize` takes a path: the input goes through one scratch file per fuzzing process.
fn scratch() -> &'static PathBuf {
    static PATH: OnceLock<PathBuf> = OnceLock::new();
    PATH.get_or_init(|| {
        std::env::temp_dir().join(format!("mecanum-fuzz-mcap-{}.mcap", std::process::id()))
    })
}

/// Longest log span replayed, ns: replay runs one step per control period of the span.
const MAX_REPLAY_SPAN_NS: u64 = 500_000_000;

fuzz_target!(|data: &[u8]| {
    let mut messages = 0usize;
    let walked = drivelog::for_each_message(data, |_| messages += 1, |_, _| {});

    let content = replay::read_log_bytes(data);
    assert_eq!(walked.is_ok(), content.is_ok());
    if let Ok(read) = &walked {
        assert_eq!(read.messages, messages as u64);
        assert_eq!(read.file_len, data.len() as u64);
        if let Some(d) = &read.damage {
            // The damage is named at an offset within the file, and its text says where.
            assert!(d.offset <= data.len() as u64);
            assert!(!d.to_string().is_empty());
        }
    }
    if let Ok(c) = &content {
        assert_eq!(c.topics.values().sum::<u64>(), messages as u64);
        for f in c.rx.iter().chain(&c.tx) {
            mecanum_fuzz::check_frame(&f.frame);
        }
    }

    std::fs::write(scratch(), data).expect("scratch file");
    let summary = hostsim::analysis::summary::summarize(scratch());
    // The summary also refuses a readable log in another layout than this project's.
    let ours = content
        .as_ref()
        .is_ok_and(|c| !replay::is_old_layout(&c.read));
    assert_eq!(summary.is_ok(), ours);
    if let Ok(s) = &summary {
        assert!(s.duration_s >= 0.0);
    }

    let Ok(content) = content else { return };
    let end = content
        .rx
        .iter()
        .chain(&content.tx)
        .map(|f: &TimedFrame| f.t_ns)
        .max()
        .unwrap_or(0);
    if end > MAX_REPLAY_SPAN_NS {
        return;
    }
    let config = content
        .config
        .as_deref()
        .and_then(|text| Config::from_toml_str(text).ok())
        .unwrap_or_else(Config::dji_m3508_example);
    // Spans of at most 0.5 s have no gap over replay::MAX_GAP_NS: only a configuration error
    // could stop the replay, and a configuration that loads is accepted.
    let report = replay::replay_frames(&config, &content.rx, &content.tx)
        .expect("a configuration that loads is accepted, and 0.5 s has no long gap");
    assert!(report.fed <= content.rx.len());
    assert!(report.compared <= content.tx.len());
    let _ = replay::mcap_playback(&content, true, true);
});
