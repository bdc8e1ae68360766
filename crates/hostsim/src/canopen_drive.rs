//! Simulated CANopen CiA 402 drives on the bus: each node's NMT state, its object dictionary
//! as an SDO server (what the master writes is what the node does), its PDOs as mapped,
//! answered on SYNC, its heartbeat and the master's watched, EMCY, boot-up, and the 402 state
//! machine powering its axes ([`Cia402Axis`]) in the plant.
//!
//! PDOs are packed and unpacked from the mapping the master wrote (`0x1600..`/`0x1A00..`),
//! not from the firmware codec's fixed layout: a master that maps wrong gets what a drive
//! would give it. A mapping or COB-ID written out of the disable → map → enable order is
//! refused with the abort code a drive gives. A communication error (the master's heartbeat
//! lost, a bus-off) takes an operational node to pre-operational, CiA 301's default error
//! behaviour (`0x1029:01` = 0). Reset communication resets the communication area
//! (0x1000-0x1FFF) only; reset node and a power cycle the whole dictionary and the drive. The
//! model is specified in `docs/simulator.md`, section "CiA 402 drive".

use std::collections::BTreeMap;

use embedded_can::{Frame, Id, StandardId};
use firmware::CanFrame;
use firmware::protocol::canopen::{
    self, DriveState402, Emcy, Message, NmtCommand, NmtState, NodeId, SdoRequest, SdoResponse,
};

use crate::plant::{Cia402Axis, Plant, Wheel};

/// Time from a request (SDO, SYNC, NMT) to the node's answer, ns.
pub const ANSWER_NS: u64 = 200_000;
/// Time from an NMT reset to the boot-up, ns.
pub const BOOT_NS: u64 = 2_000_000;
/// EMCY error code of a scenario's `drive_fault` (CiA 402: continuous over-current).
pub const EMCY_DRIVE_FAULT: u16 = 0x2310;
/// EMCY error code of a heartbeat consumer timeout (CiA 301: life guard / heartbeat error).
pub const EMCY_HEARTBEAT: u16 = 0x8130;
/// EMCY error code a node sends when it is back from bus-off (CiA 301: recovered from bus
/// off).
pub const EMCY_BUS_OFF_RECOVERED: u16 = 0x8140;
/// A quick stop ends once every axis of the node turns slower than this, rad/s (motor side).
pub const QUICK_STOP_REST_RAD_S: f64 = 0.1;
/// The device type (0x1000) the nodes report: CiA 402, servo drive.
pub const DEVICE_TYPE: u32 = 0x0002_0192;
/// EMCY error code of a successful fault reset (CiA 301: error reset or no error).
pub const EMCY_ERROR_RESET: u16 = 0x0000;
/// The communication area of the object dictionary (CiA 301): what reset communication sets
/// back to its defaults.
const COMMUNICATION_AREA: core::ops::RangeInclusive<u16> = 0x1000..=0x1FFF;
/// The error register (0x1001): a state of the node, not a parameter, so kept by reset
/// communication.
const ERROR_REGISTER: (u16, u8) = (0x1001, 0);

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

/// Statuswords (the codec's: bit 4 voltage enabled, bit 9 remote).
mod sw {
    use firmware::protocol::canopen::DriveState402 as S;
    pub const SWITCH_ON_DISABLED: u16 = S::SwitchOnDisabled.statusword();
    pub const OPERATION_ENABLED: u16 = S::OperationEnabled.statusword();
    pub const QUICK_STOP_ACTIVE: u16 = S::QuickStopActive.statusword();
    pub const FAULT: u16 = S::Fault.statusword();
}

/// SDO abort codes the nodes give (CiA 301 table 22).
mod abort {
    pub const NO_OBJECT: u32 = 0x0602_0000;
    pub const READ_ONLY: u32 = 0x0601_0002;
    pub const CANNOT_MAP: u32 = 0x0604_0041;
    pub const INCOMPATIBLE: u32 = 0x0604_0043;
    pub const NO_SUBINDEX: u32 = 0x0609_0011;
    pub const INVALID_VALUE: u32 = 0x0609_0030;
    pub const DEVICE_STATE: u32 = 0x0800_0022;
}

/// Faults a scenario can give a node, for the fault matrix.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct NodeFaults {
    /// The node sends no heartbeat.
    pub heartbeat_silent: bool,
    /// Its enable never reaches operation enabled (stays switched on).
    pub refuses_enable: bool,
    /// An SDO write to this object is aborted with this code.
    pub abort: Option<((u16, u8), u32)>,
}

/// A PDO mapping entry: object index, sub-index, length in bits.
type Entry = (u16, u8, u8);

/// What an NMT reset resets (CiA 301's two reset states).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Reset {
    /// Reset node (reset application), as a power cycle: everything.
    Node,
    /// Reset communication: the communication area (0x1000-0x1FFF) only.
    Communication,
}

/// One simulated node.
#[derive(Debug, Clone)]
struct Node {
    id: NodeId,
    /// The wheels of its axes: sub-index 0 (single-axis) or 1 and 2.
    axes: [Option<Wheel>; 3],
    od: BTreeMap<(u16, u8), u32>,
    nmt: NmtState,
    statusword: u16,
    last_controlword: u16,
    /// Targets of sub-indices 0, 1, 2, raw.
    targets: [i32; 3],
    next_heartbeat_ns: u64,
    last_master_heartbeat_ns: Option<u64>,
    faults: NodeFaults,
    /// The scenario's faults last set (for their rising edges).
    scenario: crate::sim::DriveFaults,
    /// Its CAN controller is bus-off: it sends and receives nothing.
    bus_off: bool,
    /// A shutdown (transition 8) or disable operation (5) under way on the slow down ramp
    /// (0x605B / 0x605C = 1): the state it enters once the axes are at rest. Operation
    /// enabled meanwhile, its targets zero.
    slowing_to: Option<DriveState402>,
}

/// The CiA 402 nodes of a configuration.
#[derive(Debug, Clone)]
pub struct CanopenDrives {
    nodes: Vec<Node>,
    /// Motor rev/s per raw unit of 0x60FF, motor rpm per raw unit of 0x606C.
    target_rev_s_per_unit: f64,
    actual_rpm_per_unit: f64,
    /// Frames owed: send time (ns), node (index), frame; in time order per node.
    queue: Vec<(u64, usize, CanFrame)>,
    emcy_sent: u32,
}

impl CanopenDrives {
    /// The nodes of a `Drive::Cia402` configuration, booting at time 0.
    #[must_use]
    pub fn new(config: &firmware::Config) -> Self {
        let firmware::config::Drive::Cia402(firmware::config::Cia402Drive {
            node_ids,
            axes,
            target_rpm_per_unit,
            actual_rpm_per_unit,
            ..
        }) = config.drive
        else {
            return Self::empty();
        };
        let mut nodes: Vec<Node> = Vec::new();
        for ((wheel, &id), &axis) in Wheel::ALL.iter().zip(&node_ids).zip(&axes) {
            let Some(nid) = NodeId::new(id) else { continue };
            let i = match nodes.iter().position(|n| n.id == nid) {
                Some(i) => i,
                None => {
                    nodes.push(Node::new(nid));
                    nodes.len() - 1
                }
            };
            if let Some(slot) = nodes[i].axes.get_mut(usize::from(axis)) {
                *slot = Some(*wheel);
            }
        }
        let mut drives = Self {
            nodes,
            target_rev_s_per_unit: f64::from(target_rpm_per_unit) / 60.0,
            actual_rpm_per_unit: f64::from(actual_rpm_per_unit),
            queue: Vec::new(),
            emcy_sent: 0,
        };
        for i in 0..drives.nodes.len() {
            drives.reset(i, 0, Reset::Node);
        }
        drives
    }

    const fn empty() -> Self {
        Self {
            nodes: Vec::new(),
            target_rev_s_per_unit: 0.0,
            actual_rpm_per_unit: 1.0,
            queue: Vec::new(),
            emcy_sent: 0,
        }
    }

    /// The faults of node `id` from now on.
    pub fn set_faults(&mut self, id: u8, faults: NodeFaults) {
        if let Some(n) = self.nodes.iter_mut().find(|n| n.id.get() == id) {
            n.faults = faults;
        }
    }

    /// Node `id` reboots at `t_ns`: its axes lose power and it boots (boot-up, defaults).
    pub fn reboot(&mut self, id: u8, t_ns: u64, plant: &mut Plant<Cia402Axis>) {
        if let Some(i) = self.nodes.iter().position(|n| n.id.get() == id) {
            self.reset(i, t_ns, Reset::Node);
            self.power(i, plant);
        }
    }

    /// Node `id` faults at `t_ns` with EMCY `code` (a drive error: overcurrent 0x2310, ...).
    pub fn fault(&mut self, id: u8, t_ns: u64, code: u16, plant: &mut Plant<Cia402Axis>) {
        if let Some(i) = self.nodes.iter().position(|n| n.id.get() == id) {
            self.enter_fault(i, t_ns, code, plant);
        }
    }

    /// The scenario's faults of each wheel's node from `at_ns` on: heartbeat, enable and SDO
    /// faults as they say; a rising `reboot` reboots the node, a rising `fault` faults it
    /// (EMCY 0x2310); `bus_off` holds it off the bus, and it comes back pre-operational.
    pub fn set_wheel_faults(
        &mut self,
        at_ns: u64,
        faults: [crate::sim::DriveFaults; 4],
        plant: &mut Plant<Cia402Axis>,
    ) {
        for i in 0..self.nodes.len() {
            let mut f = crate::sim::DriveFaults::default();
            for (w, wf) in Wheel::ALL.iter().zip(faults) {
                if self.nodes[i].axes.contains(&Some(*w)) {
                    f.silent |= wf.silent;
                    f.reboot |= wf.reboot;
                    f.fault |= wf.fault;
                    f.refuses_enable |= wf.refuses_enable;
                    f.sdo_abort |= wf.sdo_abort;
                    f.bus_off |= wf.bus_off;
                }
            }
            let before = self.nodes[i].scenario;
            self.nodes[i].scenario = f;
            self.nodes[i].faults = NodeFaults {
                heartbeat_silent: f.silent,
                refuses_enable: f.refuses_enable,
                abort: f.sdo_abort.then_some(((0x6060, 0), abort::INVALID_VALUE)),
            };
            if f.reboot && !before.reboot {
                self.reset(i, at_ns, Reset::Node);
                self.power(i, plant);
            }
            if f.fault && !before.fault {
                self.enter_fault(i, at_ns, EMCY_DRIVE_FAULT, plant);
            }
            if f.bus_off && !before.bus_off {
                self.go_bus_off(i, plant);
            }
            if !f.bus_off && before.bus_off {
                self.recover_bus_off(i, at_ns);
            }
        }
    }

    /// Node `i`'s controller goes bus-off: what it had queued is lost; the drive reacts to
    /// the communication error (abort connection: fault, no torque) and leaves operational.
    fn go_bus_off(&mut self, i: usize, plant: &mut Plant<Cia402Axis>) {
        self.nodes[i].bus_off = true;
        self.queue.retain(|&(_, n, _)| n != i);
        let n = &mut self.nodes[i];
        n.statusword = sw::FAULT;
        n.raise_error(EMCY_BUS_OFF_RECOVERED);
        if n.nmt == NmtState::Operational {
            n.nmt = NmtState::PreOperational;
        }
        self.power(i, plant);
    }

    /// Node `i` is back on the bus at `t_ns`: its EMCY (recovered from bus-off), then its
    /// heartbeat with the state it is in now.
    fn recover_bus_off(&mut self, i: usize, t_ns: u64) {
        self.nodes[i].bus_off = false;
        let register = self.nodes[i].get(ERROR_REGISTER.0, ERROR_REGISTER.1);
        #[allow(clippy::cast_possible_truncation)] // 0x1001 holds a byte.
        self.emcy(i, t_ns, EMCY_BUS_OFF_RECOVERED, register as u8);
        self.heartbeat_now(i, t_ns);
    }

    /// Node `i`'s NMT state becomes `state` at `t_ns`: if it changes, the heartbeat says so
    /// at once and the producer's period starts again from there (as CANopenNode does).
    fn set_nmt(&mut self, i: usize, state: NmtState, t_ns: u64) {
        if self.nodes[i].nmt != state {
            self.nodes[i].nmt = state;
            self.heartbeat_now(i, t_ns);
        }
    }

    /// Node `i`'s heartbeat at `t_ns` (if it produces one), the next a period later.
    fn heartbeat_now(&mut self, i: usize, t_ns: u64) {
        let n = &mut self.nodes[i];
        let Some(period) = n.heartbeat_period_ns() else {
            return;
        };
        n.next_heartbeat_ns = t_ns + period;
        if !n.faults.heartbeat_silent {
            let (node, state) = (n.id, n.nmt);
            self.send(i, t_ns, Message::Heartbeat { node, state });
        }
    }

    /// EMCY frames sent so far.
    #[must_use]
    pub const fn emcy_sent(&self) -> u32 {
        self.emcy_sent
    }

    /// The statusword of node `id`.
    #[must_use]
    pub fn statusword(&self, id: u8) -> Option<u16> {
        self.nodes
            .iter()
            .find(|n| n.id.get() == id)
            .map(|n| n.statusword)
    }

    /// Node `i`'s EMCY `code` with `error_register`, counted when it goes out (a node off the
    /// bus sends nothing).
    fn emcy(&mut self, i: usize, t_ns: u64, code: u16, error_register: u8) {
        self.emcy_sent += u32::from(!self.nodes[i].bus_off);
        let emcy = Emcy {
            error_code: code,
            error_register,
            manufacturer: [0; 5],
        };
        self.send(
            i,
            t_ns,
            Message::Emcy {
                node: self.nodes[i].id,
                emcy,
            },
        );
    }

    fn send(&mut self, i: usize, t_ns: u64, msg: Message) {
        if !self.nodes[i].bus_off {
            self.queue.push((t_ns, i, msg.to_can_frame()));
        }
    }

    /// Node `i` resets at `t_ns`: [`Reset::Node`] (or a power cycle) sets its dictionary at
    /// its defaults and its drive switch on disabled, [`Reset::Communication`] only the
    /// communication area (the drive, its mode and targets are kept); pre-operational, its
    /// heartbeat consumer idle until the master's next heartbeat. What it had queued (a
    /// boot-up still owed, answers) is lost with the reset; the boot-up goes out [`BOOT_NS`]
    /// later.
    fn reset(&mut self, i: usize, t_ns: u64, what: Reset) {
        self.queue.retain(|&(_, n, _)| n != i);
        let n = &mut self.nodes[i];
        match what {
            Reset::Node => {
                let (axes, faults, scenario, bus_off) = (n.axes, n.faults, n.scenario, n.bus_off);
                *n = Node::new(n.id);
                (n.axes, n.faults, n.scenario, n.bus_off) = (axes, faults, scenario, bus_off);
            }
            Reset::Communication => n.reset_communication(),
        }
        let id = n.id;
        // The heartbeat producer starts with the boot-up, at its default period (0: off).
        self.send(
            i,
            t_ns + BOOT_NS,
            Message::Heartbeat {
                node: id,
                state: NmtState::BootUp,
            },
        );
    }

    fn enter_fault(&mut self, i: usize, t_ns: u64, code: u16, plant: &mut Plant<Cia402Axis>) {
        let n = &mut self.nodes[i];
        if n.statusword == sw::FAULT {
            return;
        }
        n.statusword = sw::FAULT;
        n.slowing_to = None;
        let register = n.raise_error(code);
        self.emcy(i, t_ns, code, register);
        self.power(i, plant);
    }

    /// Powers node `i`'s axes as its state says, with their targets.
    fn power(&self, i: usize, plant: &mut Plant<Cia402Axis>) {
        let n = &self.nodes[i];
        for (sub, wheel) in n.axes.iter().enumerate() {
            let Some(wheel) = wheel else { continue };
            let axis = plant.drive_mut(*wheel);
            match n.statusword {
                sw::OPERATION_ENABLED if n.slowing_to.is_none() => {
                    axis.set_powered(true);
                    axis.set_target(f64::from(n.targets[sub]) * self.target_rev_s_per_unit);
                }
                sw::OPERATION_ENABLED | sw::QUICK_STOP_ACTIVE => {
                    axis.set_powered(true);
                    axis.set_target(0.0);
                }
                _ => {
                    axis.set_target(0.0);
                    axis.set_powered(false);
                }
            }
        }
    }

    /// A frame on the bus at `t_ns`.
    pub fn on_frame(&mut self, t_ns: u64, frame: &CanFrame, plant: &mut Plant<Cia402Axis>) {
        let Id::Standard(id) = frame.id() else { return };
        let raw = id.as_raw();
        // PDOs first: their ids are whatever the master mapped.
        for i in 0..self.nodes.len() {
            if self.nodes[i].nmt == NmtState::Operational
                && !self.nodes[i].bus_off
                && let Some(k) = self.nodes[i].rpdo_with(raw)
            {
                self.on_rpdo(i, k, t_ns + ANSWER_NS, frame.data(), plant);
                return;
            }
        }
        match canopen::decode(frame) {
            Ok(Message::Nmt { command, node }) => {
                for i in 0..self.nodes.len() {
                    if node.is_none_or(|id| id == self.nodes[i].id) && !self.nodes[i].bus_off {
                        self.on_nmt(i, command, t_ns, plant);
                    }
                }
            }
            Ok(Message::Sync { .. }) => self.on_sync(t_ns, plant),
            Ok(Message::SdoRequest { node, request }) => {
                if let Some(i) = self.nodes.iter().position(|n| n.id == node && !n.bus_off) {
                    let response = self.nodes[i].sdo(request);
                    let n = &mut self.nodes[i];
                    match response {
                        SdoResponse::Downloaded {
                            index: 0x1017,
                            sub: 0,
                        } => {
                            // The producer runs from the write on, at the new period.
                            let start = t_ns + ANSWER_NS;
                            n.next_heartbeat_ns =
                                n.heartbeat_period_ns().map_or(u64::MAX, |p| start + p);
                        }
                        SdoResponse::Downloaded {
                            index: 0x1016,
                            sub: 1,
                        } => {
                            // The consumer (re)starts at the producer's next heartbeat.
                            n.last_master_heartbeat_ns = None;
                        }
                        _ => {}
                    }
                    self.send(i, t_ns + ANSWER_NS, Message::SdoResponse { node, response });
                }
            }
            Ok(Message::Heartbeat { node, .. }) => {
                for n in &mut self.nodes {
                    if !n.bus_off && n.consumer().is_some_and(|(master, _)| master == node.get()) {
                        n.last_master_heartbeat_ns = Some(t_ns);
                    }
                }
            }
            _ => {}
        }
    }

    fn on_nmt(&mut self, i: usize, command: NmtCommand, t_ns: u64, plant: &mut Plant<Cia402Axis>) {
        let answer = t_ns + ANSWER_NS;
        match command {
            NmtCommand::Start => self.set_nmt(i, NmtState::Operational, answer),
            NmtCommand::Stop => self.set_nmt(i, NmtState::Stopped, answer),
            NmtCommand::EnterPreOperational => self.set_nmt(i, NmtState::PreOperational, answer),
            NmtCommand::ResetNode => {
                self.reset(i, t_ns, Reset::Node);
                self.power(i, plant);
            }
            NmtCommand::ResetCommunication => self.reset(i, t_ns, Reset::Communication),
        }
    }

    fn on_sync(&mut self, t_ns: u64, plant: &mut Plant<Cia402Axis>) {
        // A quick stop ends when the axes are at rest: switch on disabled, no power; so does
        // a shutdown or disable operation on the slow down ramp, in its own next state.
        for i in 0..self.nodes.len() {
            let n = &self.nodes[i];
            let at_rest = n
                .axes
                .iter()
                .flatten()
                .all(|w| plant.shaft(*w).speed.abs() < QUICK_STOP_REST_RAD_S);
            let done = match (n.statusword, n.slowing_to) {
                (sw::QUICK_STOP_ACTIVE, _) => Some(DriveState402::SwitchOnDisabled),
                (sw::OPERATION_ENABLED, Some(next)) => Some(next),
                _ => None,
            };
            if let Some(next) = done
                && at_rest
            {
                self.nodes[i].statusword = next.statusword();
                self.nodes[i].slowing_to = None;
                self.power(i, plant);
            }
        }
        let mut frames = Vec::new();
        for (i, n) in self.nodes.iter().enumerate() {
            if n.nmt != NmtState::Operational || n.bus_off {
                continue;
            }
            let actual = n.axes.map(|w| {
                w.map_or(0, |w| {
                    let rpm = plant.shaft(w).speed * 60.0 / core::f64::consts::TAU;
                    // Saturating float-to-int: a wheel far beyond any drive's range.
                    #[allow(clippy::cast_possible_truncation)]
                    let raw = (rpm / self.actual_rpm_per_unit).round() as i32;
                    raw
                })
            });
            for k in 0..4u16 {
                let Some((cob, entries)) = n.tpdo(k) else {
                    continue;
                };
                let mut data = [0u8; 8];
                let mut at = 0usize;
                for (index, sub, bits) in entries {
                    let value: u32 = match (index, sub) {
                        (0x6041, 0) => u32::from(n.statusword),
                        // Two's complement on the wire.
                        #[allow(clippy::cast_sign_loss)]
                        (0x606C, s) => actual[usize::from(s).min(2)] as u32,
                        _ => 0,
                    };
                    let bytes = usize::from(bits / 8);
                    data[at..at + bytes].copy_from_slice(&value.to_le_bytes()[..bytes]);
                    at += bytes;
                }
                if let Some(id) = StandardId::new(cob)
                    && let Some(frame) = CanFrame::standard(id, &data[..at])
                {
                    frames.push((t_ns + ANSWER_NS, i, frame));
                }
            }
        }
        self.queue.extend(frames);
    }

    fn on_rpdo(&mut self, i: usize, k: u16, t_ns: u64, data: &[u8], plant: &mut Plant<Cia402Axis>) {
        let Some(entries) = self.nodes[i].mapping(0x1600 + k) else {
            return;
        };
        let mut at = 0usize;
        let mut controlword = None;
        for (index, sub, bits) in entries {
            let bytes = usize::from(bits / 8);
            let Some(field) = data.get(at..at + bytes) else {
                // A frame shorter than its mapping: a drive ignores it.
                return;
            };
            let mut word = [0u8; 4];
            word[..bytes].copy_from_slice(field);
            let value = u32::from_le_bytes(word);
            at += bytes;
            match (index, sub) {
                // 16 bits mapped.
                #[allow(clippy::cast_possible_truncation)]
                (0x6040, 0) => controlword = Some(value as u16),
                // Two's complement on the wire.
                #[allow(clippy::cast_possible_wrap)]
                (0x60FF, s) => self.nodes[i].targets[usize::from(s).min(2)] = value as i32,
                _ => {}
            }
        }
        if let Some(cw) = controlword
            && self.nodes[i].control(cw)
        {
            self.emcy(i, t_ns, EMCY_ERROR_RESET, 0);
        }
        self.power(i, plant);
    }

    /// The frames the nodes send up to `until_ns`: answers, TPDOs, heartbeats, EMCY; and the
    /// master's heartbeat watched.
    pub fn feedback(
        &mut self,
        until_ns: u64,
        plant: &mut Plant<Cia402Axis>,
        out: &mut Vec<(u64, CanFrame)>,
    ) {
        for i in 0..self.nodes.len() {
            // The heartbeat consumer, from the master's first heartbeat on: a time-out is a
            // communication error (once until the master is heard again; the drive's abort
            // connection: fault), and an operational node goes pre-operational.
            if let Some((_, timeout_ms)) = self.nodes[i].consumer()
                && let Some(last) = self.nodes[i].last_master_heartbeat_ns
            {
                let deadline = last + u64::from(timeout_ms) * 1_000_000;
                if deadline <= until_ns {
                    // The heartbeats owed before it, in the state before it.
                    self.produce_heartbeats(i, deadline - 1);
                    self.nodes[i].last_master_heartbeat_ns = None;
                    self.enter_fault(i, deadline, EMCY_HEARTBEAT, plant);
                    if self.nodes[i].nmt == NmtState::Operational {
                        self.set_nmt(i, NmtState::PreOperational, deadline);
                    }
                }
            }
            self.produce_heartbeats(i, until_ns);
        }
        let mut due = Vec::new();
        self.queue.retain(|&(t, _, f)| {
            if t <= until_ns {
                due.push((t, f));
                false
            } else {
                true
            }
        });
        // Boot-ups start the heartbeat producer at the node's default period.
        for (t, f) in &due {
            if let Ok(Message::Heartbeat {
                node,
                state: NmtState::BootUp,
            }) = canopen::decode(f)
                && let Some(n) = self.nodes.iter_mut().find(|n| n.id == node)
            {
                n.next_heartbeat_ns = n.heartbeat_period_ns().map_or(u64::MAX, |p| t + p);
            }
        }
        due.sort_by_key(|(t, _)| *t);
        out.extend(due);
    }

    /// Node `i`'s periodic heartbeats up to `until_ns`.
    fn produce_heartbeats(&mut self, i: usize, until_ns: u64) {
        loop {
            let n = &mut self.nodes[i];
            if n.next_heartbeat_ns > until_ns {
                break;
            }
            let t = n.next_heartbeat_ns;
            n.next_heartbeat_ns = n.heartbeat_period_ns().map_or(u64::MAX, |p| t + p);
            if !n.faults.heartbeat_silent {
                let (node, state) = (n.id, n.nmt);
                self.send(i, t, Message::Heartbeat { node, state });
            }
        }
    }

    /// When the next frame is due, ns.
    #[must_use]
    pub fn next_feedback_ns(&self) -> u64 {
        let queued = self
            .queue
            .iter()
            .map(|(t, _, _)| *t)
            .min()
            .unwrap_or(u64::MAX);
        let beats = self
            .nodes
            .iter()
            .map(|n| n.next_heartbeat_ns)
            .min()
            .unwrap_or(u64::MAX);
        queued.min(beats)
    }
}

impl Node {
    fn new(id: NodeId) -> Self {
        let node = u32::from(id.get());
        let mut od = BTreeMap::new();
        od.insert((0x1000, 0), DEVICE_TYPE);
        od.insert(ERROR_REGISTER, 0);
        od.insert((0x1017, 0), 0);
        od.insert((0x1016, 1), 0);
        od.insert((0x6060, 0), 0);
        // Shutdown and disable operation option codes: 0 (disable the drive function at once,
        // the axes coast) or 1 (slow down on the slow down ramp first).
        od.insert((0x605B, 0), 0);
        od.insert((0x605C, 0), 0);
        // The mode of operation display: the mode in effect (at once here).
        od.insert((0x6061, 0), 0);
        // The predefined connection set, PDOs valid as a drive ships them.
        for k in 0..4u32 {
            let k16 = u16::try_from(k).unwrap_or(0);
            od.insert((0x1400 + k16, 1), 0x200 + 0x100 * k + node);
            od.insert((0x1400 + k16, 2), 0xFF);
            od.insert((0x1800 + k16, 1), 0x180 + 0x100 * k + node);
            od.insert((0x1800 + k16, 2), 0xFF);
            for map in [0x1600 + k16, 0x1A00 + k16] {
                for sub in 0..=8 {
                    od.insert((map, sub), 0);
                }
            }
        }
        Self {
            id,
            axes: [None; 3],
            od,
            nmt: NmtState::PreOperational,
            statusword: sw::SWITCH_ON_DISABLED,
            last_controlword: 0,
            targets: [0; 3],
            next_heartbeat_ns: u64::MAX,
            last_master_heartbeat_ns: None,
            faults: NodeFaults::default(),
            scenario: crate::sim::DriveFaults::default(),
            bus_off: false,
            slowing_to: None,
        }
    }

    fn get(&self, index: u16, sub: u8) -> u32 {
        self.od.get(&(index, sub)).copied().unwrap_or(0)
    }

    /// Reset communication: the communication area at its defaults (but the error register,
    /// the node's state), pre-operational, no heartbeat produced or watched. The application
    /// (the drive's state, 0x6000 and up) is kept.
    fn reset_communication(&mut self) {
        let fresh = Node::new(self.id);
        for (&key, &value) in &fresh.od {
            if COMMUNICATION_AREA.contains(&key.0) && key != ERROR_REGISTER {
                self.od.insert(key, value);
            }
        }
        self.nmt = fresh.nmt;
        self.next_heartbeat_ns = fresh.next_heartbeat_ns;
        self.last_master_heartbeat_ns = fresh.last_master_heartbeat_ns;
    }

    /// An error with EMCY `code` is present: its bits set in the error register; returns the
    /// register.
    fn raise_error(&mut self, code: u16) -> u8 {
        #[allow(clippy::cast_possible_truncation)] // 0x1001 holds a byte.
        let register = self.get(ERROR_REGISTER.0, ERROR_REGISTER.1) as u8 | error_register(code);
        self.od.insert(ERROR_REGISTER, u32::from(register));
        register
    }

    fn heartbeat_period_ns(&self) -> Option<u64> {
        let ms = self.get(0x1017, 0);
        (ms > 0).then(|| u64::from(ms) * 1_000_000)
    }

    /// The consumer entry (0x1016:01): the producer's node and the time, ms.
    fn consumer(&self) -> Option<(u8, u16)> {
        let v = self.get(0x1016, 1);
        let (node, ms) = (((v >> 16) & 0x7F) as u8, (v & 0xFFFF) as u16);
        (node != 0 && ms != 0).then_some((node, ms))
    }

    /// The entries `(index, sub, bits)` of mapping object `map`, if its PDO is valid.
    fn mapping(&self, map: u16) -> Option<Vec<Entry>> {
        let comm = map - 0x200;
        if self.get(comm, 1) & 0x8000_0000 != 0 {
            return None;
        }
        let count = self.get(map, 0).min(8);
        Some(
            (1..=count)
                .map(|s| {
                    // s <= 8.
                    #[allow(clippy::cast_possible_truncation)]
                    let e = self.get(map, s as u8);
                    ((e >> 16) as u16, (e >> 8) as u8, e as u8)
                })
                .collect(),
        )
    }

    /// The RPDO (0..=3) received on `cob`, if one is valid on it.
    fn rpdo_with(&self, cob: u16) -> Option<u16> {
        (0..4u16).find(|k| {
            let c = self.get(0x1400 + k, 1);
            c & 0x8000_0000 == 0 && c & 0x7FF == u32::from(cob)
        })
    }

    /// TPDO `k`'s COB-ID and entries, if it is valid and sent on SYNC.
    fn tpdo(&self, k: u16) -> Option<(u16, Vec<Entry>)> {
        let kind = self.get(0x1800 + k, 2);
        if kind == 0 || kind > 240 {
            return None;
        }
        let entries = self.mapping(0x1A00 + k)?;
        // 11 bits.
        #[allow(clippy::cast_possible_truncation)]
        let cob = (self.get(0x1800 + k, 1) & 0x7FF) as u16;
        Some((cob, entries))
    }

    /// Whether `(index, sub)` may be mapped into an RPDO (`rx`) or a TPDO.
    fn mappable(&self, index: u16, sub: u8, rx: bool) -> bool {
        let dual = self.axes[1].is_some() || self.axes[2].is_some();
        let axis_sub = if dual {
            (1..=2).contains(&sub)
        } else {
            sub == 0
        };
        match index {
            0x6040 => rx && sub == 0,
            0x60FF => rx && axis_sub,
            0x6041 => !rx && sub == 0,
            0x606C => !rx && axis_sub,
            _ => false,
        }
    }

    /// Answers one SDO request.
    fn sdo(&mut self, request: SdoRequest) -> SdoResponse {
        let (index, sub) = request.object();
        let refuse = |code| SdoResponse::Abort { index, sub, code };
        match request {
            SdoRequest::Abort { .. } => refuse(abort::INCOMPATIBLE),
            SdoRequest::Upload { .. } => match self.od.get(&(index, sub)) {
                Some(&value) => SdoResponse::Uploaded {
                    index,
                    sub,
                    value,
                    size: 4,
                },
                None if self.od.keys().any(|(i, _)| *i == index) => refuse(abort::NO_SUBINDEX),
                None => refuse(abort::NO_OBJECT),
            },
            SdoRequest::Download { value, .. } => {
                if let Some((object, code)) = self.faults.abort
                    && object == (index, sub)
                {
                    return refuse(code);
                }
                match self.check_write(index, sub, value) {
                    Ok(()) => {
                        self.od.insert((index, sub), value);
                        if (index, sub) == (0x6060, 0) {
                            self.od.insert((0x6061, 0), value);
                        }
                        SdoResponse::Downloaded { index, sub }
                    }
                    Err(code) => refuse(code),
                }
            }
        }
    }

    /// Whether writing `value` to `(index, sub)` is allowed now (CiA 301's PDO rules).
    fn check_write(&self, index: u16, sub: u8, value: u32) -> Result<(), u32> {
        if !self.od.contains_key(&(index, sub)) {
            return Err(if self.od.keys().any(|(i, _)| *i == index) {
                abort::NO_SUBINDEX
            } else {
                abort::NO_OBJECT
            });
        }
        match index {
            0x1000 | 0x1001 | 0x6061 => Err(abort::READ_ONLY),
            0x6060 if value != 3 => Err(abort::INVALID_VALUE),
            0x605B | 0x605C if value > 1 => Err(abort::INVALID_VALUE),
            // Mapping: only while the PDO is off; entries only while the count is 0.
            0x1600..=0x1603 | 0x1A00..=0x1A03 => {
                let comm = index - 0x200;
                if self.get(comm, 1) & 0x8000_0000 == 0 {
                    return Err(abort::DEVICE_STATE);
                }
                let rx = index < 0x1A00;
                if sub == 0 {
                    let entries: Vec<_> = (1..=value.min(8))
                        .map(|s| self.get(index, s as u8))
                        .collect();
                    let bits: u32 = entries.iter().map(|e| e & 0xFF).sum();
                    let ok = value <= 8
                        && bits <= 64
                        && entries
                            .iter()
                            .all(|e| self.mappable((e >> 16) as u16, (e >> 8) as u8, rx));
                    if ok { Ok(()) } else { Err(abort::CANNOT_MAP) }
                } else if self.get(index, 0) != 0 {
                    Err(abort::DEVICE_STATE)
                } else if self.mappable((value >> 16) as u16, (value >> 8) as u8, rx)
                    && matches!(value & 0xFF, 16 | 32)
                {
                    Ok(())
                } else {
                    Err(abort::CANNOT_MAP)
                }
            }
            // A valid PDO's COB-ID changes only through invalid.
            0x1400..=0x1403 | 0x1800..=0x1803 if sub == 1 => {
                let now = self.get(index, 1);
                let both_valid = now & 0x8000_0000 == 0 && value & 0x8000_0000 == 0;
                if both_valid && now & 0x7FF != value & 0x7FF {
                    Err(abort::INVALID_VALUE)
                } else {
                    Ok(())
                }
            }
            _ => Ok(()),
        }
    }

    /// The 402 state machine (the codec's drive side), on a controlword: true if it reset a
    /// fault (the error register is then cleared).
    fn control(&mut self, cw: u16) -> bool {
        let state = DriveState402::from_statusword(self.statusword)
            .unwrap_or(DriveState402::SwitchOnDisabled);
        let may_enable = self.get(0x6060, 0) == 3 && !self.faults.refuses_enable;
        let next = state.on_controlword(cw, self.last_controlword, may_enable);
        // Transitions 8 and 5 with option code 1 (0x605B, 0x605C): the drive slows down
        // first, still operation enabled.
        let option = match next {
            DriveState402::ReadyToSwitchOn => self.get(0x605B, 0),
            DriveState402::SwitchedOn => self.get(0x605C, 0),
            _ => 0,
        };
        let slows = state == DriveState402::OperationEnabled && option == 1;
        self.slowing_to = slows.then_some(next);
        self.statusword = if slows { state } else { next }.statusword();
        self.last_controlword = cw;
        let reset = state == DriveState402::Fault && next != state;
        if reset {
            self.od.insert(ERROR_REGISTER, 0);
        }
        reset
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000_000;

    /// The example's nodes 1 and 2 (dual-axis) and their plant, booted: what each test
    /// starts from.
    struct Bench {
        drives: CanopenDrives,
        plant: Plant<Cia402Axis>,
        /// Every frame the nodes sent: time (ns), frame.
        sent: Vec<(u64, CanFrame)>,
    }

    impl Bench {
        fn new() -> Self {
            let config = firmware::Config::cia402_example();
            Self {
                drives: CanopenDrives::new(&config),
                plant: Plant::cia402_from_config(&config).unwrap(),
                sent: Vec::new(),
            }
        }

        /// The nodes' frames up to `t_ns`.
        fn run_to(&mut self, t_ns: u64) {
            self.drives.feedback(t_ns, &mut self.plant, &mut self.sent);
        }

        /// `msg` on the bus at `t_ns` (after the nodes' frames up to then).
        fn put(&mut self, t_ns: u64, msg: Message) {
            self.run_to(t_ns);
            let frame = msg.to_can_frame();
            self.drives.on_frame(t_ns, &frame, &mut self.plant);
        }

        fn nmt(&mut self, t_ns: u64, command: NmtCommand) {
            let node = Some(node1());
            self.put(t_ns, Message::Nmt { command, node });
        }

        /// An SDO request to node 1 at `t_ns`; its answer.
        fn sdo(&mut self, t_ns: u64, request: SdoRequest) -> SdoResponse {
            let from = self.sent.len();
            self.put(
                t_ns,
                Message::SdoRequest {
                    node: node1(),
                    request,
                },
            );
            self.run_to(t_ns + ANSWER_NS);
            self.sent[from..]
                .iter()
                .find_map(|(_, f)| match canopen::decode(f) {
                    Ok(Message::SdoResponse { node, response }) if node == node1() => {
                        Some(response)
                    }
                    _ => None,
                })
                .expect("an SDO answer")
        }

        fn download(&mut self, t_ns: u64, index: u16, sub: u8, value: u32) {
            let request = SdoRequest::Download {
                index,
                sub,
                value,
                size: 4,
            };
            assert_eq!(
                self.sdo(t_ns, request),
                SdoResponse::Downloaded { index, sub },
                "{index:04X}:{sub:02X} = {value:#x}"
            );
        }

        fn upload(&mut self, t_ns: u64, index: u16, sub: u8) -> u32 {
            match self.sdo(t_ns, SdoRequest::Upload { index, sub }) {
                SdoResponse::Uploaded { value, .. } => value,
                other => panic!("{index:04X}:{sub:02X}: {other:?}"),
            }
        }

        /// Node 1's RPDO1 carries its controlword (disable, map, enable), mode 3, started.
        fn started_with_controlword(&mut self, t_ns: u64) {
            for (k, (index, sub, value)) in [
                (0x1400, 1, 0x8000_0201),
                (0x1600, 0, 0),
                (0x1600, 1, 0x6040_0010),
                (0x1600, 0, 1),
                (0x1400, 1, 0x201),
                (0x6060, 0, 3),
            ]
            .into_iter()
            .enumerate()
            {
                self.download(t_ns + k as u64 * MS, index, sub, value);
            }
            self.nmt(t_ns + 10 * MS, NmtCommand::Start);
        }

        fn controlword(&mut self, t_ns: u64, cw: u16) {
            let frame = CanFrame::standard(StandardId::new(0x201).unwrap(), &cw.to_le_bytes());
            self.run_to(t_ns);
            self.drives.on_frame(t_ns, &frame.unwrap(), &mut self.plant);
        }

        /// Node 1's EMCY frames so far: time, error code, error register.
        fn emcys(&self) -> Vec<(u64, u16, u8)> {
            self.messages()
                .filter_map(|(t, m)| match m {
                    Message::Emcy { node, emcy } if node == node1() => {
                        Some((t, emcy.error_code, emcy.error_register))
                    }
                    _ => None,
                })
                .collect()
        }

        /// Node 1's heartbeats (and boot-ups) so far: time, state.
        fn heartbeats(&self) -> Vec<(u64, NmtState)> {
            self.messages()
                .filter_map(|(t, m)| match m {
                    Message::Heartbeat { node, state } if node == node1() => Some((t, state)),
                    _ => None,
                })
                .collect()
        }

        fn messages(&self) -> impl Iterator<Item = (u64, Message)> + '_ {
            self.sent
                .iter()
                .filter_map(|(t, f)| canopen::decode(f).ok().map(|m| (*t, m)))
        }

        fn state(&self) -> DriveState402 {
            DriveState402::from_statusword(self.drives.statusword(1).unwrap()).unwrap()
        }
    }

    fn node1() -> NodeId {
        NodeId::new(1).unwrap()
    }

    #[test]
    fn reset_communication_resets_the_communication_area_only_reset_node_everything() {
        let mut b = Bench::new();
        b.started_with_controlword(3 * MS);
        b.download(20 * MS, 0x1017, 0, 50);
        for cw in [0x06, 0x07, 0x0F] {
            b.controlword(30 * MS, cw);
        }
        assert_eq!(b.state(), DriveState402::OperationEnabled);
        b.nmt(40 * MS, NmtCommand::ResetCommunication);
        b.run_to(40 * MS + BOOT_NS);
        assert_eq!(
            b.heartbeats().last(),
            Some(&(40 * MS + BOOT_NS, NmtState::BootUp))
        );
        // The communication area at its defaults: no heartbeat, the predefined RPDO1 (its
        // mapping empty, as the node ships), RPDO2 valid on 0x301.
        let t = 50 * MS;
        assert_eq!(b.upload(t, 0x1017, 0), 0);
        assert_eq!(b.upload(t, 0x1600, 0), 0);
        assert_eq!(b.upload(t, 0x1401, 1), 0x301);
        // The application kept: the mode (and its display), the drive's state.
        assert_eq!(b.upload(t, 0x6060, 0), 3);
        assert_eq!(b.upload(t, 0x6061, 0), 3);
        assert_eq!(b.state(), DriveState402::OperationEnabled);
        // Reset node: everything, the drive switch on disabled.
        b.nmt(60 * MS, NmtCommand::ResetNode);
        b.run_to(60 * MS + BOOT_NS);
        assert_eq!(b.upload(70 * MS, 0x6060, 0), 0);
        assert_eq!(b.state(), DriveState402::SwitchOnDisabled);
    }

    #[test]
    fn a_reset_before_the_power_on_boot_up_leaves_one_boot_up_its_own() {
        let mut b = Bench::new();
        // Powered at 0 (boot-up owed at BOOT_NS); the master's reset at 1 ms.
        b.nmt(MS, NmtCommand::ResetCommunication);
        b.run_to(20 * MS);
        assert_eq!(b.heartbeats(), [(MS + BOOT_NS, NmtState::BootUp)]);
        // Node 2, not reset, sent its power-on boot-up.
        let node2 = b
            .messages()
            .filter(|(_, m)| matches!(m, Message::Heartbeat { node, .. } if node.get() == 2))
            .count();
        assert_eq!(node2, 1);
    }

    #[test]
    fn emcy_error_register_carries_the_class_of_the_error() {
        for (code, register) in [
            (0x2310, 0x03), // over-current: current
            (0x3210, 0x05), // over-voltage: voltage
            (0x4210, 0x09), // temperature
            (0x8130, 0x11), // heartbeat / life guard: communication
            (0x8140, 0x11), // recovered from bus-off
            (0x8210, 0x11), // PDO length: protocol, communication
            (0x8611, 0x01), // following error: generic only
            (0x1000, 0x01), // generic
            (0x0000, 0x00), // error reset
        ] {
            assert_eq!(error_register(code), register, "{code:#06x}");
        }
        let mut b = Bench::new();
        b.run_to(3 * MS);
        b.drives.fault(1, 4 * MS, EMCY_DRIVE_FAULT, &mut b.plant);
        b.run_to(5 * MS);
        assert_eq!(b.emcys(), [(4 * MS, 0x2310, 0x03)]);
        assert_eq!(b.upload(6 * MS, 0x1001, 0), 0x03);
        // Read-only.
        assert_eq!(
            b.sdo(
                7 * MS,
                SdoRequest::Download {
                    index: 0x1001,
                    sub: 0,
                    value: 0,
                    size: 1
                }
            ),
            SdoResponse::Abort {
                index: 0x1001,
                sub: 0,
                code: abort::READ_ONLY
            }
        );
    }

    #[test]
    fn a_fault_reset_sends_emcy_error_reset_and_clears_the_register() {
        let mut b = Bench::new();
        b.started_with_controlword(3 * MS);
        b.controlword(20 * MS, 0x06);
        b.drives.fault(1, 21 * MS, EMCY_DRIVE_FAULT, &mut b.plant);
        // No edge of bit 7 yet: nothing.
        b.controlword(22 * MS, 0x06);
        assert_eq!(b.state(), DriveState402::Fault);
        b.controlword(23 * MS, 0x80);
        b.controlword(24 * MS, 0x80);
        b.run_to(30 * MS);
        assert_eq!(b.state(), DriveState402::SwitchOnDisabled);
        assert_eq!(
            b.emcys(),
            [(21 * MS, 0x2310, 0x03), (23 * MS + ANSWER_NS, 0x0000, 0x00)]
        );
        assert_eq!(b.upload(31 * MS, 0x1001, 0), 0);
    }

    #[test]
    fn the_heartbeat_consumer_starts_at_the_masters_first_heartbeat() {
        let mut b = Bench::new();
        b.started_with_controlword(3 * MS);
        b.download(20 * MS, 0x1017, 0, 50);
        b.download(21 * MS, 0x1016, 1, 127 << 16 | 150);
        // Started, the consumer set, and no heartbeat of the master for a second: nothing.
        b.run_to(1_000 * MS);
        assert!(b.emcys().is_empty());
        let master = NodeId::new(127).unwrap();
        let beat = Message::Heartbeat {
            node: master,
            state: NmtState::Operational,
        };
        b.put(1_000 * MS, beat);
        b.put(1_050 * MS, beat);
        b.run_to(2_000 * MS);
        // The time-out 150 ms after the last one: EMCY 0x8130, pre-operational at once.
        assert_eq!(b.emcys(), [(1_200 * MS, 0x8130, 0x11)]);
        let states: Vec<_> = b
            .heartbeats()
            .into_iter()
            .filter(|(t, _)| (1_100 * MS..1_300 * MS).contains(t))
            .collect();
        assert_eq!(
            states.iter().map(|h| h.1).collect::<Vec<_>>(),
            [
                NmtState::Operational,
                NmtState::Operational,
                NmtState::PreOperational,
                NmtState::PreOperational
            ],
            "{states:?}"
        );
        assert!(
            states.contains(&(1_200 * MS, NmtState::PreOperational)),
            "{states:?}"
        );
    }

    #[derive(serde::Deserialize)]
    struct TransitionTable {
        statusword: BTreeMap<String, u16>,
        table: Rows,
    }

    #[derive(serde::Deserialize)]
    struct Rows {
        rows: Vec<(String, u16, u16, u8, String, String)>,
    }

    /// CiA 402's state table (tests/cia402_transitions.toml, which the Python peer's test
    /// reads too): each row from its state, its controlword after the one before it, in its
    /// mode of operation.
    #[test]
    fn both_drive_models_follow_the_transition_table() {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../tests/cia402_transitions.toml"
        );
        let text = std::fs::read_to_string(path).unwrap();
        let t: TransitionTable = toml::from_str(&text).unwrap();
        let states = [
            DriveState402::SwitchOnDisabled,
            DriveState402::ReadyToSwitchOn,
            DriveState402::SwitchedOn,
            DriveState402::OperationEnabled,
            DriveState402::QuickStopActive,
            DriveState402::Fault,
        ];
        let named = |name: &str| *states.iter().find(|s| s.as_str() == name).unwrap();
        assert!(t.table.rows.len() >= 60);
        for (from, cw, previous, mode, to, transition) in &t.table.rows {
            let mut n = Node::new(node1());
            n.statusword = named(from).statusword();
            n.last_controlword = *previous;
            n.od.insert((0x6060, 0), u32::from(*mode));
            let reset = n.control(*cw);
            let row = format!(
                "{from} {cw:#04x} (after {previous:#04x}, mode {mode}) -> {to} ({transition})"
            );
            assert_eq!(
                DriveState402::from_statusword(n.statusword).map(DriveState402::as_str),
                Some(to.as_str()),
                "{row}"
            );
            assert_eq!(n.statusword & 0x6F, t.statusword[to], "{row}");
            assert_eq!(reset, from == "FAULT" && to != "FAULT", "{row}");
        }
    }

    fn write(n: &mut Node, index: u16, sub: u8, value: u32) -> SdoResponse {
        n.sdo(SdoRequest::Download {
            index,
            sub,
            value,
            size: 4,
        })
    }

    #[test]
    fn a_mapping_changes_only_in_the_disable_map_enable_order() {
        let mut n = Node::new(NodeId::new(1).unwrap());
        n.axes = [Some(Wheel::FrontLeft), None, None];
        let refused = |code| SdoResponse::Abort {
            index: 0x1600,
            sub: 0,
            code,
        };
        // RPDO1 is valid as the drive ships: its mapping is locked.
        assert_eq!(write(&mut n, 0x1600, 0, 0), refused(abort::DEVICE_STATE));
        assert!(matches!(
            write(&mut n, 0x1400, 1, 0x8000_0201),
            SdoResponse::Downloaded { .. }
        ));
        assert!(matches!(
            write(&mut n, 0x1600, 0, 0),
            SdoResponse::Downloaded { .. }
        ));
        assert!(matches!(
            write(&mut n, 0x1600, 1, 0x6040_0010),
            SdoResponse::Downloaded { .. }
        ));
        // A TPDO object in an RPDO, or a dual-axis sub-index on a single-axis node: refused.
        for bad in [0x6041_0010, 0x60FF_0120] {
            assert_eq!(
                write(&mut n, 0x1600, 2, bad),
                SdoResponse::Abort {
                    index: 0x1600,
                    sub: 2,
                    code: abort::CANNOT_MAP
                }
            );
        }
        assert!(matches!(
            write(&mut n, 0x1600, 2, 0x60FF_0020),
            SdoResponse::Downloaded { .. }
        ));
        assert!(matches!(
            write(&mut n, 0x1600, 0, 2),
            SdoResponse::Downloaded { .. }
        ));
        // Entries only while the count is 0.
        assert_eq!(
            write(&mut n, 0x1600, 1, 0x6040_0010),
            SdoResponse::Abort {
                index: 0x1600,
                sub: 1,
                code: abort::DEVICE_STATE
            }
        );
        assert!(matches!(
            write(&mut n, 0x1400, 1, 0x201),
            SdoResponse::Downloaded { .. }
        ));
        assert_eq!(
            n.mapping(0x1600),
            Some(vec![(0x6040, 0, 16), (0x60FF, 0, 32)])
        );
        assert_eq!(n.rpdo_with(0x201), Some(0));
    }
}
