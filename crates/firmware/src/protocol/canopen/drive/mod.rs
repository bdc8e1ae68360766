//! A simulated CiA 402 drive, the CANopen slave the master in `control::cia402` talks to: the
//! one test double of the simulator, the control tests, the benchmark and the cross-target
//! scenario. `no_std`, no heap, integers only (the same frames on every target).
//!
//! A node ([`Drive402`]) has CiA 301's NMT states, a fixed-capacity object dictionary served
//! by expedited SDO (`dictionary`, `server`), PDOs packed and unpacked from the mapping the
//! master wrote (`mapping`), SYNC-answered TPDOs, its heartbeat produced and the master's
//! consumed, EMCY with the error register, boot-up, and the 402 state machine (`machine`,
//! on the codec's [`DriveState402::on_controlword`]). [`Drives402`] is the nodes of one
//! configuration on one bus. What a node sends waits in its queue (`queue`) until the
//! caller's clock passes its time: an answer [`Timing::answer_ns`] after the request, a
//! boot-up [`Timing::boot_ns`] after a reset.
//!
//! The axes are the caller's, behind [`Axes`]: the node commands each wheel
//! ([`AxisCommand`]: a velocity target, a slow down or quick stop to rest, no torque) and
//! reads its actual velocity (`0x606C`) and whether it is at rest. Faults are the caller's
//! to inject: [`Faults`] (no heartbeat, an enable refused, an SDO abort), and a reboot, a
//! drive fault with its EMCY, a bus-off. The model is specified in `docs/simulator.md`,
//! section "CiA 402 drive".

mod bus;
mod dictionary;
mod machine;
mod mapping;
mod node;
mod queue;
mod server;
#[cfg(test)]
mod tests;

pub use bus::Drives402;
pub use node::Drive402;
pub use server::abort;

#[cfg(doc)]
use super::DriveState402;

/// The SDO writes (index, sub-index, value) that map node 1's PDOs as the master maps them,
/// in order: RPDO1 (COB-ID 0x201) the controlword and sub 1's target velocity, TPDO1 (0x181,
/// on every SYNC) the statusword and sub 1's actual velocity, each disabled, mapped and
/// enabled again; then profile velocity mode (3). For tests that need a configured node
/// without the master.
pub const NODE1_PDO_SETUP: [(u16, u8, u32); 14] = [
    (0x1400, 1, 0x8000_0201),
    (0x1600, 0, 0),
    (0x1600, 1, 0x6040_0010),
    (0x1600, 2, 0x60FF_0120),
    (0x1600, 0, 2),
    (0x1400, 1, 0x201),
    (0x1800, 1, 0x8000_0181),
    (0x1A00, 0, 0),
    (0x1A00, 1, 0x6041_0010),
    (0x1A00, 2, 0x606C_0120),
    (0x1A00, 0, 2),
    (0x1800, 2, 1),
    (0x1800, 1, 0x181),
    (0x6060, 0, 3),
];

/// EMCY error code of a drive fault (CiA 402: continuous over-current), the simulator's
/// `drive_fault`.
pub const EMCY_DRIVE_FAULT: u16 = 0x2310;
/// EMCY error code of a heartbeat consumer timeout (CiA 301: life guard / heartbeat error).
pub const EMCY_HEARTBEAT: u16 = 0x8130;
/// EMCY error code a node sends when it is back from bus-off (CiA 301: recovered from bus
/// off).
pub const EMCY_BUS_OFF_RECOVERED: u16 = 0x8140;
/// EMCY error code of a successful fault reset (CiA 301: error reset or no error).
pub const EMCY_ERROR_RESET: u16 = 0x0000;
/// The device type (0x1000) the nodes report: CiA 402, servo drive.
pub const DEVICE_TYPE: u32 = 0x0002_0192;

/// The error register (0x1001) bits of an EMCY error code (CiA 301 table "error register"):
/// bit 0 (generic) with any error, and the class bit of its code: current (0x2xxx) bit 1,
/// voltage (0x3xxx) bit 2, temperature (0x4xxx) bit 3, communication (0x81xx) and protocol
/// (0x82xx) errors bit 4; 0 for error reset (0x0000).
#[must_use]
pub const fn error_register(code: u16) -> u8 {
    let class = match code >> 12 {
        0x2 => 0x02,
        0x3 => 0x04,
        0x4 => 0x08,
        0x8 if matches!(code >> 8, 0x81 | 0x82) => 0x10,
        _ => 0,
    };
    if code == EMCY_ERROR_RESET {
        0
    } else {
        0x01 | class
    }
}

/// When a node answers, in the caller's clock (ns).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Timing {
    /// From a request (SDO, SYNC, NMT, an RPDO's fault reset) to the node's answer.
    pub answer_ns: u64,
    /// From a reset (NMT reset, reboot, power-on) to the boot-up.
    pub boot_ns: u64,
    /// The heartbeat producer's timer free-runs: its heartbeats come at the multiples of its
    /// period (0x1017) on the caller's clock. Otherwise (CANopenNode) the period runs from
    /// the write of 0x1017, the boot-up and each heartbeat sent on a change of NMT state.
    pub heartbeat_aligned: bool,
}

impl Timing {
    /// A node stepped once a millisecond: everything answered the next millisecond.
    pub const NEXT_MS: Self = Self {
        answer_ns: 1_000_000,
        boot_ns: 1_000_000,
        heartbeat_aligned: false,
    };
}

/// What a drive does that CiA 402 leaves to its maker.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Options {
    /// Quick stop option code (0x605A, fixed here) 5-8: quick stop active is kept once the
    /// axes are at rest (until the master disables the voltage). Otherwise (option code 2)
    /// it ends in switch on disabled at the first SYNC with every axis at rest.
    pub quick_stop_stays: bool,
    /// The node has no 0x605B / 0x605C (shutdown and disable operation option codes): SDO
    /// "object does not exist", and a shutdown or disable operation takes the torque at once.
    pub lacks_option_codes: bool,
    /// After a boot-up the node enters operational by itself (a vendor auto-start, CiA 302's
    /// "self-starting" NMT slave) and says so in a heartbeat right after the boot-up.
    pub self_starting: bool,
}

/// Faults the caller gives a node, from now on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Faults {
    /// The node sends no heartbeat (its boot-up, PDOs, SDO answers and EMCY still go out).
    pub heartbeat_silent: bool,
    /// Its enable never reaches operation enabled (it stays switched on).
    pub refuses_enable: bool,
    /// An SDO write to this object is aborted with this code.
    pub abort: Option<((u16, u8), u32)>,
}

/// What a node asks of one of its axes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AxisCommand {
    /// No torque: the axis coasts.
    Off,
    /// Follow this target velocity (0x60FF, drive units): operation enabled.
    Velocity(i32),
    /// Powered, to rest on the slow down ramp: a shutdown or disable operation with its option
    /// code at 1, until the axes are at rest.
    SlowDown,
    /// Powered, to rest on the quick stop ramp: quick stop active.
    QuickStop,
}

/// The axes a node drives, by wheel (the index into the configuration's `node_ids`).
pub trait Axes {
    /// Wheel `wheel` is to do `command` from now on.
    fn command(&mut self, wheel: usize, command: AxisCommand);
    /// Wheel `wheel`'s actual velocity (0x606C), drive units.
    fn velocity(&self, wheel: usize) -> i32;
    /// Whether wheel `wheel` is at rest (what ends a quick stop or a slow down).
    fn at_rest(&self, wheel: usize) -> bool;
}
