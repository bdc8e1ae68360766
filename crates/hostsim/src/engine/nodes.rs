//! The nodes of a scenario, built from its data: the drives on the plant ([`plant_for`]), the
//! host that plays its actions and host faults, and the pod node with its errors and silences.
//! The one place that reads a [`Scenario`] into the nodes' own parameters.

use firmware::config::Drive as DriveConfig;
use firmware::control::{LOAD_SIGNATURE, RESTORE, SAVE_SIGNATURE, STORE};
use firmware::protocol::canopen::{Message, NodeId, SdoRequest};
use firmware::protocol::robot::{self, Command, ModeRequest};

use crate::nodes::SimPlant;
use crate::nodes::drives::SimDrives;
use crate::nodes::host::{HostAction, HostNode};
use crate::nodes::plant::ParamError;
use crate::nodes::pods::{PodNode, WithPods, pods_seed};
use crate::scenario::{FaultName, Scenario, StoreCommand};

/// The plant of a scenario: its drives ([`SimDrives::with_spec`]) for its configuration and
/// `[plant]` table.
///
/// # Errors
/// [`ParamError`] as [`SimDrives::with_spec`], or naming `faults[].kind` when a wheel fault
/// that acts on CANopen nodes is given for drives of another protocol.
pub fn plant_for(scenario: &Scenario) -> Result<SimDrives, ParamError> {
    if !matches!(scenario.config.drive, DriveConfig::Cia402(_))
        && scenario.wheel_faults.iter().any(|f| f.kind.cia402_only())
    {
        return Err(ParamError::new(
            "faults[].kind",
            f64::NAN,
            "stuck_encoder or motor_offline: drive_silent, drive_reboot, drive_fault, \
             enable_refused, sdo_abort and drive_bus_off act on CANopen nodes, a \
             protocol = \"cia402\" configuration",
        ));
    }
    SimDrives::with_spec(&scenario.config, &scenario.plant)
}

/// The host of `scenario`, before its first action: its actions as the host's script, its
/// command rate and its host faults.
pub(crate) fn host(scenario: &Scenario) -> HostNode {
    HostNode::new(
        script(scenario),
        scenario.command_hz,
        scenario.host_faults.clone(),
    )
}

/// `plant` with the pod node of `scenario`: its `[pods]` on the configuration's pods, seeded
/// with [`pods_seed`]`(scenario.seed)`, silent in its `pods_silent` faults; none without a
/// `[pods]` table or without configured pods.
pub(crate) fn with_pods<'a, P: SimPlant>(plant: &'a mut P, scenario: &Scenario) -> WithPods<'a, P> {
    let nominal = scenario.config.odometry.pods;
    let node = scenario
        .pods
        .as_ref()
        .filter(|_| !nominal.is_empty())
        .map(|params| {
            PodNode::new(params, nominal.as_slice(), pods_seed(scenario.seed)).silenced(
                scenario
                    .node_faults
                    .iter()
                    .filter(|f| f.kind == FaultName::PodsSilent)
                    .map(|f| (f.from_us * 1000, f.until_us.saturating_mul(1000))),
            )
        });
    WithPods::new(plant, node)
}

/// The scenario's actions in time order, one host action each.
fn script(s: &Scenario) -> Vec<(u64, HostAction)> {
    let node = firmware::params::service_node(&s.config);
    let mut out = Vec::new();
    for (t, a) in s.timed_actions() {
        let mut push = |action| out.push((t, action));
        for (flag, cmd) in [
            (a.estop, Command::Estop),
            (a.reset, Command::Mode(ModeRequest::Reset)),
            (a.disable, Command::Mode(ModeRequest::Disable)),
            (a.enable, Command::Mode(ModeRequest::Enable)),
            (a.status_request, Command::StatusRequest),
        ] {
            if flag {
                push(HostAction::Send(cmd));
            }
        }
        if let Some(t) = a.wheel_test {
            push(HostAction::Send(Command::WheelTest(robot::WheelTest {
                wheel: t.wheel,
                speed: t.speed,
                duration_ms: t.duration_ms,
            })));
        }
        if let Some(set) = a.set
            && let Some(frame) = set
                .param
                .0
                .ty
                .from_f64(set.value)
                .and_then(|raw| set.param.0.download(node, raw))
        {
            push(HostAction::Frame(frame));
        }
        if let Some(store) = a.store
            && let Some(node) = NodeId::new(node)
        {
            let (index, value) = match store {
                StoreCommand::Save => (STORE, SAVE_SIGNATURE),
                StoreCommand::Restore => (RESTORE, LOAD_SIGNATURE),
            };
            let request = SdoRequest::Download {
                index,
                sub: 1,
                value,
                size: 4,
            };
            push(HostAction::Frame(
                Message::SdoRequest { node, request }.to_can_frame(),
            ));
        }
        if let Some(tw) = a.twist {
            push(HostAction::Twist(tw));
        }
        if a.silence {
            push(HostAction::Stream(false));
        }
        if a.resume {
            push(HostAction::Stream(true));
        }
    }
    out
}
