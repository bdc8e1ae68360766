//! The host node: the robot's commander on the bus, as the simulator runs it.
//!
//! It plays its script of timed actions (enable, disable, reset, e-stop, status and
//! wheel-test requests, parameter writes: a scenario's actions, as the engine gives them), streams `TWIST_CMD`
//! at its command rate with an alive counter (`seq`, one more per fresh frame), and injects
//! its host faults: during a `repeated_twist` fault it sends its last frame again, unchanged;
//! during a `non_finite_twist` fault three frames with a NaN and infinities each command
//! period.
//!
//! The node only says what it sends and when ([`HostNode::frames_until`]); the engine that
//! owns the bus queues the frames.

use firmware::CanFrame;
use firmware::protocol::robot::{self, Command, TwistCmd};

/// The three `TWIST_CMD` frames a `non_finite_twist` fault injects, around the setpoint
/// `twist`: `vx` NaN, `vy` +∞, `wz` −∞, as they reach the wire.
///
/// The i16 fields cannot carry a non-finite number. NaN goes out as the raw value `-32768`,
/// which the DBC reserves as "invalid" (the project's own encoder writes a NaN as 0, a valid
/// stop; a host that marks NaN as invalid sends this). An infinity saturates to the field's
/// extreme, ±32.767, far beyond any speed limit. The firmware must reject all three.
#[must_use]
pub fn non_finite_twist_frames(twist: [f32; 3], seq: u8) -> [CanFrame; 3] {
    let [vx, vy, wz] = twist;
    let frame = |vx, vy, wz| Command::Twist(TwistCmd { vx, vy, wz, seq }).to_can_frame();
    let mut nan = frame(0.0, vy, wz);
    let offset = robot::layout::TWIST_VX.offset;
    let mut data = [0u8; 8];
    data.copy_from_slice(embedded_can::Frame::data(&nan));
    data[offset..offset + 2].copy_from_slice(&i16::MIN.to_le_bytes());
    if let embedded_can::Id::Standard(id) = embedded_can::Frame::id(&nan) {
        nan = CanFrame::from_buffer(id, data, 8);
    }
    [
        nan,
        frame(vx, f32::INFINITY, wz),
        frame(vx, vy, f32::NEG_INFINITY),
    ]
}

/// What the host does at one moment: one step of its script.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum HostAction {
    /// Send this command once.
    Send(Command),
    /// Stream this twist from now on.
    Twist([f32; 3]),
    /// Stop (`false`) or resume (`true`) streaming.
    Stream(bool),
    /// Send this frame once (a parameter request to the robot's service).
    Frame(CanFrame),
}

/// What a host fault sends.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HostFaultKind {
    /// `non_finite_twist`: [`non_finite_twist_frames`] once per command period.
    NonFiniteTwist,
    /// `repeated_twist`: the last twist frame again, unchanged, instead of a fresh one.
    RepeatedTwist,
}

/// A host fault: what, when.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HostFault {
    /// What it sends.
    pub kind: HostFaultKind,
    /// Start, µs.
    pub from_us: u64,
    /// End, µs.
    pub until_us: u64,
}

impl HostFault {
    /// Whether the fault is active at `t_us`.
    #[must_use]
    pub const fn active(&self, t_us: u64) -> bool {
        self.from_us <= t_us && t_us < self.until_us
    }
}

/// The host node. See the [module documentation](self).
#[derive(Debug, Clone)]
pub struct HostNode {
    actions: Vec<(u64, HostAction)>,
    faults: Vec<HostFault>,
    twist: [f32; 3],
    streaming: bool,
    /// The next twist's `seq`: one more in every fresh frame.
    seq: u8,
    /// The last fresh twist frame, which a `repeated_twist` fault sends again.
    last_twist: Option<CanFrame>,
    next_action: usize,
    command_period_us: u64,
    next_command_us: u64,
    /// Per host fault: when its next injection is due, µs.
    next_injection_us: Vec<u64>,
}

impl HostNode {
    /// A host that plays `script` (time µs, action; in time order), streams its twist every
    /// `command_hz`-th of a second and injects `faults`; before its first action.
    #[must_use]
    pub fn new(script: Vec<(u64, HostAction)>, command_hz: f64, faults: Vec<HostFault>) -> Self {
        let next_injection_us = faults.iter().map(|f| f.from_us).collect();
        Self {
            actions: script,
            faults,
            twist: [0.0; 3],
            streaming: false,
            seq: 0,
            last_twist: None,
            next_action: 0,
            command_period_us: (1e6 / command_hz).round().max(1.0) as u64,
            next_command_us: 0,
            next_injection_us,
        }
    }

    /// The twist setpoint the host streams.
    #[must_use]
    pub const fn twist(&self) -> [f32; 3] {
        self.twist
    }

    /// The frames the host sends up to `t_us` (inclusive) that it has not sent yet, appended
    /// to `out` as (send time in ns, frame) in the order it sends them: the actions due, then
    /// the twist stream, then the injected faults. Each change of the twist setpoint is
    /// appended to `twists` as (ns, twist).
    pub fn frames_until(
        &mut self,
        t_us: u64,
        out: &mut Vec<(u64, CanFrame)>,
        twists: &mut Vec<(u64, [f32; 3])>,
    ) {
        while let Some(&(at_us, action)) = self.actions.get(self.next_action)
            && at_us <= t_us
        {
            match action {
                HostAction::Send(cmd) => out.push((at_us * 1000, cmd.to_can_frame())),
                HostAction::Frame(frame) => out.push((at_us * 1000, frame)),
                HostAction::Twist(tw) => {
                    self.twist = tw;
                    self.streaming = true;
                    self.next_command_us = at_us;
                    twists.push((at_us * 1000, tw));
                }
                HostAction::Stream(on) => {
                    self.streaming = on;
                    self.next_command_us = at_us;
                }
            }
            self.next_action += 1;
        }
        // Every command due by now (more than one a step when command_hz > control_hz).
        while self.streaming && self.next_command_us <= t_us {
            let at_us = self.next_command_us;
            let repeating = self
                .faults
                .iter()
                .any(|f| f.kind == HostFaultKind::RepeatedTwist && f.active(at_us));
            let frame = match self.last_twist {
                Some(last) if repeating => last,
                _ => {
                    let [vx, vy, wz] = self.twist;
                    let frame = Command::Twist(TwistCmd {
                        vx,
                        vy,
                        wz,
                        seq: self.seq,
                    })
                    .to_can_frame();
                    self.seq = self.seq.wrapping_add(1);
                    self.last_twist = Some(frame);
                    frame
                }
            };
            out.push((at_us * 1000, frame));
            self.next_command_us += self.command_period_us;
        }
        for (fault, next_us) in self.faults.iter().zip(&mut self.next_injection_us) {
            if fault.kind != HostFaultKind::NonFiniteTwist {
                continue;
            }
            while *next_us <= t_us && *next_us < fault.until_us {
                for frame in non_finite_twist_frames(self.twist, self.seq) {
                    out.push((*next_us * 1000, frame));
                }
                *next_us += self.command_period_us;
            }
        }
    }
}
