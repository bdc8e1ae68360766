//! `can_msgs/msg/Frame`, as ros2_socketcan uses it.

use serde::{Deserialize, Serialize};

use super::{HEADER, Header, MsgDef, RosMsg, Time};

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
