//! An ODrive axis (firmware 0.6, CAN Simple): a velocity-mode drive with its own watchdog.
//!
//! [`OdriveAxis`] is built from [`OdriveParams`]; it takes the firmware's ODrive commands
//! ([`OdriveAxis::apply`]) and produces [`OdriveFeedback`] (encoder estimates, heartbeats,
//! `Get_Error` answers). Its error bits include [`WATCHDOG_TIMER_EXPIRED`] and
//! [`ESTOP_REQUESTED`].
//!
//! The state machine, velocity loop, watchdog and feedback schedule are specified in
//! `docs/simulator.md`, section "ODrive axis".

use firmware::protocol::odrive::{AxisState, Command, ControlMode, Feedback, Heartbeat, InputMode};

use super::error::{ParamError, non_negative, positive};
use super::{Drive, Shaft};

/// ODrive 0.6 error bit: the axis watchdog expired.
pub const WATCHDOG_TIMER_EXPIRED: u32 = 0x0100_0000;
/// ODrive 0.6 error bit: an `Estop` message was received.
pub const ESTOP_REQUESTED: u32 = 0x0200_0000;

/// ODrive 0.6 `ProcedureResult` values used by the model.
pub mod procedure_result {
    /// The last procedure succeeded (initial value).
    pub const SUCCESS: u8 = 0;
    /// A procedure (closed-loop control counts as one) is running.
    pub const BUSY: u8 = 1;
    /// The procedure was ended by a request (closed loop left for idle).
    pub const CANCELLED: u8 = 2;
    /// The axis disarmed because of an error.
    pub const DISARMED: u8 = 3;
    /// The requested state is not supported (by this model).
    pub const INVALID_STATE: u8 = 13;
}

/// ODrive axis parameters (motor side unless said otherwise).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OdriveParams {
    /// Motor turns per wheel turn (5: the example's belt).
    pub gear_ratio: f64,
    /// Rotor inertia, kg·m² (a D5065-class motor; the plant adds it times `gear_ratio²`).
    pub rotor_inertia: f64,
    /// `controller.config.vel_gain`, N·m per rev/s.
    pub vel_gain: f64,
    /// `controller.config.vel_integrator_gain`, N·m per rev.
    pub vel_integrator_gain: f64,
    /// Motor torque limit, N·m (current limit times torque constant).
    pub torque_limit: f64,
    /// `controller.config.vel_limit`, rev/s.
    pub vel_limit: f64,
    /// `controller.config.vel_ramp_rate`, rev/s² (input mode vel ramp).
    pub vel_ramp_rate: f64,
    /// Coulomb friction of motor and belt, N·m at the motor.
    pub coulomb_friction: f64,
    /// Speed below which the Coulomb friction is smoothed to zero, rad/s at the motor.
    pub friction_smoothing: f64,
    /// Viscous friction, N·m·s/rad at the motor.
    pub viscous_friction: f64,
    /// Watchdog timeout, s; `None` disables the watchdog (the ODrive default).
    pub watchdog_timeout: Option<f64>,
    /// Encoder estimates period, ns (10 ms).
    pub encoder_period_ns: u64,
    /// Heartbeat period, ns (100 ms).
    pub heartbeat_period_ns: u64,
}

impl Default for OdriveParams {
    fn default() -> Self {
        Self {
            gear_ratio: 5.0,
            rotor_inertia: 1.1e-4,
            vel_gain: 1.0 / 6.0,
            vel_integrator_gain: 1.0 / 3.0,
            torque_limit: 0.6,
            vel_limit: 60.0,
            vel_ramp_rate: 100.0,
            coulomb_friction: 0.01,
            friction_smoothing: 2.0,
            viscous_friction: 1.0e-5,
            watchdog_timeout: None,
            encoder_period_ns: 10_000_000,
            heartbeat_period_ns: 100_000_000,
        }
    }
}

/// A message from the axis (typed; [`OdriveFeedback::to_firmware`] gives the codec's).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum OdriveFeedback {
    /// `Get_Encoder_Estimates` (motor side).
    EncoderEstimates {
        /// Position, rev (unbounded).
        pos: f64,
        /// Velocity, rev/s.
        vel: f64,
    },
    /// `Heartbeat`.
    Heartbeat(Heartbeat),
    /// `Get_Error` response.
    Error {
        /// Active error bits.
        active_errors: u32,
        /// Error bits that disarmed the axis.
        disarm_reason: u32,
    },
}

impl OdriveFeedback {
    /// The firmware codec's message (positions and speeds narrowed to `f32` as on the wire).
    #[must_use]
    pub fn to_firmware(self) -> Feedback {
        match self {
            // The wire format is f32.
            #[allow(clippy::cast_possible_truncation)]
            Self::EncoderEstimates { pos, vel } => Feedback::EncoderEstimates {
                pos: pos as f32,
                vel: vel as f32,
            },
            Self::Heartbeat(hb) => Feedback::Heartbeat(hb),
            Self::Error {
                active_errors,
                disarm_reason,
            } => Feedback::Error {
                active_errors,
                disarm_reason,
            },
        }
    }
}

/// One ODrive axis (the model: `docs/simulator.md`, section "ODrive axis").
#[derive(Debug, Clone, PartialEq)]
pub struct OdriveAxis {
    params: OdriveParams,
    state: AxisState,
    control_mode: ControlMode,
    input_mode: InputMode,
    input_vel: f64,
    torque_ff: f64,
    vel_setpoint: f64,
    integrator: f64,
    torque: f64,
    errors: u32,
    disarm_reason: u32,
    procedure_result: u8,
    since_feed: f64,
    watchdog_timeout: Option<f64>,
    next_encoder_ns: u64,
    next_heartbeat_ns: u64,
}

impl Default for OdriveAxis {
    fn default() -> Self {
        Self::build(OdriveParams::default())
    }
}

impl OdriveAxis {
    /// An idle axis without errors, velocity control, passthrough.
    ///
    /// # Errors
    /// [`ParamError`] for the first parameter out of range.
    pub fn new(params: OdriveParams) -> Result<Self, ParamError> {
        positive("odrive.gear_ratio", params.gear_ratio)?;
        non_negative("odrive.rotor_inertia", params.rotor_inertia)?;
        non_negative("odrive.vel_gain", params.vel_gain)?;
        non_negative("odrive.vel_integrator_gain", params.vel_integrator_gain)?;
        non_negative("odrive.torque_limit", params.torque_limit)?;
        positive("odrive.vel_limit", params.vel_limit)?;
        positive("odrive.vel_ramp_rate", params.vel_ramp_rate)?;
        non_negative("odrive.coulomb_friction", params.coulomb_friction)?;
        positive("odrive.friction_smoothing", params.friction_smoothing)?;
        non_negative("odrive.viscous_friction", params.viscous_friction)?;
        if let Some(t) = params.watchdog_timeout {
            positive("odrive.watchdog_timeout", t)?;
        }
        for (field, p) in [
            ("odrive.encoder_period_ns", params.encoder_period_ns),
            ("odrive.heartbeat_period_ns", params.heartbeat_period_ns),
        ] {
            if p == 0 {
                return Err(ParamError::new(field, 0.0, "a period > 0"));
            }
        }
        Ok(Self::build(params))
    }

    const fn build(params: OdriveParams) -> Self {
        Self {
            params,
            state: AxisState::Idle,
            control_mode: ControlMode::VelocityControl,
            input_mode: InputMode::Passthrough,
            input_vel: 0.0,
            torque_ff: 0.0,
            vel_setpoint: 0.0,
            integrator: 0.0,
            torque: 0.0,
            errors: 0,
            disarm_reason: 0,
            procedure_result: procedure_result::SUCCESS,
            since_feed: 0.0,
            watchdog_timeout: params.watchdog_timeout,
            next_encoder_ns: params.encoder_period_ns,
            next_heartbeat_ns: params.heartbeat_period_ns,
        }
    }

    /// The parameters.
    #[must_use]
    pub const fn params(&self) -> &OdriveParams {
        &self.params
    }

    /// Applies one command as received from the bus. Returns the reply a request asks for.
    pub fn apply(&mut self, command: &Command) -> Option<OdriveFeedback> {
        match *command {
            Command::Estop => self.estop(),
            Command::GetError => {
                return Some(OdriveFeedback::Error {
                    active_errors: self.errors,
                    disarm_reason: self.disarm_reason,
                });
            }
            // The model answers the error request only; its heartbeat and estimates keep
            // their schedule.
            Command::GetHeartbeat | Command::GetEncoderEstimates => {}
            Command::SetAxisState(s) => self.set_axis_state(s),
            Command::SetControllerMode {
                control_mode,
                input_mode,
            } => self.set_controller_mode(control_mode, input_mode),
            Command::SetInputVel { vel, torque_ff } => {
                self.set_input_vel(f64::from(vel), f64::from(torque_ff));
            }
            Command::ClearErrors { .. } => self.clear_errors(),
        }
        None
    }

    /// `Set_Axis_State`: `Idle` or `ClosedLoopControl`; others are refused.
    pub fn set_axis_state(&mut self, requested: AxisState) {
        match requested {
            AxisState::Idle => {
                if self.state == AxisState::ClosedLoopControl {
                    self.procedure_result = procedure_result::CANCELLED;
                }
                self.disarm();
            }
            AxisState::ClosedLoopControl => {
                if self.errors != 0 {
                    self.procedure_result = procedure_result::DISARMED;
                } else if self.state != AxisState::ClosedLoopControl {
                    self.state = AxisState::ClosedLoopControl;
                    self.procedure_result = procedure_result::BUSY;
                    self.integrator = 0.0;
                    self.since_feed = 0.0;
                    // The ramp starts from zero (a robot enabling at rest); in passthrough
                    // the setpoint in force applies at once.
                    self.vel_setpoint = 0.0;
                }
            }
            _ => self.procedure_result = procedure_result::INVALID_STATE,
        }
    }

    /// `Set_Controller_Mode`. Only velocity control is modelled: in another control mode the
    /// loop outputs only the torque feed-forward.
    pub fn set_controller_mode(&mut self, control_mode: ControlMode, input_mode: InputMode) {
        self.control_mode = control_mode;
        self.input_mode = input_mode;
    }

    /// `Set_Input_Vel`: velocity setpoint (rev/s, motor side) and torque feed-forward (N·m);
    /// feeds the watchdog. Non-finite values are ignored (the setpoint is kept).
    pub fn set_input_vel(&mut self, vel: f64, torque_ff: f64) {
        if vel.is_finite() && torque_ff.is_finite() {
            self.input_vel = vel;
            self.torque_ff = torque_ff;
        }
        self.since_feed = 0.0;
    }

    /// `Clear_Errors`: clears the error bits (the axis stays in its state, `Idle` after a
    /// fault).
    pub fn clear_errors(&mut self) {
        self.errors = 0;
        self.disarm_reason = 0;
    }

    /// `Estop`: sets [`ESTOP_REQUESTED`] and disarms.
    pub fn estop(&mut self) {
        self.fault(ESTOP_REQUESTED);
    }

    /// Enables the watchdog with `timeout` seconds, or disables it (`None`).
    ///
    /// # Errors
    /// [`ParamError`] unless the timeout is finite and `> 0`.
    pub fn set_watchdog(&mut self, timeout: Option<f64>) -> Result<(), ParamError> {
        if let Some(t) = timeout {
            positive("odrive.watchdog_timeout", t)?;
        }
        self.watchdog_timeout = timeout;
        self.since_feed = 0.0;
        Ok(())
    }

    /// The axis state.
    #[must_use]
    pub const fn axis_state(&self) -> AxisState {
        self.state
    }

    /// Active error bits.
    #[must_use]
    pub const fn errors(&self) -> u32 {
        self.errors
    }

    /// The control and input mode.
    #[must_use]
    pub const fn controller_mode(&self) -> (ControlMode, InputMode) {
        (self.control_mode, self.input_mode)
    }

    /// The velocity setpoint the loop is tracking now (after the ramp), rev/s.
    #[must_use]
    pub const fn vel_setpoint(&self) -> f64 {
        self.vel_setpoint
    }

    /// The motor torque the loop commands, N·m.
    #[must_use]
    pub const fn torque(&self) -> f64 {
        self.torque
    }

    /// The heartbeat as it would be sent now.
    #[must_use]
    pub fn heartbeat(&self) -> Heartbeat {
        Heartbeat {
            axis_error: self.errors | self.disarm_reason,
            axis_state: self.state,
            procedure_result: self.procedure_result,
            trajectory_done: true,
        }
    }

    fn disarm(&mut self) {
        self.state = AxisState::Idle;
        self.integrator = 0.0;
        self.torque = 0.0;
    }

    fn fault(&mut self, bit: u32) {
        self.errors |= bit;
        if self.state == AxisState::ClosedLoopControl {
            self.disarm_reason |= bit;
            self.procedure_result = procedure_result::DISARMED;
        }
        self.disarm();
    }

    /// The loop's torque for motor speed `vel` (rev/s).
    fn control(&mut self, h: f64, vel: f64) -> f64 {
        let p = self.params;
        self.vel_setpoint = match self.input_mode {
            InputMode::VelRamp => {
                let step = p.vel_ramp_rate * h;
                self.vel_setpoint + (self.input_vel - self.vel_setpoint).clamp(-step, step)
            }
            _ => self.input_vel,
        }
        .clamp(-p.vel_limit, p.vel_limit);
        if self.control_mode != ControlMode::VelocityControl {
            return self.torque_ff.clamp(-p.torque_limit, p.torque_limit);
        }
        let err = self.vel_setpoint - vel;
        let raw = self.torque_ff + p.vel_gain * err + self.integrator;
        let torque = raw.clamp(-p.torque_limit, p.torque_limit);
        if torque == raw {
            self.integrator += p.vel_integrator_gain * err * h;
        } else {
            self.integrator *= 0.99;
        }
        torque
    }
}

impl Drive for OdriveAxis {
    type Feedback = OdriveFeedback;

    fn gear_ratio(&self) -> f64 {
        self.params.gear_ratio
    }

    fn reflected_inertia(&self) -> f64 {
        self.params.rotor_inertia * self.params.gear_ratio * self.params.gear_ratio
    }

    fn advance(&mut self, h: f64, motor: Shaft) -> f64 {
        if self.state == AxisState::ClosedLoopControl {
            self.since_feed += h;
            if self.watchdog_timeout.is_some_and(|t| self.since_feed > t) {
                self.fault(WATCHDOG_TIMER_EXPIRED);
            }
        }
        self.torque = if self.state == AxisState::ClosedLoopControl {
            self.control(h, motor.speed / core::f64::consts::TAU)
        } else {
            0.0
        };
        let p = &self.params;
        let (w, ws) = (motor.speed, p.friction_smoothing);
        let friction =
            p.coulomb_friction * w / (w * w + ws * ws).sqrt() + p.viscous_friction * motor.speed;
        (self.torque - friction) * p.gear_ratio
    }

    fn next_feedback_ns(&self) -> u64 {
        self.next_encoder_ns.min(self.next_heartbeat_ns)
    }

    fn emit_feedback(&mut self, now_ns: u64, motor: Shaft, out: &mut Vec<OdriveFeedback>) {
        if now_ns >= self.next_heartbeat_ns {
            out.push(OdriveFeedback::Heartbeat(self.heartbeat()));
            let p = self.params.heartbeat_period_ns;
            self.next_heartbeat_ns = (now_ns / p + 1) * p;
        }
        if now_ns >= self.next_encoder_ns {
            out.push(OdriveFeedback::EncoderEstimates {
                pos: motor.angle / core::f64::consts::TAU,
                vel: motor.speed / core::f64::consts::TAU,
            });
            let p = self.params.encoder_period_ns;
            self.next_encoder_ns = (now_ns / p + 1) * p;
        }
    }
}
