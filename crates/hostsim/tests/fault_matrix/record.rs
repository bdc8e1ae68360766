//! Recording a run: every control step as the fault matrix judges it, and what the firmware
//! should have seen, from the bus deliveries.

use firmware::Config;
use firmware::control::Fault;
use firmware::protocol::dji::{self, CurrentCommand, EscModel};
use firmware::protocol::robot::{Command, RobotState};
use hostsim::bus::{Fate, Node};
use hostsim::engine::{LogOptions, StepView, run_observed};
use hostsim::nodes::drives::SimDrives;
use hostsim::scenario::Scenario;
use kinematics::ChassisVelocity;

/// One control step as the record shows it.
#[derive(Debug, Clone, Copy)]
pub(super) struct Step {
    pub(super) t_us: u64,
    pub(super) state: RobotState,
    pub(super) fault: Fault,
    pub(super) commanded: ChassisVelocity<f32>,
    /// The step's DJI current frame, A (motor sign).
    pub(super) currents: [f32; 4],
    /// The wheel speed setpoints are all zero.
    pub(super) setpoints_zero: bool,
    pub(super) rx_errors: u64,
    /// Twists the firmware counted as repeats of the last accepted one.
    pub(super) repeated_seq: u64,
    pub(super) odom_error_m: f64,
    /// A motor's feedback gap has exceeded the stale limit by this step (the oracle).
    pub(super) stale_due: bool,
}

impl Step {
    pub(super) fn zero_current(&self) -> bool {
        self.currents.iter().all(|&a| a == 0.0)
    }
}

#[derive(Debug, Default)]
pub(super) struct Record {
    pub(super) steps: Vec<Step>,
    /// Delivery times (µs) of the twist commands the firmware must accept.
    pub(super) twists: Vec<u64>,
    /// Delivery times (µs) of the twists that repeat the `seq` of the last one in `twists`:
    /// the firmware must count them and not accept them.
    pub(super) repeats: Vec<u64>,
    /// Repeats whose bytes differ from the twist they repeat.
    pub(super) repeats_changed: u64,
    /// Host frames corrupted on the bus.
    pub(super) corrupted_host: u64,
    /// Largest gap (µs) between two decodable feedback frames of one motor, at step times.
    pub(super) max_feedback_gap_us: u64,
}

impl Record {
    pub(super) fn at(&self, t_us: u64) -> &Step {
        let i = self.steps.partition_point(|s| s.t_us < t_us);
        &self.steps[i.min(self.steps.len() - 1)]
    }

    /// The first step at or after `from_us` that satisfies `pred`.
    pub(super) fn first(&self, from_us: u64, pred: impl Fn(&Step) -> bool) -> Option<&Step> {
        self.steps.iter().find(|s| s.t_us >= from_us && pred(s))
    }

    /// The last accepted twist delivered at or before `t_us`.
    pub(super) fn last_twist(&self, t_us: u64) -> Option<u64> {
        self.twists.iter().rev().copied().find(|&t| t <= t_us)
    }

    /// Largest gap (µs) between accepted twists delivered in `[from_us, until_us)`.
    pub(super) fn max_twist_gap(&self, from_us: u64, until_us: u64) -> u64 {
        let mut last = self.last_twist(from_us).unwrap_or(from_us);
        let mut gap = 0;
        for &t in self.twists.iter().filter(|&&t| t > from_us && t < until_us) {
            gap = gap.max(t - last);
            last = t;
        }
        gap.max(until_us.saturating_sub(last))
    }
}

/// The `seq` of `frame` if it is a twist the firmware must take: it decodes and is within
/// the configured limits. (It is a command if its `seq` differs from the last command's,
/// else a repeat: see [`run`].)
pub(super) fn acceptable_twist(config: &Config, frame: &firmware::CanFrame) -> Option<u8> {
    let Ok(Command::Twist(t)) = Command::decode(frame) else {
        return None;
    };
    let l = &config.limits;
    (t.vx.hypot(t.vy) <= l.max_linear_speed && t.wz.abs() <= l.max_angular_speed).then_some(t.seq)
}

pub(super) fn run(s: &Scenario) -> Record {
    let config = s.config;
    let stale_us = 1_000 * u64::from(config.timing.stale_periods);
    let mut plant = SimDrives::new(&config).unwrap();
    let mut rec = Record::default();
    let mut last_feedback: [Option<u64>; 4] = [None; 4];
    let mut stale_seen = false;
    // The last twist command: its seq and its frame. (The host never repeats a seq on its
    // own, so across its enables this is the firmware's rule too.)
    let mut last_twist: Option<(u8, firmware::CanFrame)> = None;
    let observe = |v: &StepView<'_>| {
        for tx in v.delivered.iter().filter(|tx| tx.fate != Fate::Dropped) {
            let t_us = tx.delivered_ns / 1000;
            match tx.from {
                Node::Host => {
                    rec.corrupted_host += u64::from(tx.fate == Fate::Corrupted);
                    match (acceptable_twist(&config, &tx.frame), last_twist) {
                        (Some(seq), Some((last, frame))) if seq == last => {
                            rec.repeats.push(t_us);
                            rec.repeats_changed += u64::from(tx.frame != frame);
                        }
                        (Some(seq), _) => {
                            rec.twists.push(t_us);
                            last_twist = Some((seq, tx.frame));
                        }
                        (None, _) => {}
                    }
                }
                Node::Drives => {
                    if let Ok(fb) = dji::Feedback::decode(&tx.frame, EscModel::C620) {
                        let wheel = usize::from(fb.esc.get() - 1);
                        last_feedback[wheel] = Some(t_us);
                    }
                }
                // The fault matrix's scenarios have no IMU and no pods.
                Node::Controller | Node::Imu | Node::Pods => {}
            }
        }
        // The firmware's stale rule, from the deliveries: feedback older than the limit.
        for seen in last_feedback.iter().flatten() {
            let gap = v.t_us - seen;
            rec.max_feedback_gap_us = rec.max_feedback_gap_us.max(gap);
            stale_seen |= gap > stale_us;
        }
        let snap = v.controller.snapshot();
        let currents = v
            .sent
            .iter()
            .find_map(|f| CurrentCommand::decode(f, EscModel::C620).ok())
            .map(|c| c.amps())
            .expect("a current frame every step");
        let p = snap.pose;
        rec.steps.push(Step {
            t_us: v.t_us,
            state: snap.state,
            fault: snap.fault,
            commanded: snap.commanded,
            currents,
            setpoints_zero: snap.wheel_setpoints.0.iter().all(|&w| w == 0.0),
            rx_errors: u64::from(snap.rx_errors.total()),
            repeated_seq: u64::from(snap.repeated_seq),
            odom_error_m: (f64::from(p.x) - v.truth[0]).hypot(f64::from(p.y) - v.truth[1]),
            stale_due: stale_seen,
        });
    };
    run_observed(s, &mut plant, None, LogOptions::default(), observe).unwrap();
    rec
}
