//! The bring-up check, and what its observations say about a robot's wiring.
//!
//! A new robot's first hour goes to signs and wheel order: a motor mounted the other way than
//! `drive.inverted` says, drives wired to other wheels than `drive.esc_ids` (or
//! `drive.node_ids`) says. With the robot on blocks, the check drives each configured wheel
//! in turn through the firmware's `WHEEL_TEST` (only a disabled robot runs it: a quarter of
//! the current limit, a bounded time) and someone watches which wheel turns, and which way.
//! No encoder can tell that: the drive that turned reports its own motion, with the sign the
//! configuration gives it, so to the firmware every wheel turned the right way. On a real
//! robot the person watching answers (`mecanum-drive check`, the Python package); in the
//! simulator the plant's ground truth does ([`run_check`]).
//!
//! [`diagnose`] turns the four observations into the fix: configured wheel `i` drove the
//! physical wheel `p` (`p` is on the drive id the configuration gives `i`) in direction `d`,
//! so wheel `p`'s id is the configured `ids[i]`, and its motor is mounted as configured for
//! `i` if `d` is forward, the other way if backward. The Python package's check computes the
//! same rule (`mecanum_drive.check`); the Python tests hold the two to the same answers.

use firmware::config::{Cia402Drive, Config, Drive};
use firmware::control::Fault;
use firmware::protocol::robot::{self, RobotState, WheelTestResult};
use serde::Serialize;

use crate::engine::{LogOptions, SimError, run_observed};
use crate::nodes::drives::SimDrives;
use crate::nodes::plant::ParamError;
use crate::nodes::plant::PlantSpec;
use crate::scenario::{Action, Scenario, ScenarioError, WheelTestSpec};

/// Why the simulated check could not run.
#[derive(Debug, thiserror::Error)]
pub enum CheckError {
    /// The plant refuses a value (of the configuration or the `plant` wiring).
    #[error("plant: {0}")]
    Plant(#[from] ParamError),
    /// The scenario of a test could not be made.
    #[error(transparent)]
    Scenario(#[from] ScenarioError),
    /// The run failed (a configuration the firmware refuses).
    #[error(transparent)]
    Sim(#[from] SimError),
}

/// Wheel names in the project's order.
pub const WHEEL_NAMES: [&str; 4] = ["FL", "FR", "RL", "RR"];

/// A wheel that turned less than this (rad, either way) in a test did not turn.
pub const TURNED_MIN_ANGLE: f64 = 0.3;

/// How a robot is wired: a drive id (ESC id, ODrive or CANopen node id) and a mounting sign
/// per wheel. (A CiA 402 robot's `drive.axes` are not part of it: a dual-axis drive's two
/// wheels swapped show as wheels that do not turn where expected, not as a swap to propose.)
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Wiring {
    /// `drive.esc_ids` (DJI) or `drive.node_ids` (ODrive, CiA 402), FL, FR, RL, RR.
    pub ids: [u8; 4],
    /// `drive.inverted`.
    pub inverted: [bool; 4],
    /// `true` for node ids (`node_ids`), `false` for DJI (`esc_ids`).
    pub odrive: bool,
}

impl Wiring {
    /// The wiring a configuration states.
    #[must_use]
    pub const fn of(config: &Config) -> Self {
        match config.drive {
            Drive::Dji {
                esc_ids, inverted, ..
            } => Self {
                ids: esc_ids,
                inverted,
                odrive: false,
            },
            Drive::Odrive {
                node_ids, inverted, ..
            }
            | Drive::Cia402(Cia402Drive {
                node_ids, inverted, ..
            }) => Self {
                ids: node_ids,
                inverted,
                odrive: true,
            },
        }
    }

    /// The configuration key of the ids: `esc_ids` or `node_ids`.
    #[must_use]
    pub const fn ids_key(&self) -> &'static str {
        if self.odrive { "node_ids" } else { "esc_ids" }
    }

    /// `config` with this wiring.
    #[must_use]
    pub fn apply(&self, config: &Config) -> Config {
        let mut c = *config;
        match &mut c.drive {
            Drive::Dji {
                esc_ids, inverted, ..
            } => (*esc_ids, *inverted) = (self.ids, self.inverted),
            Drive::Odrive {
                node_ids, inverted, ..
            }
            | Drive::Cia402(Cia402Drive {
                node_ids, inverted, ..
            }) => (*node_ids, *inverted) = (self.ids, self.inverted),
        }
        c
    }
}

/// What was seen when one configured wheel was tested: which physical wheel turned, and
/// whether it rolled the robot forward.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Seen {
    /// The wheel that turned, 0..=3 (FL, FR, RL, RR).
    pub wheel: usize,
    /// It turned so as to roll the robot forward.
    pub forward: bool,
}

/// The verdict on one configured wheel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// The right wheel turned the right way.
    Right,
    /// The right wheel turned backwards: its motor is mounted the other way than configured.
    Reversed,
    /// Another wheel turned (forward or not): the drive on this wheel's id is on that wheel.
    OtherWheel(Seen),
    /// No wheel turned: no drive answers to this id, or it is not connected to a wheel.
    Nothing,
}

/// The check's conclusion.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Diagnosis {
    /// Per configured wheel.
    pub verdicts: [Verdict; 4],
    /// The corrected wiring, if the observations determine it (every wheel seen turning,
    /// each physical wheel once).
    pub fixed: Option<Wiring>,
    /// Why there is no fix, if there is none.
    pub unresolved: Option<String>,
}

impl Diagnosis {
    /// `true` if every wheel turned as configured.
    #[must_use]
    pub fn is_right(&self) -> bool {
        self.verdicts.iter().all(|v| *v == Verdict::Right)
    }

    /// The configuration lines that fix the wiring, under `[drive]`: only the keys that
    /// change. Empty when nothing needs fixing or nothing can be said.
    #[must_use]
    pub fn fix_lines(&self, configured: &Wiring) -> Vec<String> {
        let Some(fixed) = self.fixed else {
            return Vec::new();
        };
        let mut lines = Vec::new();
        if fixed.ids != configured.ids {
            let ids: Vec<String> = fixed.ids.iter().map(u8::to_string).collect();
            lines.push(format!("{} = [{}]", configured.ids_key(), ids.join(", ")));
        }
        if fixed.inverted != configured.inverted {
            let inv: Vec<String> = fixed.inverted.iter().map(bool::to_string).collect();
            lines.push(format!("inverted = [{}]", inv.join(", ")));
        }
        lines
    }
}

/// The wiring the observations imply (see the [module documentation](self)).
#[must_use]
pub fn diagnose(configured: &Wiring, seen: [Option<Seen>; 4]) -> Diagnosis {
    let verdicts: [Verdict; 4] = core::array::from_fn(|i| match seen[i] {
        None => Verdict::Nothing,
        Some(s) if s.wheel == i && s.forward => Verdict::Right,
        Some(s) if s.wheel == i => Verdict::Reversed,
        Some(s) => Verdict::OtherWheel(s),
    });
    let mut fixed = *configured;
    let mut claimed: [Option<usize>; 4] = [None; 4];
    let mut unresolved = None;
    for (i, s) in seen.iter().enumerate() {
        let Some(s) = s else {
            unresolved.get_or_insert_with(|| {
                format!(
                    "no wheel turned when {} was tested: no drive answers to {} {}, or it \
                     drives no wheel",
                    WHEEL_NAMES[i],
                    configured.ids_key(),
                    configured.ids[i]
                )
            });
            continue;
        };
        if s.wheel > 3 {
            unresolved.get_or_insert_with(|| format!("wheel index {} out of 0..=3", s.wheel));
            continue;
        }
        if let Some(j) = claimed[s.wheel] {
            unresolved.get_or_insert_with(|| {
                format!(
                    "{} turned when {} and when {} were tested: one drive answers to two ids?",
                    WHEEL_NAMES[s.wheel], WHEEL_NAMES[j], WHEEL_NAMES[i]
                )
            });
            continue;
        }
        claimed[s.wheel] = Some(i);
        fixed.ids[s.wheel] = configured.ids[i];
        fixed.inverted[s.wheel] = configured.inverted[i] ^ !s.forward;
    }
    Diagnosis {
        verdicts,
        fixed: unresolved.is_none().then_some(fixed),
        unresolved,
    }
}

/// What one wheel test did in the simulator.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WheelRun {
    /// The configured wheel tested.
    pub wheel: usize,
    /// The firmware's `WHEEL_TEST_RESULT`, if it sent one.
    pub result: Option<WheelTestResult>,
    /// The firmware's fault at the end (a runaway, a missing motor).
    pub fault: Fault,
    /// How far each physical wheel turned, rad, robot-forward positive (ground truth).
    pub turned: [f64; 4],
    /// What a person watching would say: the wheel that turned most, if it turned at least
    /// [`TURNED_MIN_ANGLE`].
    pub seen: Option<Seen>,
    /// How far the body moved, m (on blocks: nothing).
    pub body_moved_m: f64,
}

/// The bring-up check of a configuration on a simulated robot, on blocks
/// ([`PlantSpec::lifted`]) and wired as `plant` says: each configured wheel tested in turn
/// at `speed` rad/s for `duration_ms`, each on a fresh robot.
///
/// # Errors
/// [`CheckError`] if the configuration or the plant is refused.
pub fn run_check(
    config: &Config,
    plant: &PlantSpec,
    speed: f32,
    duration_ms: u16,
) -> Result<[WheelRun; 4], CheckError> {
    let spec = PlantSpec {
        lifted: true,
        ..plant.clone()
    };
    let mut runs = Vec::with_capacity(4);
    for wheel in 0..4u8 {
        let mut s = Scenario::from_toml("duration_s = 1.0", std::path::Path::new("check.toml"))?;
        s.name = format!("check-{}", WHEEL_NAMES[usize::from(wheel)]);
        s.config = *config;
        s.plant = spec.clone();
        s.duration_s = 0.1 + f64::from(duration_ms) * 1e-3 + 0.4;
        s.actions = vec![Action {
            wheel_test: Some(WheelTestSpec {
                wheel,
                speed,
                duration_ms,
            }),
            ..Action::at(0.1)
        }];
        let mut drives = SimDrives::with_spec(config, &spec)?;
        let mut result = None;
        let mut fault = Fault::None;
        run_observed(&s, &mut drives, None, LogOptions::default(), |v| {
            for f in v.sent {
                if let Ok(robot::Telemetry::WheelTestResult(r)) = robot::Telemetry::decode(f) {
                    result = Some(r);
                }
            }
            if v.controller.state() == RobotState::Fault {
                fault = v.controller.fault();
            }
        })?;
        let st = drives.chassis_state();
        let turned = st.wheel_angle;
        let (most, angle) = turned
            .iter()
            .copied()
            .enumerate()
            .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
            .unwrap_or((0, 0.0));
        let seen = (angle.abs() >= TURNED_MIN_ANGLE).then_some(Seen {
            wheel: most,
            forward: angle > 0.0,
        });
        runs.push(WheelRun {
            wheel: usize::from(wheel),
            result,
            fault,
            turned,
            seen,
            body_moved_m: st.pose.x.hypot(st.pose.y),
        });
    }
    Ok(runs
        .try_into()
        .unwrap_or_else(|_| unreachable!("four runs")))
}

/// The check's report: per wheel what turned and the verdict, and the configuration lines
/// that fix the wiring; printed as a person reads it (`Display`) or as JSON (`hostsim check
/// --json`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Report {
    /// Where the configuration came from.
    pub configuration: String,
    /// Every wheel turned as configured.
    pub right: bool,
    /// Per configured wheel, FL, FR, RL, RR.
    pub wheels: Vec<WheelReport>,
    /// The `[drive]` lines that fix the wiring ([`Diagnosis::fix_lines`]).
    pub fix: Vec<String>,
    /// Why there is no fix, if there is none.
    pub unresolved: Option<String>,
    /// The test's wheel speed, rad/s: text only.
    #[serde(skip)]
    pub speed: f32,
    /// The test's length, ms: text only.
    #[serde(skip)]
    pub duration_ms: u16,
    /// The key of the drive ids, singular (`esc_id`, `node_id`): text only.
    #[serde(skip)]
    pub id_key: &'static str,
}

/// One wheel's test in a [`Report`].
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct WheelReport {
    /// The configured wheel tested.
    pub wheel: &'static str,
    /// Its configured drive id.
    pub id: u8,
    /// The wheel that turned, if one did.
    pub turned: Option<&'static str>,
    /// Whether it turned robot-forward, if one did.
    pub forward: Option<bool>,
    /// How far each physical wheel turned, rad, robot-forward positive.
    pub angles_rad: [f64; 4],
    /// The verdict ([`verdict_text`]).
    pub verdict: String,
    /// The firmware's `WHEEL_TEST_RESULT`, if it sent one.
    pub firmware: Option<FirmwareResult>,
    /// The firmware's fault at the end.
    pub fault: &'static str,
}

/// The firmware's own result of a wheel's test.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FirmwareResult {
    /// `DONE`, `STOPPED`, `FAULT` or `REFUSED`.
    pub outcome: &'static str,
    /// The angle it measured, rad.
    pub angle_rad: f32,
    /// The peak current, A.
    pub peak_current_a: f32,
}

impl Report {
    /// The report of the check of the configuration from `source` (`configured`), whose
    /// tests at `speed` rad/s for `duration_ms` gave `runs` and the diagnosis `d`.
    #[must_use]
    pub fn new(
        source: String,
        (speed, duration_ms): (f32, u16),
        configured: &Wiring,
        runs: &[WheelRun; 4],
        d: &Diagnosis,
    ) -> Self {
        let wheels = runs
            .iter()
            .zip(d.verdicts)
            .map(|(r, v)| WheelReport {
                wheel: WHEEL_NAMES[r.wheel],
                id: configured.ids[r.wheel],
                turned: r.seen.map(|s| WHEEL_NAMES[s.wheel]),
                forward: r.seen.map(|s| s.forward),
                angles_rad: r.turned,
                verdict: verdict_text(r.wheel, v),
                firmware: r.result.map(|t| FirmwareResult {
                    outcome: t.outcome.as_str(),
                    angle_rad: t.angle,
                    peak_current_a: t.peak_current,
                }),
                fault: r.fault.as_str(),
            })
            .collect();
        Self {
            configuration: source,
            right: d.is_right(),
            wheels,
            fix: d.fix_lines(configured),
            unresolved: d.unresolved.clone(),
            speed,
            duration_ms,
            id_key: configured.ids_key().trim_end_matches('s'),
        }
    }
}

impl core::fmt::Display for Report {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        writeln!(
            f,
            "bring-up check of {} on a simulated robot on blocks, each wheel at {} rad/s for {} \
             ms:",
            self.configuration, self.speed, self.duration_ms
        )?;
        for w in &self.wheels {
            let firmware = match w.firmware {
                Some(r) => format!(
                    "firmware: {} turned {:+.2} rad, peak {:+.2} A, {}",
                    w.wheel, r.angle_rad, r.peak_current_a, r.outcome
                ),
                None => "firmware: no result".to_string(),
            };
            let fault = if w.fault == Fault::None.as_str() {
                String::new()
            } else {
                format!(", fault {}", w.fault)
            };
            writeln!(
                f,
                "{} ({} {}): {}  [{firmware}{fault}]",
                w.wheel, self.id_key, w.id, w.verdict
            )?;
        }
        if self.right {
            write!(f, "wiring: as configured")
        } else if let Some(why) = &self.unresolved {
            write!(f, "wiring: cannot be fixed from these observations: {why}")
        } else {
            write!(f, "wiring: wrong; fix the configuration's [drive] section:")?;
            for l in &self.fix {
                write!(f, "\n    {l}")?;
            }
            Ok(())
        }
    }
}

/// One line on a verdict.
#[must_use]
pub fn verdict_text(wheel: usize, v: Verdict) -> String {
    let name = WHEEL_NAMES[wheel];
    match v {
        Verdict::Right => format!("{name} turned forward: right"),
        Verdict::Reversed => {
            format!("{name} turned backward: its motor is mounted the other way than configured")
        }
        Verdict::OtherWheel(s) => format!(
            "{} turned {} instead: wired to the wrong wheel",
            WHEEL_NAMES[s.wheel],
            if s.forward { "forward" } else { "backward" }
        ),
        Verdict::Nothing => "no wheel turned".to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DJI: Wiring = Wiring {
        ids: [1, 2, 3, 4],
        inverted: [false, true, false, true],
        odrive: false,
    };

    fn seen(wheel: usize, forward: bool) -> Option<Seen> {
        Some(Seen { wheel, forward })
    }

    #[test]
    fn a_right_robot_needs_no_fix() {
        let d = diagnose(&DJI, core::array::from_fn(|i| seen(i, true)));
        assert!(d.is_right());
        assert!(d.fix_lines(&DJI).is_empty());
    }

    #[test]
    fn a_reversed_wheel_and_swapped_ids_give_their_lines() {
        // FR turned backward; FL's test turned RL and RL's turned FL.
        let d = diagnose(
            &DJI,
            [seen(2, true), seen(1, false), seen(0, true), seen(3, true)],
        );
        assert_eq!(d.verdicts[1], Verdict::Reversed);
        assert_eq!(
            d.fix_lines(&DJI),
            [
                "esc_ids = [3, 2, 1, 4]",
                "inverted = [false, false, false, true]"
            ]
        );
    }

    #[test]
    fn a_diagonal_swap_of_mirrored_drives_is_ids_and_signs() {
        // ESC 1 (configured FL, not inverted) is on RR, which is mirrored: RR turns backward.
        let d = diagnose(
            &DJI,
            [seen(3, false), seen(1, true), seen(2, true), seen(0, false)],
        );
        let fixed = d.fixed.unwrap();
        assert_eq!(fixed.ids, [4, 2, 3, 1]);
        assert_eq!(fixed.inverted, DJI.inverted, "the mounting was right");
    }

    #[test]
    fn missing_or_doubled_observations_are_named_not_guessed() {
        let d = diagnose(&DJI, [seen(0, true), None, seen(2, true), seen(3, true)]);
        assert!(d.fixed.is_none());
        assert!(d.unresolved.unwrap().contains("FR was tested"));
        let d = diagnose(
            &DJI,
            [seen(0, true), seen(0, true), seen(2, true), seen(3, true)],
        );
        assert!(
            d.unresolved
                .unwrap()
                .contains("FL turned when FL and when FR")
        );
    }
}
