//! Enabling: the CiA 402 state machine walked one confirmed step at a time (shutdown, switch
//! on, enable operation), the halt on a disable or a fault, and each cycle's SYNC, controlwords
//! and targets.

use kinematics::WheelSpeeds;

use super::{Cia402, Node, Phase};
use crate::control::{Instant, Outbox, Wheel, push};
use crate::protocol::canopen::{DriveState402, Message, STATUSWORD_FAULT, controlword};
use crate::protocol::robot::RobotState;
use crate::protocol::wire;

/// CiA 402: an enable step (shutdown, switch on, enable operation) whose state the statusword
/// does not show within this long fails, µs.
pub const CIA402_TRANSITION_TIMEOUT_US: u64 = 250_000;
/// CiA 402: statuswords received until this long after a fault reset was sent may predate
/// it: their fault bit is ignored, µs.
pub const CIA402_RESET_GRACE_US: u64 = 20_000;

/// What a node's controlword asks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Command {
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

impl Node {
    /// The controlword of this cycle (a fault reset is sent once).
    pub(super) fn controlword(&mut self) -> u16 {
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

impl Cia402 {
    pub(super) fn on_statusword(&mut self, i: usize, now: Instant, sw: u16) {
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

    /// Motion stopped: shutdown on a disable, quick stop on a fault or an e-stop, nothing
    /// while the robot stays enabled (at zero).
    pub(in crate::control) fn halt(&mut self, state: RobotState) {
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
    pub(in crate::control) fn request_enable(&mut self, only: Option<u8>) {
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

    /// A cycle: SYNC and every started node's RPDOs (controlword and targets), if any node
    /// is started. Targets only once every node asked to enable is operation enabled.
    pub(super) fn emit_cycle(
        &mut self,
        out: &mut Outbox,
        wheels: &[Wheel; 4],
        setpoints: WheelSpeeds<f32, 4>,
    ) {
        let now = self.now;
        let started = |n: &Node| n.phase == Phase::Started { start_owed: false };
        if !self.nodes.iter().any(started) {
            return;
        }
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
                for ((w, &(i, second)), sp) in wheels.iter().zip(&self.wheel_node).zip(setpoints.0)
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
}
