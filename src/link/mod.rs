//! The MAVLink side of the daemon, protocol without sockets where it can be:
//!
//! * [`address`]: connection addresses as mavlink-router and MAVSDK users write them.
//! * [`codec`]: framing (MAVLink 1 and 2 in, MAVLink 2 out), skip counters.
//! * [`params`]: the MAVLink parameters (names, types, checks, persistence).
//! * [`signing`]: MAVLink 2 signing keys, signatures, replay protection.
//! * [`transport`]: serial, UDP and TCP with reconnection; the only part that does I/O.

pub mod address;
pub mod codec;
pub mod params;
pub mod signing;
pub mod transport;

pub use address::LinkAddress;
