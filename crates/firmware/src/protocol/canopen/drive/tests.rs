//! The node's logic on scripted axes: resets, EMCY, the heartbeat consumer, the 402 table
//! (`tests/cia402_transitions.toml`), the PDO rules, and the makers' options.

extern crate std;

use std::collections::BTreeMap;
use std::format;
use std::string::String;
use std::vec::Vec;

use embedded_can::StandardId;

use super::*;
use crate::protocol::canopen::{
    self, DriveState402, Message, NmtCommand, NmtState, NodeId, SdoRequest, SdoResponse,
};
use crate::{CanFrame, Config};

const MS: u64 = 1_000_000;
/// The simulator's timing (hostsim's `ANSWER_NS`, `BOOT_NS`).
const TIMING: Timing = Timing {
    answer_ns: 200_000,
    boot_ns: 2 * MS,
    heartbeat_aligned: false,
};

/// Axes that follow their command at once: the target's velocity, 0 otherwise; at rest
/// unless `moving`.
#[derive(Debug, Default)]
struct Wheels {
    command: [Option<AxisCommand>; 4],
    moving: [bool; 4],
}

impl Axes for Wheels {
    fn command(&mut self, wheel: usize, command: AxisCommand) {
        self.command[wheel] = Some(command);
    }

    fn velocity(&self, wheel: usize) -> i32 {
        match self.command[wheel] {
            Some(AxisCommand::Velocity(t)) => t,
            _ => 0,
        }
    }

    fn at_rest(&self, wheel: usize) -> bool {
        !self.moving[wheel]
    }
}

/// The example's nodes 1 and 2 (dual-axis: wheels 0 and 1, 2 and 3), booted at 0: what each
/// test starts from.
struct Bench {
    drives: Drives402,
    axes: Wheels,
    /// Every frame the nodes sent: time (ns), frame.
    sent: Vec<(u64, CanFrame)>,
}

impl Bench {
    fn new() -> Self {
        Self::with(TIMING, Options::default())
    }

    fn with(timing: Timing, options: Options) -> Self {
        Self {
            drives: Drives402::new(&Config::cia402_example(), timing, options),
            axes: Wheels::default(),
            sent: Vec::new(),
        }
    }

    /// The nodes' frames up to `t_ns`.
    fn run_to(&mut self, t_ns: u64) {
        let sent = &mut self.sent;
        self.drives
            .feedback(t_ns, &mut self.axes, |t, f| sent.push((t, f)));
    }

    /// `msg` on the bus at `t_ns` (after the nodes' frames up to then).
    fn put(&mut self, t_ns: u64, msg: Message) {
        self.run_to(t_ns);
        self.drives
            .on_frame(t_ns, &msg.to_can_frame(), &mut self.axes);
    }

    fn nmt(&mut self, t_ns: u64, command: NmtCommand) {
        let node = Some(node1());
        self.put(t_ns, Message::Nmt { command, node });
    }

    /// An SDO request to node 1 at `t_ns`; its answer.
    fn sdo(&mut self, t_ns: u64, request: SdoRequest) -> SdoResponse {
        let from = self.sent.len();
        let node = node1();
        self.put(t_ns, Message::SdoRequest { node, request });
        self.run_to(t_ns + TIMING.answer_ns);
        self.sent[from..]
            .iter()
            .find_map(|(_, f)| match canopen::decode(f) {
                Ok(Message::SdoResponse { node, response }) if node == node1() => Some(response),
                _ => None,
            })
            .expect("an SDO answer")
    }

    fn download(&mut self, t_ns: u64, index: u16, sub: u8, value: u32) {
        let request = SdoRequest::Download {
            index,
            sub,
            value,
            size: 4,
        };
        assert_eq!(
            self.sdo(t_ns, request),
            SdoResponse::Downloaded { index, sub },
            "{index:04X}:{sub:02X} = {value:#x}"
        );
    }

    fn upload(&mut self, t_ns: u64, index: u16, sub: u8) -> u32 {
        match self.sdo(t_ns, SdoRequest::Upload { index, sub }) {
            SdoResponse::Uploaded { value, .. } => value,
            other => panic!("{index:04X}:{sub:02X}: {other:?}"),
        }
    }

    /// Node 1's RPDO1 carries its controlword and sub 1's target, TPDO1 its statusword and
    /// sub 1's velocity on SYNC (disable, map, enable); mode 3, started.
    fn started(&mut self, t_ns: u64) {
        for (k, (index, sub, value)) in NODE1_PDO_SETUP.into_iter().enumerate() {
            self.download(t_ns + k as u64 * MS, index, sub, value);
        }
        self.nmt(t_ns + 20 * MS, NmtCommand::Start);
    }

    /// Node 1's RPDO1 at `t_ns`.
    fn rpdo(&mut self, t_ns: u64, controlword: u16, target: i32) {
        let node = node1();
        let msg = Message::Rpdo1 {
            node,
            controlword,
            target,
        };
        self.put(t_ns, msg);
    }

    /// SYNC at `t_ns`; node 1's TPDO1 answer (statusword, velocity), if any.
    fn sync(&mut self, t_ns: u64) -> Option<(u16, i32)> {
        let from = self.sent.len();
        self.put(t_ns, Message::Sync { counter: None });
        self.run_to(t_ns + TIMING.answer_ns);
        self.sent[from..]
            .iter()
            .find_map(|(_, f)| match canopen::decode(f) {
                Ok(Message::Tpdo1 {
                    node,
                    statusword,
                    velocity,
                }) if node == node1() => Some((statusword, velocity)),
                _ => None,
            })
    }

    /// Node 1's EMCY frames so far: time, error code, error register.
    fn emcys(&self) -> Vec<(u64, u16, u8)> {
        self.messages()
            .filter_map(|(t, m)| match m {
                Message::Emcy { node, emcy } if node == node1() => {
                    Some((t, emcy.error_code, emcy.error_register))
                }
                _ => None,
            })
            .collect()
    }

    /// Node 1's heartbeats (and boot-ups) so far: time, state.
    fn heartbeats(&self) -> Vec<(u64, NmtState)> {
        self.messages()
            .filter_map(|(t, m)| match m {
                Message::Heartbeat { node, state } if node == node1() => Some((t, state)),
                _ => None,
            })
            .collect()
    }

    fn messages(&self) -> impl Iterator<Item = (u64, Message)> + '_ {
        self.sent
            .iter()
            .filter_map(|(t, f)| canopen::decode(f).ok().map(|m| (*t, m)))
    }

    fn node1(&mut self) -> &mut Drive402 {
        self.drives.node_mut(1).unwrap()
    }

    fn state(&self) -> DriveState402 {
        self.drives.node(1).unwrap().state()
    }
}

fn node1() -> NodeId {
    NodeId::new(1).unwrap()
}

#[test]
fn reset_communication_resets_the_communication_area_only_reset_node_everything() {
    let mut b = Bench::new();
    b.started(3 * MS);
    b.download(30 * MS, 0x1017, 0, 50);
    for cw in [0x06, 0x07, 0x0F] {
        b.rpdo(31 * MS, cw, 0);
    }
    assert_eq!(b.state(), DriveState402::OperationEnabled);
    b.nmt(40 * MS, NmtCommand::ResetCommunication);
    b.run_to(40 * MS + TIMING.boot_ns);
    assert_eq!(
        b.heartbeats().last(),
        Some(&(40 * MS + TIMING.boot_ns, NmtState::BootUp))
    );
    // The communication area at its defaults: no heartbeat, the predefined RPDO1 (its
    // mapping empty, as the node ships), RPDO2 valid on 0x301.
    let t = 50 * MS;
    assert_eq!(b.upload(t, 0x1017, 0), 0);
    assert_eq!(b.upload(t, 0x1600, 0), 0);
    assert_eq!(b.upload(t, 0x1401, 1), 0x301);
    // The application kept: the mode (and its display), the drive's state.
    assert_eq!(b.upload(t, 0x6060, 0), 3);
    assert_eq!(b.upload(t, 0x6061, 0), 3);
    assert_eq!(b.state(), DriveState402::OperationEnabled);
    // Reset node: everything, the drive switch on disabled.
    b.nmt(60 * MS, NmtCommand::ResetNode);
    b.run_to(60 * MS + TIMING.boot_ns);
    assert_eq!(b.upload(70 * MS, 0x6060, 0), 0);
    assert_eq!(b.state(), DriveState402::SwitchOnDisabled);
}

#[test]
fn a_reset_before_the_power_on_boot_up_leaves_one_boot_up_its_own() {
    let mut b = Bench::new();
    // Powered at 0 (boot-up owed at 2 ms); the master's reset at 1 ms.
    b.nmt(MS, NmtCommand::ResetCommunication);
    b.run_to(20 * MS);
    assert_eq!(b.heartbeats(), [(MS + TIMING.boot_ns, NmtState::BootUp)]);
    // Node 2, not reset, sent its power-on boot-up.
    let node2 = b
        .messages()
        .filter(|(_, m)| matches!(m, Message::Heartbeat { node, .. } if node.get() == 2))
        .count();
    assert_eq!(node2, 1);
}

#[test]
fn emcy_error_register_carries_the_class_of_the_error() {
    for (code, register) in [
        (0x2310, 0x03), // over-current: current
        (0x3210, 0x05), // over-voltage: voltage
        (0x4210, 0x09), // temperature
        (0x8130, 0x11), // heartbeat / life guard: communication
        (0x8140, 0x11), // recovered from bus-off
        (0x8210, 0x11), // PDO length: protocol, communication
        (0x8611, 0x01), // following error: generic only
        (0x1000, 0x01), // generic
        (0x0000, 0x00), // error reset
    ] {
        assert_eq!(error_register(code), register, "{code:#06x}");
    }
    let mut b = Bench::new();
    b.run_to(3 * MS);
    b.drives
        .node_mut(1)
        .unwrap()
        .fault(4 * MS, EMCY_DRIVE_FAULT, &mut b.axes);
    b.run_to(5 * MS);
    assert_eq!(b.emcys(), [(4 * MS, 0x2310, 0x03)]);
    assert_eq!(b.upload(6 * MS, 0x1001, 0), 0x03);
    // Read-only.
    let request = SdoRequest::Download {
        index: 0x1001,
        sub: 0,
        value: 0,
        size: 1,
    };
    assert_eq!(
        b.sdo(7 * MS, request),
        SdoResponse::Abort {
            index: 0x1001,
            sub: 0,
            code: abort::READ_ONLY
        }
    );
}

#[test]
fn a_fault_reset_sends_emcy_error_reset_and_clears_the_register() {
    let mut b = Bench::new();
    b.started(3 * MS);
    b.rpdo(30 * MS, 0x06, 0);
    b.drives
        .node_mut(1)
        .unwrap()
        .fault(31 * MS, EMCY_DRIVE_FAULT, &mut b.axes);
    // No edge of bit 7 yet: nothing.
    b.rpdo(32 * MS, 0x06, 0);
    assert_eq!(b.state(), DriveState402::Fault);
    b.rpdo(33 * MS, 0x80, 0);
    b.rpdo(34 * MS, 0x80, 0);
    b.run_to(40 * MS);
    assert_eq!(b.state(), DriveState402::SwitchOnDisabled);
    assert_eq!(
        b.emcys(),
        [
            (31 * MS, 0x2310, 0x03),
            (33 * MS + TIMING.answer_ns, 0x0000, 0x00)
        ]
    );
    assert_eq!(b.upload(41 * MS, 0x1001, 0), 0);
}

#[test]
fn the_heartbeat_consumer_starts_at_the_masters_first_heartbeat() {
    let mut b = Bench::new();
    b.started(3 * MS);
    b.download(30 * MS, 0x1017, 0, 50);
    b.download(31 * MS, 0x1016, 1, 127 << 16 | 150);
    // Started, the consumer set, and no heartbeat of the master for a second: nothing.
    b.run_to(1_000 * MS);
    assert!(b.emcys().is_empty());
    let master = NodeId::new(127).unwrap();
    let beat = Message::Heartbeat {
        node: master,
        state: NmtState::Operational,
    };
    b.put(1_000 * MS, beat);
    b.put(1_050 * MS, beat);
    b.run_to(2_000 * MS);
    // The time-out 150 ms after the last one: EMCY 0x8130, pre-operational at once.
    assert_eq!(b.emcys(), [(1_200 * MS, 0x8130, 0x11)]);
    let states: Vec<_> = b
        .heartbeats()
        .into_iter()
        .filter(|(t, _)| (1_100 * MS..1_300 * MS).contains(t))
        .collect();
    assert_eq!(
        states.iter().map(|h| h.1).collect::<Vec<_>>(),
        [
            NmtState::Operational,
            NmtState::Operational,
            NmtState::PreOperational,
            NmtState::PreOperational
        ],
        "{states:?}"
    );
    assert!(
        states.contains(&(1_200 * MS, NmtState::PreOperational)),
        "{states:?}"
    );
}

#[derive(serde::Deserialize)]
struct TransitionTable {
    statusword: BTreeMap<String, u16>,
    table: Rows,
}

#[derive(serde::Deserialize)]
struct Rows {
    rows: Vec<(String, u16, u16, u8, String, String)>,
}

/// CiA 402's state table (tests/cia402_transitions.toml, which the Python peer's test reads
/// too): each row from its state, its controlword after the one before it, in its mode of
/// operation.
#[test]
fn both_drive_models_follow_the_transition_table() {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../tests/cia402_transitions.toml"
    );
    let text = std::fs::read_to_string(path).unwrap();
    let t: TransitionTable = toml::from_str(&text).unwrap();
    let states = [
        DriveState402::SwitchOnDisabled,
        DriveState402::ReadyToSwitchOn,
        DriveState402::SwitchedOn,
        DriveState402::OperationEnabled,
        DriveState402::QuickStopActive,
        DriveState402::Fault,
    ];
    let named = |name: &str| *states.iter().find(|s| s.as_str() == name).unwrap();
    assert!(t.table.rows.len() >= 60);
    for (from, cw, previous, mode, to, transition) in &t.table.rows {
        let mut n = Drive402::new(node1(), [Some(0), None, None], TIMING, Options::default());
        n.state = named(from);
        n.last_controlword = *previous;
        n.od.set(0x6060, 0, u32::from(*mode));
        let reset = n.control(*cw);
        let row =
            format!("{from} {cw:#04x} (after {previous:#04x}, mode {mode}) -> {to} ({transition})");
        assert_eq!(n.state.as_str(), to.as_str(), "{row}");
        assert_eq!(n.statusword() & 0x6F, t.statusword[to], "{row}");
        assert_eq!(reset, from == "FAULT" && to != "FAULT", "{row}");
    }
}

fn write(n: &mut Drive402, index: u16, sub: u8, value: u32) -> SdoResponse {
    let request = SdoRequest::Download {
        index,
        sub,
        value,
        size: 4,
    };
    n.on_sdo(request, 0);
    let mut answer = None;
    n.feedback(u64::MAX - 1, &mut Wheels::default(), |_, f| {
        if let Ok(Message::SdoResponse { response, .. }) = canopen::decode(&f) {
            answer = Some(response);
        }
    });
    answer.expect("an answer")
}

fn written(index: u16, sub: u8) -> SdoResponse {
    SdoResponse::Downloaded { index, sub }
}

#[test]
fn a_mapping_changes_only_in_the_disable_map_enable_order() {
    let mut n = Drive402::new(node1(), [Some(0), None, None], TIMING, Options::default());
    let refused = |sub, code| SdoResponse::Abort {
        index: 0x1600,
        sub,
        code,
    };
    // RPDO1 is valid as the drive ships: its mapping is locked.
    assert_eq!(write(&mut n, 0x1600, 0, 0), refused(0, abort::DEVICE_STATE));
    assert_eq!(write(&mut n, 0x1400, 1, 0x8000_0201), written(0x1400, 1));
    assert_eq!(write(&mut n, 0x1600, 0, 0), written(0x1600, 0));
    assert_eq!(write(&mut n, 0x1600, 1, 0x6040_0010), written(0x1600, 1));
    // A TPDO object in an RPDO, or a dual-axis sub-index on a single-axis node: refused.
    for bad in [0x6041_0010, 0x60FF_0120] {
        assert_eq!(write(&mut n, 0x1600, 2, bad), refused(2, abort::CANNOT_MAP));
    }
    assert_eq!(write(&mut n, 0x1600, 2, 0x60FF_0020), written(0x1600, 2));
    assert_eq!(write(&mut n, 0x1600, 0, 2), written(0x1600, 0));
    // Entries only while the count is 0.
    assert_eq!(
        write(&mut n, 0x1600, 1, 0x6040_0010),
        refused(1, abort::DEVICE_STATE)
    );
    assert_eq!(write(&mut n, 0x1400, 1, 0x201), written(0x1400, 1));
    let entries = mapping::entries(&n.od, 0x1600).unwrap();
    assert_eq!(entries[..], [(0x6040, 0, 16), (0x60FF, 0, 32)]);
    assert_eq!(mapping::rpdo_with(&n.od, 0x201), Some(0));
    // A valid PDO's COB-ID changes only through invalid; missing objects and sub-indices.
    assert_eq!(
        write(&mut n, 0x1400, 1, 0x202),
        SdoResponse::Abort {
            index: 0x1400,
            sub: 1,
            code: abort::INVALID_VALUE
        }
    );
    assert_eq!(
        write(&mut n, 0x1016, 0, 1),
        SdoResponse::Abort {
            index: 0x1016,
            sub: 0,
            code: abort::NO_SUBINDEX
        }
    );
    assert_eq!(
        write(&mut n, 0x6064, 0, 1),
        SdoResponse::Abort {
            index: 0x6064,
            sub: 0,
            code: abort::NO_OBJECT
        }
    );
}

/// Node 1 operation enabled with a target of 100 on sub 1 and its wheels turning.
fn driving(b: &mut Bench) {
    b.started(3 * MS);
    for cw in [0x06, 0x07] {
        b.rpdo(30 * MS, cw, 0);
    }
    b.rpdo(30 * MS, 0x0F, 100);
    b.axes.moving = [true; 4];
    assert_eq!(b.axes.command[0], Some(AxisCommand::Velocity(100)));
    assert_eq!(b.sync(31 * MS), Some((0x0237, 100)));
}

#[test]
fn a_shutdown_with_option_code_1_slows_down_powered_until_the_axes_rest() {
    let mut b = Bench::new();
    b.download(2 * MS + 500_000, 0x605B, 0, 1);
    driving(&mut b);
    b.rpdo(32 * MS, 0x06, 100);
    assert_eq!(b.state(), DriveState402::OperationEnabled, "slowing down");
    assert_eq!(b.axes.command[0], Some(AxisCommand::SlowDown));
    assert_eq!(b.sync(36 * MS).map(|s| s.0), Some(0x0237));
    b.axes.moving = [false; 4];
    assert_eq!(b.sync(40 * MS).map(|s| s.0), Some(0x0231));
    assert_eq!(b.axes.command[0], Some(AxisCommand::Off));
}

#[test]
fn a_drive_without_the_option_codes_refuses_them_and_stops_at_once() {
    let options = Options {
        lacks_option_codes: true,
        ..Options::default()
    };
    let mut b = Bench::with(TIMING, options);
    let request = SdoRequest::Download {
        index: 0x605B,
        sub: 0,
        value: 1,
        size: 2,
    };
    assert_eq!(
        b.sdo(2 * MS + 500_000, request),
        SdoResponse::Abort {
            index: 0x605B,
            sub: 0,
            code: abort::NO_OBJECT
        }
    );
    driving(&mut b);
    b.rpdo(32 * MS, 0x06, 100);
    assert_eq!(b.state(), DriveState402::ReadyToSwitchOn);
    assert_eq!(b.axes.command[0], Some(AxisCommand::Off));
}

#[test]
fn a_quick_stop_ends_at_rest_unless_the_maker_keeps_it_active() {
    for stays in [false, true] {
        let options = Options {
            quick_stop_stays: stays,
            ..Options::default()
        };
        let mut b = Bench::with(TIMING, options);
        driving(&mut b);
        b.rpdo(32 * MS, 0x02, 0);
        assert_eq!(b.axes.command[0], Some(AxisCommand::QuickStop));
        assert_eq!(b.sync(36 * MS).map(|s| s.0), Some(0x0217), "moving");
        b.axes.moving = [false; 4];
        let want = if stays { 0x0217 } else { 0x0250 };
        assert_eq!(b.sync(40 * MS).map(|s| s.0), Some(want), "stays: {stays}");
    }
}

#[test]
fn a_self_starting_node_is_operational_from_its_boot_up() {
    let options = Options {
        self_starting: true,
        ..Options::default()
    };
    let mut b = Bench::with(TIMING, options);
    b.nmt(MS, NmtCommand::ResetCommunication);
    assert_eq!(b.node1().nmt(), NmtState::Operational);
    b.run_to(10 * MS);
    assert_eq!(
        b.heartbeats(),
        [(3 * MS, NmtState::BootUp), (3 * MS, NmtState::Operational)]
    );
    // Its predefined RPDO2 (0x301) takes frames from then on.
    assert_eq!(b.node1().rpdo_on(0x301), Some(1));
}

#[test]
fn an_aligned_producer_beats_at_the_multiples_of_its_period() {
    let timing = Timing {
        heartbeat_aligned: true,
        ..Timing::NEXT_MS
    };
    let mut b = Bench::with(timing, Options::default());
    b.put(3 * MS, {
        let request = SdoRequest::Download {
            index: 0x1017,
            sub: 0,
            value: 50,
            size: 2,
        };
        Message::SdoRequest {
            node: node1(),
            request,
        }
    });
    b.run_to(160 * MS);
    let beats: Vec<u64> = b.heartbeats().iter().skip(1).map(|h| h.0).collect();
    assert_eq!(beats, [50 * MS, 100 * MS, 150 * MS]);
}

#[test]
fn a_node_bus_off_sends_nothing_and_comes_back_with_emcy_and_its_heartbeat() {
    let mut b = Bench::new();
    driving(&mut b);
    b.download(32 * MS, 0x1017, 0, 50);
    b.drives.node_mut(1).unwrap().go_bus_off(&mut b.axes);
    assert_eq!(b.node1().nmt(), NmtState::PreOperational);
    assert_eq!(b.state(), DriveState402::Fault);
    let before = b.sent.len();
    assert_eq!(b.sync(40 * MS), None);
    b.run_to(200 * MS);
    assert!(
        b.sent[before..]
            .iter()
            .all(|(_, f)| { !matches!(canopen::decode(f), Ok(m) if m.node() == Some(node1())) }),
        "silent while bus-off"
    );
    b.node1().recover_bus_off(200 * MS);
    b.run_to(200 * MS);
    assert_eq!(b.emcys(), [(200 * MS, 0x8140, 0x11)]);
    assert_eq!(
        b.heartbeats().last(),
        Some(&(200 * MS, NmtState::PreOperational))
    );
    assert_eq!(b.drives.emcy_sent(), 1);
}

#[test]
fn a_short_rpdo_is_not_acted_on() {
    let mut b = Bench::new();
    driving(&mut b);
    let id = StandardId::new(0x201).unwrap();
    let short = CanFrame::standard(id, &[0x02, 0x00, 0x10]).unwrap();
    b.drives.on_frame(32 * MS, &short, &mut b.axes);
    assert_eq!(b.state(), DriveState402::OperationEnabled);
    assert_eq!(b.axes.command[0], Some(AxisCommand::Velocity(100)));
    assert_eq!(b.node1().frames_lost(), 0);
}
