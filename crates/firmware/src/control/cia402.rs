//! CANopen CiA 402 drives, with the core as their master: each node configured by SDO after
//! its boot-up and started, then SYNC and the targets every cycle, the 402 enable sequence on
//! an enable, the statusword and actual velocities into the wheels, the heartbeats watched
//! both ways (`docs/protocol.md`, "CANopen CiA 402"; `docs/control.md`, "Faults").
//!
//! Nodes are configured in parallel, one SDO transfer in flight per node. A node's state is
//! its [`Phase`] (reset owed, waiting for boot-up, configuring, started) and its [`Command`]
//! (what its controlword asks); anything that faults the robot is kept as the node's
//! [`DriveIssue`] until the host's reset, and [`Cia402::issue`] gives the latest for logs.
//! A started node's heartbeat must say operational; the host's reset starts again a node
//! that left it (or resets and configures it again if its heartbeat was lost meanwhile).

use core::fmt;

use embedded_can::Frame;
use kinematics::WheelSpeeds;

use super::time::Every;
use super::{Instant, Outbox, Wheel, push};
use crate::protocol::DecodeError;
use crate::protocol::canopen::{
    self, DriveState402, Message, NmtCommand, NmtState, NodeId, STATUSWORD_FAULT, SdoRequest,
    SdoResponse, abort_code, controlword,
};
use crate::protocol::robot::{Fault, RobotState};
use crate::protocol::wire;

/// CiA 402: an SDO transfer of the configuration not answered within this long fails, µs.
pub const CANOPEN_SDO_TIMEOUT_US: u64 = 200_000;
/// CiA 402: an enable step (shutdown, switch on, enable operation) whose state the statusword
/// does not show within this long fails, µs.
pub const CIA402_TRANSITION_TIMEOUT_US: u64 = 250_000;
/// CiA 402: statuswords received until this long after a fault reset was sent may predate
/// it: their fault bit is ignored, µs.
pub const CIA402_RESET_GRACE_US: u64 = 20_000;
/// CANopen: heartbeats received until this long after NMT start was sent may predate it: a
/// state other than operational in them is ignored, µs.
pub const CANOPEN_NMT_GRACE_US: u64 = 20_000;

/// CiA 402: the mode of operation display (0x6061) is read again this long after it did not
/// show profile velocity yet, µs.
pub const CIA402_MODE_POLL_US: u64 = 10_000;
/// CiA 402: reads of the mode of operation display (0x6061) before a node that does not show
/// profile velocity fails its configuration (`CIA402_MODE_POLL_US` apart: half a second).
pub const CIA402_MODE_POLLS: u8 = 50;

/// The device type's profile (object 0x1000, low 16 bits) of a CiA 402 drive.
const DEVICE_PROFILE_402: u32 = 402;
/// Most SDO transfers of one node's configuration (a dual-axis node's 37).
const SETUP_MAX: usize = 40;
/// The predefined RPDO2 of node N is `0x300 + N` (CiA 301), the robot protocol's block.
const RPDO2_FUNCTION: u16 = 0x300;
/// Profile velocity mode (objects 0x6060 and 0x6061).
const MODE_PROFILE_VELOCITY: u32 = 3;
/// Shutdown (0x605B) and disable operation (0x605C) option code 1: slow down on the slow
/// down ramp, then disable the drive function.
const OPTION_SLOW_DOWN: u32 = 1;

/// Why a CiA 402 drive faulted the robot, with what the bus said: for logs and the runner's
/// report (`STATUS.fault` carries only the [`Fault`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DriveIssue {
    /// The drive aborted an SDO transfer of its configuration.
    SdoAbort {
        /// The node.
        node: u8,
        /// The object, index and sub-index.
        object: (u16, u8),
        /// The abort code.
        code: u32,
    },
    /// An SDO transfer of the configuration was not answered in time.
    SdoTimeout {
        /// The node.
        node: u8,
        /// The object.
        object: (u16, u8),
    },
    /// The device type (0x1000) is not a CiA 402 drive's.
    NotADrive {
        /// The node.
        node: u8,
        /// The device type read.
        device_type: u32,
    },
    /// An enable step timed out.
    TransitionTimeout {
        /// The node.
        node: u8,
        /// The controlword sent.
        controlword: u16,
        /// The last statusword received, if any.
        statusword: Option<u16>,
    },
    /// No heartbeat within the consumer time.
    HeartbeatLost {
        /// The node.
        node: u8,
    },
    /// A boot-up after the node was configured.
    Rebooted {
        /// The node.
        node: u8,
    },
    /// A started node's heartbeat reports a state other than operational.
    NotOperational {
        /// The node.
        node: u8,
        /// The NMT state it reports.
        state: NmtState,
    },
    /// A node reported itself operational (heartbeat or TPDO) after its boot-up, before the
    /// master started it: a self-starting drive, whose predefined RPDO2 (`0x300 + node`)
    /// takes the robot protocol's frames from its every power-on.
    SelfStarted {
        /// The node.
        node: u8,
    },
    /// The mode of operation display (0x6061) did not show profile velocity (3).
    ModeNotShown {
        /// The node.
        node: u8,
        /// The last mode read.
        mode: i8,
    },
    /// The statusword shows a fault, or (enabled) a state other than operation enabled.
    DriveFault {
        /// The node.
        node: u8,
        /// The statusword.
        statusword: u16,
        /// The node's last EMCY error code (0 if none came).
        emcy_code: u16,
    },
}

impl DriveIssue {
    /// The fault it reports.
    #[must_use]
    pub const fn fault(&self) -> Fault {
        match self {
            Self::SdoAbort { .. }
            | Self::SdoTimeout { .. }
            | Self::NotADrive { .. }
            | Self::ModeNotShown { .. } => Fault::DriveSetup,
            Self::TransitionTimeout { .. } => Fault::DriveTransition,
            Self::HeartbeatLost { .. } => Fault::DriveSilent,
            Self::Rebooted { .. } => Fault::DriveRebooted,
            Self::NotOperational { .. } | Self::SelfStarted { .. } => Fault::DriveNmt,
            Self::DriveFault { .. } => Fault::DriveError,
        }
    }
}

impl fmt::Display for DriveIssue {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Self::SdoAbort {
                node,
                object: (index, sub),
                code,
            } => {
                write!(
                    f,
                    "node {node}: SDO abort 0x{code:08X} on 0x{index:04X}:{sub:02X}"
                )?;
                if let Some(text) = canopen::abort_text(code) {
                    write!(f, " ({text})")?;
                }
                Ok(())
            }
            Self::SdoTimeout {
                node,
                object: (index, sub),
            } => write!(
                f,
                "node {node}: no SDO answer on 0x{index:04X}:{sub:02X} within {} ms",
                CANOPEN_SDO_TIMEOUT_US / 1000
            ),
            Self::NotADrive { node, device_type } => write!(
                f,
                "node {node}: device type 0x{device_type:08X} is not a CiA 402 drive"
            ),
            Self::TransitionTimeout {
                node,
                controlword,
                statusword,
            } => {
                write!(
                    f,
                    "node {node}: controlword 0x{controlword:04X} not followed within {} ms, ",
                    CIA402_TRANSITION_TIMEOUT_US / 1000
                )?;
                match statusword {
                    Some(sw) => write!(f, "last statusword 0x{sw:04X} ({})", state_name(sw)),
                    None => f.write_str("no statusword received"),
                }
            }
            Self::HeartbeatLost { node } => write!(f, "node {node}: heartbeat lost"),
            Self::Rebooted { node } => write!(f, "node {node}: booted again, configured anew"),
            Self::NotOperational { node, state } => {
                write!(f, "node {node}: NMT {}", state.as_str())
            }
            Self::SelfStarted { node } => write!(
                f,
                "node {node}: NMT OPERATIONAL before NMT start (a self-starting drive: its \
                 RPDO2 0x{:03X} is in the robot's block)",
                RPDO2_FUNCTION + u16::from(node)
            ),
            Self::ModeNotShown { node, mode } => write!(
                f,
                "node {node}: mode of operation display 0x6061 = {mode}, not 3 (profile \
                 velocity), after {} reads",
                CIA402_MODE_POLLS
            ),
            Self::DriveFault {
                node,
                statusword,
                emcy_code,
            } => write!(
                f,
                "node {node}: statusword 0x{statusword:04X} ({}), last EMCY 0x{emcy_code:04X}",
                state_name(statusword)
            ),
        }
    }
}

fn state_name(sw: u16) -> &'static str {
    DriveState402::from_statusword(sw).map_or("undefined", DriveState402::as_str)
}

/// Where a node is in its life on the bus.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// NMT reset communication owed (the master's first step, or a recovery).
    Reset,
    /// Waiting for its boot-up (after the master's NMT reset).
    Boot,
    /// Being configured: transfer `step` of its sequence, sent at `sent` (`None`: owed).
    Setup { step: u8, sent: Option<Instant> },
    /// Configured; NMT start owed (`start_owed`) or sent.
    Started { start_owed: bool },
    /// Its configuration failed: left alone until it boots again.
    Failed,
}

/// What a node's controlword asks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Command {
    /// Shutdown (0x06): ready to switch on, no torque.
    Shutdown,
    /// Quick stop (0x02): stop on the drive's quick-stop ramp, then no torque.
    QuickStop,
    /// Enabling: `controlword` sent since `since` (`None`: not sent yet), until the
    /// statusword shows its state.
    Enabling {
        controlword: u16,
        since: Option<Instant>,
    },
    /// Operation enabled: following the targets.
    Enabled,
}

/// One CANopen node (one or two wheels).
#[derive(Debug, Clone, Copy)]
struct Node {
    id: NodeId,
    /// Two axes (sub-indices 1 and 2) rather than one (sub-index 0).
    dual: bool,
    phase: Phase,
    command: Command,
    /// The last statusword (none since a boot-up or a fault reset).
    statusword: Option<u16>,
    last_heartbeat: Option<Instant>,
    /// Fault reset owed (sent once, in the next cycle).
    fault_reset: bool,
    /// When the last fault reset was owed or sent (see [`CIA402_RESET_GRACE_US`]).
    reset_at: Option<Instant>,
    /// The error code of the node's last EMCY.
    last_emcy: u16,
    /// What faults the robot, until the host's reset.
    issue: Option<DriveIssue>,
    /// The NMT state of its last heartbeat since it was started (`None`: none yet, or only
    /// ones that may predate the start).
    nmt: Option<NmtState>,
    /// When NMT start was last sent.
    started_at: Option<Instant>,
    /// Started once at least: a reset and configuration after that is a recovery.
    was_started: bool,
    /// Its heartbeat was never lost since its start: its configuration is intact.
    heard: bool,
    /// Its RPDO2 is known off (its write acknowledged) since its last reset or boot-up.
    rpdo2_off: bool,
    /// Booted since the master's last reset and not started since: a node that says it is
    /// operational now started itself.
    fresh: bool,
    /// NMT enter pre-operational owed (a self-started node).
    preop_owed: bool,
    /// An SDO abort (timeout) owed, on this object.
    abort_owed: Option<(u16, u8)>,
    /// Reads of 0x6061 that did not show profile velocity; the next not before `poll_at`.
    polls: u8,
    poll_at: Option<Instant>,
}

impl Node {
    const fn new(id: NodeId, dual: bool) -> Self {
        Self {
            id,
            dual,
            phase: Phase::Reset,
            command: Command::Shutdown,
            statusword: None,
            last_heartbeat: None,
            fault_reset: false,
            reset_at: None,
            last_emcy: 0,
            issue: None,
            nmt: None,
            started_at: None,
            was_started: false,
            heard: false,
            rpdo2_off: false,
            fresh: false,
            preop_owed: false,
            abort_owed: None,
            polls: 0,
            poll_at: None,
        }
    }

    /// Keeps the first issue until the reset.
    fn raise(&mut self, issue: DriveIssue) {
        if self.issue.is_none() {
            self.issue = Some(issue);
        }
    }

    /// The node showed it is operational (a TPDO, an operational heartbeat): if it booted
    /// and was not started since, it started itself; it is refused (the issue, once a
    /// boot) and sent to pre-operational.
    fn started_itself(&mut self) -> Option<DriveIssue> {
        let unstarted = matches!(
            self.phase,
            Phase::Setup { .. } | Phase::Started { start_owed: true }
        );
        if !(self.fresh && unstarted) {
            return None;
        }
        self.fresh = false;
        self.preop_owed = true;
        let issue = DriveIssue::SelfStarted {
            node: self.id.get(),
        };
        self.raise(issue);
        Some(issue)
    }

    /// The controlword of this cycle (a fault reset is sent once).
    fn controlword(&mut self) -> u16 {
        if core::mem::take(&mut self.fault_reset) {
            return controlword::FAULT_RESET;
        }
        let state = self.statusword.and_then(DriveState402::from_statusword);
        match self.command {
            // A drive whose quick stop option (0x605A, 5-8) keeps it in quick stop active
            // leaves it only by disable voltage (transition 12); 0x06 is no transition
            // there, whether shutting down or starting an enable.
            Command::Shutdown
            | Command::Enabling {
                controlword: controlword::SHUTDOWN,
                ..
            } if state == Some(DriveState402::QuickStopActive) => controlword::DISABLE_VOLTAGE,
            Command::Shutdown => controlword::SHUTDOWN,
            Command::QuickStop => controlword::QUICK_STOP,
            Command::Enabling { controlword, .. } => controlword,
            Command::Enabled => controlword::ENABLE_OPERATION,
        }
    }
}

/// The parameters of a [`Cia402`] (from `Drive::Cia402` and the timing).
#[derive(Debug, Clone, Copy)]
pub(super) struct Params {
    pub node_ids: [u8; 4],
    pub axes: [u8; 4],
    pub gear_ratio: f32,
    pub target_rpm_per_unit: f32,
    pub actual_rpm_per_unit: f32,
    pub master_node: u8,
    pub heartbeat_ms: u16,
    pub heartbeat_timeout_ms: u16,
    pub control_hz: u32,
    pub cycle_hz: u32,
}

/// The drives of the four wheels.
#[derive(Debug, Clone)]
pub(super) struct Cia402 {
    nodes: heapless::Vec<Node, 4>,
    /// Each wheel's node (index into `nodes`) and whether it is the node's second axis.
    wheel_node: [(usize, bool); 4],
    /// Wheel rad/s per raw unit of target velocity.
    target_scale: f64,
    /// Wheel rad/s per raw unit of actual velocity.
    actual_scale: f32,
    /// Seconds per cycle: each TPDO's velocity counts for one.
    cycle_s: f32,
    master: Option<NodeId>,
    heartbeat_ms: u16,
    heartbeat_timeout_ms: u16,
    heartbeat_clock: Every,
    /// The time of the step being run.
    now: Instant,
    emcy_count: u32,
    /// The latest issue of any node (kept after the reset, for the report).
    latest: Option<DriveIssue>,
    /// The master's boot-up was sent (at its first step).
    booted: bool,
}

impl Cia402 {
    /// The nodes of a validated configuration.
    pub(super) fn new(p: &Params) -> Self {
        let mut nodes = heapless::Vec::<Node, 4>::new();
        let mut wheel_node = [(0, false); 4];
        for ((slot, &id), &axis) in wheel_node.iter_mut().zip(&p.node_ids).zip(&p.axes) {
            let index = nodes.iter().position(|n| n.id.get() == id).or_else(|| {
                // Validated ids; four wheels give at most four nodes.
                let node = Node::new(NodeId::new(id)?, axis != 0);
                nodes.push(node).ok()?;
                Some(nodes.len() - 1)
            });
            *slot = (index.unwrap_or(usize::MAX), axis == 2);
        }
        let rpm_to_wheel = core::f64::consts::TAU / 60.0 / f64::from(p.gear_ratio);
        Self {
            nodes,
            wheel_node,
            target_scale: f64::from(p.target_rpm_per_unit) * rpm_to_wheel,
            actual_scale: (f64::from(p.actual_rpm_per_unit) * rpm_to_wheel) as f32,
            cycle_s: 1.0 / p.cycle_hz as f32,
            master: NodeId::new(p.master_node),
            heartbeat_ms: p.heartbeat_ms,
            heartbeat_timeout_ms: p.heartbeat_timeout_ms,
            // Validated: a whole number of control periods.
            heartbeat_clock: Every::new(p.control_hz * u32::from(p.heartbeat_ms) / 1000),
            now: Instant::default(),
            emcy_count: 0,
            latest: None,
            booted: false,
        }
    }

    /// The latest issue of any node since the start: what a log says of a CiA 402 fault.
    pub(super) const fn issue(&self) -> Option<DriveIssue> {
        self.latest
    }

    /// Some node's RPDO2 may be on (from the start, and from each reset or boot-up of the
    /// node until its RPDO2-off write is acknowledged) while it is brought up: the robot's
    /// own frames in `0x300..=0x31F` are held (`docs/protocol.md`, "The RPDO2 window").
    /// The hold ends when the node fails its configuration (its SDO time-out bounds it) or,
    /// before its boot-up, when the robot is `faulted` (a node that never boots): a robot
    /// with a fault to report speaks.
    pub(super) fn rpdo2_pending(&self, faulted: bool) -> bool {
        self.nodes.iter().any(|n| {
            !n.rpdo2_off
                && match n.phase {
                    Phase::Setup { .. } => true,
                    Phase::Reset | Phase::Boot => !faulted,
                    Phase::Started { .. } | Phase::Failed => false,
                }
        })
    }

    /// A frame with standard id `id` would be a node's RPDO2 now (`0x300 + node`, its RPDO2
    /// not known off): it is not sent.
    pub(super) fn is_open_rpdo2(&self, id: u16) -> bool {
        self.nodes
            .iter()
            .any(|n| !n.rpdo2_off && RPDO2_FUNCTION + u16::from(n.id.get()) == id)
    }

    /// EMCY frames received since the start (saturating).
    pub(super) const fn emcy_count(&self) -> u32 {
        self.emcy_count
    }

    fn node_of(&mut self, id: NodeId) -> Option<&mut Node> {
        self.nodes.iter_mut().find(|n| n.id == id)
    }

    /// Takes one frame from a node.
    pub(super) fn on_frame<F: Frame>(
        &mut self,
        now: Instant,
        frame: &F,
        wheels: &mut [Wheel; 4],
    ) -> Result<(), DecodeError> {
        let msg = canopen::decode(frame)?;
        let (index, second_axis, velocity) = match msg {
            // Another master's frames, or the drives' requests to one: not feedback.
            Message::Nmt { .. }
            | Message::Sync { .. }
            | Message::Rpdo1 { .. }
            | Message::Rpdo3 { .. }
            | Message::SdoRequest { .. } => return Ok(()),
            Message::Tpdo1 {
                node,
                statusword,
                velocity,
            } => {
                let i = self.index_of(node).ok_or_else(|| super::unknown(frame))?;
                if self.pdo_from_unstarted(i) {
                    return Ok(());
                }
                self.on_statusword(i, now, statusword);
                (i, false, velocity)
            }
            Message::Tpdo2 { node, velocity } => {
                let i = self.index_of(node).ok_or_else(|| super::unknown(frame))?;
                if self.pdo_from_unstarted(i) {
                    return Ok(());
                }
                (i, true, velocity)
            }
            Message::Heartbeat { node, state } => {
                let n = self.node_of(node).ok_or_else(|| super::unknown(frame))?;
                n.last_heartbeat = Some(now.mark(n.last_heartbeat));
                let booted = state == NmtState::BootUp;
                let self_started = if state == NmtState::Operational {
                    n.started_itself()
                } else {
                    None
                };
                if booted {
                    // A boot-up restores the communication objects: RPDO2 is on again.
                    n.rpdo2_off = false;
                    n.fresh = n.phase != Phase::Reset;
                }
                let setup = Phase::Setup {
                    step: 0,
                    sent: None,
                };
                match n.phase {
                    // The reset is owed: what the node says now predates it.
                    Phase::Reset => {}
                    // A boot-up, or a heartbeat of a node whose boot-up was missed.
                    Phase::Boot => n.phase = setup,
                    Phase::Setup { .. } | Phase::Failed if booted => n.phase = setup,
                    Phase::Started { .. } if booted => {
                        let issue = DriveIssue::Rebooted { node: node.get() };
                        n.raise(issue);
                        n.phase = setup;
                        n.statusword = None;
                        n.nmt = None;
                        self.latest = Some(issue);
                    }
                    Phase::Started { start_owed: false } => {
                        let predates_start = n
                            .started_at
                            .is_some_and(|t| now.micros_since(t) <= CANOPEN_NMT_GRACE_US);
                        if state == NmtState::Operational || !predates_start {
                            n.nmt = Some(state);
                        }
                    }
                    Phase::Setup { .. } | Phase::Failed | Phase::Started { .. } => {}
                }
                if self_started.is_some() {
                    self.latest = self_started;
                }
                return Ok(());
            }
            Message::Emcy { node, emcy } => {
                let n = self.node_of(node).ok_or_else(|| super::unknown(frame))?;
                n.last_emcy = emcy.error_code;
                self.emcy_count = self.emcy_count.saturating_add(1);
                return Ok(());
            }
            Message::SdoResponse { node, response } => {
                let i = self.index_of(node).ok_or_else(|| super::unknown(frame))?;
                self.on_sdo(i, now, response);
                return Ok(());
            }
        };
        for (w, &(n, second)) in wheels.iter_mut().zip(&self.wheel_node) {
            if n == index && second == second_axis {
                // i32 to f32 rounds above 2^24 raw units, far beyond any wheel speed.
                w.speed = w.sign * velocity as f32 * self.actual_scale;
                w.pending += w.speed * self.cycle_s;
                w.last_seen = Some(now.mark(w.last_seen));
            }
        }
        Ok(())
    }

    fn index_of(&self, id: NodeId) -> Option<usize> {
        self.nodes.iter().position(|n| n.id == id)
    }

    /// A TPDO from node `i`, which is not started: not feedback (it predates a reset, or
    /// the node started itself, which refuses it).
    fn pdo_from_unstarted(&mut self, i: usize) -> bool {
        let Some(n) = self.nodes.get_mut(i) else {
            return true;
        };
        if n.phase == (Phase::Started { start_owed: false }) {
            return false;
        }
        if let Some(issue) = n.started_itself() {
            self.latest = Some(issue);
        }
        true
    }

    fn on_statusword(&mut self, i: usize, now: Instant, sw: u16) {
        let Some(n) = self.nodes.get_mut(i) else {
            return;
        };
        let predates_reset = n
            .reset_at
            .is_some_and(|t| now.micros_since(t) <= CIA402_RESET_GRACE_US);
        if predates_reset && sw & STATUSWORD_FAULT != 0 {
            return;
        }
        n.statusword = Some(sw);
        if let Command::Enabling { controlword, .. } = n.command {
            let state = DriveState402::from_statusword(sw);
            let next = match controlword {
                controlword::SHUTDOWN if state == Some(DriveState402::ReadyToSwitchOn) => {
                    Some(controlword::SWITCH_ON)
                }
                controlword::SWITCH_ON if state == Some(DriveState402::SwitchedOn) => {
                    Some(controlword::ENABLE_OPERATION)
                }
                controlword::ENABLE_OPERATION if state == Some(DriveState402::OperationEnabled) => {
                    None
                }
                _ => return,
            };
            n.command = match next {
                Some(controlword) => Command::Enabling {
                    controlword,
                    since: None,
                },
                None => Command::Enabled,
            };
        }
    }

    fn on_sdo(&mut self, i: usize, now: Instant, response: SdoResponse) {
        let (heartbeat_ms, timeout_ms, master) =
            (self.heartbeat_ms, self.heartbeat_timeout_ms, self.master);
        let Some(n) = self.nodes.get_mut(i) else {
            return;
        };
        let Phase::Setup {
            step,
            sent: Some(_),
        } = n.phase
        else {
            return;
        };
        let sequence = setup_sequence(n, heartbeat_ms, timeout_ms, master);
        let Some(request) = sequence.get(usize::from(step)) else {
            return;
        };
        if !response.answers(request) {
            // Not this transfer's answer (a late one to an earlier transfer, or another
            // command on the same object).
            return;
        }
        let node = n.id.get();
        let object = request.object();
        let failure = match response {
            // An optional object the drive does not have (or whose value it does not take):
            // the configuration goes on without it (`optional`).
            SdoResponse::Abort { code, .. } if optional(object) && tolerated(code) => None,
            SdoResponse::Abort { code, .. } => Some(DriveIssue::SdoAbort { node, object, code }),
            SdoResponse::Uploaded { value, .. }
                if object == (0x1000, 0) && value & 0xFFFF != DEVICE_PROFILE_402 =>
            {
                Some(DriveIssue::NotADrive {
                    node,
                    device_type: value,
                })
            }
            SdoResponse::Uploaded { value, .. }
                if object == (0x6061, 0) && value & 0xFF != MODE_PROFILE_VELOCITY =>
            {
                // The drive has not switched yet: read again, up to the limit.
                n.polls = n.polls.saturating_add(1);
                if n.polls < CIA402_MODE_POLLS {
                    n.phase = Phase::Setup { step, sent: None };
                    n.poll_at = Some(Instant::from_micros(
                        now.as_micros().saturating_add(CIA402_MODE_POLL_US),
                    ));
                    return;
                }
                Some(DriveIssue::ModeNotShown {
                    node,
                    // The low byte is the INTEGER8 read.
                    mode: (value & 0xFF) as u8 as i8,
                })
            }
            _ => None,
        };
        if let Some(issue) = failure {
            n.raise(issue);
            n.phase = Phase::Failed;
            self.latest = Some(issue);
            return;
        }
        if object == (0x1401, 1) {
            // RPDO2 off: the robot's frames are no controlword of this node any more. A
            // configuration (anew) begins.
            n.rpdo2_off = true;
            n.polls = 0;
            n.poll_at = None;
        }
        n.phase = if usize::from(step) + 1 < sequence.len() {
            Phase::Setup {
                step: step + 1,
                sent: None,
            }
        } else {
            // The heartbeat consumer's window starts with the node.
            n.last_heartbeat = Some(now);
            Phase::Started { start_owed: true }
        };
    }

    /// Motion stopped: shutdown on a disable, quick stop on a fault or an e-stop, nothing
    /// while the robot stays enabled (at zero).
    pub(super) fn halt(&mut self, state: RobotState) {
        let command = match state {
            RobotState::Enabled => return,
            RobotState::Disabled | RobotState::WheelTest => Command::Shutdown,
            RobotState::Fault | RobotState::Estop => Command::QuickStop,
        };
        for n in &mut self.nodes {
            n.command = command;
        }
    }

    /// Runs the enable sequence on every node (`only` `None`) or on wheel `only`'s.
    pub(super) fn request_enable(&mut self, only: Option<u8>) {
        let only = only.and_then(|w| self.wheel_node.get(usize::from(w)).map(|s| s.0));
        for (i, n) in self.nodes.iter_mut().enumerate() {
            if only.is_none_or(|o| o == i) {
                n.command = Command::Enabling {
                    controlword: controlword::SHUTDOWN,
                    since: None,
                };
            }
        }
    }

    /// The host's reset: forgets the issues, owes a fault reset to a node whose statusword
    /// shows a fault, configures again a node whose configuration failed, and recovers a
    /// started node whose heartbeat says it is not operational: NMT start if its heartbeat
    /// was never lost (its configuration is intact), else reset communication and the whole
    /// configuration; either way a fault reset with its first cycle (a drive's reaction to
    /// the communication error may have been a fault, which no TPDO could show).
    pub(super) fn clear_errors(&mut self, now: Instant) {
        for n in &mut self.nodes {
            n.issue = None;
            let left_operational = n.phase == Phase::Started { start_owed: false }
                && n.nmt.is_some_and(|s| s != NmtState::Operational);
            if left_operational {
                n.phase = if n.heard {
                    Phase::Started { start_owed: true }
                } else {
                    Phase::Reset
                };
                n.nmt = None;
            }
            if left_operational || n.statusword.is_some_and(|sw| sw & STATUSWORD_FAULT != 0) {
                n.fault_reset = true;
                n.reset_at = Some(now);
                n.statusword = None;
            }
            if n.phase == Phase::Failed {
                n.phase = Phase::Setup {
                    step: 0,
                    sent: None,
                };
            }
        }
    }

    /// A step begins at `now`: the timeouts (SDO, enable steps, heartbeats) and the
    /// statuswords are judged.
    pub(super) fn step_started(&mut self, now: Instant) {
        self.now = now;
        let heartbeat_timeout_us = u64::from(self.heartbeat_timeout_ms) * 1000;
        let mut latest = None;
        for n in &mut self.nodes {
            let node = n.id.get();
            if n.fault_reset {
                n.reset_at = Some(now);
            }
            let issue = match (n.phase, n.command) {
                (
                    Phase::Setup {
                        step,
                        sent: Some(t),
                    },
                    _,
                ) if now.micros_since(t) > CANOPEN_SDO_TIMEOUT_US => {
                    let (hb, timeout, master) =
                        (self.heartbeat_ms, self.heartbeat_timeout_ms, self.master);
                    let object = setup_sequence(n, hb, timeout, master)
                        .get(usize::from(step))
                        .map_or((0, 0), SdoRequest::object);
                    n.phase = Phase::Failed;
                    // The client gives the transfer up and says so (CiA 301).
                    n.abort_owed = Some(object);
                    Some(DriveIssue::SdoTimeout { node, object })
                }
                (phase, _)
                    if watched(phase, n.was_started)
                        && n.last_heartbeat
                            .is_some_and(|t| now.micros_since(t) > heartbeat_timeout_us) =>
                {
                    n.heard = false;
                    Some(DriveIssue::HeartbeatLost { node })
                }
                (Phase::Started { start_owed: false }, _)
                    if n.nmt.is_some_and(|s| s != NmtState::Operational) =>
                {
                    n.nmt
                        .map(|state| DriveIssue::NotOperational { node, state })
                }
                (
                    _,
                    Command::Enabling {
                        controlword,
                        since: Some(since),
                    },
                ) if now.micros_since(since) > CIA402_TRANSITION_TIMEOUT_US => {
                    Some(DriveIssue::TransitionTimeout {
                        node,
                        controlword,
                        statusword: n.statusword,
                    })
                }
                _ => n.statusword.and_then(|sw| {
                    let faulted = sw & STATUSWORD_FAULT != 0;
                    let left = n.command == Command::Enabled
                        && DriveState402::from_statusword(sw)
                            != Some(DriveState402::OperationEnabled);
                    (faulted || left).then_some(DriveIssue::DriveFault {
                        node,
                        statusword: sw,
                        emcy_code: n.last_emcy,
                    })
                }),
            };
            if let Some(issue) = issue
                && n.issue.is_none()
            {
                n.issue = Some(issue);
                latest = Some(issue);
            }
        }
        if latest.is_some() {
            self.latest = latest;
        }
    }

    /// What faults wheel `i`: its node's issue.
    #[inline]
    pub(super) fn wheel_fault(&self, i: usize) -> Fault {
        self.wheel_node
            .get(i)
            .and_then(|&(n, _)| self.nodes.get(n))
            .and_then(|n| n.issue)
            .map_or(Fault::None, |issue| issue.fault())
    }

    /// Wheel `i`'s node is being configured (its feedback is not expected yet): also while
    /// it is reset and configured again after it was started (a recovery).
    #[inline]
    pub(super) fn wheel_configuring(&self, i: usize) -> bool {
        self.wheel_node
            .get(i)
            .and_then(|&(n, _)| self.nodes.get(n))
            .is_some_and(|n| match n.phase {
                Phase::Setup { .. } | Phase::Started { start_owed: true } => true,
                Phase::Reset | Phase::Boot | Phase::Failed => n.was_started,
                Phase::Started { start_owed: false } => false,
            })
    }

    /// The frames owed this step: the NMT resets owed (each node's at the first step), the
    /// next SDO transfer of each node being configured, NMT start, and (`cycle_due`) SYNC and
    /// every started node's RPDOs; the master's heartbeat at its period.
    pub(super) fn emit(
        &mut self,
        out: &mut Outbox,
        wheels: &mut [Wheel; 4],
        setpoints: WheelSpeeds<f32, 4>,
        cycle_due: bool,
    ) {
        let now = self.now;
        let (heartbeat_ms, timeout_ms, master) =
            (self.heartbeat_ms, self.heartbeat_timeout_ms, self.master);
        let first = !self.booted;
        if first {
            // The master's own boot-up (CiA 301), its first frame; its heartbeat follows
            // at its period.
            self.booted = true;
            if let Some(node) = self.master {
                let boot_up = Message::Heartbeat {
                    node,
                    state: NmtState::BootUp,
                };
                push(out, boot_up.to_can_frame());
            }
        }
        for (index, n) in self.nodes.iter_mut().enumerate() {
            if let Some((index, sub)) = n.abort_owed.take() {
                let request = SdoRequest::Abort {
                    index,
                    sub,
                    code: abort_code::TIMEOUT,
                };
                push(
                    out,
                    Message::SdoRequest {
                        node: n.id,
                        request,
                    }
                    .to_can_frame(),
                );
            }
            if core::mem::take(&mut n.preop_owed) {
                let preop = Message::Nmt {
                    command: NmtCommand::EnterPreOperational,
                    node: Some(n.id),
                };
                push(out, preop.to_can_frame());
            }
            match n.phase {
                Phase::Reset => {
                    let reset = Message::Nmt {
                        command: NmtCommand::ResetCommunication,
                        node: Some(n.id),
                    };
                    push(out, reset.to_can_frame());
                    n.phase = Phase::Boot;
                    n.statusword = None;
                    // Reset communication restores the predefined PDOs: RPDO2 is on.
                    n.rpdo2_off = false;
                    n.fresh = false;
                    // A recovered node's boot-up is due within the consumer time.
                    n.last_heartbeat = Some(now);
                }
                Phase::Setup { step, sent: None }
                    if n.poll_at.is_none_or(|t| now.as_micros() >= t.as_micros()) =>
                {
                    n.poll_at = None;
                    let sequence = setup_sequence(n, heartbeat_ms, timeout_ms, master);
                    if let Some(&request) = sequence.get(usize::from(step)) {
                        let msg = Message::SdoRequest {
                            node: n.id,
                            request,
                        };
                        push(out, msg.to_can_frame());
                        n.phase = Phase::Setup {
                            step,
                            sent: Some(now),
                        };
                    }
                }
                Phase::Started { start_owed: true } => {
                    let start = Message::Nmt {
                        command: NmtCommand::Start,
                        node: Some(n.id),
                    };
                    push(out, start.to_can_frame());
                    n.phase = Phase::Started { start_owed: false };
                    n.started_at = Some(now);
                    n.nmt = None;
                    n.was_started = true;
                    n.heard = true;
                    n.fresh = false;
                    // Feedback is expected from now on.
                    for (w, &(i, _)) in wheels.iter_mut().zip(&self.wheel_node) {
                        if i == index {
                            w.last_seen = Some(now.mark(w.last_seen));
                        }
                    }
                }
                _ => {}
            }
        }
        let started = |n: &Node| n.phase == Phase::Started { start_owed: false };
        if cycle_due && self.nodes.iter().any(started) {
            push(out, Message::Sync { counter: None }.to_can_frame());
            // Targets only once every node asked to enable is operation enabled.
            let moving = !self
                .nodes
                .iter()
                .any(|n| matches!(n.command, Command::Enabling { .. }));
            for (index, n) in self.nodes.iter_mut().enumerate() {
                if !started(n) {
                    continue;
                }
                let mut targets = [0i32; 2];
                if moving && n.command == Command::Enabled {
                    for ((w, &(i, second)), sp) in
                        wheels.iter().zip(&self.wheel_node).zip(setpoints.0)
                    {
                        if i == index {
                            let raw = wire::to_raw(
                                w.sign * sp,
                                self.target_scale,
                                i32::MIN.into(),
                                i32::MAX.into(),
                            );
                            // Clamped to i32 by `to_raw`.
                            targets[usize::from(second)] = raw as i32;
                        }
                    }
                }
                // An enable step's time runs from the cycle that first sends it.
                if let Command::Enabling {
                    controlword,
                    since: None,
                } = n.command
                {
                    n.command = Command::Enabling {
                        controlword,
                        since: Some(now),
                    };
                }
                let rpdo1 = Message::Rpdo1 {
                    node: n.id,
                    controlword: n.controlword(),
                    target: targets[0],
                };
                push(out, rpdo1.to_can_frame());
                if n.dual {
                    let rpdo3 = Message::Rpdo3 {
                        node: n.id,
                        target: targets[1],
                    };
                    push(out, rpdo3.to_can_frame());
                }
            }
        }
        // The heartbeat's first tick is the boot-up's step: the boot-up stands for it.
        if self.heartbeat_clock.tick()
            && !first
            && let Some(node) = self.master
        {
            let heartbeat = Message::Heartbeat {
                node,
                state: NmtState::Operational,
            };
            push(out, heartbeat.to_can_frame());
        }
    }
}

/// A node's configuration, in order (`docs/protocol.md`, "Configuration of a node").
fn setup_sequence(
    n: &Node,
    heartbeat_ms: u16,
    heartbeat_timeout_ms: u16,
    master: Option<NodeId>,
) -> heapless::Vec<SdoRequest, SETUP_MAX> {
    let mut out = heapless::Vec::new();
    let node = u32::from(n.id.get());
    // SETUP_MAX covers the longest sequence.
    let write = |out: &mut heapless::Vec<SdoRequest, SETUP_MAX>, index, sub, value, size| {
        let _ = out.push(SdoRequest::Download {
            index,
            sub,
            value,
            size,
        });
    };
    // RPDO2 off first, before anything else, even the device type: from the boot-up until
    // this write its predefined COB-ID, 0x300 + node, is a robot protocol frame
    // ("The RPDO2 window"). 0x1401 is CiA 301's, on any node.
    write(
        &mut out,
        0x1401,
        1,
        (u32::from(RPDO2_FUNCTION) + node) | COB_INVALID,
        4,
    );
    // The device type: a node that is not a 402 drive is told nothing more.
    let _ = out.push(SdoRequest::Upload {
        index: 0x1000,
        sub: 0,
    });
    let mut write = |index: u16, sub: u8, value: u32, size: u8| {
        write(&mut out, index, sub, value, size);
    };
    // Profile velocity mode, the heartbeat produced and the master's consumed.
    write(0x6060, 0, MODE_PROFILE_VELOCITY, 1);
    write(0x1017, 0, heartbeat_ms.into(), 2);
    let master = u32::from(master.map_or(0, NodeId::get));
    write(0x1016, 1, master << 16 | u32::from(heartbeat_timeout_ms), 4);
    // A disable (0x06 from operation enabled, transition 8) and a disable operation (0x07,
    // transition 5) slow down on the drive's ramp before the torque goes; optional objects.
    write(0x605B, 0, OPTION_SLOW_DOWN, 2);
    write(0x605C, 0, OPTION_SLOW_DOWN, 2);
    // (comm index, mapping index, COB-ID, transmission type, entries); entries are
    // index << 16 | sub << 8 | bits.
    let (sub1, sub2) = if n.dual { (1, 2) } else { (0, 0) };
    let entry = |index: u32, sub: u32, bits: u32| index << 16 | sub << 8 | bits;
    let rpdo1 = [entry(0x6040, 0, 16), entry(0x60FF, sub1, 32)];
    let rpdo3 = [entry(0x60FF, sub2, 32)];
    let tpdo1 = [entry(0x6041, 0, 16), entry(0x606C, sub1, 32)];
    let tpdo2 = [entry(0x606C, sub2, 32)];
    let used: [(u16, u32, u8, &[u32]); 4] = [
        (0x1400, 0x200, 0xFF, &rpdo1),
        (0x1402, 0x400, 0xFF, &rpdo3),
        (0x1800, 0x180, 1, &tpdo1),
        (0x1801, 0x280, 1, &tpdo2),
    ];
    for &(comm, function, kind, entries) in &used {
        let second = comm == 0x1402 || comm == 0x1801;
        if second && !n.dual {
            continue;
        }
        let cob = function + node;
        let map = comm + 0x200;
        write(comm, 1, cob | COB_INVALID, 4);
        write(map, 0, 0, 1);
        for (sub, &e) in (1u8..).zip(entries) {
            write(map, sub, e, 4);
        }
        // At most two entries.
        write(map, 0, entries.len() as u32, 1);
        write(comm, 2, kind.into(), 1);
        write(comm, 1, cob, 4);
    }
    // Every other PDO not used off, at its predefined COB-ID (RPDO2 was the first).
    for (comm, function) in [
        (0x1402, 0x400),
        (0x1403, 0x500),
        (0x1801, 0x280),
        (0x1802, 0x380),
        (0x1803, 0x480),
    ] {
        let used_here = n.dual && (comm == 0x1402 || comm == 0x1801);
        if !used_here {
            write(comm, 1, (function + node) | COB_INVALID, 4);
        }
    }
    // Last, the mode of operation display: read until it shows profile velocity (the mode
    // may take effect some time after 0x6060 is written), before NMT start and any enable.
    let _ = out.push(SdoRequest::Upload {
        index: 0x6061,
        sub: 0,
    });
    out
}

/// Optional objects of the configuration: a drive without them (or without the value
/// written) is configured without them.
const fn optional((index, sub): (u16, u8)) -> bool {
    matches!(index, 0x605B | 0x605C) && sub == 0
}

/// The abort codes that say an optional object is absent or does not take the value.
const fn tolerated(code: u32) -> bool {
    matches!(
        code,
        abort_code::NO_OBJECT | abort_code::NO_SUBINDEX | abort_code::INVALID_VALUE
    )
}

/// COB-ID bit 31: the PDO is off.
const COB_INVALID: u32 = 0x8000_0000;

/// Whether a node in `phase` has its heartbeat watched: once started, and while it is reset
/// again in a recovery (its boot-up is then due within the consumer time).
const fn watched(phase: Phase, was_started: bool) -> bool {
    match phase {
        Phase::Started { .. } => true,
        Phase::Reset | Phase::Boot => was_started,
        Phase::Setup { .. } | Phase::Failed => false,
    }
}
