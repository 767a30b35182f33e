//! The MAVLink side of the daemon, protocol without sockets where it can be:
//!
//! * [`LinkAddress`]: connection addresses as mavlink-router and MAVSDK users write them;
//!   defined in [`crate::settings::address`], because validating the configuration parses
//!   them and the link depends on the settings, not the other way round.
//! * [`codec`]: framing (MAVLink 1 and 2 in, MAVLink 2 out), skip counters.
//! * [`params`]: the MAVLink parameters (names, types, checks, persistence).
//! * [`peers`]: whom a listening link talks to (frames that vouch, not datagrams).
//! * [`signing`]: MAVLink 2 signing keys, signatures, replay protection.
//! * [`transport`]: serial, UDP and TCP with reconnection; the only part that does I/O.

pub mod codec;
pub mod metadata;
pub mod params;
pub mod peers;
pub mod signing;
pub mod transport;

pub use crate::settings::address::{self, LinkAddress};
