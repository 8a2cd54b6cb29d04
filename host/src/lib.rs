//! # Host library
//!
//! The host side of the material scanner:
//! - [`link`]: transports (serial/CDC-ACM, USB bulk, the in-process
//!   simulator) and the protocol client; [`discovery`] finds scanners.
//! - [`camera`]: cameras on the trigger line (simulated, folder source).
//! - [`scan`]: mirror table set-up and scan capture into a scan directory
//!   (`docs/scan-format.md`), frames as OpenEXR ([`exrio`]).
//! - [`strobe`]: the camera's exposure strobe, as a scan reads it.
//! - [`exposure`], [`hdr`], [`defects`]: auto exposure, HDR merging, and
//!   the sensor's defective pixels found while metering.
//! - [`simulator`]: the simulated scanner as the host starts it.
//! - [`build`]: the material builder — calibration and region images.
//! - [`brdf`]: measured BRDFs — MERL tables, the NPF model, AWLS fitting,
//!   previews.
//!
//! Library code returns typed errors; only the command line ([`cli`]) uses
//! `anyhow`.

pub mod brdf;
pub mod build;
pub mod camera;
pub mod check;
#[cfg(feature = "cli")]
pub mod cli;
pub mod defects;
pub mod discovery;
pub mod exposure;
pub mod exrio;
pub mod frame_file;
pub mod fsutil;
pub mod hdr;
#[cfg(any(test, feature = "hostile-device"))]
pub mod hostile;
pub mod link;
pub mod scan;
#[cfg(feature = "sim")]
pub mod simulator;
pub(crate) mod stats;
pub mod strobe;

pub use protocol;
pub use scanner_geometry as geometry;
