//! The built-in scenarios (`hostsim run square`, ...).

use firmware::Config;

use super::{Action, Scenario, ScenarioError};
use crate::nodes::plant::PlantSpec;

impl Scenario {
    /// A built-in scenario on the DJI example chassis. See [`Scenario::BUILTINS`].
    ///
    /// - `square`: 1 m sides at 0.5 m/s, driving forward, left, back and right without
    ///   turning (the mecanum party trick).
    /// - `circle`: 0.5 m/s forward while turning at 0.5 rad/s, one full turn.
    /// - `strafe`: 0.5 m/s to the left for 3 s, then back.
    /// - `spin`: two turns on the spot at 1.5 rad/s.
    /// - `figure-eight`: a left circle then a right circle.
    /// - `compass`: the eight compass directions of Table I of Tlale and de Villiers in
    ///   turn, 1.5 s each.
    /// - `watchdog`: drive forward, then go silent: the firmware must stop and disable.
    /// - `calibration`: the motion `hostsim calibrate` needs, each leg both ways with a
    ///   0.5 s stop between legs: 1 s standing still, 1 m forward and back at 0.5 m/s, 1 m
    ///   (commanded) left and right at 0.5 m/s, one turn each way at 1.5 rad/s. Its robot is
    ///   fixed ([`PlantSpec::dji_m3508_example`]), so a run with a calibrated `--config`
    ///   changes only what the firmware believes.
    ///
    /// # Errors
    /// [`ScenarioError::UnknownBuiltin`] with the list of names.
    pub fn builtin(name: &str) -> Result<Self, ScenarioError> {
        let mut actions = vec![Action {
            enable: true,
            ..Action::at(0.05)
        }];
        let mut t = 0.1;
        let leg = |actions: &mut Vec<Action>, t: &mut f64, dur: f64, vx: f32, vy: f32, wz: f32| {
            actions.push(Action::twist(*t, vx, vy, wz));
            *t += dur;
        };
        let tau = std::f64::consts::TAU;
        match name {
            "square" => {
                for (vx, vy) in [(0.5, 0.0), (0.0, 0.5), (-0.5, 0.0), (0.0, -0.5)] {
                    leg(&mut actions, &mut t, 2.0, vx, vy, 0.0);
                }
            }
            "circle" => leg(&mut actions, &mut t, tau / 0.5, 0.5, 0.0, 0.5),
            "strafe" => {
                leg(&mut actions, &mut t, 3.0, 0.0, 0.5, 0.0);
                leg(&mut actions, &mut t, 3.0, 0.0, -0.5, 0.0);
            }
            "spin" => leg(&mut actions, &mut t, 2.0 * tau / 1.5, 0.0, 0.0, 1.5),
            "figure-eight" => {
                leg(&mut actions, &mut t, tau / 0.6, 0.4, 0.0, 0.6);
                leg(&mut actions, &mut t, tau / 0.6, 0.4, 0.0, -0.6);
            }
            "compass" => {
                let s = std::f32::consts::FRAC_1_SQRT_2 * 0.5;
                for (vx, vy) in [
                    (0.5, 0.0),
                    (s, -s),
                    (0.0, -0.5),
                    (-s, -s),
                    (-0.5, 0.0),
                    (-s, s),
                    (0.0, 0.5),
                    (s, s),
                ] {
                    leg(&mut actions, &mut t, 1.5, vx, vy, 0.0);
                }
            }
            "calibration" => {
                leg(&mut actions, &mut t, 1.0, 0.0, 0.0, 0.0);
                let turn = tau / 1.5;
                for (dur, vx, vy, wz) in [
                    (2.0, 0.5, 0.0, 0.0),
                    (2.0, -0.5, 0.0, 0.0),
                    (2.0, 0.0, 0.5, 0.0),
                    (2.0, 0.0, -0.5, 0.0),
                    (turn, 0.0, 0.0, 1.5),
                    (turn, 0.0, 0.0, -1.5),
                ] {
                    leg(&mut actions, &mut t, dur, vx, vy, wz);
                    leg(&mut actions, &mut t, 0.5, 0.0, 0.0, 0.0);
                }
            }
            "watchdog" => {
                leg(&mut actions, &mut t, 1.0, 0.8, 0.0, 0.0);
                actions.push(Action {
                    silence: true,
                    ..Action::at(t)
                });
                t += 1.5;
            }
            other => return Err(ScenarioError::UnknownBuiltin(other.to_string())),
        }
        if name != "watchdog" {
            leg(&mut actions, &mut t, 1.0, 0.0, 0.0, 0.0);
        }
        let plant = if name == "calibration" {
            PlantSpec::dji_m3508_example()
        } else {
            PlantSpec::default()
        };
        Ok(Self {
            name: name.to_string(),
            duration_s: t,
            seed: 1,
            command_hz: 50.0,
            config: Config::dji_m3508_example(),
            actions,
            bus_faults: Vec::new(),
            wheel_faults: Vec::new(),
            host_faults: Vec::new(),
            plant,
            imu: None,
            pods: None,
            node_faults: Vec::new(),
        })
    }
}
