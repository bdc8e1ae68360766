//! The nodes of one `protocol = "cia402"` configuration on one bus: each frame of the master
//! given to the nodes it is for, and their frames collected in time order.

use embedded_can::{Frame, Id};

use super::{Axes, Drive402, Options, Timing};
use crate::CanFrame;
use crate::config::{Cia402Drive, Config, Drive};
use crate::protocol::canopen::{self, Message, NodeId};

/// Nodes a configuration can have (one per wheel at most).
const NODES: usize = 4;

/// The CiA 402 nodes of a configuration.
#[derive(Debug, Clone, Default)]
pub struct Drives402 {
    nodes: heapless::Vec<Drive402, NODES>,
}

impl Drives402 {
    /// The nodes of a `Drive::Cia402` configuration (none for another drive), one per node id
    /// in the order they first appear, each driving its wheels on their sub-indices, all
    /// powered on at time 0.
    #[must_use]
    pub fn new(config: &Config, timing: Timing, options: Options) -> Self {
        let Drive::Cia402(Cia402Drive { node_ids, axes, .. }) = config.drive else {
            return Self::default();
        };
        let mut wheels: heapless::Vec<(NodeId, [Option<u8>; 3]), NODES> = heapless::Vec::new();
        for (wheel, (&id, &axis)) in (0u8..).zip(node_ids.iter().zip(&axes)) {
            let Some(id) = NodeId::new(id) else { continue };
            let i = match wheels.iter().position(|(n, _)| *n == id) {
                Some(i) => i,
                None => {
                    // At most one node per wheel: always room.
                    let _ = wheels.push((id, [None; 3]));
                    wheels.len() - 1
                }
            };
            if let Some(slot) = wheels[i].1.get_mut(usize::from(axis)) {
                *slot = Some(wheel);
            }
        }
        let mut nodes = heapless::Vec::new();
        for (id, w) in wheels {
            let _ = nodes.push(Drive402::new(id, w, timing, options));
        }
        Self { nodes }
    }

    /// The nodes.
    #[must_use]
    pub fn nodes(&self) -> &[Drive402] {
        &self.nodes
    }

    /// The nodes, to give faults to.
    pub fn nodes_mut(&mut self) -> &mut [Drive402] {
        &mut self.nodes
    }

    /// Node `id`.
    #[must_use]
    pub fn node(&self, id: u8) -> Option<&Drive402> {
        self.nodes.iter().find(|n| n.id().get() == id)
    }

    /// Node `id`, to give faults to.
    pub fn node_mut(&mut self, id: u8) -> Option<&mut Drive402> {
        self.nodes.iter_mut().find(|n| n.id().get() == id)
    }

    /// EMCY frames the nodes sent so far.
    #[must_use]
    pub fn emcy_sent(&self) -> u32 {
        self.nodes.iter().map(Drive402::emcy_sent).sum()
    }

    /// A frame on the bus at `t_ns`. PDOs first, their ids being whatever the master mapped:
    /// the first node with a valid RPDO on the id takes it. Then NMT (to its nodes), SYNC (to
    /// all), SDO requests (to theirs) and heartbeats (the consumers').
    pub fn on_frame(&mut self, t_ns: u64, frame: &CanFrame, axes: &mut impl Axes) {
        let Id::Standard(id) = frame.id() else { return };
        let raw = id.as_raw();
        for n in &mut self.nodes {
            if let Some(k) = n.rpdo_on(raw) {
                n.on_rpdo(k, t_ns, frame.data(), axes);
                return;
            }
        }
        match canopen::decode(frame) {
            Ok(Message::Nmt { command, node }) => {
                for n in &mut self.nodes {
                    if node.is_none_or(|id| id == n.id()) {
                        n.on_nmt(command, t_ns, axes);
                    }
                }
            }
            Ok(Message::Sync { .. }) => {
                for n in &mut self.nodes {
                    n.on_sync(t_ns, axes);
                }
            }
            Ok(Message::SdoRequest { node, request }) => {
                if let Some(n) = self.nodes.iter_mut().find(|n| n.id() == node) {
                    n.on_sdo(request, t_ns);
                }
            }
            Ok(Message::Heartbeat { node, .. }) => {
                for n in &mut self.nodes {
                    n.on_heartbeat(node, t_ns);
                }
            }
            _ => {}
        }
    }

    /// The frames the nodes send up to `until_ns` (answers, TPDOs, heartbeats, EMCY), in time
    /// order (at one time: by node, then as queued), and the master's heartbeat watched.
    pub fn feedback(
        &mut self,
        until_ns: u64,
        axes: &mut impl Axes,
        mut out: impl FnMut(u64, CanFrame),
    ) {
        for n in &mut self.nodes {
            n.run_to(until_ns, axes);
        }
        loop {
            let mut next: Option<(u64, usize)> = None;
            for (i, n) in self.nodes.iter().enumerate() {
                let t = n.next_queued_ns();
                if t <= until_ns && next.is_none_or(|(best, _)| t < best) {
                    next = Some((t, i));
                }
            }
            let Some((_, i)) = next else { break };
            if let Some((t, frame)) = self.nodes[i].pop_due(until_ns) {
                out(t, frame);
            }
        }
    }

    /// When the nodes' next frame is due: one queued, or a heartbeat.
    #[must_use]
    pub fn next_due_ns(&self) -> u64 {
        self.nodes
            .iter()
            .map(Drive402::next_due_ns)
            .min()
            .unwrap_or(u64::MAX)
    }
}
