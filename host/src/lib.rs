//! # Host library
//!
//! The host side of the material scanner: for now the measured-BRDF toolkit
//! ([`brdf`]: MERL tables, the NPF model, AWLS fitting, previews). The device
//! link, scan capture and material building come with their issues.
//!
//! Library code returns typed errors; only the `scanner` binary uses `anyhow`.

pub mod brdf;
pub mod fsutil;

pub use protocol;
