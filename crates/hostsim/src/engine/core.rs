//! The in-process firmware node: the real core ([`Controller`]) stepped at every tick, with
//! the frames the bus delivered by then, its frames put on the bus at the tick's time. A
//! scenario's `runner_restart` faults take it down for their window (it receives and sends
//! nothing) and start a fresh core at their end, on the saved parameters if any. Saves go to a
//! flash in RAM laid out and programmed as the board's (`firmware::storage`, a few words
//! before each step), and each end is logged (`/firmware/store`).

use firmware::CanFrame;
use firmware::control::{Controller, Instant, Outbox, SaveOutcome};
use firmware::storage::{self, F407_LAYOUT, RamFlash, Store};

use super::{Firmware, Record, deliver_due};
use crate::bus::{Bus, Fate, Node, Transmission};
use crate::engine::SimError;
use crate::scenario::{FaultName, Scenario};
use drivelog::{CoreLog, McapLog};

/// The in-process core as the engine's firmware node: a [`Controller`] stepped at every tick,
/// down for each `runner_restart` window and started afresh at its end.
#[derive(Debug)]
pub struct InProcess {
    config: firmware::Config,
    ctl: Controller,
    /// The runner's deaths: from, until (µs); a fresh core starts at `until`.
    restarts: Vec<(u64, u64)>,
    down: bool,
    /// Transmissions on the bus not delivered yet.
    started: Vec<Transmission>,
    out: Outbox,
    /// The firmware boots DISABLED without a fault: the log says the changes from there.
    core_log: CoreLog,
    /// The board's parameter flash (sectors 0 to 2), and its record log.
    flash: RamFlash,
    store: Store,
    /// The end of a save given to the core at the last tick, to log.
    saved: Option<SaveOutcome>,
}

impl InProcess {
    /// The core of `scenario`'s configuration, logging its internals as `options` says.
    ///
    /// # Errors
    /// The firmware refused the configuration.
    pub fn new(scenario: &Scenario, options: super::LogOptions) -> Result<Self, SimError> {
        let mut flash = RamFlash::new((F407_LAYOUT.starts[1] + F407_LAYOUT.sector_bytes) as usize);
        let (ctl, store) = boot(&scenario.config, &mut flash)?;
        Ok(Self {
            config: scenario.config,
            ctl,
            flash,
            store,
            saved: None,
            restarts: scenario
                .node_faults
                .iter()
                .filter(|f| f.kind == FaultName::RunnerRestart)
                .map(|f| (f.from_us, f.until_us))
                .collect(),
            down: false,
            started: Vec::new(),
            out: Outbox::new(),
            core_log: CoreLog::new(options.snapshot_every, options.pose_every).from_boot(),
        })
    }

    /// The core (as it stopped, while it is down).
    #[must_use]
    pub const fn controller(&self) -> &Controller {
        &self.ctl
    }

    /// The core is not running (a `runner_restart` fault's window).
    #[must_use]
    pub const fn is_down(&self) -> bool {
        self.down
    }
}

impl Firmware for InProcess {
    type Error = SimError;

    fn run_until(
        &mut self,
        bus: &mut Bus,
        until_ns: u64,
        done: &mut Vec<Transmission>,
    ) -> Result<(), SimError> {
        // Frames delivered by `until_ns` started before it: all of them are known after this.
        bus.advance_into(until_ns, &mut self.started);
        deliver_due(&mut self.started, until_ns, done);
        Ok(())
    }

    fn tick(
        &mut self,
        bus: &mut Bus,
        t_us: u64,
        delivered: &mut Vec<Transmission>,
        sent: &mut Vec<CanFrame>,
    ) -> Result<(), SimError> {
        let down = self
            .restarts
            .iter()
            .any(|&(from, until)| from <= t_us && t_us < until);
        if self.down && !down {
            (self.ctl, self.store) = boot(&self.config, &mut self.flash)?;
        }
        self.down = down;
        let t_ns = t_us * 1000;
        // What starts by the tick starts before the core's frames are queued; a frame queued
        // with a time the bus had passed may be delivered by now.
        bus.advance_into(t_ns + 1, &mut self.started);
        let late = delivered.len();
        deliver_due(&mut self.started, t_ns, delivered);
        if delivered.len() > late {
            delivered.sort_by_key(|tx| tx.delivered_ns);
        }
        if down {
            self.out.clear();
            return Ok(());
        }
        for tx in delivered.iter() {
            if tx.fate != Fate::Dropped && tx.from != Node::Controller {
                let at = Instant::from_micros(tx.delivered_ns / 1000);
                self.ctl.on_frame(at, &tx.frame);
            }
        }
        self.saved = self
            .store
            .serve(&mut self.ctl, &mut self.flash, storage::WORDS_PER_STEP);
        self.ctl
            .step_into(Instant::from_micros(t_us), &mut self.out);
        for f in &self.out {
            bus.send(t_ns, Node::Controller, *f);
            sent.push(*f);
        }
        Ok(())
    }

    fn receiving(&self) -> bool {
        !self.down
    }

    fn observe(
        &mut self,
        t_us: u64,
        mut log: Option<&mut McapLog>,
        truth: [f64; 3],
        velocity: &dyn Fn() -> [f64; 3],
        record: &mut Record,
    ) -> Result<(), SimError> {
        let pose = pose_array(self.ctl.pose());
        record.pose(pose, truth);
        if t_us.is_multiple_of(10_000) {
            record.track_point(t_us as f64 * 1e-6, pose, truth);
        }
        if self.down {
            return Ok(());
        }
        if let (Some(outcome), Some(l)) = (self.saved.take(), log.as_deref_mut()) {
            l.saved(t_us * 1000, outcome)?;
        }
        let truth_now = || (truth, velocity());
        let changes = self
            .core_log
            .step(log, t_us * 1000, &self.ctl, Some(&truth_now))?;
        let t = t_us as f64 * 1e-6;
        if changes.state {
            let (state, fault) = (self.ctl.state().to_string(), self.ctl.fault().to_string());
            record.transitions.push((t, state, fault));
        }
        if changes.heading {
            let source = self.ctl.heading_source().to_string();
            record.heading_changes.push((t, source));
        }
        Ok(())
    }

    fn drain(
        &mut self,
        bus: &mut Bus,
        until_ns: u64,
        done: &mut Vec<Transmission>,
    ) -> Result<(), SimError> {
        bus.advance_into(until_ns, &mut self.started);
        deliver_due(&mut self.started, u64::MAX, done);
        Ok(())
    }
}

/// The firmware's pose as `[x, y, heading]` in f64, the plant's format.
pub(crate) fn pose_array(p: kinematics::Pose2<f32>) -> [f64; 3] {
    [f64::from(p.x), f64::from(p.y), f64::from(p.heading)]
}

/// A boot on `flash`, as the board's: the newest saved set for `config` if there is one (else
/// `config`), the stale sector erased.
fn boot(config: &firmware::Config, flash: &mut RamFlash) -> Result<(Controller, Store), SimError> {
    let ctl = Controller::new(config)?;
    let (mut store, found) = Store::mount(flash, F407_LAYOUT, config).map_err(SimError::Flash)?;
    store.erase_stale(flash).map_err(SimError::Flash)?;
    let ctl = match found.saved {
        Some(s) => ctl.with_saved(&s.config, s.seq)?,
        None => ctl,
    };
    Ok((ctl, store))
}
