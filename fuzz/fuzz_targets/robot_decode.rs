//! The robot protocol: `robot::decode`, `Command::decode`, `Telemetry::decode` on any frame.
//! Never panics; what decodes re-encodes to a frame that decodes to the same message.
#![no_main]

use firmware::protocol::RxErrorCounters;
use firmware::protocol::robot::{self, Command, Message, Telemetry};
use libfuzzer_sys::fuzz_target;
use mecanum_fuzz::{FrameInput, check_frame};

fuzz_target!(|input: FrameInput| {
    let Some(frame) = input.build() else { return };
    let mut errors = RxErrorCounters::new();
    let any = robot::decode(&frame);
    let cmd = Command::decode(&frame);
    let tel = Telemetry::decode(&frame);
    match any {
        Ok(Message::Command(c)) => {
            assert_eq!(cmd, Ok(c));
            let again = c.to_can_frame();
            check_frame(&again);
            assert_eq!(Command::decode(&again), Ok(c));
        }
        Ok(Message::Telemetry(t)) => {
            assert!(cmd.is_err());
            assert_eq!(tel, Ok(t));
            let again = t.to_can_frame();
            check_frame(&again);
            assert_eq!(Telemetry::decode(&again), Ok(t));
        }
        Err(e) => {
            let _ = std::format!("{e}");
            errors.record(&e);
        }
    }
    if cmd.is_ok() || tel.is_ok() {
        let embedded_can::Id::Standard(id) = embedded_can::Frame::id(&frame) else {
            panic!("an extended id decoded");
        };
        assert!(robot::in_block(id.as_raw()));
    }
});
