//! ODrive CAN Simple axes: their heartbeats and encoder estimates into the wheels, and the
//! velocity setpoints and axis state requests out. The ODrive runs its own velocity loop; the
//! core asks for closed loop on an enable (or one axis in a wheel test), for idle on a stop,
//! and clears the drives' errors on a reset (`docs/control.md`, "Faults").

use embedded_can::Frame;
use kinematics::WheelSpeeds;

use super::{Instant, Outbox, Wheel, WheelOf, push, unknown};
use crate::protocol::DecodeError;
use crate::protocol::odrive::{self, AxisState, ControlMode, InputMode, NodeId};

/// ODrive: a position estimate that moved more than this many times what
/// `limits.max_wheel_speed` allows since the previous one (plus one estimate period) is not
/// integrated into the odometry (a drive reboot restarting its count, a corrupt value); it
/// becomes the new reference and is counted as an out-of-range frame.
pub const ODRIVE_MAX_JUMP_FACTOR: f32 = 2.0;
/// ODrive: heartbeats received until this long after the step that asked for closed loop
/// (after an enable) may predate the request: their axis state is not judged, µs. One and a
/// half heartbeat periods, so that a stalled runner or drive does not turn an old heartbeat
/// into a fault. A later heartbeat of an enabled robot that reports another state is a
/// `DriveError`.
pub const ODRIVE_STATE_GRACE_US: u64 = 150_000;
/// ODrive: after a reset, heartbeat and `Get_Error` frames received until this long after the
/// next step sent `Clear_Errors` may predate the clearing: their error bits are ignored, µs.
/// One and a half heartbeat periods, as [`ODRIVE_STATE_GRACE_US`]; a cause that persists
/// shows in the first heartbeat after it.
pub const ODRIVE_CLEAR_GRACE_US: u64 = 150_000;

/// Encoder estimates come every 10 ms (the ODrive's default).
pub(super) const FEEDBACK_PERIOD_US: u64 = 10_000;

/// The axes of the four wheels.
#[derive(Debug, Clone)]
pub(super) struct Odrive {
    /// Each wheel's node (validated, so every one is `Some`).
    nodes: [Option<NodeId>; 4],
    gear_ratio: f32,
    /// `Set_Controller_Mode` asks for the velocity ramp rather than passthrough.
    vel_ramp: bool,
    /// The most a position estimate may move per µs since the previous one, motor turns
    /// ([`ODRIVE_MAX_JUMP_FACTOR`]).
    max_turns_per_us: f32,
    axes: [Axis; 4],
    /// The state request owed to the axes (sent on the next step).
    request: Option<AxisState>,
    /// The one wheel the request goes to (a wheel test); `None`: every wheel.
    only: Option<u8>,
    /// `Clear_Errors` is owed to the axes (after a reset; sent on the next step).
    clear_errors: bool,
    /// When `Clear_Errors` was last owed or sent.
    errors_cleared_at: Option<Instant>,
    /// When closed loop was last asked for or sent.
    closed_loop_at: Option<Instant>,
}

/// What one axis has told.
#[derive(Debug, Clone, Copy, Default)]
struct Axis {
    /// The last position estimate, motor turns.
    last_pos: Option<f32>,
    /// The axis error of the last heartbeat, and the active errors of `Get_Error` since.
    error: u32,
    /// The state of the last heartbeat that does not predate the last closed-loop request.
    state: Option<AxisState>,
}

impl Odrive {
    /// The axes `node_ids` (validated); `max_wheel_speed` in rad/s.
    pub(super) fn new(
        node_ids: [u8; 4],
        gear_ratio: f32,
        vel_ramp: bool,
        max_wheel_speed: f32,
    ) -> Self {
        Self {
            nodes: node_ids.map(NodeId::new),
            gear_ratio,
            vel_ramp,
            max_turns_per_us: max_turns_per_us(max_wheel_speed, gear_ratio),
            axes: [Axis::default(); 4],
            request: None,
            only: None,
            clear_errors: false,
            errors_cleared_at: None,
            closed_loop_at: None,
        }
    }

    /// A new `limits.max_wheel_speed` (rad/s), for the estimates' plausibility check.
    pub(super) fn set_max_wheel_speed(&mut self, max_wheel_speed: f32) {
        self.max_turns_per_us = max_turns_per_us(max_wheel_speed, self.gear_ratio);
    }

    /// Takes one frame from an axis into its wheel.
    pub(super) fn on_frame<F: Frame>(
        &mut self,
        now: Instant,
        frame: &F,
        wheel_of: &WheelOf,
        wheels: &mut [Wheel; 4],
    ) -> Result<(), DecodeError> {
        if odrive::is_request(frame) {
            // Another host polling a drive (odrivetool, a logger): not feedback, not an error.
            return Ok(());
        }
        let fb = odrive::Feedback::decode(frame)?;
        // Error bits from before the last `Clear_Errors` (see ODRIVE_CLEAR_GRACE_US).
        let errors_stale = self
            .errors_cleared_at
            .is_some_and(|t| now.micros_since(t) <= ODRIVE_CLEAR_GRACE_US);
        let state_stale = self
            .closed_loop_at
            .is_some_and(|t| now.micros_since(t) <= ODRIVE_STATE_GRACE_US);
        let i = wheel_of.get(fb.node.get());
        let (Some(w), Some(a)) = (wheels.get_mut(i), self.axes.get_mut(i)) else {
            return Err(unknown(frame));
        };
        match fb.msg {
            odrive::Feedback::Heartbeat(hb) => {
                a.error = if errors_stale { 0 } else { hb.axis_error };
                if !state_stale {
                    a.state = Some(hb.axis_state);
                }
            }
            odrive::Feedback::EncoderEstimates { pos, vel } => {
                let turns_to_rad = core::f32::consts::TAU / self.gear_ratio;
                let jump = a.last_pos.zip(w.last_seen).map(|(last, seen)| {
                    let elapsed_us = now.micros_since(seen).saturating_add(FEEDBACK_PERIOD_US);
                    (pos - last, self.max_turns_per_us * elapsed_us as f32)
                });
                a.last_pos = Some(pos);
                w.speed = w.sign * vel * turns_to_rad;
                w.last_seen = Some(now.mark(w.last_seen));
                if let Some((delta, max)) = jump {
                    // An infinite difference (finite estimates far apart) fails too.
                    if !delta.is_finite() || delta.abs() > max {
                        return Err(DecodeError::OutOfRange {
                            field: "pos_estimate",
                            value: delta as i64,
                        });
                    }
                    w.pending += w.sign * delta * turns_to_rad;
                }
            }
            odrive::Feedback::Error { active_errors, .. } => {
                if !errors_stale {
                    a.error |= active_errors;
                }
            }
        }
        Ok(())
    }

    /// Asks for closed loop (with velocity mode) at the next step, on every axis (`only`
    /// `None`: an enable) or on wheel `only`'s alone (a wheel test). Axis states reported from
    /// now until the request goes out predate it.
    pub(super) fn request_closed_loop(&mut self, now: Instant, only: Option<u8>) {
        self.request = Some(AxisState::ClosedLoopControl);
        self.only = only;
        self.closed_loop_at = Some(now);
        for a in &mut self.axes {
            a.state = None;
        }
    }

    /// Asks for idle on every axis at the next step.
    pub(super) fn request_idle(&mut self) {
        self.request = Some(AxisState::Idle);
        self.only = None;
    }

    /// Forgets the axes' errors and owes them `Clear_Errors` (a reset): error bits received
    /// from now until the clear goes out predate it.
    pub(super) fn clear_errors(&mut self, now: Instant) {
        self.clear_errors = true;
        self.errors_cleared_at = Some(now);
        for a in &mut self.axes {
            a.error = 0;
        }
    }

    /// Wheel `i`'s axis reports an error, or (`enabled`) a state other than closed loop.
    #[inline]
    pub(super) fn wheel_fault(&self, i: usize, enabled: bool) -> bool {
        self.axes.get(i).is_some_and(|a| {
            a.error != 0 || (enabled && a.state.is_some_and(|s| s != AxisState::ClosedLoopControl))
        })
    }

    /// A step begins at `now`: what is owed goes out in it, so the grace windows count from
    /// it.
    pub(super) fn step_started(&mut self, now: Instant) {
        if self.clear_errors {
            self.errors_cleared_at = Some(now);
        }
        if self.request == Some(AxisState::ClosedLoopControl) {
            self.closed_loop_at = Some(now);
        }
    }

    /// The frames owed: `Clear_Errors`, the state request, and (`setpoints_due`) every axis's
    /// velocity setpoint.
    pub(super) fn emit(
        &mut self,
        out: &mut Outbox,
        wheels: &[Wheel; 4],
        setpoints: WheelSpeeds<f32, 4>,
        setpoints_due: bool,
    ) {
        if core::mem::take(&mut self.clear_errors) {
            let clear = odrive::Command::ClearErrors { identify: false };
            for node in self.nodes.iter().flatten() {
                push(out, clear.to_can_frame(*node));
            }
        }
        if let Some(state) = self.request.take() {
            let only = self.only.map(usize::from);
            let addressed = self
                .nodes
                .iter()
                .enumerate()
                .filter(|(wheel, _)| only.is_none_or(|w| w == *wheel))
                .filter_map(|(_, node)| node.as_ref());
            for node in addressed {
                if state == AxisState::ClosedLoopControl {
                    let mode = odrive::Command::SetControllerMode {
                        control_mode: ControlMode::VelocityControl,
                        input_mode: if self.vel_ramp {
                            InputMode::VelRamp
                        } else {
                            InputMode::Passthrough
                        },
                    };
                    push(out, mode.to_can_frame(*node));
                }
                push(
                    out,
                    odrive::Command::SetInputVel {
                        vel: 0.0,
                        torque_ff: 0.0,
                    }
                    .to_can_frame(*node),
                );
                push(
                    out,
                    odrive::Command::SetAxisState(state).to_can_frame(*node),
                );
            }
        }
        if setpoints_due {
            let rad_to_turns = self.gear_ratio / core::f32::consts::TAU;
            for ((node, w), sp) in self.nodes.iter().zip(wheels).zip(setpoints.0) {
                if let Some(node) = node {
                    let cmd = odrive::Command::SetInputVel {
                        vel: w.sign * sp * rad_to_turns,
                        torque_ff: 0.0,
                    };
                    push(out, cmd.to_can_frame(*node));
                }
            }
        }
    }
}

/// The largest change of a position estimate per µs that is plausible at `max_wheel_speed`.
fn max_turns_per_us(max_wheel_speed: f32, gear_ratio: f32) -> f32 {
    ODRIVE_MAX_JUMP_FACTOR * max_wheel_speed * gear_ratio / core::f32::consts::TAU * 1e-6
}
