//! The control tests' CiA 402 nodes: the firmware crate's drive double
//! (`protocol::canopen::drive`), stepped once a millisecond (answers, boot-ups and TPDOs the
//! next millisecond; heartbeats at the multiples of their period; quick stop kept active, as
//! a drive with option code 5-8), on axes that follow their target at once and slow down by
//! `SLOW_DOWN_PER_CYCLE` a SYNC.
//!
//! Each [`ScriptedNode`] is a drive with a script around it: its public fields are what a test
//! reads and writes. The faults and the maker's options written there, and a state written
//! over (`statusword`, `nmt`), are given to the drive before each exchange; the drive's state
//! is read back after it. The rest is the harness's own: a node that is mute, does not answer
//! SDO, answers one wrongly or shows the mode late, and the logs of what it received.

use embedded_can::{Frame, Id};
use firmware::CanFrame;
use firmware::config::{Cia402Drive, Config, Drive};
use firmware::protocol::canopen::drive::{
    Axes, AxisCommand, Drive402, Drives402, Faults, Options, Timing,
};
use firmware::protocol::canopen::{
    self, DriveState402, Message, NmtState, NodeId, SdoRequest, SdoResponse,
};

/// Statuswords the scripted drives report (the codec's: bit 4 voltage enabled, bit 9 remote).
pub mod sw {
    use firmware::protocol::canopen::DriveState402 as S;
    pub const SWITCH_ON_DISABLED: u16 = S::SwitchOnDisabled.statusword();
    pub const READY_TO_SWITCH_ON: u16 = S::ReadyToSwitchOn.statusword();
    pub const SWITCHED_ON: u16 = S::SwitchedOn.statusword();
    pub const OPERATION_ENABLED: u16 = S::OperationEnabled.statusword();
    pub const QUICK_STOP_ACTIVE: u16 = S::QuickStopActive.statusword();
}

/// How much a scripted drive's actual velocity falls a cycle on its slow down ramp, raw.
pub const SLOW_DOWN_PER_CYCLE: i32 = 40;

/// Once a millisecond, heartbeats on the multiples of their period.
const TIMING: Timing = Timing {
    heartbeat_aligned: true,
    ..Timing::NEXT_MS
};

/// A node's axes, by wheel: they follow a velocity target at once (actual raw units per
/// target raw unit: `per_target`), slow down by [`SLOW_DOWN_PER_CYCLE`] a SYNC, and stop at
/// once in quick stop or without torque.
#[derive(Debug, Clone)]
struct ScriptedAxes {
    command: [AxisCommand; 4],
    actual: [i32; 4],
    per_target: f32,
}

impl ScriptedAxes {
    /// One SYNC cycle of the axes.
    fn cycle(&mut self) {
        for (a, c) in self.actual.iter_mut().zip(self.command) {
            *a = match c {
                AxisCommand::Velocity(t) => (t as f32 * self.per_target).round() as i32,
                AxisCommand::SlowDown => a.signum() * (a.abs() - SLOW_DOWN_PER_CYCLE).max(0),
                AxisCommand::QuickStop | AxisCommand::Off => 0,
            };
        }
    }
}

impl Axes for ScriptedAxes {
    fn command(&mut self, wheel: usize, command: AxisCommand) {
        self.command[wheel] = command;
    }

    fn velocity(&self, wheel: usize) -> i32 {
        self.actual[wheel]
    }

    fn at_rest(&self, wheel: usize) -> bool {
        self.actual[wheel] == 0
    }
}

/// One scripted node.
#[derive(Debug, Clone)]
pub struct ScriptedNode {
    pub id: NodeId,
    /// The drive.
    pub drive: Drive402,
    /// Its NMT state (its heartbeat says it at the next multiple of the period); written
    /// over, the drive is put there without a heartbeat.
    pub nmt: NmtState,
    /// Its statusword; written over, the drive is put in that state.
    pub statusword: u16,
    /// The mode of operation (0x6060), as last written.
    pub mode: i8,
    /// The node sends no heartbeat (its TPDOs still flow).
    pub heartbeat_silent: bool,
    /// The node sends nothing at all.
    pub mute: bool,
    /// The node never reaches operation enabled (it stays switched on).
    pub refuses_enable: bool,
    /// An SDO download to this object is aborted with this code.
    pub abort: Option<((u16, u8), u32)>,
    /// SDO requests are not answered.
    pub sdo_silent: bool,
    /// Every SDO request received, in order.
    pub sdo_log: Vec<SdoRequest>,
    /// Every controlword received while operational, with its time (µs).
    pub controlwords: Vec<(u64, u16)>,
    /// After a boot-up the node enters operational by itself (a vendor auto-start, CiA
    /// 302's "self-starting" NMT slave) and says so in a heartbeat at once.
    pub self_starting: bool,
    /// RPDO2's COB-ID (0x1401:01; bit 31: off); reset by a boot-up to the predefined
    /// `0x300 + node`, on.
    pub rpdo2: u32,
    /// Every frame on RPDO2's COB-ID while it is on and the node operational (a 402 drive's
    /// predefined set maps it to the controlword in bytes 0-1): (time µs, controlword).
    pub rpdo2_taken: Vec<(u64, u16)>,
    /// When the RPDO2-off write was taken, µs.
    pub rpdo2_off_at: Option<u64>,
    /// Reads of 0x6061 that still show the previous mode (the mode takes effect late).
    pub mode_lag_reads: u32,
    /// The mode 0x6061 shows until `mode_lag_reads` reads are done.
    pub mode_shown_before: i8,
    /// A download to this object is answered with an upload response (the wrong command).
    pub wrong_answer: Option<(u16, u8)>,
    /// The node has no 0x605B / 0x605C (aborted "object does not exist").
    pub lacks_options: bool,
    /// 0x605B, the shutdown option code (1: slow down on the ramp, then disable).
    pub shutdown_option: u32,
    /// The actual velocities of its axes (sub-index 0 or 1, and 2), raw: what the TPDOs
    /// report.
    pub actual: [i32; 2],
    axes: ScriptedAxes,
    /// The drive's NMT state and statusword as last read back.
    seen: (NmtState, u16),
    /// The time of the last exchange, ns.
    now_ns: u64,
}

/// The scripted nodes of a CiA 402 configuration.
#[derive(Debug, Clone, Default)]
pub struct ScriptedBus {
    pub nodes: Vec<ScriptedNode>,
}

impl ScriptedBus {
    pub fn new(config: &Config) -> Self {
        let Drive::Cia402(Cia402Drive {
            target_rpm_per_unit,
            actual_rpm_per_unit,
            ..
        }) = config.drive
        else {
            return Self::default();
        };
        let options = Options {
            quick_stop_stays: true,
            ..Options::default()
        };
        let drives = Drives402::new(config, TIMING, options);
        let axes = ScriptedAxes {
            command: [AxisCommand::Off; 4],
            actual: [0; 4],
            per_target: target_rpm_per_unit / actual_rpm_per_unit,
        };
        let nodes = drives
            .nodes()
            .iter()
            .map(|drive| ScriptedNode::new(drive.clone(), axes.clone()))
            .collect();
        Self { nodes }
    }

    pub fn node(&mut self, id: u8) -> &mut ScriptedNode {
        self.nodes.iter_mut().find(|n| n.id.get() == id).unwrap()
    }

    /// The frames the nodes send at `now_us`: what they owe, their heartbeats.
    pub fn feed(&mut self, now_us: u64) -> Vec<CanFrame> {
        let mut out = Vec::new();
        for n in &mut self.nodes {
            n.exchange(now_us, |n| {
                n.drive.feedback(n.now_ns, &mut n.axes, |_, f| {
                    if !n.mute {
                        out.push(f);
                    }
                });
            });
        }
        out
    }

    /// Takes the frames of one step (the master's, or a host's).
    pub fn take(&mut self, now_us: u64, frames: &[CanFrame]) {
        for f in frames {
            for n in &mut self.nodes {
                n.exchange(now_us, |n| n.watch(now_us, f));
            }
            self.route(now_us, f);
        }
    }

    /// One frame to the nodes it is for: PDOs first (the first node with a valid RPDO on
    /// its id), then NMT, SYNC (the axes' cycle first), SDO and heartbeats.
    fn route(&mut self, now_us: u64, f: &CanFrame) {
        let Id::Standard(id) = f.id() else { return };
        for n in &mut self.nodes {
            if let Some(k) = n.drive.rpdo_on(id.as_raw()) {
                n.exchange(now_us, |n| {
                    let t = n.now_ns;
                    n.drive.on_rpdo(k, t, f.data(), &mut n.axes)
                });
                return;
            }
        }
        let Ok(msg) = canopen::decode(f) else { return };
        for n in &mut self.nodes {
            n.exchange(now_us, |n| {
                let t = n.now_ns;
                match msg {
                    Message::Nmt { command, node } if node.is_none_or(|id| id == n.id) => {
                        n.drive.on_nmt(command, t, &mut n.axes);
                    }
                    Message::Sync { .. } => {
                        n.axes.cycle();
                        n.drive.on_sync(t, &mut n.axes);
                    }
                    Message::SdoRequest { node, request } if node == n.id => n.sdo(request),
                    Message::Heartbeat { node, .. } => n.drive.on_heartbeat(node, t),
                    _ => {}
                }
            });
        }
    }
}

impl ScriptedNode {
    fn new(drive: Drive402, axes: ScriptedAxes) -> Self {
        let mut n = Self {
            id: drive.id(),
            nmt: drive.nmt(),
            statusword: drive.statusword(),
            seen: (drive.nmt(), drive.statusword()),
            drive,
            mode: 0,
            heartbeat_silent: false,
            mute: false,
            refuses_enable: false,
            abort: None,
            sdo_silent: false,
            sdo_log: Vec::new(),
            controlwords: Vec::new(),
            self_starting: false,
            rpdo2: 0,
            rpdo2_taken: Vec::new(),
            rpdo2_off_at: None,
            mode_lag_reads: 0,
            mode_shown_before: 0,
            wrong_answer: None,
            lacks_options: false,
            shutdown_option: 0,
            actual: [0; 2],
            axes,
            now_ns: 0,
        };
        n.read_back();
        n
    }

    /// Operational: PDOs flow.
    pub fn operational(&self) -> bool {
        self.nmt == NmtState::Operational
    }

    /// The node enters `state` by itself (CiA 301's error behaviour: pre-operational on a
    /// communication error) and says so in a heartbeat at once.
    pub fn enter(&mut self, state: NmtState) {
        self.exchange_now(|n| n.drive.enter(state, n.now_ns));
    }

    /// A power cycle: boot-up, pre-operational, switch on disabled, the dictionary at its
    /// defaults (a self-starting node then enters operational at once).
    pub fn reboot(&mut self) {
        self.exchange_now(|n| n.drive.reboot(n.now_ns, &mut n.axes));
    }

    /// A drive fault with its EMCY.
    pub fn fault(&mut self, code: u16) {
        self.exchange_now(|n| n.drive.fault(n.now_ns, code, &mut n.axes));
    }

    /// `f` with the drive at `now_us`: the script given to it before, its state read after.
    fn exchange(&mut self, now_us: u64, f: impl FnOnce(&mut Self)) {
        self.now_ns = now_us * 1000;
        self.exchange_now(f);
    }

    fn exchange_now(&mut self, f: impl FnOnce(&mut Self)) {
        self.drive.set_faults(Faults {
            heartbeat_silent: self.heartbeat_silent,
            refuses_enable: self.refuses_enable,
            abort: self.abort,
        });
        let mut options = self.drive.options();
        options.lacks_option_codes = self.lacks_options;
        options.self_starting = self.self_starting;
        self.drive.set_options(options);
        if self.nmt != self.seen.0 {
            self.drive.set_nmt_quietly(self.nmt);
        }
        if self.statusword != self.seen.1
            && let Some(state) = DriveState402::from_statusword(self.statusword)
        {
            self.drive.set_state(state, &mut self.axes);
        }
        f(self);
        self.read_back();
    }

    /// The drive's state into the script's fields.
    fn read_back(&mut self) {
        let d = &self.drive;
        (self.nmt, self.statusword) = (d.nmt(), d.statusword());
        self.seen = (self.nmt, self.statusword);
        self.mode = d.entry(0x6060, 0).unwrap_or(0) as u8 as i8;
        self.rpdo2 = d.entry(0x1401, 1).unwrap_or(0);
        self.shutdown_option = d.entry(0x605B, 0).unwrap_or(0);
        let [single, first, second] = d.wheels();
        let actual = |w: Option<u8>| w.map_or(0, |w| self.axes.actual[usize::from(w)]);
        self.actual = [actual(single.or(first)), actual(second)];
    }

    /// What the harness logs of a frame before the node takes it.
    fn watch(&mut self, now_us: u64, f: &CanFrame) {
        if let Id::Standard(id) = f.id()
            && self.operational()
            && self.rpdo2 == u32::from(id.as_raw())
        {
            let data = f.data();
            let byte = |i: usize| data.get(i).copied().unwrap_or(0);
            self.rpdo2_taken
                .push((now_us, u16::from_le_bytes([byte(0), byte(1)])));
        }
        if let Ok(Message::Rpdo1 {
            node, controlword, ..
        }) = canopen::decode(f)
            && node == self.id
            && self.operational()
        {
            self.controlwords.push((now_us, controlword));
        }
    }

    /// An SDO request: logged, then answered by the drive unless the script says otherwise.
    fn sdo(&mut self, request: SdoRequest) {
        self.sdo_log.push(request);
        if self.sdo_silent {
            return;
        }
        let (index, sub) = request.object();
        let t = self.now_ns;
        match request {
            SdoRequest::Download { .. } if self.wrong_answer == Some((index, sub)) => {
                let response = SdoResponse::Uploaded {
                    index,
                    sub,
                    value: 0,
                    size: 4,
                };
                self.drive.answer(t, response);
            }
            SdoRequest::Upload { .. } if (index, sub) == (0x6061, 0) && self.mode_lag_reads > 0 => {
                self.mode_lag_reads -= 1;
                let value = u32::from(self.mode_shown_before as u8);
                let response = SdoResponse::Uploaded {
                    index,
                    sub,
                    value,
                    size: 1,
                };
                self.drive.answer(t, response);
            }
            SdoRequest::Download { value, .. } => {
                self.drive.on_sdo(request, t);
                let off = (index, sub) == (0x1401, 1) && value & 0x8000_0000 != 0;
                if off && self.drive.entry(0x1401, 1) == Some(value) {
                    self.rpdo2_off_at = Some(t / 1000);
                }
            }
            _ => self.drive.on_sdo(request, t),
        }
    }
}
