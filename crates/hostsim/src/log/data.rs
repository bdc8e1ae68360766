//! Message data of the channels other than `/can/*` (see [`json`](super::json) for those),
//! built by the writing thread from the values the simulation's thread recorded.

use std::fmt;
use std::io::Write;

use firmware::control::Snapshot;
use firmware::protocol::{dji, odrive};
use foxglove::Encode;
use foxglove::schemas::{FrameTransform, Log, PoseInFrame, Quaternion, Timestamp, Vector3};

/// Four numbers as a JSON array, formatted in place (no `String` per array).
struct JsonArray<'a>(&'a [f32; 4]);

impl fmt::Display for JsonArray<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let [a, b, c, d] = self.0;
        write!(f, "[{a},{b},{c},{d}]")
    }
}

/// `/firmware/snapshot`.
pub(super) fn snapshot(buf: &mut Vec<u8>, s: &Snapshot) {
    let _ = write!(
        buf,
        r#"{{"state":"{:?}","fault":"{:?}","commanded":{{"vx":{},"vy":{},"wz":{}}},"measured":{{"vx":{},"vy":{},"wz":{}}},"wheel_setpoints":{},"wheel_speeds":{},"currents":{},"motors_online":{},"rx_errors":{},"unknown_ids":{}}}"#,
        s.state,
        s.fault,
        s.commanded.vx,
        s.commanded.vy,
        s.commanded.wz,
        s.measured.vx,
        s.measured.vy,
        s.measured.wz,
        JsonArray(&s.wheel_setpoints.0),
        JsonArray(&s.wheel_speeds.0),
        JsonArray(&s.currents),
        s.motors_online,
        s.rx_errors.total() - s.rx_errors.unknown_id,
        s.rx_errors.unknown_id,
    );
}

/// `/motors/feedback` of a DJI drive.
pub(super) fn dji_feedback(buf: &mut Vec<u8>, f: &dji::Feedback) {
    let _ = write!(
        buf,
        r#"{{"protocol":"dji","id":{},"rotor_angle":{},"rotor_speed_rpm":{},"current_a":{},"temperature_c":{}}}"#,
        f.esc.get(),
        f.rotor_angle,
        f.rotor_speed_rpm,
        f.current_amps(),
        f.temperature_c
    );
}

/// `/motors/feedback` of an ODrive.
pub(super) fn odrive_feedback(buf: &mut Vec<u8>, a: &odrive::Addressed<odrive::Feedback>) {
    let id = a.node.get();
    let _ = match a.msg {
        odrive::Feedback::EncoderEstimates { pos, vel } => write!(
            buf,
            r#"{{"protocol":"odrive","id":{id},"pos_rev":{pos},"vel_rev_s":{vel}}}"#
        ),
        odrive::Feedback::Heartbeat(h) => write!(
            buf,
            r#"{{"protocol":"odrive","id":{id},"axis_error":{},"axis_state":"{:?}"}}"#,
            h.axis_error, h.axis_state
        ),
        odrive::Feedback::Error { active_errors, .. } => write!(
            buf,
            r#"{{"protocol":"odrive","id":{id},"axis_error":{active_errors}}}"#
        ),
    };
}

/// `/cmd/twist`.
pub(super) fn twist(buf: &mut Vec<u8>, twist: [f32; 3], streaming: bool) {
    let _ = write!(
        buf,
        r#"{{"vx":{},"vy":{},"wz":{},"streaming":{}}}"#,
        twist[0], twist[1], twist[2], streaming
    );
}

fn ns_stamp(t_ns: u64) -> Timestamp {
    Timestamp::new((t_ns / 1_000_000_000) as u32, (t_ns % 1_000_000_000) as u32)
}

fn yaw_quaternion(yaw: f64) -> Quaternion {
    let (s, c) = (yaw * 0.5).sin_cos();
    Quaternion {
        x: 0.0,
        y: 0.0,
        z: s,
        w: c,
    }
}

fn encode(buf: &mut Vec<u8>, msg: &impl Encode) {
    // Encoding into a Vec cannot run out of space.
    let _ = msg.encode(buf);
}

/// `/odom/pose` or `/ground_truth/pose`: `pose` `[x, y, yaw]` in `frame`.
pub(super) fn pose(buf: &mut Vec<u8>, t_ns: u64, frame: &str, pose: [f64; 3]) {
    let msg = PoseInFrame {
        timestamp: Some(ns_stamp(t_ns)),
        frame_id: frame.to_string(),
        pose: Some(foxglove::schemas::Pose {
            position: Some(Vector3 {
                x: pose[0],
                y: pose[1],
                z: 0.0,
            }),
            orientation: Some(yaw_quaternion(pose[2])),
        }),
    };
    encode(buf, &msg);
}

/// `/tf`: `world → child` at `pose` `[x, y, yaw]`.
pub(super) fn transform(buf: &mut Vec<u8>, t_ns: u64, child: &str, pose: [f64; 3]) {
    let tf = FrameTransform {
        timestamp: Some(ns_stamp(t_ns)),
        parent_frame_id: "world".to_string(),
        child_frame_id: child.to_string(),
        translation: Some(Vector3 {
            x: pose[0],
            y: pose[1],
            z: 0.0,
        }),
        rotation: Some(yaw_quaternion(pose[2])),
    };
    encode(buf, &tf);
}

/// `/firmware/log`.
pub(super) fn text(buf: &mut Vec<u8>, t_ns: u64, level: i32, message: &str) {
    let msg = Log {
        timestamp: Some(ns_stamp(t_ns)),
        level,
        message: message.to_string(),
        name: "firmware".to_string(),
        file: String::new(),
        line: 0,
    };
    encode(buf, &msg);
}
