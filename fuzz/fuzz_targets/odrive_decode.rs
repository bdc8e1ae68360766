//! ODrive CAN Simple codec: `odrive::decode`, `Command::decode`, `Feedback::decode` on any
//! frame. Never panics; what decodes re-encodes (for the same node) to a frame that decodes
//! to the same message.
#![no_main]

use firmware::protocol::RxErrorCounters;
use firmware::protocol::odrive::{self, Command, Feedback, Message};
use libfuzzer_sys::fuzz_target;
use mecanum_fuzz::{FrameInput, check_frame};

fuzz_target!(|input: FrameInput| {
    let Some(frame) = input.build() else { return };
    let mut errors = RxErrorCounters::new();
    let any = odrive::decode(&frame);
    let cmd = Command::decode(&frame);
    let fb = Feedback::decode(&frame);
    match any {
        Ok(Message::Command(c)) => {
            assert_eq!(cmd, Ok(c));
            let again = c.msg.to_can_frame(c.node);
            check_frame(&again);
            assert_eq!(Command::decode(&again), Ok(c));
            assert_eq!(Message::Command(c).to_can_frame(), again);
        }
        Ok(Message::Feedback(f)) => {
            assert!(cmd.is_err());
            assert_eq!(fb, Ok(f));
            let again = f.msg.to_can_frame(f.node);
            check_frame(&again);
            assert_eq!(Feedback::decode(&again), Ok(f));
            assert_eq!(Message::Feedback(f).to_can_frame(), again);
        }
        Err(e) => {
            let _ = std::format!("{e}");
            errors.record(&e);
        }
    }
    if let Ok(c) = cmd {
        assert!(c.node.get() <= 63);
    }
});
