//! A candump log's replay: the frame streams compared, and the odometry the core computes
//! against the last logged `ODOM_POSITION`/`ODOM_VELOCITY`, within tolerances.

use std::path::{Path, PathBuf};

use firmware::CanFrame;
use firmware::config::Config;
use firmware::control::{Controller, Instant};
use firmware::protocol::robot::{OdomPosition, OdomVelocity, Telemetry};
use serde::Serialize;

use super::*;

/// Tolerances of the odometry comparison of a candump replay.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct OdometryTolerance {
    /// Largest position difference, m. Default 0.01.
    pub position_m: f64,
    /// Largest heading difference, rad. Default 0.01.
    pub heading_rad: f64,
}

impl Default for OdometryTolerance {
    fn default() -> Self {
        Self {
            position_m: 0.01,
            heading_rad: 0.01,
        }
    }
}

/// An odometry reading: pose and body velocity at a time.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct OdometryReading {
    /// Time since the log's first frame, s.
    pub t_s: f64,
    /// x, m.
    pub x: f64,
    /// y, m.
    pub y: f64,
    /// Heading, rad.
    pub heading: f64,
    /// Forward velocity, m/s.
    pub vx: f64,
    /// Leftward velocity, m/s.
    pub vy: f64,
    /// Yaw rate, rad/s.
    pub wz: f64,
}

/// The logged odometry against the replayed core's.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct OdometryComparison {
    /// The last logged `ODOM_POSITION` (x, y) and `ODOM_VELOCITY` (heading, velocity),
    /// decoded with the robot codec; `t_s` is the `ODOM_POSITION` frame's time.
    pub logged: OdometryReading,
    /// The replayed core at its last step at or before `logged.t_s`.
    pub replayed: OdometryReading,
    /// Distance between the two positions, m.
    pub position_error_m: f64,
    /// Heading difference (wrapped), rad.
    pub heading_error_rad: f64,
    /// Largest velocity component difference, m/s or rad/s (reported, not judged).
    pub velocity_error: f64,
    /// The tolerances applied.
    pub tolerance: OdometryTolerance,
    /// Position and heading within the tolerances.
    pub agrees: bool,
}

/// A frame in a report: candump text and time since the log's first frame.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ReportFrame {
    /// Time since the log's first frame (replayed: the step time), s.
    pub t_s: String,
    /// The frame in candump notation.
    pub frame: String,
}

impl ReportFrame {
    pub(crate) fn new(f: &TimedFrame) -> Self {
        Self {
            t_s: format!("{:.6}", f.t_ns as f64 * 1e-9),
            frame: drivelog::candump::format_frame(&f.frame),
        }
    }
}

/// The first difference between the logged and the replayed outbound streams (time
/// ignored).
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct StreamDifference {
    /// Index in the outbound stream.
    pub index: usize,
    /// What the log has (`None`: the log has no more).
    pub logged: Option<ReportFrame>,
    /// What the replay sent (`None`: the replay sent no more).
    pub replayed: Option<ReportFrame>,
}

/// The outcome of a candump replay. Serialises to the JSON of `hostsim replay --json`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CandumpReplay {
    /// Interfaces in the log.
    pub interfaces: Vec<String>,
    /// Frames in the log.
    pub frames: usize,
    /// Frames the firmware received (fed to the replay).
    pub received: usize,
    /// Frames the firmware sent (compared).
    pub sent: usize,
    /// Control period, µs.
    pub period_us: u64,
    /// Steps run.
    pub steps: u64,
    /// From the first to the last frame, s.
    pub duration_s: f64,
    /// Frames the replayed core sent.
    pub replayed: usize,
    /// Leading outbound frames that are equal, time ignored.
    pub matching_prefix: usize,
    /// The outbound streams are equal frame for frame (time ignored).
    pub identical: bool,
    /// The first difference, if any.
    pub first_difference: Option<StreamDifference>,
    /// The odometry comparison; `None` if the log has no odometry frames.
    pub odometry: Option<OdometryComparison>,
    /// The replayed core's pose after its last step.
    pub final_pose: OdometryReading,
    /// Frames the replayed core rejected (malformed, unknown id, ...), by kind.
    pub rejected: firmware::protocol::RxErrorCounters,
}

impl CandumpReplay {
    /// `identical`, `odometry_agrees` or `differs`.
    #[must_use]
    pub fn verdict(&self) -> &'static str {
        if self.identical {
            "identical"
        } else if self.odometry.as_ref().is_some_and(|o| o.agrees) {
            "odometry_agrees"
        } else {
            "differs"
        }
    }

    /// The replay agrees with the log: identical streams, or the same odometry.
    #[must_use]
    pub fn agrees(&self) -> bool {
        self.verdict() != "differs"
    }
}

/// Why a candump log could not be replayed.
#[derive(Debug, thiserror::Error)]
pub enum CandumpReplayError {
    /// The log could not be read or has a bad line.
    #[error(transparent)]
    Read(#[from] drivelog::candump::ReadError),
    /// The log has no frames.
    #[error("{}: no frames", path.display())]
    Empty {
        /// The log file.
        path: PathBuf,
    },
    /// The configuration is refused by the firmware.
    #[error("configuration refused: {0}")]
    Refused(#[from] firmware::config::ConfigError),
    /// The log's time line has a gap too long to replay.
    #[error("{}: {source}", path.display())]
    TimeGap {
        /// The log file.
        path: PathBuf,
        /// The gap.
        source: TimeGap,
    },
}

/// Replays a candump log: see [`replay_split`].
///
/// # Errors
/// [`CandumpReplayError`] naming the file and line, or the configuration error.
pub fn replay_candump(
    path: &Path,
    config: &Config,
    tolerance: OdometryTolerance,
) -> Result<CandumpReplay, CandumpReplayError> {
    let entries = drivelog::candump::read_file(path)?;
    if entries.is_empty() {
        return Err(CandumpReplayError::Empty {
            path: path.to_path_buf(),
        });
    }
    replay_split(config, &split_candump(config, &entries), tolerance).map_err(|e| match e {
        ReplayRunError::Config(e) => CandumpReplayError::Refused(e),
        ReplayRunError::TimeGap(source) => CandumpReplayError::TimeGap {
            path: path.to_path_buf(),
            source,
        },
    })
}

fn reading(t_ns: u64, pose: [f32; 3], velocity: [f32; 3]) -> OdometryReading {
    OdometryReading {
        t_s: t_ns as f64 * 1e-9,
        x: f64::from(pose[0]),
        y: f64::from(pose[1]),
        heading: f64::from(pose[2]),
        vx: f64::from(velocity[0]),
        vy: f64::from(velocity[1]),
        wz: f64::from(velocity[2]),
    }
}

/// Runs a fresh [`Controller`] on a split candump log and compares it with the log.
///
/// Steps run every control period from the first frame (time 0) through the last one.
/// Before each step, the received frames logged at or before the step time are fed,
/// stamped with the step time (as the Linux runner stamps what it drains). The outbound
/// frames are compared with the logged ones in order, time ignored: a real-time log is
/// not on the replay's step grid, so only the order and the contents can match exactly.
/// The odometry is compared at the last logged `ODOM_POSITION`: the replayed core's pose
/// at its last step at or before that time against the logged pose (x, y from
/// `ODOM_POSITION`, heading from the last `ODOM_VELOCITY`).
///
/// The replayed core starts disabled at pose zero, as the runner does: a capture that
/// starts after the runner was enabled or had moved replays a core that never enables (the
/// frame streams differ) and whose odometry is offset by the runner's earlier motion. Start
/// the capture before the runner.
///
/// # Errors
/// [`ReplayRunError`] if the firmware refuses `config`, or if the log's time line has a gap
/// longer than [`MAX_GAP_NS`] ([`check_time_gaps`]).
pub fn replay_split(
    config: &Config,
    log: &SplitLog,
    tolerance: OdometryTolerance,
) -> Result<CandumpReplay, ReplayRunError> {
    let mut ctl = Controller::new(config)?;
    check_time_gaps(&log.all)?;
    let period_ns = ctl.period_micros() * 1000;
    let (logged_pos, logged_vel) = last_logged_odometry(&log.tx);
    let target_ns = logged_pos.map(|(t, _)| t);

    let end_ns = log.all.last().map_or(0, |f| f.t_ns);
    let mut next_rx = 0;
    let mut out_index = 0usize;
    let mut first_difference = None;
    let mut steps = 0u64;
    let mut at_target = None;
    let mut t_ns = 0u64;
    let mut last_step_ns = 0u64;
    while t_ns <= end_ns {
        let now = Instant::from_micros(t_ns / 1000);
        while let Some(f) = log.rx.get(next_rx)
            && f.t_ns <= t_ns
        {
            ctl.on_frame(now, &f.frame);
            next_rx += 1;
        }
        let sent: Vec<CanFrame> = ctl.step(now).iter().copied().collect();
        out_index = compare_step(sent, &log.tx, out_index, t_ns, &mut first_difference);
        steps += 1;
        last_step_ns = t_ns;
        if target_ns.is_some_and(|t| t_ns <= t) {
            at_target = Some((t_ns, pose_and_velocity(&ctl)));
        }
        // The gap check bounds end_ns far below u64::MAX; stop rather than wrap regardless.
        let Some(next) = t_ns.checked_add(period_ns) else {
            break;
        };
        t_ns = next;
    }
    if first_difference.is_none() && out_index < log.tx.len() {
        first_difference = Some(StreamDifference {
            index: out_index,
            logged: Some(ReportFrame::new(&log.tx[out_index])),
            replayed: None,
        });
    }
    let matching_prefix = first_difference.as_ref().map_or(out_index, |d| d.index);
    let odometry = match (logged_pos, at_target) {
        (Some((t, p)), Some((t_rep, (pose, vel)))) => {
            let v = logged_vel.unwrap_or_default();
            let logged = reading(t, [p.x, p.y, v.heading], [v.vx, v.vy, v.wz]);
            Some(compare_odometry(
                logged,
                reading(t_rep, pose, vel),
                tolerance,
            ))
        }
        _ => None,
    };
    let (pose, vel) = pose_and_velocity(&ctl);
    Ok(CandumpReplay {
        interfaces: log.interfaces.clone(),
        frames: log.all.len(),
        received: log.rx.len(),
        sent: log.tx.len(),
        period_us: ctl.period_micros(),
        steps,
        duration_s: end_ns as f64 * 1e-9,
        replayed: out_index,
        matching_prefix,
        identical: first_difference.is_none(),
        first_difference,
        odometry,
        final_pose: reading(last_step_ns, pose, vel),
        rejected: ctl.snapshot().rx_errors,
    })
}

/// The last `ODOM_POSITION` the log's outbound frames hold (with its time) and the last
/// `ODOM_VELOCITY`.
fn last_logged_odometry(tx: &[TimedFrame]) -> (Option<(u64, OdomPosition)>, Option<OdomVelocity>) {
    let mut logged_pos = None;
    let mut logged_vel = None;
    for f in tx {
        match Telemetry::decode(&f.frame) {
            Ok(Telemetry::OdomPosition(p)) => logged_pos = Some((f.t_ns, p)),
            Ok(Telemetry::OdomVelocity(v)) => logged_vel = Some(v),
            _ => {}
        }
    }
    (logged_pos, logged_vel)
}

/// The core's pose and measured velocity.
fn pose_and_velocity(ctl: &Controller) -> ([f32; 3], [f32; 3]) {
    let s = ctl.snapshot();
    (
        [s.pose.x, s.pose.y, s.pose.heading],
        [s.measured.vx, s.measured.vy, s.measured.wz],
    )
}

/// Compares a step's frames (`sent`, at `t_ns`) with the logged ones from `out_index` on,
/// recording the first difference; returns the index after them.
fn compare_step(
    mut sent: Vec<CanFrame>,
    tx: &[TimedFrame],
    mut out_index: usize,
    t_ns: u64,
    first_difference: &mut Option<StreamDifference>,
) -> usize {
    // A step's frames leave in the bus's order (a capture of a simulated or a real CAN
    // bus), or in the order the core queued them (a vcan capture): compared in one order.
    sent.sort_by_key(wire_order);
    let end = (out_index + sent.len()).min(tx.len());
    let mut logged: Vec<TimedFrame> = tx[out_index.min(end)..end].to_vec();
    logged.sort_by_key(|f| wire_order(&f.frame));
    for (i, frame) in sent.into_iter().enumerate() {
        let logged = logged.get(i);
        if first_difference.is_none() && logged.map(|l| l.frame) != Some(frame) {
            *first_difference = Some(StreamDifference {
                index: out_index,
                logged: logged.map(ReportFrame::new),
                replayed: Some(ReportFrame::new(&TimedFrame { t_ns, frame })),
            });
        }
        out_index += 1;
    }
    out_index
}

/// The replayed odometry against the logged one, within `tolerance`.
fn compare_odometry(
    logged: OdometryReading,
    replayed: OdometryReading,
    tolerance: OdometryTolerance,
) -> OdometryComparison {
    let position_error_m = (logged.x - replayed.x).hypot(logged.y - replayed.y);
    let heading_error_rad = kinematics::wrap_angle(logged.heading - replayed.heading).abs();
    let velocity_error = (logged.vx - replayed.vx)
        .abs()
        .max((logged.vy - replayed.vy).abs())
        .max((logged.wz - replayed.wz).abs());
    OdometryComparison {
        logged,
        replayed,
        position_error_m,
        heading_error_rad,
        velocity_error,
        tolerance,
        agrees: position_error_m <= tolerance.position_m
            && heading_error_rad <= tolerance.heading_rad,
    }
}
