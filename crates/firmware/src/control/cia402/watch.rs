//! Watching the nodes: heartbeats and NMT states, self-started and rebooted nodes, faults
//! and timeouts judged each step, and the host's reset that recovers them.

use core::fmt;

use super::enable::{CIA402_TRANSITION_TIMEOUT_US, Command};
use super::setup::{self, CANOPEN_SDO_TIMEOUT_US, CIA402_MODE_POLLS, RPDO2_FUNCTION};
use super::{Cia402, Node, Phase};
use crate::control::{Instant, Outbox, push};
use crate::protocol::canopen::{
    self, DriveState402, Message, NmtState, STATUSWORD_FAULT, SdoRequest,
};
use crate::protocol::robot::Fault;

/// CANopen: heartbeats received until this long after NMT start was sent may predate it: a
/// state other than operational in them is ignored, µs.
pub const CANOPEN_NMT_GRACE_US: u64 = 20_000;

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

impl Node {
    /// The node showed it is operational (a TPDO, an operational heartbeat): if it booted
    /// and was not started since, it started itself; it is refused (the issue, once a
    /// boot) and sent to pre-operational.
    pub(super) fn started_itself(&mut self) -> Option<DriveIssue> {
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
}

impl Cia402 {
    /// A heartbeat (or the boot-up) of node `i` in NMT `state`: a boot-up begins its
    /// configuration (a reboot of a started node is an issue), a started node's state is
    /// kept for [`Self::step_started`], an operational one that was not started refused.
    pub(super) fn on_heartbeat(&mut self, i: usize, now: Instant, state: NmtState) {
        let Some(n) = self.nodes.get_mut(i) else {
            return;
        };
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
                let issue = DriveIssue::Rebooted { node: n.id.get() };
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
    }

    /// A TPDO from node `i`, which is not started: not feedback (it predates a reset, or
    /// the node started itself, which refuses it).
    pub(super) fn pdo_from_unstarted(&mut self, i: usize) -> bool {
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

    /// The host's reset: forgets the issues, owes a fault reset to a node whose statusword
    /// shows a fault, configures again a node whose configuration failed, and recovers a
    /// started node whose heartbeat says it is not operational: NMT start if its heartbeat
    /// was never lost (its configuration is intact), else reset communication and the whole
    /// configuration; either way a fault reset with its first cycle (a drive's reaction to
    /// the communication error may have been a fault, which no TPDO could show).
    pub(in crate::control) fn clear_errors(&mut self, now: Instant) {
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
    pub(in crate::control) fn step_started(&mut self, now: Instant) {
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
                    let object = setup::setup_sequence(n, hb, timeout, master)
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
    pub(in crate::control) fn wheel_fault(&self, i: usize) -> Fault {
        self.wheel_node
            .get(i)
            .and_then(|&(n, _)| self.nodes.get(n))
            .and_then(|n| n.issue)
            .map_or(Fault::None, |issue| issue.fault())
    }

    /// The master's heartbeat at its period; not at the first step (`first`), whose
    /// boot-up stands for it.
    pub(super) fn emit_heartbeat(&mut self, out: &mut Outbox, first: bool) {
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

/// Whether a node in `phase` has its heartbeat watched: once started, and while it is reset
/// again in a recovery (its boot-up is then due within the consumer time).
const fn watched(phase: Phase, was_started: bool) -> bool {
    match phase {
        Phase::Started { .. } => true,
        Phase::Reset | Phase::Boot => was_started,
        Phase::Setup { .. } | Phase::Failed => false,
    }
}
