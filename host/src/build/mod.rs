//! The material builder (`../shared/spec/scanner-pipeline.md` §2): from a
//! checkerboard scan, a diffuse-white scan and a sample scan to calibrated
//! region images (Fig. 8; Fig. 6 steps 1–3).
//!
//! - [`locate`]: each mirror's view of the sample in the checkerboard scan
//!   (silhouette, Fourier phase, checker corners);
//! - [`linalg`], [`plane`]: the small numerics under it.

pub mod linalg;
pub mod locate;
pub mod plane;
