//! MAVLink connection addresses as mavlink-router and MAVSDK users write them:
//! `serial:/dev/ttyAMA0:921600`, `udpin:0.0.0.0:14540`, `udpout:127.0.0.1:14550`,
//! `tcpout:host:port`, `tcpin:host:port`.
//!
//! It lives with the settings because validating `mavlink.connection` parses it; the link
//! re-exports it. Why not `mavlink::ConnectionAddress::parse_address` (mavlink-core 0.21),
//! which reads the same syntax:
//! * its TCP, UDP and serial forms exist only with the crate's `transport-*` features,
//!   which build its own transports (and `serialport`); `link::transport` does its own I/O
//!   on tokio, so those features are left out;
//! * it keeps `host:port` as an unchecked string, so `udpin:0.0.0.0`, `tcpout::5760` or
//!   port 70000 would pass `mavloc config check` and fail only when the daemon connects;
//!   it also takes baud 0;
//! * it splits a serial address at the first colon, so a device path that has colons
//!   (`/dev/serial/by-path/pci-0000:00:14.0-usb-0:1:1.0-port0`) does not parse;
//! * its errors are `io::Error`s with fixed texts ("Protocol unsupported", "Invalid baud
//!   rate") that name neither the address nor the accepted forms, which ours do;
//! * it accepts `udpbcast:` and `file:`, which the transport does not implement.

use std::fmt;

/// A parsed connection address.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum LinkAddress {
    /// Serial device and baud rate.
    Serial { device: String, baud: u32 },
    /// Listen for UDP datagrams; answers go to whoever spoke last.
    UdpIn { host: String, port: u16 },
    /// Send UDP datagrams to a fixed peer.
    UdpOut { host: String, port: u16 },
    /// Accept one TCP client.
    TcpIn { host: String, port: u16 },
    /// Connect to a TCP server.
    TcpOut { host: String, port: u16 },
}

impl LinkAddress {
    /// Parses an address; the error says what was expected.
    pub fn parse(s: &str) -> Result<LinkAddress, String> {
        let (scheme, rest) = s.split_once(':').ok_or_else(|| {
            format!("`{s}` has no scheme; expected serial:, udpin:, udpout:, tcpin: or tcpout:")
        })?;
        type Make = fn(String, u16) -> LinkAddress;
        let make: Option<Make> = match scheme {
            "serial" => None,
            "udpin" => Some(|host, port| LinkAddress::UdpIn { host, port }),
            "udpout" => Some(|host, port| LinkAddress::UdpOut { host, port }),
            "tcpin" => Some(|host, port| LinkAddress::TcpIn { host, port }),
            "tcpout" => Some(|host, port| LinkAddress::TcpOut { host, port }),
            other => {
                let hint = match other {
                    "udp" => "; did you mean udpin (listen, e.g. for mavlink-router) or udpout (send to a fixed peer)?",
                    "tcp" => "; did you mean tcpin (listen) or tcpout (connect)?",
                    _ => "",
                };
                return Err(format!(
                    "`{s}`: unknown scheme `{other}`; expected serial, udpin, udpout, tcpin or tcpout{hint}"
                ));
            }
        };
        // The port or baud rate is after the last colon, so IPv6-free hosts and device
        // paths keep their own characters.
        let (head, tail) =
            rest.rsplit_once(':').ok_or_else(|| format!("`{s}` lacks a `:port` (or `:baud` for serial)"))?;
        if head.is_empty() {
            return Err(format!("`{s}` has an empty host or device"));
        }
        match make {
            None => match tail.parse::<u32>() {
                Ok(baud) if baud > 0 => Ok(LinkAddress::Serial { device: head.to_string(), baud }),
                _ => Err(format!("`{s}`: baud rate `{tail}` is not a positive integer")),
            },
            Some(make) => {
                let port = match tail.parse::<u16>() {
                    Ok(port) if port > 0 => port,
                    _ => return Err(format!("`{s}`: port `{tail}` is not in 1..=65535")),
                };
                // An IPv6 address goes in brackets (`udpin:[::1]:14540`), as in a URL; it was
                // refused as "not an IP address".
                let host = match head.strip_prefix('[').and_then(|h| h.strip_suffix(']')) {
                    Some(v6) => {
                        check_ipv6(s, head, v6)?;
                        v6
                    }
                    None if head.contains(':') => {
                        return Err(format!("`{s}`: an IPv6 address goes in brackets, as `[{head}]`"))
                    }
                    None => head,
                };
                check_host(s, host, matches!(scheme, "udpin" | "tcpin"))?;
                Ok(make(host.to_string(), port))
            }
        }
    }
}

/// An IPv6 address in brackets, with a zone (`fe80::1%eth0`, RFC 6874) where it is
/// link-local: a link-local address means nothing without the interface it is on, which
/// is how a companion computer reaches a ground station over USB or Ethernet with no
/// configured addresses. The system's resolver (getaddrinfo) turns the zone into the
/// socket's scope id when the link opens; an interface that does not exist is reported
/// then, since a USB network may appear only after the daemon starts.
fn check_ipv6(s: &str, head: &str, v6: &str) -> Result<(), String> {
    let (addr, zone) = match v6.split_once('%') {
        Some((a, z)) => (a, Some(z)),
        None => (v6, None),
    };
    let Ok(ip) = addr.parse::<std::net::Ipv6Addr>() else {
        return Err(format!("`{s}`: `{head}` is not an IPv6 address in brackets"));
    };
    match zone {
        None => Ok(()),
        Some(z) if !ip.is_unicast_link_local() => Err(format!(
            "`{s}`: a zone (`%{z}`) belongs only to a link-local address (fe80::/10), and `{addr}` is not one"
        )),
        // Interface names are at most 15 bytes on Linux (IFNAMSIZ 16 with the NUL).
        Some(z)
            if z.is_empty()
                || z.len() > 15
                || !z.bytes().all(|b| b.is_ascii_alphanumeric() || b"-_.@".contains(&b)) =>
        {
            Err(format!("`{s}`: `%{z}` is not a network interface name or index"))
        }
        Some(_) => Ok(()),
    }
}

/// A host mavloc can use: a listening link binds to an address of this machine (an IP
/// address or `localhost`); one that connects may name a host, but not something shaped
/// like an IPv4 address that is none (`999.1.1.1` would be looked up by DNS forever).
fn check_host(s: &str, host: &str, listening: bool) -> Result<(), String> {
    // A zone (`fe80::1%eth0`) was checked with its address.
    let ip = host.split('%').next().unwrap_or(host).parse::<std::net::IpAddr>().is_ok();
    let looks_ipv4 = host.split('.').count() == 4
        && host.split('.').all(|p| !p.is_empty() && p.bytes().all(|b| b.is_ascii_digit()));
    if looks_ipv4 && !ip {
        return Err(format!("`{s}`: `{host}` is not an IPv4 address (each part 0..=255)"));
    }
    if listening && !ip && host != "localhost" {
        return Err(format!(
            "`{s}`: a listening link binds to an address of this machine: an IP address (0.0.0.0 for all, 127.0.0.1 for loopback) or localhost, not `{host}`"
        ));
    }
    Ok(())
}

/// `host:port`, an IPv6 host in brackets.
pub fn host_port(host: &str, port: u16) -> String {
    if host.contains(':') {
        format!("[{host}]:{port}")
    } else {
        format!("{host}:{port}")
    }
}

impl fmt::Display for LinkAddress {
    /// The same syntax, which is also what the `mavlink` crate's `connect` accepts.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            LinkAddress::Serial { device, baud } => write!(f, "serial:{device}:{baud}"),
            LinkAddress::UdpIn { host, port } => write!(f, "udpin:{}", host_port(host, *port)),
            LinkAddress::UdpOut { host, port } => write!(f, "udpout:{}", host_port(host, *port)),
            LinkAddress::TcpIn { host, port } => write!(f, "tcpin:{}", host_port(host, *port)),
            LinkAddress::TcpOut { host, port } => write!(f, "tcpout:{}", host_port(host, *port)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_the_usual_forms_and_round_trips() {
        for s in [
            "serial:/dev/ttyAMA0:921600",
            "udpin:0.0.0.0:14540",
            "udpout:127.0.0.1:14550",
            "tcpout:localhost:5760",
            "tcpin:0.0.0.0:5760",
            "udpin:[::1]:14540",
            "tcpout:[fe80::1]:5760",
        ] {
            let a = LinkAddress::parse(s).unwrap();
            assert_eq!(a.to_string(), s);
        }
        assert_eq!(
            LinkAddress::parse("serial:/dev/ttyAMA0:921600").unwrap(),
            LinkAddress::Serial { device: "/dev/ttyAMA0".into(), baud: 921600 }
        );
    }

    #[test]
    fn an_ipv6_address_goes_in_brackets() {
        assert_eq!(
            LinkAddress::parse("tcpin:[::1]:5760").unwrap(),
            LinkAddress::TcpIn { host: "::1".into(), port: 5760 }
        );
        let e = LinkAddress::parse("udpin:::1:14540").unwrap_err();
        assert!(e.contains("goes in brackets, as `[::1]`"), "{e}");
        let e = LinkAddress::parse("udpin:[nope]:14540").unwrap_err();
        assert!(e.contains("`[nope]` is not an IPv6 address"), "{e}");
    }

    #[test]
    fn a_link_local_ipv6_address_carries_its_zone() {
        for s in
            ["udpin:[fe80::1%eth0]:14540", "udpout:[fe80::fc:ff:fe00:1%2]:14550", "tcpin:[fe80::1%usb0]:5760"]
        {
            assert_eq!(LinkAddress::parse(s).unwrap().to_string(), s);
        }
        let e = LinkAddress::parse("udpin:[::1%lo]:14540").unwrap_err();
        assert!(e.contains("only to a link-local address"), "{e}");
        let e = LinkAddress::parse("udpin:[fe80::1%]:14540").unwrap_err();
        assert!(e.contains("not a network interface"), "{e}");
        let e = LinkAddress::parse("udpin:[fe80::1%a b]:14540").unwrap_err();
        assert!(e.contains("not a network interface"), "{e}");
        let e = LinkAddress::parse("udpin:[fe80::zz%eth0]:14540").unwrap_err();
        assert!(e.contains("not an IPv6 address"), "{e}");
    }

    #[test]
    fn serial_device_paths_may_contain_colons() {
        let s = "serial:/dev/serial/by-path/pci-0000:00:14.0-usb-0:1:1.0-port0:57600";
        let device = "/dev/serial/by-path/pci-0000:00:14.0-usb-0:1:1.0-port0".to_string();
        assert_eq!(LinkAddress::parse(s).unwrap(), LinkAddress::Serial { device, baud: 57600 });
    }

    #[test]
    fn errors_say_what_is_wrong() {
        assert!(LinkAddress::parse("udp:1.2.3.4:5").unwrap_err().contains("unknown scheme"));
        assert!(LinkAddress::parse("udpin:0.0.0.0:70000").unwrap_err().contains("port"));
        assert!(LinkAddress::parse("udpin:0.0.0.0").unwrap_err().contains("port"));
        assert!(LinkAddress::parse("serial:/dev/ttyS0:fast").unwrap_err().contains("baud"));
        assert!(LinkAddress::parse("14540").unwrap_err().contains("scheme"));
        assert!(LinkAddress::parse("tcpout::5760").unwrap_err().contains("empty"));
    }

    #[test]
    fn hosts_that_cannot_work_are_refused_with_a_hint() {
        let e = LinkAddress::parse("udpin:999.1.1.1:14540").unwrap_err();
        assert!(e.contains("not an IPv4 address"), "{e}");
        let e = LinkAddress::parse("udpin:example.com:14540").unwrap_err();
        assert!(e.contains("binds to an address of this machine"), "{e}");
        assert!(LinkAddress::parse("udpin:localhost:14540").is_ok());
        assert!(LinkAddress::parse("tcpout:px4.local:5760").is_ok());
        let e = LinkAddress::parse("udp:127.0.0.1:14540").unwrap_err();
        assert!(e.contains("did you mean udpin"), "{e}");
    }
}
