//! Fig. 9's direct images: a material's large piece (≈10× the small
//! sample's area) seen and lit straight from the directions at which
//! mirrors see the small sample, rectified onto the piece, written as a set
//! the host reads (`scanner_formats::direct`, docs/direct-images.md).

use std::path::Path;
use std::sync::Arc;

use scanner_formats::direct::{DirectImage, DirectManifest, FORMAT, MANIFEST, WhiteImage};

use crate::geometry::{DVec3, ScannerGeometry};
use crate::materials::{DiffuseWhite, Material, Sample};
use crate::optics::{HOLDER_ALBEDO, OpticalSim, PhotoCamera};

/// The metering exposure of a direct image, s.
pub const METERING_EXPOSURE_S: f64 = 0.05;
/// Where auto exposure puts the image's 99.9th percentile, of full scale.
const METERED_LEVEL: f64 = 0.7;
/// The exposures auto exposure may choose, s.
const EXPOSURE_RANGE_S: [f64; 2] = [1e-3, 2.0];
/// Each shorter exposure, while any pixel clips, is this fraction of the
/// one before.
const BRACKET_STEP: f64 = 0.5;
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

/// An image `render(exposure_s)`, exposed as a photographer would: metered
/// so that its 99.9th percentile lies at 70 % of full scale, then shortened
/// while any pixel clips; with its exposure.
fn exposed(render: impl Fn(f64) -> crate::optics::Frame) -> (crate::optics::Frame, f64) {
    let metering = render(METERING_EXPOSURE_S);
    let mut values = metering.rgb;
    let at = ((values.len() - 1) as f64 * 0.999) as usize;
    let level = *values.select_nth_unstable_by(at, f32::total_cmp).1 as f64;
    let mut exposure_s = if level > 0.0 {
        (METERING_EXPOSURE_S * METERED_LEVEL / level.min(1.0))
            .clamp(EXPOSURE_RANGE_S[0], EXPOSURE_RANGE_S[1])
    } else {
        EXPOSURE_RANGE_S[1]
    };
    let mut frame = render(exposure_s);
    for _ in 1..MAX_BRACKETS {
        if frame.rgb.iter().all(|&v| v < 1.0) {
            break;
        }
        exposure_s *= BRACKET_STEP;
        frame = render(exposure_s);
    }
    (frame, exposure_s)
}

/// Render and write the direct images of `material`'s large piece from
/// the `count` mirror directions of the scanner's `design` (its nominal
/// geometry: where a photographer would set the camera) nearest the axis,
/// at `px_per_mm`, into `out` (created), with a direct image of the
/// diffuse-white target from the first direction as their white
/// reference, and their manifest. Every file is written atomically, the
/// manifest last.
pub fn write_set(
    sim: &OpticalSim,
    design: &ScannerGeometry,
    material: Arc<dyn Material>,
    count: usize,
    px_per_mm: f64,
    out: &Path,
) -> Result<DirectManifest, String> {
    let piece = Sample::large(material);
    std::fs::create_dir_all(out).map_err(|e| format!("{}: {e}", out.display()))?;
    let mut image = Vec::new();
    let mirrors = nearest_axis_mirrors(design, count);
    for (k, &(l, d)) in mirrors.iter().enumerate() {
        let (frame, exposure_s) = exposed(|e| sim.direct_image(&piece, d, px_per_mm, e));
        let file = format!("direct-{k}-mirror-{l:02}.exr");
        crate::camera::write_frame_exr(&frame, &out.join(&file)).map_err(|e| e.to_string())?;
        image.push(DirectImage {
            file,
            direction: d.to_array(),
            exposure_s,
            mirror: Some(l as u32),
            camera_distance_mm: None,
        });
    }
    // The white reference, from the first image's direction.
    let target = DiffuseWhite::default();
    let white_piece = Sample { size_mm: piece.size_mm, ..Sample::large(Arc::new(target)) };
    let white = mirrors.first().map(|&(_, d)| -> Result<WhiteImage, String> {
        let (frame, exposure_s) = exposed(|e| sim.direct_image(&white_piece, d, px_per_mm, e));
        let file = "white.exr".to_string();
        crate::camera::write_frame_exr(&frame, &out.join(&file)).map_err(|e| e.to_string())?;
        Ok(WhiteImage { file, direction: d.to_array(), exposure_s, albedo: target.albedo })
    });
    let white = white.transpose()?;
    let manifest = DirectManifest { format: FORMAT, size_mm: [piece.size_mm; 2], image, white };
    let path = out.join(MANIFEST);
    scanner_formats::write_atomic(&path, manifest.to_toml().as_bytes())
        .map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(manifest)
}

/// The description of a set of photographs ([`write_photographs`]):
/// `photographs.toml`.
pub const PHOTOGRAPHS: &str = "photographs.toml";

/// One photograph of a set, as `photographs.toml` lists it.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Photograph {
    /// The linear EXR, in the set's directory.
    pub file: String,
    /// The direction it was taken and lit from (sample-local, unit).
    pub direction: [f64; 3],
    /// Its exposure, s.
    pub exposure_s: f64,
    /// The mirror whose view it copies.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mirror: Option<u32>,
    /// The piece's corners at uv (0, 0), (1, 0), (1, 1), (0, 1) in it, px:
    /// what `scanner rectify --corners` takes.
    pub corners: [[f64; 2]; 4],
}

/// A set of photographs of a large piece and its white target, taken in
/// perspective as a real camera would take them for direct images.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Photographs {
    /// The piece's side, mm.
    pub size_mm: f64,
    /// The camera's distance from the piece's centre, mm.
    pub distance_mm: f64,
    /// The camera lens' radial distortion k1, k2 about each photograph's
    /// centre, the radius in half-diagonals of the photograph (absent: a
    /// pinhole). Ground truth: `scanner rectify --lens auto` estimates it.
    #[serde(default, skip_serializing_if = "is_pinhole")]
    pub distortion: [f64; 2],
    /// The albedo of the matte background the piece was photographed on:
    /// the black holder's ([`HOLDER_ALBEDO`]), or a light card's for a
    /// piece too dark to stand out of it. The white target always lies on
    /// the black holder.
    #[serde(default = "holder_albedo")]
    pub background_albedo: f64,
    /// The photographs of the piece.
    pub photo: Vec<Photograph>,
    /// The white target's photograph, from the first direction.
    pub white: Photograph,
    /// The white target's albedo.
    pub white_albedo: f64,
}

/// The photographs' camera distance from the piece's centre by default, mm:
/// a tripod's, the view direction varying by ±5.7° over an 80 mm piece
/// (docs/direct-images.md measures what it costs).
pub const PHOTO_DISTANCE_MM: f64 = 400.0;
/// How a set of photographs is taken.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PhotoSetup {
    /// The camera's distance from the piece's centre, mm.
    pub distance_mm: f64,
    /// Its lens' radial distortion ([`Photographs::distortion`]).
    pub distortion: [f64; 2],
    /// The albedo of the matte background the piece lies on
    /// ([`Photographs::background_albedo`]).
    pub background_albedo: f64,
}

impl PhotoSetup {
    /// A pinhole camera at `distance_mm`, the piece on the black holder.
    pub fn pinhole(distance_mm: f64) -> PhotoSetup {
        PhotoSetup { distance_mm, distortion: [0.0; 2], background_albedo: HOLDER_ALBEDO }
    }

    /// The setup in range: a distance > 0, a distortion that maps the
    /// photograph one to one (its radius growing out to 1.5 × the corner's).
    pub fn check(&self) -> Result<(), String> {
        let d = self.distance_mm;
        if !(d.is_finite() && d > 0.0) {
            return Err(format!("camera distance {d} mm: must be > 0"));
        }
        let b = self.background_albedo;
        if !(0.0..=1.0).contains(&b) {
            return Err(format!("background albedo {b}: must be within [0, 1]"));
        }
        let [k1, k2] = self.distortion;
        // Out to beyond the photograph's corners (radius 1).
        if !scanner_geometry::radial_one_to_one(self.distortion, 1.5) {
            return Err(format!(
                "lens distortion [{k1}, {k2}] does not map the photograph one to one"
            ));
        }
        Ok(())
    }
}

fn holder_albedo() -> f64 {
    HOLDER_ALBEDO
}

fn is_pinhole(k: &[f64; 2]) -> bool {
    *k == [0.0; 2]
}

/// How much finer the photographs resolve the piece, at its centre, than
/// the direct images they are for.
pub const PHOTO_OVERSAMPLING: f64 = 1.5;

impl Photographs {
    /// The manifest of the direct images these photographs make once each
    /// is rectified under its own file name (docs/direct-images.md), with
    /// the camera's distance.
    pub fn manifest(&self) -> DirectManifest {
        DirectManifest {
            format: FORMAT,
            size_mm: [self.size_mm; 2],
            image: self
                .photo
                .iter()
                .map(|ph| DirectImage {
                    file: ph.file.clone(),
                    direction: ph.direction,
                    exposure_s: ph.exposure_s,
                    mirror: ph.mirror,
                    camera_distance_mm: Some(self.distance_mm),
                })
                .collect(),
            white: Some(WhiteImage {
                file: self.white.file.clone(),
                direction: self.white.direction,
                exposure_s: self.white.exposure_s,
                albedo: self.white_albedo,
            }),
        }
    }
}

/// Render and write photographs of `material`'s large piece, as
/// [`write_set`] does its direct images but through a camera at
/// `setup.distance_mm` from the piece's centre along each direction, with
/// `setup.distortion`'s lens, framed so
/// that the piece seen face on would fill 80 % of a square frame that
/// resolves it at [`PHOTO_OVERSAMPLING`] × `px_per_mm` at its centre (the
/// direct images' density: a camera somewhat sharper than the images it
/// makes), the piece on `setup.background_albedo`'s background and the
/// white target on the black holder; and
/// `photographs.toml` with each one's exposure and the piece's corners in
/// it. These are not direct images yet: `scanner rectify` makes them so.
pub fn write_photographs(
    sim: &OpticalSim,
    design: &ScannerGeometry,
    material: Arc<dyn Material>,
    count: usize,
    px_per_mm: f64,
    setup: PhotoSetup,
    out: &Path,
) -> Result<Photographs, String> {
    setup.check()?;
    let PhotoSetup { distance_mm, distortion, background_albedo } = setup;
    let piece = Sample::large(material);
    let fill = 0.8;
    let side_px =
        (PHOTO_OVERSAMPLING * px_per_mm * piece.size_mm / fill).ceil().clamp(16.0, 16384.0) as u32;
    let camera = |d: DVec3| PhotoCamera {
        distortion,
        ..PhotoCamera::framing(d, distance_mm, side_px, piece.size_mm, fill)
    };
    std::fs::create_dir_all(out).map_err(|e| format!("{}: {e}", out.display()))?;
    let shoot = |piece: &Sample, background: f64, d: DVec3, file: String, mirror| {
        let cam = camera(d);
        let (frame, exposure_s) = exposed(|e| sim.photograph(piece, &cam, e, background));
        crate::camera::write_frame_exr(&frame, &out.join(&file)).map_err(|e| e.to_string())?;
        let corners = cam.corners(piece.size_mm);
        Ok::<_, String>(Photograph { file, direction: d.to_array(), exposure_s, mirror, corners })
    };
    let mirrors = nearest_axis_mirrors(design, count);
    let Some(&(_, first)) = mirrors.first() else {
        return Err("no mirror sees the sample".into());
    };
    let photo = mirrors
        .iter()
        .enumerate()
        .map(|(k, &(l, d))| {
            let file = format!("photo-{k}-mirror-{l:02}.exr");
            shoot(&piece, background_albedo, d, file, Some(l as u32))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let target = DiffuseWhite::default();
    let white_piece = Sample { size_mm: piece.size_mm, ..Sample::large(Arc::new(target)) };
    let white = shoot(&white_piece, HOLDER_ALBEDO, first, "white.exr".into(), None)?;
    let set = Photographs {
        size_mm: piece.size_mm,
        distance_mm,
        distortion,
        background_albedo,
        photo,
        white,
        white_albedo: target.albedo,
    };
    let text = toml::to_string(&set).map_err(|e| e.to_string())?;
    let path = out.join(PHOTOGRAPHS);
    scanner_formats::write_atomic(&path, text.as_bytes())
        .map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(set)
}
