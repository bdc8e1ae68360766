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

mod can;
mod diagnostics;
mod geometry;
mod project;
#[cfg(test)]
mod tests;

pub use can::*;
pub use diagnostics::*;
pub use geometry::*;
pub use project::*;

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
