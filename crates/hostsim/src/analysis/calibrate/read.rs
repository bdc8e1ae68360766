//! What calibration reads from a log: the configuration (metadata), the wheel and pod
//! angles (`/joint_states`), the logged odometry (`/odom`) and the reference poses.

use std::collections::BTreeMap;

use firmware::config::PODS_MAX;
use kinematics::Pose2;

use super::CalibrateError;
use drivelog::msg::{self, decode};
use drivelog::{Message, ReadReport, for_each_message};

/// A pose track: log time (ns) and pose, in time order.
pub(super) type Track = Vec<(u64, Pose2<f64>)>;

/// One `/joint_states` sample: its log time, the wheel angles and the pods' (rad).
#[derive(Debug, Clone, Copy)]
pub(super) struct Joints {
    pub t: u64,
    pub wheels: [f64; 4],
    pub pods: [Option<f64>; PODS_MAX],
}

/// What a log holds for calibration.
#[derive(Default)]
pub(super) struct LogData {
    pub config: Option<String>,
    pub joints: Vec<Joints>,
    pub odom: Track,
    pub reference: Track,
    pub reference_type: Option<String>,
    /// Topic -> schema of every channel with a pose type.
    pub pose_topics: BTreeMap<String, String>,
    error: Option<CalibrateError>,
}

/// Reads `bytes` (an MCAP log) for calibration against the poses on `reference`.
///
/// # Errors
/// [`CalibrateError::Read`] for a log that cannot be read (or of the old layout), else the
/// first message that could not be decoded or a reference that is not a pose.
pub(super) fn read_log(
    bytes: &[u8],
    reference: &str,
) -> Result<(LogData, ReadReport), CalibrateError> {
    let mut d = LogData::default();
    let mut config = None;
    let read = for_each_message(
        bytes,
        |m| d.take(m, reference),
        |name, kv| {
            if name == drivelog::METADATA_NAME {
                config = kv.get("config").cloned();
            }
        },
    )
    .map_err(|e| CalibrateError::Read(format!("not a readable MCAP file: {e}")))?;
    d.config = config;
    if crate::replay::is_old_layout(&read) {
        return Err(CalibrateError::Read(crate::replay::OLD_LAYOUT.to_string()));
    }
    if let Some(e) = d.error.take() {
        return Err(e);
    }
    Ok((d, read))
}

impl LogData {
    /// Takes what calibration needs from one message; after an error, nothing.
    fn take(&mut self, m: &Message<'_>, reference: &str) {
        if self.error.is_some() {
            return;
        }
        let is_pose = matches!(
            m.schema,
            "nav_msgs/msg/Odometry" | "geometry_msgs/msg/PoseStamped"
        );
        if is_pose && !self.pose_topics.contains_key(m.topic) {
            self.pose_topics
                .insert(m.topic.to_string(), m.schema.to_string());
        }
        if m.topic == reference && !self.take_reference(m, reference) {
            return;
        }
        // The reference may be /odom itself; it is then also the odometry below.
        match m.topic {
            "/joint_states" => self.take_joints(m),
            "/odom" => match decode::<msg::Odometry>(m.data) {
                Ok(o) => {
                    let [x, y, yaw] = o.pose.pose.to_planar();
                    self.odom.push((m.log_time, Pose2::new(x, y, yaw)));
                }
                Err(e) => self.fail(m, e.to_string()),
            },
            _ => {}
        }
    }

    /// A pose on the reference topic (an odometry or a stamped pose); `false` if the topic's
    /// type is not a pose (the message is then not read further).
    fn take_reference(&mut self, m: &Message<'_>, reference: &str) -> bool {
        self.reference_type = Some(m.schema.to_string());
        let pose = match m.schema {
            "nav_msgs/msg/Odometry" => {
                decode::<msg::Odometry>(m.data).map(|o| o.pose.pose.to_planar())
            }
            "geometry_msgs/msg/PoseStamped" => {
                decode::<msg::PoseStamped>(m.data).map(|p| p.pose.to_planar())
            }
            other => {
                self.error = Some(CalibrateError::ReferenceType {
                    topic: reference.to_string(),
                    schema: other.to_string(),
                });
                return false;
            }
        };
        match pose {
            Ok([x, y, yaw]) => self.reference.push((m.log_time, Pose2::new(x, y, yaw))),
            Err(e) => self.fail(m, e.to_string()),
        }
        true
    }

    /// A `/joint_states` sample with all four wheels' angles (and the pods' it has).
    fn take_joints(&mut self, m: &Message<'_>) {
        let j = match decode::<msg::JointState>(m.data) {
            Ok(j) => j,
            Err(e) => return self.fail(m, e.to_string()),
        };
        let angle = |name: &str| {
            let i = j.name.iter().position(|n| n == name)?;
            j.position.get(i).copied()
        };
        let [fl, fr, rl, rr] = drivelog::WHEEL_NAMES.map(angle);
        if let (Some(fl), Some(fr), Some(rl), Some(rr)) = (fl, fr, rl, rr) {
            self.joints.push(Joints {
                t: m.log_time,
                wheels: [fl, fr, rl, rr],
                pods: drivelog::POD_NAMES.map(angle),
            });
        }
    }

    /// `m` could not be decoded: the error the read ends with.
    fn fail(&mut self, m: &Message<'_>, reason: String) {
        self.error = Some(CalibrateError::Decode {
            topic: m.topic.to_string(),
            t_s: m.log_time as f64 * 1e-9,
            reason,
        });
    }
}
