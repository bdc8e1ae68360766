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
//!
//! This file holds the nodes and the dispatch; `setup` brings a node up (NMT reset, boot-up,
//! the configuration by SDO, NMT start), `enable` walks the 402 state machine and sends the
//! cycle, `watch` judges heartbeats, NMT states, faults and timeouts.

use embedded_can::Frame;
use kinematics::WheelSpeeds;

use super::time::Every;
use super::{Instant, Outbox, Wheel};
use crate::config::Cia402Drive;
use crate::protocol::DecodeError;
use crate::protocol::canopen::{self, Message, NmtState, NodeId};

mod enable;
mod setup;
mod watch;

use enable::Command;
pub use enable::{CIA402_RESET_GRACE_US, CIA402_TRANSITION_TIMEOUT_US};
pub use setup::CANOPEN_SDO_TIMEOUT_US;
pub use watch::{CANOPEN_NMT_GRACE_US, DriveIssue};

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
    /// The nodes of a validated configuration, run at `control_hz` with a setpoint cycle of
    /// `cycle_hz` (`Timing::setpoint_hz`).
    pub(super) fn new(p: &Cia402Drive, control_hz: u32, cycle_hz: u32) -> Self {
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
            cycle_s: 1.0 / cycle_hz as f32,
            master: NodeId::new(p.master_node),
            heartbeat_ms: p.heartbeat_ms,
            heartbeat_timeout_ms: p.heartbeat_timeout_ms,
            // Validated: a whole number of control periods.
            heartbeat_clock: Every::new(control_hz * u32::from(p.heartbeat_ms) / 1000),
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

    /// EMCY frames received since the start (saturating).
    pub(super) const fn emcy_count(&self) -> u32 {
        self.emcy_count
    }

    fn node_of(&mut self, id: NodeId) -> Option<&mut Node> {
        self.nodes.iter_mut().find(|n| n.id == id)
    }

    fn index_of(&self, id: NodeId) -> Option<usize> {
        self.nodes.iter().position(|n| n.id == id)
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
                let i = self.index_of(node).ok_or_else(|| super::unknown(frame))?;
                self.on_heartbeat(i, now, state);
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
        let first = !self.booted;
        self.emit_bring_up(out, wheels);
        if cycle_due {
            self.emit_cycle(out, wheels, setpoints);
        }
        self.emit_heartbeat(out, first);
    }
}
