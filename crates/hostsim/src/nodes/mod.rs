//! The simulated nodes (drives on the plant, IMU, tracking pods, host) with their parameters.
//!
//! The drives on the plant's motors and chassis ([`drives`], [`plant`]), an IMU ([`imu`]),
//! tracking pods ([`pods`]) and the host that commands the robot ([`host`]); each owns its
//! parameters.
//!
//! The engine sees the drives and the sensor nodes on them as one [`SimPlant`]; the sensor
//! nodes wrap it ([`sensor::WithNode`]). Nothing here knows a scenario: the lockstep engine builds
//! the nodes from one.

pub mod drives;
pub mod host;
pub mod imu;
pub mod plant;
pub mod pods;
pub mod sensor;

use firmware::CanFrame;

use crate::bus::Node;

/// The plant as the runner sees it: drives that take command frames and produce feedback
/// frames, and a body with a true pose.
pub trait SimPlant {
    /// A frame from the bus (the drives pick out their commands; anything else is ignored).
    fn on_frame(&mut self, t_us: u64, frame: &CanFrame);
    /// Feedback frames the drives have sent up to `until_ns`, each with its send time (ns),
    /// in time order; called once per tick.
    fn feedback(&mut self, until_ns: u64, out: &mut Vec<(u64, CanFrame)>);
    /// The frames a sensor node on the plant has sent as bus node `node` up to `until_ns`
    /// (`IMU_YAW_RATE` as [`Node::Imu`], `POD_COUNTS` as [`Node::Pods`]), as
    /// [`Self::feedback`]. None by default: see [`crate::nodes::sensor::WithNode`], which the runner
    /// puts around the plant for the scenario's IMU and pods.
    fn node_frames(&mut self, _node: Node, _until_ns: u64, _out: &mut Vec<(u64, CanFrame)>) {}
    /// Advances the physics by `dt` seconds.
    fn advance(&mut self, dt: f64);
    /// Advances the physics by `dt_ns` nanoseconds ([`Self::advance`] by default).
    fn advance_ns(&mut self, dt_ns: u64) {
        self.advance(dt_ns as f64 * 1e-9);
    }
    /// When the drives next send feedback, ns of the plant's time (`u64::MAX`: not known,
    /// the runner then takes the period's end). The runner lets the bus run no further
    /// before it has those frames, which may win arbitration over the ones waiting.
    fn next_feedback_ns(&self) -> u64 {
        u64::MAX
    }
    /// Ground-truth pose `[x, y, heading]` in the world frame (m, m, rad).
    fn truth(&self) -> [f64; 3];
    /// Ground-truth body velocity `[vx, vy, wz]`.
    fn truth_velocity(&self) -> [f64; 3];
    /// Ground-truth body velocity integrated over time since the plant was built,
    /// `[∫vx dt, ∫vy dt, ∫wz dt]` (m, m, rad), in the plant's own integration steps
    /// ([`crate::nodes::plant::Chassis::body_travel`]); `None` (the default) for a plant that does
    /// not keep it: [`crate::nodes::pods::WithPods`] then integrates [`Self::truth_velocity`] itself.
    fn truth_travel(&self) -> Option<[f64; 3]> {
        None
    }
    /// Plant faults from `at_ns` on (at once if the plant is there already): `stuck[i]`
    /// freezes wheel i's encoder, `offline[i]` silences its drive. The motion before `at_ns`
    /// does not feel them; the feedback stamped `at_ns` does.
    fn set_faults(&mut self, at_ns: u64, stuck: [bool; 4], offline: [bool; 4]);
    /// CiA 402 drives' faults in force from `at_ns` on, by wheel (the wheel's node): a plant
    /// without CANopen nodes has none (such a scenario is refused before the run).
    fn set_drive_faults(&mut self, _at_ns: u64, _faults: [DriveFaults; 4]) {}
}

/// The CiA 402 faults in force on one wheel's drive (its node), from the scenario's
/// `drive_*`, `enable_refused` and `sdo_abort` faults.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct DriveFaults {
    /// `drive_silent`: no heartbeat.
    pub silent: bool,
    /// `drive_reboot`: its rising edge reboots the node.
    pub reboot: bool,
    /// `drive_fault`: its rising edge faults the node.
    pub fault: bool,
    /// `enable_refused`.
    pub refuses_enable: bool,
    /// `sdo_abort`: the write of 0x6060 is aborted.
    pub sdo_abort: bool,
    /// `drive_bus_off`: its CAN controller is bus-off (it comes back when this ends).
    pub bus_off: bool,
}

/// A plant for the unit tests of what wraps or drives one: it moves at a constant body
/// velocity and only counts time.
#[cfg(test)]
pub(crate) mod test_plant {
    use firmware::CanFrame;

    use super::SimPlant;

    /// A plant moving at the body velocity `v`, whose travel is exactly `v · t` (or, with
    /// `integrates = false`, that leaves the integral to the wrapper); it records every
    /// advance and every frame it is given, with the plant time then.
    pub(crate) struct Moving {
        pub now_ns: u64,
        pub v: [f64; 3],
        pub integrates: bool,
        pub advances: Vec<u64>,
        pub frames: Vec<(u64, CanFrame)>,
    }

    impl Moving {
        pub fn new(v: [f64; 3]) -> Self {
            Self {
                now_ns: 0,
                v,
                integrates: true,
                advances: Vec::new(),
                frames: Vec::new(),
            }
        }
    }

    impl SimPlant for Moving {
        fn on_frame(&mut self, _: u64, frame: &CanFrame) {
            self.frames.push((self.now_ns, *frame));
        }
        fn feedback(&mut self, _: u64, _: &mut Vec<(u64, CanFrame)>) {}
        fn advance(&mut self, dt: f64) {
            self.advance_ns((dt * 1e9).round() as u64);
        }
        fn advance_ns(&mut self, dt_ns: u64) {
            self.advances.push(dt_ns);
            self.now_ns += dt_ns;
        }
        fn truth(&self) -> [f64; 3] {
            [0.0; 3]
        }
        fn truth_velocity(&self) -> [f64; 3] {
            self.v
        }
        fn truth_travel(&self) -> Option<[f64; 3]> {
            let t = self.now_ns as f64 * 1e-9;
            self.integrates.then(|| self.v.map(|v| v * t))
        }
        fn set_faults(&mut self, _: u64, _: [bool; 4], _: [bool; 4]) {}
    }
}
