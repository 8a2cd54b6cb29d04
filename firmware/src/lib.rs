//! Scanner controller firmware logic (hardware-independent, `no_std`).
#![no_std]

pub use protocol;
