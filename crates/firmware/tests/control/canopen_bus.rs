//! Scripted CiA 402 nodes for the control tests: each answers the master's NMT, SDO, SYNC
//! and RPDOs the next millisecond, runs the 402 state machine, and follows its targets at
//! once in operation enabled. A test double for the core's unit tests; the simulator's drive
//! model and the Python `canopen` peer are the real peers.

use firmware::CanFrame;
use firmware::config::{Cia402Drive, Config, Drive};
use firmware::protocol::canopen::{
    self, DriveState402, Emcy, Message, NmtCommand, NmtState, NodeId, SdoRequest, SdoResponse,
};

/// Statuswords the scripted drives report (the codec's: bit 4 voltage enabled, bit 9 remote).
pub mod sw {
    use firmware::protocol::canopen::DriveState402 as S;
    pub const SWITCH_ON_DISABLED: u16 = S::SwitchOnDisabled.statusword();
    pub const READY_TO_SWITCH_ON: u16 = S::ReadyToSwitchOn.statusword();
    pub const SWITCHED_ON: u16 = S::SwitchedOn.statusword();
    pub const OPERATION_ENABLED: u16 = S::OperationEnabled.statusword();
    pub const QUICK_STOP_ACTIVE: u16 = S::QuickStopActive.statusword();
    pub const FAULT: u16 = S::Fault.statusword();
}

/// One scripted node.
#[derive(Debug, Clone)]
pub struct ScriptedNode {
    pub id: NodeId,
    /// Its NMT state (its heartbeat says it at the next multiple of the period).
    pub nmt: NmtState,
    pub statusword: u16,
    pub mode: i8,
    last_controlword: u16,
    /// Target velocities of axes 1 and 2 (or 0), raw.
    pub targets: [i32; 2],
    /// The node sends no heartbeat (its TPDOs still flow).
    pub heartbeat_silent: bool,
    /// The node sends nothing at all.
    pub mute: bool,
    /// The node never reaches operation enabled (it stays switched on).
    pub refuses_enable: bool,
    /// An SDO transfer on this object is aborted with this code.
    pub abort: Option<((u16, u8), u32)>,
    /// SDO requests are not answered.
    pub sdo_silent: bool,
    /// Every SDO request received, in order.
    pub sdo_log: Vec<SdoRequest>,
    /// Every controlword received, with its time (µs).
    pub controlwords: Vec<(u64, u16)>,
    /// After a boot-up the node enters operational by itself (a vendor auto-start, CiA
    /// 302's "self-starting" NMT slave) and says so in a heartbeat at once, as CANopenNode
    /// does on a state change.
    pub self_starting: bool,
    /// RPDO2's COB-ID (0x1401:01; bit 31: off); reset by a boot-up to the predefined
    /// `0x300 + node`, on.
    pub rpdo2: u32,
    /// Every frame taken by RPDO2 (mapped, as the predefined set of a 402 drive, to the
    /// controlword in bytes 0-1) while operational: (time µs, controlword).
    pub rpdo2_taken: Vec<(u64, u16)>,
    /// When the RPDO2-off write was answered, µs.
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
    /// The actual velocities of its axes, raw (what the TPDOs report).
    pub actual: [i32; 2],
    /// Slowing down after a shutdown with option code 1 (`SLOW_DOWN_PER_CYCLE`).
    pub slowing: bool,
    pending: Vec<CanFrame>,
}

/// How much a scripted drive's actual velocity falls a cycle on its slow down ramp, raw.
pub const SLOW_DOWN_PER_CYCLE: i32 = 40;

/// The scripted nodes of a CiA 402 configuration.
#[derive(Debug, Clone, Default)]
pub struct ScriptedBus {
    pub nodes: Vec<ScriptedNode>,
    /// Actual velocity raw units per target raw unit.
    actual_per_target: f32,
    heartbeat_us: u64,
}

impl ScriptedBus {
    pub fn new(config: &Config) -> Self {
        let Drive::Cia402(Cia402Drive {
            node_ids,
            target_rpm_per_unit,
            actual_rpm_per_unit,
            heartbeat_ms,
            ..
        }) = config.drive
        else {
            return Self::default();
        };
        let mut nodes: Vec<ScriptedNode> = Vec::new();
        for id in node_ids {
            if nodes.iter().all(|n| n.id.get() != id) {
                nodes.push(ScriptedNode {
                    id: NodeId::new(id).unwrap(),
                    nmt: NmtState::PreOperational,
                    statusword: sw::SWITCH_ON_DISABLED,
                    mode: 0,
                    last_controlword: 0,
                    targets: [0; 2],
                    heartbeat_silent: false,
                    mute: false,
                    refuses_enable: false,
                    abort: None,
                    sdo_silent: false,
                    sdo_log: Vec::new(),
                    controlwords: Vec::new(),
                    self_starting: false,
                    rpdo2: 0x300 + u32::from(id),
                    rpdo2_taken: Vec::new(),
                    rpdo2_off_at: None,
                    mode_lag_reads: 0,
                    mode_shown_before: 0,
                    wrong_answer: None,
                    lacks_options: false,
                    shutdown_option: 0,
                    actual: [0; 2],
                    slowing: false,
                    pending: Vec::new(),
                });
            }
        }
        Self {
            nodes,
            actual_per_target: target_rpm_per_unit / actual_rpm_per_unit,
            heartbeat_us: u64::from(heartbeat_ms) * 1000,
        }
    }

    pub fn node(&mut self, id: u8) -> &mut ScriptedNode {
        self.nodes.iter_mut().find(|n| n.id.get() == id).unwrap()
    }

    /// The frames the nodes send at `now_us`: what they owe from the last step, and their
    /// heartbeats.
    pub fn feed(&mut self, now_us: u64) -> Vec<CanFrame> {
        let mut out = Vec::new();
        for n in &mut self.nodes {
            let pending = std::mem::take(&mut n.pending);
            if n.mute {
                continue;
            }
            out.extend(pending);
            if !n.heartbeat_silent && now_us.is_multiple_of(self.heartbeat_us) && now_us > 0 {
                let state = n.nmt;
                out.push(Message::Heartbeat { node: n.id, state }.to_can_frame());
            }
        }
        out
    }

    /// Takes the frames of one step (the master's, or a host's).
    pub fn take(&mut self, now_us: u64, frames: &[CanFrame]) {
        for f in frames {
            if let embedded_can::Id::Standard(id) = embedded_can::Frame::id(f) {
                for n in &mut self.nodes {
                    if n.operational() && n.rpdo2 == u32::from(id.as_raw()) {
                        let data = embedded_can::Frame::data(f);
                        let cw = u16::from_le_bytes([
                            data.first().copied().unwrap_or(0),
                            data.get(1).copied().unwrap_or(0),
                        ]);
                        n.rpdo2_taken.push((now_us, cw));
                    }
                }
            }
            let Ok(msg) = canopen::decode(f) else {
                continue;
            };
            match msg {
                Message::Nmt { command, node } => {
                    for n in &mut self.nodes {
                        if node.is_none_or(|id| id == n.id) {
                            n.nmt(command);
                        }
                    }
                }
                Message::SdoRequest { node, request } => {
                    if let Some(n) = self.nodes.iter_mut().find(|n| n.id == node) {
                        n.sdo(now_us, request);
                    }
                }
                Message::Sync { .. } => {
                    let k = self.actual_per_target;
                    for n in &mut self.nodes {
                        if !n.operational() {
                            continue;
                        }
                        let moving = n.statusword == sw::OPERATION_ENABLED;
                        if n.slowing {
                            n.actual = n
                                .actual
                                .map(|v| v.signum() * (v.abs() - SLOW_DOWN_PER_CYCLE).max(0));
                            if n.actual == [0; 2] {
                                n.slowing = false;
                                n.statusword = sw::READY_TO_SWITCH_ON;
                            }
                        } else {
                            n.actual = n.targets.map(|t| {
                                if moving {
                                    (t as f32 * k).round() as i32
                                } else {
                                    0
                                }
                            });
                        }
                        let actual = n.actual;
                        n.pending.push(
                            Message::Tpdo1 {
                                node: n.id,
                                statusword: n.statusword,
                                velocity: actual[0],
                            }
                            .to_can_frame(),
                        );
                        n.pending.push(
                            Message::Tpdo2 {
                                node: n.id,
                                velocity: actual[1],
                            }
                            .to_can_frame(),
                        );
                    }
                }
                Message::Rpdo1 {
                    node,
                    controlword,
                    target,
                } => {
                    if let Some(n) = self
                        .nodes
                        .iter_mut()
                        .find(|n| n.id == node && n.operational())
                    {
                        n.controlwords.push((now_us, controlword));
                        n.control(controlword);
                        n.targets[0] = target;
                    }
                }
                Message::Rpdo3 { node, target } => {
                    if let Some(n) = self
                        .nodes
                        .iter_mut()
                        .find(|n| n.id == node && n.operational())
                    {
                        n.targets[1] = target;
                    }
                }
                _ => {}
            }
        }
    }
}

impl ScriptedNode {
    /// Operational: PDOs flow.
    pub fn operational(&self) -> bool {
        self.nmt == NmtState::Operational
    }

    /// The node enters `state` by itself (CiA 301's error behaviour: pre-operational on a
    /// communication error) and says so in a heartbeat at once.
    pub fn enter(&mut self, state: NmtState) {
        self.nmt = state;
        self.pending.push(
            Message::Heartbeat {
                node: self.id,
                state,
            }
            .to_can_frame(),
        );
    }

    /// A boot-up: pre-operational, switch on disabled, the mode forgotten, the PDOs
    /// predefined (a self-starting node then enters operational at once).
    pub fn reboot(&mut self) {
        self.nmt = NmtState::PreOperational;
        self.statusword = sw::SWITCH_ON_DISABLED;
        self.mode = 0;
        self.targets = [0; 2];
        self.actual = [0; 2];
        self.slowing = false;
        self.rpdo2 = 0x300 + u32::from(self.id.get());
        self.rpdo2_off_at = None;
        self.pending.push(
            Message::Heartbeat {
                node: self.id,
                state: NmtState::BootUp,
            }
            .to_can_frame(),
        );
        if self.self_starting {
            self.enter(NmtState::Operational);
        }
    }

    /// A drive fault with its EMCY.
    pub fn fault(&mut self, code: u16) {
        self.statusword = sw::FAULT;
        self.pending.push(
            Message::Emcy {
                node: self.id,
                emcy: Emcy {
                    error_code: code,
                    error_register: 0x01,
                    manufacturer: [0; 5],
                },
            }
            .to_can_frame(),
        );
    }

    fn nmt(&mut self, command: NmtCommand) {
        match command {
            NmtCommand::Start => self.nmt = NmtState::Operational,
            NmtCommand::Stop => self.nmt = NmtState::Stopped,
            NmtCommand::EnterPreOperational => self.nmt = NmtState::PreOperational,
            NmtCommand::ResetNode | NmtCommand::ResetCommunication => self.reboot(),
        }
    }

    fn sdo(&mut self, now_us: u64, request: SdoRequest) {
        self.sdo_log.push(request);
        if self.sdo_silent {
            return;
        }
        let (index, sub) = request.object();
        let response = match (self.abort, request) {
            (Some((object, code)), _) if object == (index, sub) => {
                SdoResponse::Abort { index, sub, code }
            }
            (_, SdoRequest::Abort { .. }) => return,
            (_, SdoRequest::Download { .. }) if self.wrong_answer == Some((index, sub)) => {
                SdoResponse::Uploaded {
                    index,
                    sub,
                    value: 0,
                    size: 4,
                }
            }
            (_, SdoRequest::Download { .. })
                if self.lacks_options && matches!(index, 0x605B | 0x605C) =>
            {
                SdoResponse::Abort {
                    index,
                    sub,
                    code: 0x0602_0000,
                }
            }
            (_, SdoRequest::Upload { .. }) if (index, sub) == (0x6061, 0) => {
                let shown = if self.mode_lag_reads > 0 {
                    self.mode_lag_reads -= 1;
                    self.mode_shown_before
                } else {
                    self.mode
                };
                SdoResponse::Uploaded {
                    index,
                    sub,
                    value: u32::from(shown as u8),
                    size: 1,
                }
            }
            (_, SdoRequest::Upload { .. }) if (index, sub) == (0x1000, 0) => {
                SdoResponse::Uploaded {
                    index,
                    sub,
                    value: 0x0002_0192,
                    size: 4,
                }
            }
            (_, SdoRequest::Download { value, .. }) => {
                if (index, sub) == (0x6060, 0) {
                    self.mode = value as i8;
                }
                if (index, sub) == (0x605B, 0) {
                    self.shutdown_option = value;
                }
                if (index, sub) == (0x1401, 1) {
                    self.rpdo2 = value;
                    if value & 0x8000_0000 != 0 {
                        self.rpdo2_off_at = Some(now_us);
                    }
                }
                SdoResponse::Downloaded { index, sub }
            }
            _ => SdoResponse::Abort {
                index,
                sub,
                code: 0x0602_0000,
            },
        };
        self.pending.push(
            Message::SdoResponse {
                node: self.id,
                response,
            }
            .to_can_frame(),
        );
    }

    /// The CiA 402 state machine (the codec's drive side), on each controlword received.
    fn control(&mut self, cw: u16) {
        let state = DriveState402::from_statusword(self.statusword)
            .unwrap_or(DriveState402::SwitchOnDisabled);
        if state == DriveState402::OperationEnabled
            && cw & 0x8F == 0x06
            && self.shutdown_option == 1
        {
            // Transition 8 with option code 1: slow down on the ramp (still operation
            // enabled), then ready to switch on.
            self.slowing = true;
            self.last_controlword = cw;
            return;
        }
        if self.slowing {
            self.last_controlword = cw;
            return;
        }
        let may_enable = self.mode == 3 && !self.refuses_enable;
        self.statusword = state
            .on_controlword(cw, self.last_controlword, may_enable)
            .statusword();
        self.last_controlword = cw;
    }
}
