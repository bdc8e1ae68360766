//! CANopen (CiA 301/402) codec: `canopen::decode` on any frame. Never panics; what decodes
//! re-encodes to a frame on the same id, with the same DLC, that decodes to the same message.
#![no_main]

use embedded_can::Frame;
use firmware::CanFrame;
use firmware::protocol::RxErrorCounters;
use firmware::protocol::canopen::{
    self, DriveState402, Message, SdoRequest, SdoResponse, abort_text, layout,
};
use libfuzzer_sys::fuzz_target;
use mecanum_fuzz::{FrameInput, check_frame};

fuzz_target!(|input: FrameInput| {
    let Some(frame) = input.build() else { return };
    let mut errors = RxErrorCounters::new();
    match canopen::decode(&frame) {
        Ok(m) => {
            let again = m.to_can_frame();
            check_frame(&again);
            assert_eq!(canopen::decode(&again), Ok(m));
            assert_eq!(m.to_frame::<CanFrame>(), Some(again));
            // The id is the message's function code and node, the DLC its own: nothing else
            // on the id decodes.
            assert_eq!(again.id(), frame.id(), "{m:?}");
            assert_eq!(again.dlc(), frame.dlc(), "{m:?}");
            if let Some(node) = m.node() {
                assert!((1..=layout::NODE_MAX).contains(&node.get()));
            }
            match m {
                Message::SdoRequest {
                    request: SdoRequest::Download { value, size, .. },
                    ..
                }
                | Message::SdoResponse {
                    response: SdoResponse::Uploaded { value, size, .. },
                    ..
                } => {
                    assert!((1..=4).contains(&size));
                    assert!(size == 4 || value >> (8 * u32::from(size)) == 0);
                }
                Message::SdoRequest {
                    request: SdoRequest::Abort { code, .. },
                    ..
                }
                | Message::SdoResponse {
                    response: SdoResponse::Abort { code, .. },
                    ..
                } => {
                    let _ = abort_text(code);
                }
                Message::Tpdo1 { statusword, .. } => {
                    let _ = DriveState402::from_statusword(statusword).map(DriveState402::as_str);
                }
                _ => {}
            }
        }
        Err(e) => {
            let _ = std::format!("{e}");
            errors.record(&e);
        }
    }
});
