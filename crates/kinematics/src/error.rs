//! Typed errors. Small, `Copy`, and carrying the rejected value so a log line can say why.

use core::fmt;

/// A body axis of the chassis twist, for errors that name one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Axis {
    /// x, forward (`vx`).
    Forward,
    /// y, to the left (`vy`).
    Lateral,
    /// Yaw, counter-clockwise (`wz`).
    Yaw,
}

impl Axis {
    /// The three axes in twist order (x, y, yaw).
    pub const ALL: [Self; 3] = [Self::Forward, Self::Lateral, Self::Yaw];

    /// `"forward"`, `"lateral"` or `"yaw"`.
    #[must_use]
    pub const fn name(self) -> &'static str {
        match self {
            Self::Forward => "forward",
            Self::Lateral => "lateral",
            Self::Yaw => "yaw",
        }
    }
}

impl fmt::Display for Axis {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Why a wheel layout was refused by [`MecanumKinematics::new`](crate::MecanumKinematics::new)
/// or [`MecanumKinematics::standard`](crate::MecanumKinematics::standard).
///
/// Values are widened to `f64` so that the error type does not depend on the scalar type.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub enum GeometryError {
    /// A parameter of wheel `wheel` is NaN or infinite.
    NonFinite {
        /// Index of the wheel in the layout (0 = FL for the standard layout).
        wheel: usize,
        /// Name of the parameter.
        field: &'static str,
    },
    /// A wheel radius is zero or negative.
    NonPositiveRadius {
        /// Index of the wheel.
        wheel: usize,
        /// The rejected radius, metres.
        radius: f64,
    },
    /// A roller axis is parallel to the wheel axle (`sin δ = 0`): the wheel cannot drive the
    /// chassis at all (Tlale and de Villiers, eq. 3: effectiveness `sin δ`).
    RollerParallelToAxle {
        /// Index of the wheel.
        wheel: usize,
        /// The rejected roller angle δ, radians.
        roller_angle: f64,
    },
    /// The wheel map has rank < 3, or so nearly that the float type cannot invert it
    /// reliably: some body motion is (almost) invisible to the wheels and forward kinematics
    /// is not unique. The roller axes are concurrent or all parallel (Gfrerrer 2008, Theorem 2), or
    /// close to it. `condition` is the (dimensionless) condition number found, possibly
    /// infinite; the limit is
    /// [`MecanumKinematics::max_condition_number`](crate::MecanumKinematics::max_condition_number)
    /// (about 362 in `f32`, 8.4e6 in `f64`).
    Singular {
        /// Ratio of the largest to the smallest singular value of the scaled wheel map.
        condition: f64,
    },
    /// A distance of the standard layout is negative. `lx` and `ly` are distances from the
    /// centre to the wheels (`>= 0`); a negative one would silently reverse the yaw
    /// direction of the whole map.
    NegativeDistance {
        /// `"lx"` or `"ly"`.
        field: &'static str,
        /// The rejected value, metres.
        value: f64,
    },
    /// The layout is geometrically fine, but its numbers do not fit the float type: an entry
    /// of the wheel map `J` or of its least-squares inverse `J⁺` overflows, or underflows to
    /// zero or to a few digits, so that `J` rounded to the type is not the layout's map or
    /// `J⁺ J` is not the identity. Lengths and radius of extreme magnitude cause it (e.g.
    /// wheels 3e-30 m from the centre of a 1e30 m wheel in `f32`); check their units.
    Unrepresentable {
        /// How far off the rounded map is, relative and with the columns scaled as for the
        /// condition number: the largest error of `J` as a fraction of its largest entry
        /// (allowed: ε of the type), or else the largest entry of `|J⁺ J − I|` (allowed:
        /// `32 N · condition · ε`), or else the largest error of a map scaled by the
        /// effectiveness factors (allowed: ε). Infinite if an entry is not finite.
        deviation: f64,
    },
    /// An effectiveness factor (see
    /// [`Effectiveness`](crate::Effectiveness)) is NaN, infinite, `<= 0` or above
    /// [`MAX_EFFECTIVENESS`](crate::MAX_EFFECTIVENESS).
    Effectiveness {
        /// The axis of the factor.
        axis: Axis,
        /// The rejected factor (dimensionless).
        value: f64,
    },
}

impl fmt::Display for GeometryError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Self::NonFinite { wheel, field } => {
                write!(f, "wheel {wheel}: {field} is not finite")
            }
            Self::NonPositiveRadius { wheel, radius } => {
                write!(f, "wheel {wheel}: radius {radius} m is not positive")
            }
            Self::RollerParallelToAxle {
                wheel,
                roller_angle,
            } => write!(
                f,
                "wheel {wheel}: roller angle {roller_angle} rad is parallel to the axle (sin = 0)"
            ),
            Self::Singular { condition } => write!(
                f,
                "wheel layout is singular (condition number {condition:e}): roller axes are \
                 (nearly) concurrent or parallel, so forward kinematics is not unique"
            ),
            Self::NegativeDistance { field, value } => write!(
                f,
                "standard layout: {field} = {value} m is negative; it is a distance from the \
                 centre (>= 0), and a negative one reverses the yaw direction"
            ),
            Self::Unrepresentable { deviation } => write!(
                f,
                "wheel map does not fit the float type (max |J+ J - I| = {deviation:e}): \
                 lengths or radius of extreme magnitude overflow or underflow it; check units"
            ),
            Self::Effectiveness { axis, value } => write!(
                f,
                "{axis} effectiveness {value} is not in (0, {}]: it is the fraction of the \
                 wheel-implied motion the robot makes (1 = no slip)",
                crate::kinematics::MAX_EFFECTIVENESS
            ),
        }
    }
}

impl core::error::Error for GeometryError {}

/// Why an encoder configuration or a raw counter reading was refused.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub enum EncoderError {
    /// The counter width must be 1 to 32 bits.
    Bits {
        /// The rejected width.
        bits: u8,
    },
    /// Counts per revolution must be positive.
    CountsPerRev {
        /// The rejected value.
        counts_per_rev: u32,
    },
    /// The gear ratio (motor turns per wheel turn) must be finite and positive.
    GearRatio {
        /// The rejected ratio.
        gear_ratio: f64,
    },
    /// A raw reading does not fit the counter's width.
    RawOutOfRange {
        /// The rejected reading.
        raw: u32,
        /// The largest valid reading, `2^bits - 1`.
        max: u32,
    },
}

impl fmt::Display for EncoderError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Self::Bits { bits } => write!(f, "encoder bits {bits} not in 1..=32"),
            Self::CountsPerRev { counts_per_rev } => {
                write!(
                    f,
                    "encoder counts_per_rev {counts_per_rev} must be positive"
                )
            }
            Self::GearRatio { gear_ratio } => {
                write!(
                    f,
                    "encoder gear_ratio {gear_ratio} must be finite and positive"
                )
            }
            Self::RawOutOfRange { raw, max } => {
                write!(f, "encoder reading {raw} out of range 0..={max}")
            }
        }
    }
}

impl core::error::Error for EncoderError {}

/// Why a tracking-pod layout was refused by
/// [`PodLocalizer::three`](crate::PodLocalizer::three) or
/// [`PodLocalizer::two`](crate::PodLocalizer::two).
///
/// Pods are named by their index in the array given to the constructor. Values are widened
/// to `f64` so that the error type does not depend on the scalar type. `condition` is the
/// Frobenius condition number of the (scaled) pod map that was found too large, possibly
/// infinite; the limit is
/// [`PodLocalizer::max_condition_number`](crate::PodLocalizer::max_condition_number)
/// (about 362 in `f32`, 8.4e6 in `f64`).
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub enum PodLayoutError {
    /// A parameter of pod `pod` is NaN or infinite.
    NonFinite {
        /// Index of the pod.
        pod: usize,
        /// Name of the parameter: `"x"`, `"y"` or `"direction"`.
        field: &'static str,
    },
    /// Two pods measure along (nearly) the same line direction, so together they see only one
    /// component of the translation: the other is invisible. For two pods this is the only
    /// geometric rejection (the heading comes from elsewhere).
    Parallel {
        /// Index of the first pod.
        first: usize,
        /// Index of the second pod.
        second: usize,
        /// Angle from the first pod's direction to the second's, rad, in `[-π, π]`: near 0
        /// (parallel) or near ±π (anti-parallel).
        angle: f64,
        /// Condition number of the 2 × 2 direction matrix.
        condition: f64,
    },
    /// All three pods measure along (nearly) the same direction, collinear or not: the
    /// translation across that direction is invisible. Every pair of them would be refused
    /// as a two-pod layout ([`Parallel`](Self::Parallel)).
    AllParallel {
        /// The largest angle between the lines of action of any two pods, rad, in `[0, π/2]`.
        angle: f64,
        /// Condition number of the scaled 3 × 3 pod map.
        condition: f64,
    },
    /// The lines of action of the three pods (nearly) meet in one point, `(x, y)` in the body
    /// frame: a rotation about that point moves every contact point perpendicular to its
    /// pod's direction, so no pod sees it. Two pods on one line with the third crossing it
    /// are a case of this (the lines meet where the third crosses).
    Concurrent {
        /// Where the lines meet (of the two pods whose lines cross at the largest angle), m.
        x: f64,
        /// Where the lines meet, m.
        y: f64,
        /// Condition number of the scaled 3 × 3 pod map.
        condition: f64,
    },
    /// The layout is geometrically fine, but its numbers do not fit the float type: a pod's
    /// moment arm or an entry of the precomputed inverse overflows, or underflows to a few
    /// digits, so that the inverse rounded to the type does not invert the model. Coordinates
    /// of extreme magnitude cause it (e.g. pods 1e-40 m from the origin in `f32`); check
    /// their units.
    Unrepresentable {
        /// The largest entry of `|F A − I|` (scaled as for the condition number), or the
        /// largest rounding error of a moment arm relative to the layout's size; infinite if
        /// an entry is not finite.
        deviation: f64,
    },
}

impl fmt::Display for PodLayoutError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Self::NonFinite { pod, field } => write!(f, "pod {pod}: {field} is not finite"),
            Self::Parallel {
                first,
                second,
                angle,
                condition,
            } => write!(
                f,
                "pods {first} and {second} are (nearly) parallel (angle between their \
                 directions {angle} rad, condition number {condition:e}): the translation \
                 across them is not determined"
            ),
            Self::AllParallel { angle, condition } => write!(
                f,
                "pods 0, 1 and 2 are (nearly) parallel (largest angle between their lines \
                 {angle} rad, condition number {condition:e}): the translation across them is \
                 not determined"
            ),
            Self::Concurrent { x, y, condition } => write!(
                f,
                "the lines of pods 0, 1 and 2 (nearly) meet at ({x} m, {y} m) (condition \
                 number {condition:e}): a rotation about that point is invisible to them"
            ),
            Self::Unrepresentable { deviation } => write!(
                f,
                "pod map does not fit the float type (deviation {deviation:e}): coordinates of \
                 extreme magnitude overflow or underflow it; check units"
            ),
        }
    }
}

impl core::error::Error for PodLayoutError {}
