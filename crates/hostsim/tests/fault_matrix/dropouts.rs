//! 1,000 random dropouts: the host goes silent, or loses its frames on the bus, at a random
//! moment of a random drive, a thousand times in one simulated session; the watchdog must
//! stop every one within its budget.

use std::fmt::Write as _;

use firmware::Config;
use firmware::protocol::robot::RobotState;
use hostsim::bus::{FaultKind, Node, SplitMix64};
use hostsim::scenario::{Action, Scenario};
use kinematics::ChassisVelocity;

use super::docs::keep_in_docs;
use super::drive::{TURN, bus_fault, drive, us};
use super::record::run;
use super::rows::{check_watchdog_stop, stop_budget_us};

/// One dropout of the random campaign.
#[derive(Debug, Clone, Copy)]
struct Dropout {
    enable_s: f64,
    onset_s: f64,
    twist: [f32; 3],
    /// The host goes silent (`false`: its frames are lost on the bus, it keeps sending).
    silence: bool,
}

const DROPOUTS: usize = 1_000;

/// The campaign: per dropout, enable, a random twist (a third pure turns, a third
/// translations, a third both), a random time of driving (5-100 ms: often still
/// accelerating), then the host goes silent or loses its frames on the bus until shortly
/// before the next enable.
fn campaign(seed: u64) -> (Scenario, Vec<Dropout>) {
    let config = Config::dji_m3508_example();
    let mut rng = SplitMix64(seed);
    let mut uniform = |lo: f64, hi: f64| lo + (hi - lo) * rng.unit();
    let mut s = drive(TURN, 1.0);
    s.actions.clear();
    let mut drops = Vec::with_capacity(DROPOUTS);
    let mut t = 0.02;
    for i in 0..DROPOUTS {
        let kind = uniform(0.0, 3.0);
        let (vx, vy) = if kind < 1.0 {
            (0.0, 0.0)
        } else {
            (uniform(-1.0, 1.0), uniform(-0.7, 0.7))
        };
        let wz = if kind >= 2.0 { 0.0 } else { uniform(-2.5, 2.5) };
        let twist = [vx as f32, vy as f32, wz as f32];
        let onset = t + 0.002 + uniform(0.005, 0.1);
        let silence = i % 2 == 0;
        let stop = stop_budget_us(&config, ChassisVelocity::new(twist[0], twist[1], twist[2]));
        let next = onset + stop as f64 * 1e-6 + 0.035;
        s.actions.push(Action {
            enable: true,
            ..Action::at(t)
        });
        s.actions
            .push(Action::twist(t + 0.002, twist[0], twist[1], twist[2]));
        if silence {
            s.actions.push(Action {
                silence: true,
                ..Action::at(onset)
            });
        } else {
            // Lost on the bus until 22 ms before the next enable: the twist (at least one
            // at 50 Hz) that then arrives finds the robot stopped and must not move it.
            bus_fault(
                &mut s,
                FaultKind::Burst,
                onset,
                next - 0.022 - onset,
                Node::Host,
            );
        }
        drops.push(Dropout {
            enable_s: t,
            onset_s: onset,
            twist,
            silence,
        });
        t = next;
    }
    s.duration_s = t;
    (s, drops)
}

#[derive(Debug, Default)]
struct Stats {
    n: usize,
    min: u64,
    max: u64,
    sum: u64,
}

impl Stats {
    fn add(&mut self, x: u64) {
        self.min = if self.n == 0 { x } else { self.min.min(x) };
        self.max = self.max.max(x);
        self.sum += x;
        self.n += 1;
    }

    fn line(&self) -> String {
        let ms = |us: u64| format!("{:.3}", us as f64 / 1000.0);
        format!(
            "{} / {} / {} ms",
            ms(self.min),
            ms(self.sum / self.n.max(1) as u64),
            ms(self.max)
        )
    }
}

#[test]
fn the_watchdog_stops_every_one_of_1000_random_dropouts() {
    let (s, drops) = campaign(0x5EED_D20F);
    let wall = std::time::Instant::now();
    let rec = run(&s);
    let wall_s = wall.elapsed().as_secs_f64();
    let (mut zero, mut detect, mut margin) = (Stats::default(), Stats::default(), Stats::default());
    let mut turns = 0;
    let mut failures = Vec::new();
    for (i, d) in drops.iter().enumerate() {
        let enable_us = us(d.enable_s);
        let next_us = drops.get(i + 1).map_or(s.duration_us(), |n| us(n.enable_s));
        // Driving before the dropout.
        let moving = rec.at(us(d.onset_s)).commanded != ChassisVelocity::default();
        let enabled = rec
            .first(enable_us, |s| s.state == RobotState::Enabled)
            .is_some_and(|s| s.t_us < us(d.onset_s));
        let result = if moving && enabled {
            check_watchdog_stop(&s.config, &rec, us(d.onset_s), next_us).and_then(|r| {
                // After a lost-frames burst, twists arrive at the stopped robot (and the
                // check above found it still stopped).
                let stopped_at = rec.last_twist(us(d.onset_s)).unwrap_or(0) + r.0;
                let late = rec.twists.iter().any(|&t| t > stopped_at && t < next_us);
                if d.silence || late {
                    Ok(r)
                } else {
                    Err("no twist reached the stopped robot".to_string())
                }
            })
        } else {
            Err("not enabled and moving at the onset".to_string())
        };
        match result {
            Ok((latency, budget, detection)) => {
                zero.add(latency);
                detect.add(detection);
                margin.add(budget - latency);
                turns += usize::from(d.twist[2] != 0.0);
            }
            Err(e) => failures.push((i, *d, e)),
        }
    }
    assert!(
        failures.is_empty(),
        "{} failed: {:#?}",
        failures.len(),
        &failures[..failures.len().min(5)]
    );
    let silent = drops.iter().filter(|d| d.silence).count();
    let mut t = String::new();
    writeln!(t, "| dropouts | with a turn | host silent / frames lost | simulated | zero current after the last twist (min / mean / max) | watchdog after the last twist (min / mean / max) | budget left (min / mean / max) | failed |").unwrap();
    writeln!(t, "|---|---|---|---|---|---|---|---|").unwrap();
    writeln!(
        t,
        "| {} | {turns} | {silent} / {} | {:.0} s | {} | {} | {} | 0 |",
        drops.len(),
        drops.len() - silent,
        s.duration_s,
        zero.line(),
        detect.line(),
        margin.line()
    )
    .unwrap();
    println!("{t}\n({:.1} s simulated in {wall_s:.1} s)", s.duration_s);
    keep_in_docs("watchdog-dropouts", &t);
}
