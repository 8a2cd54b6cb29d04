//! End-to-end tests across firmware, simulator and host live in `tests/tests/`;
//! this library holds what they share with the long-running examples.

use hil_sim::materials::Sample;
use host::build::Calibration;
use host::build::RegionSet;
use host::build::fidelity::{material_psnr, pair_queries};
use scanner_geometry::{AxisValues, DVec3, ScannerGeometry, world_to_sample};

/// Material PSNR of `regions` against the ground truth of `sample` at the
/// captured pairs (the nominal mirror directions): (PSNR, gain-free PSNR,
/// gain).
pub fn captured_pair_psnr(
    g: &ScannerGeometry,
    regions: &RegionSet,
    sample: &Sample,
) -> (f64, f64, f64) {
    let (mut est, mut tru) = (Vec::new(), Vec::new());
    for (li, &l) in regions.lights.iter().enumerate() {
        for (vi, &v) in regions.views.iter().enumerate() {
            let q = pair_queries(
                g.light_direction(l).expect("a reachable mirror").to_array(),
                g.mirror_direction(v).expect("a mirror").to_array(),
            );
            tru.extend(hil_sim::truth::answer(sample, &q));
            est.extend(q.iter().map(|q| regions.sample(li, vi, q.uv).map(|x| x as f32)));
        }
    }
    material_psnr(&est, &tru)
}

/// Angles (degrees) between a calibration's directions and the as-built
/// scanner's, beside those of the nominal geometry alone.
#[derive(Debug, Clone, Default)]
pub struct DirectionErrors {
    /// Per view, calibrated.
    pub view: Vec<f64>,
    /// Per view, nominal (towards the mirror's centre).
    pub view_nominal: Vec<f64>,
    /// Per light, calibrated.
    pub light: Vec<f64>,
    /// Per light, nominal (towards where the inverse kinematics' beam meets the mirror).
    pub light_nominal: Vec<f64>,
}

/// The direction errors of `cal` (made with nominal geometry `g`) against
/// the as-built scanner `truth`: views towards the camera mirrored in the
/// as-built mirror, lights along the as-built beam at the commanded axes.
pub fn direction_errors(
    g: &ScannerGeometry,
    truth: &ScannerGeometry,
    cal: &Calibration,
) -> DirectionErrors {
    let mut e = DirectionErrors::default();
    for v in &cal.views {
        let c = truth.mirrors[v.view].reflect_point(DVec3::from(truth.camera.position_mm));
        let t = world_to_sample(c.normalize());
        e.view.push(DVec3::from(v.direction).angle_between(t).to_degrees());
        e.view_nominal
            .push(g.mirror_direction(v.view).expect("a mirror").angle_between(t).to_degrees());
    }
    for l in &cal.lights {
        let beam = truth.beam(AxisValues::from_array(l.axes));
        let n = DVec3::from(truth.mirrors[l.light].normal).normalize();
        let t = world_to_sample(-(beam.dir - 2.0 * beam.dir.dot(n) * n));
        e.light.push(DVec3::from(l.direction).angle_between(t).to_degrees());
        e.light_nominal.push(
            g.light_direction(l.light).expect("a reachable mirror").angle_between(t).to_degrees(),
        );
    }
    e
}
