//! The material builder (`../shared/spec/scanner-pipeline.md` §2): from a
//! checkerboard scan, a diffuse-white scan and a sample scan to calibrated
//! region images (Fig. 8; Fig. 6 steps 1–3) and on to the material file.
//!
//! - [`locate`]: each mirror's view of the sample in the checkerboard scan
//!   (silhouette, Fourier phase, checker corners);
//! - [`linalg`], [`plane`]: the small numerics under it;
//! - [`palette`], [`material`]: palettes, direction tables and the material
//!   file (Fig. 6 steps 4–5, Fig. 11A).

pub mod calibrate;
pub mod corners;
pub mod edges;
pub mod enlarge;
pub mod error;
pub mod export;
pub mod glossy;
pub mod gltf;
pub mod height;
pub mod lens;
pub mod linalg;
pub mod locate;
pub mod material;
pub mod memory;
pub mod outline;
pub mod palette;
pub mod plane;
pub mod rectify;
pub mod regions;
pub mod scanread;
pub mod superres;
pub mod texel_fit;

pub use calibrate::{Calibration, calibrate};
pub use error::BuildError;
pub use regions::{RegionOptions, RegionSet, extract_regions};
pub mod bundle;
pub mod fidelity;
