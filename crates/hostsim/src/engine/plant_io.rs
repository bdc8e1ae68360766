//! The plant's side of a tick: the drives', IMU's and pods' frames onto the bus, the
//! scenario's wheel faults onto the plant, and each transmission into the log.

use firmware::CanFrame;

use super::LogOptions;
use crate::bus::{Fate, Node, Transmission};
use crate::nodes::{DriveFaults, SimPlant};
use crate::scenario::{FaultName, Scenario};
use drivelog::{Direction, LogError, McapLog};

/// Logs one transmission: on `/can/rx` if the firmware received it, on `/can/tx` if it sent
/// it (dropped or not), and on `/can/faults` if the fault injector dropped or corrupted it.
///
/// # Errors
/// The log could not be written.
pub fn log_transmission(
    l: &mut McapLog,
    tx: &Transmission,
    options: LogOptions,
) -> Result<(), LogError> {
    if options.faults && tx.fate != Fate::Delivered {
        l.bus_fault(
            tx.end_ns,
            tx.from.name(),
            tx.fate.name(),
            &tx.sent,
            &tx.frame,
        )?;
    }
    if tx.from == Node::Controller {
        l.frame(
            Direction::Tx,
            tx.delivered_ns,
            tx.queued_ns,
            tx.end_ns,
            &tx.sent,
        )
    } else if tx.fate != Fate::Dropped {
        l.frame(
            Direction::Rx,
            tx.delivered_ns,
            tx.queued_ns,
            tx.end_ns,
            &tx.frame,
        )
    } else {
        Ok(())
    }
}

/// Hands `send` the drives' feedback frames, the IMU's and the pod node's frames sent up to
/// `until_ns`, each with its send time and its node (the drives', then the IMU's, then the
/// pods', each in time order); `feedback` is scratch space.
pub fn queue_feedback<P: SimPlant>(
    plant: &mut P,
    feedback: &mut Vec<(u64, CanFrame)>,
    until_ns: u64,
    mut send: impl FnMut(u64, Node, CanFrame),
) {
    for node in [Node::Drives, Node::Imu, Node::Pods] {
        feedback.clear();
        match node {
            Node::Drives => plant.feedback(until_ns, feedback),
            _ => plant.node_frames(node, until_ns, feedback),
        }
        for &(at_ns, f) in feedback.iter() {
            send(at_ns, node, f);
        }
    }
}

/// Sets the scenario's wheel faults in force at `t_us` on the plant, from `t_us` on.
pub fn set_wheel_faults<P: SimPlant>(s: &Scenario, plant: &mut P, t_us: u64) {
    let stuck = wheel_flags(s, t_us, FaultName::StuckEncoder);
    let offline = wheel_flags(s, t_us, FaultName::MotorOffline);
    plant.set_faults(t_us * 1000, stuck, offline);
    if s.wheel_faults.iter().any(|f| f.kind.cia402_only()) {
        let [silent, reboot, fault, refuses_enable, sdo_abort, bus_off] = [
            FaultName::DriveSilent,
            FaultName::DriveReboot,
            FaultName::DriveFault,
            FaultName::EnableRefused,
            FaultName::SdoAbort,
            FaultName::DriveBusOff,
        ]
        .map(|kind| wheel_flags(s, t_us, kind));
        let faults = core::array::from_fn(|i| DriveFaults {
            silent: silent[i],
            reboot: reboot[i],
            fault: fault[i],
            refuses_enable: refuses_enable[i],
            sdo_abort: sdo_abort[i],
            bus_off: bus_off[i],
        });
        plant.set_drive_faults(t_us * 1000, faults);
    }
}

fn wheel_flags(s: &Scenario, t_us: u64, kind: FaultName) -> [bool; 4] {
    let mut flags = [false; 4];
    for f in &s.wheel_faults {
        if f.kind == kind && f.active(t_us) {
            flags[f.wheel] = true;
        }
    }
    flags
}
