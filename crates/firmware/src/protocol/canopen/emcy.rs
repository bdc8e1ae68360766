//! EMCY (`0x080 + node`): a node's emergency message.

use super::layout;
use crate::protocol::wire::Payload;

/// An emergency message's contents.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct Emcy {
    /// Error code (CiA 301 table 21, CiA 402 for drive errors); 0 = error reset.
    pub error_code: u16,
    /// The error register (object 0x1001).
    pub error_register: u8,
    /// Manufacturer-specific bytes 3-7.
    pub manufacturer: [u8; 5],
}

impl Emcy {
    /// Writes the message's payload.
    pub(super) fn put(&self, p: &mut Payload) {
        layout::EMCY_ERROR_CODE.put_raw(p, self.error_code.into());
        layout::EMCY_ERROR_REGISTER.put_raw(p, self.error_register.into());
        let [m0, m1, m2, m3, m4] = self.manufacturer;
        layout::EMCY_MANUFACTURER_LOW.put_raw(p, m0.into());
        layout::EMCY_MANUFACTURER_HIGH.put_raw(p, u32::from_le_bytes([m1, m2, m3, m4]).into());
    }

    /// Reads a payload.
    pub(super) fn read(p: &Payload) -> Self {
        let low = layout::EMCY_MANUFACTURER_LOW.raw(p) as u8;
        let [a, b, c, d] = (layout::EMCY_MANUFACTURER_HIGH.raw(p) as u32).to_le_bytes();
        Self {
            error_code: layout::EMCY_ERROR_CODE.raw(p) as u16,
            error_register: layout::EMCY_ERROR_REGISTER.raw(p) as u8,
            manufacturer: [low, a, b, c, d],
        }
    }
}
