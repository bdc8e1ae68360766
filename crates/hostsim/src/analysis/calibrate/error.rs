//! Why a log cannot be calibrated: [`CalibrateError`], and the [`MissingMotion`] it names
//! when the log lacks the motion a value needs.

use std::fmt;

use serde::Serialize;

use super::pods;

/// A motion the log lacks, for a value it then cannot determine.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MissingMotion {
    /// What is missing (`forward travel`, `strafe`, `rotation`). For a pod, the body motion
    /// that gives the travel along or across its direction: the nearer body axis.
    pub motion: &'static str,
    /// How much of it the log has (m, or rad for rotation). For a pod, the reference's
    /// travel along (`radius`) or across (`direction_deg`) the pod's configured direction.
    pub have: f64,
    /// How much it needs.
    pub need: f64,
    /// The value it cannot fit (a pod's: `radius`, `direction_deg`, `lever`).
    pub value: &'static str,
    /// The pod (its index in the configuration), for a pod's value.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pod: Option<usize>,
}

impl fmt::Display for MissingMotion {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if let Some(pod) = self.pod {
            return pods::describe(self, pod, f);
        }
        match self.motion {
            "rotation" => write!(
                f,
                "no rotation in this log ({:.1}° of turning at a steady speed, needs >= {:.0}°): \
                 cannot fit {}; spin on the spot both ways",
                self.have.to_degrees(),
                self.need.to_degrees(),
                self.value
            ),
            "strafe" => write!(
                f,
                "no strafe in this log ({:.2} m of lateral travel at a steady speed, needs >= \
                 {:.1} m): cannot fit {}; drive sideways both ways",
                self.have, self.need, self.value
            ),
            _ => write!(
                f,
                "no forward travel in this log ({:.2} m at a steady speed, needs >= {:.1} m): \
                 cannot fit {}; drive forward and back",
                self.have, self.need, self.value
            ),
        }
    }
}

/// Why a log could not be calibrated. Each names what is missing or wrong.
#[derive(Debug, thiserror::Error)]
pub enum CalibrateError {
    /// The file could not be read, or is not MCAP.
    #[error("{0}")]
    Read(String),
    /// No configuration in the metadata.
    #[error(
        "the log has no drive configuration (metadata `mecanum_drive`, key `config`): the \
         odometry's model is unknown"
    )]
    NoConfig,
    /// The logged configuration does not load.
    #[error("the log's configuration: {0}")]
    Config(String),
    /// A general wheel layout: no lx + ly to fit.
    #[error(
        "the log's configuration has geometry.layout = \"general\": calibration fits the \
         standard layout's wheel_radius and lx + ly"
    )]
    GeneralLayout,
    /// No message on the reference topic.
    #[error(
        "no reference poses: the log has no topic {topic:?} (pose topics in it: {available}); \
         name one with --reference",
        available = if available.is_empty() { "none".to_string() } else { available.join(", ") }
    )]
    NoReference {
        /// The topic asked for.
        topic: String,
        /// The log's topics of a pose type.
        available: Vec<String>,
    },
    /// The reference topic's type is not a pose.
    #[error(
        "reference {topic:?} is a {schema}, not a pose: use a geometry_msgs/msg/PoseStamped or \
         nav_msgs/msg/Odometry topic"
    )]
    ReferenceType {
        /// The topic.
        topic: String,
        /// Its type.
        schema: String,
    },
    /// A message could not be decoded.
    #[error("{topic} at {t_s:.3} s: {reason}")]
    Decode {
        /// The topic.
        topic: String,
        /// Its log time, s.
        t_s: f64,
        /// The decoder's error.
        reason: String,
    },
    /// The configuration has tracking pods, the log's `/joint_states` not their angles.
    #[error(
        "the log's configuration has {pods} tracking pods, but its /joint_states carry no \
         angle of pod{missing} (joints pod0, pod1...): the pods cannot be fitted"
    )]
    NoPodAngles {
        /// Pods configured.
        pods: usize,
        /// The first pod without angles.
        missing: usize,
    },
    /// No odometry: neither wheel angles nor `/odom`.
    #[error("the log has no /joint_states with the wheels fl, fr, rl, rr and no /odom")]
    NoOdometry,
    /// The odometry and the reference do not overlap in time.
    #[error(
        "the reference {topic} and the odometry overlap in {windows} windows of {window_s} s \
         (log times: odometry {odometry}, reference {reference}): nothing to fit"
    )]
    NoOverlap {
        /// The reference topic.
        topic: String,
        /// Windows found.
        windows: usize,
        /// Window length.
        window_s: f64,
        /// The odometry's time span.
        odometry: String,
        /// The reference's time span.
        reference: String,
    },
    /// The log's motion cannot determine one or more values.
    #[error(
        "{}; as the built-in `calibration` scenario does (hostsim run calibration)",
        .0.iter().map(ToString::to_string).collect::<Vec<_>>().join("; ")
    )]
    MissingMotion(Vec<MissingMotion>),
    /// The reference moves against the odometry along an axis: another body frame.
    #[error(
        "the reference moves against the odometry along {axis} (correction {correction:.3}): \
         is its body frame the robot's (x forward, y left, yaw counter-clockwise)?"
    )]
    Opposed {
        /// The axis.
        axis: &'static str,
        /// The fitted correction.
        correction: f64,
    },
    /// The fitted configuration is refused by the firmware's validation.
    #[error("the fitted configuration is not valid: {0}")]
    Refused(String),
    /// `window_s` out of range.
    #[error("--window = {0}: expected a window in [0.01, 10] s")]
    Window(f64),
}
