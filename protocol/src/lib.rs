//! # Scanner wire protocol
//!
//! The one data-type crate that the firmware, the host and the simulator share
//! (postcard is not self-describing: both ends must compile the same schema).
//! `no_std`, no allocation: every buffer is sized at compile time from the
//! messages' [`MaxSize`](postcard::experimental::max_size::MaxSize).
//!
//! ## Layers
//! - [`msg`]: the message table. The host sends [`Request`]s; the device answers
//!   each with one [`Reply`] and sends unsolicited [`Event`]s, both wrapped in
//!   [`ToHost`].
//! - [`frame`]: `COBS(seq ‖ postcard(message) ‖ CRC-32C) ‖ 0x00` framing and the
//!   chunk-tolerant [`FrameDecoder`].
//!
//! ## Reliability contract
//! The host numbers requests with an 8-bit sequence number and keeps at most one
//! request outstanding. The device answers with the same number. If the reply
//! does not come (loss or corruption: the decoder drops bad frames), the host
//! sends the *same* frame again; the device recognises the repeated number and
//! re-sends its cached reply instead of executing the request twice.
//! [`Request::Hello`] always executes and resets that memory, so a new host
//! session may start numbering anywhere.
//!
//! The wire format is specified byte by byte in `docs/protocol.md`.
#![no_std]
#![warn(missing_docs)]

// The `arbitrary` derive (tests and fuzzing only) names `std`.
#[cfg(feature = "arbitrary")]
extern crate std;

pub mod frame;
pub mod msg;

pub use frame::{
    CRC, Feed, Frame, FrameDecoder, FrameError, MAX_FLUSHED_FRAME_LEN, MAX_FRAME_LEN, Message,
    decode_frame, encode_flushed_frame, encode_frame, max_frame_len,
};
pub use msg::*;

/// The protocol version this crate implements.
pub const PROTOCOL_VERSION: ProtocolVersion = ProtocolVersion { major: 1, minor: 5 };

/// The controller samples its inputs (switches, emergency stop, driver
/// fault, the camera's strobe) every this many µs: the resolution of every
/// edge it reports ([`StrobeWindow`], the switches' step counts).
pub const INPUT_SAMPLE_US: u32 = 200;

/// Largest disagreement between an axis' step count and its home or index
/// switch that still counts as "no steps lost", steps: the switch's
/// hysteresis and the 200 µs input sampling at full speed, with margin.
pub const POSITION_TOLERANCE_STEPS: i32 = 32;

/// Device interface GUID of the vendor-class bulk interface, announced in
/// the board's MS OS 2.0 descriptors (Windows binds WinUSB to it).
pub const USB_WINUSB_GUID: &str = "{6E3A5C51-8B7F-4F0C-9F2B-5C1A0D8E7B42}";

/// USB vendor id of the scanner controller (pid.codes open-source VID).
pub const USB_VID: u16 = 0x1209;
/// USB product id of the scanner controller.
pub const USB_PID: u16 = 0x5CA7;

/// Why a peer refuses to talk: the majors differ.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct VersionMismatch {
    /// Our version.
    pub ours: ProtocolVersion,
    /// The peer's version.
    pub theirs: ProtocolVersion,
}

impl core::fmt::Display for VersionMismatch {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(
            f,
            "incompatible protocol: we speak {}, the peer speaks {} (major versions differ); \
             update the firmware or the host so both speak {}.x",
            self.ours, self.theirs, self.ours.major
        )
    }
}

impl core::error::Error for VersionMismatch {}

/// Check a peer's protocol version against ours.
pub const fn check_version(theirs: ProtocolVersion) -> Result<(), VersionMismatch> {
    if PROTOCOL_VERSION.is_compatible_with(theirs) {
        Ok(())
    } else {
        Err(VersionMismatch { ours: PROTOCOL_VERSION, theirs })
    }
}

// Wire-size budgets from the foundation issue, checked at compile time for the
// worst case (every varint at its longest).
const _: () = assert!(MAX_FRAME_LEN <= 128, "frames must fit a 128-byte buffer");
