//! Shared input types of the fuzz targets: frames built from fuzz bytes through every
//! constructor `firmware::CanFrame` has, and the checks every decoded frame must pass.

use arbitrary::Arbitrary;
use embedded_can::{ExtendedId, Frame, StandardId};
use firmware::CanFrame;

/// A frame as the fuzzer describes it. Standard ids are taken modulo 0x800 so that every id
/// in 0..=0x7FF is reachable; DLCs are passed raw (values above 8 included) to check that the
/// constructors cap or refuse them.
#[derive(Arbitrary, Debug, Clone)]
pub enum FrameInput {
    /// `CanFrame::from_buffer(id, buffer, dlc)` (dlc capped at 8 by the constructor).
    Buffer { id: u16, buffer: [u8; 8], dlc: u8 },
    /// `CanFrame::standard(id, data)`: `None` for more than 8 bytes.
    Standard { id: u16, data: Vec<u8> },
    /// `CanFrame::remote(id, dlc)` (dlc capped at 8).
    Remote { id: u16, dlc: u8 },
    /// `Frame::new` / `Frame::new_remote` with a 29-bit id.
    Extended {
        id: u32,
        data: Vec<u8>,
        remote: bool,
        dlc: u8,
    },
}

fn sid(raw: u16) -> StandardId {
    StandardId::new(raw & 0x7FF).expect("masked to 11 bits")
}

impl FrameInput {
    /// The frame, if the constructor accepts the input.
    #[must_use]
    pub fn build(&self) -> Option<CanFrame> {
        let frame = match self {
            Self::Buffer { id, buffer, dlc } => {
                Some(CanFrame::from_buffer(sid(*id), *buffer, *dlc))
            }
            Self::Standard { id, data } => {
                let f = CanFrame::standard(sid(*id), data);
                assert_eq!(
                    f.is_some(),
                    data.len() <= 8,
                    "standard() accepts iff len <= 8"
                );
                f
            }
            Self::Remote { id, dlc } => Some(CanFrame::remote(sid(*id), *dlc)),
            Self::Extended {
                id,
                data,
                remote,
                dlc,
            } => {
                let id = ExtendedId::new(id & 0x1FFF_FFFF).expect("masked to 29 bits");
                if *remote {
                    <CanFrame as Frame>::new_remote(id, usize::from(*dlc))
                } else {
                    <CanFrame as Frame>::new(id, data)
                }
            }
        }?;
        check_frame(&frame);
        Some(frame)
    }
}

/// The invariants `CanFrame` documents: dlc <= 8, data length = dlc for a data frame and 0 for
/// a remote one, bytes past dlc zero; `from_frame`/`convert` are the identity.
pub fn check_frame(f: &CanFrame) {
    assert!(f.dlc() <= 8);
    if f.is_remote_frame() {
        assert!(f.data().is_empty());
        assert_eq!(f.buffer(), [0; 8]);
    } else {
        assert_eq!(f.data().len(), f.dlc());
        assert!(f.buffer()[f.dlc()..].iter().all(|&b| b == 0));
    }
    assert_eq!(CanFrame::from_frame(f), Some(*f));
    assert_eq!(f.convert::<CanFrame>(), Some(*f));
}
