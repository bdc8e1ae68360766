//! DJI RoboMaster C620 (M3508 motor) and C610 (M2006 motor) ESCs: a current interface, so
//! the firmware runs the wheel velocity loop itself.
//!
//! # The protocol
//!
//! CAN 2.0A at 1 Mbit/s, DLC 8, big-endian ("Motorola") 16-bit fields. The layout is in
//! `dbc/dji_c620.dbc` (C620 scaling).
//!
//! | id | message | dir | fields |
//! |---|---|---|---|
//! | `0x200` | `CURRENT_CMD_1_4` | host → ESC | current setpoints of ESC 1-4, i16 each, bytes 0-1 = ESC 1 |
//! | `0x1FF` | `CURRENT_CMD_5_8` | host → ESC | current setpoints of ESC 5-8 |
//! | `0x200 + n` | `FEEDBACK_n` (n = 1..=8) | ESC → host | `rotor_angle` u16 0..=8191 (one rotor turn), `rotor_speed` i16 rpm, `torque_current` i16, `temperature` u8 °C, byte 7 unused |
//!
//! Currents use the model's scale ([`EscModel`]): C620 raw `-16384..=16384` ↔ -20..20 A,
//! C610 raw `-10000..=10000` ↔ -10..10 A. The ESCs send feedback at 1 kHz. The angle and
//! speed are the rotor's, before the gearbox (M3508 3591/187 ≈ 19.2:1, M2006 36:1); the angle
//! counter wraps at 13 bits.
//!
//! # Encoding and decoding
//!
//! Messages keep the raw integers and the [`EscModel`], with conversions to SI. Decoding
//! rejects a rotor angle above 8191 and currents outside the model's range
//! ([`DecodeError::OutOfRange`]); encoding clamps currents to the model's range.

use core::f32::consts::TAU;

use embedded_can::{Frame, StandardId};

use super::error::DecodeError;
use super::wire::{self, Field, Payload};
use crate::frame::CanFrame;

/// The frame layout: the Rust mirror of `dbc/dji_c620.dbc`.
pub mod layout {
    use crate::protocol::wire::{ByteOrder::Big, Field, MessageDef, WireType::*};

    /// Current command for ESC 1-4.
    pub const CURRENT_CMD_1_4: MessageDef = MessageDef::new("CURRENT_CMD_1_4", 0x200, 8);
    /// Current command for ESC 5-8.
    pub const CURRENT_CMD_5_8: MessageDef = MessageDef::new("CURRENT_CMD_5_8", 0x1FF, 8);
    /// Feedback of ESC n has id `FEEDBACK.id + n`.
    pub const FEEDBACK: MessageDef = MessageDef::new("FEEDBACK", 0x200, 8);

    /// Current setpoints of `CURRENT_CMD_1_4`, ESC 1 first; raw range and scale are set per
    /// model ([`super::EscModel`]) at run time.
    pub const CURRENT_1_4: [Field; 4] = [
        Field::int("current_1", 0, I16, Big),
        Field::int("current_2", 2, I16, Big),
        Field::int("current_3", 4, I16, Big),
        Field::int("current_4", 6, I16, Big),
    ];
    /// Current setpoints of `CURRENT_CMD_5_8`, ESC 5 first.
    pub const CURRENT_5_8: [Field; 4] = [
        Field::int("current_5", 0, I16, Big),
        Field::int("current_6", 2, I16, Big),
        Field::int("current_7", 4, I16, Big),
        Field::int("current_8", 6, I16, Big),
    ];

    /// Rotor angle counts per turn.
    pub const ANGLE_COUNTS: u16 = 8192;
    /// `FEEDBACK.rotor_angle`, counts 0..=8191.
    pub const ROTOR_ANGLE: Field =
        Field::int("rotor_angle", 0, U16, Big).range(0, ANGLE_COUNTS as i64 - 1);
    /// `FEEDBACK.rotor_speed`, rpm.
    pub const ROTOR_SPEED: Field = Field::int("rotor_speed", 2, I16, Big);
    /// `FEEDBACK.torque_current`, model scale.
    pub const TORQUE_CURRENT: Field = Field::int("torque_current", 4, I16, Big);
    /// `FEEDBACK.temperature`, °C.
    pub const TEMPERATURE: Field = Field::int("temperature", 6, U8, Big);
}

/// Which ESC: sets the current scale and raw limit.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub enum EscModel {
    /// C620 (M3508): raw ±16384 ↔ ±20 A.
    C620,
    /// C610 (M2006): raw ±10000 ↔ ±10 A.
    C610,
}

impl EscModel {
    /// Largest raw current magnitude.
    #[must_use]
    #[inline]
    pub const fn raw_limit(self) -> i16 {
        match self {
            Self::C620 => 16384,
            Self::C610 => 10000,
        }
    }

    /// Current at the raw limit, A.
    #[must_use]
    pub const fn max_amps(self) -> f32 {
        match self {
            Self::C620 => 20.0,
            Self::C610 => 10.0,
        }
    }

    /// Amperes per raw unit (C620: 20/16384, exact in binary; C610: 0.001).
    #[must_use]
    pub const fn amps_per_lsb(self) -> f32 {
        match self {
            Self::C620 => 20.0 / 16384.0,
            Self::C610 => 10.0 / 10000.0,
        }
    }

    /// Amperes per raw unit as the DBC factor (f64).
    const fn lsb(self) -> f64 {
        match self {
            Self::C620 => 20.0 / 16384.0,
            Self::C610 => 0.001,
        }
    }

    /// Raw current to amperes.
    #[must_use]
    pub fn raw_to_amps(self, raw: i16) -> f32 {
        (f64::from(raw) * self.lsb()) as f32
    }

    /// Amperes to raw current: rounded, clamped to the model's range, NaN gives 0.
    ///
    /// The same result as [`wire::to_raw`] with the bounds `±raw_limit` (the nearest raw
    /// value in f64, ties to even), worked out in 32-bit integers and without branches.
    #[must_use]
    #[inline]
    pub fn amps_to_raw(self, amps: f32) -> i16 {
        let lim = i32::from(self.raw_limit());
        let r = f64::from(amps) / self.lsb();
        // Truncation toward zero, exact inside the range; NaN gives 0 (and so does the
        // rounding below, whose comparisons are all false). Outside the range the rounded
        // value is not used, so the wrapping there does not matter.
        let t = r as i32;
        let frac = r - f64::from(t);
        let odd = t & 1 != 0;
        let up = (frac > 0.5) | ((frac == 0.5) & odd);
        let down = (frac < -0.5) | ((frac == -0.5) & odd);
        let rounded = t.wrapping_add(i32::from(up)).wrapping_sub(i32::from(down));
        let n = if r <= f64::from(-lim) {
            -lim
        } else if r >= f64::from(lim) {
            lim
        } else {
            rounded
        };
        // |n| <= raw_limit <= 16384.
        n as i16
    }

    /// The raw range as a field of the given layout row.
    const fn limit(self, field: Field) -> Field {
        let lim = self.raw_limit() as i64;
        field.range(-lim, lim).scaled(self.lsb())
    }
}

u8_id!(
    /// A DJI ESC id, `1..=8` (the number set on the ESC).
    EscId(1..=8)
);

impl EscId {
    /// The command frame that carries this ESC's current.
    #[must_use]
    #[inline]
    pub const fn group(self) -> EscGroup {
        if self.0 <= 4 {
            EscGroup::Esc1To4
        } else {
            EscGroup::Esc5To8
        }
    }

    /// Slot 0..=3 of this ESC in its command frame.
    #[must_use]
    #[inline]
    pub const fn slot(self) -> usize {
        ((self.0 - 1) % 4) as usize
    }

    /// The id of this ESC's feedback frame, `0x200 + id`.
    #[must_use]
    pub const fn feedback_id(self) -> StandardId {
        sid(layout::FEEDBACK.id + self.0 as u16)
    }
}

/// The two current command frames.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub enum EscGroup {
    /// `0x200`: ESC 1-4.
    Esc1To4,
    /// `0x1FF`: ESC 5-8.
    Esc5To8,
}

impl EscGroup {
    /// The group's layout row.
    #[must_use]
    pub const fn def(self) -> wire::MessageDef {
        match self {
            Self::Esc1To4 => layout::CURRENT_CMD_1_4,
            Self::Esc5To8 => layout::CURRENT_CMD_5_8,
        }
    }

    /// The group's current fields, ESC 1 (or 5) first.
    #[must_use]
    pub const fn fields(self) -> &'static [Field; 4] {
        match self {
            Self::Esc1To4 => &layout::CURRENT_1_4,
            Self::Esc5To8 => &layout::CURRENT_5_8,
        }
    }

    /// The first ESC id of the group (1 or 5).
    #[must_use]
    pub const fn first_esc(self) -> u8 {
        match self {
            Self::Esc1To4 => 1,
            Self::Esc5To8 => 5,
        }
    }
}

const fn sid(raw: u16) -> StandardId {
    // Every id of the layout table is below 0x800.
    match StandardId::new(raw) {
        Some(id) => id,
        None => StandardId::ZERO,
    }
}

/// A current command to four ESCs (one frame).
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct CurrentCommand {
    /// ESC model (scale and limit).
    pub model: EscModel,
    /// Which four ESCs.
    pub group: EscGroup,
    /// Raw current setpoints, ESC 1 (or 5) first; encoding clamps them to the model's range.
    pub raw: [i16; 4],
}

impl CurrentCommand {
    /// All four currents zero.
    #[must_use]
    pub const fn zero(model: EscModel, group: EscGroup) -> Self {
        Self {
            model,
            group,
            raw: [0; 4],
        }
    }

    /// From currents in amperes (rounded, clamped; NaN gives 0).
    #[must_use]
    pub fn from_amps(model: EscModel, group: EscGroup, amps: [f32; 4]) -> Self {
        Self {
            model,
            group,
            raw: amps.map(|a| model.amps_to_raw(a)),
        }
    }

    /// The currents in amperes.
    #[must_use]
    pub fn amps(&self) -> [f32; 4] {
        self.raw.map(|r| self.model.raw_to_amps(r))
    }

    /// Decodes a command frame for `model`.
    ///
    /// # Errors
    /// `UnknownId` for ids other than 0x200/0x1FF; `OutOfRange` for currents beyond the model's
    /// limit; see [`DecodeError`].
    pub fn decode<F: Frame>(frame: &F, model: EscModel) -> Result<Self, DecodeError> {
        let id = wire::standard_id(frame)?;
        let group = if id == layout::CURRENT_CMD_1_4.id {
            EscGroup::Esc1To4
        } else if id == layout::CURRENT_CMD_5_8.id {
            EscGroup::Esc5To8
        } else {
            return Err(wire::unknown(frame));
        };
        let p = wire::data_payload(frame, id, &[group.def().dlc])?;
        let mut raw = [0i16; 4];
        for (out, field) in raw.iter_mut().zip(group.fields().iter()) {
            // Within the model's limit, hence within i16.
            *out = model.limit(*field).checked(&p)? as i16;
        }
        Ok(Self { model, group, raw })
    }

    /// Encodes into a [`CanFrame`], clamping currents to the model's range.
    #[must_use]
    #[inline]
    pub fn to_can_frame(&self) -> CanFrame {
        // One arm per group, so that each sees its layout rows as constants.
        match self.group {
            EscGroup::Esc1To4 => self.encode(layout::CURRENT_CMD_1_4, &layout::CURRENT_1_4),
            EscGroup::Esc5To8 => self.encode(layout::CURRENT_CMD_5_8, &layout::CURRENT_5_8),
        }
    }

    #[inline]
    fn encode(&self, def: wire::MessageDef, fields: &[Field; 4]) -> CanFrame {
        let mut p = Payload::new();
        for (raw, field) in self.raw.iter().zip(fields) {
            self.model.limit(*field).put_raw(&mut p, i64::from(*raw));
        }
        CanFrame::from_buffer(sid(def.id), p.0, def.dlc)
    }

    /// Encodes into any [`Frame`] type; `None` only if that type rejects a valid frame.
    #[must_use]
    pub fn to_frame<F: Frame>(&self) -> Option<F> {
        self.to_can_frame().convert()
    }
}

/// One ESC's feedback frame, raw fields plus conversions.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct Feedback {
    /// ESC model (scale of the current).
    pub model: EscModel,
    /// Which ESC.
    pub esc: EscId,
    /// Rotor angle, counts 0..=8191 per rotor turn.
    pub rotor_angle: u16,
    /// Rotor speed, rpm.
    pub rotor_speed_rpm: i16,
    /// Measured torque current, raw (model scale).
    pub torque_current: i16,
    /// Temperature, °C.
    pub temperature_c: u8,
}

impl Feedback {
    /// Rotor angle, rad in `0..2π`.
    #[must_use]
    pub fn rotor_angle_rad(&self) -> f32 {
        f32::from(self.rotor_angle) * (TAU / f32::from(layout::ANGLE_COUNTS))
    }

    /// Rotor speed, rad/s (before the gearbox).
    #[must_use]
    pub fn rotor_speed_rad_s(&self) -> f32 {
        f32::from(self.rotor_speed_rpm) * (TAU / 60.0)
    }

    /// Torque current, A.
    #[must_use]
    pub fn current_amps(&self) -> f32 {
        self.model.raw_to_amps(self.torque_current)
    }

    /// Decodes a feedback frame (ids 0x201..=0x208) for `model`.
    ///
    /// # Errors
    /// `UnknownId` for other ids; `OutOfRange` for a rotor angle above 8191 or a current beyond
    /// the model's limit; see [`DecodeError`].
    #[inline]
    pub fn decode<F: Frame>(frame: &F, model: EscModel) -> Result<Self, DecodeError> {
        let id = wire::standard_id(frame)?;
        let esc = id
            .checked_sub(layout::FEEDBACK.id)
            .and_then(|n| u8::try_from(n).ok())
            .and_then(EscId::new)
            .ok_or_else(|| wire::unknown(frame))?;
        let p = wire::data_payload(frame, id, &[layout::FEEDBACK.dlc])?;
        Ok(Self {
            model,
            esc,
            // Range-checked to 0..=8191.
            rotor_angle: layout::ROTOR_ANGLE.checked(&p)? as u16,
            rotor_speed_rpm: layout::ROTOR_SPEED.raw(&p) as i16,
            torque_current: model.limit(layout::TORQUE_CURRENT).checked(&p)? as i16,
            temperature_c: layout::TEMPERATURE.raw(&p) as u8,
        })
    }

    /// Encodes into a [`CanFrame`] (what a simulated ESC sends); the angle is reduced modulo
    /// 8192 and the current clamped to the model's range.
    #[must_use]
    pub fn to_can_frame(&self) -> CanFrame {
        let mut p = Payload::new();
        layout::ROTOR_ANGLE.put_raw(&mut p, i64::from(self.rotor_angle % layout::ANGLE_COUNTS));
        layout::ROTOR_SPEED.put_raw(&mut p, i64::from(self.rotor_speed_rpm));
        self.model
            .limit(layout::TORQUE_CURRENT)
            .put_raw(&mut p, i64::from(self.torque_current));
        layout::TEMPERATURE.put_raw(&mut p, i64::from(self.temperature_c));
        CanFrame::from_buffer(self.esc.feedback_id(), p.0, layout::FEEDBACK.dlc)
    }

    /// Encodes into any [`Frame`] type; `None` only if that type rejects a valid frame.
    #[must_use]
    pub fn to_frame<F: Frame>(&self) -> Option<F> {
        self.to_can_frame().convert()
    }
}

/// Any message of the protocol.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Message {
    /// Host → ESCs.
    Command(CurrentCommand),
    /// ESC → host.
    Feedback(Feedback),
}

impl Message {
    /// Encodes into a [`CanFrame`].
    #[must_use]
    pub fn to_can_frame(&self) -> CanFrame {
        match self {
            Self::Command(c) => c.to_can_frame(),
            Self::Feedback(f) => f.to_can_frame(),
        }
    }
}

/// Whether a raw 11-bit id is one of this protocol's (`0x1FF..=0x208`).
#[must_use]
pub const fn is_dji_id(id: u16) -> bool {
    id >= layout::CURRENT_CMD_5_8.id && id <= layout::FEEDBACK.id + 8
}

/// Decodes any frame of the protocol for `model`, in either direction.
///
/// # Errors
/// See [`DecodeError`].
pub fn decode<F: Frame>(frame: &F, model: EscModel) -> Result<Message, DecodeError> {
    match CurrentCommand::decode(frame, model) {
        Err(DecodeError::UnknownId { .. }) => Feedback::decode(frame, model).map(Message::Feedback),
        other => other.map(Message::Command),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `amps_to_raw` is `wire::to_raw` with the model's bounds, for every kind of input:
    /// a dense sweep through and beyond the range, exact ties, and non-finite values.
    #[test]
    fn amps_to_raw_is_to_raw_with_the_model_bounds() {
        for model in [EscModel::C620, EscModel::C610] {
            let lim = i64::from(model.raw_limit());
            let reference = |a: f32| wire::to_raw(a, model.lsb(), -lim, lim) as i16;
            let check = |a: f32| assert_eq!(model.amps_to_raw(a), reference(a), "{a}");
            // Quarter-LSB steps over 1.25 times the range, so ties and their neighbours.
            let lsb = model.lsb();
            for k in -82_000i32..=82_000 {
                let a = (f64::from(k) * lsb / 4.0) as f32;
                check(a);
                check(f32::from_bits(a.to_bits() + 1));
                check(f32::from_bits(a.to_bits().wrapping_sub(1)));
            }
            for a in [
                0.0,
                -0.0,
                f32::NAN,
                f32::INFINITY,
                f32::NEG_INFINITY,
                f32::MAX,
                f32::MIN,
                f32::MIN_POSITIVE,
                1e-40,
                3e9,
                -3e9,
            ] {
                check(a);
            }
        }
    }
}
