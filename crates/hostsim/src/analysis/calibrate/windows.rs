//! The fit's windows: the odometry and the reference cut into consecutive windows of the
//! same length, their body-frame increments, and the steady ones that enter the fit.

use kinematics::{Effectiveness, MecanumKinematics, Pose2, Twist2, WheelDeltas};

use super::read::{Joints, Track};
use super::{CalibrateError, GeometryValues, pods};

/// A window enters the fit if the odometry moves at least this fast in it (m/s, or rad/s).
const MOVING: f64 = 5e-3;

/// A window is steady if its neighbours' increments differ from its own by at most this
/// fraction of it, plus [`STEADY_FLOOR`].
const STEADY_RELATIVE: f64 = 0.02;

/// The absolute part of the steadiness bound, per second of window (m/s, or rad/s).
const STEADY_FLOOR: f64 = 2e-3;

/// The longest gap between two samples a window may span, ns: a longer one (a tracker that
/// lost the robot, a paused log) starts a new window after it.
const MAX_GAP_NS: u64 = 250_000_000;

/// One window: its start and end (log time, ns) and the body-frame increments over it.
#[derive(Debug, Clone, Copy)]
pub(super) struct Window {
    pub t0: u64,
    pub t1: u64,
    pub odometry: Twist2<f64>,
    pub reference: Twist2<f64>,
}

/// The windows of the fit: those in which the odometry moves ([`MOVING`]) at a steady
/// speed, its increment within [`STEADY_RELATIVE`] (plus [`STEADY_FLOOR`]) of both
/// neighbours' on every axis. Constant factors describe the steady slip; the transients of
/// a start or a stop (the body lagging the wheels while it accelerates, sliding on after
/// they stop, the velocity loop's ringing) come and go and would bias the fit by how much
/// starting and stopping the log has.
pub(super) fn steady_windows(all: &[Window], window_s: f64) -> impl Iterator<Item = &Window> {
    let floor = STEADY_FLOOR * window_s;
    let moving = MOVING * window_s;
    let parts = |t: &Twist2<f64>| [t.dx, t.dy, t.dtheta];
    all.windows(3).filter_map(move |w| {
        let (before, this, after) = (&w[0], &w[1], &w[2]);
        let contiguous = before.t1 == this.t0 && this.t1 == after.t0;
        let u = parts(&this.odometry);
        let close = |other: &Window| {
            parts(&other.odometry)
                .iter()
                .zip(u)
                .all(|(v, u)| (v - u).abs() <= STEADY_RELATIVE * u.abs() + floor)
        };
        let moves = u[0].hypot(u[1]) > moving || u[2].abs() > moving;
        (contiguous && moves && close(before) && close(after)).then_some(this)
    })
}

/// Consecutive windows of `window_s` over the odometry samples that have a reference pose:
/// each window's (odometry, reference) body-frame increments.
pub(super) fn windows(odometry: &Track, reference: &Track, window_s: f64) -> Vec<Window> {
    let window_ns = (window_s * 1e9).round() as u64;
    let samples: Vec<(u64, Pose2<f64>, Pose2<f64>)> = odometry
        .iter()
        .filter_map(|&(t, o)| Some((t, o, interpolate(reference, t)?)))
        .collect();
    let mut out = Vec::new();
    let mut start = 0;
    for i in 1..samples.len() {
        let (t, o, r) = samples[i];
        if t - samples[i - 1].0 > MAX_GAP_NS {
            start = i;
            continue;
        }
        let (t0, o0, r0) = samples[start];
        if t - t0 >= window_ns {
            out.push(Window {
                t0,
                t1: t,
                odometry: o0.relative(o).log(),
                reference: r0.relative(r).log(),
            });
            start = i;
        }
    }
    out
}

/// The reference pose at `t_ns`, interpolated on SE(2) between the samples around it; `None`
/// outside the samples or across a gap longer than [`MAX_GAP_NS`].
fn interpolate(track: &Track, t_ns: u64) -> Option<Pose2<f64>> {
    let i = track.partition_point(|(t, _)| *t < t_ns);
    let (t1, p1) = *track.get(i)?;
    if t1 == t_ns {
        return Some(p1);
    }
    let (t0, p0) = *track.get(i.checked_sub(1)?)?;
    if t1 - t0 > MAX_GAP_NS {
        return None;
    }
    let s = (t_ns - t0) as f64 / (t1 - t0) as f64;
    let u = p0.relative(p1).log();
    Some(p0.exp(Twist2::new(u.dx * s, u.dy * s, u.dtheta * s)))
}

/// The odometry of the logged configuration recomputed from the wheel angles: each sample's
/// increments through the forward kinematics (effectiveness included) and the SE(2)
/// exponential, as the firmware integrates them.
pub(super) fn wheel_odometry(
    g: &GeometryValues,
    joints: &[Joints],
) -> Result<Track, CalibrateError> {
    let k = Effectiveness::new(
        g.forward_effectiveness,
        g.lateral_effectiveness,
        g.yaw_effectiveness,
    );
    let map = MecanumKinematics::standard_with_effectiveness(g.lx, g.ly, g.wheel_radius, k)
        .map_err(|e| CalibrateError::Config(e.to_string()))?;
    let mut pose = Pose2::default();
    let mut track = Vec::with_capacity(joints.len());
    let mut last = joints[0].wheels;
    for j in joints {
        let d: [f64; 4] = core::array::from_fn(|i| j.wheels[i] - last[i]);
        pose = pose.exp(map.displacement(&WheelDeltas::new(d[0], d[1], d[2], d[3])));
        last = j.wheels;
        track.push((j.t, pose));
    }
    Ok(track)
}

/// The pods' windows: for each of the fit's windows, the reference's increment and each of
/// the `pods` configured pods' angle increments, from the `/joint_states` samples at the
/// window's ends (the windows' ends are those samples' times). None without pods.
///
/// # Errors
/// [`CalibrateError::NoPodAngles`] if the samples lack a pod's angle.
pub(super) fn pod_windows(
    pods: usize,
    joints: &[Joints],
    steady: &[&Window],
) -> Result<Vec<pods::PodWindow>, CalibrateError> {
    if pods == 0 {
        return Ok(Vec::new());
    }
    let no_angles = |missing| CalibrateError::NoPodAngles { pods, missing };
    let Some(first) = joints.first() else {
        return Err(no_angles(0));
    };
    if let Some(missing) = (0..pods).find(|&i| first.pods[i].is_none()) {
        return Err(no_angles(missing));
    }
    let at = |t: u64| {
        let i = joints.partition_point(|j| j.t < t);
        joints.get(i).filter(|j| j.t == t)
    };
    Ok(steady
        .iter()
        .filter_map(|w| {
            let (j0, j1) = (at(w.t0)?, at(w.t1)?);
            let angles = (0..pods)
                .map(|i| Some(j1.pods[i]? - j0.pods[i]?))
                .collect::<Option<Vec<f64>>>()?;
            Some(pods::PodWindow {
                reference: w.reference,
                angles,
            })
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn interpolation_follows_the_arc_and_refuses_gaps() {
        let p0 = Pose2::new(1.0, 2.0, 0.5);
        let step = Twist2::new(0.2, -0.1, 0.4);
        let p1 = p0.exp(step);
        let track = vec![(1_000, p0), (2_000, p1), (2_000 + MAX_GAP_NS + 1, p1)];
        let mid = interpolate(&track, 1_500).unwrap();
        let half = p0.exp(Twist2::new(0.1, -0.05, 0.2));
        assert!((mid.x - half.x).abs() < 1e-12 && (mid.y - half.y).abs() < 1e-12);
        assert!((mid.heading - half.heading).abs() < 1e-12);
        assert_eq!(interpolate(&track, 1_000), Some(p0));
        assert_eq!(interpolate(&track, 999), None);
        assert_eq!(interpolate(&track, 3_000), None);
    }
}
