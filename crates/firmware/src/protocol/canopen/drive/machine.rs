//! The node's 402 state machine: the codec's drive side on each controlword, the option codes
//! of a shutdown and a disable operation, a quick stop or a slow down ended once the axes are
//! at rest, and what each state asks of the axes.

use super::node::Drive402;
use super::{Axes, AxisCommand};
use crate::protocol::canopen::DriveState402;

impl Drive402 {
    /// The 402 machine on a controlword; true if it reset a fault (the error register is then
    /// cleared). Transitions 8 and 5 with their option code (0x605B, 0x605C) at 1 slow down
    /// first, still operation enabled; operation enabled only in mode 3 (0x6060).
    pub(super) fn control(&mut self, cw: u16) -> bool {
        let state = self.state;
        let may_enable = self.od.get(0x6060, 0) == 3 && !self.faults.refuses_enable;
        let next = state.on_controlword(cw, self.last_controlword, may_enable);
        let option = match next {
            DriveState402::ReadyToSwitchOn => self.od.get(0x605B, 0),
            DriveState402::SwitchedOn => self.od.get(0x605C, 0),
            _ => 0,
        };
        let slows = state == DriveState402::OperationEnabled && option == 1;
        self.slowing_to = slows.then_some(next);
        self.state = if slows { state } else { next };
        self.last_controlword = cw;
        let reset = state == DriveState402::Fault && next != state;
        if reset {
            self.od.set(0x1001, 0, 0);
        }
        reset
    }

    /// What its state asks of the axis at sub-index `sub`: its target in operation enabled, to
    /// rest while slowing down or in quick stop, no torque otherwise.
    pub(super) fn command(&self, sub: usize) -> AxisCommand {
        match (self.state, self.slowing_to) {
            (DriveState402::OperationEnabled, None) => AxisCommand::Velocity(self.targets[sub]),
            (DriveState402::OperationEnabled, Some(_)) => AxisCommand::SlowDown,
            (DriveState402::QuickStopActive, _) => AxisCommand::QuickStop,
            _ => AxisCommand::Off,
        }
    }

    /// Commands each of its axes as its state says.
    pub(super) fn power(&self, axes: &mut impl Axes) {
        for (sub, wheel) in self.wheels.iter().enumerate() {
            if let Some(wheel) = wheel {
                axes.command(usize::from(*wheel), self.command(sub));
            }
        }
    }

    /// At a SYNC: a quick stop ends when the axes are at rest (switch on disabled, no power;
    /// unless the maker keeps quick stop active); so does a shutdown or disable operation on
    /// the slow down ramp, in its own next state.
    pub(super) fn settle(&mut self, axes: &mut impl Axes) {
        let at_rest = self
            .wheels
            .iter()
            .flatten()
            .all(|w| axes.at_rest(usize::from(*w)));
        let done = match (self.state, self.slowing_to) {
            (DriveState402::QuickStopActive, _) if !self.options.quick_stop_stays => {
                Some(DriveState402::SwitchOnDisabled)
            }
            (DriveState402::OperationEnabled, Some(next)) => Some(next),
            _ => None,
        };
        if let Some(next) = done
            && at_rest
        {
            self.state = next;
            self.slowing_to = None;
            self.power(axes);
        }
    }
}
