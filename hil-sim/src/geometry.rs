//! The scanner's geometry as the simulator uses it: the **nominal** geometry
//! and kinematics come from the host-side crate `scanner-geometry`
//! (re-exported here); what is the simulator's alone is the seeded
//! **as-built** perturbation ([`AsBuilt::perturbed`]) — ground truth the host
//! never sees, and what its calibration has to recover.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
pub use scanner_geometry::*;

/// The as-built copy of a nominal geometry.
pub trait AsBuilt {
    /// The as-built scanner: this geometry with seeded manufacturing errors
    /// of realistic size (see [`Tolerances`]).
    fn perturbed(&self, seed: u64, tol: &Tolerances) -> ScannerGeometry;
}

impl AsBuilt for ScannerGeometry {
    /// The as-built scanner: this geometry with seeded manufacturing errors
    /// of realistic size (see [`Tolerances`]).
    fn perturbed(&self, seed: u64, tol: &Tolerances) -> ScannerGeometry {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x0041_5342_5549_4C54);
        let mut gauss = |sigma: f64| {
            if sigma > 0.0 {
                Normal::new(0.0, sigma).expect("sigma > 0").sample(&mut rng)
            } else {
                0.0
            }
        };
        let mut g = self.clone();
        for m in &mut g.mirrors {
            let (n, u, v) = m.frame();
            let (a, b) =
                (gauss(tol.mirror_tilt_deg).to_radians(), gauss(tol.mirror_tilt_deg).to_radians());
            m.normal = (n + u * a + v * b).normalize().to_array();
            let shift = DVec3::new(
                gauss(tol.mirror_shift_mm),
                gauss(tol.mirror_shift_mm),
                gauss(tol.mirror_shift_mm),
            );
            m.center_mm = (m.center() + shift).to_array();
            m.reflectance = (m.reflectance * (1.0 + gauss(tol.reflectance_rel))).clamp(0.0, 1.0);
        }
        let c = &mut g.camera;
        let (r, dn, f) = c.basis();
        let (a, b, roll) = (
            gauss(tol.camera_rotation_deg).to_radians(),
            gauss(tol.camera_rotation_deg).to_radians(),
            gauss(tol.camera_rotation_deg).to_radians(),
        );
        let f2 = (f + r * a + dn * b).normalize();
        let up = -(dn + r * roll);
        c.forward = f2.to_array();
        c.up = (up - f2 * up.dot(f2)).normalize().to_array();
        c.position_mm = (DVec3::from(c.position_mm)
            + DVec3::new(
                gauss(tol.camera_shift_mm),
                gauss(tol.camera_shift_mm),
                gauss(tol.camera_shift_mm),
            ))
        .to_array();
        c.focal_px *= 1.0 + gauss(tol.focal_rel);
        c.principal_px[0] += gauss(tol.principal_px);
        c.principal_px[1] += gauss(tol.principal_px);
        let s = &mut g.source;
        s.disk_zero_deg += gauss(tol.axis_zero_deg);
        s.tilt_zero_deg += gauss(tol.axis_zero_deg);
        s.track_zero_mm += gauss(tol.track_zero_mm);
        g
    }
}

/// Manufacturing tolerances (1 σ) of the as-built scanner.
#[derive(Debug, Clone, PartialEq)]
pub struct Tolerances {
    /// Mirror normal, each of two axes, degrees.
    pub mirror_tilt_deg: f64,
    /// Mirror centre, each axis, mm.
    pub mirror_shift_mm: f64,
    /// Mirror reflectance, relative.
    pub reflectance_rel: f64,
    /// Camera orientation, each of three axes, degrees.
    pub camera_rotation_deg: f64,
    /// Camera position, each axis, mm.
    pub camera_shift_mm: f64,
    /// Focal length, relative.
    pub focal_rel: f64,
    /// Principal point, each axis, px (of the default sensor's scale).
    pub principal_px: f64,
    /// Disk index and tilt home positions, degrees.
    pub axis_zero_deg: f64,
    /// Track home position, mm.
    pub track_zero_mm: f64,
}

impl Default for Tolerances {
    /// Hand-assembled mirror array and stock optics: 0.15° mirror tilt,
    /// 0.3 mm placement, 1 % reflectance, 0.1° / 0.5 mm camera mount, 0.3 %
    /// focal length, 3 px principal point, 0.05° switch positions, 0.1 mm
    /// track home.
    fn default() -> Tolerances {
        Tolerances {
            mirror_tilt_deg: 0.15,
            mirror_shift_mm: 0.3,
            reflectance_rel: 0.01,
            camera_rotation_deg: 0.1,
            camera_shift_mm: 0.5,
            focal_rel: 0.003,
            principal_px: 3.0,
            axis_zero_deg: 0.05,
            track_zero_mm: 0.1,
        }
    }
}

impl Tolerances {
    /// No errors: the as-built scanner is the nominal one.
    pub fn none() -> Tolerances {
        Tolerances {
            mirror_tilt_deg: 0.0,
            mirror_shift_mm: 0.0,
            reflectance_rel: 0.0,
            camera_rotation_deg: 0.0,
            camera_shift_mm: 0.0,
            focal_rel: 0.0,
            principal_px: 0.0,
            axis_zero_deg: 0.0,
            track_zero_mm: 0.0,
        }
    }
}
