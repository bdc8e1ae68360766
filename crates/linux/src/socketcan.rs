//! The SocketCAN adapter: [`SocketCanBus`] on a raw CAN socket, and why an interface cannot
//! be used ([`OpenError`]).

use std::io;
use std::path::PathBuf;

use embedded_can::Frame as _;

use firmware::CanFrame;

use crate::bus::{Bus, BusErrorFrame};
use crate::run::id_text;

/// Why a SocketCAN interface could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    /// No interface of that name.
    #[error(
        "CAN interface {iface:?} does not exist ({source}); a virtual one: \
         `ip link add dev {iface} type vcan && ip link set up {iface}`"
    )]
    NoSuchInterface {
        /// The interface name.
        iface: String,
        /// The OS error.
        source: io::Error,
    },
    /// The kernel has no SocketCAN (`EAFNOSUPPORT`).
    #[error(
        "cannot open CAN interface {iface:?}: no SocketCAN in this kernel, or the can and \
         can_raw modules are not loaded ({source})"
    )]
    NoSocketCan {
        /// The interface name.
        iface: String,
        /// The OS error.
        source: io::Error,
    },
    /// The interface exists but is down.
    #[error(
        "CAN interface {iface:?} is down (flags {flags:#x} in {}); bring it up: \
         `ip link set up {iface}`",
        .path.display()
    )]
    Down {
        /// The interface name.
        iface: String,
        /// The interface flags read.
        flags: u32,
        /// Where they were read.
        path: PathBuf,
    },
    /// Any other error while opening or configuring the socket.
    #[error("cannot open CAN interface {iface:?}: {source}")]
    Io {
        /// The interface name.
        iface: String,
        /// The OS error.
        source: io::Error,
    },
}

/// The error frames [`SocketCanBus`] asks SocketCAN for: every class (`CAN_ERR_MASK`) but
/// lost arbitration (`CAN_ERR_LOSTARB`, 0x2), which is how a CAN bus shares itself, not a
/// fault: on a busy bus it would drown the real errors.
const ERROR_CLASSES: u32 = libc::CAN_ERR_MASK & !libc::CAN_ERR_LOSTARB;

/// A raw SocketCAN socket on one interface, non-blocking, classic CAN frames, and the
/// controller's error frames (every class but lost arbitration: bus errors, error-passive,
/// bus-off, restarts, missing ACKs), which SocketCAN does not deliver unless asked to.
#[derive(Debug)]
pub struct SocketCanBus {
    socket: socketcan::CanSocket,
    iface: String,
}

impl SocketCanBus {
    /// Opens `iface` (e.g. `vcan0`, `can0`) in non-blocking mode and checks that it is up.
    ///
    /// # Errors
    /// An [`OpenError`] naming the interface.
    pub fn open(iface: &str) -> Result<Self, OpenError> {
        use socketcan::{Socket as _, SocketOptions as _};
        let socket = socketcan::CanSocket::open(iface).map_err(|source| {
            let iface = iface.to_string();
            match source.raw_os_error() {
                Some(libc::ENODEV | libc::ENXIO) => OpenError::NoSuchInterface { iface, source },
                Some(libc::EAFNOSUPPORT | libc::EPROTONOSUPPORT) => {
                    OpenError::NoSocketCan { iface, source }
                }
                _ if source.kind() == io::ErrorKind::NotFound => {
                    OpenError::NoSuchInterface { iface, source }
                }
                _ => OpenError::Io { iface, source },
            }
        })?;
        socket
            .set_nonblocking(true)
            .and_then(|()| socket.set_error_filter(ERROR_CLASSES))
            .map_err(|source| OpenError::Io {
                iface: iface.to_string(),
                source,
            })?;
        // Writes to a down interface fail with ENETDOWN: refuse at startup instead. The flags
        // file may be unreadable (no sysfs): then the check is skipped.
        let path = PathBuf::from(format!("/sys/class/net/{iface}/flags"));
        if let Ok(text) = std::fs::read_to_string(&path)
            && let Ok(flags) = u32::from_str_radix(text.trim().trim_start_matches("0x"), 16)
            && flags & 1 == 0
        {
            return Err(OpenError::Down {
                iface: iface.to_string(),
                flags,
                path,
            });
        }
        Ok(Self {
            socket,
            iface: iface.to_string(),
        })
    }

    /// The interface's name.
    #[must_use]
    pub fn iface(&self) -> &str {
        &self.iface
    }

    /// From now on receives only the standard frames of id `id`, and no error frames: what
    /// a client of one node's service listens to ([`SdoClient`](crate::SdoClient)).
    ///
    /// # Errors
    /// The socket refused the filter.
    pub fn listen_only(&mut self, id: u16) -> io::Result<()> {
        use socketcan::{Socket as _, SocketOptions as _};
        let mask = libc::CAN_SFF_MASK | libc::CAN_EFF_FLAG | libc::CAN_RTR_FLAG;
        self.socket
            .set_filters(&[socketcan::CanFilter::new(u32::from(id), mask)])?;
        self.socket.set_error_filter(0)?;
        // What the socket held before the filter is stale.
        while self.socket.read_frame().is_ok() {}
        Ok(())
    }
}

impl crate::sdo::FramePort for SocketCanBus {
    fn send(&mut self, frame: &CanFrame) -> io::Result<()> {
        Bus::send(self, frame)
    }

    fn recv_timeout(&mut self, timeout: std::time::Duration) -> io::Result<Option<CanFrame>> {
        use socketcan::Socket as _;
        if let Some(frame) = self.try_recv()? {
            return Ok(Some(frame));
        }
        match self.socket.read_frame_timeout(timeout) {
            Ok(frame) => convert(frame).map(Some),
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock
                ) =>
            {
                Ok(None)
            }
            Err(e) => Err(e),
        }
    }
}

/// A frame read from the socket: an error frame as a [`BusErrorFrame`] error, a frame that is
/// not classic CAN as `InvalidData`.
fn convert(frame: socketcan::CanFrame) -> io::Result<CanFrame> {
    if let socketcan::CanFrame::Error(e) = frame {
        return Err(io::Error::other(BusErrorFrame(e.into_error().to_string())));
    }
    CanFrame::from_frame(&frame).ok_or_else(|| {
        io::Error::new(
            io::ErrorKind::InvalidData,
            format!("frame with DLC {} is not a classic CAN frame", frame.dlc()),
        )
    })
}

impl Bus for SocketCanBus {
    fn try_recv(&mut self) -> io::Result<Option<CanFrame>> {
        use socketcan::Socket as _;
        match self.socket.read_frame() {
            Ok(frame) => convert(frame).map(Some),
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => Ok(None),
            Err(e) => Err(e),
        }
    }

    fn send(&mut self, frame: &CanFrame) -> io::Result<()> {
        use socketcan::Socket as _;
        let frame: socketcan::CanFrame = frame.convert().ok_or_else(|| {
            io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("socketcan rejected frame {}", id_text(frame)),
            )
        })?;
        self.socket.write_frame(&frame)
    }

    /// Opens a new socket on the interface (see [`SocketCanBus::open`]): a socket whose
    /// device was removed stays dead even when a device of the same name comes back, and
    /// the frames queued before a link loss are stale. Fails while the interface is missing
    /// or down; costs a sysfs read and a socket when it does not.
    fn reopen(&mut self) -> io::Result<()> {
        let fresh = Self::open(&self.iface).map_err(io::Error::other)?;
        *self = fresh;
        Ok(())
    }
}
