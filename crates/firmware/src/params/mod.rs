//! The robot's parameters: every field of a [`Config`] a host may read over CAN, each with its
//! object (CiA 301 index and sub-index), type, unit, declared range and when it may change.
//!
//! [`PARAMS`] is the one description: the EDS (`dbc/mecanum_robot.eds`, written by
//! `mecanum-codec params --eds`), the CLI, the ROS 2 bridge and the live server read it, and
//! the core's parameter service applies it. [`Param::read`] gives a field's raw 4-byte value
//! (an `f32`'s bits for [`ParamType::Real32`]); [`Param::write`] gives the configuration with
//! one field changed, or the [`Refusal`] that names the parameter, the value and the rule: the
//! declared range, the robot's state ([`Change`]), then every rule of [`Config::validate`].
//! Nothing here keeps state or reads a clock. The object map and the classes are specified in
//! `docs/protocol.md`, section "Parameters".

mod table;
#[cfg(test)]
mod tests;

use core::fmt;

use crate::config::{Config, ConfigError, Drive, PODS_MAX, PodConfig, Pods};
use crate::frame::CanFrame;
use crate::protocol::canopen::{Message, NodeId, SdoRequest, abort_code};

pub use table::PARAMS;

/// A parameter's CANopen data type (CiA 301), as its 4 data bytes carry it, little-endian.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ParamType {
    /// `BOOLEAN` (0x0001): 0 or 1.
    Boolean,
    /// `UNSIGNED8` (0x0005); enums are their numbers.
    Unsigned8,
    /// `UNSIGNED32` (0x0007).
    Unsigned32,
    /// `REAL32` (0x0008): an IEEE 754 `f32`.
    Real32,
}

impl ParamType {
    /// The CiA 301 data type index (an EDS's `DataType`).
    #[must_use]
    pub const fn data_type(self) -> u16 {
        match self {
            Self::Boolean => 0x0001,
            Self::Unsigned8 => 0x0005,
            Self::Unsigned32 => 0x0007,
            Self::Real32 => 0x0008,
        }
    }

    /// Bytes on the wire (an expedited SDO's size).
    #[must_use]
    pub const fn size(self) -> u8 {
        match self {
            Self::Boolean | Self::Unsigned8 => 1,
            Self::Unsigned32 | Self::Real32 => 4,
        }
    }

    /// The value of `raw` as a number (an `f32` widened exactly).
    #[must_use]
    pub fn to_f64(self, raw: u32) -> f64 {
        match self {
            Self::Real32 => f64::from(f32::from_bits(raw)),
            Self::Boolean | Self::Unsigned8 | Self::Unsigned32 => f64::from(raw),
        }
    }

    /// The raw value of `value`: `None` for a number this type cannot hold (a fraction, a
    /// negative or too large integer, or NaN).
    #[must_use]
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    pub fn from_f64(self, value: f64) -> Option<u32> {
        let max = match self {
            Self::Real32 => return (!value.is_nan()).then_some((value as f32).to_bits()),
            Self::Boolean => 1.0,
            Self::Unsigned8 => f64::from(u8::MAX),
            Self::Unsigned32 => f64::from(u32::MAX),
        };
        // In range, the cast is exact for a whole number only.
        (value >= 0.0 && value <= max && f64::from(value as u32) == value).then_some(value as u32)
    }
}

/// When a parameter may change at run time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Change {
    /// In any state, taking effect at the next control step (gains, limits, timeouts).
    Live,
    /// Only while the robot is disabled: what the core precomputes or the odometry depends
    /// on (geometry, rates, the odometry's sources and pods).
    Disabled,
    /// Never over CAN: the drive's protocol, ids and ratio, the control and setpoint rates
    /// (a new configuration file, or a new image).
    Fixed,
}

impl Change {
    /// The name the EDS, the CLI and the hosts use.
    #[must_use]
    pub const fn name(self) -> &'static str {
        match self {
            Self::Live => "live",
            Self::Disabled => "disabled",
            Self::Fixed => "fixed",
        }
    }
}

/// One parameter: a field of [`Config`] as a host sees it.
#[derive(Clone, Copy)]
pub struct Param {
    /// Its name, the configuration file's key (`gains.kp`, `odometry.pods[1].x`).
    pub name: &'static str,
    /// CiA 301 object index (0x2000..).
    pub index: u16,
    /// Sub-index (1..).
    pub sub: u8,
    /// Data type.
    pub ty: ParamType,
    /// SI unit, or "" for a count, a flag or an enum.
    pub unit: &'static str,
    /// The smallest value it may be set to (the tuning bound; [`Config::validate`] may ask
    /// for more, e.g. `> 0`).
    pub low: f64,
    /// The largest value (`f64::INFINITY` where `inf` is a setting).
    pub high: f64,
    /// When it may change.
    pub change: Change,
    /// One line for a UI: what it is; an enum's values.
    pub doc: &'static str,
    /// The field's raw value in `config`; `None` where the configuration has no such field
    /// (another geometry layout, a pod it does not have).
    get: fn(&Config) -> Option<u32>,
    /// Sets the field to a raw value; `false` where the configuration has no such field.
    set: fn(&mut Config, u32) -> bool,
}

impl fmt::Debug for Param {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Param")
            .field("name", &self.name)
            .field("index", &self.index)
            .field("sub", &self.sub)
            .finish_non_exhaustive()
    }
}

/// Why a read or a write is refused. Its `Display` names the parameter, the value and the rule.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Refusal {
    /// No parameter has this name or object.
    Unknown,
    /// The configuration has no such field (another geometry layout, a pod it does not have).
    Absent {
        /// The parameter.
        name: &'static str,
    },
    /// Never written over CAN ([`Change::Fixed`]).
    ReadOnly {
        /// The parameter.
        name: &'static str,
    },
    /// Written only while the robot is disabled ([`Change::Disabled`]).
    WhileEnabled {
        /// The parameter.
        name: &'static str,
    },
    /// Not a value of the parameter's type (NaN, a boolean other than 0 or 1).
    NotAValue {
        /// The parameter.
        name: &'static str,
        /// The value, as a number.
        value: f64,
    },
    /// Below [`Param::low`].
    TooLow {
        /// The parameter.
        name: &'static str,
        /// The value.
        value: f64,
        /// The bound.
        low: f64,
    },
    /// Above [`Param::high`].
    TooHigh {
        /// The parameter.
        name: &'static str,
        /// The value.
        value: f64,
        /// The bound.
        high: f64,
    },
    /// A rule of [`Config::validate`] refuses the configuration it would make.
    Invalid(ConfigError),
}

impl Refusal {
    /// The CiA 301 SDO abort code a parameter service answers with.
    #[must_use]
    pub const fn abort_code(&self) -> u32 {
        match self {
            Self::Unknown => abort_code::NO_OBJECT,
            Self::Absent { .. } => abort_code::NO_SUBINDEX,
            Self::ReadOnly { .. } => abort_code::READ_ONLY,
            Self::WhileEnabled { .. } => abort_code::DEVICE_STATE,
            Self::NotAValue { .. } | Self::Invalid(_) => abort_code::INVALID_VALUE,
            Self::TooHigh { .. } => abort_code::TOO_HIGH,
            Self::TooLow { .. } => abort_code::TOO_LOW,
        }
    }
}

impl fmt::Display for Refusal {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Self::Unknown => write!(f, "no such parameter"),
            Self::Absent { name } => write!(f, "{name}: not in this configuration"),
            Self::ReadOnly { name } => write!(
                f,
                "{name}: read-only over CAN (a new configuration file or image changes it)"
            ),
            Self::WhileEnabled { name } => write!(f, "{name}: changes only while disabled"),
            Self::NotAValue { name, value } => write!(f, "{name} = {value}: not a valid value"),
            Self::TooLow { name, value, low } => write!(f, "{name} = {value}: below {low}"),
            Self::TooHigh { name, value, high } => write!(f, "{name} = {value}: above {high}"),
            Self::Invalid(e) => write!(f, "{e}"),
        }
    }
}

impl Param {
    /// The field's raw value in `config`.
    ///
    /// # Errors
    /// [`Refusal::Absent`] where the configuration has no such field.
    pub fn read(&self, config: &Config) -> Result<u32, Refusal> {
        (self.get)(config).ok_or(Refusal::Absent { name: self.name })
    }

    /// The request that sets this parameter to `raw` on the service of node `node` (an
    /// expedited SDO download of the type's size); `None` for a node id outside `1..=127`.
    #[must_use]
    pub fn download(&self, node: u8, raw: u32) -> Option<CanFrame> {
        let request = SdoRequest::Download {
            index: self.index,
            sub: self.sub,
            value: raw,
            size: self.ty.size(),
        };
        let node = NodeId::new(node)?;
        Some(Message::SdoRequest { node, request }.to_can_frame())
    }

    /// `config` with this field set to `raw`, checked: the robot's state (`enabled`), the
    /// type, the declared range, then [`Config::validate`] on the whole configuration.
    ///
    /// # Errors
    /// The first [`Refusal`] found, in that order.
    pub fn write(&self, config: &Config, raw: u32, enabled: bool) -> Result<Config, Refusal> {
        let name = self.name;
        match self.change {
            Change::Fixed => return Err(Refusal::ReadOnly { name }),
            Change::Disabled if enabled => return Err(Refusal::WhileEnabled { name }),
            Change::Live | Change::Disabled => {}
        }
        let value = self.ty.to_f64(raw);
        let fits = match self.ty {
            ParamType::Real32 => !value.is_nan(),
            ParamType::Boolean => raw <= 1,
            ParamType::Unsigned8 => raw <= u32::from(u8::MAX),
            ParamType::Unsigned32 => true,
        };
        if !fits {
            return Err(Refusal::NotAValue { name, value });
        }
        if value < self.low {
            return Err(Refusal::TooLow {
                name,
                value,
                low: self.low,
            });
        }
        if value > self.high {
            return Err(Refusal::TooHigh {
                name,
                value,
                high: self.high,
            });
        }
        let mut candidate = *config;
        if !(self.set)(&mut candidate, raw) {
            return Err(Refusal::Absent { name });
        }
        candidate.validate().map_err(Refusal::Invalid)?;
        Ok(candidate)
    }
}

/// The robot's parameter service's node id when its drives are not CANopen nodes (with CiA
/// 402 drives it is their master's, `drive.master_node`).
pub const SERVICE_NODE_DEFAULT: u8 = 127;

/// The node id of the robot's parameter service for `config`: requests on `0x600 + id`,
/// responses on `0x580 + id`.
#[must_use]
pub const fn service_node(config: &Config) -> u8 {
    match config.drive {
        Drive::Cia402(ref d) => d.master_node,
        Drive::Dji { .. } | Drive::Odrive { .. } => SERVICE_NODE_DEFAULT,
    }
}

/// The parameter called `name`.
#[must_use]
pub fn find(name: &str) -> Option<&'static Param> {
    PARAMS.iter().find(|p| p.name == name)
}

/// The parameter at object `index`, sub-index `sub`.
#[must_use]
pub fn at(index: u16, sub: u8) -> Option<&'static Param> {
    PARAMS.iter().find(|p| p.index == index && p.sub == sub)
}

/// The highest sub-index of object `index` (what its sub-index 0 reads, as a record's entry
/// count): `None` for an index no parameter has.
#[must_use]
pub fn highest_sub(index: u16) -> Option<u8> {
    PARAMS
        .iter()
        .filter(|p| p.index == index)
        .map(|p| p.sub)
        .max()
}

/// Whether `target` differs from `base` only in parameters a host may write ([`Change::Live`]
/// or [`Change::Disabled`]): what a saved configuration must be to run on the image whose
/// built-in configuration is `base`.
#[must_use]
pub fn reachable(base: &Config, target: &Config) -> bool {
    let mut made = *base;
    for p in PARAMS.iter().filter(|p| p.change != Change::Fixed) {
        if let Some(raw) = (p.get)(target) {
            (p.set)(&mut made, raw);
        }
    }
    made == *target
}

/// Pod `i` of `config`, if it has one.
fn pod(config: &Config, i: usize) -> Option<PodConfig> {
    config.odometry.pods.as_slice().get(i).copied()
}

/// Changes pod `i` of `config` with `edit`; `false` if it has no pod `i`.
fn set_pod(config: &mut Config, i: usize, edit: impl FnOnce(&mut PodConfig)) -> bool {
    let pods = config.odometry.pods.as_slice();
    let mut list = [PodConfig::default(); PODS_MAX];
    let Some(slot) = list.get_mut(..pods.len()) else {
        return false;
    };
    slot.copy_from_slice(pods);
    let Some(p) = slot.get_mut(i) else {
        return false;
    };
    edit(p);
    match Pods::new(slot) {
        Some(pods) => {
            config.odometry.pods = pods;
            true
        }
        None => false,
    }
}
