//! The parameter service: the robot as a CiA 301 SDO server on its own node id
//! ([`Controller::param_node`]), for the parameters of [`crate::params`] and its identity.
//!
//! A request (`0x600 + node`) is kept when it arrives and served at the start of the next
//! step: a change is in force for that whole step and after, never for half of one, and a
//! replay of the same frames makes the same change at the same step. The response
//! (`0x580 + node`) goes out with that step's frames. A change goes through
//! [`Param::write`](crate::params::Param::write) (state, type, range, `Config::validate`);
//! new gains are taken up bumplessly by the current loop's integrators; the id that
//! `HEARTBEAT.config_id` sends follows the configuration in force. Object map, classes and
//! abort codes: `docs/protocol.md`, section "Parameters".

use embedded_can::Frame;

use super::{Controller, DriveState, pods};
use crate::config::Config;
use crate::frame::CanFrame;
use crate::params;
use crate::protocol::DecodeError;
use crate::protocol::canopen::{self, Message, NodeId, SdoRequest, SdoResponse, abort_code};
use crate::protocol::robot::{PROTOCOL_VERSION, RobotState};

/// Abort code: the data type's length does not match the request's size.
const WRONG_LENGTH: u32 = 0x0607_0010;
/// Abort code: attempt to write a read-only object.
const READ_ONLY: u32 = 0x0601_0002;

impl Controller {
    /// The node id of the robot's parameter service: requests on `0x600 + id`, responses on
    /// `0x580 + id`.
    #[must_use]
    pub const fn param_node(&self) -> u8 {
        self.param_node
    }

    /// Whether `raw_id` is the parameter service's request id.
    pub(super) fn is_param_request(&self, raw_id: u16) -> bool {
        raw_id == canopen::layout::SDO_REQUEST.id + u16::from(self.param_node)
    }

    /// A frame on the request id: kept for the next step (a request not yet served is
    /// replaced: a client sends its next one only after an answer or its own time-out).
    pub(super) fn on_param_frame<F: Frame>(&mut self, frame: &F) -> Result<(), DecodeError> {
        match canopen::decode(frame)? {
            Message::SdoRequest { request, .. } => {
                self.param_request = Some(request);
                Ok(())
            }
            _ => Err(DecodeError::UnknownId { id: frame.id() }),
        }
    }

    /// Serves the request kept, at a step's start: the response to send, if any (a client's
    /// abort has none).
    pub(super) fn serve_param(&mut self) -> Option<CanFrame> {
        let request = self.param_request.take()?;
        let (index, sub) = request.object();
        let response = match request {
            SdoRequest::Upload { .. } => match self.upload(index, sub) {
                Ok((value, size)) => SdoResponse::Uploaded {
                    index,
                    sub,
                    value,
                    size,
                },
                Err(code) => SdoResponse::Abort { index, sub, code },
            },
            SdoRequest::Download { value, size, .. } => {
                match self.download(index, sub, value, size) {
                    Ok(()) => SdoResponse::Downloaded { index, sub },
                    Err(code) => SdoResponse::Abort { index, sub, code },
                }
            }
            SdoRequest::Abort { .. } => return None,
        };
        let node = NodeId::new(self.param_node)?;
        Some(Message::SdoResponse { node, response }.to_can_frame())
    }

    /// The value and size of object `index`, `sub`.
    fn upload(&self, index: u16, sub: u8) -> Result<(u32, u8), u32> {
        match (index, sub) {
            (0x1000, 0) => return Ok((0, 4)),
            (0x1018, 0) => return Ok((3, 1)),
            (0x1018, 1 | 2) => return Ok((0, 4)),
            (0x1018, 3) => return Ok((u32::from(PROTOCOL_VERSION), 4)),
            (0x1000 | 0x1018, _) => return Err(abort_code::NO_SUBINDEX),
            _ => {}
        }
        let highest = params::highest_sub(index).ok_or(abort_code::NO_OBJECT)?;
        if sub == 0 {
            return Ok((u32::from(highest), 1));
        }
        let p = params::at(index, sub).ok_or(abort_code::NO_SUBINDEX)?;
        let value = p.read(&self.config).map_err(|e| e.abort_code())?;
        Ok((value, p.ty.size()))
    }

    /// Writes `value` (`size` bytes) to object `index`, `sub`, and puts the configuration it
    /// makes in force.
    fn download(&mut self, index: u16, sub: u8, value: u32, size: u8) -> Result<(), u32> {
        let Some(p) = params::at(index, sub) else {
            // An object that reads but is no parameter (the identity, a record's size).
            return Err(self
                .upload(index, sub)
                .map_or_else(|code| code, |_| READ_ONLY));
        };
        if size != p.ty.size() {
            return Err(WRONG_LENGTH);
        }
        let moving = matches!(self.state, RobotState::Enabled | RobotState::WheelTest);
        let new = p
            .write(&self.config, value, moving)
            .map_err(|e| e.abort_code())?;
        self.apply_config(new);
        Ok(())
    }

    /// Puts `new` (validated, and allowed in this state) in force: the id, and what the core
    /// derived from the fields that changed.
    fn apply_config(&mut self, new: Config) {
        let old = self.config;
        if new == old {
            return;
        }
        let (speeds, max) = (self.wheels.map(|w| w.speed), self.current_limit());
        if new.gains != old.gains
            && let DriveState::Dji(d) = &mut self.drive
        {
            d.current
                .retune(&old.gains, &new.gains, self.setpoints.0, speeds, max);
        }
        if new.limits.max_wheel_speed != old.limits.max_wheel_speed
            && let DriveState::Odrive(o) = &mut self.drive
        {
            o.set_max_wheel_speed(new.limits.max_wheel_speed);
        }
        if new.geometry != old.geometry
            && let Ok(kin) = new.kinematics()
        {
            self.kin = kin;
        }
        let (t, was) = (&new.timing, &old.timing);
        if t.odometry_hz != was.odometry_hz {
            self.odom_clock = super::Every::new(t.control_hz / t.odometry_hz);
        }
        if t.status_hz != was.status_hz {
            self.status_clock = super::Every::new(t.control_hz / t.status_hz);
        }
        if new.odometry.pods != old.odometry.pods || new.odometry.source != old.odometry.source {
            self.pods = pods::Pods::new(&new.odometry);
        }
        self.config = new;
        self.config_id = new.id();
    }
}
