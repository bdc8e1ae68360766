//! The drives on the bus: the adapter between CAN frames and the [`plant`](crate::nodes::plant).
//!
//! Command frames addressed to the configured ESCs or ODrive nodes are decoded with the
//! firmware crate's codecs (the same ones the firmware encodes with) and applied to the drive
//! models; the drives' due feedback is encoded back into frames, timestamped when the drive
//! sent it. Frames that are not for a configured drive are ignored, as a real drive would.
//! CiA 402 nodes are [`CanopenDrives`], which speak CANopen themselves.

pub mod canopen;

use firmware::CanFrame;
use firmware::config::{Config, Drive as DriveConfig};
use firmware::protocol::dji::{CurrentCommand, EscId, EscModel};
use firmware::protocol::odrive::{self, NodeId};

use self::canopen::CanopenDrives;
use crate::nodes::SimPlant;
use crate::nodes::plant::{
    ChassisParams, Cia402Axis, DjiDrive, OdriveAxis, ParamError, Plant, PlantSpec, Wheel,
};

/// A plant of one drive kind, with the ids its drives answer to.
#[derive(Debug, Clone)]
pub enum SimDrives {
    /// C620 ESCs; `esc[i]` is wheel i's ESC.
    Dji {
        /// The plant.
        plant: Box<Plant<DjiDrive>>,
        /// ESC id per wheel.
        esc: [EscId; 4],
        /// ESC model (current scale).
        model: EscModel,
    },
    /// ODrive axes; `node[i]` is wheel i's node.
    Odrive {
        /// The plant.
        plant: Box<Plant<OdriveAxis>>,
        /// Node id per wheel.
        node: [NodeId; 4],
    },
    /// CiA 402 drives: hub-motor axes, and the CANopen nodes that command them.
    Cia402 {
        /// The plant.
        plant: Box<Plant<Cia402Axis>>,
        /// The nodes.
        nodes: Box<CanopenDrives>,
    },
}

impl SimDrives {
    /// The plant for a firmware configuration: its geometry, drives, ids and mounting signs.
    ///
    /// # Errors
    /// [`ParamError`] naming the field the plant cannot model (e.g. a C610 configuration:
    /// only the C620 + M3508 is modelled).
    pub fn new(config: &Config) -> Result<Self, ParamError> {
        let bad_id = |field| ParamError::new(field, f64::NAN, "a valid id");
        match config.drive {
            DriveConfig::Dji { model, esc_ids, .. } => {
                let mut esc = [EscId::new(1).ok_or(bad_id("drive.esc_ids"))?; 4];
                for (e, &id) in esc.iter_mut().zip(&esc_ids) {
                    *e = EscId::new(id).ok_or(bad_id("drive.esc_ids"))?;
                }
                Ok(Self::Dji {
                    plant: Box::new(Plant::dji_from_config(config)?),
                    esc,
                    model,
                })
            }
            DriveConfig::Odrive { node_ids, .. } => {
                let mut node = [NodeId::new(0).ok_or(bad_id("drive.node_ids"))?; 4];
                for (n, &id) in node.iter_mut().zip(&node_ids) {
                    *n = NodeId::new(id).ok_or(bad_id("drive.node_ids"))?;
                }
                Ok(Self::Odrive {
                    plant: Box::new(Plant::odrive_from_config(config)?),
                    node,
                })
            }
            DriveConfig::Cia402(_) => Ok(Self::Cia402 {
                plant: Box::new(Plant::cia402_from_config(config)?),
                nodes: Box::new(CanopenDrives::new(config)),
            }),
        }
    }
}

impl SimDrives {
    /// The plant of a configuration where the robot differs from it
    /// ([`PlantSpec`]): [`Self::new`], then the robot's true
    /// geometry and roller drag, its wiring (motors mounted the other way, drives on each
    /// other's ids) and whether it stands on blocks.
    ///
    /// # Errors
    /// [`ParamError`] as [`Self::new`], or naming the `plant.*` value the plant refuses.
    pub fn with_spec(config: &Config, spec: &PlantSpec) -> Result<Self, ParamError> {
        let drives = Self::new(config)?;
        if spec.is_empty() {
            return Ok(drives);
        }
        // `apply` validates the whole spec, wiring included, before it changes anything.
        let adjust = |c: &mut ChassisParams| spec.apply(c);
        let rewire = |inverted: [bool; 4]| spec.wired_inverted(inverted);
        // Friction so low that no wheel moves the body: a robot on blocks.
        const LIFTED_FRICTION: f64 = 1e-9;
        let mut drives = match drives {
            Self::Dji { plant, esc, model } => {
                let plant = (*plant).with_chassis(adjust)?;
                let inverted = rewire(plant.inverted());
                Self::Dji {
                    plant: Box::new(plant.with_inverted(inverted)),
                    esc: spec.wired_ids(esc),
                    model,
                }
            }
            Self::Odrive { plant, node } => {
                let plant = (*plant).with_chassis(adjust)?;
                let inverted = rewire(plant.inverted());
                Self::Odrive {
                    plant: Box::new(plant.with_inverted(inverted)),
                    node: spec.wired_ids(node),
                }
            }
            // Its motors mounted otherwise; its nodes' wiring is the configuration's.
            Self::Cia402 { plant, nodes } => {
                let plant = (*plant).with_chassis(adjust)?;
                let inverted = rewire(plant.inverted());
                Self::Cia402 {
                    plant: Box::new(plant.with_inverted(inverted)),
                    nodes,
                }
            }
        };
        if spec.lifted {
            match &mut drives {
                Self::Dji { plant, .. } => plant.set_friction(LIFTED_FRICTION)?,
                Self::Odrive { plant, .. } => plant.set_friction(LIFTED_FRICTION)?,
                Self::Cia402 { plant, .. } => plant.set_friction(LIFTED_FRICTION)?,
            }
        }
        Ok(drives)
    }

    /// The true state of the chassis and its wheels (ground truth).
    #[must_use]
    pub fn chassis_state(&self) -> &crate::nodes::plant::ChassisState {
        match self {
            Self::Dji { plant, .. } => plant.chassis().state(),
            Self::Odrive { plant, .. } => plant.chassis().state(),
            Self::Cia402 { plant, .. } => plant.chassis().state(),
        }
    }
}

impl SimPlant for SimDrives {
    fn on_frame(&mut self, t_us: u64, frame: &CanFrame) {
        match self {
            Self::Dji { plant, esc, model } => {
                let Ok(cmd) = CurrentCommand::decode(frame, *model) else {
                    return;
                };
                for (wheel, id) in Wheel::ALL.into_iter().zip(*esc) {
                    if id.group() == cmd.group && !plant.is_offline(wheel) {
                        plant.drive_mut(wheel).set_current_raw(cmd.raw[id.slot()]);
                    }
                }
            }
            Self::Odrive { plant, node } => {
                let Ok(addressed) = odrive::Command::decode(frame) else {
                    return;
                };
                for (wheel, id) in Wheel::ALL.into_iter().zip(*node) {
                    if id == addressed.node && !plant.is_offline(wheel) {
                        // A reply (Get_Error) would go out with the next feedback; the
                        // firmware does not ask for one.
                        let _ = plant.drive_mut(wheel).apply(&addressed.msg);
                    }
                }
            }
            Self::Cia402 { plant, nodes } => nodes.on_frame(t_us * 1000, frame, plant),
        }
    }

    fn feedback(&mut self, until_ns: u64, out: &mut Vec<(u64, CanFrame)>) {
        match self {
            Self::Dji { plant, esc, .. } => {
                for f in plant.drain_feedback() {
                    debug_assert!(f.time_ns <= until_ns);
                    let frame = f.feedback.to_firmware(esc[f.wheel.index()]).to_can_frame();
                    out.push((f.time_ns, frame));
                }
            }
            Self::Odrive { plant, node } => {
                for f in plant.drain_feedback() {
                    let frame = f.feedback.to_firmware().to_can_frame(node[f.wheel.index()]);
                    out.push((f.time_ns, frame));
                }
            }
            Self::Cia402 { plant, nodes } => nodes.feedback(until_ns, plant, out),
        }
        out.sort_by_key(|(t, _)| *t);
    }

    fn advance(&mut self, dt: f64) {
        // Parameters were validated at construction; a step error would be a modelling bug
        // (a non-finite state), which the summary would show as a frozen plant.
        let _ = match self {
            Self::Dji { plant, .. } => plant.step(dt),
            Self::Odrive { plant, .. } => plant.step(dt),
            Self::Cia402 { plant, .. } => plant.step(dt),
        };
    }

    fn advance_ns(&mut self, dt_ns: u64) {
        match self {
            Self::Dji { plant, .. } => plant.advance_ns(dt_ns),
            Self::Odrive { plant, .. } => plant.advance_ns(dt_ns),
            Self::Cia402 { plant, .. } => plant.advance_ns(dt_ns),
        }
    }

    fn next_feedback_ns(&self) -> u64 {
        match self {
            Self::Dji { plant, .. } => plant.next_feedback_ns(),
            Self::Odrive { plant, .. } => plant.next_feedback_ns(),
            Self::Cia402 { nodes, .. } => nodes.next_feedback_ns(),
        }
    }

    fn truth(&self) -> [f64; 3] {
        let p = match self {
            Self::Dji { plant, .. } => plant.pose(),
            Self::Odrive { plant, .. } => plant.pose(),
            Self::Cia402 { plant, .. } => plant.pose(),
        };
        [p.x, p.y, p.heading]
    }

    fn truth_velocity(&self) -> [f64; 3] {
        let v = match self {
            Self::Dji { plant, .. } => plant.velocity(),
            Self::Odrive { plant, .. } => plant.velocity(),
            Self::Cia402 { plant, .. } => plant.velocity(),
        };
        [v.vx, v.vy, v.wz]
    }

    fn truth_travel(&self) -> Option<[f64; 3]> {
        let travel = match self {
            Self::Dji { plant, .. } => plant.chassis().body_travel(),
            Self::Odrive { plant, .. } => plant.chassis().body_travel(),
            Self::Cia402 { plant, .. } => plant.chassis().body_travel(),
        };
        Some(travel)
    }

    fn set_faults(&mut self, at_ns: u64, stuck: [bool; 4], offline: [bool; 4]) {
        match self {
            Self::Dji { plant, .. } => plant.set_faults_at(at_ns, stuck, offline),
            Self::Odrive { plant, .. } => plant.set_faults_at(at_ns, stuck, offline),
            Self::Cia402 { plant, .. } => plant.set_faults_at(at_ns, stuck, offline),
        }
    }

    fn set_drive_faults(&mut self, at_ns: u64, faults: [crate::nodes::DriveFaults; 4]) {
        if let Self::Cia402 { plant, nodes } = self {
            nodes.set_wheel_faults(at_ns, faults, plant);
        }
    }
}
