//! The mecanum drive's logs: ROS 2 bags in MCAP.
//!
//! One format for every log the project writes (the simulator's runs, `hostsim plant` on a
//! real interface, and the firmware's runner on a robot): MCAP profile `ros2`, every channel
//! a ROS 2 message type (schema encoding `ros2msg` with the full `.msg` text, message
//! encoding `cdr`), so Foxglove, PlotJuggler, `ros2 bag` (rosbag2's MCAP storage) and Python's
//! `rosbags` read them without this project's code. The candump text logs (`candump -L`) have
//! their one grammar here too: [`candump`].
//!
//! # Channels
//!
//! [`Channel::ALL`]; what each carries and when is the README's "Logs" table, the one place
//! it is written (a test checks it names every channel with its type).
//!
//! Log time 0 is the start of the run. The run's configuration (TOML) and its origin
//! (scenario, seed, program and versions) are the [`METADATA_NAME`] metadata record, written
//! before the first message, so that `replay` can rebuild the same firmware.
//!
//! # Writing and reading
//!
//! [`McapLog`] is what a run calls: it records each message's values in a batch (a few
//! dozen bytes a message, no encoding), and hands each batch to a thread of its own, which
//! encodes the messages in CDR ([`msg`]) and writes the MCAP file (zstd chunks, each
//! compressed whole, with message indexes; the summary section with chunk indexes and
//! statistics) with the `mcap` crate's record types.
//! A chunk ends at least every quarter second of log time, a killed run loses at most the last
//! second, and the log is `NAME.mcap.part` until it is finished (`docs/logs.md`, section
//! "Crash safety"); every other output file is written as a `.part` too ([`output`]).
//! [`for_each_message`] reads a log with the `mcap` crate's reader, every complete chunk of a
//! damaged file included, and names the byte offset of the damage ([`read`]). A
//! [`MessageTap`] sees every message as the writing thread writes it: the `live` crate serves
//! them to Foxglove while the run goes on.
//!
//! # Example
//!
//! ```
//! use std::collections::BTreeMap;
//! use drivelog::{Direction, McapLog, for_each_message, msg};
//! use embedded_can::StandardId;
//! use firmware::CanFrame;
//!
//! let path = std::env::temp_dir().join(format!("drivelog-doc-{}.mcap", std::process::id()));
//! let metadata = BTreeMap::from([("scenario".to_string(), "doc".to_string())]);
//! let mut log = McapLog::create(&path, &metadata)?;
//! let frame = CanFrame::standard(StandardId::new(0x201).unwrap(), &[1, 2, 3]).unwrap();
//! // Received by the firmware at 1 ms, queued by its sender 130 µs before, off the wire at 1 ms.
//! log.frame(Direction::Rx, 1_000_000, 870_000, 1_000_000, &frame)?;
//! log.finish()?;
//!
//! let bytes = std::fs::read(&path)?;
//! let mut frames = Vec::new();
//! let report = for_each_message(
//!     &bytes,
//!     |m| frames.push((m.topic.to_string(), msg::decode::<msg::Frame>(m.data).unwrap())),
//!     |_, _| {},
//! )?;
//! assert!(report.is_complete());
//! assert_eq!(frames[0].0, "/can/rx");
//! assert_eq!(frames[0].1.to_can(), Some(frame));
//! # std::fs::remove_file(&path)?;
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
//!

pub mod candump;
pub mod core_log;
pub mod msg;
pub mod output;
pub mod read;
pub mod write;

pub use core_log::{Changes, CoreLog, PoseTwist, StatusLog, heading_source_line, state_line};
pub use output::{Staged, file_stem, part_path};
pub use read::{Damage, Message, Problem, ReadReport, Undecodable, for_each_message};
pub use write::{CHUNK_SIZE, Direction, LogError, McapLog, MessageTap, OdometrySource, step_aside};

/// The MCAP profile of every log.
pub const PROFILE: &str = "ros2";

/// The name of the metadata record that holds the run's configuration (`config`, TOML; its
/// id `config_id`, `0x1a2b`, as the robot's `HEARTBEAT` sends it) and origin (`program`: `hostsim run`, `hostsim plant`, `mecanum-runner`; `scenario`, `seed`,
/// `hostsim_version`, `firmware_version`, `protocol_version` as the program knows them).
pub const METADATA_NAME: &str = "mecanum_drive";

/// The wheels' joint names, in the project's wheel order.
pub const WHEEL_NAMES: [&str; 4] = ["fl", "fr", "rl", "rr"];

/// The joint names of the tracking pods in `/joint_states`, after the wheels (a robot with
/// pods only; position only: a free-rolling pod has no speed the core measures, and no
/// effort).
pub const POD_NAMES: [&str; 3] = ["pod0", "pod1", "pod2"];

/// A channel of the logs.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Channel {
    /// `/can/rx`.
    CanRx,
    /// `/can/tx`.
    CanTx,
    /// `/can/faults`.
    CanFaults,
    /// `/cmd_vel`.
    CmdVel,
    /// `/odom`.
    Odom,
    /// `/ground_truth/odom`.
    GroundTruth,
    /// `/tf`.
    Tf,
    /// `/joint_states`.
    JointStates,
    /// `/diagnostics`.
    Diagnostics,
    /// `/rosout`.
    Rosout,
    /// `/firmware/steps`.
    Steps,
    /// `/firmware/store`.
    Store,
}

impl Channel {
    /// Every channel, in channel id order (id = index + 1).
    pub const ALL: [Self; 12] = [
        Self::CanRx,
        Self::CanTx,
        Self::CanFaults,
        Self::CmdVel,
        Self::Odom,
        Self::GroundTruth,
        Self::Tf,
        Self::JointStates,
        Self::Diagnostics,
        Self::Rosout,
        Self::Steps,
        Self::Store,
    ];

    /// The topic.
    #[must_use]
    pub const fn topic(self) -> &'static str {
        match self {
            Self::CanRx => "/can/rx",
            Self::CanTx => "/can/tx",
            Self::CanFaults => "/can/faults",
            Self::CmdVel => "/cmd_vel",
            Self::Odom => "/odom",
            Self::GroundTruth => "/ground_truth/odom",
            Self::Tf => "/tf",
            Self::JointStates => "/joint_states",
            Self::Diagnostics => "/diagnostics",
            Self::Rosout => "/rosout",
            Self::Steps => "/firmware/steps",
            Self::Store => "/firmware/store",
        }
    }

    /// The message type.
    #[must_use]
    pub fn def(self) -> &'static msg::MsgDef {
        match self {
            Self::CanRx | Self::CanTx => &msg::FRAME,
            Self::CanFaults => &msg::BUS_FAULT,
            Self::CmdVel => &msg::TWIST_STAMPED,
            Self::Odom | Self::GroundTruth => &msg::ODOMETRY,
            Self::Tf => &msg::TF_MESSAGE,
            Self::JointStates => &msg::JOINT_STATE,
            Self::Diagnostics => &msg::DIAGNOSTIC_ARRAY,
            Self::Rosout => &msg::LOG,
            Self::Steps => &msg::STEP,
            Self::Store => &msg::SAVE_RESULT,
        }
    }

    /// The channel of `topic`.
    #[must_use]
    pub fn from_topic(topic: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|c| c.topic() == topic)
    }

    /// Channel id in the file.
    #[must_use]
    pub const fn id(self) -> u16 {
        self as u16 + 1
    }
}

/// Frames of reference.
pub mod frames {
    /// The odometry's fixed frame.
    pub const ODOM: &str = "odom";
    /// The robot, as its odometry places it.
    pub const BASE_LINK: &str = "base_link";
    /// The robot, where it really is (simulator).
    pub const BASE_LINK_TRUTH: &str = "base_link_truth";
}
