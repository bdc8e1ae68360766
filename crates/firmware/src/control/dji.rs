//! DJI RoboMaster C620/C610 ESCs: their feedback into the wheels, the velocity loop's currents
//! out in the two command frames, and the stuck-encoder watch that only a rotor angle allows
//! (`docs/control.md`, "Stuck encoder").

use embedded_can::Frame;
use kinematics::{Encoder, EncoderConfig, WheelSpeeds};

use super::current_loop::{CurrentLoop, WatchInputs};
use super::{Instant, Outbox, Wheel, WheelOf, push, unknown};
use crate::config::{ConfigError, Gains};
use crate::protocol::DecodeError;
use crate::protocol::dji::{self, CurrentCommand, EscGroup, EscId, EscModel};
use crate::protocol::robot::Fault;

/// Stuck-encoder band: a rotor angle within this many counts (of 8192 per rotor turn) of
/// where the rotor last moved counts as not moving.
pub const ENCODER_STUCK_BAND_COUNTS: u16 = 2;
/// Rotor speed (rpm, motor side, either sign) above which a still angle is a contradiction.
pub const ENCODER_STUCK_MIN_ROTOR_RPM: f32 = 100.0;
/// How long a still rotor must report speed before `EncoderStuck` (rule 1), µs.
pub const ENCODER_STUCK_SPINNING_US: u64 = 10_000;
/// How long a still rotor must be driven while the other wheels move before `EncoderStuck`
/// (rule 2), µs.
pub const ENCODER_STUCK_DRAGGED_US: u64 = 50_000;
/// Fraction of `limits.max_current` that counts as driven hard (rule 2).
pub const ENCODER_STUCK_MIN_CURRENT: f32 = 0.25;

/// DJI ESCs send feedback every millisecond.
pub(super) const FEEDBACK_PERIOD_US: u64 = 1_000;

/// The ESCs of the four wheels.
#[derive(Debug, Clone)]
pub(super) struct Dji {
    model: EscModel,
    gear_ratio: f32,
    /// The wheel whose current goes into each slot of the two command frames (ESC 1-4,
    /// ESC 5-8); `None` for an ESC that no wheel has.
    slots: [[Option<u8>; 4]; 2],
    rotors: [Rotor; 4],
    /// Wheel speed, rad/s, of [`ENCODER_STUCK_MIN_ROTOR_RPM`].
    stuck_speed: f32,
    pub(super) current: CurrentLoop,
}

/// What one ESC's rotor angle has told.
#[derive(Debug, Clone, Copy)]
struct Rotor {
    /// The rotor angle integrator.
    encoder: Encoder<f32>,
    watch: StuckWatch,
}

impl Dji {
    /// The ESCs `esc_ids` (validated: in range, one per wheel).
    pub(super) fn new(
        model: EscModel,
        gear_ratio: f32,
        esc_ids: [u8; 4],
        period_us: u64,
    ) -> Result<Self, ConfigError> {
        let mut e = match model {
            EscModel::C620 => EncoderConfig::dji_m3508(false),
            EscModel::C610 => EncoderConfig::dji_m2006(false),
        };
        e.gear_ratio = gear_ratio;
        let encoder = Encoder::new(&e).map_err(|_| ConfigError {
            field: "drive.gear_ratio",
            value: f64::from(gear_ratio),
            expected: "a finite number > 0",
        })?;
        let mut slots = [[None; 4]; 2];
        for (wheel, id) in (0u8..).zip(esc_ids) {
            if let Some(esc) = EscId::new(id) {
                let group = usize::from(esc.group() == EscGroup::Esc5To8);
                slots[group][esc.slot()] = Some(wheel);
            }
        }
        let rpm_to_wheel = core::f32::consts::TAU / 60.0 / gear_ratio;
        Ok(Self {
            model,
            gear_ratio,
            slots,
            rotors: [Rotor {
                encoder,
                watch: StuckWatch::default(),
            }; 4],
            stuck_speed: ENCODER_STUCK_MIN_ROTOR_RPM * rpm_to_wheel,
            current: CurrentLoop::new(period_us),
        })
    }

    /// Takes one ESC feedback frame into its wheel.
    #[inline]
    pub(super) fn on_frame<F: Frame>(
        &mut self,
        now: Instant,
        frame: &F,
        wheel_of: &WheelOf,
        wheels: &mut [Wheel; 4],
    ) -> Result<(), DecodeError> {
        let fb = dji::Feedback::decode(frame, self.model)?;
        let i = wheel_of.get(fb.esc.get());
        let (Some(w), Some(r)) = (wheels.get_mut(i), self.rotors.get_mut(i)) else {
            return Err(unknown(frame));
        };
        // The decoder has checked the angle range, so the encoder accepts it.
        let counts = r.encoder.update(u32::from(fb.rotor_angle)).unwrap_or(0);
        r.watch.on_angle(fb.rotor_angle, dji::layout::ANGLE_COUNTS);
        w.pending += w.sign * r.encoder.counts_to_radians(counts);
        w.speed = w.sign * fb.rotor_speed_rad_s() / self.gear_ratio;
        w.last_seen = Some(now.mark(w.last_seen));
        Ok(())
    }

    /// The velocity loop of the wheels in `mask` (bit i: wheel i; the others get no current)
    /// with the current limit `max`, and the command frames; returns the currents, A.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn emit(
        &mut self,
        out: &mut Outbox,
        wheels: &[Wheel; 4],
        setpoints: WheelSpeeds<f32, 4>,
        gains: &Gains,
        mask: u8,
        max: f32,
        dt: f32,
    ) -> [f32; 4] {
        let speeds = wheels.map(|w| w.speed);
        let currents = self.current.run(setpoints.0, speeds, gains, mask, max, dt);
        // Raw current of each wheel's ESC.
        let mut raw = [0i16; 4];
        for ((r, w), i) in raw.iter_mut().zip(wheels).zip(currents) {
            *r = self.model.amps_to_raw(w.sign * i);
        }
        for (group, slots) in [EscGroup::Esc1To4, EscGroup::Esc5To8]
            .into_iter()
            .zip(self.slots)
        {
            if slots.iter().any(Option::is_some) {
                let cmd = CurrentCommand {
                    model: self.model,
                    group,
                    raw: slots.map(|w| {
                        w.and_then(|w| raw.get(usize::from(w)).copied())
                            .unwrap_or(0)
                    }),
                };
                push(out, cmd.to_can_frame());
            }
        }
        currents
    }

    /// Runs the stuck-encoder watch, then the current loop's runaway and fight watches, every
    /// one of them (so that their intervals stay current); the first fault found.
    pub(super) fn watch(&mut self, now: Instant, w: &WatchInputs<'_>) -> Fault {
        let stuck = self.watch_encoders(now, w);
        let (runaway, fight) = self.current.watch(now, w);
        if stuck {
            Fault::EncoderStuck
        } else if runaway {
            Fault::WheelRunaway
        } else if fight {
            Fault::WheelFight
        } else {
            Fault::None
        }
    }

    /// Every rotor's stuck-encoder watch for this step; `true` if one has fired.
    fn watch_encoders(&mut self, now: Instant, w: &WatchInputs<'_>) -> bool {
        if !self.rotors.iter().any(|r| r.watch.still) {
            // The common case: every rotor moved. No interval runs (what `judge` would
            // conclude for each), and the least-squares fit is not needed.
            for r in &mut self.rotors {
                r.watch.spinning_since = None;
                r.watch.dragged_since = None;
            }
            return false;
        }
        let min_speed = self.stuck_speed;
        let min_current = ENCODER_STUCK_MIN_CURRENT * w.max_current;
        let driven: [bool; 4] = core::array::from_fn(|i| {
            self.rotors[i].watch.still && w.currents[i].abs() >= min_current
        });
        // The least-squares fit is only worth its cost when some still wheel is driven.
        let implied = if driven.contains(&true) {
            w.kin.implied_by_others(&WheelSpeeds(w.speeds))
        } else {
            [None; 4]
        };
        let mut stuck = false;
        for (i, r) in self.rotors.iter_mut().enumerate() {
            let spinning = w.speeds[i].abs() >= min_speed;
            let dragged = driven[i] && implied[i].is_some_and(|s| s.abs() >= min_speed);
            stuck |= r.watch.judge(now, spinning, dragged);
        }
        stuck
    }
}

/// Stuck-encoder watch of one rotor.
#[derive(Debug, Clone, Copy, Default)]
struct StuckWatch {
    /// Rotor angle, raw counts, where the rotor was last seen to move.
    anchor: Option<u16>,
    /// A feedback frame after the one that set `anchor` stayed within the band.
    still: bool,
    /// First step of the running interval of rule 1 (still and reporting speed).
    spinning_since: Option<Instant>,
    /// First step of the running interval of rule 2 (still, driven, the others move).
    dragged_since: Option<Instant>,
}

impl StuckWatch {
    #[inline]
    fn on_angle(&mut self, raw: u16, counts_per_turn: u16) {
        match self.anchor {
            Some(a) if circular_distance(raw, a, counts_per_turn) <= ENCODER_STUCK_BAND_COUNTS => {
                self.still = true;
            }
            _ => {
                self.anchor = Some(raw);
                self.still = false;
            }
        }
    }

    /// Updates both intervals for this step; `true` once either has lasted its window.
    fn judge(&mut self, now: Instant, spinning: bool, dragged: bool) -> bool {
        let since = |flag: bool, start: Option<Instant>| flag.then(|| start.unwrap_or(now));
        self.spinning_since = since(self.still && spinning, self.spinning_since);
        self.dragged_since = since(self.still && dragged, self.dragged_since);
        self.spinning_since
            .is_some_and(|t| now.micros_since(t) >= ENCODER_STUCK_SPINNING_US)
            || self
                .dragged_since
                .is_some_and(|t| now.micros_since(t) >= ENCODER_STUCK_DRAGGED_US)
    }
}

/// Distance between two readings of a counter that wraps at `modulus`, the short way round.
#[inline]
fn circular_distance(a: u16, b: u16, modulus: u16) -> u16 {
    let d = a.abs_diff(b) % modulus;
    d.min(modulus - d)
}
