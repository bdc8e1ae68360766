//! ROS 2 message types of the logs, their `.msg` schemas, and their CDR encoding.
//!
//! Each type is a struct whose fields are the message's fields in the `.msg` order, with
//! serde deriving the encoding: `cdr-encoding` writes a struct's fields in order, aligned to
//! their size from the start of the payload, strings as a `u32` length (NUL included), the
//! bytes and a NUL, sequences as a `u32` count and the elements, fixed arrays as the elements
//! alone. So each struct *is* the layout, written once; [`encode`] and [`decode`] are the only
//! encoder and decoder. The `.msg` texts ([`MsgDef`]) are the standard definitions (comments
//! left out), for the Schema records: a reader that knows none of these types (Foxglove,
//! `rosbags`) builds its decoder from them.
//!
//! Every standard type here is the one in ROS 2 (Humble and later): `builtin_interfaces`,
//! `std_msgs`, `geometry_msgs`, `nav_msgs`, `sensor_msgs`, `tf2_msgs`, `diagnostic_msgs`,
//! `rcl_interfaces`, and `can_msgs/msg/Frame` as ros2_socketcan uses it. One type is the
//! project's own: [`BusFault`], for the frames the simulated bus's fault injector dropped or
//! corrupted, which no standard type describes.

use serde::{Deserialize, Serialize};
use serde_big_array::BigArray;

/// The CDR encapsulation header of every message: CDR, little-endian, no options.
pub const CDR_LE_HEADER: [u8; 4] = [0x00, 0x01, 0x00, 0x00];

/// Why a message could not be decoded.
#[derive(Debug, thiserror::Error)]
pub enum DecodeError {
    /// Shorter than the encapsulation header, or another encapsulation than CDR
    /// little-endian (the only one this project writes).
    #[error("not a little-endian CDR message (encapsulation header {header:02x?})")]
    Encapsulation {
        /// The first bytes (up to 4).
        header: Vec<u8>,
    },
    /// The payload does not match the type.
    #[error("bad CDR payload for {type_name}: {reason}")]
    Payload {
        /// The ROS 2 type name.
        type_name: &'static str,
        /// The decoder's error.
        reason: String,
    },
}

/// A ROS 2 message type: its name and `.msg` text.
pub trait RosMsg: Serialize + for<'de> Deserialize<'de> {
    /// Its definition.
    const DEF: &'static MsgDef;
}

/// A message definition: the type name (`pkg/msg/Name`), its `.msg` text, and the types its
/// fields use (for the Schema record's dependency sections).
#[derive(Debug)]
pub struct MsgDef {
    /// `pkg/msg/Name`.
    pub name: &'static str,
    /// The `.msg` text, fields with fully qualified types (`pkg/Name`).
    pub text: &'static str,
    /// The types its fields use, directly.
    pub deps: &'static [&'static MsgDef],
}

impl MsgDef {
    /// The Schema record's data (encoding `ros2msg`), as rosbag2 writes it: the type's text,
    /// then every type it uses, directly or not, each once, after a line of 80 `=` and a
    /// `MSG: pkg/Name` line.
    #[must_use]
    pub fn schema_text(&self) -> String {
        let mut out = self.text.to_string();
        let mut seen: Vec<&str> = vec![self.name];
        let mut stack: Vec<&MsgDef> = self.deps.iter().rev().copied().collect();
        while let Some(def) = stack.pop() {
            if seen.contains(&def.name) {
                continue;
            }
            seen.push(def.name);
            out.push_str(&"=".repeat(80));
            out.push_str("\nMSG: ");
            out.push_str(&def.name.replace("/msg/", "/"));
            out.push('\n');
            out.push_str(def.text);
            stack.extend(def.deps.iter().rev().copied());
        }
        out
    }
}

/// Appends `msg` to `out`: the encapsulation header, then its CDR payload.
pub fn encode<M: RosMsg>(out: &mut Vec<u8>, msg: &M) {
    out.extend_from_slice(&CDR_LE_HEADER);
    // The payload aligns from its own start, after the header: a serializer of its own that
    // counts from zero. Writing into a Vec cannot fail, and every type here is serializable.
    let written = cdr_encoding::to_writer::<_, byteorder::LittleEndian, _>(&mut *out, msg);
    debug_assert!(written.is_ok(), "{written:?}");
}

/// Decodes a message of type `M` from a message's data (header and payload).
///
/// # Errors
/// [`DecodeError`] if it is not little-endian CDR or does not fit `M`.
pub fn decode<M: RosMsg>(data: &[u8]) -> Result<M, DecodeError> {
    match data.get(..4) {
        Some(h) if h == CDR_LE_HEADER => {}
        _ => {
            return Err(DecodeError::Encapsulation {
                header: data[..data.len().min(4)].to_vec(),
            });
        }
    }
    cdr_encoding::from_bytes::<M, byteorder::LittleEndian>(&data[4..])
        .map(|(m, _)| m)
        .map_err(|e| DecodeError::Payload {
            type_name: M::DEF.name,
            reason: e.to_string(),
        })
}

macro_rules! ros_msg {
    ($ty:ty, $def:ident) => {
        impl RosMsg for $ty {
            const DEF: &'static MsgDef = &$def;
        }
    };
}

// ---- builtin_interfaces, std_msgs ----

/// `builtin_interfaces/msg/Time`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Time {
    /// Seconds.
    pub sec: i32,
    /// Nanoseconds, `0..1e9`.
    pub nanosec: u32,
}

impl Time {
    /// The time `t_ns` nanoseconds after the epoch (log time 0 in a simulated run). Times past
    /// 2^31 s saturate.
    #[must_use]
    pub fn from_ns(t_ns: u64) -> Self {
        Self {
            sec: i32::try_from(t_ns / 1_000_000_000).unwrap_or(i32::MAX),
            nanosec: (t_ns % 1_000_000_000) as u32,
        }
    }

    /// Nanoseconds since the epoch; negative times are 0.
    #[must_use]
    pub fn to_ns(self) -> u64 {
        u64::try_from(self.sec).unwrap_or(0) * 1_000_000_000 + u64::from(self.nanosec)
    }
}

/// Definition of [`Time`].
pub static TIME: MsgDef = MsgDef {
    name: "builtin_interfaces/msg/Time",
    text: "int32 sec\nuint32 nanosec\n",
    deps: &[],
};
ros_msg!(Time, TIME);

/// `std_msgs/msg/Header`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Header {
    /// When the data was taken.
    pub stamp: Time,
    /// The frame the data is in.
    pub frame_id: String,
}

impl Header {
    /// A header at `t_ns` in `frame_id`.
    #[must_use]
    pub fn new(t_ns: u64, frame_id: &str) -> Self {
        Self {
            stamp: Time::from_ns(t_ns),
            frame_id: frame_id.to_string(),
        }
    }
}

/// Definition of [`Header`].
pub static HEADER: MsgDef = MsgDef {
    name: "std_msgs/msg/Header",
    text: "builtin_interfaces/Time stamp\nstring frame_id\n",
    deps: &[&TIME],
};
ros_msg!(Header, HEADER);

// ---- can_msgs ----

/// `can_msgs/msg/Frame`, the type of ros2_socketcan.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Frame {
    /// `stamp`: when the frame completed on the wire; `frame_id`: empty.
    pub header: Header,
    /// Arbitration id (11 or 29 bits).
    pub id: u32,
    /// Remote frame: no data, `dlc` is the requested length.
    pub is_rtr: bool,
    /// 29-bit id.
    pub is_extended: bool,
    /// An error frame (never written by this project).
    pub is_error: bool,
    /// Data length code, 0..=8.
    pub dlc: u8,
    /// Data, padded with zeros to 8 bytes.
    pub data: [u8; 8],
}

/// Definition of [`Frame`].
pub static FRAME: MsgDef = MsgDef {
    name: "can_msgs/msg/Frame",
    text: "std_msgs/Header header\nuint32 id\nbool is_rtr\nbool is_extended\nbool is_error\n\
           uint8 dlc\nuint8[8] data\n",
    deps: &[&HEADER],
};
ros_msg!(Frame, FRAME);

impl Frame {
    /// The message of `frame`, stamped `stamp_ns`.
    #[must_use]
    pub fn from_can(stamp_ns: u64, frame: &firmware::CanFrame) -> Self {
        use embedded_can::{Frame as _, Id};
        let (id, is_extended) = match frame.id() {
            Id::Standard(id) => (u32::from(id.as_raw()), false),
            Id::Extended(id) => (id.as_raw(), true),
        };
        let mut data = [0u8; 8];
        data[..frame.data().len()].copy_from_slice(frame.data());
        Self {
            header: Header {
                stamp: Time::from_ns(stamp_ns),
                frame_id: String::new(),
            },
            id,
            is_rtr: frame.is_remote_frame(),
            is_extended,
            is_error: false,
            dlc: frame.dlc() as u8,
            data,
        }
    }

    /// The CAN frame; `None` for an error frame, an id out of its range or a DLC over 8.
    #[must_use]
    pub fn to_can(&self) -> Option<firmware::CanFrame> {
        use embedded_can::{ExtendedId, Frame as _, Id, StandardId};
        if self.is_error {
            return None;
        }
        let id: Id = if self.is_extended {
            ExtendedId::new(self.id)?.into()
        } else {
            StandardId::new(u16::try_from(self.id).ok()?)?.into()
        };
        let dlc = usize::from(self.dlc);
        if dlc > 8 {
            return None;
        }
        if self.is_rtr {
            firmware::CanFrame::new_remote(id, dlc)
        } else {
            firmware::CanFrame::new(id, &self.data[..dlc])
        }
    }
}

// ---- geometry_msgs ----

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

// ---- nav_msgs, tf2_msgs ----

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

// ---- sensor_msgs ----

/// `sensor_msgs/msg/JointState`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct JointState {
    pub header: Header,
    pub name: Vec<String>,
    pub position: Vec<f64>,
    pub velocity: Vec<f64>,
    pub effort: Vec<f64>,
}

/// Definition of [`JointState`].
pub static JOINT_STATE: MsgDef = MsgDef {
    name: "sensor_msgs/msg/JointState",
    text: "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\n\
           float64[] effort\n",
    deps: &[&HEADER],
};
ros_msg!(JointState, JOINT_STATE);

// ---- diagnostic_msgs ----

/// `diagnostic_msgs/msg/KeyValue`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct KeyValue {
    pub key: String,
    pub value: String,
}

/// Definition of [`KeyValue`].
pub static KEY_VALUE: MsgDef = MsgDef {
    name: "diagnostic_msgs/msg/KeyValue",
    text: "string key\nstring value\n",
    deps: &[],
};
ros_msg!(KeyValue, KEY_VALUE);

/// `diagnostic_msgs/msg/DiagnosticStatus`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct DiagnosticStatus {
    /// [`DiagnosticStatus::OK`], `WARN`, `ERROR` or `STALE`.
    pub level: u8,
    /// The component.
    pub name: String,
    /// What is going on, in a few words.
    pub message: String,
    /// The hardware's id.
    pub hardware_id: String,
    /// The figures.
    pub values: Vec<KeyValue>,
}

impl DiagnosticStatus {
    /// Level OK.
    pub const OK: u8 = 0;
    /// Level WARN.
    pub const WARN: u8 = 1;
    /// Level ERROR.
    pub const ERROR: u8 = 2;
    /// Level STALE.
    pub const STALE: u8 = 3;

    /// The value of `key`, if present.
    #[must_use]
    pub fn value(&self, key: &str) -> Option<&str> {
        self.values
            .iter()
            .find(|kv| kv.key == key)
            .map(|kv| kv.value.as_str())
    }
}

/// Definition of [`DiagnosticStatus`].
pub static DIAGNOSTIC_STATUS: MsgDef = MsgDef {
    name: "diagnostic_msgs/msg/DiagnosticStatus",
    text: "byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\nbyte level\nstring name\n\
           string message\nstring hardware_id\ndiagnostic_msgs/KeyValue[] values\n",
    deps: &[&KEY_VALUE],
};
ros_msg!(DiagnosticStatus, DIAGNOSTIC_STATUS);

/// `diagnostic_msgs/msg/DiagnosticArray`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct DiagnosticArray {
    pub header: Header,
    pub status: Vec<DiagnosticStatus>,
}

/// Definition of [`DiagnosticArray`].
pub static DIAGNOSTIC_ARRAY: MsgDef = MsgDef {
    name: "diagnostic_msgs/msg/DiagnosticArray",
    text: "std_msgs/Header header\ndiagnostic_msgs/DiagnosticStatus[] status\n",
    deps: &[&HEADER, &DIAGNOSTIC_STATUS],
};
ros_msg!(DiagnosticArray, DIAGNOSTIC_ARRAY);

// ---- rcl_interfaces ----

/// `rcl_interfaces/msg/Log`, the type of `/rosout`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct Log {
    pub stamp: Time,
    /// [`Log::INFO`], `WARN`, ...
    pub level: u8,
    pub name: String,
    pub msg: String,
    pub file: String,
    pub function: String,
    pub line: u32,
}

impl Log {
    /// Level DEBUG.
    pub const DEBUG: u8 = 10;
    /// Level INFO.
    pub const INFO: u8 = 20;
    /// Level WARN.
    pub const WARN: u8 = 30;
    /// Level ERROR.
    pub const ERROR: u8 = 40;
    /// Level FATAL.
    pub const FATAL: u8 = 50;
}

/// Definition of [`Log`].
pub static LOG: MsgDef = MsgDef {
    name: "rcl_interfaces/msg/Log",
    text: "byte DEBUG=10\nbyte INFO=20\nbyte WARN=30\nbyte ERROR=40\nbyte FATAL=50\n\
           builtin_interfaces/Time stamp\nuint8 level\nstring name\nstring msg\nstring file\n\
           string function\nuint32 line\n",
    deps: &[&TIME],
};
ros_msg!(Log, LOG);

// ---- the project's own ----

/// `mecanum_drive_msgs/msg/BusFault`: a frame the simulated bus's fault injector dropped or
/// corrupted. No standard type carries a frame's sender and fate.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct BusFault {
    /// `stamp`: when the frame completed on the wire.
    pub header: Header,
    /// `controller`, `drives` or `host`.
    pub sender: String,
    /// `dropped` (nobody received it) or `corrupted` (received with [`Self::received`]).
    pub fate: String,
    /// The frame as its sender sent it.
    pub frame: Frame,
    /// The data as received: corrupted bytes, or the sent data if dropped.
    pub received: [u8; 8],
}

/// Definition of [`BusFault`].
pub static BUS_FAULT: MsgDef = MsgDef {
    name: "mecanum_drive_msgs/msg/BusFault",
    text: "# A frame the simulated bus's fault injector dropped or corrupted.\n\
           std_msgs/Header header # stamp: when the frame completed on the wire\n\
           string sender # controller, drives or host\n\
           string fate # dropped or corrupted\n\
           can_msgs/Frame frame # as sent\n\
           uint8[8] received # the data as received (the sent data if dropped)\n",
    deps: &[&HEADER, &FRAME],
};
ros_msg!(BusFault, BUS_FAULT);

/// `mecanum_drive_msgs/msg/Step`: a control step of a runner in real time, whose steps are not
/// on the control period's grid (`/firmware/steps`): replay steps its core at these times.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Step {
    /// The time passed to the core's step (the message's log time).
    pub stamp: Time,
    /// [`Step::STEP`] or [`Step::SHUTDOWN`].
    pub kind: u8,
}

impl Step {
    /// A control step (`Controller::step`).
    pub const STEP: u8 = 0;
    /// The shutdown (`Controller::shutdown`), after the last step.
    pub const SHUTDOWN: u8 = 1;
}

/// Definition of [`Step`].
pub static STEP: MsgDef = MsgDef {
    name: "mecanum_drive_msgs/msg/Step",
    text: "# A control step of a runner in real time (not on the control period's grid).\n\
           uint8 STEP=0\n\
           uint8 SHUTDOWN=1\n\
           builtin_interfaces/Time stamp # the time passed to the core\n\
           uint8 kind # STEP or SHUTDOWN\n",
    deps: &[&TIME],
};
ros_msg!(Step, STEP);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_frame_is_the_ros2_socketcan_layout() {
        let f = Frame {
            header: Header::new(1_000_000_002, "ab"),
            id: 0x201,
            is_rtr: false,
            is_extended: true,
            is_error: false,
            dlc: 8,
            data: [1, 2, 3, 4, 5, 6, 7, 8],
        };
        let mut out = Vec::new();
        encode(&mut out, &f);
        #[rustfmt::skip]
        let want = [
            0, 1, 0, 0, // encapsulation
            1, 0, 0, 0, 2, 0, 0, 0, // stamp 1 s 2 ns
            3, 0, 0, 0, b'a', b'b', 0, // "ab" with its NUL, length 3
            0, // padding to 4
            1, 2, 0, 0, // id
            0, 1, 0, 8, // is_rtr, is_extended, is_error, dlc
            1, 2, 3, 4, 5, 6, 7, 8,
        ];
        assert_eq!(out, want);
        assert_eq!(decode::<Frame>(&out).unwrap(), f);
    }

    #[test]
    fn odometry_aligns_its_doubles_from_the_payload_start() {
        let o = Odometry {
            header: Header::new(5, "odom"),
            child_frame_id: "base_link".into(),
            pose: PoseWithCovariance {
                pose: Pose::planar([1.0, 2.0, 0.5]),
                covariance: [0.25; 36],
            },
            twist: TwistWithCovariance {
                twist: Twist::planar([0.1, 0.2, 0.3]),
                covariance: [0.0; 36],
            },
        };
        let mut out = Vec::new();
        encode(&mut out, &o);
        // Header: 8 + 4 + "odom\0" = 17 -> 20 (align 4); child: 4 + "base_link\0" = 34 -> 40
        // (align 8) for x.
        let x = f64::from_le_bytes(out[4 + 40..4 + 48].try_into().unwrap());
        assert_eq!(x, 1.0);
        // 7 doubles of pose and 36 of covariance, 6 of twist and 36 of covariance.
        assert_eq!(out.len(), 4 + 40 + 8 * (7 + 36 + 6 + 36));
        let back = decode::<Odometry>(&out).unwrap();
        assert_eq!(back, o);
        let p = back.pose.pose.to_planar();
        assert!((p[2] - 0.5).abs() < 1e-15, "{p:?}");
    }

    /// A tracker's pose, as a ROS 2 publisher writes it (built by hand here, not by
    /// [`encode`]): the doubles start at the next multiple of 8 after the frame id.
    #[test]
    fn a_tracker_pose_stamped_decodes_from_the_ros2_layout() {
        let mut raw = vec![0, 1, 0, 0];
        raw.extend_from_slice(&3i32.to_le_bytes()); // stamp 3 s
        raw.extend_from_slice(&500u32.to_le_bytes()); // 500 ns
        raw.extend_from_slice(&6u32.to_le_bytes()); // "world" and its NUL
        raw.extend_from_slice(b"world\0");
        raw.extend_from_slice(&[0; 6]); // 18 -> 24, the alignment of a double
        let yaw: f64 = -2.5;
        for v in [
            1.25,
            -0.5,
            0.0,
            0.0,
            0.0,
            (yaw / 2.0).sin(),
            (yaw / 2.0).cos(),
        ] {
            raw.extend_from_slice(&f64::to_le_bytes(v));
        }
        let p = decode::<PoseStamped>(&raw).unwrap();
        assert_eq!(p.header, Header::new(3_000_000_500, "world"));
        let planar = p.pose.to_planar();
        assert_eq!(planar[..2], [1.25, -0.5]);
        assert!((planar[2] - yaw).abs() < 1e-15, "{planar:?}");
        let mut out = Vec::new();
        encode(&mut out, &p);
        assert_eq!(out, raw);
        assert!(
            POSE_STAMPED
                .schema_text()
                .contains("\nMSG: geometry_msgs/Quaternion\n")
        );
    }

    #[test]
    fn a_schema_lists_each_dependency_once_after_its_separator() {
        let text = ODOMETRY.schema_text();
        assert!(text.starts_with("std_msgs/Header header\n"));
        for dep in [
            "std_msgs/Header",
            "builtin_interfaces/Time",
            "geometry_msgs/PoseWithCovariance",
            "geometry_msgs/Pose",
            "geometry_msgs/Point",
            "geometry_msgs/Quaternion",
            "geometry_msgs/TwistWithCovariance",
            "geometry_msgs/Twist",
            "geometry_msgs/Vector3",
        ] {
            let section = format!("{}\nMSG: {dep}\n", "=".repeat(80));
            assert_eq!(text.matches(&section).count(), 1, "{dep}:\n{text}");
        }
        assert_eq!(text.matches("\nMSG: ").count(), 9);
    }

    #[test]
    fn every_can_frame_round_trips() {
        use embedded_can::{ExtendedId, Frame as _, StandardId};
        let frames = [
            firmware::CanFrame::new(StandardId::new(0x7FF).unwrap(), &[9; 3]).unwrap(),
            firmware::CanFrame::new(ExtendedId::new(0x1ABC_DEF0).unwrap(), &[]).unwrap(),
            firmware::CanFrame::new_remote(StandardId::new(0x29).unwrap(), 8).unwrap(),
            firmware::CanFrame::new_remote(ExtendedId::new(0x1).unwrap(), 4).unwrap(),
        ];
        for f in frames {
            let m = Frame::from_can(7, &f);
            let mut out = Vec::new();
            encode(&mut out, &m);
            assert_eq!(decode::<Frame>(&out).unwrap().to_can(), Some(f), "{f:?}");
        }
        let bad = Frame {
            id: 0x800,
            ..Frame::default()
        };
        assert_eq!(bad.to_can(), None);
        assert!(matches!(
            decode::<Frame>(&[0, 0, 0, 0, 1]),
            Err(DecodeError::Encapsulation { .. })
        ));
        assert!(matches!(
            decode::<Frame>(&[0, 1, 0, 0, 1]),
            Err(DecodeError::Payload { .. })
        ));
    }
}
