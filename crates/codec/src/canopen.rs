//! CANopen (CiA 301/402) in `mecanum-codec`: `decode --canopen` and the golden frames.
//!
//! Message names are those of `dbc/cia402.dbc` (`TPDO1_1`, `SDO_REQUEST_2`, `HEARTBEAT_127`;
//! `NMT`, `SYNC`), with the node's number for any node 1-127, and field names its signal
//! names (the firmware layout's [`Field`](firmware::protocol::wire::Field) names).

use embedded_can::Frame;
use firmware::CanFrame;
use firmware::protocol::DecodeError;
use firmware::protocol::canopen::{
    self, Emcy, Message, NmtCommand, NmtState, NodeId, SdoRequest, SdoResponse, controlword, layout,
};
use firmware::protocol::wire::Payload;

use crate::json::Decoded;

/// A CANopen frame as decoded: the message and the SDO command byte that was on the wire (the
/// message keeps what the byte means; several bytes mean the same, `0x42` and `0x43` for one).
#[derive(Clone, Debug)]
pub struct CanopenFrame {
    message: Message,
    /// Byte 0 of the frame, reported for SDO frames only.
    sdo_command: u8,
}

impl CanopenFrame {
    /// A message as the Rust encoder writes it (the command byte is the encoder's).
    pub fn encoded(message: Message) -> Self {
        Self {
            message,
            sdo_command: sdo_command(&message.to_can_frame()),
        }
    }

    /// Decodes a frame with `firmware::protocol::canopen::decode`.
    pub fn decode(frame: &CanFrame) -> Result<Self, DecodeError> {
        let message = canopen::decode(frame)?;
        Ok(Self {
            message,
            sdo_command: sdo_command(frame),
        })
    }

    /// The message's frame as the Rust encoder writes it.
    pub fn to_can_frame(&self) -> CanFrame {
        self.message.to_can_frame()
    }

    /// The DBC's message name and signals: enums as their numbers; SDO frames with the command
    /// byte as received and the data as the decoder reads it (the `size` low bytes of an
    /// expedited transfer, the code of an abort, 0 where the command carries no data), plus
    /// the transfer's `size` for expedited data.
    pub fn fields(&self) -> Decoded {
        let def = self.message.def();
        let d = match self.message.node() {
            // NMT addresses its node in the data, not the id.
            Some(node) if !matches!(self.message, Message::Nmt { .. }) => {
                Decoded::new("canopen", format!("{}_{}", def.name, node.get()))
                    .extra("node", node.get().into())
            }
            _ => Decoded::new("canopen", def.name),
        };
        match self.message {
            Message::Nmt { command, node } => d
                .i(&layout::NMT_COMMAND, command.raw())
                .i(&layout::NMT_NODE, node.map_or(0, NodeId::get)),
            Message::Sync { counter: None } => d,
            Message::Sync { counter: Some(c) } => d.extra("counter", c.into()),
            Message::Emcy { emcy, .. } => d
                .i(&layout::EMCY_ERROR_CODE, emcy.error_code)
                .i(&layout::EMCY_ERROR_REGISTER, emcy.error_register)
                .i(&layout::EMCY_MANUFACTURER_LOW, manufacturer(&emcy)),
            Message::Tpdo1 {
                statusword,
                velocity,
                ..
            } => d
                .i(&layout::STATUSWORD, statusword)
                .i(&layout::VELOCITY_ACTUAL, velocity),
            Message::Tpdo2 { velocity, .. } => d.i(&layout::VELOCITY_ACTUAL_2, velocity),
            Message::Rpdo1 {
                controlword,
                target,
                ..
            } => d
                .i(&layout::CONTROLWORD, controlword)
                .i(&layout::TARGET_VELOCITY, target),
            Message::Rpdo3 { target, .. } => d.i(&layout::TARGET_VELOCITY_2, target),
            Message::SdoRequest { request, .. } => {
                let (data, size) = match request {
                    SdoRequest::Upload { .. } => (0, None),
                    SdoRequest::Download { value, size, .. } => (value, Some(size)),
                    SdoRequest::Abort { code, .. } => (code, None),
                };
                self.sdo(d, request.object(), data, size)
            }
            Message::SdoResponse { response, .. } => {
                let (data, size) = match response {
                    SdoResponse::Uploaded { value, size, .. } => (value, Some(size)),
                    SdoResponse::Downloaded { .. } => (0, None),
                    SdoResponse::Abort { code, .. } => (code, None),
                };
                self.sdo(d, response.object(), data, size)
            }
            Message::Heartbeat { state, .. } => d.i(&layout::HEARTBEAT_STATE, state.raw()),
        }
    }

    fn sdo(&self, d: Decoded, (index, sub): (u16, u8), data: u32, size: Option<u8>) -> Decoded {
        let d = match size {
            Some(size) => d.extra("size", size.into()),
            None => d,
        };
        d.i(&layout::SDO_COMMAND, self.sdo_command)
            .i(&layout::SDO_INDEX, index)
            .i(&layout::SDO_SUBINDEX, sub)
            .i(&layout::SDO_DATA, data)
    }
}

/// Byte 0 of a frame (the SDO command byte of an SDO frame).
fn sdo_command(frame: &CanFrame) -> u8 {
    u8::try_from(layout::SDO_COMMAND.raw(&Payload::from_slice(frame.data()))).unwrap_or(0)
}

/// The 5 manufacturer bytes of an EMCY as the DBC's 40-bit little-endian signal.
fn manufacturer(emcy: &Emcy) -> i64 {
    emcy.manufacturer
        .iter()
        .rev()
        .fold(0, |acc, &b| acc << 8 | i64::from(b))
}

/// The golden CANopen messages: every message kind and every enum value, for nodes 1 and 2
/// (the nodes of `dbc/cia402.dbc`) and the master's heartbeat (node 127); SDO uploads and
/// downloads of 1, 2 and 4 bytes and aborts both ways.
pub fn golden_set() -> Vec<CanopenFrame> {
    let mut v = network_messages();
    for n in [1, 2] {
        v.extend(node_messages(node_id(n)));
    }
    v.into_iter().map(CanopenFrame::encoded).collect()
}

fn node_id(n: u8) -> NodeId {
    NodeId::new(n).unwrap_or_else(|| unreachable!("node ids 1..=127"))
}

/// NMT to one node and to all, SYNC, and the master's heartbeat.
fn network_messages() -> Vec<Message> {
    let node = node_id;
    vec![
        Message::Nmt {
            command: NmtCommand::ResetCommunication,
            node: None,
        },
        Message::Nmt {
            command: NmtCommand::Start,
            node: Some(node(1)),
        },
        Message::Nmt {
            command: NmtCommand::Stop,
            node: Some(node(2)),
        },
        Message::Nmt {
            command: NmtCommand::EnterPreOperational,
            node: None,
        },
        Message::Nmt {
            command: NmtCommand::ResetNode,
            node: Some(node(127)),
        },
        Message::Sync { counter: None },
        Message::Heartbeat {
            node: node(127),
            state: NmtState::Operational,
        },
    ]
}

/// One node's messages: EMCY, the PDOs with every controlword, SDO both ways, and its
/// heartbeat in every state.
fn node_messages(node: NodeId) -> Vec<Message> {
    let k = i32::from(node.get());
    let mut v = emcy_and_pdos(node);
    for (cw, target) in [
        (controlword::SHUTDOWN, 0),
        (controlword::SWITCH_ON, 0),
        (controlword::ENABLE_OPERATION, 2_000 * k),
        (controlword::QUICK_STOP, i32::MAX),
        (controlword::FAULT_RESET, i32::MIN),
    ] {
        v.push(Message::Rpdo1 {
            node,
            controlword: cw,
            target,
        });
    }
    v.extend(sdo_messages(node));
    for state in [
        NmtState::BootUp,
        NmtState::Stopped,
        NmtState::Operational,
        NmtState::PreOperational,
    ] {
        v.push(Message::Heartbeat { node, state });
    }
    v
}

/// SDO requests (upload, downloads of 1, 2 and 4 bytes, abort) and responses (uploads of 1, 2
/// and 4 bytes, a download's answer, aborts).
fn sdo_messages(node: NodeId) -> Vec<Message> {
    let mut v = Vec::new();
    for request in [
        SdoRequest::Upload {
            index: 0x1000,
            sub: 0,
        },
        SdoRequest::Download {
            index: 0x6060,
            sub: 0,
            value: 3,
            size: 1,
        },
        SdoRequest::Download {
            index: 0x1017,
            sub: 0,
            value: 50,
            size: 2,
        },
        SdoRequest::Download {
            index: 0x1016,
            sub: 1,
            value: 127 << 16 | 150,
            size: 4,
        },
        SdoRequest::Download {
            index: 0x1A00,
            sub: 1,
            value: 0x6041_0010,
            size: 4,
        },
        SdoRequest::Abort {
            index: 0x6060,
            sub: 0,
            code: 0x0504_0000,
        },
    ] {
        v.push(Message::SdoRequest { node, request });
    }
    for response in [
        SdoResponse::Uploaded {
            index: 0x6061,
            sub: 0,
            value: 3,
            size: 1,
        },
        SdoResponse::Uploaded {
            index: 0x6041,
            sub: 0,
            value: 0x0637,
            size: 2,
        },
        SdoResponse::Uploaded {
            index: 0x1000,
            sub: 0,
            value: 0x0002_0192,
            size: 4,
        },
        SdoResponse::Downloaded {
            index: 0x1A00,
            sub: 2,
        },
        SdoResponse::Abort {
            index: 0x6060,
            sub: 0,
            code: 0x0609_0011,
        },
        SdoResponse::Abort {
            index: 0x1400,
            sub: 1,
            code: 0x0800_0022,
        },
    ] {
        v.push(Message::SdoResponse { node, response });
    }
    v
}

/// EMCY (typical, all zeros, all ones), the TPDOs and RPDO3, extremes included.
fn emcy_and_pdos(node: NodeId) -> Vec<Message> {
    let n = node.get();
    let k = i32::from(n);
    vec![
        Message::Emcy {
            node,
            emcy: Emcy {
                error_code: 0x8130,
                error_register: 0x11,
                manufacturer: [1, 2, 3, 4, n],
            },
        },
        Message::Emcy {
            node,
            emcy: Emcy {
                error_code: 0,
                error_register: 0,
                manufacturer: [0; 5],
            },
        },
        Message::Emcy {
            node,
            emcy: Emcy {
                error_code: 0xFFFF,
                error_register: 0xFF,
                manufacturer: [0xFF; 5],
            },
        },
        Message::Tpdo1 {
            node,
            statusword: 0x0637,
            velocity: -123_456 * k,
        },
        Message::Tpdo1 {
            node,
            statusword: 0xFFFF,
            velocity: i32::MIN,
        },
        Message::Tpdo2 {
            node,
            velocity: 98_765 * k,
        },
        Message::Tpdo2 {
            node,
            velocity: i32::MAX,
        },
        Message::Rpdo3 { node, target: -1 },
        Message::Rpdo3 {
            node,
            target: i32::MIN,
        },
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use embedded_can::StandardId;

    /// `dbc/cia402.dbc`, for its value tables.
    const DBC: &str = include_str!("../../../dbc/cia402.dbc");

    /// The `VAL_` table of a signal of message `id`: (raw, name) pairs.
    fn value_table(id: u16, signal: &str) -> Vec<(u8, String)> {
        let head = format!("VAL_ {id} {signal} ");
        let line = DBC
            .lines()
            .find_map(|l| l.strip_prefix(&head))
            .unwrap_or_else(|| panic!("no {head}"));
        let mut out = Vec::new();
        let mut rest = line.trim_end_matches(';').trim();
        while let Some((raw, tail)) = rest.split_once(" \"") {
            let (name, tail) = tail.split_once('"').expect("closing quote");
            out.push((raw.trim().parse().expect("raw value"), name.to_owned()));
            rest = tail.trim();
        }
        out
    }

    #[test]
    fn value_tables_are_the_rust_enums() {
        let nmt: Vec<_> = (0..=u8::MAX)
            .filter_map(NmtCommand::from_raw)
            .map(|c| (c.raw(), c.as_str().to_owned()))
            .collect();
        assert_eq!(value_table(0x000, "command"), nmt);
        let states: Vec<_> = (0..=u8::MAX)
            .filter_map(NmtState::from_raw)
            .map(|s| (s.raw(), s.as_str().to_owned()))
            .collect();
        for id in [0x701, 0x702, 0x77F] {
            assert_eq!(value_table(id, "state"), states, "{id:#x}");
        }
    }

    fn frame(id: u16, data: &[u8]) -> CanFrame {
        CanFrame::standard(StandardId::new(id).unwrap(), data).unwrap()
    }

    #[test]
    fn sdo_fields_carry_the_wire_command_byte_and_the_decoded_data() {
        // An upload response without a size (0x42): 4 bytes, reported as received.
        let f = CanopenFrame::decode(&frame(0x582, &[0x42, 0, 0x10, 0, 0x92, 1, 2, 0])).unwrap();
        let d = f.fields();
        assert_eq!(d.message, "SDO_RESPONSE_2");
        let json = d.json(frame(0x582, &[]).id(), None);
        assert!(json.contains("\"node\":2,\"size\":4"), "{json}");
        assert!(json.contains("\"command\":66,"), "{json}");
        assert!(json.contains("\"data\":131474}"), "{json}");
        // A 1-byte download with junk in the unused bytes: the data is the one byte.
        let f = CanopenFrame::decode(&frame(0x601, &[0x2F, 0x60, 0x60, 0, 3, 9, 9, 9])).unwrap();
        let json = f.fields().json(frame(0x601, &[]).id(), None);
        assert!(json.contains("\"size\":1"), "{json}");
        assert!(
            json.contains("\"fields\":{\"command\":47,\"index\":24672,\"subindex\":0,\"data\":3}"),
            "{json}"
        );
    }

    #[test]
    fn golden_set_covers_every_kind_for_nodes_1_and_2() {
        let set = golden_set();
        let names: std::collections::BTreeSet<_> = set.iter().map(|f| f.fields().message).collect();
        for base in [
            "EMCY",
            "TPDO1",
            "TPDO2",
            "RPDO1",
            "RPDO3",
            "SDO_REQUEST",
            "SDO_RESPONSE",
            "HEARTBEAT",
        ] {
            for n in [1, 2] {
                assert!(names.contains(&format!("{base}_{n}")), "{base}_{n}");
            }
        }
        for name in ["NMT", "SYNC", "HEARTBEAT_127"] {
            assert!(names.contains(name), "{name}");
        }
        for f in &set {
            let back = CanopenFrame::decode(&f.to_can_frame()).unwrap();
            assert_eq!(back.message, f.message);
            assert_eq!(back.sdo_command, f.sdo_command);
        }
    }
}
