//! The address a live server binds: `--live [ADDR]`.

use std::net::{IpAddr, Ipv4Addr, SocketAddr, ToSocketAddrs};

/// Foxglove's default port for the WebSocket protocol.
pub const DEFAULT_PORT: u16 = 8765;

/// Where a live server listens unless another address is named: loopback only.
pub const DEFAULT_ADDR: SocketAddr = SocketAddr::new(IpAddr::V4(Ipv4Addr::LOCALHOST), DEFAULT_PORT);

/// The address of `--live ADDR`: `HOST:PORT` (`127.0.0.1:8765`, `[::1]:9000`,
/// `localhost:9000`), an IP address alone (port [`DEFAULT_PORT`]), or a port alone (on
/// loopback). Port 0 asks the system for a free port.
///
/// # Errors
/// A message naming the value and what is expected.
pub fn parse_addr(s: &str) -> Result<SocketAddr, String> {
    let t = s.trim();
    if let Ok(addr) = t.parse::<SocketAddr>() {
        return Ok(addr);
    }
    if let Ok(ip) = t
        .trim_start_matches('[')
        .trim_end_matches(']')
        .parse::<IpAddr>()
    {
        return Ok(SocketAddr::new(ip, DEFAULT_PORT));
    }
    if let Ok(port) = t.parse::<u16>() {
        return Ok(SocketAddr::new(DEFAULT_ADDR.ip(), port));
    }
    if t.contains(':')
        && let Ok(mut addrs) = t.to_socket_addrs()
        && let Some(addr) = addrs.next()
    {
        return Ok(addr);
    }
    Err(format!(
        "{s:?}: expected an address to serve on, such as 127.0.0.1:8765, a port, or an IP address"
    ))
}

/// Whether a server on `addr` can be reached from other machines (not loopback): the
/// protocol has no authentication, so a program warns then.
#[must_use]
pub fn is_exposed(addr: SocketAddr) -> bool {
    !addr.ip().is_loopback()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn addresses_ports_and_hosts() {
        let ok = |s: &str| parse_addr(s).unwrap().to_string();
        assert_eq!(ok("127.0.0.1:9000"), "127.0.0.1:9000");
        assert_eq!(ok("0.0.0.0:9000"), "0.0.0.0:9000");
        assert_eq!(ok("0.0.0.0"), "0.0.0.0:8765");
        assert_eq!(ok("9000"), "127.0.0.1:9000");
        assert_eq!(ok("0"), "127.0.0.1:0");
        assert_eq!(ok("[::1]:9000"), "[::1]:9000");
        assert_eq!(ok("::1"), "[::1]:8765");
        assert!(parse_addr("localhost:9000").unwrap().ip().is_loopback());
        let err = parse_addr("nowhere").unwrap_err();
        assert!(
            err.contains("\"nowhere\"") && err.contains("127.0.0.1:8765"),
            "{err}"
        );
        assert!(parse_addr("1.2.3.4:99999").is_err());
    }

    #[test]
    fn only_loopback_is_not_exposed() {
        assert!(!is_exposed(DEFAULT_ADDR));
        assert!(!is_exposed(parse_addr("[::1]:1").unwrap()));
        assert!(is_exposed(parse_addr("0.0.0.0:1").unwrap()));
        assert!(is_exposed(parse_addr("192.168.1.2:1").unwrap()));
    }
}
