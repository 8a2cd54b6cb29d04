//! # hil-sim: the simulated scanner
//!
//! A scanner controller the host cannot tell from real hardware: the
//! firmware's own [`Controller`](firmware::Controller) — not a
//! re-implementation — driving simulated stepper motors (which stall when
//! asked for more than their torque allows), home and index switches with
//! hysteresis, a light and a camera trigger, in simulated time.
//!
//! - [`physics`]: motors and switches.
//! - [`device`]: the simulated board ([`SimDevice`]) and the physical
//!   [`Truth`] that tests score the host against (host code never reads it).
//! - [`faults`]: seeded fault injection ([`FaultPlan`]).
//! - [`link`]: the deterministic in-process [`SimLink`] and the real-time
//!   [`PtyServer`].
//! - [`geometry`]: the scanner's **nominal** geometry file and kinematics
//!   (public: the host computes its mirror table from it).
//! - [`optics`]: the optical simulator rendering frames from the seeded
//!   as-built geometry and a ground-truth sample ([`materials`]).
//! - [`camera`]: the simulated camera, rendering at each trigger pulse from
//!   the simulated axes' physical positions.
//! - [`rig`]: board and camera in one deterministic process ([`SimRig`]).
//! - [`direct`]: Fig. 9's direct images of a large piece, as a set the host
//!   reads (docs/direct-images.md).
//! - [`defects`]: the sensor's stuck and dead pixels, when asked for.
//! - [`texture_set`]: user-defined samples from image maps
//!   (docs/texture-set.md); [`materials::lookup`] takes a library name or a
//!   texture-set directory.
//!
//! The simulator stands in for hardware and knows nothing of host internals.

pub mod camera;
pub mod defects;
pub mod device;
pub mod direct;
pub mod faults;
pub mod geometry;
pub mod link;
pub mod materials;
pub mod optics;
pub mod physics;
pub mod rig;
pub mod texture_set;
pub mod truth;

pub use device::{SimConfig, SimDevice, TriggerRecord, Truth};
pub use faults::{FaultEvent, FaultPlan, FaultSpec, FaultWhen};
pub use link::{LinkError, Port, PtyServer, SimLink};
pub use rig::SimRig;
