//! The settings of CANopen CiA 402 drives (`[drive] protocol = "cia402"`) and their checks.

use super::{ConfigError, check_gear_ratio, field_at, positive};
use crate::protocol::canopen::NodeId;

/// CANopen CiA 402 drives in profile velocity mode, and the core as their master
/// (`docs/protocol.md`, section "CANopen CiA 402"): [`Drive::Cia402`](super::Drive::Cia402).
///
/// In TOML, the keys of the `[drive]` table beside `protocol = "cia402"`.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct Cia402Drive {
    /// Node id (1..=127) of each wheel's drive; a dual-axis drive's node appears twice.
    pub node_ids: [u8; 4],
    /// Each wheel's axis on its node: 0 for a single-axis drive (objects at sub-index
    /// 0), 1 or 2 for an axis of a dual-axis drive (sub-indices 1 and 2).
    pub axes: [u8; 4],
    /// Motor turns per wheel turn (1 for a hub motor).
    pub gear_ratio: f32,
    /// `true` where a positive motor velocity rolls the robot backward.
    pub inverted: [bool; 4],
    /// Motor rpm per raw unit of target velocity (0x60FF): 1 for drives that take rpm.
    pub target_rpm_per_unit: f32,
    /// Motor rpm per raw unit of actual velocity (0x606C): 0.1 for drives that report
    /// 0.1 rpm.
    pub actual_rpm_per_unit: f32,
    /// The master's own node id (1..=127), whose heartbeat (`0x700 + master_node`) the
    /// drives watch. Default [`defaults::master_node`].
    pub master_node: u8,
    /// The drives' and the master's heartbeat period, ms (object 0x1017). Default
    /// [`defaults::heartbeat_ms`].
    pub heartbeat_ms: u16,
    /// A heartbeat silent this long is lost, ms: the master's limit for each drive's, and
    /// the drives' for the master's (object 0x1016). Default
    /// [`defaults::heartbeat_timeout_ms`].
    pub heartbeat_timeout_ms: u16,
}

/// The defaults of the optional keys of [`Cia402Drive`].
pub mod defaults {
    /// `drive.master_node`: 127.
    #[must_use]
    pub const fn master_node() -> u8 {
        127
    }

    /// `drive.heartbeat_ms`: 50.
    #[must_use]
    pub const fn heartbeat_ms() -> u16 {
        50
    }

    /// `drive.heartbeat_timeout_ms`: 150.
    #[must_use]
    pub const fn heartbeat_timeout_ms() -> u16 {
        150
    }
}

impl Cia402Drive {
    /// The checks of [`Config::validate`](super::Config::validate) on these settings, with
    /// the control rate the heartbeat period must divide.
    pub(super) fn check(&self, control_hz: u32) -> Result<(), ConfigError> {
        check_nodes(self.node_ids, self.axes, self.master_node)?;
        check_gear_ratio(self.gear_ratio)?;
        positive("drive.target_rpm_per_unit", self.target_rpm_per_unit)?;
        positive("drive.actual_rpm_per_unit", self.actual_rpm_per_unit)?;
        let heartbeat_ms = self.heartbeat_ms;
        if heartbeat_ms == 0 || !(u32::from(heartbeat_ms) * control_hz).is_multiple_of(1000) {
            return Err(ConfigError {
                field: "drive.heartbeat_ms",
                value: f64::from(heartbeat_ms),
                expected: "a period > 0 ms that is a whole number of control periods",
            });
        }
        if self.heartbeat_timeout_ms <= heartbeat_ms {
            return Err(ConfigError {
                field: "drive.heartbeat_timeout_ms",
                value: f64::from(self.heartbeat_timeout_ms),
                expected: "a time longer than drive.heartbeat_ms",
            });
        }
        Ok(())
    }
}

/// The nodes of a CiA 402 configuration: ids in 1..=127, axes 0 (single-axis node, one
/// wheel) or 1 and 2 (dual-axis node, a wheel each), the master's id not a drive's.
fn check_nodes(node_ids: [u8; 4], axes: [u8; 4], master: u8) -> Result<(), ConfigError> {
    for (i, (&id, &axis)) in node_ids.iter().zip(&axes).enumerate() {
        if NodeId::new(id).is_none() {
            return Err(ConfigError {
                field: field_at("drive.node_ids", i),
                value: f64::from(id),
                expected: "a CANopen node id in 1..=127",
            });
        }
        if axis > 2 {
            return Err(ConfigError {
                field: field_at("drive.axes", i),
                value: f64::from(axis),
                expected: "0 (a single-axis drive) or 1, 2 (an axis of a dual-axis drive)",
            });
        }
        for (&other_id, &other_axis) in node_ids[..i].iter().zip(&axes[..i]) {
            if other_id == id && (axis == 0 || other_axis == 0 || other_axis == axis) {
                return Err(ConfigError {
                    field: field_at("drive.axes", i),
                    value: f64::from(axis),
                    expected: "a different axis (1 or 2) of a node that drives two wheels; \
                               0 only on a node that drives one",
                });
            }
        }
        if id == master {
            return Err(ConfigError {
                field: "drive.master_node",
                value: f64::from(master),
                expected: "a node id in 1..=127 that no drive has",
            });
        }
    }
    if NodeId::new(master).is_none() {
        return Err(ConfigError {
            field: "drive.master_node",
            value: f64::from(master),
            expected: "a node id in 1..=127 that no drive has",
        });
    }
    Ok(())
}
