//! End-to-end tests across firmware, simulator and host live in `tests/tests/`;
//! this library holds what they share with the long-running examples.

use hil_sim::materials::Sample;
use host::build::RegionSet;
use host::build::fidelity::{material_psnr, pair_queries};
use scanner_geometry::ScannerGeometry;

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
