//! One node: its NMT state and resets, heartbeat producer and consumer, EMCY and the faults
//! a caller injects, and what it does with each frame of the master.

use embedded_can::{Frame, Id};

use super::dictionary::Dictionary;
use super::queue::Owed;
use super::{Axes, EMCY_BUS_OFF_RECOVERED, EMCY_ERROR_RESET, EMCY_HEARTBEAT, Faults, Options};
use super::{Timing, error_register, mapping, server};
use crate::CanFrame;
use crate::protocol::canopen::{
    DriveState402, Emcy, Message, NmtCommand, NmtState, NodeId, SdoRequest, SdoResponse, layout,
};

/// What an NMT reset resets (CiA 301's two reset states).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Reset {
    /// Reset node (reset application), as a power cycle: everything.
    Node,
    /// Reset communication: the communication area (0x1000-0x1FFF) only.
    Communication,
}

/// One simulated CiA 402 node (see the [module](super) documentation).
#[derive(Debug, Clone)]
pub struct Drive402 {
    pub(super) id: NodeId,
    /// The wheel of each axis, by sub-index: 0 (single-axis), or 1 and 2.
    pub(super) wheels: [Option<u8>; 3],
    pub(super) timing: Timing,
    pub(super) options: Options,
    pub(super) od: Dictionary,
    pub(super) nmt: NmtState,
    pub(super) state: DriveState402,
    pub(super) last_controlword: u16,
    /// Targets of sub-indices 0, 1, 2, raw.
    pub(super) targets: [i32; 3],
    pub(super) next_heartbeat_ns: u64,
    pub(super) last_master_heartbeat_ns: Option<u64>,
    pub(super) faults: Faults,
    /// Its CAN controller is bus-off: it sends and receives nothing.
    pub(super) bus_off: bool,
    /// A shutdown (transition 8) or disable operation (5) under way on the slow down ramp
    /// (0x605B / 0x605C = 1): the state it enters once the axes are at rest. Operation
    /// enabled meanwhile, its targets zero.
    pub(super) slowing_to: Option<DriveState402>,
    pub(super) owed: Owed,
    pub(super) emcy_sent: u32,
}

impl Drive402 {
    /// Node `id`, powered on at time 0 (its boot-up [`Timing::boot_ns`] later), driving wheel
    /// `wheels[s]` on sub-index `s` (0 for a single-axis node; 1 and 2 for a dual-axis one).
    #[must_use]
    pub fn new(id: NodeId, wheels: [Option<u8>; 3], timing: Timing, options: Options) -> Self {
        let mut node = Self::fresh(id, wheels, timing, options);
        node.reset(0, Reset::Node);
        node
    }

    fn fresh(id: NodeId, wheels: [Option<u8>; 3], timing: Timing, options: Options) -> Self {
        Self {
            id,
            wheels,
            timing,
            options,
            od: Dictionary::new(id, !options.lacks_option_codes),
            nmt: NmtState::PreOperational,
            state: DriveState402::SwitchOnDisabled,
            last_controlword: 0,
            targets: [0; 3],
            next_heartbeat_ns: u64::MAX,
            last_master_heartbeat_ns: None,
            faults: Faults::default(),
            bus_off: false,
            slowing_to: None,
            owed: Owed::default(),
            emcy_sent: 0,
        }
    }

    /// Its node id.
    #[must_use]
    pub const fn id(&self) -> NodeId {
        self.id
    }

    /// The wheel of each of its axes, by sub-index.
    #[must_use]
    pub const fn wheels(&self) -> [Option<u8>; 3] {
        self.wheels
    }

    /// Its NMT state.
    #[must_use]
    pub const fn nmt(&self) -> NmtState {
        self.nmt
    }

    /// Its 402 state.
    #[must_use]
    pub const fn state(&self) -> DriveState402 {
        self.state
    }

    /// Its statusword (0x6041).
    #[must_use]
    pub const fn statusword(&self) -> u16 {
        self.state.statusword()
    }

    /// The value of object `(index, sub)` of its dictionary, if it has it.
    #[must_use]
    pub fn entry(&self, index: u16, sub: u8) -> Option<u32> {
        self.od.entry(index, sub)
    }

    /// The faults given to it.
    #[must_use]
    pub const fn faults(&self) -> Faults {
        self.faults
    }

    /// Its faults from now on.
    pub fn set_faults(&mut self, faults: Faults) {
        self.faults = faults;
    }

    /// Its maker's options.
    #[must_use]
    pub const fn options(&self) -> Options {
        self.options
    }

    /// Its maker's options from now on.
    pub fn set_options(&mut self, options: Options) {
        self.options = options;
        self.od.set_option_codes(!options.lacks_option_codes);
    }

    /// Whether it is bus-off.
    #[must_use]
    pub const fn is_bus_off(&self) -> bool {
        self.bus_off
    }

    /// EMCY frames it sent (not those it queued while bus-off).
    #[must_use]
    pub const fn emcy_sent(&self) -> u32 {
        self.emcy_sent
    }

    /// Frames it could not queue (its queue full: frames not collected in time).
    #[must_use]
    pub const fn frames_lost(&self) -> u32 {
        self.owed.lost()
    }

    /// When its next queued frame is due.
    pub(super) fn next_queued_ns(&self) -> u64 {
        self.owed.next_ns().unwrap_or(u64::MAX)
    }

    /// When its next frame is due: one queued, or its next heartbeat.
    #[must_use]
    pub fn next_due_ns(&self) -> u64 {
        self.next_queued_ns().min(self.next_heartbeat_ns)
    }

    /// Puts the drive in `state` at once, as if it got there by itself (a test's shortcut:
    /// the master is not told until the next TPDO).
    pub fn set_state(&mut self, state: DriveState402, axes: &mut impl Axes) {
        self.state = state;
        self.slowing_to = None;
        self.power(axes);
    }

    /// Puts the node in NMT state `state` without a heartbeat saying so (the next periodic
    /// one does).
    pub fn set_nmt_quietly(&mut self, state: NmtState) {
        self.nmt = state;
    }

    /// The node enters NMT state `state` at `t_ns` by itself (CiA 301's error behaviour: a
    /// communication error), and says so in a heartbeat at once.
    pub fn enter(&mut self, state: NmtState, t_ns: u64) {
        self.set_nmt(state, t_ns);
    }

    /// It reboots at `t_ns` (a power cycle): its axes lose power and it boots (boot-up,
    /// defaults).
    pub fn reboot(&mut self, t_ns: u64, axes: &mut impl Axes) {
        self.reset(t_ns, Reset::Node);
        self.power(axes);
    }

    /// It faults at `t_ns` with EMCY `code` (a drive error: over-current 0x2310, ...).
    pub fn fault(&mut self, t_ns: u64, code: u16, axes: &mut impl Axes) {
        if self.state == DriveState402::Fault {
            return;
        }
        self.state = DriveState402::Fault;
        self.slowing_to = None;
        let register = self.raise_error(code);
        self.emcy(t_ns, code, register);
        self.power(axes);
    }

    /// Its CAN controller goes bus-off: what it had queued is lost; the drive reacts to the
    /// communication error (abort connection: fault, no torque) and leaves operational.
    pub fn go_bus_off(&mut self, axes: &mut impl Axes) {
        self.bus_off = true;
        self.owed.clear();
        self.state = DriveState402::Fault;
        self.raise_error(EMCY_BUS_OFF_RECOVERED);
        if self.nmt == NmtState::Operational {
            self.nmt = NmtState::PreOperational;
        }
        self.power(axes);
    }

    /// It is back on the bus at `t_ns`: its EMCY (recovered from bus-off), then its heartbeat
    /// with the state it is in now.
    pub fn recover_bus_off(&mut self, t_ns: u64) {
        self.bus_off = false;
        self.emcy(t_ns, EMCY_BUS_OFF_RECOVERED, self.od.error_register());
        self.heartbeat_now(t_ns);
    }

    /// Queues an SDO `response` to a request at `t_ns`, answered as the node answers (for a
    /// caller that scripts a wrong answer).
    pub fn answer(&mut self, t_ns: u64, response: SdoResponse) {
        let node = self.id;
        self.send(
            t_ns + self.timing.answer_ns,
            Message::SdoResponse { node, response },
        );
    }

    /// The RPDO (0..=3) a frame on `cob` is for this node now: operational, on the bus, one
    /// of its valid RPDOs on that COB-ID.
    #[must_use]
    pub fn rpdo_on(&self, cob: u16) -> Option<u16> {
        if self.nmt != NmtState::Operational || self.bus_off {
            return None;
        }
        mapping::rpdo_with(&self.od, cob)
    }

    /// RPDO `k` received at `t_ns` with `data`: unpacked by its mapping (a frame shorter than
    /// its mapping is not acted on); the controlword runs the 402 machine, the targets go to
    /// the axes.
    pub fn on_rpdo(&mut self, k: u16, t_ns: u64, data: &[u8], axes: &mut impl Axes) {
        let Some(entries) = mapping::entries(&self.od, 0x1600 + k) else {
            return;
        };
        let mut controlword = None;
        let targets = &mut self.targets;
        let whole = mapping::unpack(&entries, data, |index, sub, value| match (index, sub) {
            // 16 bits mapped.
            #[allow(clippy::cast_possible_truncation)]
            (0x6040, 0) => controlword = Some(value as u16),
            // Two's complement on the wire.
            #[allow(clippy::cast_possible_wrap)]
            (0x60FF, s) => targets[usize::from(s).min(2)] = value as i32,
            _ => {}
        });
        if !whole {
            return;
        }
        if let Some(cw) = controlword
            && self.control(cw)
        {
            self.emcy(t_ns + self.timing.answer_ns, EMCY_ERROR_RESET, 0);
        }
        self.power(axes);
    }

    /// NMT `command` at `t_ns` (to this node or to all).
    pub fn on_nmt(&mut self, command: NmtCommand, t_ns: u64, axes: &mut impl Axes) {
        if self.bus_off {
            return;
        }
        let answer = t_ns + self.timing.answer_ns;
        match command {
            NmtCommand::Start => self.set_nmt(NmtState::Operational, answer),
            NmtCommand::Stop => self.set_nmt(NmtState::Stopped, answer),
            NmtCommand::EnterPreOperational => self.set_nmt(NmtState::PreOperational, answer),
            NmtCommand::ResetNode => {
                self.reset(t_ns, Reset::Node);
                self.power(axes);
            }
            NmtCommand::ResetCommunication => self.reset(t_ns, Reset::Communication),
        }
    }

    /// An SDO `request` to this node at `t_ns`: answered [`Timing::answer_ns`] later.
    pub fn on_sdo(&mut self, request: SdoRequest, t_ns: u64) {
        if self.bus_off {
            return;
        }
        let dual = self.wheels[1].is_some() || self.wheels[2].is_some();
        let response = server::answer(&mut self.od, request, self.faults.abort, dual);
        let start = t_ns + self.timing.answer_ns;
        match response {
            // The producer runs from the write on, at the new period.
            SdoResponse::Downloaded {
                index: 0x1017,
                sub: 0,
            } => self.next_heartbeat_ns = self.first_heartbeat_ns(start),
            // The consumer (re)starts at the producer's next heartbeat.
            SdoResponse::Downloaded {
                index: 0x1016,
                sub: 1,
            } => self.last_master_heartbeat_ns = None,
            _ => {}
        }
        let node = self.id;
        self.send(start, Message::SdoResponse { node, response });
    }

    /// Node `node`'s heartbeat at `t_ns`: the master's, if this node consumes it.
    pub fn on_heartbeat(&mut self, node: NodeId, t_ns: u64) {
        if !self.bus_off && self.od.consumer().is_some_and(|(m, _)| m == node.get()) {
            self.last_master_heartbeat_ns = Some(t_ns);
        }
    }

    /// SYNC at `t_ns`: a quick stop or a slow down whose axes are at rest ends; an
    /// operational node's TPDOs go out [`Timing::answer_ns`] later.
    pub fn on_sync(&mut self, t_ns: u64, axes: &mut impl Axes) {
        self.settle(axes);
        if self.nmt != NmtState::Operational || self.bus_off {
            return;
        }
        for k in 0..4u16 {
            let Some((cob, entries)) = mapping::tpdo(&self.od, k) else {
                continue;
            };
            let frame = mapping::pack(cob, &entries, |index, sub| match (index, sub) {
                (0x6041, 0) => u32::from(self.state.statusword()),
                // Two's complement on the wire.
                #[allow(clippy::cast_sign_loss)]
                (0x606C, s) => self.wheel(s).map_or(0, |w| axes.velocity(w)) as u32,
                _ => 0,
            });
            if let Some(frame) = frame {
                self.owed.push(t_ns + self.timing.answer_ns, frame);
            }
        }
    }

    /// The wheel of sub-index `sub` (beyond 2: sub-index 2's).
    fn wheel(&self, sub: u8) -> Option<usize> {
        self.wheels[usize::from(sub).min(2)].map(usize::from)
    }

    /// Its time-outs up to `until_ns`: the master's heartbeat watched, its own produced. The
    /// consumer runs from the master's first heartbeat after the entry was written: a
    /// time-out is a communication error (once until the master is heard again; the drive's
    /// abort connection: fault), and an operational node goes pre-operational.
    pub fn run_to(&mut self, until_ns: u64, axes: &mut impl Axes) {
        if let Some((_, timeout_ms)) = self.od.consumer()
            && let Some(last) = self.last_master_heartbeat_ns
        {
            let deadline = last + u64::from(timeout_ms) * 1_000_000;
            if deadline <= until_ns {
                // The heartbeats owed before it, in the state before it.
                self.produce_heartbeats(deadline - 1);
                self.last_master_heartbeat_ns = None;
                self.fault(deadline, EMCY_HEARTBEAT, axes);
                if self.nmt == NmtState::Operational {
                    self.set_nmt(NmtState::PreOperational, deadline);
                }
            }
        }
        self.produce_heartbeats(until_ns);
    }

    /// Its next frame due by `until_ns` (after [`Self::run_to`]), with its time. A boot-up
    /// starts the heartbeat producer.
    pub fn pop_due(&mut self, until_ns: u64) -> Option<(u64, CanFrame)> {
        let (t, frame) = self.owed.pop_due(until_ns)?;
        let boot_up =
            frame.id() == Id::Standard(self.id.can_id(layout::HEARTBEAT)) && frame.data() == [0x00];
        if boot_up {
            self.next_heartbeat_ns = self.first_heartbeat_ns(t);
        }
        Some((t, frame))
    }

    /// Its frames up to `until_ns`, in time order ([`Self::run_to`], then [`Self::pop_due`]).
    pub fn feedback(
        &mut self,
        until_ns: u64,
        axes: &mut impl Axes,
        mut out: impl FnMut(u64, CanFrame),
    ) {
        self.run_to(until_ns, axes);
        while let Some((t, frame)) = self.pop_due(until_ns) {
            out(t, frame);
        }
    }

    /// Its periodic heartbeats up to `until_ns`.
    fn produce_heartbeats(&mut self, until_ns: u64) {
        while self.next_heartbeat_ns <= until_ns {
            let t = self.next_heartbeat_ns;
            self.next_heartbeat_ns = self.first_heartbeat_ns(t);
            if !self.faults.heartbeat_silent {
                let (node, state) = (self.id, self.nmt);
                self.send(t, Message::Heartbeat { node, state });
            }
        }
    }

    /// The first heartbeat of a producer (re)started at `from_ns`: a period later, or at the
    /// next multiple of the period where its timer free-runs ([`Timing::heartbeat_aligned`]);
    /// never when it is off.
    fn first_heartbeat_ns(&self, from_ns: u64) -> u64 {
        match self.od.heartbeat_period_ns() {
            Some(p) if self.timing.heartbeat_aligned => (from_ns / p + 1) * p,
            Some(p) => from_ns + p,
            None => u64::MAX,
        }
    }

    /// Its NMT state becomes `state` at `t_ns`: if it changes, the heartbeat says so at once
    /// and the producer's period starts again from there (as CANopenNode does).
    fn set_nmt(&mut self, state: NmtState, t_ns: u64) {
        if self.nmt != state {
            self.nmt = state;
            self.heartbeat_now(t_ns);
        }
    }

    /// Its heartbeat at `t_ns` (if it produces one), the next a period later.
    fn heartbeat_now(&mut self, t_ns: u64) {
        if self.od.heartbeat_period_ns().is_none() {
            return;
        }
        self.next_heartbeat_ns = self.first_heartbeat_ns(t_ns);
        if !self.faults.heartbeat_silent {
            let (node, state) = (self.id, self.nmt);
            self.send(t_ns, Message::Heartbeat { node, state });
        }
    }

    /// An error with EMCY `code` is present: its bits set in the error register; returns the
    /// register.
    fn raise_error(&mut self, code: u16) -> u8 {
        let register = self.od.error_register() | error_register(code);
        self.od.set(0x1001, 0, u32::from(register));
        register
    }

    /// Its EMCY `code` with `error_register`, counted when it goes out (a node off the bus
    /// sends nothing).
    fn emcy(&mut self, t_ns: u64, code: u16, error_register: u8) {
        self.emcy_sent += u32::from(!self.bus_off);
        let emcy = Emcy {
            error_code: code,
            error_register,
            manufacturer: [0; 5],
        };
        let node = self.id;
        self.send(t_ns, Message::Emcy { node, emcy });
    }

    fn send(&mut self, t_ns: u64, msg: Message) {
        if !self.bus_off {
            self.owed.push(t_ns, msg.to_can_frame());
        }
    }

    /// It resets at `t_ns`: [`Reset::Node`] (or a power cycle) sets its dictionary at its
    /// defaults and its drive switch on disabled, [`Reset::Communication`] only the
    /// communication area (the drive, its mode and targets are kept); pre-operational, its
    /// heartbeat consumer idle until the master's next heartbeat. What it had queued (a
    /// boot-up still owed, answers) is lost with the reset; the boot-up goes out
    /// [`Timing::boot_ns`] later (a self-starting node's operational heartbeat with it).
    pub(super) fn reset(&mut self, t_ns: u64, what: Reset) {
        self.owed.clear();
        match what {
            Reset::Node => {
                let mut fresh = Self::fresh(self.id, self.wheels, self.timing, self.options);
                (fresh.faults, fresh.bus_off) = (self.faults, self.bus_off);
                (fresh.emcy_sent, fresh.owed) = (self.emcy_sent, core::mem::take(&mut self.owed));
                *self = fresh;
            }
            Reset::Communication => {
                self.od.reset_communication(self.id);
                self.nmt = NmtState::PreOperational;
                self.next_heartbeat_ns = u64::MAX;
                self.last_master_heartbeat_ns = None;
            }
        }
        let (node, boot) = (self.id, t_ns + self.timing.boot_ns);
        // The heartbeat producer starts with the boot-up, at its default period (0: off).
        self.send(
            boot,
            Message::Heartbeat {
                node,
                state: NmtState::BootUp,
            },
        );
        if self.options.self_starting {
            self.nmt = NmtState::Operational;
            if !self.faults.heartbeat_silent {
                let state = self.nmt;
                self.send(boot, Message::Heartbeat { node, state });
            }
        }
    }
}
