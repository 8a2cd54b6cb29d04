//! The simulated scanner: firmware logic with simulated hardware.

pub use protocol;
