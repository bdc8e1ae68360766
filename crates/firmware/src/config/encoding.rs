//! The configuration as bytes: what a board image carries, and what its id is taken over.
//!
//! A board has no file system, so its build (`boards/stm32f407/build.rs`) reads the user's
//! TOML on the host, validates it and writes [`Config::encode`]'s bytes into the image, which
//! [`Config::decode`]s them at boot. [`Config::id`] is the CRC-16 of the same bytes: the robot
//! sends it in every `HEARTBEAT` (`config_id`) and logs it, so a user can tell which
//! configuration a robot runs, on a board, in the runner or in the simulator alike.
//!
//! Hand-written, not serde: the configuration's enums are internally tagged (`layout`,
//! `protocol`), which no non-self-describing serde format (postcard, bincode) can read back,
//! and the decoder has to run in a `no_std` image without a heap. Every field is written in a
//! fixed order at a fixed width (f32 as its bits, so `inf` and the exact values survive), the
//! shorter layouts padded with zeros to one length, [`ENCODED_LEN`]. The first byte is the
//! format's version: an id names a configuration for one version of this format.

use crc::{CRC_16_IBM_3740, Crc};

use super::{
    Cia402Drive, Config, ConfigError, Drive, Gains, Geometry, HeadingMode, Limits, OdometryConfig,
    OdometryMode, PODS_MAX, PodConfig, Pods, Timing, WheelConfig,
};
use crate::protocol::dji::EscModel;

/// The format's version, the first byte of the encoding (2: the CiA 402 drive's fields; 3:
/// the odometry source and the tracking pods).
const FORMAT: u8 = 3;

/// Bytes of the geometry: a tag and 23 f32 (four wheels of five, three factors).
const GEOMETRY_LEN: usize = 1 + 23 * 4;
/// Bytes of the drive: a tag, the ESC model, four ids, the gear ratio, the inversion bits
/// and the ramp flag; then the CiA 402 drive's: four axes, the two velocity units, the
/// master's node and the two heartbeat times.
const DRIVE_LEN: usize = 1 + 1 + 4 + 4 + 1 + 1 + 4 + 2 * 4 + 1 + 2 * 2;

/// Bytes of the odometry: the heading tag, the gyro's two times and flag; the source tag,
/// the pod timeout, the pod count and three pods of four f32 and a u32.
const ODOMETRY_LEN: usize = 1 + 2 * 4 + 1 + 1 + 4 + 1 + PODS_MAX * 5 * 4;

/// The length of every encoded configuration, bytes.
pub const ENCODED_LEN: usize = 1 + GEOMETRY_LEN + DRIVE_LEN + 8 * 4 + 3 * 4 + 7 * 4 + ODOMETRY_LEN;

/// The CRC of [`Config::id`]: CRC-16/IBM-3740 (CCITT-FALSE), as in many CAN tools.
const CRC: Crc<u16> = Crc::<u16>::new(&CRC_16_IBM_3740);

impl Config {
    /// The configuration as [`ENCODED_LEN`] bytes: what a board image carries (its build reads
    /// the TOML on the host and writes these bytes; the image [`decode`](Self::decode)s them),
    /// and what [`id`](Self::id) is taken over.
    ///
    /// Every field in declaration order at a fixed width, little-endian (f32 as its bits, so
    /// `inf` and the exact values survive); enums as a tag byte; the shorter geometry and
    /// drive variants padded with zeros to the longest; the first byte the format's version.
    #[must_use]
    pub fn encode(&self) -> [u8; ENCODED_LEN] {
        let mut w = Writer {
            out: [0; ENCODED_LEN],
            at: 0,
        };
        // Every field, so that a new one cannot be left out.
        let Self {
            geometry,
            drive,
            limits,
            gains,
            timing,
            odometry,
        } = *self;
        w.u8(FORMAT);
        let start = w.at;
        w.geometry(geometry);
        w.at = start + GEOMETRY_LEN;
        w.drive(drive);
        w.at = start + GEOMETRY_LEN + DRIVE_LEN;
        w.limits(limits);
        let Gains { kp, ki, kv } = gains;
        w.f32s(&[kp, ki, kv]);
        w.timing(timing);
        w.odometry(odometry);
        debug_assert_eq!(w.at, ENCODED_LEN);
        w.out
    }

    /// Reads an [`encode`](Self::encode)d configuration and [`validate`](Self::validate)s it.
    ///
    /// # Errors
    /// A [`ConfigError`] naming what is wrong: the length (`encoded.len`), the format version
    /// (`encoded.format`), a tag out of range (`geometry.layout`, `drive.protocol`,
    /// `drive.model`, `odometry.heading_source`, `odometry.source`, `odometry.pods`, a flag other than 0 or 1), or the first
    /// field out of range as [`validate`](Self::validate) finds it.
    pub fn decode(bytes: &[u8]) -> Result<Self, ConfigError> {
        if bytes.len() != ENCODED_LEN {
            return Err(ConfigError {
                field: "encoded.len",
                value: bytes.len() as f64,
                expected: "the length of this firmware's encoding (firmware::config::ENCODED_LEN)",
            });
        }
        let mut r = Reader { bytes, at: 0 };
        let format = r.u8();
        if format != FORMAT {
            return Err(ConfigError {
                field: "encoded.format",
                value: f64::from(format),
                expected: "the format version of this firmware's encoding",
            });
        }
        let geometry = read_geometry(&mut r)?;
        let drive = read_drive(&mut r)?;
        let limits = Limits {
            max_linear_speed: r.f32(),
            max_angular_speed: r.f32(),
            max_linear_accel: r.f32(),
            max_angular_accel: r.f32(),
            stop_linear_decel: r.f32(),
            stop_angular_decel: r.f32(),
            max_wheel_speed: r.f32(),
            max_current: r.f32(),
        };
        let gains = Gains {
            kp: r.f32(),
            ki: r.f32(),
            kv: r.f32(),
        };
        let timing = Timing {
            control_hz: r.u32(),
            odometry_hz: r.u32(),
            status_hz: r.u32(),
            setpoint_hz: r.u32(),
            command_timeout_ms: r.u32(),
            boot_timeout_ms: r.u32(),
            stale_periods: r.u32(),
        };
        let odometry = read_odometry(&mut r)?;
        let config = Self {
            geometry,
            drive,
            limits,
            gains,
            timing,
            odometry,
        };
        config.validate()?;
        Ok(config)
    }

    /// The configuration's id: the CRC-16/IBM-3740 of its [`encode`](Self::encode)d bytes.
    /// Sent in `HEARTBEAT.config_id`; equal ids mean equal configurations (up to the CRC's
    /// 1 in 65,536 chance) for one version of the encoding.
    #[must_use]
    pub fn id(&self) -> u16 {
        CRC.checksum(&self.encode())
    }
}

/// The geometry: its layout's fields, the effectiveness factors at the block's end.
fn read_geometry(r: &mut Reader<'_>) -> Result<Geometry, ConfigError> {
    let start = r.at;
    let layout = r.u8();
    let geometry_fields = |r: &mut Reader<'_>| {
        r.at = start + GEOMETRY_LEN - 3 * 4;
        [r.f32(), r.f32(), r.f32()]
    };
    let geometry = match layout {
        0 => {
            let [lx, ly, wheel_radius] = [r.f32(), r.f32(), r.f32()];
            let [forward, lateral, yaw] = geometry_fields(r);
            Geometry::Standard {
                lx,
                ly,
                wheel_radius,
                forward_effectiveness: forward,
                lateral_effectiveness: lateral,
                yaw_effectiveness: yaw,
            }
        }
        1 => {
            let wheels = [(); 4].map(|()| WheelConfig {
                x: r.f32(),
                y: r.f32(),
                axle_angle: r.f32(),
                roller_angle: r.f32(),
                radius: r.f32(),
            });
            let [forward, lateral, yaw] = geometry_fields(r);
            Geometry::General {
                wheels,
                forward_effectiveness: forward,
                lateral_effectiveness: lateral,
                yaw_effectiveness: yaw,
            }
        }
        other => return Err(tag("geometry.layout", other, "0 (standard) or 1 (general)")),
    };
    Ok(geometry)
}

/// The drive: protocol, ids, gear ratio and inversion, then the protocol's own fields.
fn read_drive(r: &mut Reader<'_>) -> Result<Drive, ConfigError> {
    let start = r.at;
    let protocol = r.u8();
    let model = r.u8();
    let ids = [r.u8(), r.u8(), r.u8(), r.u8()];
    let gear_ratio = r.f32();
    let inverted_bits = r.u8();
    if inverted_bits > 0x0F {
        return Err(tag("drive.inverted", inverted_bits, "4 bits, FL FR RL RR"));
    }
    let inverted = [0, 1, 2, 3].map(|i| inverted_bits & (1 << i) != 0);
    let drive = match protocol {
        0 => Drive::Dji {
            model: pick(
                "drive.model",
                model,
                [EscModel::C620, EscModel::C610],
                "0 (C620) or 1 (C610)",
            )?,
            esc_ids: ids,
            gear_ratio,
            inverted,
        },
        1 => Drive::Odrive {
            node_ids: ids,
            gear_ratio,
            inverted,
            vel_ramp: r.flag("drive.vel_ramp")?,
        },
        2 => {
            r.at += 1;
            Drive::Cia402(Cia402Drive {
                node_ids: ids,
                axes: [r.u8(), r.u8(), r.u8(), r.u8()],
                gear_ratio,
                inverted,
                target_rpm_per_unit: r.f32(),
                actual_rpm_per_unit: r.f32(),
                master_node: r.u8(),
                heartbeat_ms: r.u16(),
                heartbeat_timeout_ms: r.u16(),
            })
        }
        other => {
            return Err(tag(
                "drive.protocol",
                other,
                "0 (dji), 1 (odrive) or 2 (cia402)",
            ));
        }
    };
    r.at = start + DRIVE_LEN;
    Ok(drive)
}

/// The odometry's section: heading source, the gyro's settings, the source and the pods.
fn read_odometry(r: &mut Reader<'_>) -> Result<OdometryConfig, ConfigError> {
    let heading_source = pick(
        "odometry.heading_source",
        r.u8(),
        [HeadingMode::Wheels, HeadingMode::Gyro],
        "0 (wheels) or 1 (gyro)",
    )?;
    let gyro_timeout_ms = r.u32();
    let gyro_standstill_ms = r.u32();
    let gyro_bias_estimation = r.flag("odometry.gyro_bias_estimation")?;
    let source = pick(
        "odometry.source",
        r.u8(),
        [
            OdometryMode::Wheels,
            OdometryMode::Pods2Gyro,
            OdometryMode::Pods3,
        ],
        "0 (wheels), 1 (pods2_gyro) or 2 (pods3)",
    )?;
    let pod_timeout_ms = r.u32();
    let count = r.u8();
    let mut list = [PodConfig::default(); PODS_MAX];
    for pod in &mut list {
        *pod = PodConfig {
            x: r.f32(),
            y: r.f32(),
            direction_deg: r.f32(),
            radius: r.f32(),
            counts_per_turn: r.u32(),
        };
    }
    let pods = list
        .get(..usize::from(count))
        .and_then(Pods::new)
        .ok_or_else(|| tag("odometry.pods", count, "at most 3 pods"))?;
    let odometry = OdometryConfig {
        heading_source,
        gyro_timeout_ms,
        gyro_standstill_ms,
        gyro_bias_estimation,
        source,
        pod_timeout_ms,
        pods,
    };
    Ok(odometry)
}

fn bits(flags: [bool; 4]) -> u8 {
    flags
        .iter()
        .enumerate()
        .fold(0, |acc, (i, &f)| acc | (u8::from(f) << i))
}

fn tag(field: &'static str, value: u8, expected: &'static str) -> ConfigError {
    ConfigError {
        field,
        value: f64::from(value),
        expected,
    }
}

/// The value of a unit-like enum (or a flag) whose tag is `raw`: tags are the indices in
/// `values`, in the order [`Config::encode`] writes them; any other is an error naming `field`
/// and the `expected` tags.
fn pick<T: Copy, const N: usize>(
    field: &'static str,
    raw: u8,
    values: [T; N],
    expected: &'static str,
) -> Result<T, ConfigError> {
    values
        .get(usize::from(raw))
        .copied()
        .ok_or_else(|| tag(field, raw, expected))
}

impl Writer {
    /// The geometry: its layout's tag and values, then the three effectiveness factors at the
    /// end of the geometry's bytes, whichever the layout.
    fn geometry(&mut self, geometry: Geometry) {
        let w = self;
        let start = w.at;
        match geometry {
            Geometry::Standard {
                lx,
                ly,
                wheel_radius,
                ..
            } => {
                w.u8(0);
                w.f32s(&[lx, ly, wheel_radius]);
            }
            Geometry::General { wheels, .. } => {
                w.u8(1);
                for WheelConfig {
                    x,
                    y,
                    axle_angle,
                    roller_angle,
                    radius,
                } in wheels
                {
                    w.f32s(&[x, y, axle_angle, roller_angle, radius]);
                }
            }
        }
        w.at = start + GEOMETRY_LEN - 3 * 4;
        w.f32s(&geometry.effectiveness().as_array());
    }

    /// The drive: both protocols in one layout, then the CiA 402 drive's own fields.
    fn drive(&mut self, drive: Drive) {
        let w = self;
        // Both drives in one layout, as `decode` reads it: protocol, ESC model (0 for ODrive),
        // ids, gear ratio, inversion bits, then the ODrive's ramp flag (0 for DJI).
        let (protocol, model, ids, gear_ratio, inverted, vel_ramp) = match drive {
            Drive::Dji {
                model,
                esc_ids,
                gear_ratio,
                inverted,
            } => {
                let model = match model {
                    EscModel::C620 => 0,
                    EscModel::C610 => 1,
                };
                (0, model, esc_ids, gear_ratio, inverted, false)
            }
            Drive::Odrive {
                node_ids,
                gear_ratio,
                inverted,
                vel_ramp,
            } => (1, 0, node_ids, gear_ratio, inverted, vel_ramp),
            Drive::Cia402(Cia402Drive {
                node_ids,
                gear_ratio,
                inverted,
                ..
            }) => (2, 0, node_ids, gear_ratio, inverted, false),
        };
        w.u8(protocol);
        w.u8(model);
        w.bytes(&ids);
        w.f32s(&[gear_ratio]);
        w.u8(bits(inverted));
        w.u8(u8::from(vel_ramp));
        if let Drive::Cia402(Cia402Drive {
            axes,
            target_rpm_per_unit,
            actual_rpm_per_unit,
            master_node,
            heartbeat_ms,
            heartbeat_timeout_ms,
            ..
        }) = drive
        {
            w.bytes(&axes);
            w.f32s(&[target_rpm_per_unit, actual_rpm_per_unit]);
            w.u8(master_node);
            w.bytes(&heartbeat_ms.to_le_bytes());
            w.bytes(&heartbeat_timeout_ms.to_le_bytes());
        }
    }

    /// The limits, every field in declaration order.
    fn limits(&mut self, limits: Limits) {
        let w = self;
        let Limits {
            max_linear_speed,
            max_angular_speed,
            max_linear_accel,
            max_angular_accel,
            stop_linear_decel,
            stop_angular_decel,
            max_wheel_speed,
            max_current,
        } = limits;
        w.f32s(&[
            max_linear_speed,
            max_angular_speed,
            max_linear_accel,
            max_angular_accel,
            stop_linear_decel,
            stop_angular_decel,
            max_wheel_speed,
            max_current,
        ]);
    }

    /// The timing, every field in declaration order.
    fn timing(&mut self, timing: Timing) {
        let w = self;
        let Timing {
            control_hz,
            odometry_hz,
            status_hz,
            setpoint_hz,
            command_timeout_ms,
            boot_timeout_ms,
            stale_periods,
        } = timing;
        for v in [
            control_hz,
            odometry_hz,
            status_hz,
            setpoint_hz,
            command_timeout_ms,
            boot_timeout_ms,
            stale_periods,
        ] {
            w.bytes(&v.to_le_bytes());
        }
    }

    /// The odometry: heading source, gyro times and flag, source, pod timeout and count,
    /// then every pod slot (unused ones zeros).
    fn odometry(&mut self, odometry: OdometryConfig) {
        let w = self;
        let OdometryConfig {
            heading_source,
            gyro_timeout_ms,
            gyro_standstill_ms,
            gyro_bias_estimation,
            source,
            pod_timeout_ms,
            pods,
        } = odometry;
        w.u8(match heading_source {
            HeadingMode::Wheels => 0,
            HeadingMode::Gyro => 1,
        });
        w.bytes(&gyro_timeout_ms.to_le_bytes());
        w.bytes(&gyro_standstill_ms.to_le_bytes());
        w.u8(u8::from(gyro_bias_estimation));
        w.u8(match source {
            OdometryMode::Wheels => 0,
            OdometryMode::Pods2Gyro => 1,
            OdometryMode::Pods3 => 2,
        });
        w.bytes(&pod_timeout_ms.to_le_bytes());
        // At most PODS_MAX, so the count fits a byte.
        w.u8(pods.len() as u8);
        for i in 0..PODS_MAX {
            // Unused slots are zeros.
            let pod = pods.as_slice().get(i).copied().unwrap_or_default();
            w.f32s(&[pod.x, pod.y, pod.direction_deg, pod.radius]);
            w.bytes(&pod.counts_per_turn.to_le_bytes());
        }
    }
}

struct Writer {
    out: [u8; ENCODED_LEN],
    at: usize,
}

impl Writer {
    fn bytes(&mut self, b: &[u8]) {
        self.out[self.at..self.at + b.len()].copy_from_slice(b);
        self.at += b.len();
    }

    fn u8(&mut self, v: u8) {
        self.bytes(&[v]);
    }

    fn f32s(&mut self, values: &[f32]) {
        for v in values {
            self.bytes(&v.to_bits().to_le_bytes());
        }
    }
}

/// Reads fixed-width fields from a slice whose length was checked to be [`ENCODED_LEN`].
struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl Reader<'_> {
    fn take<const N: usize>(&mut self) -> [u8; N] {
        let mut out = [0; N];
        out.copy_from_slice(&self.bytes[self.at..self.at + N]);
        self.at += N;
        out
    }

    fn u8(&mut self) -> u8 {
        self.take::<1>()[0]
    }

    fn u16(&mut self) -> u16 {
        u16::from_le_bytes(self.take())
    }

    fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.take())
    }

    fn f32(&mut self) -> f32 {
        f32::from_bits(self.u32())
    }

    fn flag(&mut self, field: &'static str) -> Result<bool, ConfigError> {
        pick(field, self.u8(), [false, true], "0 or 1")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn examples_read_back_exactly() {
        for config in [
            Config::dji_m3508_example(),
            Config::odrive_example(),
            Config::cia402_example(),
        ] {
            let bytes = config.encode();
            assert_eq!(Config::decode(&bytes), Ok(config));
        }
    }

    #[test]
    fn ids_differ_between_the_examples_and_follow_every_field() {
        let dji = Config::dji_m3508_example();
        assert_ne!(dji.id(), Config::odrive_example().id());
        let mut other = dji;
        other.limits.max_current = 15.0;
        assert_ne!(dji.id(), other.id());
        let mut other = dji;
        other.odometry.gyro_bias_estimation = false;
        assert_ne!(dji.id(), other.id());
    }

    #[test]
    fn bad_bytes_name_what_is_wrong() {
        let bytes = Config::dji_m3508_example().encode();
        let e = Config::decode(&bytes[1..]).unwrap_err();
        assert_eq!(
            (e.field, e.value),
            ("encoded.len", (ENCODED_LEN - 1) as f64)
        );
        let mut b = bytes;
        b[0] = 9;
        assert_eq!(Config::decode(&b).unwrap_err().field, "encoded.format");
        let mut b = bytes;
        b[1] = 2;
        let e = Config::decode(&b).unwrap_err();
        assert_eq!((e.field, e.value), ("geometry.layout", 2.0));
        // The wheel radius (after the tag, lx and ly) set to zero: validation names it.
        let mut b = bytes;
        b[2 + 8..2 + 12].copy_from_slice(&0f32.to_bits().to_le_bytes());
        let e = Config::decode(&b).unwrap_err();
        assert_eq!((e.field, e.value), ("geometry.wheel_radius", 0.0));
    }
}
