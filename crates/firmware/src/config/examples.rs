//! The example chassis of `config/`, built in code: what the tests, the simulator and a board
//! without a file system start from.

use super::{
    Cia402Drive, Config, Drive, Gains, Geometry, Limits, OdometryConfig, Timing, cia402_defaults,
};
use crate::protocol::dji::EscModel;

impl Config {
    /// The example 4 x M3508 / C620 chassis (`config/dji_m3508.toml`): 0.40 m x 0.36 m
    /// between wheel centres, 76 mm radius wheels, ESC ids 1-4, right side mirrored.
    #[must_use]
    pub fn dji_m3508_example() -> Self {
        Self {
            geometry: Geometry::Standard {
                lx: 0.20,
                ly: 0.18,
                wheel_radius: 0.076,
                forward_effectiveness: 1.0,
                lateral_effectiveness: 1.0,
                yaw_effectiveness: 1.0,
            },
            drive: Drive::Dji {
                model: EscModel::C620,
                esc_ids: [1, 2, 3, 4],
                gear_ratio: 3591.0 / 187.0,
                inverted: [false, true, false, true],
            },
            limits: Limits::default(),
            gains: Gains::default(),
            timing: Timing::default(),
            odometry: OdometryConfig::default(),
        }
    }

    /// The example 4-axis ODrive chassis (`config/odrive.toml`): nodes 0-3, 5:1 belt,
    /// 0.30 m x 0.25 m between wheel centres, 50 mm radius wheels.
    #[must_use]
    pub fn odrive_example() -> Self {
        Self {
            geometry: Geometry::Standard {
                lx: 0.15,
                ly: 0.125,
                wheel_radius: 0.05,
                forward_effectiveness: 1.0,
                lateral_effectiveness: 1.0,
                yaw_effectiveness: 1.0,
            },
            drive: Drive::Odrive {
                node_ids: [0, 1, 2, 3],
                gear_ratio: 5.0,
                inverted: [false, true, false, true],
                vel_ramp: false,
            },
            limits: Limits {
                max_wheel_speed: 60.0,
                ..Limits::default()
            },
            gains: Gains::default(),
            timing: Timing::default(),
            odometry: OdometryConfig::default(),
        }
    }

    /// The example CiA 402 chassis (`config/cia402.toml`): two dual-axis hub-motor drives
    /// (nodes 1 and 2, a ZLAC8015D-class drive per axle: target velocity in rpm, actual in
    /// 0.1 rpm), 0.50 m x 0.42 m between wheel centres, 100 mm radius wheels, a 250 Hz cycle.
    #[must_use]
    pub fn cia402_example() -> Self {
        Self {
            geometry: Geometry::Standard {
                lx: 0.25,
                ly: 0.21,
                wheel_radius: 0.1,
                forward_effectiveness: 1.0,
                lateral_effectiveness: 1.0,
                yaw_effectiveness: 1.0,
            },
            drive: Drive::Cia402(Cia402Drive {
                node_ids: [1, 1, 2, 2],
                axes: [1, 2, 1, 2],
                gear_ratio: 1.0,
                inverted: [false, true, false, true],
                target_rpm_per_unit: 1.0,
                actual_rpm_per_unit: 0.1,
                master_node: cia402_defaults::master_node(),
                heartbeat_ms: cia402_defaults::heartbeat_ms(),
                heartbeat_timeout_ms: cia402_defaults::heartbeat_timeout_ms(),
            }),
            limits: Limits {
                max_linear_speed: 1.5,
                max_angular_speed: 3.0,
                // Hub motors at 300 rpm: 31 rad/s.
                max_wheel_speed: 30.0,
                ..Limits::default()
            },
            gains: Gains::default(),
            timing: Timing {
                setpoint_hz: 250,
                ..Timing::default()
            },
            odometry: OdometryConfig::default(),
        }
    }
}
