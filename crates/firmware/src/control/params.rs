//! The parameter service: the robot as a CiA 301 SDO server on its own node id
//! ([`Controller::param_node`]), for the parameters of [`crate::params`] and its identity.
//!
//! A request (`0x600 + node`) is kept when it arrives and served at the start of the next
//! step: a change is in force for that whole step and after, never for half of one, and a
//! replay of the same frames makes the same change at the same step. The response
//! (`0x580 + node`) goes out with that step's frames. A change goes through
//! [`Param::write`](crate::params::Param::write) (state, type, range, `Config::validate`);
//! new gains are taken up bumplessly by the current loop's integrators; the id that
//! `HEARTBEAT.config_id` sends follows the configuration in force. A save (`0x1010:01`) or a
//! restore of the built-in set (`0x1011:01`) is handed to the edge, which stores it
//! ([`Controller::take_save`]) and reports the end ([`Controller::on_saved`], a logged input);
//! the response goes out at the step after. Object map, classes and abort codes:
//! `docs/protocol.md`, section "Parameters".

use embedded_can::Frame;

use super::{Controller, DriveState, pods};
use crate::config::Config;
use crate::frame::CanFrame;
use crate::params;
use crate::protocol::DecodeError;
use crate::protocol::canopen::{self, Message, NodeId, SdoRequest, SdoResponse, abort_code};
use crate::protocol::robot::{PROTOCOL_VERSION, RobotState};

/// `0x1010` Store parameters: sub-index 1 ("all") saves the configuration in force.
pub const STORE: u16 = 0x1010;
/// `0x1011` Restore default parameters: sub-index 1 puts the built-in configuration in force
/// and saves it.
pub const RESTORE: u16 = 0x1011;
/// The signature a save writes to `0x1010:01`: `save`, little-endian (CiA 301).
pub const SAVE_SIGNATURE: u32 = u32::from_le_bytes(*b"save");
/// The signature a restore writes to `0x1011:01`: `load`, little-endian (CiA 301).
pub const LOAD_SIGNATURE: u32 = u32::from_le_bytes(*b"load");
/// `0x2100` The configurations' ids and the saved set, read-only ([`INFO`]).
pub const INFO_INDEX: u16 = 0x2100;
/// The entries of [`INFO_INDEX`] (all `UNSIGNED32`), by sub-index from 1: name and meaning.
pub const INFO: [(&str, &str); 4] = [
    (
        "info.running_id",
        "Id of the configuration in force (HEARTBEAT.config_id)",
    ),
    (
        "info.builtin_id",
        "Id of the image's (or configuration file's) built-in configuration",
    ),
    (
        "info.saved_id",
        "Id of the configuration a restart runs: the saved set, else the built-in one",
    ),
    (
        "info.saved_seq",
        "Sequence number of the saved set's record; 0: none saved",
    ),
];

/// How a save handed to the edge ended: the edge's report to the core, logged as an input.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SaveOutcome {
    /// Stored as record number `seq`.
    Stored {
        /// The record's sequence number.
        seq: u32,
    },
    /// Not stored: the CiA 301 abort code the response carries
    /// ([`SaveError::abort_code`](crate::storage::SaveError::abort_code)).
    Failed {
        /// The abort code.
        code: u32,
    },
}

impl From<Result<u32, crate::storage::SaveError>> for SaveOutcome {
    fn from(result: Result<u32, crate::storage::SaveError>) -> Self {
        match result {
            Ok(seq) => Self::Stored { seq },
            Err(e) => Self::Failed {
                code: e.abort_code(),
            },
        }
    }
}

/// A save or restore (its object, [`STORE`] or [`RESTORE`]) not yet answered.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub(super) enum Saving {
    /// None.
    #[default]
    Idle,
    /// Served at this step; the edge takes it after the step.
    Asked {
        /// The object written.
        index: u16,
    },
    /// The edge is storing the configuration with id `id`.
    Writing {
        /// The object written.
        index: u16,
        /// The id of the configuration being stored.
        id: u16,
    },
    /// Ended; answered at the next step.
    Ended {
        /// The object written.
        index: u16,
        /// How.
        outcome: SaveOutcome,
    },
}

/// What the parameter service knows of the saved set (object [`INFO_INDEX`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct SavedSet {
    /// The built-in configuration's id.
    pub builtin_id: u16,
    /// The id of the set a restart runs.
    pub id: u16,
    /// Its record's number; 0 for the built-in set.
    pub seq: u32,
}

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

    /// The configuration a save or restore served at the last step asks the edge to store
    /// (its built-in id is [`builtin_id`](Self::builtin_id)), once. The edge calls this after
    /// every step and reports the end with [`on_saved`](Self::on_saved).
    pub fn take_save(&mut self) -> Option<Config> {
        let Saving::Asked { index } = self.saving else {
            return None;
        };
        self.saving = Saving::Writing {
            index,
            id: self.config_id,
        };
        Some(self.config)
    }

    /// The edge's report that the save it took ended (a logged input: replay calls it at the
    /// same point). Answered at the next step. Ignored when no save is being stored.
    pub fn on_saved(&mut self, outcome: SaveOutcome) {
        let Saving::Writing { index, id } = self.saving else {
            return;
        };
        if let SaveOutcome::Stored { seq } = outcome {
            self.saved = SavedSet {
                id,
                seq,
                ..self.saved
            };
        }
        self.saving = Saving::Ended { index, outcome };
    }

    /// The built-in configuration (the image's, or the configuration file's): what a restore
    /// puts back.
    #[must_use]
    pub const fn builtin(&self) -> &Config {
        &self.builtin
    }

    /// The number of the saved record a restart runs (0: none saved, the built-in set).
    #[must_use]
    pub const fn saved_seq(&self) -> u32 {
        self.saved.seq
    }

    /// The id of the built-in configuration (the image's, or the configuration file's): what a
    /// saved record is saved under.
    #[must_use]
    pub const fn builtin_id(&self) -> u16 {
        self.saved.builtin_id
    }

    /// Starts with `saved` in force, found in storage as record `seq`, instead of the built-in
    /// configuration this controller was made with. For the edge's boot, before any step.
    ///
    /// # Errors
    /// The first [`ConfigError`](crate::config::ConfigError) of `saved`'s validation.
    pub fn with_saved(self, saved: &Config, seq: u32) -> Result<Self, super::Error> {
        let builtin = self.builtin;
        let mut ctl = Self::new(saved)?;
        ctl.builtin = builtin;
        ctl.saved = SavedSet {
            builtin_id: builtin.id(),
            id: saved.id(),
            seq,
        };
        Ok(ctl)
    }

    /// Serves the request kept, or answers the save that ended, at a step's start: the
    /// response to send, if any (a client's abort has none). One a step: a request waits
    /// for the step after an ended save's answer.
    pub(super) fn serve_param(&mut self) -> Option<CanFrame> {
        let response = if let Saving::Ended { index, outcome } = self.saving {
            self.saving = Saving::Idle;
            match outcome {
                SaveOutcome::Stored { .. } => SdoResponse::Downloaded { index, sub: 1 },
                SaveOutcome::Failed { code } => SdoResponse::Abort {
                    index,
                    sub: 1,
                    code,
                },
            }
        } else {
            self.serve_request()?
        };
        let node = NodeId::new(self.param_node)?;
        Some(Message::SdoResponse { node, response }.to_can_frame())
    }

    /// The response to the request kept, if one is due now: a save or restore answers later.
    fn serve_request(&mut self) -> Option<SdoResponse> {
        let request = self.param_request.take()?;
        let (index, sub) = request.object();
        Some(match request {
            SdoRequest::Upload { .. } => match self.upload(index, sub) {
                Ok((value, size)) => SdoResponse::Uploaded {
                    index,
                    sub,
                    value,
                    size,
                },
                Err(code) => SdoResponse::Abort { index, sub, code },
            },
            SdoRequest::Download { value, size, .. } if matches!(index, STORE | RESTORE) => {
                match self.ask_save(index, sub, value, size) {
                    Ok(()) => return None,
                    Err(code) => SdoResponse::Abort { index, sub, code },
                }
            }
            SdoRequest::Download { value, size, .. } => {
                match self.download(index, sub, value, size) {
                    Ok(()) => SdoResponse::Downloaded { index, sub },
                    Err(code) => SdoResponse::Abort { index, sub, code },
                }
            }
            SdoRequest::Abort { .. } => return None,
        })
    }

    /// A write to [`STORE`] or [`RESTORE`]: checked, and handed to the edge (a restore puts
    /// the built-in configuration in force first).
    fn ask_save(&mut self, index: u16, sub: u8, value: u32, size: u8) -> Result<(), u32> {
        if sub != 1 {
            return Err(abort_code::NO_SUBINDEX);
        }
        if size != 4 {
            return Err(abort_code::WRONG_LENGTH);
        }
        let signature = if index == STORE {
            SAVE_SIGNATURE
        } else {
            LOAD_SIGNATURE
        };
        if value != signature {
            return Err(abort_code::NOT_STORED);
        }
        let moving = matches!(self.state, RobotState::Enabled | RobotState::WheelTest);
        if self.saving != Saving::Idle || (index == RESTORE && moving) {
            return Err(abort_code::DEVICE_STATE);
        }
        if index == RESTORE {
            self.apply_config(self.builtin);
        }
        self.saving = Saving::Asked { index };
        Ok(())
    }

    /// The value and size of object `index`, `sub`.
    fn upload(&self, index: u16, sub: u8) -> Result<(u32, u8), u32> {
        match (index, sub) {
            (0x1000, 0) => return Ok((0, 4)),
            (0x1018, 0) => return Ok((3, 1)),
            (0x1018, 1 | 2) => return Ok((0, 4)),
            (0x1018, 3) => return Ok((u32::from(PROTOCOL_VERSION), 4)),
            (STORE | RESTORE, 0) => return Ok((1, 1)),
            // Bit 0: saves on command (CiA 301); a restore reads as 1 too.
            (STORE | RESTORE, 1) => return Ok((1, 4)),
            (INFO_INDEX, 0) => return Ok((INFO.len() as u32, 1)),
            (INFO_INDEX, 1) => return Ok((u32::from(self.config_id), 4)),
            (INFO_INDEX, 2) => return Ok((u32::from(self.saved.builtin_id), 4)),
            (INFO_INDEX, 3) => return Ok((u32::from(self.saved.id), 4)),
            (INFO_INDEX, 4) => return Ok((self.saved.seq, 4)),
            (0x1000 | 0x1018 | STORE | RESTORE | INFO_INDEX, _) => {
                return Err(abort_code::NO_SUBINDEX);
            }
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
                .map_or_else(|code| code, |_| abort_code::READ_ONLY));
        };
        if size != p.ty.size() {
            return Err(abort_code::WRONG_LENGTH);
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
