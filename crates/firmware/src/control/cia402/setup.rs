//! Bringing a node up: NMT reset communication, its boot-up, the configuration by SDO (one
//! transfer in flight per node) and NMT start; the RPDO2 window the robot's frames wait out.

use super::watch::DriveIssue;
use super::{Cia402, Node, Phase};
use crate::control::{Instant, Outbox, Wheel, push};
use crate::protocol::canopen::{
    Message, NmtCommand, NmtState, NodeId, SdoRequest, SdoResponse, abort_code,
};

/// CiA 402: an SDO transfer of the configuration not answered within this long fails, µs.
pub const CANOPEN_SDO_TIMEOUT_US: u64 = 200_000;
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
pub(super) const RPDO2_FUNCTION: u16 = 0x300;
/// Profile velocity mode (objects 0x6060 and 0x6061).
const MODE_PROFILE_VELOCITY: u32 = 3;
/// Shutdown (0x605B) and disable operation (0x605C) option code 1: slow down on the slow
/// down ramp, then disable the drive function.
const OPTION_SLOW_DOWN: u32 = 1;

/// COB-ID bit 31: the PDO is off.
const COB_INVALID: u32 = 0x8000_0000;

impl Cia402 {
    /// Some node's RPDO2 may be on (from the start, and from each reset or boot-up of the
    /// node until its RPDO2-off write is acknowledged) while it is brought up: the robot's
    /// own frames in `0x300..=0x31F` are held (`docs/protocol.md`, "The RPDO2 window").
    /// The hold ends when the node fails its configuration (its SDO time-out bounds it) or,
    /// before its boot-up, when the robot is `faulted` (a node that never boots): a robot
    /// with a fault to report speaks.
    pub(in crate::control) fn rpdo2_pending(&self, faulted: bool) -> bool {
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
    pub(in crate::control) fn is_open_rpdo2(&self, id: u16) -> bool {
        self.nodes
            .iter()
            .any(|n| !n.rpdo2_off && RPDO2_FUNCTION + u16::from(n.id.get()) == id)
    }

    pub(super) fn on_sdo(&mut self, i: usize, now: Instant, response: SdoResponse) {
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

    /// Wheel `i`'s node is being configured (its feedback is not expected yet): also while
    /// it is reset and configured again after it was started (a recovery).
    #[inline]
    pub(in crate::control) fn wheel_configuring(&self, i: usize) -> bool {
        self.wheel_node
            .get(i)
            .and_then(|&(n, _)| self.nodes.get(n))
            .is_some_and(|n| match n.phase {
                Phase::Setup { .. } | Phase::Started { start_owed: true } => true,
                Phase::Reset | Phase::Boot | Phase::Failed => n.was_started,
                Phase::Started { start_owed: false } => false,
            })
    }

    /// The bring-up frames owed this step: the master's boot-up (its first frame), SDO aborts
    /// and NMT pre-operational owed, NMT reset communication, each node's next SDO transfer
    /// of its configuration, NMT start.
    pub(super) fn emit_bring_up(&mut self, out: &mut Outbox, wheels: &mut [Wheel; 4]) {
        let now = self.now;
        let (heartbeat_ms, timeout_ms, master) =
            (self.heartbeat_ms, self.heartbeat_timeout_ms, self.master);
        if !self.booted {
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
    }
}

/// A node's configuration, in order (`docs/protocol.md`, "Configuration of a node").
pub(super) fn setup_sequence(
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
