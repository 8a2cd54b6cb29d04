//! Fig. 9's direct images: a material's large piece (≈10× the small
//! sample's area) seen and lit straight from the directions at which
//! mirrors see the small sample, rectified onto the piece, written as a set
//! the host reads (`scanner_formats::direct`, docs/direct-images.md).

use std::path::Path;
use std::sync::Arc;

use scanner_formats::direct::{DirectImage, DirectManifest, FORMAT, MANIFEST};

use crate::geometry::{DVec3, ScannerGeometry};
use crate::materials::{Material, Sample};
use crate::optics::OpticalSim;

/// The first exposure of a direct image, s; shorter ones follow while any
/// pixel clips.
pub const FIRST_EXPOSURE_S: f64 = 0.05;
/// Each shorter exposure is this fraction of the one before.
const BRACKET_STEP: f64 = 0.25;
/// Most exposures tried for one image.
const MAX_BRACKETS: usize = 12;

/// The `count` mirrors whose views of the sample lie nearest the camera
/// axis (the sample's normal), nearest first, with their directions.
pub fn nearest_axis_mirrors(g: &ScannerGeometry, count: usize) -> Vec<(usize, DVec3)> {
    let mut dirs: Vec<(usize, DVec3)> =
        (0..g.mirrors.len()).filter_map(|l| g.mirror_direction(l).map(|d| (l, d))).collect();
    dirs.sort_by(|a, b| b.1.z.total_cmp(&a.1.z));
    dirs.truncate(count);
    dirs
}

/// The mirror views' scale on the sample, px per mm: f / 2a.
pub fn mirror_view_scale(g: &ScannerGeometry) -> f64 {
    g.camera.focal_px / (2.0 * g.ellipsoid.semi_major_mm)
}

/// Render and write the direct images of `material`'s large piece from
/// the `count` mirror directions nearest the axis, at `px_per_mm`, into
/// `out` (created), with their manifest. Each image takes the first
/// exposure at which no pixel clips. The images and manifest are written
/// atomically, the manifest last.
pub fn write_set(
    sim: &OpticalSim,
    material: Arc<dyn Material>,
    count: usize,
    px_per_mm: f64,
    out: &Path,
) -> Result<DirectManifest, String> {
    let g = sim.geometry();
    let piece = Sample::large(material);
    std::fs::create_dir_all(out).map_err(|e| format!("{}: {e}", out.display()))?;
    let mut image = Vec::new();
    for (k, (l, d)) in nearest_axis_mirrors(g, count).into_iter().enumerate() {
        let mut exposure_s = FIRST_EXPOSURE_S;
        let mut frame = sim.direct_image(&piece, d, px_per_mm, exposure_s);
        for _ in 1..MAX_BRACKETS {
            if frame.rgb.iter().all(|&v| v < 1.0) {
                break;
            }
            exposure_s *= BRACKET_STEP;
            frame = sim.direct_image(&piece, d, px_per_mm, exposure_s);
        }
        let file = format!("direct-{k}-mirror-{l:02}.exr");
        crate::camera::write_frame_exr(&frame, &out.join(&file)).map_err(|e| e.to_string())?;
        image.push(DirectImage {
            file,
            direction: d.to_array(),
            exposure_s,
            mirror: Some(l as u32),
        });
    }
    let manifest = DirectManifest { format: FORMAT, size_mm: [piece.size_mm; 2], image };
    let path = out.join(MANIFEST);
    scanner_formats::write_atomic(&path, manifest.to_toml().as_bytes())
        .map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(manifest)
}
