//! The encoding: what the caller's thread records (an [`Event`] a message, in a [`Batch`])
//! and the writing thread's [`Encoder`], which turns them into CDR messages (`crate::msg`)
//! in the `mcap` writer and shows each to the tap.

use std::io;

use firmware::CanFrame;
use firmware::control::Snapshot;
use mcap::records::MessageHeader;

use super::thread::{Writer, mcap_err};
use super::{Direction, MessageTap, OdometrySource};
use crate::msg::{self, Header, RosMsg};
use crate::{Channel, POD_NAMES, WHEEL_NAMES, frames};

/// A logged message, or the two of an odometry, as values: the writing thread encodes them.
#[derive(Clone, Copy)]
pub(super) enum Event {
    /// `/can/rx` or `/can/tx`.
    Frame {
        log_ns: u64,
        publish_ns: u64,
        stamp_ns: u64,
        frame: CanFrame,
        dir: Direction,
    },
    /// `/can/faults`: [`Batch::faults`]`[index]`.
    Fault { t_ns: u64, index: u32 },
    /// `/cmd_vel`.
    Twist { t_ns: u64, twist: [f32; 3] },
    /// `/joint_states` and `/diagnostics`: [`Batch::snapshots`]`[index]`.
    Snapshot { t_ns: u64, index: u32 },
    /// `/odom` or `/ground_truth/odom`, and `/tf`: [`Batch::odometry`]`[index]`.
    Odometry { t_ns: u64, index: u32 },
    /// `/rosout`: [`Batch::texts`]`[index]`.
    Text { t_ns: u64, level: u8, index: u32 },
    /// `/firmware/steps`.
    Step { t_ns: u64, kind: u8 },
    /// `/firmware/store`.
    Saved { t_ns: u64, result: msg::SaveResult },
    /// `/diagnostics` with the tap's status alone ([`McapLog::tap_status`]).
    TapStatus { t_ns: u64 },
}

/// A `/can/faults` message's values.
#[derive(Clone, Copy)]
pub(super) struct FaultRecord {
    pub(super) sender: &'static str,
    pub(super) fate: &'static str,
    pub(super) sent: CanFrame,
    pub(super) received: [u8; 8],
}

/// An odometry message's values.
#[derive(Clone, Copy)]
pub(super) struct OdometryRecord {
    pub(super) source: OdometrySource,
    pub(super) pose: [f64; 3],
    pub(super) twist: [f64; 3],
}

/// The messages logged between two hand-overs to the writing thread, in order. The larger
/// values are kept beside the events, so that an event stays small.
#[derive(Default)]
pub(super) struct Batch {
    pub(super) events: Vec<Event>,
    pub(super) faults: Vec<FaultRecord>,
    pub(super) snapshots: Vec<Snapshot>,
    pub(super) odometry: Vec<OdometryRecord>,
    pub(super) texts: Vec<String>,
    /// A tap for the writing thread to install before this batch's messages
    /// ([`McapLog::set_tap`]).
    pub(super) tap: Option<Box<dyn MessageTap>>,
}

impl Batch {
    pub(super) fn is_empty(&self) -> bool {
        self.events.is_empty()
    }

    pub(super) fn clear(&mut self) {
        self.events.clear();
        self.faults.clear();
        self.snapshots.clear();
        self.odometry.clear();
        self.texts.clear();
    }
}

/// The writing thread's state: the `mcap` writer, the encoding buffer and the tap.
pub(super) struct Encoder {
    pub(super) writer: Writer,
    pub(super) buf: Vec<u8>,
    pub(super) tap: Option<Box<dyn MessageTap>>,
}

impl Encoder {
    /// Encodes and writes `batch`'s messages, then ends the chunk and flushes the file
    /// (installing the tap that came with it first).
    pub(super) fn batch(&mut self, batch: &mut Batch) -> io::Result<()> {
        if let Some(tap) = batch.tap.take() {
            self.tap = Some(tap);
        }
        for event in &batch.events {
            self.event(batch, event).map_err(mcap_err)?;
        }
        self.writer.flush().map_err(mcap_err)?;
        if let Some(tap) = self.tap.as_mut() {
            tap.end_batch();
        }
        Ok(())
    }

    #[inline]
    pub(super) fn write<M: RosMsg>(
        &mut self,
        channel: Channel,
        log_ns: u64,
        publish_ns: u64,
        msg: &M,
    ) -> mcap::McapResult<()> {
        self.buf.clear();
        msg::encode(&mut self.buf, msg);
        let header = MessageHeader {
            channel_id: channel.id(),
            // Not numbered: the specification's "recorded as zero" for messages whose
            // publisher assigns no sequence. A global count costs 0.9 MB (8 %) of the 60 s
            // square's log, whose messages compress to about 20 bytes each.
            sequence: 0,
            log_time: log_ns,
            publish_time: publish_ns,
        };
        self.writer.write_to_known_channel(&header, &self.buf)?;
        if let Some(tap) = self.tap.as_mut() {
            tap.message(channel, log_ns, publish_ns, &self.buf);
        }
        Ok(())
    }

    fn event(&mut self, batch: &Batch, event: &Event) -> mcap::McapResult<()> {
        match *event {
            Event::Frame {
                log_ns,
                publish_ns,
                stamp_ns,
                frame,
                dir,
            } => {
                let channel = match dir {
                    Direction::Rx => Channel::CanRx,
                    Direction::Tx => Channel::CanTx,
                };
                let m = msg::Frame::from_can(stamp_ns, &frame);
                self.write(channel, log_ns, publish_ns, &m)
            }
            Event::Fault { t_ns, index } => {
                let f = &batch.faults[index as usize];
                let m = msg::BusFault {
                    header: Header::new(t_ns, ""),
                    sender: f.sender.to_string(),
                    fate: f.fate.to_string(),
                    frame: msg::Frame::from_can(t_ns, &f.sent),
                    received: f.received,
                };
                self.write(Channel::CanFaults, t_ns, t_ns, &m)
            }
            Event::Twist { t_ns, twist } => {
                let m = msg::TwistStamped {
                    header: Header::new(t_ns, frames::BASE_LINK),
                    twist: msg::Twist::planar(twist.map(f64::from)),
                };
                self.write(Channel::CmdVel, t_ns, t_ns, &m)
            }
            Event::Snapshot { t_ns, index } => {
                let s = &batch.snapshots[index as usize];
                self.write(Channel::JointStates, t_ns, t_ns, &joint_state(t_ns, s))?;
                let mut m = diagnostics(t_ns, s);
                if let Some(status) = self.tap.as_mut().and_then(|tap| tap.status()) {
                    m.status.push(status);
                }
                self.write(Channel::Diagnostics, t_ns, t_ns, &m)
            }
            Event::Odometry { t_ns, index } => {
                let o = batch.odometry[index as usize];
                let (channel, child) = match o.source {
                    OdometrySource::Firmware => (Channel::Odom, frames::BASE_LINK),
                    OdometrySource::GroundTruth => (Channel::GroundTruth, frames::BASE_LINK_TRUTH),
                };
                let header = Header::new(t_ns, frames::ODOM);
                let pose = msg::Pose::planar(o.pose);
                let m = msg::Odometry {
                    header: header.clone(),
                    child_frame_id: child.to_string(),
                    pose: msg::PoseWithCovariance {
                        pose,
                        covariance: [0.0; 36],
                    },
                    twist: msg::TwistWithCovariance {
                        twist: msg::Twist::planar(o.twist),
                        covariance: [0.0; 36],
                    },
                };
                self.write(channel, t_ns, t_ns, &m)?;
                let tf = msg::TfMessage {
                    transforms: vec![msg::TransformStamped {
                        header,
                        child_frame_id: child.to_string(),
                        transform: msg::Transform {
                            translation: msg::Vector3 {
                                x: pose.position.x,
                                y: pose.position.y,
                                z: 0.0,
                            },
                            rotation: pose.orientation,
                        },
                    }],
                };
                self.write(Channel::Tf, t_ns, t_ns, &tf)
            }
            Event::Text { t_ns, level, index } => {
                let m = msg::Log {
                    stamp: msg::Time::from_ns(t_ns),
                    level,
                    name: "firmware".to_string(),
                    msg: batch.texts[index as usize].clone(),
                    ..msg::Log::default()
                };
                self.write(Channel::Rosout, t_ns, t_ns, &m)
            }
            Event::Step { t_ns, kind } => {
                let m = msg::Step {
                    stamp: msg::Time::from_ns(t_ns),
                    kind,
                };
                self.write(Channel::Steps, t_ns, t_ns, &m)
            }
            Event::Saved { t_ns, result } => self.write(Channel::Store, t_ns, t_ns, &result),
            Event::TapStatus { t_ns } => {
                let m = msg::DiagnosticArray {
                    header: Header::new(t_ns, ""),
                    status: self
                        .tap
                        .as_mut()
                        .and_then(|tap| tap.status())
                        .into_iter()
                        .collect(),
                };
                self.write(Channel::Diagnostics, t_ns, t_ns, &m)
            }
        }
    }
}

/// `/joint_states` of a snapshot.
/// A robot with tracking pods adds them after the wheels (`pod0`...), with a position only:
/// ROS allows `velocity` and `effort` shorter than `name`, and no speed or effort of a pod is
/// known to the core.
fn joint_state(t_ns: u64, s: &Snapshot) -> msg::JointState {
    let pods = usize::from(s.pods).min(POD_NAMES.len());
    let mut name = WHEEL_NAMES.map(str::to_string).to_vec();
    name.extend(POD_NAMES[..pods].iter().map(|n| (*n).to_string()));
    let mut position = s.wheel_angles.map(f64::from).to_vec();
    position.extend(s.pod_angles[..pods].iter().map(|&a| f64::from(a)));
    msg::JointState {
        header: Header::new(t_ns, ""),
        name,
        position,
        velocity: s.wheel_speeds.0.map(f64::from).to_vec(),
        effort: s.currents.map(f64::from).to_vec(),
    }
}

/// The name of the firmware's [`msg::DiagnosticStatus`].
pub const DIAGNOSTIC_NAME: &str = "mecanum_drive: firmware";

/// `/diagnostics` of a snapshot: one status, [`DIAGNOSTIC_NAME`] (and a tap's after it,
/// [`MessageTap::status`]), whose values are named
/// `state`, `fault`, `motors_online` (a mask, wheel i at bit i), `steps`, `commanded_vx`...,
/// `measured_vx`..., `setpoint_fl`... (rad/s), one counter per rejected-frame kind
/// (`rx_unknown_id`, `rx_wrong_dlc`...) and `repeated_seq` (twists and gyro frames not used
/// because their `seq` repeated the last accepted one's). A robot configured for gyro heading
/// adds `heading_source` (`Gyro`, or `WheelsGyroSilent`: the gyro is silent and the wheels
/// give the heading, which makes the status a warning), `gyro_bias` (rad/s) and
/// `gyro_bias_samples`; without a gyro these keys are absent, as before they existed. A robot
/// with tracking pods adds `odometry_source` (`PODS2_GYRO`, `PODS3`, or `WHEELS_PODS_SILENT`, a
/// warning) and the slip estimate `slip_vx`, `slip_vy` (m/s), `slip_wz` (rad/s).
fn diagnostics(t_ns: u64, s: &Snapshot) -> msg::DiagnosticArray {
    use firmware::protocol::robot::{HeadingSource, OdometrySource, RobotState};
    let gyro_silent = s.heading_source == HeadingSource::WheelsGyroSilent;
    let pods_silent = s.odometry_source == OdometrySource::WheelsPodsSilent;
    let level = match s.state {
        RobotState::Fault => msg::DiagnosticStatus::ERROR,
        RobotState::Estop => msg::DiagnosticStatus::WARN,
        _ if gyro_silent || pods_silent => msg::DiagnosticStatus::WARN,
        _ => msg::DiagnosticStatus::OK,
    };
    let mut message = if s.fault == firmware::protocol::robot::Fault::None {
        s.state.to_string()
    } else {
        format!("{}, fault {}", s.state, s.fault)
    };
    if gyro_silent {
        message.push_str(", heading from the wheels: gyro silent");
    }
    if pods_silent {
        message.push_str(", odometry from the wheels: pods silent");
    }
    let mut values = Vec::with_capacity(24);
    let mut kv = |key: &str, value: String| {
        values.push(msg::KeyValue {
            key: key.to_string(),
            value,
        });
    };
    kv("state", s.state.to_string());
    kv("fault", s.fault.to_string());
    kv("motors_online", format!("{:#06b}", s.motors_online));
    kv("steps", s.steps.to_string());
    for (prefix, v) in [("commanded", &s.commanded), ("measured", &s.measured)] {
        kv(&format!("{prefix}_vx"), v.vx.to_string());
        kv(&format!("{prefix}_vy"), v.vy.to_string());
        kv(&format!("{prefix}_wz"), v.wz.to_string());
    }
    for (name, sp) in WHEEL_NAMES.iter().zip(s.wheel_setpoints.0) {
        kv(&format!("setpoint_{name}"), sp.to_string());
    }
    let e = &s.rx_errors;
    for (key, n) in [
        ("rx_unknown_id", e.unknown_id),
        ("rx_extended_id", e.extended_id),
        ("rx_remote", e.remote),
        ("rx_wrong_dlc", e.wrong_dlc),
        ("rx_non_finite", e.non_finite),
        ("rx_out_of_range", e.out_of_range),
        ("repeated_seq", s.repeated_seq),
    ] {
        kv(key, n.to_string());
    }
    if s.heading_source != HeadingSource::Wheels {
        kv("heading_source", s.heading_source.to_string());
        kv("gyro_bias", s.gyro_bias.to_string());
        kv("gyro_bias_samples", s.gyro_bias_samples.to_string());
    }
    if s.pods > 0 {
        kv("odometry_source", s.odometry_source.to_string());
        kv("slip_vx", s.slip.vx.to_string());
        kv("slip_vy", s.slip.vy.to_string());
        kv("slip_wz", s.slip.wz.to_string());
    }
    msg::DiagnosticArray {
        header: Header::new(t_ns, ""),
        status: vec![msg::DiagnosticStatus {
            level,
            name: DIAGNOSTIC_NAME.to_string(),
            message,
            hardware_id: String::new(),
            values,
        }],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_event_is_small() {
        // What the caller's thread writes per frame, instead of the encoded message.
        assert!(size_of::<Event>() <= 48, "{}", size_of::<Event>());
    }
}
