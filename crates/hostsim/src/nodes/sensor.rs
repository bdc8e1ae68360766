//! A sensor node on the plant: [`WithNode`] puts a node that samples the plant at instants
//! of its own (the IMU, [`crate::nodes::imu`]; the tracking pods, [`crate::nodes::pods`]) beside any
//! [`SimPlant`], and hands its frames to the runner ([`SimPlant::node_frames`]).
//!
//! The wrapper advances the plant to each sample instant, so a sample carries the state of
//! that instant, not of the end of the runner's period. Without a node it passes every call
//! through unchanged, so a run without the sensor is what it was before the sensor existed.
//! Instants on the plant's 1 ms grid are substep boundaries already; other rates split a
//! substep there (see `docs/simulator.md`).

use firmware::CanFrame;

use crate::bus::Node;
use crate::nodes::{DriveFaults, SimPlant};

/// A node that samples the plant at instants of its own and sends frames as bus node
/// [`Self::NODE`].
pub trait SensorNode {
    /// The bus node its frames go out as.
    const NODE: Node;
    /// When the next sample is due, ns of the plant's time.
    fn next_ns(&self) -> u64;
    /// The plant it is put on, at time 0 (a node that measures from the start).
    fn start<P: SimPlant + ?Sized>(&mut self, _plant: &P) {}
    /// The plant just advanced by `dt_ns` (a node that integrates what the plant does not).
    fn advanced<P: SimPlant + ?Sized>(&mut self, _plant: &P, _dt_ns: u64) {}
    /// Takes the sample due at `at_ns` ([`Self::next_ns`]) from the plant, which is there.
    fn measure<P: SimPlant + ?Sized>(&mut self, at_ns: u64, plant: &P);
    /// Moves the frames sent up to `until_ns` into `out`, in time order.
    fn drain(&mut self, until_ns: u64, out: &mut Vec<(u64, CanFrame)>);
}

/// A plant with a sensor node on it (none: a pass-through).
#[derive(Debug)]
pub struct WithNode<'a, P: SimPlant, N: SensorNode> {
    inner: &'a mut P,
    node: Option<N>,
    /// The plant's time, ns since the start (the runner's calls are all that moves it).
    now_ns: u64,
}

impl<'a, P: SimPlant, N: SensorNode> WithNode<'a, P, N> {
    /// `plant` (at time 0) with `node` on it.
    pub fn with(plant: &'a mut P, mut node: Option<N>) -> Self {
        if let Some(n) = &mut node {
            n.start(&*plant);
        }
        Self {
            inner: plant,
            node,
            now_ns: 0,
        }
    }

    /// The node, if there is one.
    #[must_use]
    pub const fn node(&self) -> Option<&N> {
        self.node.as_ref()
    }

    /// Advances the inner plant by `dt_ns` (> 0), telling the node.
    fn step_inner(&mut self, dt_ns: u64) {
        self.inner.advance_ns(dt_ns);
        self.now_ns += dt_ns;
        if let Some(node) = &mut self.node {
            node.advanced(&*self.inner, dt_ns);
        }
    }
}

impl<P: SimPlant, N: SensorNode> SimPlant for WithNode<'_, P, N> {
    fn on_frame(&mut self, t_us: u64, frame: &CanFrame) {
        self.inner.on_frame(t_us, frame);
    }

    fn feedback(&mut self, until_ns: u64, out: &mut Vec<(u64, CanFrame)>) {
        self.inner.feedback(until_ns, out);
    }

    fn node_frames(&mut self, node: Node, until_ns: u64, out: &mut Vec<(u64, CanFrame)>) {
        // The plant's own, if it has any (a test's), then this node's.
        self.inner.node_frames(node, until_ns, out);
        if node == N::NODE
            && let Some(n) = &mut self.node
        {
            n.drain(until_ns, out);
        }
    }

    fn advance(&mut self, dt: f64) {
        if self.node.is_none() {
            // Exactly the plant's own step, as without the node.
            self.inner.advance(dt);
            self.now_ns += crate::nodes::plant::round(dt * 1e9) as u64;
            return;
        }
        self.advance_ns(crate::nodes::plant::round(dt * 1e9) as u64);
    }

    fn advance_ns(&mut self, dt_ns: u64) {
        if self.node.is_none() {
            // Exactly the plant's own calls, zero-length ones too.
            self.inner.advance_ns(dt_ns);
            self.now_ns += dt_ns;
            return;
        }
        let end = self.now_ns + dt_ns;
        // Stop at each sample instant: the sample reads the state of that instant.
        while let Some(at) = self.node.as_ref().map(N::next_ns)
            && at <= end
        {
            if at > self.now_ns {
                self.step_inner(at - self.now_ns);
            }
            if let Some(node) = &mut self.node {
                node.measure(at, &*self.inner);
            }
        }
        if end > self.now_ns {
            self.step_inner(end - self.now_ns);
        }
    }

    fn next_feedback_ns(&self) -> u64 {
        let inner = self.inner.next_feedback_ns();
        self.node.as_ref().map_or(inner, |n| inner.min(n.next_ns()))
    }

    fn truth(&self) -> [f64; 3] {
        self.inner.truth()
    }

    fn truth_velocity(&self) -> [f64; 3] {
        self.inner.truth_velocity()
    }

    fn truth_travel(&self) -> Option<[f64; 3]> {
        self.inner.truth_travel()
    }

    fn set_faults(&mut self, at_ns: u64, stuck: [bool; 4], offline: [bool; 4]) {
        self.inner.set_faults(at_ns, stuck, offline);
    }

    fn set_drive_faults(&mut self, at_ns: u64, faults: [DriveFaults; 4]) {
        self.inner.set_drive_faults(at_ns, faults);
    }
}
