//! **Ground truth (tests, benchmarks and `hil-sim truth` only):** the
//! small sample's f · cos θi for shading queries (docs/query-format.md),
//! to score what the host builds from simulated scans. Host code never
//! calls it.

use glam::DVec3;
use rayon::prelude::*;
use scanner_formats::queries::Query;

use crate::materials::Sample;

/// f · cos θi (radiance towards `wo` per unit irradiance from `wi`) of
/// `sample` for every query; 0 where either direction is below the
/// horizon.
pub fn answer(sample: &Sample, queries: &[Query]) -> Vec<[f32; 3]> {
    queries
        .par_iter()
        .with_min_len(1024)
        .map(|q| {
            let r = sample.reflected_radiance(q.uv, DVec3::from(q.wo), DVec3::from(q.wi));
            r.map(|v| v as f32)
        })
        .collect()
}
