//! What every run's log says of its firmware, decided once: a `/rosout` line when the state
//! (with the fault, and what a CiA 402 drive's bus said of it) or the heading source changes,
//! in the DBC's names ([`StatusLog`]), and at a fixed cadence of control steps the core's
//! snapshot (`/joint_states`, `/diagnostics`) and its odometry (`/odom`, `/tf`) with the
//! ground truth beside it when the run has a simulated robot ([`CoreLog`]). The simulator and
//! the runner feed a [`CoreLog`] their core at every step, and it says each parameter change
//! ([`config_lines`]); `hostsim plant` and boardsim, which
//! see the firmware only through its frames, feed a [`StatusLog`] and [`CoreLog::odometry`]
//! what the frames say.

use firmware::Config;
use firmware::control::Controller;
use firmware::params::{PARAMS, ParamType};
use firmware::protocol::robot::{Fault, HeadingSource, RobotState};

use crate::msg::Log;
use crate::write::{LogError, McapLog, OdometrySource};

/// The `/rosout` line for the robot's state: its level (as `/diagnostics` rates them: a
/// fault is an error, an e-stop a warning) and text, `state FAULT, fault MOTOR_STALE`.
#[must_use]
pub fn state_line(state: RobotState, fault: Fault) -> (u8, String) {
    let level = match state {
        RobotState::Fault => Log::ERROR,
        RobotState::Estop => Log::WARN,
        _ => Log::INFO,
    };
    (level, format!("state {state}, fault {fault}"))
}

/// The `/rosout` line for the firmware's heading source changing to `source`: its level and
/// text. Losing the gyro is a warning (the robot keeps driving on wheel heading), getting it
/// (back) is information. `gyro_timeout_ms` is the configuration's `odometry.gyro_timeout_ms`.
#[must_use]
pub fn heading_source_line(source: HeadingSource, gyro_timeout_ms: u32) -> (u8, String) {
    match source {
        HeadingSource::WheelsGyroSilent => (
            Log::WARN,
            format!(
                "heading source WHEELS_GYRO_SILENT: no valid IMU_YAW_RATE for {gyro_timeout_ms} ms, \
                 the wheels give the heading"
            ),
        ),
        HeadingSource::Gyro => (
            Log::INFO,
            "heading source GYRO: IMU_YAW_RATE alive, the gyro gives the heading".to_string(),
        ),
        HeadingSource::Wheels => (Log::INFO, "heading source WHEELS".to_string()),
    }
}

/// The `/rosout` lines for the configuration in force changing from `old` to `new`: one per
/// parameter whose value changed, `gains.kp 1.2 -> 1.5, config 0x1a2b -> 0x3c4d` (a value the
/// configuration lacks is `-`).
#[must_use]
pub fn config_lines(old: &Config, new: &Config) -> Vec<String> {
    let (old_id, new_id) = (old.id(), new.id());
    let show = |ty: ParamType, raw: Option<u32>| match (ty, raw) {
        (_, None) => "-".to_string(),
        (ParamType::Real32, Some(raw)) => f32::from_bits(raw).to_string(),
        (_, Some(raw)) => raw.to_string(),
    };
    PARAMS
        .iter()
        .filter_map(|p| {
            let (a, b) = (p.read(old).ok(), p.read(new).ok());
            (a != b).then(|| {
                format!(
                    "{} {} -> {}, config 0x{old_id:04x} -> 0x{new_id:04x}",
                    p.name,
                    show(p.ty, a),
                    show(p.ty, b)
                )
            })
        })
        .collect()
}

/// The status last logged, and the lines its changes make.
#[derive(Debug, Clone, Default)]
pub struct StatusLog {
    state: Option<(RobotState, Fault)>,
    heading: HeadingSource,
}

impl StatusLog {
    /// A log that has said nothing yet: the first state it is given is a change. The heading
    /// source starts as the firmware's does, `WHEELS`.
    #[must_use]
    pub const fn new() -> Self {
        Self {
            state: None,
            heading: HeadingSource::Wheels,
        }
    }

    /// A log whose run starts in `state` with `fault` without saying so (a run that begins
    /// with the firmware's boot, which is `DISABLED` with no fault).
    #[must_use]
    pub const fn starting_in(mut self, state: RobotState, fault: Fault) -> Self {
        self.state = Some((state, fault));
        self
    }

    /// The line for the robot's state, if it changed.
    pub fn state(&mut self, state: RobotState, fault: Fault) -> Option<(u8, String)> {
        (self.state != Some((state, fault))).then(|| {
            self.state = Some((state, fault));
            state_line(state, fault)
        })
    }

    /// The line for the heading source, if it changed (`gyro_timeout_ms` as
    /// [`heading_source_line`] takes it).
    pub fn heading(&mut self, source: HeadingSource, gyro_timeout_ms: u32) -> Option<(u8, String)> {
        (self.heading != source).then(|| {
            self.heading = source;
            heading_source_line(source, gyro_timeout_ms)
        })
    }
}

/// A pose `[x, y, heading]` (m, m, rad) and a body twist `[vx, vy, wz]`.
pub type PoseTwist = ([f64; 3], [f64; 3]);

/// What a run logs of its core at each control step.
#[derive(Debug, Clone)]
pub struct CoreLog {
    status: StatusLog,
    /// The configuration in force at the last step (`None` before the first).
    config: Option<Config>,
    snapshot_every: u32,
    pose_every: u32,
    steps: u64,
}

/// What changed at a step (for a caller that keeps its own record of the run).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Changes {
    /// The state or the fault.
    pub state: bool,
    /// The heading source.
    pub heading: bool,
    /// The configuration in force (a parameter set over CAN).
    pub config: bool,
}

impl CoreLog {
    /// Status lines at every change; the snapshot every `snapshot_every` steps and the
    /// odometry every `pose_every` steps, from the first (0: never).
    #[must_use]
    pub const fn new(snapshot_every: u32, pose_every: u32) -> Self {
        Self {
            status: StatusLog::new(),
            config: None,
            snapshot_every,
            pose_every,
            steps: 0,
        }
    }

    /// The same, for a run that starts with the core's boot (`DISABLED`, no fault) without
    /// saying so ([`StatusLog::starting_in`]).
    #[must_use]
    pub const fn from_boot(mut self) -> Self {
        self.status = self.status.starting_in(RobotState::Disabled, Fault::None);
        self
    }

    /// A new file of the same run: its first step says the status again.
    pub fn new_file(&mut self) {
        self.status = StatusLog::new();
    }

    /// The log of the control step the core `ctl` just ran at `t_ns` (written to `log` if
    /// there is one); `truth`, the simulated robot's pose and twist, beside the odometry.
    /// Returns what changed.
    ///
    /// # Errors
    /// The log's [`LogError`].
    pub fn step(
        &mut self,
        log: Option<&mut McapLog>,
        t_ns: u64,
        ctl: &Controller,
        truth: Option<&dyn Fn() -> PoseTwist>,
    ) -> Result<Changes, LogError> {
        let due = |n: u32| n > 0 && self.steps.is_multiple_of(u64::from(n));
        let (snapshot, pose) = (due(self.snapshot_every), due(self.pose_every));
        self.steps += 1;
        self.write(log, t_ns, ctl, truth, snapshot, pose)
    }

    /// The log of the core's last state (after its shutdown): status lines, the snapshot and
    /// the odometry whatever the cadence.
    ///
    /// # Errors
    /// The log's [`LogError`].
    pub fn last(
        &mut self,
        log: Option<&mut McapLog>,
        t_ns: u64,
        ctl: &Controller,
        truth: Option<&dyn Fn() -> PoseTwist>,
    ) -> Result<Changes, LogError> {
        self.write(log, t_ns, ctl, truth, true, true)
    }

    fn write(
        &mut self,
        mut log: Option<&mut McapLog>,
        t_ns: u64,
        ctl: &Controller,
        truth: Option<&dyn Fn() -> PoseTwist>,
        snapshot: bool,
        pose: bool,
    ) -> Result<Changes, LogError> {
        let mut changes = Changes::default();
        let timeout_ms = ctl.config().odometry.gyro_timeout_ms;
        // A CiA 402 fault's line says what the bus said (node, object, code, statusword).
        let state_line = self
            .status
            .state(ctl.state(), ctl.fault())
            .map(|(level, text)| match ctl.drive_issue() {
                Some(issue) if ctl.state() == RobotState::Fault && issue.fault() == ctl.fault() => {
                    (level, format!("{text} ({issue})"))
                }
                _ => (level, text),
            });
        for (line, changed) in [
            (state_line, &mut changes.state),
            (
                self.status.heading(ctl.heading_source(), timeout_ms),
                &mut changes.heading,
            ),
        ] {
            if let Some((level, text)) = line {
                *changed = true;
                if let Some(l) = log.as_deref_mut() {
                    l.text(t_ns, level, &text)?;
                }
            }
        }
        // Copied only when it changed (the first step, a parameter set): not at every step.
        if self.config.as_ref() != Some(ctl.config())
            && let Some(old) = self.config.replace(*ctl.config())
        {
            changes.config = true;
            if let Some(l) = log.as_deref_mut() {
                for text in config_lines(&old, ctl.config()) {
                    l.text(t_ns, Log::INFO, &text)?;
                }
            }
        }
        let Some(log) = log else {
            return Ok(changes);
        };
        if snapshot || pose {
            let s = ctl.snapshot();
            if snapshot {
                log.snapshot(t_ns, &s)?;
            }
            if pose {
                let odom = [s.pose.x, s.pose.y, s.pose.heading].map(f64::from);
                let twist = [s.measured.vx, s.measured.vy, s.measured.wz].map(f64::from);
                Self::odometry(log, t_ns, (odom, twist), truth.map(|t| t()))?;
            }
        }
        Ok(changes)
    }

    /// The firmware's odometry, and the simulated robot's `truth` beside it if there is one:
    /// `/odom`, `/ground_truth/odom` and their `/tf`.
    ///
    /// # Errors
    /// The log's [`LogError`].
    pub fn odometry(
        log: &mut McapLog,
        t_ns: u64,
        (pose, twist): PoseTwist,
        truth: Option<PoseTwist>,
    ) -> Result<(), LogError> {
        log.odometry(t_ns, OdometrySource::Firmware, pose, twist)?;
        if let Some((pose, twist)) = truth {
            log.odometry(t_ns, OdometrySource::GroundTruth, pose, twist)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_change_is_one_line_in_the_dbc_names() {
        let mut log = StatusLog::new();
        assert_eq!(
            log.state(RobotState::Disabled, Fault::None),
            Some((Log::INFO, "state DISABLED, fault NONE".into()))
        );
        assert_eq!(log.state(RobotState::Disabled, Fault::None), None);
        assert_eq!(
            log.state(RobotState::Fault, Fault::MotorStale),
            Some((Log::ERROR, "state FAULT, fault MOTOR_STALE".into()))
        );
        assert_eq!(
            log.state(RobotState::Estop, Fault::None).unwrap().0,
            Log::WARN
        );
        assert_eq!(log.heading(HeadingSource::Wheels, 100), None);
        let (level, text) = log.heading(HeadingSource::WheelsGyroSilent, 100).unwrap();
        assert_eq!(level, Log::WARN);
        assert!(text.contains("for 100 ms"), "{text}");
        let mut booted = StatusLog::new().starting_in(RobotState::Disabled, Fault::None);
        assert_eq!(booted.state(RobotState::Disabled, Fault::None), None);
    }

    #[test]
    fn a_parameter_change_is_one_line_with_both_values_and_both_ids() {
        let old = Config::dji_m3508_example();
        let mut new = old;
        new.gains.kp = 1.5;
        let want = format!(
            "gains.kp 1.2 -> 1.5, config 0x{:04x} -> 0x{:04x}",
            old.id(),
            new.id()
        );
        assert_eq!(config_lines(&old, &new), [want]);
        assert!(config_lines(&old, &old).is_empty());
    }
}
