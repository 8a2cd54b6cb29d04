//! # Scanner controller logic
//!
//! The firmware's whole behaviour as a hardware-independent `no_std` library
//! with no allocation: it runs unchanged on the STM32F411 (the board binary in
//! `firmware/board/`), on the PC inside `hil-sim`, in host unit tests, and on
//! a Cortex-M4 under QEMU (`firmware/qemu-tests/`).
//!
//! - [`step`]: the step generator the step-timer interrupt runs (O(1) integer
//!   work per step, Klipper-style interval/count/add segments).
//! - [`planner`]: trapezoidal profiles compressed into segments whose step
//!   times are within one timer tick of the analytic profile.
//! - [`controller`]: request dispatcher, homing, capture sequencer, safety.
//! - [`hal`]: the small traits the hardware implements.
//! - [`config`]: axis defaults from spec/hardware.md and the persisted blob.
//! - [`strobe`]: the watch of the camera's exposure strobe.
//! - [`bootloader`]: the way into the chip's ROM bootloader (USB DFU).
//!
//! Time is always passed in as ticks of [`hal::TICK_HZ`]; nothing reads a clock.
#![no_std]
#![warn(missing_docs)]

pub mod bootloader;
#[cfg(feature = "selftest")]
pub mod chaos;
pub mod config;
pub mod controller;
pub mod hal;
pub mod planner;
#[cfg(feature = "selftest")]
pub mod selftest;
pub mod step;
pub mod strobe;
#[cfg(feature = "selftest")]
pub mod testkit;
pub mod timer;
pub mod trigger;
#[cfg(feature = "usb")]
pub mod usb;

pub use controller::Controller;
pub use protocol;
