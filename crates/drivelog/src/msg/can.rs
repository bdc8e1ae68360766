//! `can_msgs/msg/Frame`, as ros2_socketcan uses it.

use serde::{Deserialize, Serialize};

use super::{CDR_LE_HEADER, HEADER, Header, MsgDef, RosMsg, Time};

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

    /// Appends the message of `frame`, stamped `stamp_ns`, to `out`: the very bytes
    /// [`encode`](super::encode) appends for [`Frame::from_can`], laid out here without
    /// serde. The logs' commonest message (317,000 of the 60 s square's 353,000), whose serde
    /// encoding cost the log's writing thread about 0.03 s of the run's 0.2 s
    /// (`docs/benchmarks.md`, "The cost of logging"); the tests hold the two equal.
    pub fn encode_can(out: &mut Vec<u8>, stamp_ns: u64, frame: &firmware::CanFrame) {
        let m = Self::from_can(stamp_ns, frame);
        let mut bytes = [0u8; 36];
        bytes[..4].copy_from_slice(&CDR_LE_HEADER);
        // The payload's offsets count from its own start, after the 4 header bytes.
        bytes[4..8].copy_from_slice(&m.header.stamp.sec.to_le_bytes());
        bytes[8..12].copy_from_slice(&m.header.stamp.nanosec.to_le_bytes());
        // `frame_id`, empty: its length with the NUL (1), the NUL, 3 bytes to align `id`.
        bytes[12] = 1;
        bytes[20..24].copy_from_slice(&m.id.to_le_bytes());
        bytes[24] = u8::from(m.is_rtr);
        bytes[25] = u8::from(m.is_extended);
        bytes[26] = u8::from(m.is_error);
        bytes[27] = m.dlc;
        bytes[28..].copy_from_slice(&m.data);
        out.extend_from_slice(&bytes);
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
