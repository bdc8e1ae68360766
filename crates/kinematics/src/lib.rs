#![doc = include_str!("../README.md")]
#![no_std]
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod encoder;
pub mod error;
pub mod kinematics;
pub mod odometry;
pub mod pods;
pub mod real;
pub mod types;

pub use encoder::{Encoder, EncoderConfig};
pub use error::{Axis, EncoderError, GeometryError, PodLayoutError};
pub use kinematics::{Effectiveness, MAX_EFFECTIVENESS, MecanumKinematics, WheelGeometry};
pub use odometry::Odometry;
pub use pods::{PodGeometry, PodLocalizer, ThreePodLocalizer, TwoPodLocalizer};
pub use real::{Real, wrap_angle};
pub use types::{ChassisVelocity, Pose2, Twist2, WheelDeltas, WheelSpeeds};
