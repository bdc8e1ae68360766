//! `[[faults]]`: what goes wrong on the bus, in a motor or at the host, and when.

use serde::Deserialize;

use super::{Invalid, given, secs_to_us};
use crate::bus::{Fault, FaultKind, Node};
use crate::nodes::host::{HostFault, HostFaultKind};
use crate::scenario::ScenarioError;

/// A fault on the timeline, as written in a scenario.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FaultSpec {
    /// `drop`, `burst`, `delay`, `corrupt`, `stuck_encoder`, `motor_offline`,
    /// `non_finite_twist`, `repeated_twist`, `pods_silent`, `runner_restart`, or for CiA 402
    /// drives `drive_silent`, `drive_reboot`, `drive_fault`, `enable_refused`, `sdo_abort`,
    /// `drive_bus_off`.
    pub kind: FaultName,
    /// Start, s.
    pub from_s: f64,
    /// End, s (exclusive).
    pub until_s: f64,
    /// Probability for `drop` and `corrupt`.
    #[serde(default)]
    pub rate: Option<f64>,
    /// Extra latency for `delay`, ms.
    #[serde(default)]
    pub delay_ms: Option<f64>,
    /// Sender the bus fault applies to (all if absent).
    #[serde(default)]
    pub sender: Option<SenderName>,
    /// Wheel (0 FL, 1 FR, 2 RL, 3 RR) for `stuck_encoder` and `motor_offline`, and the wheel
    /// whose drive (CANopen node) the CiA 402 faults act on.
    #[serde(default)]
    pub wheel: Option<usize>,
}

/// Fault kinds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FaultName {
    /// Random frame loss.
    Drop,
    /// Total frame loss.
    Burst,
    /// Extra delivery latency.
    Delay,
    /// A flipped data byte.
    Corrupt,
    /// A wheel's encoder stops changing while the wheel turns.
    StuckEncoder,
    /// A drive is off: it sends nothing and drives nothing (the wheel coasts).
    MotorOffline,
    /// Besides its own stream, the host sends `TWIST_CMD` frames whose values are not finite
    /// numbers (see [`crate::nodes::host::non_finite_twist_frames`]), once per command period.
    NonFiniteTwist,
    /// CiA 402: the wheel's drive sends no heartbeat (its PDOs still flow).
    DriveSilent,
    /// CiA 402: the wheel's drive reboots at `from_s` (once; boot-up 2 ms later, its
    /// configuration lost).
    DriveReboot,
    /// CiA 402: the wheel's drive faults at `from_s` (statusword fault, EMCY 0x2310), until
    /// a fault reset.
    DriveFault,
    /// CiA 402: the wheel's drive does not reach operation enabled (it stays switched on).
    EnableRefused,
    /// CiA 402: the wheel's drive aborts the master's write of the mode (0x6060) with
    /// 0x06090030 (invalid value).
    SdoAbort,
    /// CiA 402: the wheel's drive is bus-off from `from_s` (it sends and takes nothing; its
    /// axes lose torque) and back at `until_s`, pre-operational, with EMCY 0x8140.
    DriveBusOff,
    /// The host's stream stops incrementing `TWIST_CMD.seq`: each frame it sends is its last
    /// one before the fault, unchanged (a stuck host, USB adapter or gateway repeating one
    /// frame), whatever its setpoint; afterwards it sends fresh frames again.
    RepeatedTwist,
    /// The tracking-pod node (`[pods]`) sends nothing: its pods roll and count on, its `seq`
    /// counts on, its frames stay off the bus (a disconnected node; `crate::nodes::pods`).
    PodsSilent,
    /// The runner is killed at `from_s` (the firmware core sends and takes nothing) and
    /// started again at `until_s`: a fresh core, as a restarted runner or a rebooted board.
    RunnerRestart,
}

impl FaultName {
    /// Whether the fault acts on a CiA 402 drive (a CANopen node), and only there.
    #[must_use]
    pub const fn cia402_only(self) -> bool {
        matches!(
            self,
            Self::DriveSilent
                | Self::DriveReboot
                | Self::DriveFault
                | Self::EnableRefused
                | Self::SdoAbort
                | Self::DriveBusOff
        )
    }

    /// The name a scenario file uses (`stuck_encoder`).
    #[must_use]
    pub const fn as_str(self) -> &'static str {
        match self {
            Self::Drop => "drop",
            Self::Burst => "burst",
            Self::Delay => "delay",
            Self::Corrupt => "corrupt",
            Self::StuckEncoder => "stuck_encoder",
            Self::MotorOffline => "motor_offline",
            Self::NonFiniteTwist => "non_finite_twist",
            Self::RepeatedTwist => "repeated_twist",
            Self::DriveSilent => "drive_silent",
            Self::DriveReboot => "drive_reboot",
            Self::DriveFault => "drive_fault",
            Self::EnableRefused => "enable_refused",
            Self::SdoAbort => "sdo_abort",
            Self::DriveBusOff => "drive_bus_off",
            Self::PodsSilent => "pods_silent",
            Self::RunnerRestart => "runner_restart",
        }
    }
}

/// Bus nodes as named in scenarios.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SenderName {
    /// The firmware core.
    Controller,
    /// The motor drives.
    Drives,
    /// The commanding host.
    Host,
    /// The IMU node (`[imu]`).
    Imu,
    /// The tracking-pod node (`[pods]`).
    Pods,
}

impl From<SenderName> for Node {
    fn from(s: SenderName) -> Self {
        match s {
            SenderName::Controller => Self::Controller,
            SenderName::Drives => Self::Drives,
            SenderName::Host => Self::Host,
            SenderName::Imu => Self::Imu,
            SenderName::Pods => Self::Pods,
        }
    }
}

/// A plant-side fault: which wheel, when.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WheelFault {
    /// Stuck encoder, offline, or a CiA 402 drive's fault.
    pub kind: FaultName,
    /// Wheel index.
    pub wheel: usize,
    /// Start, µs.
    pub from_us: u64,
    /// End, µs.
    pub until_us: u64,
}

impl WheelFault {
    /// Whether the fault is active at `t_us`.
    #[must_use]
    pub const fn active(&self, t_us: u64) -> bool {
        self.from_us <= t_us && t_us < self.until_us
    }
}

/// A fault of a node other than the drives and the host: a sensor node on the plant
/// (`pods_silent`) or the firmware's own (`runner_restart`); what, when.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NodeFault {
    /// What it does (`PodsSilent`, `RunnerRestart`).
    pub kind: FaultName,
    /// Start, µs.
    pub from_us: u64,
    /// End, µs.
    pub until_us: u64,
}

impl NodeFault {
    /// Whether the fault is active at `t_us`.
    #[must_use]
    pub const fn active(&self, t_us: u64) -> bool {
        self.from_us <= t_us && t_us < self.until_us
    }
}

/// A file's faults by where they act: on the bus, in a motor, at the host, at a sensor node.
pub(super) type Faults = (Vec<Fault>, Vec<WheelFault>, Vec<HostFault>, Vec<NodeFault>);

/// The faults of a file whose run lasts `duration_s`, checked and sorted by where they act.
pub(super) fn build(
    faults: &[FaultSpec],
    duration_s: f64,
    invalid: &Invalid<'_>,
) -> Result<Faults, ScenarioError> {
    let mut bus_faults = Vec::new();
    let mut wheel_faults = Vec::new();
    let mut host_faults = Vec::new();
    let mut node_faults = Vec::new();
    for (i, f) in faults.iter().enumerate() {
        check_window(i, f, duration_s, invalid)?;
        check_fields(i, f, invalid)?;
        let (from_us, until_us) = (secs_to_us(f.from_s), secs_to_us(f.until_s));
        let kind = bus_kind(i, f, invalid)?;
        match f.kind {
            FaultName::PodsSilent | FaultName::RunnerRestart => node_faults.push(NodeFault {
                kind: f.kind,
                from_us,
                until_us,
            }),
            FaultName::NonFiniteTwist | FaultName::RepeatedTwist => host_faults.push(HostFault {
                kind: if f.kind == FaultName::NonFiniteTwist {
                    HostFaultKind::NonFiniteTwist
                } else {
                    HostFaultKind::RepeatedTwist
                },
                from_us,
                until_us,
            }),
            _ => match kind {
                Some(kind) => bus_faults.push(Fault {
                    kind,
                    from_us,
                    until_us,
                    sender: f.sender.map(Node::from),
                }),
                None => match f.wheel {
                    Some(wheel) if wheel < 4 => wheel_faults.push(WheelFault {
                        kind: f.kind,
                        wheel,
                        from_us,
                        until_us,
                    }),
                    other => {
                        return Err(invalid.at(
                            &format!("faults[{i}].wheel"),
                            given(other),
                            "a wheel index 0..=3 (FL, FR, RL, RR)",
                        ));
                    }
                },
            },
        }
    }
    Ok((bus_faults, wheel_faults, host_faults, node_faults))
}

/// Fault `i`'s window: `0 <= from_s < until_s`, starting before the run ends.
fn check_window(
    i: usize,
    f: &FaultSpec,
    duration_s: f64,
    invalid: &Invalid<'_>,
) -> Result<(), ScenarioError> {
    if !(f.from_s.is_finite() && f.until_s.is_finite() && 0.0 <= f.from_s && f.from_s < f.until_s) {
        return Err(invalid.at(
            &format!("faults[{i}].from_s..until_s"),
            format!("{}..{}", f.from_s, f.until_s),
            "0 <= from_s < until_s",
        ));
    }
    if f.from_s >= duration_s {
        return Err(invalid.at(
            &format!("faults[{i}].from_s"),
            f.from_s.to_string(),
            "a time before duration_s (a later fault would never happen)",
        ));
    }
    Ok(())
}

/// Fault `i` sets no field its kind does not use.
fn check_fields(i: usize, f: &FaultSpec, invalid: &Invalid<'_>) -> Result<(), ScenarioError> {
    // A field another kind uses is a mistake (a `wheel` on a `drop` fault would
    // otherwise drop every frame, not one wheel's).
    let (rate_used, delay_used, sender_used, wheel_used, uses) = match f.kind {
        FaultName::Drop | FaultName::Corrupt => (true, false, true, false, "rate, sender"),
        FaultName::Burst => (false, false, true, false, "sender"),
        FaultName::Delay => (false, true, true, false, "delay_ms, sender"),
        FaultName::StuckEncoder
        | FaultName::MotorOffline
        | FaultName::DriveSilent
        | FaultName::DriveReboot
        | FaultName::DriveFault
        | FaultName::EnableRefused
        | FaultName::SdoAbort
        | FaultName::DriveBusOff => (false, false, false, true, "wheel"),
        FaultName::NonFiniteTwist
        | FaultName::RepeatedTwist
        | FaultName::PodsSilent
        | FaultName::RunnerRestart => (false, false, false, false, "no other field"),
    };
    for (field, given, used) in [
        ("rate", f.rate.map(|x| x.to_string()), rate_used),
        ("delay_ms", f.delay_ms.map(|x| x.to_string()), delay_used),
        ("sender", f.sender.map(|x| format!("{x:?}")), sender_used),
        ("wheel", f.wheel.map(|x| x.to_string()), wheel_used),
    ] {
        if let (Some(value), false) = (given, used) {
            return Err(ScenarioError::UnusedField {
                path: invalid.path.to_path_buf(),
                field: format!("faults[{i}].{field}"),
                value,
                kind: f.kind,
                uses,
            });
        }
    }
    Ok(())
}

/// What fault `i` does to the frames on the bus, with its rate or delay checked; `None` for
/// a fault that acts elsewhere (a motor, the host, a node).
fn bus_kind(
    i: usize,
    f: &FaultSpec,
    invalid: &Invalid<'_>,
) -> Result<Option<FaultKind>, ScenarioError> {
    let rate = |f: &FaultSpec| match f.rate {
        Some(r) if (0.0..=1.0).contains(&r) => Ok(r),
        other => Err(invalid.at(
            &format!("faults[{i}].rate"),
            given(other),
            "a probability in 0..=1",
        )),
    };
    Ok(match f.kind {
        FaultName::Drop => Some(FaultKind::Drop { rate: rate(f)? }),
        FaultName::Corrupt => Some(FaultKind::Corrupt { rate: rate(f)? }),
        FaultName::Burst => Some(FaultKind::Burst),
        FaultName::Delay => match f.delay_ms {
            Some(ms) if ms.is_finite() && (0.0..=10_000.0).contains(&ms) => {
                Some(FaultKind::Delay {
                    micros: (ms * 1000.0).round() as u64,
                })
            }
            other => {
                return Err(invalid.at(
                    &format!("faults[{i}].delay_ms"),
                    given(other),
                    "a delay in 0..=10000 ms",
                ));
            }
        },
        FaultName::StuckEncoder
        | FaultName::MotorOffline
        | FaultName::NonFiniteTwist
        | FaultName::RepeatedTwist
        | FaultName::DriveSilent
        | FaultName::DriveReboot
        | FaultName::DriveFault
        | FaultName::EnableRefused
        | FaultName::SdoAbort
        | FaultName::DriveBusOff
        | FaultName::PodsSilent
        | FaultName::RunnerRestart => None,
    })
}
