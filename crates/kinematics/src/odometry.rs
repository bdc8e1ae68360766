//! Dead reckoning: poses advanced from wheel angle increments.
//!
//! Each step, forward kinematics turns the wheel increments into a body displacement
//! ([`MecanumKinematics::displacement`]) and the pose moves along the arc of constant body
//! velocity that produces it ([`Pose2::exp`], the SE(2) exponential). Unlike an Euler update,
//! the result does not depend on the step size: driving a circle in 10 steps or in 10,000
//! lands on the same arc.

use crate::kinematics::MecanumKinematics;
use crate::real::Real;
use crate::types::{Pose2, Twist2, WheelDeltas};

/// A pose estimate integrated from wheel increments. Holds only the pose; the kinematics are
/// passed to [`update`](Self::update) so one map can serve several estimators.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Odometry<T> {
    pose: Pose2<T>,
}

impl<T: Real> Odometry<T> {
    /// An estimator starting at `pose`.
    #[must_use]
    pub const fn new(pose: Pose2<T>) -> Self {
        Self { pose }
    }

    /// The current pose.
    #[must_use]
    pub const fn pose(&self) -> Pose2<T> {
        self.pose
    }

    /// Replaces the pose (e.g. from a localisation fix), keeping nothing of the old one.
    pub fn set_pose(&mut self, pose: Pose2<T>) {
        self.pose = pose;
    }

    /// Returns to the origin with heading zero.
    pub fn reset(&mut self) {
        self.pose = Pose2::default();
    }

    /// Advances by one step's wheel angle increments (rad, layout order) and returns the new
    /// pose.
    #[inline]
    pub fn update<const N: usize>(
        &mut self,
        kinematics: &MecanumKinematics<T, N>,
        deltas: &WheelDeltas<T, N>,
    ) -> Pose2<T> {
        self.apply(kinematics.displacement(deltas))
    }

    /// Advances by a body displacement (body frame at the start of the step).
    #[inline]
    pub fn apply(&mut self, twist: Twist2<T>) -> Pose2<T> {
        self.pose = self.pose.exp(twist);
        self.pose
    }
}
