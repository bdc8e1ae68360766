//! The project's own types, which no standard type describes: a bus fault, a control step and
//! the end of a parameter save.

use serde::{Deserialize, Serialize};

use super::{FRAME, Frame, HEADER, Header, MsgDef, RosMsg, TIME, Time};

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

/// `mecanum_drive_msgs/msg/SaveResult`: the end of a parameter save, as the robot's edge (its
/// flash, the runner's file, the simulator's flash) reported it to the core before the step at
/// `stamp` (`/firmware/store`): an input replay gives the core at the same step.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct SaveResult {
    /// The step before which the core was told (the message's log time).
    pub stamp: Time,
    /// The stored record's sequence number; 0 when not stored.
    pub seq: u32,
    /// 0 when stored; else the CiA 301 SDO abort code the save's response carries.
    pub abort_code: u32,
}

/// Definition of [`SaveResult`].
pub static SAVE_RESULT: MsgDef = MsgDef {
    name: "mecanum_drive_msgs/msg/SaveResult",
    text: "# The end of a parameter save, as the robot's edge reported it to the core.\n\
           builtin_interfaces/Time stamp # the step before which the core was told\n\
           uint32 seq # the stored record's number; 0 when not stored\n\
           uint32 abort_code # 0 when stored; else the SDO abort code of the response\n",
    deps: &[&TIME],
};
ros_msg!(SaveResult, SAVE_RESULT);
