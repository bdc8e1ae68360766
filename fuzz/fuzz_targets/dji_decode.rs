//! DJI C620/C610 codec: `dji::decode`, `Feedback::decode`, `CurrentCommand::decode` on any
//! frame, for both ESC models. Never panics; what decodes re-encodes to a frame that decodes
//! to the same message.
#![no_main]

use firmware::protocol::RxErrorCounters;
use firmware::protocol::dji::{self, CurrentCommand, EscModel, Feedback, Message};
use libfuzzer_sys::fuzz_target;
use mecanum_fuzz::{FrameInput, check_frame};

fuzz_target!(|input: FrameInput| {
    let Some(frame) = input.build() else { return };
    let mut errors = RxErrorCounters::new();
    for model in [EscModel::C620, EscModel::C610] {
        let any = dji::decode(&frame, model);
        let cmd = CurrentCommand::decode(&frame, model);
        let fb = Feedback::decode(&frame, model);
        match any {
            Ok(Message::Command(c)) => {
                assert_eq!(cmd, Ok(c));
                let again = c.to_can_frame();
                check_frame(&again);
                assert_eq!(CurrentCommand::decode(&again, model), Ok(c));
                assert_eq!(c.to_frame::<firmware::CanFrame>(), Some(again));
                let _ = c.amps();
            }
            Ok(Message::Feedback(f)) => {
                assert!(cmd.is_err());
                assert_eq!(fb, Ok(f));
                assert!(f.rotor_angle <= 8191);
                let again = f.to_can_frame();
                check_frame(&again);
                assert_eq!(Feedback::decode(&again, model), Ok(f));
                assert!(f.rotor_angle_rad().is_finite());
                assert!(f.rotor_speed_rad_s().is_finite());
                assert!(f.current_amps().is_finite());
            }
            Err(e) => {
                assert!(fb.is_err() || cmd.is_err());
                let _ = std::format!("{e}");
                errors.record(&e);
            }
        }
    }
    let _ = dji::is_dji_id(0);
});
