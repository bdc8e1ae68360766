//! Scripted CiA 402 nodes for the control tests: each answers the master's NMT, SDO, SYNC
//! and RPDOs the next millisecond, runs the 402 state machine, and follows its targets at
//! once in operation enabled. A test double for the core's unit tests; the simulator's drive
//! model and the Python `canopen` peer are the real peers.

use firmware::CanFrame;
use firmware::config::{Config, Drive};
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
    pending: Vec<CanFrame>,
}

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
        let Drive::Cia402 {
            node_ids,
            target_rpm_per_unit,
            actual_rpm_per_unit,
            heartbeat_ms,
            ..
        } = config.drive
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

    /// Takes the master's frames of one step.
    pub fn take(&mut self, now_us: u64, frames: &[CanFrame]) {
        for f in frames {
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
                        n.sdo(request);
                    }
                }
                Message::Sync { .. } => {
                    let k = self.actual_per_target;
                    for n in &mut self.nodes {
                        if !n.operational() {
                            continue;
                        }
                        let moving = n.statusword == sw::OPERATION_ENABLED;
                        let actual = n.targets.map(|t| {
                            if moving {
                                (t as f32 * k).round() as i32
                            } else {
                                0
                            }
                        });
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

    /// A boot-up: pre-operational, switch on disabled, the mode forgotten.
    pub fn reboot(&mut self) {
        self.nmt = NmtState::PreOperational;
        self.statusword = sw::SWITCH_ON_DISABLED;
        self.mode = 0;
        self.targets = [0; 2];
        self.pending.push(
            Message::Heartbeat {
                node: self.id,
                state: NmtState::BootUp,
            }
            .to_can_frame(),
        );
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

    fn sdo(&mut self, request: SdoRequest) {
        self.sdo_log.push(request);
        if self.sdo_silent {
            return;
        }
        let (index, sub) = request.object();
        let response = match (self.abort, request) {
            (Some((object, code)), _) if object == (index, sub) => {
                SdoResponse::Abort { index, sub, code }
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
        let may_enable = self.mode == 3 && !self.refuses_enable;
        self.statusword = state
            .on_controlword(cw, self.last_controlword, may_enable)
            .statusword();
        self.last_controlword = cw;
    }
}
