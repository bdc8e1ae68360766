//! Golden frames: byte vectors written by hand from the protocol facts (DESIGN.md, the DBC
//! files), not produced by the encoders. Each is decoded and compared with the expected message,
//! and the message is encoded and compared with the bytes.
//!
//! One file a protocol: the robot's own (`robot.rs`), ODrive CAN Simple (`odrive.rs`), DJI
//! C620/C610 (`dji.rs`).

mod dji;
mod odrive;
mod robot;

use embedded_can::{Frame as _, StandardId};
use firmware::CanFrame;

fn sid(raw: u16) -> StandardId {
    StandardId::new(raw).unwrap()
}

fn frame(id: u16, data: &[u8]) -> CanFrame {
    CanFrame::standard(sid(id), data).unwrap()
}

fn assert_close(got: f32, want: f32, tol: f32) {
    assert!(
        (got - want).abs() <= tol,
        "got {got}, want {want} (tolerance {tol})"
    );
}

#[test]
fn generic_frame_conversion() {
    // The encoders build any Frame type; CanFrame converts to itself.
    let f: Option<CanFrame> = firmware::protocol::robot::Command::StatusRequest.to_frame();
    assert_eq!(f, Some(frame(0x303, &[])));
    let g: Option<CanFrame> =
        firmware::protocol::odrive::Command::GetError.to_frame(odrive::node2());
    assert!(g.unwrap().is_remote_frame());
}
