//! `[odometry]`'s tracking pods: where the odometry's increments come from
//! ([`OdometryMode`]) and the pods' layout ([`PodConfig`], at most [`PODS_MAX`] in [`Pods`]).
//!
//! A pod is an unpowered omni wheel with an encoder, rolling freely on the floor: it sees the
//! body slide where no drive encoder can. The model, the formulas and the fallback to the
//! wheels are specified in `docs/control.md`, "Odometry from tracking pods"; the frame that
//! carries the counts is `POD_COUNTS` (`docs/protocol.md`).
//!
//! [`Pods`] is a fixed array and a length, so that [`Config`](super::Config) stays `Copy`
//! and heap-free; in TOML it is an array of tables (`[[odometry.pods]]`).

use kinematics::{PodGeometry, PodLayoutError, PodLocalizer};

use super::ConfigError;
pub use crate::protocol::robot::layout::PODS_MAX;

/// Where the odometry takes each step's increments from (`odometry.source`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Deserialize, serde::Serialize))]
#[cfg_attr(feature = "serde", serde(rename_all = "snake_case"))]
pub enum OdometryMode {
    /// `"wheels"`: the drive encoders (and the gyro's rotation with `heading_source =
    /// "gyro"`).
    #[default]
    Wheels,
    /// `"pods2_gyro"`: two pods' translation, the gyro's rotation (needs `heading_source =
    /// "gyro"`), as Road Runner's two-wheel localizer and goBILDA's Pinpoint.
    Pods2Gyro,
    /// `"pods3"`: three pods give translation and rotation, as Road Runner's three-wheel
    /// localizer.
    Pods3,
}

impl OdometryMode {
    /// How many pods the mode reads (0 for the wheels).
    #[must_use]
    pub const fn pods(self) -> usize {
        match self {
            Self::Wheels => 0,
            Self::Pods2Gyro => 2,
            Self::Pods3 => 3,
        }
    }
}

/// One tracking pod (`[[odometry.pods]]`): where it touches the floor, which way it counts
/// up, and its wheel.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Deserialize, serde::Serialize))]
#[cfg_attr(feature = "serde", serde(deny_unknown_fields))]
pub struct PodConfig {
    /// Contact point, forward of the body's reference point, m.
    pub x: f32,
    /// Contact point, left of the body's reference point, m.
    pub y: f32,
    /// The direction of travel in which its count increases, degrees counter-clockwise from
    /// the body's x axis (0: a forward-counting "parallel" pod, 90: a leftward-counting
    /// "perpendicular" one).
    pub direction_deg: f32,
    /// The omni wheel's radius, m (> 0).
    pub radius: f32,
    /// Encoder counts per turn of the pod wheel (quadrature edges), in `1..=1_000_000`.
    pub counts_per_turn: u32,
}

impl PodConfig {
    /// The pod's travel per encoder count, m.
    #[must_use]
    pub fn metres_per_count(&self) -> f32 {
        core::f32::consts::TAU * self.radius / self.counts_per_turn as f32
    }

    /// The pod's place and direction for the localizer (direction in radians).
    #[must_use]
    pub fn geometry(&self) -> PodGeometry<f32> {
        PodGeometry {
            x: self.x,
            y: self.y,
            direction: self.direction_deg.to_radians(),
        }
    }
}

/// The configured pods, at most [`PODS_MAX`], in the order of `POD_COUNTS.count0..2`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Pods {
    list: [PodConfig; PODS_MAX],
    len: u8,
}

impl Pods {
    /// The pods of `list`; `None` for more than [`PODS_MAX`].
    #[must_use]
    pub fn new(list: &[PodConfig]) -> Option<Self> {
        let mut pods = Self::default();
        for pod in list {
            *pods.list.get_mut(usize::from(pods.len))? = *pod;
            pods.len += 1;
        }
        Some(pods)
    }

    /// The pods, in order.
    #[must_use]
    pub fn as_slice(&self) -> &[PodConfig] {
        &self.list[..usize::from(self.len)]
    }

    /// How many.
    #[must_use]
    pub fn len(&self) -> usize {
        usize::from(self.len)
    }

    /// Whether there are none.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
}

/// The solve of a valid pod layout: two pods (the heading from elsewhere) or three.
#[derive(Debug, Clone, Copy)]
pub(crate) enum PodSolve {
    /// `"pods2_gyro"`.
    Two(PodLocalizer<f32, 2>),
    /// `"pods3"`.
    Three(PodLocalizer<f32, 3>),
}

/// The localizer a valid configuration builds: the solve of `mode`'s pods.
///
/// # Errors
/// The first field that is wrong, named: a pod count that does not match the mode, a pod's
/// value, or a layout that cannot determine what the mode asks of it (two pods counting along
/// parallel lines cannot tell sideways motion; three whose lines of action meet in one point
/// cannot see a rotation about it).
pub(crate) fn localizer(mode: OdometryMode, pods: &Pods) -> Result<Option<PodSolve>, ConfigError> {
    if pods.len() != mode.pods() {
        return Err(ConfigError {
            field: "odometry.pods",
            value: pods.len() as f64,
            expected: match mode {
                OdometryMode::Wheels => {
                    "no pods with odometry.source = \"wheels\" (set source to \"pods2_gyro\" \
                     or \"pods3\" to use them)"
                }
                OdometryMode::Pods2Gyro => "2 pods for odometry.source = \"pods2_gyro\"",
                OdometryMode::Pods3 => "3 pods for odometry.source = \"pods3\"",
            },
        });
    }
    for (i, pod) in pods.as_slice().iter().enumerate() {
        let bad = |field: &'static str, value: f64, expected: &'static str| ConfigError {
            field: field_at(field, i),
            value,
            expected,
        };
        for (field, value, limit, expected) in [
            (
                "odometry.pods.x",
                pod.x,
                100.0,
                "a finite coordinate within ±100 m",
            ),
            (
                "odometry.pods.y",
                pod.y,
                100.0,
                "a finite coordinate within ±100 m",
            ),
            (
                "odometry.pods.direction_deg",
                pod.direction_deg,
                360.0,
                "a finite direction within ±360°",
            ),
        ] {
            if !value.is_finite() || value.abs() > limit {
                return Err(bad(field, f64::from(value), expected));
            }
        }
        if !(pod.radius.is_finite() && pod.radius > 0.0 && pod.radius <= 1.0) {
            return Err(bad(
                "odometry.pods.radius",
                f64::from(pod.radius),
                "a radius in (0, 1] m",
            ));
        }
        if !(1..=1_000_000).contains(&pod.counts_per_turn) {
            return Err(bad(
                "odometry.pods.counts_per_turn",
                f64::from(pod.counts_per_turn),
                "a count in 1..=1000000",
            ));
        }
    }
    let g = |i: usize| pods.list[i].geometry();
    let solve = match mode {
        OdometryMode::Wheels => return Ok(None),
        OdometryMode::Pods2Gyro => {
            PodSolve::Two(PodLocalizer::two([g(0), g(1)]).map_err(layout_error)?)
        }
        OdometryMode::Pods3 => {
            PodSolve::Three(PodLocalizer::three([g(0), g(1), g(2)]).map_err(layout_error)?)
        }
    };
    Ok(Some(solve))
}

fn layout_error(e: PodLayoutError) -> ConfigError {
    // Degrees to f32's precision, as the configuration holds its values (-180, not
    // -179.999995).
    #[allow(clippy::cast_possible_truncation)]
    let degrees = |rad: f64| f64::from(rad.to_degrees() as f32);
    let (field, value, expected) = match e {
        PodLayoutError::NonFinite { pod, field } => (
            field_at(
                match field {
                    "x" => "odometry.pods.x",
                    "y" => "odometry.pods.y",
                    _ => "odometry.pods.direction_deg",
                },
                pod,
            ),
            f64::NAN,
            "a finite value",
        ),
        PodLayoutError::Parallel { second, angle, .. } => (
            field_at("odometry.pods.direction_deg", second),
            degrees(angle),
            "a direction not parallel to pod 0's: two pods counting along parallel lines \
             cannot tell the translation across them (the value is the angle between them, °)",
        ),
        PodLayoutError::AllParallel { angle, .. } => (
            "odometry.pods.direction_deg",
            degrees(angle),
            "three pods not all parallel: along parallel lines they cannot tell the \
             translation across them (the value is the largest angle between them, °)",
        ),
        PodLayoutError::Concurrent { .. } => (
            "odometry.pods",
            f64::NAN,
            "three pods whose lines of action do not meet in one point: a rotation about \
             that point is invisible to them (move one pod off it)",
        ),
        _ => (
            "odometry.pods",
            f64::NAN,
            "coordinates whose solve fits f32 (check their units: metres)",
        ),
    };
    ConfigError {
        field,
        value,
        expected,
    }
}

/// `prefix` with the pod's index, as a static string (the error names the pod).
fn field_at(prefix: &'static str, i: usize) -> &'static str {
    macro_rules! table {
        ($($p:literal),*) => {
            match prefix {
                $($p => [concat!($p, "[0]"), concat!($p, "[1]"), concat!($p, "[2]")][i.min(2)],)*
                _ => prefix,
            }
        };
    }
    table!(
        "odometry.pods.x",
        "odometry.pods.y",
        "odometry.pods.direction_deg",
        "odometry.pods.radius",
        "odometry.pods.counts_per_turn"
    )
}

#[cfg(feature = "serde")]
mod serde_impl {
    //! `[[odometry.pods]]`: an array of up to [`PODS_MAX`] tables.
    use core::fmt;

    use serde::de::{Error, SeqAccess, Visitor};
    use serde::ser::SerializeSeq;
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    use super::{PODS_MAX, PodConfig, Pods};

    impl Serialize for Pods {
        fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
            let mut seq = s.serialize_seq(Some(self.len()))?;
            for pod in self.as_slice() {
                seq.serialize_element(pod)?;
            }
            seq.end()
        }
    }

    impl<'de> Deserialize<'de> for Pods {
        fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
            struct List;
            impl<'de> Visitor<'de> for List {
                type Value = Pods;
                fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                    write!(f, "at most {PODS_MAX} pods")
                }
                fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Pods, A::Error> {
                    let mut pods = Pods::default();
                    while let Some(pod) = seq.next_element::<PodConfig>()? {
                        let len = pods.len();
                        let Some(slot) = pods.list.get_mut(len) else {
                            return Err(A::Error::invalid_length(
                                PODS_MAX + 1,
                                &"at most 3 pods (POD_COUNTS carries three counts)",
                            ));
                        };
                        *slot = pod;
                        pods.len += 1;
                    }
                    Ok(pods)
                }
            }
            d.deserialize_seq(List)
        }
    }
}
