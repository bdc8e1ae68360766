//! Message data of the channels other than `/can/*` (see [`json`](super::json) for those),
//! built by the writing thread from the values the simulation's thread recorded. The JSON is
//! the text `write!` gave (numbers as `Display` writes them), without `core::fmt` for the
//! numbers.

use std::io::Write;

use firmware::control::Snapshot;
use firmware::protocol::{dji, odrive};
use foxglove::Encode;
use foxglove::schemas::{FrameTransform, Log, PoseInFrame, Quaternion, Timestamp, Vector3};

use super::json::{push_f32, push_i64, push_u64};

/// Appends `[a,b,c,d]`.
fn push_array(buf: &mut Vec<u8>, values: &[f32; 4]) {
    let mut sep = b'[';
    for &v in values {
        buf.push(sep);
        push_f32(buf, v);
        sep = b',';
    }
    buf.push(b']');
}

/// `/firmware/snapshot`.
pub(super) fn snapshot(buf: &mut Vec<u8>, s: &Snapshot) {
    let _ = write!(buf, r#"{{"state":"{:?}","fault":"{:?}""#, s.state, s.fault);
    for (name, v) in [("commanded", &s.commanded), ("measured", &s.measured)] {
        buf.extend_from_slice(b",\"");
        buf.extend_from_slice(name.as_bytes());
        buf.extend_from_slice(br#"":{"vx":"#);
        push_f32(buf, v.vx);
        buf.extend_from_slice(br#","vy":"#);
        push_f32(buf, v.vy);
        buf.extend_from_slice(br#","wz":"#);
        push_f32(buf, v.wz);
        buf.push(b'}');
    }
    buf.extend_from_slice(br#","wheel_setpoints":"#);
    push_array(buf, &s.wheel_setpoints.0);
    buf.extend_from_slice(br#","wheel_speeds":"#);
    push_array(buf, &s.wheel_speeds.0);
    buf.extend_from_slice(br#","currents":"#);
    push_array(buf, &s.currents);
    buf.extend_from_slice(br#","motors_online":"#);
    push_u64(buf, u64::from(s.motors_online));
    buf.extend_from_slice(br#","rx_errors":"#);
    push_u64(buf, u64::from(s.rx_errors.total() - s.rx_errors.unknown_id));
    buf.extend_from_slice(br#","unknown_ids":"#);
    push_u64(buf, u64::from(s.rx_errors.unknown_id));
    buf.push(b'}');
}

/// `/motors/feedback` of a DJI drive.
pub(super) fn dji_feedback(buf: &mut Vec<u8>, f: &dji::Feedback) {
    buf.extend_from_slice(br#"{"protocol":"dji","id":"#);
    push_u64(buf, u64::from(f.esc.get()));
    buf.extend_from_slice(br#","rotor_angle":"#);
    push_u64(buf, u64::from(f.rotor_angle));
    buf.extend_from_slice(br#","rotor_speed_rpm":"#);
    push_i64(buf, i64::from(f.rotor_speed_rpm));
    buf.extend_from_slice(br#","current_a":"#);
    push_f32(buf, f.current_amps());
    buf.extend_from_slice(br#","temperature_c":"#);
    push_u64(buf, u64::from(f.temperature_c));
    buf.push(b'}');
}

/// `/motors/feedback` of an ODrive.
pub(super) fn odrive_feedback(buf: &mut Vec<u8>, a: &odrive::Addressed<odrive::Feedback>) {
    buf.extend_from_slice(br#"{"protocol":"odrive","id":"#);
    push_u64(buf, u64::from(a.node.get()));
    match a.msg {
        odrive::Feedback::EncoderEstimates { pos, vel } => {
            buf.extend_from_slice(br#","pos_rev":"#);
            push_f32(buf, pos);
            buf.extend_from_slice(br#","vel_rev_s":"#);
            push_f32(buf, vel);
        }
        odrive::Feedback::Heartbeat(h) => {
            buf.extend_from_slice(br#","axis_error":"#);
            push_u64(buf, u64::from(h.axis_error));
            let _ = write!(buf, r#","axis_state":"{:?}""#, h.axis_state);
        }
        odrive::Feedback::Error { active_errors, .. } => {
            buf.extend_from_slice(br#","axis_error":"#);
            push_u64(buf, u64::from(active_errors));
        }
    }
    buf.push(b'}');
}

/// `/cmd/twist`.
pub(super) fn twist(buf: &mut Vec<u8>, twist: [f32; 3], streaming: bool) {
    buf.extend_from_slice(br#"{"vx":"#);
    push_f32(buf, twist[0]);
    buf.extend_from_slice(br#","vy":"#);
    push_f32(buf, twist[1]);
    buf.extend_from_slice(br#","wz":"#);
    push_f32(buf, twist[2]);
    buf.extend_from_slice(if streaming {
        br#","streaming":true}"#
    } else {
        br#","streaming":false}"#
    });
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
