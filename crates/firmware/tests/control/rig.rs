//! The shared rig: a controller with scripted drives, and the helpers that read its frames.

pub use firmware::CanFrame;
pub use firmware::config::{Config, Drive, Geometry};
pub use firmware::control::{Controller, Instant, Outbox};
pub use firmware::protocol::dji::{self, CurrentCommand, EscModel};
pub use firmware::protocol::odrive::{self, AxisState, ControlMode, NodeId};
pub use firmware::protocol::robot::{self, Command, Fault, ModeRequest, RobotState, TwistCmd};
pub use proptest::prelude::*;

pub use crate::canopen_bus::{ScriptedBus, sw};

/// One millisecond of simulated time per tick (the default 1 kHz loop).
pub const TICK_US: u64 = 1_000;

/// A controller with scripted drives: each alive motor reports `speed` (wheel rad/s in the
/// motor's own sign) at the drive's feedback rate, with a consistent angle.
pub struct Rig {
    pub ctl: Controller,
    pub config: Config,
    pub now_us: u64,
    pub alive: [bool; 4],
    /// Motor-side wheel speed each drive reports, rad/s.
    pub speed: [f32; 4],
    /// Motor-side rotor angle, counts (DJI) / turns (ODrive), unwrapped.
    pub rotor: [f64; 4],
    /// DJI: a stuck encoder reports this rotor angle and rpm whatever the rotor does.
    pub frozen: [Option<(u16, i16)>; 4],
    /// ODrive: the axis error each heartbeat reports, until a `Clear_Errors` to the node
    /// clears it (unless `error_persists`).
    pub axis_error: [u32; 4],
    /// ODrive: the cause of the axis error is still there: `Clear_Errors` does not clear it.
    pub error_persists: [bool; 4],
    /// Every frame emitted, with its time.
    pub log: Vec<(u64, CanFrame)>,
    /// The `seq` of the next twist (the alive counter a host increments).
    pub seq: u8,
    /// CiA 402: the scripted nodes.
    pub canopen: ScriptedBus,
}

impl Rig {
    pub fn new(config: Config) -> Self {
        let canopen = ScriptedBus::new(&config);
        Self {
            ctl: Controller::new(&config).expect("valid config"),
            config,
            now_us: 0,
            alive: [true; 4],
            speed: [0.0; 4],
            rotor: [0.0; 4],
            frozen: [None; 4],
            axis_error: [0; 4],
            error_persists: [false; 4],
            log: Vec::new(),
            seq: 0,
            canopen,
        }
    }

    pub fn dji() -> Self {
        Self::new(Config::dji_m3508_example())
    }

    /// ODrive example with the watchdog stop "at once", so setpoints reach zero in one period.
    pub fn odrive() -> Self {
        let mut c = Config::odrive_example();
        c.limits.stop_linear_decel = f32::INFINITY;
        c.limits.stop_angular_decel = f32::INFINITY;
        Self::new(c)
    }

    pub fn now(&self) -> Instant {
        Instant::from_micros(self.now_us)
    }

    /// A host's frame: to the controller, and seen by the scripted CiA 402 nodes.
    pub fn send(&mut self, cmd: Command) {
        let frame = cmd.to_can_frame();
        self.ctl.on_frame(self.now(), &frame);
        self.canopen.take(self.now_us, &[frame]);
    }

    pub fn raw(&mut self, frame: CanFrame) {
        self.ctl.on_frame(self.now(), &frame);
    }

    /// Sends a twist as a host does: `seq` one more than the last one's.
    pub fn twist(&mut self, vx: f32, vy: f32, wz: f32) {
        let seq = self.seq;
        self.seq = seq.wrapping_add(1);
        self.twist_seq(vx, vy, wz, seq);
    }

    /// Sends a twist with this `seq` (the counter of `twist` is left alone).
    pub fn twist_seq(&mut self, vx: f32, vy: f32, wz: f32, seq: u8) {
        self.send(Command::Twist(TwistCmd { vx, vy, wz, seq }));
    }

    pub fn feed_motors(&mut self) {
        let ms = self.now_us / 1000;
        match self.config.drive {
            Drive::Dji {
                model,
                esc_ids,
                gear_ratio,
                ..
            } => {
                for w in 0..4 {
                    let rotor_rad_s = self.speed[w] * gear_ratio;
                    self.rotor[w] += f64::from(rotor_rad_s) * 1e-3 * 8192.0 / std::f64::consts::TAU;
                    if !self.alive[w] {
                        continue;
                    }
                    let (rotor_angle, rotor_speed_rpm) = self.frozen[w].unwrap_or((
                        self.rotor[w].rem_euclid(8192.0) as u16,
                        (rotor_rad_s * 60.0 / std::f32::consts::TAU).round() as i16,
                    ));
                    let fb = dji::Feedback {
                        model,
                        esc: dji::EscId::new(esc_ids[w]).unwrap(),
                        rotor_angle,
                        rotor_speed_rpm,
                        torque_current: 0,
                        temperature_c: 30,
                    };
                    self.raw(fb.to_can_frame());
                }
            }
            Drive::Odrive {
                node_ids,
                gear_ratio,
                ..
            } => {
                for w in 0..4 {
                    let turns_s = self.speed[w] * gear_ratio / std::f32::consts::TAU;
                    self.rotor[w] += f64::from(turns_s) * 1e-3;
                    if !self.alive[w] {
                        continue;
                    }
                    let node = NodeId::new(node_ids[w]).unwrap();
                    if ms.is_multiple_of(10) {
                        let est = odrive::Feedback::EncoderEstimates {
                            pos: self.rotor[w] as f32,
                            vel: turns_s,
                        };
                        self.raw(est.to_can_frame(node));
                    }
                    if ms.is_multiple_of(100) {
                        self.raw(odrive_heartbeat(
                            node.get(),
                            AxisState::ClosedLoopControl,
                            self.axis_error[w],
                        ));
                    }
                }
            }
            Drive::Cia402(_) => {
                for frame in self.canopen.feed(self.now_us) {
                    self.raw(frame);
                }
            }
        }
    }

    /// Feeds this millisecond's motor feedback, runs one step, advances the clock.
    pub fn tick(&mut self) -> Outbox {
        self.feed_motors();
        let out = self.ctl.step(self.now());
        self.canopen.take(self.now_us, &out);
        for f in &out {
            self.log.push((self.now_us, *f));
            if let Drive::Odrive { node_ids, .. } = self.config.drive
                && let Ok(a) = odrive::Command::decode(f)
                && let odrive::Command::ClearErrors { .. } = a.msg
                && let Some(w) = node_ids.iter().position(|&n| n == a.node.get())
                && !self.error_persists[w]
            {
                self.axis_error[w] = 0;
            }
        }
        self.now_us += TICK_US;
        out
    }

    pub fn run_ms(&mut self, ms: u64) -> Vec<Outbox> {
        (0..ms).map(|_| self.tick()).collect()
    }

    /// Runs until `pred` holds for a step's output; returns the time it first held.
    pub fn run_until(&mut self, max_ms: u64, pred: impl Fn(&Rig, &Outbox) -> bool) -> Option<u64> {
        for _ in 0..max_ms {
            let t = self.now_us;
            let out = self.tick();
            if pred(self, &out) {
                return Some(t);
            }
        }
        None
    }

    pub fn enable(&mut self) {
        self.send(Command::Mode(ModeRequest::Enable));
    }

    /// Enables after 20 ms, commands `[vx, vy, wz]` every 10 ms for 300 ms and once more,
    /// then the host falls silent; returns the time of that last command, µs.
    pub fn drive_then_fall_silent(&mut self, [vx, vy, wz]: [f32; 3]) -> u64 {
        self.run_ms(20);
        self.enable();
        for _ in 0..30 {
            self.twist(vx, vy, wz);
            self.run_ms(10);
        }
        self.twist(vx, vy, wz);
        self.now_us
    }

    pub fn status(&self) -> robot::Status {
        self.log
            .iter()
            .rev()
            .find_map(|(_, f)| match robot::Telemetry::decode(f) {
                Ok(robot::Telemetry::Status(s)) => Some(s),
                _ => None,
            })
            .expect("a status frame was sent")
    }

    /// The last `STATUS_COUNTERS` sent, with its time.
    pub fn counters(&self) -> (u64, robot::StatusCounters) {
        self.log
            .iter()
            .rev()
            .find_map(|(t, f)| match robot::Telemetry::decode(f) {
                Ok(robot::Telemetry::StatusCounters(c)) => Some((*t, c)),
                _ => None,
            })
            .expect("a status counters frame was sent")
    }
}

/// The ODrive velocity setpoints (rev/s) in a step's output, in wheel order; None if absent.
pub fn odrive_vels(config: &Config, out: &Outbox) -> Option<[f32; 4]> {
    let Drive::Odrive { node_ids, .. } = config.drive else {
        panic!("not an ODrive config")
    };
    let mut vels = [f32::NAN; 4];
    for f in out {
        if let Ok(a) = odrive::Command::decode(f)
            && let odrive::Command::SetInputVel { vel, .. } = a.msg
            && let Some(w) = node_ids.iter().position(|&n| n == a.node.get())
        {
            vels[w] = vel;
        }
    }
    vels.iter().all(|v| !v.is_nan()).then_some(vels)
}

/// The DJI currents (A, motor sign) in a step's output, ESC 1-4.
pub fn dji_currents(out: &Outbox) -> Option<[f32; 4]> {
    out.iter().find_map(|f| {
        CurrentCommand::decode(f, EscModel::C620)
            .ok()
            .map(|c| c.amps())
    })
}

pub fn all_zero(v: [f32; 4]) -> bool {
    v.iter().all(|&x| x == 0.0)
}

/// Drives forward, stops commanding at `t_last`, and returns the time zero setpoints first
/// appear and the last nonzero one before that.
pub fn watchdog_zero_time(rig: &mut Rig, with_status_polls: bool) -> (u64, u64) {
    let t_last = rig.drive_then_fall_silent([0.3, 0.1, 0.2]);
    let mut zero_at = None;
    for ms in 0..400u32 {
        if with_status_polls && ms.is_multiple_of(5) {
            rig.send(Command::StatusRequest);
        }
        let t = rig.now_us;
        let out = rig.tick();
        if let Some(v) = odrive_vels(&rig.config, &out) {
            if all_zero(v) {
                zero_at.get_or_insert(t);
            } else {
                assert!(zero_at.is_none(), "motion resumed at {t}");
            }
        }
    }
    (t_last, zero_at.expect("zero setpoints were sent"))
}

/// Streams `twist` every 10 ms for `ms` while the wheels follow the core's setpoints with a
/// 10 ms lag (so the velocity loops work and command current).
pub fn follow(rig: &mut Rig, [vx, vy, wz]: [f32; 3], ms: u64) {
    for k in 0..ms {
        if k % 10 == 0 {
            rig.twist(vx, vy, wz);
        }
        rig.tick();
        let sp = rig.ctl.snapshot().wheel_setpoints.0;
        // Motor sign: the right-hand motors are mirrored.
        for (w, s) in [sp[0], -sp[1], sp[2], -sp[3]].into_iter().enumerate() {
            rig.speed[w] += (s - rig.speed[w]) * 0.1;
        }
    }
}

/// An ODrive enabled and driving forward after its first heartbeats.
pub fn odrive_driving() -> Rig {
    let mut rig = Rig::odrive();
    rig.run_ms(150);
    rig.enable();
    rig.twist(0.2, 0.0, 0.0);
    rig.run_ms(50);
    assert_eq!(rig.ctl.state(), RobotState::Enabled);
    rig
}

/// An ODrive heartbeat from `node` (trajectory done, no procedure result).
pub fn odrive_heartbeat(node: u8, axis_state: AxisState, axis_error: u32) -> CanFrame {
    odrive::Feedback::Heartbeat(odrive::Heartbeat {
        axis_error,
        axis_state,
        procedure_result: 0,
        trajectory_done: true,
    })
    .to_can_frame(NodeId::new(node).unwrap())
}
