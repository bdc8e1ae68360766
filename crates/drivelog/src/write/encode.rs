//! The encoding: what the caller's thread records (an [`Event`] a message, in a [`Batch`])
//! and the writing thread's [`Encoder`], which turns them into CDR messages (`crate::msg`)
//! in the `mcap` writer and shows each to the tap.

use std::io;

use firmware::CanFrame;
use firmware::control::Snapshot;

use super::thread::Writer;
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

/// The writing thread's state: the file, the tap, and the messages of a snapshot, refilled
/// for each (their names and keys are the same from one to the next: 6,000 of each in the
/// 60 s square, which allocated some 300,000 strings when built anew).
pub(super) struct Encoder {
    pub(super) writer: Writer,
    pub(super) tap: Option<Box<dyn MessageTap>>,
    joints: msg::JointState,
    diagnostics: msg::DiagnosticArray,
}

impl Encoder {
    pub(super) fn new(writer: Writer) -> Self {
        Self {
            writer,
            tap: None,
            joints: msg::JointState::default(),
            diagnostics: msg::DiagnosticArray::default(),
        }
    }

    /// Encodes and writes `batch`'s messages, then ends the chunk and flushes the file
    /// (installing the tap that came with it first).
    pub(super) fn batch(&mut self, batch: &mut Batch) -> io::Result<()> {
        if let Some(tap) = batch.tap.take() {
            self.tap = Some(tap);
        }
        for event in &batch.events {
            self.event(batch, event)?;
        }
        self.writer.flush()?;
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
    ) -> io::Result<()> {
        self.write_with(channel, log_ns, publish_ns, |buf| msg::encode(buf, msg))
    }

    /// Writes the message that `encode` appends to the file's open chunk, and shows it to the
    /// tap.
    #[inline]
    fn write_with(
        &mut self,
        channel: Channel,
        log_ns: u64,
        publish_ns: u64,
        encode: impl FnOnce(&mut Vec<u8>),
    ) -> io::Result<()> {
        let cdr = self
            .writer
            .message(channel.id(), log_ns, publish_ns, encode)?;
        if let Some(tap) = self.tap.as_mut() {
            tap.message(channel, log_ns, publish_ns, cdr);
        }
        Ok(())
    }

    fn event(&mut self, batch: &Batch, event: &Event) -> io::Result<()> {
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
                self.write_with(channel, log_ns, publish_ns, |buf| {
                    msg::Frame::encode_can(buf, stamp_ns, &frame);
                })
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
                let mut joints = std::mem::take(&mut self.joints);
                joint_state(&mut joints, t_ns, s);
                let written = self.write(Channel::JointStates, t_ns, t_ns, &joints);
                self.joints = joints;
                written?;
                let mut m = std::mem::take(&mut self.diagnostics);
                diagnostics(&mut m, t_ns, s);
                if let Some(status) = self.tap.as_mut().and_then(|tap| tap.status()) {
                    m.status.push(status);
                }
                let written = self.write(Channel::Diagnostics, t_ns, t_ns, &m);
                m.status.truncate(1);
                self.diagnostics = m;
                written
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

/// `/joint_states` of a snapshot, in `m` (its names kept from the last one when the same).
/// A robot with tracking pods adds them after the wheels (`pod0`...), with a position only:
/// ROS allows `velocity` and `effort` shorter than `name`, and no speed or effort of a pod is
/// known to the core.
fn joint_state(m: &mut msg::JointState, t_ns: u64, s: &Snapshot) {
    let pods = usize::from(s.pods).min(POD_NAMES.len());
    let names = WHEEL_NAMES.iter().chain(&POD_NAMES[..pods]);
    if !m.name.iter().eq(names.clone()) {
        m.name = names.map(|n| (*n).to_string()).collect();
    }
    m.header.stamp = msg::Time::from_ns(t_ns);
    m.header.frame_id.clear();
    m.position.clear();
    m.position.extend(s.wheel_angles.map(f64::from));
    m.position
        .extend(s.pod_angles[..pods].iter().map(|&a| f64::from(a)));
    m.velocity.clear();
    m.velocity.extend(s.wheel_speeds.0.map(f64::from));
    m.effort.clear();
    m.effort.extend(s.currents.map(f64::from));
}

/// The name of the firmware's [`msg::DiagnosticStatus`].
pub const DIAGNOSTIC_NAME: &str = "mecanum_drive: firmware";

/// `/diagnostics` of a snapshot, in `m` (the last one's strings reused): one status, [`DIAGNOSTIC_NAME`] (and a tap's after it,
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
fn diagnostics(m: &mut msg::DiagnosticArray, t_ns: u64, s: &Snapshot) {
    use firmware::protocol::robot::{HeadingSource, OdometrySource, RobotState};
    use std::fmt::Write as _;
    let gyro_silent = s.heading_source == HeadingSource::WheelsGyroSilent;
    let pods_silent = s.odometry_source == OdometrySource::WheelsPodsSilent;
    m.header.stamp = msg::Time::from_ns(t_ns);
    m.header.frame_id.clear();
    m.status.truncate(1);
    if m.status.is_empty() {
        m.status.push(msg::DiagnosticStatus {
            name: DIAGNOSTIC_NAME.to_string(),
            ..msg::DiagnosticStatus::default()
        });
    }
    let status = &mut m.status[0];
    status.level = match s.state {
        RobotState::Fault => msg::DiagnosticStatus::ERROR,
        RobotState::Estop => msg::DiagnosticStatus::WARN,
        _ if gyro_silent || pods_silent => msg::DiagnosticStatus::WARN,
        _ => msg::DiagnosticStatus::OK,
    };
    let message = &mut status.message;
    message.clear();
    let _ = if s.fault == firmware::protocol::robot::Fault::None {
        write!(message, "{}", s.state)
    } else {
        write!(message, "{}, fault {}", s.state, s.fault)
    };
    if gyro_silent {
        message.push_str(", heading from the wheels: gyro silent");
    }
    if pods_silent {
        message.push_str(", odometry from the wheels: pods silent");
    }
    let mut kv = Values {
        values: &mut status.values,
        n: 0,
    };
    kv.set(("state", ""), s.state);
    kv.set(("fault", ""), s.fault);
    kv.set(
        ("motors_online", ""),
        format_args!("{:#06b}", s.motors_online),
    );
    kv.set(("steps", ""), s.steps);
    for (prefix, v) in [("commanded", &s.commanded), ("measured", &s.measured)] {
        kv.set((prefix, "_vx"), v.vx);
        kv.set((prefix, "_vy"), v.vy);
        kv.set((prefix, "_wz"), v.wz);
    }
    for (name, sp) in WHEEL_NAMES.iter().zip(s.wheel_setpoints.0) {
        kv.set(("setpoint_", name), sp);
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
        kv.set((key, ""), n);
    }
    if s.heading_source != HeadingSource::Wheels {
        kv.set(("heading_source", ""), s.heading_source);
        kv.set(("gyro_bias", ""), s.gyro_bias);
        kv.set(("gyro_bias_samples", ""), s.gyro_bias_samples);
    }
    if s.pods > 0 {
        kv.set(("odometry_source", ""), s.odometry_source);
        kv.set(("slip_vx", ""), s.slip.vx);
        kv.set(("slip_vy", ""), s.slip.vy);
        kv.set(("slip_wz", ""), s.slip.wz);
    }
    let n = kv.n;
    status.values.truncate(n);
}

/// A status's values, set in order over the last message's: a key that is the same keeps its
/// string, and the value is written into the old value's.
struct Values<'a> {
    values: &'a mut Vec<msg::KeyValue>,
    /// Values set so far.
    n: usize,
}

impl Values<'_> {
    /// Sets the next value: its key is `key.0` then `key.1`.
    fn set(&mut self, (a, b): (&str, &str), value: impl std::fmt::Display) {
        use std::fmt::Write as _;
        match self.values.get_mut(self.n) {
            Some(kv)
                if kv.key.len() == a.len() + b.len()
                    && kv.key.starts_with(a)
                    && kv.key.ends_with(b) =>
            {
                kv.value.clear();
                let _ = write!(kv.value, "{value}");
            }
            _ => {
                self.values.truncate(self.n);
                self.values.push(msg::KeyValue {
                    key: format!("{a}{b}"),
                    value: value.to_string(),
                });
            }
        }
        self.n += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_snapshot_refilled_over_another_is_the_one_built_anew() {
        use firmware::protocol::robot::{Fault, HeadingSource, OdometrySource, RobotState};
        let plain = firmware::Controller::new(&firmware::Config::dji_m3508_example())
            .unwrap()
            .snapshot();
        let gyro = Snapshot {
            heading_source: HeadingSource::WheelsGyroSilent,
            gyro_bias: 0.25,
            ..plain
        };
        let pods = Snapshot {
            pods: 3,
            pod_angles: [1.5, -2.0, 3.25],
            odometry_source: OdometrySource::WheelsPodsSilent,
            state: RobotState::Fault,
            fault: Fault::MotorStale,
            steps: 12_345,
            ..gyro
        };
        let two_pods = Snapshot { pods: 2, ..plain };
        let (mut joints, mut diag) = Default::default();
        // Keys and names appear, change and go, in both directions.
        for (i, s) in [plain, gyro, pods, two_pods, pods, plain]
            .iter()
            .enumerate()
        {
            let t = 1_000_000 * i as u64;
            joint_state(&mut joints, t, s);
            diagnostics(&mut diag, t, s);
            let (mut fresh_joints, mut fresh_diag) = Default::default();
            joint_state(&mut fresh_joints, t, s);
            diagnostics(&mut fresh_diag, t, s);
            assert_eq!(joints, fresh_joints, "{i}");
            assert_eq!(diag, fresh_diag, "{i}");
        }
        assert_eq!(joints.name, ["fl", "fr", "rl", "rr"]);
        assert!(!diag.status[0].values.iter().any(|kv| kv.key == "slip_vx"));
    }

    #[test]
    fn an_event_is_small() {
        // What the caller's thread writes per frame, instead of the encoded message.
        assert!(size_of::<Event>() <= 48, "{}", size_of::<Event>());
    }
}
