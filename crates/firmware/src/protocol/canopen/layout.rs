//! The frame layout: the Rust mirror of `dbc/cia402.dbc` (ids are the function codes; a
//! node's frame is `id + node`).

use crate::protocol::wire::{ByteOrder::Little, Field, MessageDef, WireType::*};

/// Largest node id.
pub const NODE_MAX: u8 = 127;

/// NMT node control (id 0x000, master → all).
pub const NMT: MessageDef = MessageDef::new("NMT", 0x000, 2);
/// SYNC (id 0x080, master → all); DLC 0, or 1 with a counter.
pub const SYNC: MessageDef = MessageDef::new("SYNC", 0x080, 0);
/// DLCs accepted for SYNC.
pub const SYNC_DLCS: [u8; 2] = [0, 1];
/// EMCY (0x080 + node).
pub const EMCY: MessageDef = MessageDef::new("EMCY", 0x080, 8);
/// TPDO1 (0x180 + node): statusword and the (first) axis's actual velocity.
pub const TPDO1: MessageDef = MessageDef::new("TPDO1", 0x180, 6);
/// TPDO2 (0x280 + node): the second axis's actual velocity (dual-axis nodes).
pub const TPDO2: MessageDef = MessageDef::new("TPDO2", 0x280, 4);
/// RPDO1 (0x200 + node): controlword and the (first) axis's target velocity.
pub const RPDO1: MessageDef = MessageDef::new("RPDO1", 0x200, 6);
/// RPDO3 (0x400 + node): the second axis's target velocity (dual-axis nodes). RPDO2's
/// predefined id, 0x300 + node, is the robot protocol's block.
pub const RPDO3: MessageDef = MessageDef::new("RPDO3", 0x400, 4);
/// SDO server → client (0x580 + node).
pub const SDO_RESPONSE: MessageDef = MessageDef::new("SDO_RESPONSE", 0x580, 8);
/// SDO client → server (0x600 + node).
pub const SDO_REQUEST: MessageDef = MessageDef::new("SDO_REQUEST", 0x600, 8);
/// Heartbeat and boot-up (0x700 + node).
pub const HEARTBEAT: MessageDef = MessageDef::new("HEARTBEAT", 0x700, 1);

/// `NMT.command` (see [`super::NmtCommand`]).
pub const NMT_COMMAND: Field = Field::int("command", 0, U8, Little);
/// `NMT.node`: 0 addresses every node.
pub const NMT_NODE: Field = Field::int("node", 1, U8, Little).range(0, NODE_MAX as i64);
/// `SYNC.counter` (DLC 1 only).
pub const SYNC_COUNTER: Field = Field::int("counter", 0, U8, Little).range(1, 240);

/// `EMCY.error_code` (CiA 301 table 21; 0 = error reset).
pub const EMCY_ERROR_CODE: Field = Field::int("error_code", 0, U16, Little);
/// `EMCY.error_register` (object 0x1001).
pub const EMCY_ERROR_REGISTER: Field = Field::int("error_register", 2, U8, Little);
/// The first manufacturer-specific byte of EMCY (the DBC's 40-bit `manufacturer` signal
/// is this byte and the next field).
pub const EMCY_MANUFACTURER_LOW: Field = Field::int("manufacturer", 3, U8, Little);
/// Manufacturer-specific bytes 4-7 of EMCY.
pub const EMCY_MANUFACTURER_HIGH: Field = Field::int("manufacturer", 4, U32, Little);

/// `TPDO1.statusword` (object 0x6041).
pub const STATUSWORD: Field = Field::int("statusword", 0, U16, Little);
/// `TPDO1.velocity_actual` (0x606C, sub 0 or 1), drive units.
pub const VELOCITY_ACTUAL: Field = Field::int("velocity_actual", 2, I32, Little);
/// `TPDO2.velocity_actual_2` (0x606C sub 2), drive units.
pub const VELOCITY_ACTUAL_2: Field = Field::int("velocity_actual_2", 0, I32, Little);
/// `RPDO1.controlword` (object 0x6040).
pub const CONTROLWORD: Field = Field::int("controlword", 0, U16, Little);
/// `RPDO1.target_velocity` (0x60FF, sub 0 or 1), drive units.
pub const TARGET_VELOCITY: Field = Field::int("target_velocity", 2, I32, Little);
/// `RPDO3.target_velocity_2` (0x60FF sub 2), drive units.
pub const TARGET_VELOCITY_2: Field = Field::int("target_velocity_2", 0, I32, Little);

/// SDO command byte (client or server command specifier, size and transfer bits).
pub const SDO_COMMAND: Field = Field::int("command", 0, U8, Little);
/// SDO object index.
pub const SDO_INDEX: Field = Field::int("index", 1, U16, Little);
/// SDO object sub-index.
pub const SDO_SUBINDEX: Field = Field::int("subindex", 3, U8, Little);
/// SDO data (expedited, little-endian, unused high bytes zero), or the abort code.
pub const SDO_DATA: Field = Field::int("data", 4, U32, Little);

/// `HEARTBEAT.state` (bit 7 is node guarding's toggle bit, not used by heartbeats).
pub const HEARTBEAT_STATE: Field = Field::int("state", 0, U8, Little);

/// SDO command byte: client "initiate download" (ccs 1), expedited, size given: `0x23`
/// for 4 bytes, `0x27` 3, `0x2B` 2, `0x2F` 1.
pub const SDO_DOWNLOAD: u8 = 0x23;
/// SDO command byte: client "initiate upload" (ccs 2).
pub const SDO_UPLOAD: u8 = 0x40;
/// SDO command byte: server "initiate upload" response, expedited with size (`0x43` 4
/// bytes ... `0x4F` 1); `0x42` (size not given) reads as 4 bytes.
pub const SDO_UPLOADED: u8 = 0x43;
/// SDO command byte: server "initiate download" response (scs 3).
pub const SDO_DOWNLOADED: u8 = 0x60;
/// SDO command byte: abort transfer (either direction).
pub const SDO_ABORT: u8 = 0x80;
