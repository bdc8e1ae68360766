//! How every run's log reads the robot's status: a `/rosout` line when its state (with the
//! fault) changes and when its heading source changes, in the DBC's names. The simulator,
//! the runner and boardsim feed a [`StatusLog`] what the firmware reports; the words, the
//! levels and what counts as a change are decided here once.

use firmware::protocol::robot::{Fault, HeadingSource, RobotState};

use crate::msg::Log;

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
}
