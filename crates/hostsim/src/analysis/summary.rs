//! `hostsim summary`: what a log says about a run — odometry drift against ground truth, bus
//! load, firmware state changes and faults — computed from the log alone.
//!
//! Reading goes through [`for_each_message`], which takes every complete, intact chunk and
//! stops at the first damaged record, so a log cut short by a killed run (or corrupted) is
//! summarised up to its last complete chunk, and [`LogSummary::read`] says where the damage
//! is, with its byte offset.

use std::collections::BTreeMap;
use std::path::Path;

use crate::bus::frame_bits;
use drivelog::msg;
use drivelog::{ReadReport, for_each_message};

/// Figures of a logged run.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LogSummary {
    /// Scenario name from the metadata.
    pub scenario: Option<String>,
    /// Messages per topic.
    pub topics: BTreeMap<String, u64>,
    /// Time of the last message, s.
    pub duration_s: f64,
    /// Final odometry pose `[x, y, heading]`.
    pub odometry: Option<[f64; 3]>,
    /// Final ground-truth pose.
    pub truth: Option<[f64; 3]>,
    /// Final and largest odometry position error against ground truth, m.
    pub drift: Option<(f64, f64)>,
    /// Bus load from the frames (`/can/rx`, `/can/tx`, and the frames on `/can/faults` that
    /// reached neither), in bits at 1 Mbit/s over the duration, 0..1.
    pub bus_load: Option<f64>,
    /// Frames on the bus by fate (`delivered`, `dropped`, `corrupted`).
    pub fates: BTreeMap<String, u64>,
    /// Firmware log lines `(time s, level, text)` from `/rosout` (`rcl_interfaces/msg/Log`
    /// levels: 20 info, 40 error): state changes and faults.
    pub events: Vec<(f64, u8, String)>,
    /// What was read, and where the log is damaged if it is.
    pub read: ReadReport,
    /// The messages of the topics summarised here that did not decode.
    pub undecodable: drivelog::Undecodable,
}

/// Summarises a log.
///
/// # Errors
/// A description naming the file if it cannot be read, nothing in it is readable (not
/// MCAP), or it is in the JSON layout of earlier versions. A damaged log is not an error:
/// [`LogSummary::read`] says where the damage is.
pub fn summarize(path: &Path) -> Result<LogSummary, String> {
    let bytes = drivelog::read::read_log_file(path)
        .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    let mut s = LogSummary::default();
    let mut odom: Option<(u64, [f64; 3])> = None;
    let mut truth: Option<(u64, [f64; 3])> = None;
    let mut max_err = 0.0f64;
    let mut bus_bits = 0i64;
    let mut frames = 0u64;
    let mut last_ns = 0u64;
    let read = for_each_message(
        &bytes,
        |m| {
            *s.topics.entry(m.topic.to_string()).or_default() += 1;
            last_ns = last_ns.max(m.log_time);
            match m.topic {
                "/odom" | "/ground_truth/odom" => {
                    let Some(o) = s.undecodable.decode::<msg::Odometry>(m) else {
                        return;
                    };
                    let pose = o.pose.pose.to_planar();
                    if m.topic == "/odom" {
                        odom = Some((m.log_time, pose));
                    } else {
                        truth = Some((m.log_time, pose));
                    }
                    if let (Some((to, o)), Some((tt, g))) = (odom, truth)
                        && to == tt
                    {
                        max_err = max_err.max((o[0] - g[0]).hypot(o[1] - g[1]));
                    }
                }
                "/can/rx" | "/can/tx" => {
                    if let Some(f) = s.undecodable.frame(m) {
                        bus_bits += i64::from(frame_bits(&f));
                        frames += 1;
                    }
                }
                "/can/faults" => {
                    let Some(fault) = s.undecodable.decode::<msg::BusFault>(m) else {
                        return;
                    };
                    *s.fates.entry(fault.fate.clone()).or_default() += 1;
                    let Some(sent) = fault.frame.to_can() else {
                        return;
                    };
                    // A frame the firmware sent is on /can/tx as sent, dropped or not. One of
                    // the other nodes is on /can/rx as received, unless it was dropped.
                    if fault.sender == "controller" {
                        return;
                    }
                    if fault.fate == "dropped" {
                        bus_bits += i64::from(frame_bits(&sent));
                        frames += 1;
                    } else {
                        let received = msg::Frame {
                            data: fault.received,
                            ..fault.frame.clone()
                        };
                        if let Some(received) = received.to_can() {
                            // The bus timed the frame as sent: its stuff bits, not the
                            // corrupted data's.
                            bus_bits +=
                                i64::from(frame_bits(&sent)) - i64::from(frame_bits(&received));
                        }
                    }
                }
                "/rosout" => {
                    if let Some(l) = s.undecodable.decode::<msg::Log>(m) {
                        s.events.push((m.log_time as f64 * 1e-9, l.level, l.msg));
                    }
                }
                _ => {}
            }
        },
        |name, kv| {
            if name == drivelog::METADATA_NAME {
                s.scenario = kv.get("scenario").cloned();
            }
        },
    )
    .map_err(|e| format!("{}: not a readable MCAP file: {e}", path.display()))?;
    if crate::replay::is_old_layout(&read) {
        return Err(format!("{}: {}", path.display(), crate::replay::OLD_LAYOUT));
    }
    s.read = read;
    s.duration_s = last_ns as f64 * 1e-9;
    s.odometry = odom.map(|o| o.1);
    s.truth = truth.map(|t| t.1);
    if let (Some(o), Some(g)) = (s.odometry, s.truth) {
        s.drift = Some(((o[0] - g[0]).hypot(o[1] - g[1]), max_err));
    }
    if frames > 0 && last_ns > 0 {
        let faulty: u64 = s.fates.values().sum();
        s.fates
            .insert("delivered".to_string(), frames.saturating_sub(faulty));
        // 1 Mbit/s: one bit per microsecond.
        s.bus_load = Some(bus_bits.max(0) as f64 * 1000.0 / last_ns as f64);
    }
    Ok(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn garbage_is_refused_with_a_reason() {
        let e = for_each_message(b"definitely not mcap", |_| {}, |_, _| {}).unwrap_err();
        assert_eq!(e.offset, 0);
        assert!(e.to_string().contains("MCAP magic"), "{e}");
    }
}
