//! A scenario with the board image as the firmware node of hostsim's lockstep engine
//! ([`hostsim::engine`]): the engine's host, simulated drives and plant (with the scenario's
//! IMU, bus and wheel faults) and bit-timed bus, the board in their virtual time
//! ([`Lockstep`]).
//!
//! The board steps on its own timer and sends through its mailboxes, so the engine's tick
//! does nothing to it; the engine sees it through its frames and its log: the state changes
//! are the ones the image logs at the step that made them (STATUS, a host's view, reports them
//! at its 10 Hz), the odometry is ODOM_POSITION and ODOM_VELOCITY's (0.1 mm, 0.0001 rad). The log has
//! the same channels as hostsim's but `/joint_states` and `/diagnostics` (the core's
//! internals are inside the board), plus the board's defmt lines on `/rosout`.

use std::ops::ControlFlow;

use drivelog::{CoreLog, McapLog, msg};
use firmware::protocol::robot::{Fault, RobotState, Telemetry};
use firmware::{CanFrame, StreamHash};
use hostsim::bus::{Bus, Fate, Node, Transmission};
use hostsim::engine::{Firmware, LogOptions, Record};
use hostsim::scenario::Scenario;

use crate::board::{Board, BoardError, CPU_HZ};
use crate::lockstep::{Lockstep, WireFault};
use crate::rtt::LogLine;

/// How long the board may boot before the scenario starts without its first frame, ns.
const BOOT_LIMIT_NS: u64 = 100_000_000;
/// How long the board runs on after the scenario for the frames of its last step to leave, ns:
/// a few frames' time on a loaded bus.
const DRAIN_NS: u64 = 10_000_000;

/// Why a run stopped.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The board stopped.
    #[error("the board stopped {t:.6} s after power-on: {error}")]
    Board {
        /// The board's time since power-on, s.
        t: f64,
        /// Why.
        error: BoardError,
        /// The board's log up to then (its last lines tell what it was doing).
        lines: Vec<LogLine>,
    },
    /// The image carries another configuration than the scenario's: the simulated drives
    /// would be another robot's.
    #[error(
        "the board image runs configuration id {image:#06x} (its first HEARTBEAT), the \
         scenario's configuration has id {scenario:#06x}: build the image with \
         MECANUM_CONFIG=<that file> (boards/stm32f407/README.md) or run with --config <the \
         image's file> (`mecanum-codec config-id FILE` prints a file's id); a board started on \
         a flash image with a saved parameter set runs that set"
    )]
    ConfigMismatch {
        /// The id in the board's HEARTBEAT.
        image: u16,
        /// The scenario configuration's id.
        scenario: u16,
    },
    /// The scenario's plant could not be built.
    #[error("the scenario's plant: {0}")]
    Plant(String),
    /// The log could not be written.
    #[error(transparent)]
    Log(#[from] drivelog::LogError),
}

impl RunError {
    /// The board's log lines up to the error (none if the board did not stop).
    #[must_use]
    pub fn lines(&self) -> &[LogLine] {
        match self {
            Self::Board { lines, .. } => lines,
            _ => &[],
        }
    }
}

/// What a run saw.
#[derive(Debug)]
pub struct BoardRun {
    /// (s, state, fault) at each STATUS that reported a new pair: what a host reads.
    pub transitions: Vec<(f64, RobotState, Fault)>,
    /// (s, state, fault) at each step that changed the state or the fault, as the image logs
    /// them: the in-process core's [`RunSummary::transitions`](hostsim::engine::RunSummary).
    pub state_changes: Vec<(f64, String, String)>,
    /// The last odometry the board sent: `[x, y, heading]` (m, m, rad) and its time (s).
    pub odometry: Option<([f64; 3], f64)>,
    /// Ground truth at the end.
    pub truth: [f64; 3],
    /// The board's log (its times in board cycles since power-on: [`Self::line_time_s`]).
    pub lines: Vec<LogLine>,
    /// Power-on to the tick of the board's first control step, where the scenario's time
    /// starts, ns ([`Lockstep::power_on`]).
    pub boot_ns: u64,
    /// Frames delivered to the board.
    pub frames_received: u64,
    /// Simulated seconds.
    pub simulated_s: f64,
    /// The board's odometry and the ground truth at each of its odometry frames (100 Hz).
    pub track: Vec<hostsim::engine::TrackPoint>,
    /// Every frame the board sent, with the end of its transmission (ns).
    pub sent: Vec<(u64, firmware::CanFrame)>,
    /// Hash of every transmission on the bus, all senders, with its end time (ns): two runs
    /// with the same hash put the same frames on the wire at the same times.
    pub bus_hash: u64,
    /// The board at the end (its models: clocks, CAN controller, unknown registers).
    pub board: Board,
}

impl BoardRun {
    /// The scenario time of a log line, s (negative during the boot).
    #[must_use]
    pub fn line_time_s(&self, line: &LogLine) -> f64 {
        (line.at as f64 / CPU_HZ as f64) - self.boot_ns as f64 * 1e-9
    }
}

/// What the harness does to the board itself during a run. Times are the scenario's, ns.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Harness {
    /// From this time the TIM2 interrupt is withheld until the board resets: the control
    /// loop stalls ([`Board::stall_timer`]).
    pub stall_timer_at_ns: Option<u64>,
    /// `(from, until)`: a node on the host's side floods the bus with frames of
    /// [`FLOOD_ID`] (unknown to every protocol, the lowest priority; 8 zero bytes), back to
    /// back: each queued when the one before it ends, so the bus carries nothing else but
    /// higher-priority frames.
    pub flood_ns: Option<(u64, u64)>,
    /// `(from, until)`: the board's CAN RX0 interrupt is withheld ([`Board::hold_can_rx`]).
    pub hold_can_rx_ns: Option<(u64, u64)>,
    /// `(fault, from, until)`: a fault of the board's connection to the bus
    /// ([`Lockstep::set_wire_fault`]).
    pub wire_fault_ns: Option<(WireFault, u64, u64)>,
}

/// The id of [`Harness::flood_ns`]'s frames.
pub const FLOOD_ID: u16 = 0x7FF;

/// The board's telemetry as a host reads it.
#[derive(Debug, Default)]
struct Observer {
    transitions: Vec<(f64, RobotState, Fault)>,
    position: Option<[f64; 2]>,
    odometry: Option<([f64; 3], f64)>,
}

/// What a frame of the board told the observer that is new.
enum Seen {
    /// A complete odometry (ODOM_POSITION then ODOM_VELOCITY): pose and twist.
    Odometry([f64; 3], [f64; 3]),
    /// A STATUS with a new state or fault (in the observer's `transitions`).
    Transition,
    /// A HEARTBEAT: the id of the configuration the image carries.
    ConfigId(u16),
}

impl Observer {
    /// A frame the board sent at `t` (s).
    fn on_frame(&mut self, t: f64, frame: &firmware::CanFrame) -> Option<Seen> {
        match Telemetry::decode(frame).ok()? {
            Telemetry::Status(s) => {
                let new = (s.state, s.fault);
                if self
                    .transitions
                    .last()
                    .is_some_and(|&(_, st, f)| (st, f) == new)
                {
                    return None;
                }
                self.transitions.push((t, s.state, s.fault));
                Some(Seen::Transition)
            }
            Telemetry::OdomPosition(p) => {
                self.position = Some([f64::from(p.x), f64::from(p.y)]);
                None
            }
            Telemetry::OdomVelocity(v) => {
                let [x, y] = self.position.take()?;
                let pose = [x, y, f64::from(v.heading)];
                self.odometry = Some((pose, t));
                Some(Seen::Odometry(pose, [v.vx, v.vy, v.wz].map(f64::from)))
            }
            Telemetry::Heartbeat(h) => Some(Seen::ConfigId(h.config_id)),
            _ => None,
        }
    }
}

/// The metadata of a board run's log: hostsim's (configuration, scenario, seed, versions)
/// with `program` = `boardsim run` and the image's file.
#[must_use]
pub fn run_metadata(
    scenario: &Scenario,
    image: &crate::Image,
) -> std::collections::BTreeMap<String, String> {
    let mut m = hostsim::engine::run_metadata(scenario);
    m.insert("program".into(), "boardsim run".into());
    m.insert("board_image".into(), image.path.display().to_string());
    m
}

/// The board as the engine's firmware node. See the [module documentation](self).
struct BoardNode {
    ls: Lockstep,
    harness: Harness,
    /// What the image's first HEARTBEAT must carry (the configuration it runs), until it is
    /// checked; later ones follow the parameters set over CAN.
    config_id: Option<u16>,
    /// Transmissions completed, not yet delivered (a delay fault delivers a frame of the
    /// board's after its end).
    pending: Vec<Transmission>,
    observer: Observer,
    lines: Vec<LogLine>,
    sent: Vec<(u64, CanFrame)>,
    bus_hash: StreamHash,
    boot_ns: u64,
    duration_ns: u64,
    period_us: u64,
}

/// A state change the image logs at the step that made it: `step N: state S fault F`
/// (`boards/stm32f407/src/main.rs`), as (step, state, fault).
fn state_change(text: &str) -> Option<(u64, RobotState, Fault)> {
    let (step, rest) = text.strip_prefix("step ")?.split_once(": state ")?;
    let (state, fault) = rest.split_once(" fault ")?;
    Some((
        step.parse().ok()?,
        RobotState::from_raw(state.parse().ok()?)?,
        Fault::from_raw(fault.parse().ok()?)?,
    ))
}

impl BoardNode {
    /// The board stopped with `error`: the error with the board's log up to then.
    fn stopped(&mut self, error: BoardError) -> RunError {
        self.lines.extend(self.ls.board.take_lines());
        RunError::Board {
            t: self.ls.board.now() as f64 / CPU_HZ as f64,
            error,
            lines: std::mem::take(&mut self.lines),
        }
    }

    /// Runs board and bus to `until_ns`, first to the harness's interventions due by then.
    fn run_board(&mut self, bus: &mut Bus, until_ns: u64) -> Result<(), BoardError> {
        if let Some((from, until)) = self.harness.hold_can_rx_ns.filter(|&(f, _)| f <= until_ns) {
            self.ls.run_until(bus, from)?;
            self.ls.hold_can_rx(until);
            self.harness.hold_can_rx_ns = None;
        }
        if let Some(at) = self.harness.stall_timer_at_ns.filter(|&at| at <= until_ns) {
            self.ls.run_until(bus, at)?;
            self.ls.board.stall_timer();
            self.harness.stall_timer_at_ns = None;
        }
        self.ls.run_until(bus, until_ns)
    }
}

impl Firmware for BoardNode {
    type Error = RunError;

    fn start(&mut self, bus: &mut Bus) -> Result<(), RunError> {
        // The scenario starts at the tick of the board's first step (`Lockstep::power_on`).
        self.boot_ns = match self.ls.power_on(BOOT_LIMIT_NS) {
            Ok(ns) => ns,
            Err(e) => return Err(self.stopped(e)),
        };
        if let Some((fault, from, until)) = self.harness.wire_fault_ns {
            self.ls.set_wire_fault(fault, from, until);
        }
        if let Some((from, until)) = self.harness.flood_ns {
            let frame = CanFrame::standard(
                embedded_can::StandardId::new(FLOOD_ID).expect("an 11-bit id"),
                &[0; 8],
            )
            .expect("8 bytes");
            // Back to back when nothing of higher priority is queued; otherwise the bus holds
            // them (each node offers its lowest id first) and sends them as it can.
            let frame_ns = u64::from(hostsim::bus::frame_bits(&frame)) * 1000;
            let mut at = from;
            while at < until.min(self.duration_ns) {
                bus.send(at, Node::Host, frame);
                at += frame_ns;
            }
        }
        Ok(())
    }

    fn run_until(
        &mut self,
        bus: &mut Bus,
        until_ns: u64,
        done: &mut Vec<Transmission>,
    ) -> Result<(), RunError> {
        if let Err(e) = self.run_board(bus, until_ns) {
            return Err(self.stopped(e));
        }
        for tx in self.ls.completed.drain(..) {
            self.bus_hash.add(tx.end_ns, &tx.frame);
            if tx.from == Node::Controller && tx.fate != Fate::Dropped {
                self.sent.push((tx.end_ns, tx.frame));
            }
            self.pending.push(tx);
        }
        hostsim::engine::deliver_due(&mut self.pending, until_ns, done);
        Ok(())
    }

    fn drain(
        &mut self,
        bus: &mut Bus,
        until_ns: u64,
        done: &mut Vec<Transmission>,
    ) -> Result<(), RunError> {
        // The board runs on (its frames leave from its mailboxes), for long enough that the
        // frames of its last step complete on a loaded bus.
        let until_ns = until_ns.min(self.duration_ns + DRAIN_NS);
        self.run_until(bus, until_ns, done)
    }

    fn tick(
        &mut self,
        _bus: &mut Bus,
        _t_us: u64,
        _delivered: &mut Vec<Transmission>,
        _sent: &mut Vec<CanFrame>,
    ) -> Result<(), RunError> {
        // The board steps on its own timer.
        Ok(())
    }

    fn observe(
        &mut self,
        _t_us: u64,
        mut log: Option<&mut McapLog>,
        _truth: [f64; 3],
        _velocity: &dyn Fn() -> [f64; 3],
        record: &mut Record,
    ) -> Result<(), RunError> {
        for line in self.ls.board.take_lines() {
            if let Some((step, state, fault)) = state_change(&line.text) {
                // The step's time as the core's record has it.
                let t_us = step * self.period_us;
                let (t_ns, t) = (t_us * 1000, t_us as f64 * 1e-6);
                record
                    .transitions
                    .push((t, state.to_string(), fault.to_string()));
                if let Some(l) = log.as_deref_mut() {
                    let (level, text) = drivelog::state_line(state, fault);
                    l.text(t_ns, level, &text)?;
                }
            }
            if let Some(l) = log.as_deref_mut() {
                let level = match line.level.as_str() {
                    "error" => msg::Log::ERROR,
                    "warn" => msg::Log::WARN,
                    _ => msg::Log::INFO,
                };
                let text = format!("board: {}", line.text);
                l.text(self.ls.board_ns(line.at), level, &text)?;
            }
            self.lines.push(line);
        }
        Ok(())
    }

    fn on_own_frame(
        &mut self,
        tx: &Transmission,
        log: Option<&mut McapLog>,
        truth: &dyn Fn() -> ([f64; 3], [f64; 3]),
        record: &mut Record,
    ) -> Result<(), RunError> {
        // What the board reported by its last step: the frames it offered before the step
        // after it (the engine runs on a period, and drains, for them to complete).
        let last_step_ends = self.duration_ns + self.period_us * 1000;
        if tx.fate == Fate::Dropped || tx.queued_ns >= last_step_ends {
            return Ok(());
        }
        let t = tx.delivered_ns as f64 * 1e-9;
        match self.observer.on_frame(t, &tx.frame) {
            Some(Seen::Odometry(pose, twist)) => {
                let (pose_truth, velocity) = truth();
                record.pose(pose, pose_truth);
                record.track_point(t, pose, pose_truth);
                if let Some(l) = log {
                    let truth = Some((pose_truth, velocity));
                    CoreLog::odometry(l, tx.delivered_ns, (pose, twist), truth)?;
                }
            }
            Some(Seen::ConfigId(image)) => {
                if let Some(scenario) = self.config_id.take()
                    && image != scenario
                {
                    return Err(RunError::ConfigMismatch { image, scenario });
                }
            }
            Some(Seen::Transition) | None => {}
        }
        Ok(())
    }
}

/// Runs `scenario` with `board` as the firmware node of hostsim's engine, logging to `log`
/// if given; `progress` gets the simulated time (µs) every simulated 100 ms.
///
/// # Errors
/// [`RunError`]: the board stopped, the plant could not be built, the log failed.
pub fn run_scenario(
    scenario: &Scenario,
    board: Board,
    log: Option<&mut McapLog>,
    options: LogOptions,
    harness: Harness,
    mut progress: impl FnMut(u64),
) -> Result<BoardRun, RunError> {
    let mut drives =
        hostsim::engine::plant_for(scenario).map_err(|e| RunError::Plant(e.to_string()))?;
    let mut node = BoardNode {
        ls: Lockstep::new(board),
        harness,
        config_id: Some(scenario.config.id()),
        pending: Vec::new(),
        observer: Observer::default(),
        lines: Vec::new(),
        sent: Vec::new(),
        bus_hash: StreamHash::new(),
        boot_ns: 0,
        duration_ns: scenario.duration_us() * 1000,
        period_us: 1_000_000 / u64::from(scenario.config.timing.control_hz),
    };
    let run =
        hostsim::engine::run_firmware(scenario, &mut node, &mut drives, log, options, |step| {
            if step.t_us.is_multiple_of(100_000) {
                progress(step.t_us);
            }
            ControlFlow::Continue(())
        })?;
    Ok(BoardRun {
        transitions: node.observer.transitions,
        state_changes: run.record.transitions,
        odometry: node.observer.odometry,
        truth: run.truth,
        lines: node.lines,
        boot_ns: node.boot_ns,
        frames_received: run.rx_frames,
        simulated_s: run.duration_s,
        track: run.record.track,
        sent: node.sent,
        bus_hash: node.bus_hash.value(),
        board: node.ls.board,
    })
}
