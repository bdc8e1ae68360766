//! The bus as the loop needs it ([`Bus`]), and how its errors read: busy, a lost link, an
//! error frame.

use core::fmt;
use std::io;

use serde::Serialize;

use firmware::CanFrame;

/// A CAN bus as the runner needs it: a non-blocking receive and a send.
pub trait Bus {
    /// The next received frame, `Ok(None)` when none is waiting. Must not block.
    ///
    /// # Errors
    /// Whatever the bus reports; the runner counts it and stops draining for this step.
    fn try_recv(&mut self) -> io::Result<Option<CanFrame>>;

    /// Queues one frame for sending. Should not block for long; a full queue is reported as
    /// an error that [`is_busy`] recognises, and the runner retries it.
    ///
    /// # Errors
    /// Whatever the bus reports.
    fn send(&mut self, frame: &CanFrame) -> io::Result<()>;

    /// Makes the bus usable again after a link loss ([`ErrorKind::LinkDown`],
    /// [`ErrorKind::NoDevice`]): for SocketCAN, opens a new socket on the interface once it
    /// exists and is up. Called by the runner with a back-off while the link is down, from
    /// the loop's thread, so it must not block. The default does nothing and succeeds (a bus
    /// that recovers by itself).
    ///
    /// # Errors
    /// The bus is still unusable; the runner tries again later.
    fn reopen(&mut self) -> io::Result<()> {
        Ok(())
    }
}

/// Whether a send error means "the transmit queue is full, try again shortly": `ENOBUFS`
/// (interface queue full) or `EAGAIN`/`EWOULDBLOCK` (socket buffer full).
#[must_use]
pub fn is_busy(error: &io::Error) -> bool {
    error.kind() == io::ErrorKind::WouldBlock || error.raw_os_error() == Some(libc::ENOBUFS)
}

/// What an I/O error of the bus means to the runner, for the counters ([`ErrorCounts`](crate::ErrorCounts)) and
/// the link handling (see [The link](crate::run_recorded#the-link)).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorKind {
    /// The transmit queue is full ([`is_busy`]): retried.
    Busy,
    /// The link is down (`ENETDOWN`): a link loss.
    LinkDown,
    /// The device is gone (`ENODEV`, `ENXIO`: unplugged, or removed): a link loss; the bus
    /// must be reopened.
    NoDevice,
    /// Anything else.
    Other,
}

/// Classifies a bus error (see [`ErrorKind`]).
#[must_use]
pub fn classify(error: &io::Error) -> ErrorKind {
    if is_busy(error) {
        return ErrorKind::Busy;
    }
    match error.raw_os_error() {
        Some(libc::ENETDOWN) => ErrorKind::LinkDown,
        Some(libc::ENODEV | libc::ENXIO) => ErrorKind::NoDevice,
        _ => ErrorKind::Other,
    }
}

/// An error frame of the CAN controller, as [`Bus::try_recv`] of [`SocketCanBus`](crate::SocketCanBus) reports it
/// (inside an [`io::Error`]; see [`is_bus_error_frame`]): a bus error, error-passive or
/// bus-off, a controller problem (RX overflow), a restart, a missing ACK. The text is
/// SocketCAN's decoding of the frame.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BusErrorFrame(pub String);

impl fmt::Display for BusErrorFrame {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "error frame: {}", self.0)
    }
}

impl std::error::Error for BusErrorFrame {}

/// Whether `e` is a [`BusErrorFrame`]: a bus event to count, after which the bus goes on
/// delivering frames, unlike a failed read.
#[must_use]
pub fn is_bus_error_frame(e: &io::Error) -> bool {
    e.get_ref().is_some_and(|inner| inner.is::<BusErrorFrame>())
}
