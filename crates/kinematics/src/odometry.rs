//! Dead reckoning: poses advanced from wheel angle increments.
//!
//! Each step, forward kinematics turns the wheel increments into a body displacement
//! ([`MecanumKinematics::displacement`]) and the pose moves along the arc of constant body
//! velocity that produces it ([`Pose2::exp`], the SE(2) exponential). Unlike an Euler update,
//! the result does not depend on the step size: driving a circle in 10 steps or in 10,000
//! lands on the same arc.

use crate::kinematics::MecanumKinematics;
use crate::real::{Real, wrap_angle};
use crate::types::{Pose2, Twist2, WheelDeltas};

/// A pose estimate integrated from wheel increments. Holds only the pose (as compensated
/// sums, below); the kinematics are passed to [`update`](Self::update) so one map can serve
/// several estimators.
///
/// # Precision
///
/// A control loop adds a tiny increment to the pose at every step: at 1 kHz, 0.05 mm for a
/// robot at 5 cm/s. Added to a large coordinate in `f32` (an ulp is 15 µm at 200 m), most of
/// each increment would round away: 8 % of the distance lost at 200 m from the origin, and a
/// heading of 3 rad that never changes at 0.1 mrad/s. So `x`, `y` and the heading are each
/// kept as a running sum and the rounding error of its additions (Kahan's compensated
/// summation): the pose is as accurate as if the sums were exact, at four operations per
/// coordinate and step, with the same results on every target.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Odometry<T> {
    /// The running sums (heading wrapped to `[-π, π]`).
    sum: Pose2<T>,
    /// What the additions to `sum` rounded away, negated (Kahan).
    carry: Pose2<T>,
}

/// `sum + x` with Kahan's compensation: `carry` holds what the additions so far rounded away
/// (negated), and is folded into the next increment. Four operations, no branch.
#[inline]
fn add_compensated<T: Real>(sum: T, x: T, carry: &mut T) -> T {
    let y = x - *carry;
    let t = sum + y;
    *carry = (t - sum) - y;
    t
}

impl<T: Real> Odometry<T> {
    /// An estimator starting at `pose`.
    #[must_use]
    pub fn new(pose: Pose2<T>) -> Self {
        Self {
            sum: pose,
            carry: Pose2::new(T::zero(), T::zero(), T::zero()),
        }
    }

    /// The current pose.
    #[must_use]
    pub fn pose(&self) -> Pose2<T> {
        Pose2 {
            x: self.sum.x - self.carry.x,
            y: self.sum.y - self.carry.y,
            heading: wrap_angle(self.sum.heading - self.carry.heading),
        }
    }

    /// Replaces the pose (e.g. from a localisation fix), keeping nothing of the old one.
    pub fn set_pose(&mut self, pose: Pose2<T>) {
        *self = Self::new(pose);
    }

    /// Returns to the origin with heading zero.
    pub fn reset(&mut self) {
        *self = Self::new(Pose2::default());
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

    /// Advances by a body displacement (body frame at the start of the step): along the arc
    /// of [`Pose2::exp`] from the current pose.
    #[inline]
    pub fn apply(&mut self, twist: Twist2<T>) -> Pose2<T> {
        let zero = T::zero();
        if twist.dx == zero && twist.dy == zero && twist.dtheta == zero {
            return self.pose();
        }
        // The world-frame increment: the arc from the origin at the current heading.
        let heading = self.sum.heading - self.carry.heading;
        let step = Pose2 {
            x: zero,
            y: zero,
            heading,
        }
        .exp(twist);
        self.sum.x = add_compensated(self.sum.x, step.x, &mut self.carry.x);
        self.sum.y = add_compensated(self.sum.y, step.y, &mut self.carry.y);
        let h = add_compensated(self.sum.heading, twist.dtheta, &mut self.carry.heading);
        // Exact: the remainder by 2π has no rounding error.
        self.sum.heading = wrap_angle(h);
        self.pose()
    }
}
