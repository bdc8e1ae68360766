//! A scenario with the board image as the firmware node: hostsim's host node, simulated
//! drives and plant (with the scenario's IMU, bus and wheel faults) and bit-timed bus, and the
//! board in their virtual time ([`Lockstep`]).
//!
//! The loop follows hostsim's runner where it can: the host's frames are queued at their
//! times; the bus and the board run ahead of the plant only up to the drives' next feedback
//! (whose frames may win arbitration over those waiting); each frame for the drives acts from
//! its delivery time. What differs is the firmware: the board steps on its own timer and
//! sends through its mailboxes, so the runner sees it as a host would, through its frames:
//! the state changes are the STATUS frames' (and so logged up to 100 ms after the core made
//! them, at STATUS's 10 Hz), the odometry is ODOM_POSITION and ODOM_VELOCITY's (0.1 mm,
//! 0.0001 rad). The log has the same channels as hostsim's but `/joint_states` and
//! `/diagnostics` (the core's internals are inside the board), plus the board's defmt lines
//! on `/rosout`.

use firmware::protocol::robot::{Fault, RobotState, Telemetry};
use hostsim::bus::{Bus, Fate, Node};
use hostsim::drives::SimDrives;
use hostsim::host::HostNode;
use hostsim::log::{CoreLog, McapLog, msg};
use hostsim::scenario::Scenario;
use hostsim::sim::{LogOptions, SimPlant, log_transmission, queue_feedback, set_wheel_faults};

use crate::board::{Board, BoardError, CPU_HZ};
use crate::lockstep::{Lockstep, WireFault};
use crate::rtt::LogLine;

/// How long the board may boot before the scenario starts without its first frame, ns.
const BOOT_LIMIT_NS: u64 = 100_000_000;

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
        "the board image carries configuration id {image:#06x} (its HEARTBEAT), the scenario's \
         configuration has id {scenario:#06x}: build the image with MECANUM_CONFIG=<that file> \
         (boards/stm32f407/README.md) or run with --config <the image's file> \
         (`mecanum-codec config-id FILE` prints a file's id)"
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
    Log(#[from] hostsim::log::LogError),
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
    /// (s, state, fault) at each STATUS that reported a new pair.
    pub transitions: Vec<(f64, RobotState, Fault)>,
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
    pub track: Vec<hostsim::plot::TrackPoint>,
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
    /// A STATUS with a new state or fault.
    Transition(RobotState, Fault),
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
                Some(Seen::Transition(s.state, s.fault))
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
    let mut m = hostsim::sim::run_metadata(scenario);
    m.insert("program".into(), "boardsim run".into());
    m.insert("board_image".into(), image.path.display().to_string());
    m
}

/// Runs `scenario` with `board` as the firmware node, logging to `log` if given; `progress`
/// gets the simulated time (µs) every simulated 100 ms.
///
/// # Errors
/// [`RunError`]: the board stopped, the plant could not be built, the log failed.
pub fn run_scenario(
    scenario: &Scenario,
    board: Board,
    mut log: Option<&mut McapLog>,
    options: LogOptions,
    harness: Harness,
    mut progress: impl FnMut(u64),
) -> Result<BoardRun, RunError> {
    let mut drives =
        SimDrives::for_scenario(scenario).map_err(|e| RunError::Plant(e.to_string()))?;
    let plant = &mut hostsim::imu::WithImu::new(&mut drives, scenario.imu.as_ref(), scenario.seed);
    let plant = &mut hostsim::pods::WithPods::for_scenario(plant, scenario);
    let bus = Bus::new(1_000_000, scenario.bus_faults.clone(), scenario.seed);
    let mut ls = Lockstep::new(board, bus);
    let mut host = HostNode::new(scenario);
    let mut observer = Observer::default();
    let (mut host_frames, mut twists, mut feedback) = (Vec::new(), Vec::new(), Vec::new());
    let duration_ns = scenario.duration_us() * 1000;
    // The plant's time, ns; the bus and the board run ahead of it up to `horizon`.
    let mut plant_ns = 0u64;
    let mut received = 0u64;
    let mut bus_hash = firmware::StreamHash::new();
    let mut next_progress = 0u64;
    let mut lines = Vec::new();
    let mut track = Vec::new();
    let mut board_frames = Vec::new();
    let mut stall_at = harness.stall_timer_at_ns;
    let mut hold_rx = harness.hold_can_rx_ns;
    // What the image's HEARTBEATs must carry.
    let config_id = scenario.config.id();
    let stopped = |ls: &mut Lockstep, lines: &mut Vec<LogLine>, error| {
        lines.extend(ls.board.take_lines());
        RunError::Board {
            t: ls.board.now() as f64 / CPU_HZ as f64,
            error,
            lines: std::mem::take(lines),
        }
    };
    // The scenario starts at the tick of the board's first step (see `Lockstep::power_on`).
    let boot_ns = ls
        .power_on(BOOT_LIMIT_NS)
        .map_err(|e| stopped(&mut ls, &mut lines, e))?;
    if let Some((fault, from, until)) = harness.wire_fault_ns {
        ls.set_wire_fault(fault, from, until);
    }
    set_wheel_faults(scenario, plant, 0);
    queue_feedback(plant, &mut feedback, 0, |t, n, f| ls.send(t, n, f));
    if let Some((from, until)) = harness.flood_ns {
        let frame = firmware::CanFrame::standard(
            embedded_can::StandardId::new(FLOOD_ID).expect("an 11-bit id"),
            &[0; 8],
        )
        .expect("8 bytes");
        // Back to back when nothing of higher priority is queued; otherwise the bus holds
        // them (each node offers its lowest id first) and sends them as it can.
        let frame_ns = u64::from(hostsim::bus::frame_bits(&frame)) * 1000;
        let mut at = from;
        while at < until.min(duration_ns) {
            ls.send(at, Node::Host, frame);
            at += frame_ns;
        }
    }
    while plant_ns < duration_ns {
        let horizon = duration_ns.min(plant.next_feedback_ns().max(plant_ns + 1));
        host_frames.clear();
        twists.clear();
        host.frames_until(horizon / 1000, &mut host_frames, &mut twists);
        for &(at_ns, frame) in &host_frames {
            ls.send(at_ns, Node::Host, frame);
        }
        if let Some(l) = log.as_deref_mut() {
            for &(at_ns, twist) in &twists {
                l.twist(at_ns, twist)?;
            }
        }
        if let Some((from, until)) = hold_rx.filter(|&(from, _)| from <= horizon) {
            ls.run_until(from)
                .map_err(|e| stopped(&mut ls, &mut lines, e))?;
            ls.hold_can_rx(until);
            hold_rx = None;
        }
        if let Some(at) = stall_at.filter(|&at| at <= horizon) {
            ls.run_until(at)
                .map_err(|e| stopped(&mut ls, &mut lines, e))?;
            ls.board.stall_timer();
            stall_at = None;
        }
        ls.run_until(horizon)
            .map_err(|e| stopped(&mut ls, &mut lines, e))?;
        // The transmissions completed by now: to the drives at their delivery time, to the
        // log, and the board's to the observer.
        let done = std::mem::take(&mut ls.completed);
        for tx in &done {
            bus_hash.add(tx.end_ns, &tx.frame);
            if let Some(l) = log.as_deref_mut() {
                log_transmission(l, tx, options)?;
            }
            if tx.fate == Fate::Dropped {
                continue;
            }
            if tx.from != Node::Controller {
                received += 1;
            } else {
                board_frames.push((tx.end_ns, tx.frame));
                let t = tx.delivered_ns as f64 * 1e-9;
                match observer.on_frame(t, &tx.frame) {
                    Some(Seen::Odometry(pose, twist)) => {
                        let truth = plant.truth();
                        track.push(hostsim::plot::TrackPoint {
                            t,
                            truth: [truth[0], truth[1]],
                            odom: [pose[0], pose[1]],
                        });
                        if let Some(l) = log.as_deref_mut() {
                            let truth = (truth, plant.truth_velocity());
                            CoreLog::odometry(l, tx.delivered_ns, (pose, twist), Some(truth))?;
                        }
                    }
                    Some(Seen::Transition(state, fault)) => {
                        if let Some(l) = log.as_deref_mut() {
                            let (level, text) = hostsim::log::state_line(state, fault);
                            l.text(tx.delivered_ns, level, &text)?;
                        }
                    }
                    Some(Seen::ConfigId(image)) if image != config_id => {
                        return Err(RunError::ConfigMismatch {
                            image,
                            scenario: config_id,
                        });
                    }
                    Some(Seen::ConfigId(_)) | None => {}
                }
            }
            if tx.from != Node::Drives && tx.delivered_ns > plant_ns && tx.delivered_ns <= horizon {
                plant.advance_ns(tx.delivered_ns - plant_ns);
                plant_ns = tx.delivered_ns;
                plant.on_frame(tx.delivered_ns / 1000, &tx.frame);
            }
        }
        plant.advance_ns(horizon - plant_ns);
        plant_ns = horizon;
        set_wheel_faults(scenario, plant, plant_ns / 1000 + 1);
        queue_feedback(plant, &mut feedback, plant_ns, |t, n, f| ls.send(t, n, f));
        for line in ls.board.take_lines() {
            if let Some(l) = log.as_deref_mut() {
                let level = match line.level.as_str() {
                    "error" => msg::Log::ERROR,
                    "warn" => msg::Log::WARN,
                    _ => msg::Log::INFO,
                };
                l.text(
                    ls.board_ns(line.at),
                    level,
                    &format!("board: {}", line.text),
                )?;
            }
            lines.push(line);
        }
        if let Some(l) = log.as_deref_mut() {
            l.maybe_flush()?;
        }
        while plant_ns / 1000 >= next_progress {
            progress(next_progress);
            next_progress += 100_000;
        }
    }
    Ok(BoardRun {
        transitions: observer.transitions,
        odometry: observer.odometry,
        truth: plant.truth(),
        lines,
        boot_ns,
        frames_received: received,
        simulated_s: plant_ns as f64 * 1e-9,
        track,
        sent: board_frames,
        bus_hash: bus_hash.value(),
        board: ls.board,
    })
}
