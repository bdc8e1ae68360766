//! A blocking client of one CANopen node's expedited SDO service: one request, its answer or
//! nothing within a time-out. What a host program (a live server's parameters) uses to talk
//! to the robot's parameter service (`firmware::params`), on a SocketCAN interface or on a
//! simulated bus ([`FramePort`]).
//!
//! The matching is CiA 301's: the answer comes on `0x580 + node` and names the request's
//! object with the command that answers it ([`SdoResponse::answers`]); anything else on that id
//! (a late answer to an earlier request, another client's) is passed over. CANopen gives a
//! server one client at a time: two clients of the same node at once (this one and
//! `mecanum-drive param`, say) may take each other's answers to a request on the same object.

use std::io;
use std::time::{Duration, Instant};

use firmware::CanFrame;
use firmware::protocol::canopen::{self, Message, NodeId, SdoRequest, SdoResponse, layout};

use crate::bus::is_busy;
use crate::socketcan::{OpenError, SocketCanBus};

/// Where an [`SdoClient`] sends its requests and reads the answers.
pub trait FramePort {
    /// Hands `frame` to the bus.
    ///
    /// # Errors
    /// The bus refused it (a full queue is [`is_busy`]).
    fn send(&mut self, frame: &CanFrame) -> io::Result<()>;

    /// The next frame received within `timeout`, or `None`.
    ///
    /// # Errors
    /// The bus failed.
    fn recv_timeout(&mut self, timeout: Duration) -> io::Result<Option<CanFrame>>;
}

/// A client of node `node`'s SDO service over a [`FramePort`].
#[derive(Debug)]
pub struct SdoClient<P> {
    port: P,
    node: NodeId,
}

impl<P: FramePort> SdoClient<P> {
    /// A client of `node` on `port`, which should receive the node's answers
    /// (`0x580 + node`; [`SocketCanBus::listen_only`](crate::SocketCanBus::listen_only)).
    pub const fn new(port: P, node: NodeId) -> Self {
        Self { port, node }
    }

    /// The node served.
    #[must_use]
    pub const fn node(&self) -> NodeId {
        self.node
    }

    /// Sends `request` and returns its answer, or `None` when none came within `timeout` (a
    /// transmit queue that stays full for that long counts as no answer).
    ///
    /// # Errors
    /// The port failed.
    pub fn exchange(
        &mut self,
        request: SdoRequest,
        timeout: Duration,
    ) -> io::Result<Option<SdoResponse>> {
        let deadline = Instant::now() + timeout;
        let left = || deadline.saturating_duration_since(Instant::now());
        // Answers to earlier requests that came after their time-out.
        while self.port.recv_timeout(Duration::ZERO)?.is_some() {}
        let frame = Message::SdoRequest {
            node: self.node,
            request,
        }
        .to_can_frame();
        loop {
            match self.port.send(&frame) {
                Ok(()) => break,
                Err(e) if is_busy(&e) && !left().is_zero() => {
                    std::thread::sleep(Duration::from_millis(1).min(left()));
                }
                Err(e) if is_busy(&e) => return Ok(None),
                Err(e) => return Err(e),
            }
        }
        while let Some(frame) = self.port.recv_timeout(left())? {
            if let Ok(Message::SdoResponse { node, response }) = canopen::decode(&frame)
                && node == self.node
                && response.answers(&request)
            {
                return Ok(Some(response));
            }
            if left().is_zero() {
                break;
            }
        }
        Ok(None)
    }
}

impl SdoClient<SocketCanBus> {
    /// A client of node `node` (1..=127; the robot's parameter service is
    /// `firmware::params::service_node`) on the SocketCAN interface `iface`, on a socket of
    /// its own that receives only the node's answers. A program on the same interface as the
    /// node (the runner) reaches it too: SocketCAN delivers a frame to every other socket of
    /// the interface.
    ///
    /// # Errors
    /// The interface cannot be used ([`OpenError`], naming it), or `node` is no node id.
    pub fn open(iface: &str, node: u8) -> Result<Self, OpenError> {
        let io_error = |source| OpenError::Io {
            iface: iface.to_string(),
            source,
        };
        let node = NodeId::new(node).ok_or_else(|| {
            io_error(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("SDO client of node {node}: a CANopen node id is 1..=127"),
            ))
        })?;
        let mut bus = SocketCanBus::open(iface)?;
        bus.listen_only(layout::SDO_RESPONSE.id + u16::from(node.get()))
            .map_err(io_error)?;
        Ok(Self::new(bus, node))
    }
}

#[cfg(test)]
mod tests {
    use std::collections::VecDeque;

    use super::*;

    /// A port whose "bus" answers each request with the frames queued for it.
    struct Scripted {
        sent: Vec<CanFrame>,
        answers: VecDeque<Vec<CanFrame>>,
        inbox: VecDeque<CanFrame>,
    }

    impl FramePort for Scripted {
        fn send(&mut self, frame: &CanFrame) -> io::Result<()> {
            self.sent.push(*frame);
            self.inbox
                .extend(self.answers.pop_front().unwrap_or_default());
            Ok(())
        }

        fn recv_timeout(&mut self, _: Duration) -> io::Result<Option<CanFrame>> {
            Ok(self.inbox.pop_front())
        }
    }

    fn answer(node: u8, response: SdoResponse) -> CanFrame {
        let node = NodeId::new(node).unwrap();
        Message::SdoResponse { node, response }.to_can_frame()
    }

    #[test]
    fn the_answer_is_the_one_to_the_request_from_the_node_asked() {
        let read = SdoRequest::Upload {
            index: 0x2001,
            sub: 1,
        };
        let value = SdoResponse::Uploaded {
            index: 0x2001,
            sub: 1,
            value: 7,
            size: 4,
        };
        let stale = SdoResponse::Uploaded {
            index: 0x2001,
            sub: 2,
            value: 9,
            size: 4,
        };
        let port = Scripted {
            sent: Vec::new(),
            // Another node's answer, an answer about another object, then the answer.
            answers: VecDeque::from([vec![
                answer(5, value),
                answer(127, stale),
                answer(127, value),
            ]]),
            // Left over from an earlier request: dropped before sending.
            inbox: VecDeque::from([answer(127, value)]),
        };
        let mut client = SdoClient::new(port, NodeId::new(127).unwrap());
        let got = client.exchange(read, Duration::from_millis(10)).unwrap();
        assert_eq!(got, Some(value));
        assert_eq!(client.port.sent.len(), 1);
        assert!(client.port.inbox.is_empty());
        // Nothing answers: None, not an error.
        assert_eq!(client.exchange(read, Duration::ZERO).unwrap(), None);
    }
}
