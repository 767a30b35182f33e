//! The MAVLink side of the daemon. So far: connection addresses ([`address`]), which the
//! configuration validates at start.

pub mod address;

pub use address::LinkAddress;
