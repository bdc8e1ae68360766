//! ODrive CAN Simple (`dbc/odrive_cansimple.dbc`), node 2: ids `0x40 | cmd`.

use firmware::CanFrame;
use firmware::protocol::DecodeError;
use firmware::protocol::odrive::{
    self, Addressed, AxisState, ControlMode, InputMode, NodeId, split_id,
};

use crate::{frame, sid};

pub fn node2() -> NodeId {
    NodeId::new(2).unwrap()
}

fn odrive_cmd(f: &CanFrame) -> Result<odrive::Command, DecodeError> {
    odrive::Command::decode(f).map(|a| {
        assert_eq!(a.node, node2());
        a.msg
    })
}

fn odrive_fb(f: &CanFrame) -> Result<odrive::Feedback, DecodeError> {
    odrive::Feedback::decode(f).map(|a| {
        assert_eq!(a.node, node2());
        a.msg
    })
}

#[test]
fn node_id_range_and_split() {
    assert_eq!(NodeId::new(63).map(NodeId::get), Some(63));
    assert_eq!(NodeId::new(64), None);
    assert_eq!(node2().can_id(0x0D), sid(0x4D));
    assert_eq!(split_id(sid(0x7FF)), (NodeId::new(63).unwrap(), 31));
}

#[test]
fn odrive_heartbeat() {
    // Axis_Error 0x01000000 (watchdog), state 8, procedure result 0, trajectory done.
    let f = frame(0x41, &[0x00, 0x00, 0x00, 0x01, 0x08, 0x00, 0x01, 0x00]);
    let hb = odrive::Heartbeat {
        axis_error: 0x0100_0000,
        axis_state: AxisState::ClosedLoopControl,
        procedure_result: 0,
        trajectory_done: true,
    };
    assert_eq!(odrive_fb(&f), Ok(odrive::Feedback::Heartbeat(hb)));
    assert_eq!(odrive::Feedback::Heartbeat(hb).to_can_frame(node2()), f);
    assert_eq!(
        odrive_fb(&frame(0x41, &[0, 0, 0, 0, 15, 0, 0, 0])),
        Err(DecodeError::OutOfRange {
            field: "Axis_State",
            value: 15
        })
    );
}

#[test]
fn odrive_estop_and_get_error() {
    let f = frame(0x42, &[]);
    assert_eq!(odrive_cmd(&f), Ok(odrive::Command::Estop));
    assert_eq!(odrive::Command::Estop.to_can_frame(node2()), f);

    let rtr = CanFrame::remote(sid(0x43), 8);
    assert_eq!(odrive_cmd(&rtr), Ok(odrive::Command::GetError));
    assert_eq!(odrive::Command::GetError.to_can_frame(node2()), rtr);
    // Any DLC of the request is accepted, and so is an empty data frame (ODrive docs).
    assert_eq!(
        odrive_cmd(&CanFrame::remote(sid(0x43), 0)),
        Ok(odrive::Command::GetError)
    );
    assert_eq!(odrive_cmd(&frame(0x43, &[])), Ok(odrive::Command::GetError));
    // The other messages the core reads can be requested the same way; no other.
    let hb = CanFrame::remote(sid(0x41), 8);
    assert_eq!(odrive_cmd(&hb), Ok(odrive::Command::GetHeartbeat));
    assert_eq!(odrive::Command::GetHeartbeat.to_can_frame(node2()), hb);
    let est = CanFrame::remote(sid(0x49), 8);
    assert_eq!(odrive_cmd(&est), Ok(odrive::Command::GetEncoderEstimates));
    assert_eq!(
        odrive::Command::GetEncoderEstimates.to_can_frame(node2()),
        est
    );
    assert_eq!(
        odrive_cmd(&frame(0x49, &[])),
        Ok(odrive::Command::GetEncoderEstimates)
    );
    assert!(odrive::is_request(&est) && !odrive::is_request(&frame(0x49, &[0; 8])));
    assert_eq!(
        odrive_cmd(&CanFrame::remote(sid(0x4D), 8)),
        Err(DecodeError::Remote { id: 0x4D })
    );

    let f = frame(0x43, &[0x01, 0x00, 0x00, 0x00, 0x40, 0x00, 0x00, 0x00]);
    let e = odrive::Feedback::Error {
        active_errors: 1,
        disarm_reason: 0x40,
    };
    assert_eq!(odrive_fb(&f), Ok(e));
    assert_eq!(e.to_can_frame(node2()), f);
    // The response direction rejects the RTR as a data message.
    assert_eq!(odrive_fb(&rtr), Err(DecodeError::Remote { id: 0x43 }));
}

#[test]
fn odrive_set_axis_state() {
    let f = frame(0x47, &[0x08, 0, 0, 0, 0, 0, 0, 0]);
    let c = odrive::Command::SetAxisState(AxisState::ClosedLoopControl);
    assert_eq!(odrive_cmd(&f), Ok(c));
    assert_eq!(c.to_can_frame(node2()), f);
    assert_eq!(
        odrive_cmd(&frame(0x47, &[0x01, 0, 0, 0, 0, 0, 0, 0])),
        Ok(odrive::Command::SetAxisState(AxisState::Idle))
    );
    // DLC 8 as in the official DBC; the 4-byte form is rejected.
    assert_eq!(
        odrive_cmd(&frame(0x47, &[0x08, 0, 0, 0])),
        Err(DecodeError::WrongDlc {
            id: 0x47,
            expected: 8,
            got: 4
        })
    );
    assert_eq!(
        odrive_cmd(&frame(0x47, &[0, 0, 0, 1, 0, 0, 0, 0])),
        Err(DecodeError::OutOfRange {
            field: "Axis_Requested_State",
            value: 0x0100_0000
        })
    );
}

#[test]
fn odrive_encoder_estimates() {
    // pos 1.0 = 0x3F800000, vel -2.5 = 0xC0200000.
    let f = frame(0x49, &[0x00, 0x00, 0x80, 0x3F, 0x00, 0x00, 0x20, 0xC0]);
    let e = odrive::Feedback::EncoderEstimates {
        pos: 1.0,
        vel: -2.5,
    };
    assert_eq!(odrive_fb(&f), Ok(e));
    assert_eq!(e.to_can_frame(node2()), f);
    // +inf = 0x7F800000 in vel.
    assert_eq!(
        odrive_fb(&frame(0x49, &[0, 0, 0x80, 0x3F, 0x00, 0x00, 0x80, 0x7F])),
        Err(DecodeError::NonFinite {
            field: "Vel_Estimate",
            bits: 0x7F80_0000
        })
    );
}

#[test]
fn odrive_set_controller_mode() {
    let f = frame(0x4B, &[0x02, 0, 0, 0, 0x01, 0, 0, 0]);
    let c = odrive::Command::SetControllerMode {
        control_mode: ControlMode::VelocityControl,
        input_mode: InputMode::Passthrough,
    };
    assert_eq!(odrive_cmd(&f), Ok(c));
    assert_eq!(c.to_can_frame(node2()), f);
    assert_eq!(
        odrive_cmd(&frame(0x4B, &[0x02, 0, 0, 0, 0x02, 0, 0, 0])),
        Ok(odrive::Command::SetControllerMode {
            control_mode: ControlMode::VelocityControl,
            input_mode: InputMode::VelRamp,
        })
    );
    assert_eq!(
        odrive_cmd(&frame(0x4B, &[0x04, 0, 0, 0, 0x01, 0, 0, 0])),
        Err(DecodeError::OutOfRange {
            field: "Control_Mode",
            value: 4
        })
    );
    assert_eq!(
        odrive_cmd(&frame(0x4B, &[0x02, 0, 0, 0, 0x09, 0, 0, 0])),
        Err(DecodeError::OutOfRange {
            field: "Input_Mode",
            value: 9
        })
    );
}

#[test]
fn odrive_set_input_vel() {
    // vel 10.0 = 0x41200000, torque_ff 0.5 = 0x3F000000.
    let f = frame(0x4D, &[0x00, 0x00, 0x20, 0x41, 0x00, 0x00, 0x00, 0x3F]);
    let c = odrive::Command::SetInputVel {
        vel: 10.0,
        torque_ff: 0.5,
    };
    assert_eq!(odrive_cmd(&f), Ok(c));
    assert_eq!(c.to_can_frame(node2()), f);
    // A NaN (0x7FC00000) is rejected.
    assert_eq!(
        odrive_cmd(&frame(0x4D, &[0x00, 0x00, 0xC0, 0x7F, 0, 0, 0, 0])),
        Err(DecodeError::NonFinite {
            field: "Input_Vel",
            bits: 0x7FC0_0000
        })
    );
    assert_eq!(
        odrive_cmd(&frame(0x4D, &[0, 0, 0, 0, 0x00, 0x00, 0x80, 0xFF])),
        Err(DecodeError::NonFinite {
            field: "Input_Torque_FF",
            bits: 0xFF80_0000
        })
    );
    // Encoding never puts NaN on the wire.
    let nan = odrive::Command::SetInputVel {
        vel: f32::NAN,
        torque_ff: f32::INFINITY,
    };
    let Ok(odrive::Command::SetInputVel { vel, torque_ff }) =
        odrive_cmd(&nan.to_can_frame(node2()))
    else {
        panic!()
    };
    assert_eq!((vel, torque_ff), (0.0, f32::MAX));
}

#[test]
fn odrive_clear_errors() {
    let f = frame(0x58, &[0x01]);
    let c = odrive::Command::ClearErrors { identify: true };
    assert_eq!(odrive_cmd(&f), Ok(c));
    assert_eq!(c.to_can_frame(node2()), f);
    assert_eq!(
        odrive_cmd(&frame(0x58, &[])),
        Ok(odrive::Command::ClearErrors { identify: false })
    );
    assert_eq!(
        odrive_cmd(&frame(0x58, &[0, 0])),
        Err(DecodeError::WrongDlc {
            id: 0x58,
            expected: 1,
            got: 2
        })
    );
}

#[test]
fn odrive_unknown_commands() {
    // Get_Version (0x00), Set_Input_Pos (0x0C) and 0x1F are not implemented here.
    for id in [0x40, 0x4C, 0x5F] {
        assert!(matches!(
            odrive::decode(&frame(id, &[0; 8])),
            Err(DecodeError::UnknownId { .. })
        ));
    }
    let m = odrive::decode(&frame(0x4D, &[0; 8])).unwrap();
    assert_eq!(
        m,
        odrive::Message::Command(Addressed {
            node: node2(),
            msg: odrive::Command::SetInputVel {
                vel: 0.0,
                torque_ff: 0.0
            }
        })
    );
}
