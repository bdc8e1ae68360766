//! `geometry_msgs`, `nav_msgs` and `tf2_msgs`: poses, twists, transforms and odometry.

use serde::{Deserialize, Serialize};
use serde_big_array::BigArray;

use super::{HEADER, Header, MsgDef, RosMsg};

/// `geometry_msgs/msg/Vector3`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct Vector3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// Definition of [`Vector3`].
pub static VECTOR3: MsgDef = MsgDef {
    name: "geometry_msgs/msg/Vector3",
    text: "float64 x\nfloat64 y\nfloat64 z\n",
    deps: &[],
};
ros_msg!(Vector3, VECTOR3);

/// `geometry_msgs/msg/Point`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct Point {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// Definition of [`Point`].
pub static POINT: MsgDef = MsgDef {
    name: "geometry_msgs/msg/Point",
    text: "float64 x\nfloat64 y\nfloat64 z\n",
    deps: &[],
};
ros_msg!(Point, POINT);

/// `geometry_msgs/msg/Quaternion`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

impl Quaternion {
    /// A rotation by `yaw` about z.
    #[must_use]
    pub fn from_yaw(yaw: f64) -> Self {
        let (s, c) = (yaw * 0.5).sin_cos();
        Self {
            x: 0.0,
            y: 0.0,
            z: s,
            w: c,
        }
    }

    /// The rotation's yaw (about z), for a rotation about z.
    #[must_use]
    pub fn yaw(&self) -> f64 {
        2.0 * self.z.atan2(self.w)
    }
}

impl Default for Quaternion {
    fn default() -> Self {
        Self::from_yaw(0.0)
    }
}

/// Definition of [`Quaternion`].
pub static QUATERNION: MsgDef = MsgDef {
    name: "geometry_msgs/msg/Quaternion",
    text: "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    deps: &[],
};
ros_msg!(Quaternion, QUATERNION);

/// `geometry_msgs/msg/Pose`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct Pose {
    pub position: Point,
    pub orientation: Quaternion,
}

/// Definition of [`Pose`].
pub static POSE: MsgDef = MsgDef {
    name: "geometry_msgs/msg/Pose",
    text: "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
    deps: &[&POINT, &QUATERNION],
};
ros_msg!(Pose, POSE);

impl Pose {
    /// The planar pose `[x, y, yaw]`.
    #[must_use]
    pub fn planar(p: [f64; 3]) -> Self {
        Self {
            position: Point {
                x: p[0],
                y: p[1],
                z: 0.0,
            },
            orientation: Quaternion::from_yaw(p[2]),
        }
    }

    /// `[x, y, yaw]`.
    #[must_use]
    pub fn to_planar(&self) -> [f64; 3] {
        [self.position.x, self.position.y, self.orientation.yaw()]
    }
}

/// `geometry_msgs/msg/PoseStamped`: what an external tracker publishes.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct PoseStamped {
    pub header: Header,
    pub pose: Pose,
}

/// Definition of [`PoseStamped`].
pub static POSE_STAMPED: MsgDef = MsgDef {
    name: "geometry_msgs/msg/PoseStamped",
    text: "std_msgs/Header header\ngeometry_msgs/Pose pose\n",
    deps: &[&HEADER, &POSE],
};
ros_msg!(PoseStamped, POSE_STAMPED);

/// `geometry_msgs/msg/PoseWithCovariance`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovariance {
    /// The pose.
    pub pose: Pose,
    /// Row-major 6x6 covariance of (x, y, z, rot x, rot y, rot z).
    #[serde(with = "BigArray")]
    pub covariance: [f64; 36],
}

/// Definition of [`PoseWithCovariance`].
pub static POSE_WITH_COVARIANCE: MsgDef = MsgDef {
    name: "geometry_msgs/msg/PoseWithCovariance",
    text: "geometry_msgs/Pose pose\nfloat64[36] covariance\n",
    deps: &[&POSE],
};
ros_msg!(PoseWithCovariance, POSE_WITH_COVARIANCE);

/// `geometry_msgs/msg/Twist`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct Twist {
    pub linear: Vector3,
    pub angular: Vector3,
}

impl Twist {
    /// The planar twist `[vx, vy, wz]`.
    #[must_use]
    pub fn planar(t: [f64; 3]) -> Self {
        Self {
            linear: Vector3 {
                x: t[0],
                y: t[1],
                z: 0.0,
            },
            angular: Vector3 {
                x: 0.0,
                y: 0.0,
                z: t[2],
            },
        }
    }

    /// `[vx, vy, wz]`.
    #[must_use]
    pub fn to_planar(&self) -> [f64; 3] {
        [self.linear.x, self.linear.y, self.angular.z]
    }
}

/// Definition of [`Twist`].
pub static TWIST: MsgDef = MsgDef {
    name: "geometry_msgs/msg/Twist",
    text: "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular\n",
    deps: &[&VECTOR3],
};
ros_msg!(Twist, TWIST);

/// `geometry_msgs/msg/TwistStamped`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct TwistStamped {
    pub header: Header,
    pub twist: Twist,
}

/// Definition of [`TwistStamped`].
pub static TWIST_STAMPED: MsgDef = MsgDef {
    name: "geometry_msgs/msg/TwistStamped",
    text: "std_msgs/Header header\ngeometry_msgs/Twist twist\n",
    deps: &[&HEADER, &TWIST],
};
ros_msg!(TwistStamped, TWIST_STAMPED);

/// `geometry_msgs/msg/TwistWithCovariance`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TwistWithCovariance {
    /// The twist.
    pub twist: Twist,
    /// Row-major 6x6 covariance of (vx, vy, vz, wx, wy, wz).
    #[serde(with = "BigArray")]
    pub covariance: [f64; 36],
}

/// Definition of [`TwistWithCovariance`].
pub static TWIST_WITH_COVARIANCE: MsgDef = MsgDef {
    name: "geometry_msgs/msg/TwistWithCovariance",
    text: "geometry_msgs/Twist twist\nfloat64[36] covariance\n",
    deps: &[&TWIST],
};
ros_msg!(TwistWithCovariance, TWIST_WITH_COVARIANCE);

/// `geometry_msgs/msg/Transform`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct Transform {
    pub translation: Vector3,
    pub rotation: Quaternion,
}

/// Definition of [`Transform`].
pub static TRANSFORM: MsgDef = MsgDef {
    name: "geometry_msgs/msg/Transform",
    text: "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n",
    deps: &[&VECTOR3, &QUATERNION],
};
ros_msg!(Transform, TRANSFORM);

/// `geometry_msgs/msg/TransformStamped`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TransformStamped {
    /// `frame_id`: the parent frame.
    pub header: Header,
    /// The child frame.
    pub child_frame_id: String,
    /// The child's pose in the parent.
    pub transform: Transform,
}

/// Definition of [`TransformStamped`].
pub static TRANSFORM_STAMPED: MsgDef = MsgDef {
    name: "geometry_msgs/msg/TransformStamped",
    text: "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n",
    deps: &[&HEADER, &TRANSFORM],
};
ros_msg!(TransformStamped, TRANSFORM_STAMPED);

/// `nav_msgs/msg/Odometry`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Odometry {
    /// `frame_id`: the frame of the pose (`odom`).
    pub header: Header,
    /// The frame of the twist (`base_link`).
    pub child_frame_id: String,
    /// Pose in `header.frame_id`.
    pub pose: PoseWithCovariance,
    /// Twist in `child_frame_id`.
    pub twist: TwistWithCovariance,
}

/// Definition of [`Odometry`].
pub static ODOMETRY: MsgDef = MsgDef {
    name: "nav_msgs/msg/Odometry",
    text: "std_msgs/Header header\nstring child_frame_id\n\
           geometry_msgs/PoseWithCovariance pose\ngeometry_msgs/TwistWithCovariance twist\n",
    deps: &[&HEADER, &POSE_WITH_COVARIANCE, &TWIST_WITH_COVARIANCE],
};
ros_msg!(Odometry, ODOMETRY);

/// `tf2_msgs/msg/TFMessage`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct TfMessage {
    pub transforms: Vec<TransformStamped>,
}

/// Definition of [`TfMessage`].
pub static TF_MESSAGE: MsgDef = MsgDef {
    name: "tf2_msgs/msg/TFMessage",
    text: "geometry_msgs/TransformStamped[] transforms\n",
    deps: &[&TRANSFORM_STAMPED],
};
ros_msg!(TfMessage, TF_MESSAGE);
