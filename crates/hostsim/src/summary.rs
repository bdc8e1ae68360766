//! `hostsim summary`: what a log says about a run — odometry drift against ground truth, bus
//! load, firmware state changes and faults — computed from the log alone.
//!
//! Reading goes through [`for_each_message`], which takes every complete, intact chunk and
//! stops at the first damaged record, so a log cut short by a killed run (or corrupted) is
//! summarised up to its last complete chunk, and [`LogSummary::read`] says where the damage
//! is, with its byte offset.

use std::collections::BTreeMap;
use std::path::Path;

use foxglove::Decode;
use foxglove::schemas::{Log, PoseInFrame};

use crate::bus::frame_bits;
use crate::log::{ReadReport, for_each_message};
use crate::replay::FrameJson;

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
    /// Bus load from `/can/bus` (bits at 1 Mbit/s over the duration), 0..1.
    pub bus_load: Option<f64>,
    /// Frames on the bus by fate.
    pub fates: BTreeMap<String, u64>,
    /// Firmware log lines `(time s, level, text)`: state changes and faults.
    pub events: Vec<(f64, i32, String)>,
    /// What was read, and where the log is damaged if it is.
    pub read: ReadReport,
}

fn yaw(q: &foxglove::schemas::Quaternion) -> f64 {
    2.0 * q.z.atan2(q.w)
}

fn pose_of(p: &PoseInFrame) -> Option<[f64; 3]> {
    let pose = p.pose.as_ref()?;
    let pos = pose.position.as_ref()?;
    Some([pos.x, pos.y, yaw(pose.orientation.as_ref()?)])
}

/// Summarises a hostsim MCAP log.
///
/// # Errors
/// A description naming the file if it cannot be read or nothing in it is readable (not
/// MCAP). A damaged log is not an error: [`LogSummary::read`] says where the damage is.
pub fn summarize(path: &Path) -> Result<LogSummary, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    let mut s = LogSummary::default();
    let mut odom: Option<(u64, [f64; 3])> = None;
    let mut truth: Option<(u64, [f64; 3])> = None;
    let mut max_err = 0.0f64;
    let mut bus_bits = 0u64;
    let mut last_ns = 0u64;
    let read = for_each_message(
        &bytes,
        |topic, t, data| {
            *s.topics.entry(topic.to_string()).or_default() += 1;
            last_ns = last_ns.max(t);
            match topic {
                "/odom/pose" | "/ground_truth/pose" => {
                    let Ok(p) = PoseInFrame::decode(data) else {
                        return;
                    };
                    let Some(pose) = pose_of(&p) else { return };
                    if topic == "/odom/pose" {
                        odom = Some((t, pose));
                    } else {
                        truth = Some((t, pose));
                    }
                    if let (Some((to, o)), Some((tt, g))) = (odom, truth)
                        && to == tt
                    {
                        max_err = max_err.max((o[0] - g[0]).hypot(o[1] - g[1]));
                    }
                }
                "/can/bus" => {
                    let parsed = FrameJson::parse(data);
                    if let Some(frame) = parsed.as_ref().and_then(FrameJson::frame) {
                        bus_bits += u64::from(frame_bits(&frame));
                    }
                    let fate = parsed.as_ref().and_then(|p| p.fate.as_deref());
                    *s.fates
                        .entry(fate.unwrap_or("unknown").to_string())
                        .or_default() += 1;
                }
                "/firmware/log" => {
                    if let Ok(l) = Log::decode(data) {
                        s.events.push((t as f64 * 1e-9, l.level, l.message));
                    }
                }
                _ => {}
            }
        },
        |name, kv| {
            if name == "hostsim" {
                s.scenario = kv.get("scenario").cloned();
            }
        },
    )
    .map_err(|e| format!("{}: not a readable MCAP file: {e}", path.display()))?;
    s.read = read;
    s.duration_s = last_ns as f64 * 1e-9;
    s.odometry = odom.map(|o| o.1);
    s.truth = truth.map(|t| t.1);
    if let (Some(o), Some(g)) = (s.odometry, s.truth) {
        s.drift = Some(((o[0] - g[0]).hypot(o[1] - g[1]), max_err));
    }
    if s.topics.contains_key("/can/bus") && last_ns > 0 {
        // 1 Mbit/s: one bit per microsecond.
        s.bus_load = Some(bus_bits as f64 * 1000.0 / last_ns as f64);
    }
    Ok(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn garbage_is_refused_with_a_reason() {
        let e = for_each_message(b"definitely not mcap", |_, _, _| {}, |_, _| {}).unwrap_err();
        assert_eq!(e.offset, 0);
        assert!(e.to_string().contains("MCAP magic"), "{e}");
    }
}
