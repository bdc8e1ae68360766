//! What the robot says about itself: joint states (`sensor_msgs`), diagnostics
//! (`diagnostic_msgs`) and log lines (`rcl_interfaces`).

use serde::{Deserialize, Serialize};

use super::{HEADER, Header, MsgDef, RosMsg, TIME, Time};

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
