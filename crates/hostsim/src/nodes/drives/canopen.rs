//! Simulated CANopen CiA 402 drives on the bus: the firmware crate's drive double
//! ([`firmware::protocol::canopen::drive`]: NMT, the object dictionary as an SDO server, the
//! PDOs as mapped, heartbeats, EMCY, the 402 state machine) on the plant's axes
//! ([`Cia402Axis`]), with the simulator's timing and the scenario's faults.
//!
//! This adapter holds what is the plant's: a node's command powers its wheels' axes (target
//! 0x60FF times `drive.target_rpm_per_unit`), its TPDOs report their true speed in
//! `drive.actual_rpm_per_unit` (rounded), and a quick stop or a slow down ends once every
//! axis turns slower than [`QUICK_STOP_REST_RAD_S`]. The model is specified in
//! `docs/simulator.md`, section "CiA 402 drive".

use firmware::CanFrame;
use firmware::protocol::canopen::DriveState402;
use firmware::protocol::canopen::drive::{self, Axes, AxisCommand, Drives402, Options, Timing};

pub use firmware::protocol::canopen::drive::{
    DEVICE_TYPE, EMCY_BUS_OFF_RECOVERED, EMCY_DRIVE_FAULT, EMCY_ERROR_RESET, EMCY_HEARTBEAT,
    Faults as NodeFaults, abort, error_register,
};

use crate::nodes::DriveFaults;
use crate::nodes::plant::{Cia402Axis, Plant, Wheel};

/// Time from a request (SDO, SYNC, NMT) to the node's answer, ns.
pub const ANSWER_NS: u64 = 200_000;
/// Time from an NMT reset to the boot-up, ns.
pub const BOOT_NS: u64 = 2_000_000;
/// A quick stop ends once every axis of the node turns slower than this, rad/s (motor side).
pub const QUICK_STOP_REST_RAD_S: f64 = 0.1;

/// The simulator's timing: answers 200 µs after the request, boot-ups 2 ms after a reset,
/// heartbeats a period after their start (CANopenNode).
pub const TIMING: Timing = Timing {
    answer_ns: ANSWER_NS,
    boot_ns: BOOT_NS,
    heartbeat_aligned: false,
};

/// The plant's axes as the nodes see them, by wheel index.
struct PlantAxes<'a> {
    plant: &'a mut Plant<Cia402Axis>,
    /// Motor rev/s per raw unit of 0x60FF, motor rpm per raw unit of 0x606C.
    target_rev_s_per_unit: f64,
    actual_rpm_per_unit: f64,
}

impl Axes for PlantAxes<'_> {
    fn command(&mut self, wheel: usize, command: AxisCommand) {
        let axis = self.plant.drive_mut(Wheel::ALL[wheel]);
        match command {
            AxisCommand::Velocity(target) => {
                axis.set_powered(true);
                axis.set_target(f64::from(target) * self.target_rev_s_per_unit);
            }
            AxisCommand::SlowDown | AxisCommand::QuickStop => {
                axis.set_powered(true);
                axis.set_target(0.0);
            }
            AxisCommand::Off => {
                axis.set_target(0.0);
                axis.set_powered(false);
            }
        }
    }

    fn velocity(&self, wheel: usize) -> i32 {
        let rpm = self.plant.shaft(Wheel::ALL[wheel]).speed * 60.0 / core::f64::consts::TAU;
        // Saturating float-to-int: a wheel far beyond any drive's range.
        #[allow(clippy::cast_possible_truncation)]
        let raw = (rpm / self.actual_rpm_per_unit).round() as i32;
        raw
    }

    fn at_rest(&self, wheel: usize) -> bool {
        self.plant.shaft(Wheel::ALL[wheel]).speed.abs() < QUICK_STOP_REST_RAD_S
    }
}

/// The CiA 402 nodes of a configuration.
#[derive(Debug, Clone)]
pub struct CanopenDrives {
    drives: Drives402,
    /// Motor rev/s per raw unit of 0x60FF, motor rpm per raw unit of 0x606C.
    target_rev_s_per_unit: f64,
    actual_rpm_per_unit: f64,
    /// The scenario's faults last set on each node (for their rising edges).
    scenario: Vec<DriveFaults>,
}

impl CanopenDrives {
    /// The nodes of a `Drive::Cia402` configuration, booting at time 0.
    #[must_use]
    pub fn new(config: &firmware::Config) -> Self {
        let (target_rpm, actual_rpm) = match config.drive {
            firmware::config::Drive::Cia402(d) => (d.target_rpm_per_unit, d.actual_rpm_per_unit),
            _ => (0.0, 1.0),
        };
        let drives = Drives402::new(config, TIMING, Options::default());
        Self {
            scenario: vec![DriveFaults::default(); drives.nodes().len()],
            drives,
            target_rev_s_per_unit: f64::from(target_rpm) / 60.0,
            actual_rpm_per_unit: f64::from(actual_rpm),
        }
    }

    /// The nodes (the double's state: NMT, dictionary, 402 state).
    #[must_use]
    pub const fn drives(&self) -> &Drives402 {
        &self.drives
    }

    fn split<'a>(
        &'a mut self,
        plant: &'a mut Plant<Cia402Axis>,
    ) -> (&'a mut Drives402, PlantAxes<'a>) {
        let axes = PlantAxes {
            plant,
            target_rev_s_per_unit: self.target_rev_s_per_unit,
            actual_rpm_per_unit: self.actual_rpm_per_unit,
        };
        (&mut self.drives, axes)
    }

    /// The faults of node `id` from now on.
    pub fn set_faults(&mut self, id: u8, faults: NodeFaults) {
        if let Some(n) = self.drives.node_mut(id) {
            n.set_faults(faults);
        }
    }

    /// Node `id` reboots at `t_ns`: its axes lose power and it boots (boot-up, defaults).
    pub fn reboot(&mut self, id: u8, t_ns: u64, plant: &mut Plant<Cia402Axis>) {
        let (drives, mut axes) = self.split(plant);
        if let Some(n) = drives.node_mut(id) {
            n.reboot(t_ns, &mut axes);
        }
    }

    /// Node `id` faults at `t_ns` with EMCY `code` (a drive error: overcurrent 0x2310, ...).
    pub fn fault(&mut self, id: u8, t_ns: u64, code: u16, plant: &mut Plant<Cia402Axis>) {
        let (drives, mut axes) = self.split(plant);
        if let Some(n) = drives.node_mut(id) {
            n.fault(t_ns, code, &mut axes);
        }
    }

    /// The scenario's faults of each wheel's node from `at_ns` on: heartbeat, enable and SDO
    /// faults as they say; a rising `reboot` reboots the node, a rising `fault` faults it
    /// (EMCY 0x2310); `bus_off` holds it off the bus, and it comes back pre-operational.
    pub fn set_wheel_faults(
        &mut self,
        at_ns: u64,
        faults: [DriveFaults; 4],
        plant: &mut Plant<Cia402Axis>,
    ) {
        let scenario = self.scenario.clone();
        let (drives, mut axes) = self.split(plant);
        let mut now = Vec::with_capacity(scenario.len());
        for (n, before) in drives.nodes_mut().iter_mut().zip(scenario) {
            let mut f = DriveFaults::default();
            for (w, wf) in (0u8..).zip(faults) {
                if n.wheels().contains(&Some(w)) {
                    f.silent |= wf.silent;
                    f.reboot |= wf.reboot;
                    f.fault |= wf.fault;
                    f.refuses_enable |= wf.refuses_enable;
                    f.sdo_abort |= wf.sdo_abort;
                    f.bus_off |= wf.bus_off;
                }
            }
            now.push(f);
            n.set_faults(NodeFaults {
                heartbeat_silent: f.silent,
                refuses_enable: f.refuses_enable,
                abort: f.sdo_abort.then_some(((0x6060, 0), abort::INVALID_VALUE)),
            });
            if f.reboot && !before.reboot {
                n.reboot(at_ns, &mut axes);
            }
            if f.fault && !before.fault {
                n.fault(at_ns, EMCY_DRIVE_FAULT, &mut axes);
            }
            if f.bus_off && !before.bus_off {
                n.go_bus_off(&mut axes);
            }
            if !f.bus_off && before.bus_off {
                n.recover_bus_off(at_ns);
            }
        }
        self.scenario = now;
    }

    /// EMCY frames sent so far.
    #[must_use]
    pub fn emcy_sent(&self) -> u32 {
        self.drives.emcy_sent()
    }

    /// The statusword of node `id`.
    #[must_use]
    pub fn statusword(&self, id: u8) -> Option<u16> {
        self.drives.node(id).map(drive::Drive402::statusword)
    }

    /// The 402 state of node `id`.
    #[must_use]
    pub fn state(&self, id: u8) -> Option<DriveState402> {
        self.drives.node(id).map(drive::Drive402::state)
    }

    /// A frame on the bus at `t_ns`.
    pub fn on_frame(&mut self, t_ns: u64, frame: &CanFrame, plant: &mut Plant<Cia402Axis>) {
        let (drives, mut axes) = self.split(plant);
        drives.on_frame(t_ns, frame, &mut axes);
    }

    /// The frames the nodes send up to `until_ns`: answers, TPDOs, heartbeats, EMCY; and the
    /// master's heartbeat watched.
    pub fn feedback(
        &mut self,
        until_ns: u64,
        plant: &mut Plant<Cia402Axis>,
        out: &mut Vec<(u64, CanFrame)>,
    ) {
        let (drives, mut axes) = self.split(plant);
        drives.feedback(until_ns, &mut axes, |t, f| out.push((t, f)));
    }

    /// When the next frame is due, ns.
    #[must_use]
    pub fn next_feedback_ns(&self) -> u64 {
        self.drives.next_due_ns()
    }
}

#[cfg(test)]
mod tests {
    //! The plant coupling: what a node's state does to its axes, and what the axes' speeds
    //! do to the node. The node's own logic is tested with the double, in the firmware
    //! crate (`protocol::canopen::drive`).

    use firmware::protocol::canopen::{self, Message, NmtCommand, SdoRequest};

    use super::*;

    const MS: u64 = 1_000_000;

    /// The example's nodes 1 and 2 (dual-axis) on their plant, booted.
    struct Bench {
        drives: CanopenDrives,
        plant: Plant<Cia402Axis>,
        sent: Vec<(u64, CanFrame)>,
    }

    impl Bench {
        fn new() -> Self {
            let config = firmware::Config::cia402_example();
            Self {
                drives: CanopenDrives::new(&config),
                plant: Plant::cia402_from_config(&config).unwrap(),
                sent: Vec::new(),
            }
        }

        fn put(&mut self, t_ns: u64, msg: Message) {
            self.drives.feedback(t_ns, &mut self.plant, &mut self.sent);
            self.drives
                .on_frame(t_ns, &msg.to_can_frame(), &mut self.plant);
        }

        fn download(&mut self, t_ns: u64, index: u16, sub: u8, value: u32) {
            let node = canopen::NodeId::new(1).unwrap();
            let request = SdoRequest::Download {
                index,
                sub,
                value,
                size: 4,
            };
            self.put(t_ns, Message::SdoRequest { node, request });
        }

        /// Node 1 configured as the master does it ([`drive::NODE1_PDO_SETUP`]), started,
        /// operation enabled.
        fn enabled(&mut self) {
            for (k, (index, sub, value)) in drive::NODE1_PDO_SETUP.into_iter().enumerate() {
                self.download((3 + k as u64) * MS, index, sub, value);
            }
            let node = canopen::NodeId::new(1);
            self.put(
                20 * MS,
                Message::Nmt {
                    command: NmtCommand::Start,
                    node,
                },
            );
            for cw in [0x06, 0x07, 0x0F] {
                self.rpdo(21 * MS, cw, 0);
            }
            assert_eq!(self.drives.state(1), Some(DriveState402::OperationEnabled));
        }

        fn rpdo(&mut self, t_ns: u64, cw: u16, target: i32) {
            let node = canopen::NodeId::new(1).unwrap();
            let msg = Message::Rpdo1 {
                node,
                controlword: cw,
                target,
            };
            self.put(t_ns, msg);
        }

        /// Runs the plant for `ms` milliseconds.
        fn run(&mut self, ms: u32) {
            for _ in 0..ms {
                self.plant.step(1e-3).unwrap();
            }
        }

        /// SYNC at `t_ns`; node 1's TPDO1 answer (statusword, velocity).
        fn sync(&mut self, t_ns: u64) -> (u16, i32) {
            self.put(t_ns, Message::Sync { counter: None });
            self.drives
                .feedback(t_ns + ANSWER_NS, &mut self.plant, &mut self.sent);
            self.sent
                .iter()
                .rev()
                .find_map(|(_, f)| match canopen::decode(f) {
                    Ok(Message::Tpdo1 {
                        statusword,
                        velocity,
                        ..
                    }) => Some((statusword, velocity)),
                    _ => None,
                })
                .expect("a TPDO1")
        }
    }

    #[test]
    fn operation_enabled_powers_the_axes_to_their_targets_and_the_tpdo_reports_them() {
        let mut b = Bench::new();
        b.enabled();
        // 100 raw at 1 rpm per unit (the example's `target_rpm_per_unit`): 100 rpm.
        b.rpdo(22 * MS, 0x0F, 100);
        let (fl, fr) = (Wheel::ALL[0], Wheel::ALL[1]);
        assert!(b.plant.drive(fl).powered());
        assert!(
            !b.plant.drive(Wheel::ALL[2]).powered(),
            "node 2 not enabled"
        );
        b.run(300);
        // The loop's integrator on its way there (node 2's wheels coast, dragged).
        let rpm = b.plant.shaft(fl).speed * 60.0 / core::f64::consts::TAU;
        assert!((90.0..=101.0).contains(&rpm), "{rpm} rpm");
        // Sub 2 (the other wheel) had no target.
        assert!(b.plant.shaft(fr).speed.abs() < 1.0);
        let (statusword, velocity) = b.sync(400 * MS);
        assert_eq!(statusword, DriveState402::OperationEnabled.statusword());
        let actual_rpm = f64::from(velocity) * b.drives.actual_rpm_per_unit;
        assert!((actual_rpm - rpm).abs() < 1.0, "{actual_rpm} rpm");
    }

    #[test]
    fn a_quick_stop_brakes_powered_and_ends_at_the_first_sync_at_rest() {
        let mut b = Bench::new();
        b.enabled();
        b.rpdo(22 * MS, 0x0F, 100);
        b.run(300);
        b.rpdo(400 * MS, 0x02, 0);
        let fl = Wheel::ALL[0];
        assert!(b.plant.drive(fl).powered(), "braking");
        // Still turning: the quick stop goes on.
        let (sw, _) = b.sync(401 * MS);
        assert_eq!(sw, DriveState402::QuickStopActive.statusword());
        // Both of node 1's wheels at rest (the other wheel turned with the body).
        let at_rest = |b: &Bench| {
            [fl, Wheel::ALL[1]]
                .iter()
                .all(|w| b.plant.shaft(*w).speed.abs() < QUICK_STOP_REST_RAD_S)
        };
        let mut ms = 0;
        while !at_rest(&b) {
            assert!(ms < 2_000, "the quick stop brings the wheels to rest");
            b.run(1);
            ms += 1;
        }
        let (sw, velocity) = b.sync(2_500 * MS);
        assert_eq!(sw, DriveState402::SwitchOnDisabled.statusword());
        // Below 0.1 rad/s: under 0.96 rpm, 9.5 raw.
        assert!(velocity.abs() <= 9, "{velocity}");
        assert!(!b.plant.drive(fl).powered());
    }

    #[test]
    fn a_fault_takes_the_torque_at_once() {
        let mut b = Bench::new();
        b.enabled();
        b.rpdo(22 * MS, 0x0F, 100);
        b.run(100);
        b.drives.fault(1, 130 * MS, EMCY_DRIVE_FAULT, &mut b.plant);
        assert!(!b.plant.drive(Wheel::ALL[0]).powered());
        assert_eq!(b.drives.emcy_sent(), 1);
    }
}
