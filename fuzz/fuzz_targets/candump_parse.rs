//! The candump parser: `parse_log_bytes` / `parse_line` / `parse_frame` on any bytes never
//! panic. Every parsed line formats back (`format_line`) to a line that parses to the same
//! entry (time truncated to microseconds, as candump writes it), and a short log is split
//! and replayed through the core as `hostsim replay` does.
#![no_main]

use firmware::config::Config;
use drivelog::candump::{self, Entry};
use hostsim::replay::{OdometryTolerance, replay_split, split_candump};
use libfuzzer_sys::fuzz_target;
use mecanum_fuzz::check_frame;

fn round_trip(e: &Entry) {
    check_frame(&e.frame);
    let Some(line) = candump::format_line(e.t_ns, &e.iface, &e.frame) else {
        // Parsed interfaces are whitespace-free and have no '#'; parentheses may remain.
        return;
    };
    let again = candump::parse_line(&line, 1)
        .unwrap_or_else(|err| panic!("formatted line {line:?} does not parse: {err}"))
        .expect("not blank");
    assert_eq!(again.frame, e.frame, "{line}");
    assert_eq!(again.iface, e.iface);
    assert_eq!(again.t_ns, e.t_ns / 1000 * 1000);
    assert_eq!(
        candump::parse_frame(&candump::format_frame(&e.frame)),
        Ok(e.frame)
    );
}

fuzz_target!(|data: &[u8]| {
    let _ = candump::looks_like_candump(data);
    let entries = match candump::parse_log_bytes(data) {
        Ok(entries) => entries,
        Err(e) => {
            let _ = std::format!("{e}");
            return;
        }
    };
    if let Ok(text) = std::str::from_utf8(data) {
        assert_eq!(candump::parse_log(text).ok().as_ref(), Some(&entries));
    }
    for e in &entries {
        round_trip(e);
    }
    // Replay steps through every control period of the log's time span: keep it short.
    let Some(first) = entries.iter().map(|e| e.t_ns).min() else {
        return;
    };
    let last = entries.iter().map(|e| e.t_ns).max().unwrap_or(first);
    if last - first > 200_000_000 {
        return;
    }
    for config in [Config::dji_m3508_example(), Config::odrive_example()] {
        let split = split_candump(&config, &entries);
        assert_eq!(split.all.len(), entries.len());
        let _ = replay_split(&config, &split, OdometryTolerance::default())
            .expect("example configurations are valid");
    }
});
