//! Geometry and colour calibration (Fig. 8) and the calibration file
//! (docs/calibration-format.md).
//!
//! - **Geometry**: each view's homography sample uv → frame pixel from the
//!   checkerboard scan ([`super::locate`]); the camera's pose and
//!   intrinsics and every mirror's plane adjusted to all views at once
//!   ([`super::bundle`]); the calibrated view direction (sample centre →
//!   the camera mirrored in the view's plane); each light's direction (the
//!   inverse kinematics' beam at the commanded axes, reflected in the
//!   calibrated mirror plane).
//! - **Colour**: the diffuse-white scan's response, modelled as separable
//!   view × light fields over uv — `W_lj(uv) = A_j(uv) · B_l(uv)`: A holds
//!   the view's mirror reflectance, vignetting and sensitivity (RGB), B the
//!   beam's profile over the sample, its mirror's reflectance and cos θi —
//!   fitted by alternating least squares on a grid of uv cells, so 1 600
//!   noisy white images become 80 smooth fields.

use rayon::prelude::*;
use scanner_geometry::DVec3;
use scanner_geometry::{
    AxisValues, SampleFace, ScannerGeometry, reflect_in_plane, world_to_sample,
};
use serde::{Deserialize, Serialize};

use super::bundle::{Adjusted, AssemblyTolerances, Highlights, adjust};
use super::error::BuildError;
use super::glossy::{SourceOffsets, fit_offsets, highlights, with_offsets};
use super::lens::{FrameMap, Pinhole};
use super::linalg::Homography;
use super::locate::{Checkerboard, RegionFit, locate};
use super::plane::{Plane, cell_taps};
use super::scanread::{BicubicFilter, ScanFrames, frame_bilinear, frame_dims};
use crate::defects::{DefectFinder, PixelDefect};
use crate::exrio::PixelRect;
use crate::stats::median;

/// Calibration file format name.
pub const CALIBRATION_FORMAT: &str = "material-scanner/calibration";
/// Calibration file version.
pub const CALIBRATION_VERSION: u32 = 2;
/// Default albedo of the diffuse-white target (a PTFE / Spectralon-class
/// reflectance standard); set it from the target's certificate.
pub const DEFAULT_WHITE_ALBEDO: f64 = 0.98;
/// Cells per side of the colour calibration's uv grid.
pub const COLOUR_GRID: usize = 32;

/// A scan a calibration was made from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScanRef {
    /// The scan's sample name.
    pub sample_name: String,
    /// SHA-256 of its manifest file.
    pub manifest_sha256: String,
}

/// One view (mirror seen by the camera).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewCalibration {
    /// Mirror index.
    pub view: usize,
    /// Sample uv → frame pixel (row-major 3 × 3, h33 = 1): the inner-corner
    /// fit, or the phase alignment where too few corners were found.
    pub homography: Homography,
    /// The Fourier-phase-aligned homography alone (the patent's method).
    pub homography_phase: Homography,
    /// Inner corners in the corner fit (0: none was found).
    pub corners_used: usize,
    /// RMS residual of the corner fit, px.
    pub corner_rms_px: f64,
    /// Which estimate `homography` is. (Absent in files before it was
    /// written: the corner fit if there was one, as then.)
    #[serde(default)]
    pub located_by: Option<LocatedBy>,
    /// RMS residual of the phase alignment's windows about its homography,
    /// px: ranks the views by how precisely their edges are placed
    /// ([`Self::edge_precise`]). (Absent in files before session 76, and
    /// where the alignment did not run: the edges not known to be precise.)
    #[serde(default)]
    pub phase_rms_px: Option<f64>,
    /// Where the diffuse-white target's frames put the sample's edges, px
    /// inside the homography's outline: per side (v 0, u 1, v 1, u 0) at
    /// its first and its last corner ([`super::edges`]). `None` where they
    /// could not be measured (and in files before session 77): the
    /// homography's outline.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub edge_offsets_px: Option<[[f64; 2]; 4]>,
    /// The squares (along u, v) the phase alignment had settled off before
    /// the sample's outline put it back (`None`: it had not; absent in
    /// files before session 95). A holder lighter than the checker's dark
    /// squares misleads the search's start this way.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub phase_relocked_squares: Option<[i32; 2]>,
    /// Unit direction from the sample centre towards the viewer through
    /// this mirror, sample-local frame.
    pub direction: [f64; 3],
    /// The calibrated mirror plane: a point (mm, world) and its unit normal.
    pub mirror_point_mm: [f64; 3],
    /// Unit normal, world, pointing at the foci.
    pub mirror_normal: [f64; 3],
}

/// How a view's homography was found.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LocatedBy {
    /// The fit to the checker's inner corners.
    Corners,
    /// The Fourier phase alignment (no corner fit, or one that explained
    /// the checker's pixels worse).
    Phase,
}

/// One light (mirror lit).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LightCalibration {
    /// Mirror index.
    pub light: usize,
    /// Unit direction from the sample towards the light, sample-local.
    pub direction: [f64; 3],
    /// The commanded axis values (degrees, mm, degrees) it was computed for.
    pub axes: [f64; 3],
}

/// Where a light's field is below this (its mean over lights and cells
/// being 1), its beam does not light the sample: there is nothing to
/// divide by, and the texel is read as unlit
/// ([`super::regions::RegionSet::unlit`]; so is a texel in a beam's soft
/// edge, [`BeamMap::readable`]).
pub const UNLIT_FIELD: f64 = 0.02;

/// The diffuse-white response, separable per view and per light.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ColourCalibration {
    /// Cells per side of the uv grid (cell (i, k) covers
    /// u ∈ [i/G, (i+1)/G), v ∈ [k/G, (k+1)/G); values are cell means,
    /// interpolated bilinearly between cell centres).
    pub grid: usize,
    /// Albedo of the white target.
    pub white_albedo: f64,
    /// Per view: G × G × 3 (row-major in v, u; RGB) response A_j, frame
    /// value per second per unit of the light field.
    pub view_response: Vec<Vec<f32>>,
    /// Per light: G × G field B_l (mean over all lights and cells 1).
    pub light_field: Vec<Vec<f32>>,
}

impl ColourCalibration {
    fn lookup<const C: usize>(grid: usize, field: &[f32], uv: [f64; 2]) -> [f64; C] {
        let (x0, x1, tx) = cell_taps(grid, uv[0]);
        let (y0, y1, ty) = cell_taps(grid, uv[1]);
        let at = |i: usize, j: usize, k: usize| field[(j * grid + i) * C + k] as f64;
        std::array::from_fn(|k| {
            (at(x0, y0, k) * (1.0 - tx) + at(x1, y0, k) * tx) * (1.0 - ty)
                + (at(x0, y1, k) * (1.0 - tx) + at(x1, y1, k) * tx) * ty
        })
    }

    /// The view's part A_j of the white response at `uv` (RGB).
    pub fn view(&self, vi: usize, uv: [f64; 2]) -> [f64; 3] {
        Self::lookup::<3>(self.grid, &self.view_response[vi], uv)
    }

    /// The light field B_l at `uv`.
    pub fn light(&self, li: usize, uv: [f64; 2]) -> f64 {
        Self::lookup::<1>(self.grid, &self.light_field[li], uv)[0]
    }

    /// How fully each light's beam lights each cell of the sample, as its
    /// field shows against the other lights': per cell, the light's field
    /// (over its own level where it lights the sample fully, its
    /// 90th-percentile cell) over the lights' well-lit field there — the
    /// mean of the lights between the 60th and 95th percentiles. The
    /// factorisation leaves each cell's split between view response and
    /// light field free, and the ratio cancels it; the upper band stands
    /// where half the beams miss the cell, and a mean over a band, not one
    /// light's value, hardly bends where a beam falling through it changes
    /// the lights' order. Scaled to the light's median over the cells (its
    /// cos θi, its mirror's reflectance). About 1 where every beam lights
    /// the whole sample alike; lower where a beam that lands off its
    /// mirror's centre leaves the sample in its soft edge. Per light, in
    /// `light_field` order, `grid`² cells row-major (NaN where the lights
    /// leave the cell dark); empty for fewer than three lights (nothing to
    /// compare with).
    pub fn beam_fractions(&self) -> Vec<Vec<f32>> {
        let n = self.light_field.len();
        let cells = self.grid * self.grid;
        if n < 3 || self.light_field.iter().any(|f| f.len() != cells) {
            return Vec::new();
        }
        // Each light's field over its own level where it lights the sample
        // fully (its 90th-percentile cell): a beam that misses part of the
        // sample stands as high as the others where it does light it.
        let quantile = |mut v: Vec<f64>, q: f64| -> f64 {
            v.retain(|x| x.is_finite());
            v.sort_by(f64::total_cmp);
            v.get(((v.len().max(1) - 1) as f64 * q).round() as usize).copied().unwrap_or(0.0)
        };
        let own: Vec<Vec<f64>> = self
            .light_field
            .iter()
            .map(|f| {
                let f: Vec<f64> = f.iter().map(|&x| x as f64).collect();
                let level = quantile(f.clone(), 0.9);
                f.iter().map(|x| if level > 0.0 { x / level } else { 0.0 }).collect()
            })
            .collect();
        let well_lit: Vec<f64> = (0..cells)
            .map(|c| {
                let mut v: Vec<f64> = own.iter().map(|f| f[c]).filter(|x| x.is_finite()).collect();
                v.sort_by(f64::total_cmp);
                let (lo, hi) =
                    ((v.len() * 3) / 5, (v.len() * 19).div_ceil(20).max(v.len() * 3 / 5 + 1));
                let band = &v[lo.min(v.len())..hi.min(v.len())];
                if band.is_empty() { 0.0 } else { band.iter().sum::<f64>() / band.len() as f64 }
            })
            .collect();
        own.iter()
            .map(|f| {
                let rel: Vec<f64> = f
                    .iter()
                    .zip(&well_lit)
                    .map(|(b, t)| if *t > 0.0 { b / t } else { f64::NAN })
                    .collect();
                let mid =
                    median(rel.iter().copied().filter(|r| r.is_finite()).collect()).unwrap_or(0.0);
                rel.iter()
                    .map(|r| if mid > 0.0 { (r / mid).max(0.0) as f32 } else { 0.0 })
                    .collect()
            })
            .collect()
    }

    /// Where each light's beam can be read from its frames
    /// ([`BeamMap::readable`]).
    pub fn beam_map(&self) -> BeamMap {
        let grid = self.grid;
        let fractions = self.beam_fractions();
        // Per cell, the bilinear lookup's relative error where the field
        // bends: |second difference| / 8 over the cell's own fraction, the
        // larger along u or v (a cell on the grid's edge takes the second
        // difference of its inner neighbour along that axis).
        let curvature = fractions
            .iter()
            .map(|f| {
                let at = |i: usize, j: usize| f[j * grid + i] as f64;
                let inner = |i: usize| i.clamp(1, grid.saturating_sub(2).max(1));
                (0..grid * grid)
                    .map(|c| {
                        let (i, j) = (c % grid, c / grid);
                        if grid < 3 {
                            return 0.0;
                        }
                        let (a, b) = (inner(i), inner(j));
                        let along_u = at(a - 1, j) + at(a + 1, j) - 2.0 * at(a, j);
                        let along_v = at(i, b - 1) + at(i, b + 1) - 2.0 * at(i, b);
                        let bend = along_u.abs().max(along_v.abs());
                        (bend / 8.0 / at(i, j).max(1e-6)) as f32
                    })
                    .collect()
            })
            .collect();
        BeamMap { grid, fractions, curvature }
    }

    /// How fully each light's beam covers the sample: the least of its
    /// [`Self::beam_fractions`] (1 for fewer than three lights; cells the
    /// lights leave dark not counted).
    pub fn beam_coverage(&self) -> Vec<f64> {
        let fractions = self.beam_fractions();
        if fractions.is_empty() {
            return vec![1.0; self.light_field.len()];
        }
        fractions
            .iter()
            .map(|f| {
                let least =
                    f.iter().filter(|r| r.is_finite()).fold(f32::INFINITY, |m, &r| m.min(r));
                if least.is_finite() { least as f64 } else { 0.0 }
            })
            .collect()
    }

    /// The white target's response (frame value per second) for light
    /// index `li`, view index `vi` at `uv`: A_j · B_l.
    pub fn response(&self, li: usize, vi: usize, uv: [f64; 2]) -> [f64; 3] {
        let b = self.light(li, uv);
        self.view(vi, uv).map(|a| a * b)
    }
}

/// The least share of its light a cell must get from a beam, against the
/// other beams there ([`ColourCalibration::beam_fractions`]), to be read
/// from that light's frames.
pub const BEAM_EDGE: f64 = 0.5;

/// The largest relative error the calibration's bilinear lookup of a beam's
/// field may make where the field bends ([`BeamMap`]'s curvature) for a
/// texel to be read from that light's frames. A beam's soft edge (a raised
/// cosine over a few cells) bends far more; a smooth fall-off across the
/// sample (≤ 10⁻³ for a Gaussian 20 mm wide on cells of 0.8 mm) far less.
pub const BEAM_BEND: f64 = 0.003;

/// Where each light's beam can be read from its frames: the calibration's
/// cells follow its field there closely enough to divide by
/// ([`ColourCalibration::beam_map`]).
#[derive(Debug, Clone)]
pub struct BeamMap {
    grid: usize,
    /// Per light, [`ColourCalibration::beam_fractions`].
    fractions: Vec<Vec<f32>>,
    /// Per light and cell, the bilinear lookup's relative error where the
    /// field bends.
    curvature: Vec<Vec<f32>>,
}

impl BeamMap {
    /// Light `li`'s fraction at `uv`, bilinear over the cells; 1 without
    /// fractions (fewer than three lights).
    pub fn fraction(&self, li: usize, uv: [f64; 2]) -> f64 {
        self.fractions.get(li).map_or(1.0, |f| ColourCalibration::lookup::<1>(self.grid, f, uv)[0])
    }

    /// Light `li`'s bend at `uv`: the largest of the four cells its lookup
    /// reads; 0 without fractions.
    pub fn bend(&self, li: usize, uv: [f64; 2]) -> f64 {
        let Some(c) = self.curvature.get(li) else { return 0.0 };
        let (x0, x1, _) = cell_taps(self.grid, uv[0]);
        let (y0, y1, _) = cell_taps(self.grid, uv[1]);
        [(x0, y0), (x1, y0), (x0, y1), (x1, y1)]
            .into_iter()
            .map(|(i, j)| c[j * self.grid + i] as f64)
            .fold(0.0, |m: f64, b| if m.is_nan() || b.is_nan() { f64::NAN } else { m.max(b) })
    }

    /// Whether light `li`'s frames can be read wherever the sample is: every
    /// cell passes [`Self::readable`]'s test (bilinear fractions of cells
    /// ≥ [`BEAM_EDGE`] are, and a lookup's bend is one of its cells').
    pub fn readable_everywhere(&self, li: usize) -> bool {
        let (Some(f), Some(c)) = (self.fractions.get(li), self.curvature.get(li)) else {
            return true;
        };
        f.iter().zip(c).all(|(&f, &c)| f as f64 >= BEAM_EDGE && c as f64 <= BEAM_BEND)
    }

    /// Whether light `li`'s frames can be read at `uv`: the beam gives the
    /// sample there at least [`BEAM_EDGE`] of what the well-lit beams give
    /// it, and its field bends there by no more than [`BEAM_BEND`]. (NaN,
    /// where the lights leave the cells dark: not readable.)
    pub fn readable(&self, li: usize, uv: [f64; 2]) -> bool {
        self.fraction(li, uv) >= BEAM_EDGE && self.bend(li, uv) <= BEAM_BEND
    }
}

/// The calibration file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Calibration {
    /// [`CALIBRATION_FORMAT`].
    pub format: String,
    /// [`CALIBRATION_VERSION`].
    pub version: u32,
    /// SHA-256 of the nominal geometry (scans must match it).
    pub geometry_sha256: String,
    /// Camera size, px.
    pub camera_px: [u32; 2],
    /// The checkerboard target.
    pub target: Checkerboard,
    /// The checkerboard scan.
    pub checkerboard_scan: ScanRef,
    /// The diffuse-white scan.
    pub white_scan: ScanRef,
    /// The glossy-target scan the light directions were fitted to, if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub glossy_scan: Option<ScanRef>,
    /// The source's home offsets fitted to it (zero without one).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source_offsets: Option<SourceOffsets>,
    /// Per view, in mirror order.
    pub views: Vec<ViewCalibration>,
    /// Per light, in mirror order.
    pub lights: Vec<LightCalibration>,
    /// Colour calibration; its fields are indexed like `views` and `lights`.
    pub colour: ColourCalibration,
    /// The camera's defective pixels (docs/scan-format.md, "Sensor
    /// defects"), found in the white scan: replaced in every frame the
    /// calibration reads or extracts regions from.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub defects: Vec<PixelDefect>,
    /// The camera lens' radial distortion (k1, k2) the adjustment found
    /// (`scanner_geometry::radial_distort`; k1 fitted, k2 the geometry
    /// file's): for the record — the views' homographies and directions
    /// already account for it. Absent in files from before it was fitted.
    #[serde(default)]
    pub lens_distortion: [f64; 2],
    /// k1 was held at the geometry file's, not fitted: no view was located
    /// by its corners ([`lens_measurable`]).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub lens_k1_held: bool,
}

/// Calibration settings.
#[derive(Debug, Clone)]
pub struct CalibrateOptions {
    /// The checkerboard target.
    pub target: Checkerboard,
    /// The white target's albedo.
    pub white_albedo: f64,
    /// How far the scanner may be from its geometry file (the bundle
    /// adjustment's priors).
    pub tolerances: AssemblyTolerances,
}

impl Default for CalibrateOptions {
    fn default() -> CalibrateOptions {
        CalibrateOptions {
            target: Checkerboard::default(),
            white_albedo: DEFAULT_WHITE_ALBEDO,
            tolerances: AssemblyTolerances::default(),
        }
    }
}

/// Progress of long builder steps.
pub trait BuildProgress: Sync {
    /// A stage with `total` steps starts.
    fn stage(&self, _name: &str, _total: usize) {}
    /// One step done.
    fn step(&self) {}
}

/// No progress output.
#[derive(Debug)]
pub struct Silent;
impl BuildProgress for Silent {}

/// Per row of a `w` × `h` frame, the x ranges `windows` cover, merged.
fn row_spans(windows: &[PixelRect], w: usize, h: usize) -> Vec<Vec<(usize, usize)>> {
    (0..h)
        .map(|y| {
            let mut spans: Vec<(usize, usize)> = windows
                .iter()
                .filter(|r| r[1] <= y && y < r[3] && r[0] < w)
                .map(|r| (r[0], r[2].min(w)))
                .collect();
            spans.sort_unstable();
            let mut merged: Vec<(usize, usize)> = Vec::new();
            for (a, b) in spans {
                match merged.last_mut() {
                    Some(last) if a <= last.1 => last.1 = last.1.max(b),
                    _ => merged.push((a, b)),
                }
            }
            merged
        })
        .collect()
}

/// Luminance of frame lit by each light of `scan`, summed over the frame
/// `windows` (the rest of the frame is not read and stays 0).
pub fn luminance_sum(
    scan: &ScanFrames,
    windows: &[PixelRect],
    progress: &dyn BuildProgress,
) -> Result<Plane, BuildError> {
    let lights = scan.lights();
    let Some(first) = scan.manifest.frames.first() else {
        return Err(BuildError::Input(format!("{}: no frames", scan.dir.display())));
    };
    let (w, h) = (first.width as usize, first.height as usize);
    let spans = row_spans(windows, w, h);
    // Only the windows' pixels are touched: the rest of a frame was never
    // written, and touching it would cost a page fault per 4 KiB.
    let each_pixel = |mut f: &mut dyn FnMut(usize)| {
        for (y, row) in spans.iter().enumerate() {
            for &(a, b) in row {
                (y * w + a..y * w + b).for_each(&mut f);
            }
        }
    };
    progress.stage("checkerboard frames", lights.len());
    // In the lights' order, so the sums' rounding is the same on every run
    // (a parallel fold's grouping follows the thread pool's work
    // stealing); each frame's blocks are decoded in parallel.
    let mut sum = Plane::new(w, h);
    for &l in &lights {
        let f = scan.read_within(l, windows)?;
        each_pixel(&mut |i| {
            sum.data[i] += (f.rgb[3 * i] + f.rgb[3 * i + 1] + f.rgb[3 * i + 2]) / 3.0;
        });
        progress.step();
    }
    Ok(sum)
}

/// The light direction (sample-local) of the beam at `axes`, reflected in
/// a mirror of unit normal `normal` (the beam is collimated: where it
/// meets the mirror does not matter).
pub fn light_direction(g: &ScannerGeometry, axes: [f64; 3], normal: DVec3) -> DVec3 {
    let beam = g.beam(AxisValues::from_array(axes));
    let r = beam.dir - 2.0 * beam.dir.dot(normal) * normal;
    world_to_sample(-r)
}

/// Calibrate from a checkerboard scan, a diffuse-white scan and, for the
/// light directions, optionally a glossy-target scan ([`super::glossy`]).
pub fn calibrate(
    g: &ScannerGeometry,
    checker: &ScanFrames,
    white: &ScanFrames,
    glossy: Option<&ScanFrames>,
    opts: &CalibrateOptions,
    progress: &dyn BuildProgress,
) -> Result<Calibration, BuildError> {
    if !(opts.white_albedo > 0.0 && opts.white_albedo <= 1.0) {
        return Err(BuildError::Input(format!(
            "white albedo {} outside (0, 1]",
            opts.white_albedo
        )));
    }
    // Only the frame pixels around the nominal views are read.
    let windows: Vec<PixelRect> =
        (0..g.mirrors.len()).filter_map(|j| super::locate::search_window(g, j)).collect();
    // The sensor's defects, from the white frames, replaced in every scan's.
    let defects = sensor_defects(g, white, &windows, progress)?;
    let with_defects = |s: &ScanFrames| {
        let mut s = s.clone();
        s.add_defects(&defects);
        s
    };
    let (checker, white) = (&with_defects(checker), &with_defects(white));
    let glossy = glossy.map(with_defects);
    let glossy = glossy.as_ref();
    let sum = luminance_sum(checker, &windows, progress)?;
    let views: Vec<usize> = (0..g.mirrors.len()).collect();
    progress.stage("locating views", views.len());
    // Every view is located before the first failure in mirror order is
    // reported: rayon's own `Result` collect returns whichever failed first
    // in time, a different mirror from run to run.
    let fits: Vec<Result<RegionFit, BuildError>> = views
        .par_iter()
        .map(|&j| {
            let r = locate(g, j, &sum, &opts.target).map_err(|e| BuildError::Input(e.to_string()));
            progress.step();
            r
        })
        .collect();
    let fits: Vec<RegionFit> = fits.into_iter().collect::<Result<_, _>>()?;
    drop(sum);
    // The camera and the mirror planes, adjusted to all views at once.
    let homographies: Vec<Homography> = fits.iter().map(RegionFit::best).collect();
    let lens_k1_held = !lens_measurable(&fits);
    let tol = match lens_k1_held {
        true => AssemblyTolerances { lens_k1: 0.0, ..opts.tolerances },
        false => opts.tolerances,
    };
    let (adjusted, corner_sigma) = adjusted_views(g, &views, &homographies, &fits, &tol);
    let mut view_cal = view_calibrations(g, &fits, &adjusted);
    let mut lens_distortion = adjusted.lens_distortion;
    let lights: Vec<usize> = white.lights();
    if lights != checker.lights() {
        return Err(BuildError::Input(format!(
            "the white scan lit mirrors {lights:?}, the checkerboard scan {:?}",
            checker.lights()
        )));
    }
    let (colour, edges) =
        colour_calibration(g, white, &view_cal, &lights, opts.white_albedo, progress)?;
    // The source's home offsets, from the glossy target's highlights,
    // adjusted together with the camera and the mirror planes.
    let source_offsets = match glossy {
        Some(scan) => {
            let pairs = highlights(g, scan, adjusted.camera, &view_cal, &colour, progress)?;
            // Offsets and α with the checkerboard's geometry held: the
            // starting point and the noise level of the joint adjustment.
            let first = fit_offsets(g, &pairs)?;
            let mut start = ([first.disk_deg, first.tilt_deg], first.alpha);
            let mut sigma = first.rms_rel.max(1e-4);
            let mut joint = adjusted.clone();
            for _ in 0..2 {
                let hl = Highlights { pairs: &pairs, sigma, start };
                joint = adjust(g, &views, &homographies, corner_sigma, &tol, Some(hl));
                let (offsets, alpha, rms) = joint.source.expect("adjusted with highlights");
                (start, sigma) = ((offsets, alpha), rms.max(1e-4));
            }
            view_cal = view_calibrations(g, &fits, &joint);
            lens_distortion = joint.lens_distortion;
            let (offsets, alpha, rms_rel) = joint.source.expect("adjusted with highlights");
            if !offsets.iter().all(|x| x.is_finite() && x.abs() <= 2.0) {
                return Err(BuildError::Input(format!(
                    "the glossy target's highlights fit no plausible source offset \
                     (disk {:.3}°, tilt {:.3}°)",
                    offsets[0], offsets[1]
                )));
            }
            Some(SourceOffsets {
                disk_deg: offsets[0],
                tilt_deg: offsets[1],
                alpha,
                rms_rel,
                ..first
            })
        }
        None => None,
    };
    let source = match &source_offsets {
        Some(o) => with_offsets(g, o.disk_deg, o.tilt_deg),
        None => g.clone(),
    };
    // The sample's edges as the white target's frames show them.
    for (v, e) in view_cal.iter_mut().zip(&edges) {
        v.edge_offsets_px = *e;
    }
    let mut light_cal = Vec::new();
    for &l in &lights {
        let v = view_cal.iter().find(|v| v.view == l).ok_or_else(|| {
            BuildError::Input(format!("mirror {l} is lit but not seen: cannot calibrate it"))
        })?;
        let axes = checker.axes(l)?;
        let d = light_direction(&source, axes, DVec3::from(v.mirror_normal));
        light_cal.push(LightCalibration { light: l, direction: d.to_array(), axes });
    }
    Ok(Calibration {
        format: CALIBRATION_FORMAT.into(),
        version: CALIBRATION_VERSION,
        geometry_sha256: g.hash(),
        camera_px: [g.camera.width, g.camera.height],
        target: opts.target,
        checkerboard_scan: ScanRef {
            sample_name: checker.manifest.settings.sample_name.clone(),
            manifest_sha256: checker.manifest_sha256.clone(),
        },
        white_scan: ScanRef {
            sample_name: white.manifest.settings.sample_name.clone(),
            manifest_sha256: white.manifest_sha256.clone(),
        },
        glossy_scan: glossy.map(|s| ScanRef {
            sample_name: s.manifest.settings.sample_name.clone(),
            manifest_sha256: s.manifest_sha256.clone(),
        }),
        source_offsets,
        views: view_cal,
        lights: light_cal,
        colour,
        defects,
        lens_distortion,
        lens_k1_held,
    })
}

/// The sensor's defective pixels ([`crate::defects`]) a calibration
/// records: those the white scan recorded (its metering's, its dark
/// frame's), and those its frames
/// show within `windows` — the white target lit by every mirror in turn,
/// the best frames to find them in. Frames merged from several exposures
/// (where a stuck pixel is no longer at the top code) are not looked at.
fn sensor_defects(
    g: &ScannerGeometry,
    white: &ScanFrames,
    windows: &[PixelRect],
    progress: &dyn BuildProgress,
) -> Result<Vec<PixelDefect>, BuildError> {
    let merged = !white.manifest.settings.bracket_us.is_empty()
        || white.manifest.frames.iter().any(|f| !f.bracket_us.is_empty());
    if merged {
        return Ok(white.defects().to_vec());
    }
    let (w, h) = (g.camera.width, g.camera.height);
    let mut finder = DefectFinder::uniform_target(g, w, h);
    let lights = white.lights();
    progress.stage("sensor defects", lights.len());
    // The first frame alone, then two at a time (each a full frame in
    // memory), in order. After the first only the blocks near the finder's
    // candidates are decoded: all it and the patching of the scan's own
    // defects read there.
    let (first, rest) = lights.split_at(lights.len().min(1));
    for pair in std::iter::once(first).chain(rest.chunks(2)) {
        let r = crate::defects::PATCH_RADIUS;
        let near = |b: PixelRect| {
            finder.examines([b[0].saturating_sub(r), b[1].saturating_sub(r), b[2] + r, b[3] + r])
        };
        let frames: Vec<(crate::camera::Frame, f32)> = pair
            .par_iter()
            .map(|&l| Ok((white.read_within_where(l, windows, &near)?, white.exposure_s(l)?)))
            .collect::<Result<_, BuildError>>()?;
        for (f, t) in &frames {
            finder.add_scaled(f, *t);
            progress.step();
        }
    }
    match finder.defects() {
        Ok(found) => Ok(crate::defects::union(white.defects(), &found)),
        Err(why) => {
            tracing::warn!("{}: sensor defects: {why}", white.dir.display());
            Ok(white.defects().to_vec())
        }
    }
}

/// The standard error the bundle adjustment gives each of a homography's
/// 5 × 5 grid points, px. A corner fit of n corners with RMS residual r
/// places the sample to r·√(8 / 2n) (8 parameters from 2n coordinates);
/// the 25 grid points carry only those 8 parameters' information, so each
/// weighs as if its error were √(25/8) times that. The RMS over the views
/// located by their corners (or, if none is, over every corner fit found);
/// the phase alignment's residual ranks its views
/// ([`ViewCalibration::phase_rms_px`]) but is no standard error, and its
/// views are taken as precise. At least 0.05 px.
fn grid_sigma(fits: &[RegionFit]) -> f64 {
    let variance = |f: &&RegionFit| f.corner_rms_px.powi(2) * 4.0 / f.corners_used as f64;
    let fitted = || fits.iter().filter(|f| f.corners.is_some());
    let chosen: Vec<f64> = fitted().filter(|f| f.by_corners).map(|f| variance(&f)).collect();
    let se = if chosen.is_empty() { fitted().map(|f| variance(&f)).collect() } else { chosen };
    if se.is_empty() {
        return 0.05;
    }
    ((se.iter().sum::<f64>() / se.len() as f64) * 25.0 / 8.0).sqrt().max(0.05)
}

/// Whether the views can measure the lens' k1: some view has a corner
/// fit. Located by the phase alignment alone (squares of a few pixels: a
/// 512² sensor), the views' errors have a radial pattern that k1 absorbs:
/// fitted, it came out −0.09 to −0.20 for a lens of none and −0.12 to −0.23
/// for one of −0.05, and the directions bent with it (views 0.11–0.20° RMS
/// from the as-built truth, against 0.09° with k1 held at the file's, even
/// where the file did not know the −0.05; docs/benchmarks.md, "Calibration
/// on a 512² sensor").
fn lens_measurable(fits: &[RegionFit]) -> bool {
    fits.iter().any(|f| f.corners.is_some())
}

/// The geometry adjusted to the views' homographies, and the standard
/// error their grid points were given ([`grid_sigma`]). With no corner fit
/// to measure it (squares of a few pixels: a small sensor), the phase
/// alignment's views would be taken as precise to 0.05 px whatever they
/// are; instead the adjustment's own residual measures them (each grid
/// point's, × √(25/8) as for a corner fit), and the geometry is adjusted
/// again with it, so that the priors on the camera, the lens and the
/// mirrors weigh as much as such views' information warrants. (A 512²
/// sensor: the views 0.69 px RMS from the truth, adjusted to them as if
/// within 0.05 px the view directions came out 0.50° RMS from the truth,
/// worse than the nominal geometry's 0.36°, and the lens' k1 −0.26.)
fn adjusted_views(
    g: &ScannerGeometry,
    views: &[usize],
    homographies: &[Homography],
    fits: &[RegionFit],
    tol: &AssemblyTolerances,
) -> (Adjusted, f64) {
    let sigma = grid_sigma(fits);
    let adjusted = adjust(g, views, homographies, sigma, tol, None);
    if lens_measurable(fits) {
        return (adjusted, sigma);
    }
    let measured = adjusted.rms_px * (25.0f64 / 8.0).sqrt();
    if measured.is_nan() || measured <= sigma {
        return (adjusted, sigma);
    }
    (adjust(g, views, homographies, measured, tol, None), measured)
}

/// Per located view, its calibration from the adjusted geometry.
fn view_calibrations(
    g: &ScannerGeometry,
    fits: &[RegionFit],
    adjusted: &Adjusted,
) -> Vec<ViewCalibration> {
    let centre = g.sample_point([0.5, 0.5]);
    fits.iter()
        .zip(&adjusted.planes)
        .map(|(fit, &(point, normal))| {
            let camera = adjusted.camera;
            let virtual_camera = reflect_in_plane(camera, point, normal);
            ViewCalibration {
                view: fit.view,
                homography: fit.best(),
                homography_phase: fit.phase,
                corners_used: fit.corners_used,
                corner_rms_px: if fit.corner_rms_px.is_finite() { fit.corner_rms_px } else { 0.0 },
                phase_rms_px: fit.phase_rms_px.is_finite().then_some(fit.phase_rms_px),
                edge_offsets_px: None,
                phase_relocked_squares: fit.relocked_squares,
                located_by: Some(if fit.by_corners {
                    LocatedBy::Corners
                } else {
                    LocatedBy::Phase
                }),
                direction: world_to_sample((virtual_camera - centre).normalize()).to_array(),
                mirror_point_mm: point.to_array(),
                mirror_normal: normal.to_array(),
            }
        })
        .collect()
}

/// Mean RGB of every view's G × G uv cells in one frame (4 × 4 samples a cell).
fn cell_means(
    f: &crate::camera::Frame,
    views: &[ViewCalibration],
    grid: usize,
) -> Vec<Vec<[f64; 3]>> {
    const SUB: usize = 4;
    views
        .iter()
        .map(|v| {
            let v = v.sampler();
            let mut cells = vec![[0.0; 3]; grid * grid];
            for (c, cell) in cells.iter_mut().enumerate() {
                let (ci, ck) = (c % grid, c / grid);
                for s in 0..SUB * SUB {
                    let uv = [
                        (ci as f64 + ((s % SUB) as f64 + 0.5) / SUB as f64) / grid as f64,
                        (ck as f64 + ((s / SUB) as f64 + 0.5) / SUB as f64) / grid as f64,
                    ];
                    let p = v.frame_point(uv);
                    let rgb = frame_bilinear(f, p[0], p[1]);
                    for k in 0..3 {
                        cell[k] += rgb[k] / (SUB * SUB) as f64;
                    }
                }
            }
            cells
        })
        .collect()
}

/// The colour calibration from the white scan ("Colour" in
/// docs/calibration-format.md) and, from the same frames read once, each
/// view's edges ([`super::edges`]; `None` where they could not be fitted).
fn colour_calibration(
    g: &ScannerGeometry,
    white: &ScanFrames,
    views: &[ViewCalibration],
    lights: &[usize],
    albedo: f64,
    progress: &dyn BuildProgress,
) -> Result<(ColourCalibration, Vec<Option<super::edges::EdgeFit>>), BuildError> {
    let grid = COLOUR_GRID;
    progress.stage("white frames", lights.len());
    // w[li][vi][cell] = mean frame value per second; and the sums the
    // views' edges are measured from.
    let windows = view_windows(views);
    let samplers: Vec<ViewSampler> = views.iter().map(|v| v.sampler()).collect();
    let dims = [g.camera.width as usize, g.camera.height as usize];
    let bands = super::edges::EdgeBands::new(&samplers, dims);
    let (w, sums): (Vec<Vec<Vec<[f64; 3]>>>, Vec<_>) = lights
        .par_iter()
        .map(|&l| {
            let f = white.read_within(l, &windows)?;
            let cells = cell_means(&f, views, grid);
            let sums = bands.sums(&f);
            progress.step();
            Ok((cells, sums))
        })
        .collect::<Result<Vec<_>, BuildError>>()?
        .into_iter()
        .unzip();
    let edges = bands.fit(&sums.iter().fold(bands.zero(), |a, s| a.plus(s)));
    // The noise floor: the median cell must stand 10× above the read noise.
    let exposure_s = white.manifest.settings.exposure_us as f64 * 1e-6;
    let read_codes = g.sensor.read_noise_e * g.sensor.max_code() / g.sensor.full_well_e;
    let lum: Vec<f64> = w
        .iter()
        .flatten()
        .flatten()
        .map(|c| (c[0] + c[1] + c[2]) / 3.0 * exposure_s * g.sensor.max_code())
        .collect();
    let median = median(lum).unwrap_or(f64::NAN);
    if median.is_nan() || median < 10.0 * read_codes.max(1.0) {
        return Err(BuildError::Input(format!(
            "{}: the white target is at the noise floor (median {median:.1} ADC codes, need ≥ {:.1}): \
             more exposure or light",
            white.dir.display(),
            10.0 * read_codes.max(1.0)
        )));
    }
    check_uniform(&w, grid, &white.dir)?;
    let (nl, nv, nc) = (lights.len(), views.len(), grid * grid);
    let mut a = vec![vec![[1.0f64; 3]; nc]; nv];
    let mut b = vec![vec![1.0f64; nc]; nl];
    for _ in 0..30 {
        for (vi, av) in a.iter_mut().enumerate() {
            for c in 0..nc {
                let (mut num, mut den) = ([0.0; 3], 0.0);
                for li in 0..nl {
                    let bb = b[li][c];
                    for k in 0..3 {
                        num[k] += w[li][vi][c][k] * bb;
                    }
                    den += bb * bb;
                }
                av[c] = if den > 0.0 { num.map(|x| x / den) } else { [0.0; 3] };
            }
        }
        for (li, bl) in b.iter_mut().enumerate() {
            for c in 0..nc {
                let (mut num, mut den) = (0.0, 0.0);
                for vi in 0..nv {
                    for k in 0..3 {
                        num += w[li][vi][c][k] * a[vi][c][k];
                        den += a[vi][c][k] * a[vi][c][k];
                    }
                }
                bl[c] = if den > 0.0 { num / den } else { 0.0 };
            }
        }
        let mean = b.iter().flatten().sum::<f64>() / (nl * nc) as f64;
        if mean > 0.0 {
            b.iter_mut().flatten().for_each(|x| *x /= mean);
        }
    }
    // A diffuse target's frames are the product of the two factors: a
    // glossy or textured sample's are not.
    let residual = factor_residual(&w, &a, &b);
    if residual > 0.25 {
        return Err(BuildError::Input(format!(
            "{}: not a diffuse white target: the view × light factors miss its cells by {:.0} % \
             (median; a diffuse target's by under 1 %). Is it a sample scan?",
            white.dir.display(),
            residual * 100.0
        )));
    }
    if residual > 0.05 {
        tracing::warn!(
            "{}: the white target departs from a diffuse reflector by {:.0} % (median of its \
             cells; the simulator's white: 0.6 %): its certified albedo may not hold at these \
             angles",
            white.dir.display(),
            residual * 100.0
        );
    }
    let colour = ColourCalibration {
        grid,
        white_albedo: albedo,
        view_response: a.iter().map(|v| v.iter().flatten().map(|&x| x as f32).collect()).collect(),
        light_field: b.iter().map(|l| l.iter().map(|&x| x as f32).collect()).collect(),
    };
    Ok((colour, edges))
}

/// The median over cells, lights, views and channels of |w − a·b| / w:
/// how far the white scan's cell means `w[l][v][c]` are from the product
/// of the fitted view response `a[v][c]` and light field `b[l][c]`.
fn factor_residual(w: &[Vec<Vec<[f64; 3]>>], a: &[Vec<[f64; 3]>], b: &[Vec<f64>]) -> f64 {
    let mut rel: Vec<f64> = Vec::new();
    for (wl, bl) in w.iter().zip(b) {
        for (wv, av) in wl.iter().zip(a) {
            for ((cell, ac), bc) in wv.iter().zip(av).zip(bl) {
                for k in 0..3 {
                    if cell[k] > 0.0 {
                        rel.push(((cell[k] - ac[k] * bc) / cell[k]).abs());
                    }
                }
            }
        }
    }
    median(rel).unwrap_or(0.0)
}

/// A diffuse-white target is uniform: what varies over it in one frame
/// (the beam's profile, vignetting) varies smoothly, so neighbouring cells
/// differ by a few per cent. A patterned scan — the checkerboard given as
/// `--white`, a sample — has edges between cells: its factors would carry
/// the pattern into every material. Refused when the median over all
/// cells of the largest ratio to a neighbour exceeds 1.15 (the
/// simulator's white: 1.009 at 4096², 1.001 at 512²; the checkerboard:
/// 6.5, and 1.26 with its edges blurred at 512²; woven-fabric 1.67).
fn check_uniform(
    w: &[Vec<Vec<[f64; 3]>>],
    grid: usize,
    dir: &std::path::Path,
) -> Result<(), BuildError> {
    let mut contrast: Vec<f64> = Vec::new();
    for cells in w.iter().flatten() {
        let lum = |x: usize, y: usize| {
            let c = cells[y * grid + x];
            (c[0] + c[1] + c[2]) / 3.0
        };
        for y in 0..grid {
            for x in 0..grid {
                let here = lum(x, y);
                let neighbours = [
                    (x > 0).then(|| lum(x - 1, y)),
                    (x + 1 < grid).then(|| lum(x + 1, y)),
                    (y > 0).then(|| lum(x, y - 1)),
                    (y + 1 < grid).then(|| lum(x, y + 1)),
                ];
                let worst = neighbours
                    .into_iter()
                    .flatten()
                    .filter(|&n| n > 0.0 && here > 0.0)
                    .map(|n| (here / n).ln().abs())
                    .reduce(f64::max);
                contrast.extend(worst);
            }
        }
    }
    let Some(median) = median(contrast) else {
        return Ok(());
    };
    if median > 1.15f64.ln() {
        return Err(BuildError::Input(format!(
            "{}: not a uniform white target: neighbouring cells of a view differ by {:.2}× \
             (median; a white target's by about 1 %). Is it the checkerboard or a sample scan?",
            dir.display(),
            median.exp()
        )));
    }
    Ok(())
}

/// The frame pixels the calibrated `views` are resampled from (bicubic
/// support included).
pub fn view_windows(views: &[ViewCalibration]) -> Vec<PixelRect> {
    views.iter().map(|v| v.homography.window(4.0)).collect()
}

impl ViewCalibration {
    /// Whether the view's edges are placed precisely enough for the region
    /// images to read the pixels that straddle them
    /// ([`super::regions::EdgePixels::Precise`]): measured on the white
    /// target's frames ([`super::edges`]), or else its phase alignment's
    /// residual at most [`EDGE_PRECISE_PX`].
    pub fn edge_precise(&self) -> bool {
        self.edge_offsets_px.is_some() || self.phase_rms_px.is_some_and(|r| r <= EDGE_PRECISE_PX)
    }

    /// Where to read the frame for sample position `uv`: positions closer
    /// to the sample's edge than [`EDGE_PX`] frame pixels are moved in to
    /// that distance, so no resampling filter mixes in the holder around
    /// the sample.
    pub fn frame_point(&self, uv: [f64; 2]) -> [f64; 2] {
        self.sampler().frame_point(uv)
    }

    /// [`Self::frame_point`] and the region resampling, set up once for many points.
    pub fn sampler(&self) -> ViewSampler {
        ViewSampler::with_edge_offsets(self.homography, self.edge_offsets_px.as_ref())
    }

    /// [`Self::sampler`] for a sample whose face lies `height_mm` above the
    /// holder's plane, towards the mirrors ([`Self::homography_at_height`]);
    /// the edges keep their offsets from the homography's outline.
    pub fn sampler_at_height(&self, g: &ScannerGeometry, height_mm: f64) -> ViewSampler {
        if height_mm == 0.0 {
            return self.sampler();
        }
        let h = self.homography_at_height(g, height_mm);
        ViewSampler::with_edge_offsets(h, self.edge_offsets_px.as_ref())
    }

    /// [`Self::sampler`] for a sample whose face lies at `face`
    /// ([`Self::homography_at_face`]); the edges keep their offsets from
    /// the homography's outline.
    pub fn sampler_at_face(&self, g: &ScannerGeometry, face: SampleFace) -> ViewSampler {
        if face.is_level() {
            return self.sampler_at_height(g, face.height_mm);
        }
        let h = self.homography_at_face(g, face);
        ViewSampler::with_edge_offsets(h, self.edge_offsets_px.as_ref())
    }

    /// The view's homography for the sample's face at `face` (material uv
    /// on the face → frame px): a point of the face is seen where the ray
    /// from the virtual camera through it meets the holder's plane, which
    /// the calibration's homography maps. A central projection between
    /// planes is a homography, fitted here to the outline's corners and
    /// centre (exact). A level face is [`Self::homography_at_height`].
    pub fn homography_at_face(&self, g: &ScannerGeometry, face: SampleFace) -> Homography {
        if face.is_level() {
            return self.homography_at_height(g, face.height_mm);
        }
        let c = DVec3::from(self.viewer_mm(g));
        let size = g.sample.size_mm;
        let src = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [0.5, 0.5]];
        let dst: Vec<[f64; 2]> =
            src.iter().map(|&uv| self.homography.apply(face.holder_uv_from(size, uv, c))).collect();
        Homography::fit(&src, &dst).unwrap_or(self.homography)
    }

    /// The view's homography for the plane `height_mm` above the holder's
    /// (sample uv on that plane → frame px): a point of it is seen where
    /// the ray from the virtual camera through it meets the holder's plane,
    /// which the calibration's homography maps. Central projection between
    /// parallel planes is a scaling about the camera's foot point, by
    /// z / (z − height) with z the camera's height above the plane.
    pub fn homography_at_height(&self, g: &ScannerGeometry, height_mm: f64) -> Homography {
        let c = self.viewer_mm(g);
        let size = g.sample.size_mm;
        let foot = [c[0] / size + 0.5, c[1] / size + 0.5];
        self.homography.after_scaling(c[2] / (c[2] - height_mm), foot)
    }

    /// `camera` (world, mm) mirrored in the calibrated mirror plane.
    pub fn virtual_camera(&self, camera: DVec3) -> DVec3 {
        reflect_in_plane(camera, DVec3::from(self.mirror_point_mm), DVec3::from(self.mirror_normal))
    }

    /// The view's virtual camera (the camera mirrored in the calibrated
    /// mirror plane), sample-local mm from the sample's centre: on the
    /// calibrated direction, at the distance of the nominal camera mirrored
    /// in the calibrated plane (the camera's own calibrated shift, ≤ 1 mm
    /// at ≈ 1 200 mm, moves it by less than 0.05°).
    pub fn viewer_mm(&self, g: &ScannerGeometry) -> [f64; 3] {
        let distance = (self.virtual_camera(DVec3::from(g.camera.position_mm))
            - g.sample_point([0.5, 0.5]))
        .length();
        (DVec3::from(self.direction).normalize() * distance).to_array()
    }
}

/// One edge of the sample in a frame: n · p − c is how far p lies inside
/// (frame px, n the inward unit normal); `half` is half a pixel square's
/// extent along n.
#[derive(Debug, Clone, Copy)]
struct FrameEdge {
    n: [f64; 2],
    c: f64,
    half: f64,
}

/// A view's homography with its scale and the sample's edges in the frame.
#[derive(Debug, Clone, Copy)]
pub struct ViewSampler {
    homography: Homography,
    /// Frame px per unit of u and of v at the sample's centre.
    px_per_uv: [f64; 2],
    edges: [FrameEdge; 4],
    /// Per side (v 0, u 1, v 1, u 0): whether what lies beyond it is not
    /// the holder ([`Self::with_closed_sides`]).
    closed: [bool; 4],
}

impl ViewSampler {
    /// The sampler of the view whose homography (sample uv → frame px) is `h`.
    pub fn new(h: Homography) -> ViewSampler {
        ViewSampler::with_edge_offsets(h, None)
    }

    /// The sampler of the view whose homography is `h` and whose edges lie
    /// `offsets` px inside the homography's outline: per side (v 0, u 1,
    /// v 1, u 0, from corner k to corner k + 1 of [`Homography::corners`])
    /// at its first and its last corner ([`super::edges`]). The edges
    /// decide which pixels the region images read and each straddling
    /// pixel's share; the homography, where on the sample a pixel lies.
    pub fn with_edge_offsets(h: Homography, offsets: Option<&[[f64; 2]; 4]>) -> ViewSampler {
        let j = h.jacobian([0.5, 0.5]);
        let px = [j[0][0].hypot(j[1][0]), j[0][1].hypot(j[1][1])];
        let corners = h.corners();
        let centre = h.apply([0.5, 0.5]);
        let inward = |a: [f64; 2], b: [f64; 2]| {
            let d = [b[0] - a[0], b[1] - a[1]];
            let len = d[0].hypot(d[1]).max(1e-12);
            let n = [-d[1] / len, d[0] / len];
            if n[0] * (centre[0] - a[0]) + n[1] * (centre[1] - a[1]) < 0.0 {
                [-n[0], -n[1]]
            } else {
                n
            }
        };
        let edges = std::array::from_fn(|k| {
            let (mut a, mut b) = (corners[k], corners[(k + 1) % 4]);
            if let Some(o) = offsets {
                let n = inward(a, b);
                a = [a[0] + o[k][0] * n[0], a[1] + o[k][0] * n[1]];
                b = [b[0] + o[k][1] * n[0], b[1] + o[k][1] * n[1]];
            }
            let n = inward(a, b);
            FrameEdge { n, c: n[0] * a[0] + n[1] * a[1], half: 0.5 * (n[0].abs() + n[1].abs()) }
        });
        ViewSampler { homography: h, px_per_uv: px, edges, closed: [false; 4] }
    }

    /// The same sampler where what lies beyond the sides `closed` (v 0,
    /// u 1, v 1, u 0) is not the holder — a thick sample's own sides, which
    /// show beyond the edges facing the view (`super::outline::Sides`): no
    /// pixel reaching across them is read for its share
    /// ([`Self::share`] 0), and the holder's band lies beyond the others
    /// alone ([`Self::holder_band`]).
    pub fn with_closed_sides(self, closed: [bool; 4]) -> ViewSampler {
        ViewSampler { closed, ..self }
    }

    /// The same sampler in frame coordinates shifted by `d` (e.g. into a
    /// frame window whose corner is at −d).
    pub fn translated(&self, d: [f64; 2]) -> ViewSampler {
        let edges = self.edges.map(|e| FrameEdge { c: e.c + e.n[0] * d[0] + e.n[1] * d[1], ..e });
        ViewSampler { homography: self.homography.translated(d), edges, ..*self }
    }

    /// The homography (sample uv → frame px).
    pub fn homography(&self) -> &Homography {
        &self.homography
    }

    /// Whether the pixel square centred at frame point `p` lies on the
    /// sample, [`CLEAN_MARGIN_PX`] inside its calibrated edge: the frame
    /// pixels the region images use.
    #[inline]
    pub fn pixel_on_sample(&self, p: [f64; 2]) -> bool {
        self.depth(p) >= CLEAN_MARGIN_PX
    }

    /// Whether frame point `p` lies on the sample, by the calibrated edges.
    pub fn point_on_sample(&self, p: [f64; 2]) -> bool {
        self.point_depth(p) >= 0.0
    }

    /// See [`ViewCalibration::frame_point`].
    #[inline]
    pub fn frame_point(&self, uv: [f64; 2]) -> [f64; 2] {
        self.inset_point(uv, EDGE_PX)
    }

    /// The frame point of `uv` moved in to at least `edge_px` frame px
    /// from the sample's edges (measured along u and v at the centre; at
    /// most to the centre).
    #[inline]
    fn inset_point(&self, uv: [f64; 2], edge_px: f64) -> [f64; 2] {
        let [du, dv] = self.px_per_uv.map(|px| (edge_px / px).min(0.5));
        self.homography.apply([uv[0].clamp(du, 1.0 - du), uv[1].clamp(dv, 1.0 - dv)])
    }

    /// How far the pixel square centred at frame point `p` lies inside the
    /// sample (frame px; negative: it reaches outside).
    #[inline]
    fn depth(&self, p: [f64; 2]) -> f64 {
        self.edges
            .iter()
            .map(|e| e.n[0] * p[0] + e.n[1] * p[1] - e.c - e.half)
            .fold(f64::INFINITY, f64::min)
    }

    /// The region images' resampling of frame `f` at sample position `uv`:
    /// Catmull–Rom over the frame pixels whose squares lie at least
    /// [`CLEAN_MARGIN_PX`] inside the sample, the weights renormalised over
    /// them. Nothing of the holder around the sample mixes in, while the
    /// sample's own pixels are used up to its edge. Where those pixels carry
    /// less than half the filter, the position moves in from the edges by
    /// [`REGION_EDGE_PX`] (then 2×, 4×: a corner of a rotated view) until
    /// they carry a quarter.
    pub fn region_sample(&self, f: &crate::camera::Frame, uv: [f64; 2]) -> [f64; 3] {
        self.region_filter(frame_dims(f), uv).apply(f)
    }

    /// The filter [`Self::region_sample`] applies at `uv` to frames of
    /// `dims` px: it depends on the view only, so a region builder finds
    /// it once for all lights.
    pub fn region_filter(&self, dims: [usize; 2], uv: [f64; 2]) -> BicubicFilter {
        self.region_filter_through(&Pinhole, dims, uv)
    }

    /// [`Self::region_filter`] for a frame that shows the homography's
    /// pinhole image through `lens` (a photograph's lens distortion): the
    /// homography's edges are straight in the pinhole image, and a frame
    /// pixel is on the sample if its centre, taken back through the lens,
    /// lies [`CLEAN_MARGIN_PX`] inside them.
    #[inline]
    pub fn region_filter_through(
        &self,
        lens: &impl FrameMap,
        dims: [usize; 2],
        uv: [f64; 2],
    ) -> BicubicFilter {
        let p = self.homography.apply(uv);
        let q = lens.in_frame(p);
        // Every tap lies within 2 frame px per axis of q, so within
        // 4 · half · stretch along any edge's normal: all of them usable,
        // the plain filter.
        if self.depth(p) >= 2.0 * std::f64::consts::SQRT_2 * lens.stretch() + CLEAN_MARGIN_PX {
            return BicubicFilter::new(dims, q[0], q[1]);
        }
        let clean = |x: f64, y: f64| self.pixel_on_sample(lens.in_pinhole([x, y]));
        if let Some(b) = BicubicFilter::masked(dims, q[0], q[1], clean, 0.5) {
            return b;
        }
        for k in [1.0, 2.0, 4.0] {
            let q = lens.in_frame(self.inset_point(uv, k * REGION_EDGE_PX));
            if let Some(b) = BicubicFilter::masked(dims, q[0], q[1], clean, 0.25) {
                return b;
            }
        }
        // A view of a few pixels: the plain filter at the centre.
        let q = lens.in_frame(self.homography.apply([0.5, 0.5]));
        BicubicFilter::new(dims, q[0], q[1])
    }

    /// [`Self::region_filter`] that also reads the pixels straddling the
    /// sample's edge, each for its part on the sample (at least
    /// [`MIN_EDGE_SHARE`] of its square, by the calibrated edges): the
    /// outermost texels are then measured from the pixels over them rather
    /// than taken from pixels further in. Apply it with the holder's
    /// radiance beside the sample ([`BicubicFilter::apply_beside`],
    /// [`Self::holder_band`]). Where those pixels carry less than half the
    /// filter, [`Self::region_filter`]'s.
    pub fn region_filter_straddling(&self, dims: [usize; 2], uv: [f64; 2]) -> BicubicFilter {
        let p = self.homography.apply(uv);
        if self.depth(p) >= 2.0 * std::f64::consts::SQRT_2 + CLEAN_MARGIN_PX {
            return BicubicFilter::new(dims, p[0], p[1]);
        }
        let share = |x: f64, y: f64| self.share([x, y]);
        BicubicFilter::straddling(dims, p[0], p[1], share, MIN_EDGE_SHARE, 0.5)
            .unwrap_or_else(|| self.region_filter(dims, uv))
    }

    /// The share of the pixel square centred at frame point `p` that lies
    /// on the sample, by the calibrated edges: the area of the square
    /// clipped by the four edges' half-planes, exact (a camera pixel
    /// integrates its whole square).
    pub fn share(&self, p: [f64; 2]) -> f64 {
        let d = self.depth(p);
        if d >= 0.0 {
            return 1.0;
        }
        // Across a closed side: not read.
        let across = |(e, &closed): (&FrameEdge, &bool)| {
            closed && e.n[0] * p[0] + e.n[1] * p[1] - e.c - e.half < 0.0
        };
        if self.edges.iter().zip(&self.closed).any(across) {
            return 0.0;
        }
        // Every point of the square lies within √2 · ½ px of its centre.
        if self.point_depth(p) < -std::f64::consts::FRAC_1_SQRT_2 {
            return 0.0;
        }
        let mut poly = scanner_geometry::polygon::Polygon::pixel(p);
        for e in &self.edges {
            poly = poly.clip(|q| e.n[0] * q[0] + e.n[1] * q[1] - e.c);
            if poly.is_empty() {
                return 0.0;
            }
        }
        poly.area().clamp(0.0, 1.0)
    }

    /// The frame pixels (index y · width + x in frames of `dims`) that show
    /// what surrounds the sample beside it: their centres 1.5 to 3.5 px
    /// outside its calibrated edges, beyond a side that is not closed
    /// ([`Self::with_closed_sides`]). Their median is the holder's radiance that
    /// [`Self::region_filter_straddling`]'s filters take out of the pixels
    /// straddling the edge ([`holder_radiance`]).
    pub fn holder_band(&self, dims: [usize; 2]) -> Vec<u32> {
        let corners = self.homography.corners();
        let lo = |k: usize| corners.iter().map(|c| c[k]).fold(f64::INFINITY, f64::min);
        let hi = |k: usize| corners.iter().map(|c| c[k]).fold(f64::NEG_INFINITY, f64::max);
        let range = |k: usize| {
            let a = (lo(k) - 4.0).floor().max(0.0) as usize;
            let b = ((hi(k) + 4.0).ceil().max(0.0) as usize).min(dims[k]);
            a..b
        };
        let mut band = Vec::new();
        for y in range(1) {
            for x in range(0) {
                let p = [x as f64 + 0.5, y as f64 + 0.5];
                let beyond_closed = (0..4).any(|k| self.closed[k] && self.edge_depth(k, p) < 0.0);
                if (-3.5..=-1.5).contains(&self.point_depth(p)) && !beyond_closed {
                    band.push((y * dims[0] + x) as u32);
                }
            }
        }
        band
    }

    /// How far frame point `p` lies inside the sample's calibrated edges
    /// (px; negative: outside).
    #[inline]
    fn point_depth(&self, p: [f64; 2]) -> f64 {
        (0..4).map(|side| self.edge_depth(side, p)).fold(f64::INFINITY, f64::min)
    }

    /// The inward unit normal of calibrated edge `side` (v 0, u 1, v 1, u 0).
    pub fn edge_normal(&self, side: usize) -> [f64; 2] {
        self.edges[side].n
    }

    /// How far frame point `p` lies inside one calibrated edge of the
    /// sample (px; negative: outside): `side` 0…3 the edges at v 0, u 1,
    /// v 1 and u 0.
    #[inline]
    pub fn edge_depth(&self, side: usize, p: [f64; 2]) -> f64 {
        let e = &self.edges[side];
        e.n[0] * p[0] + e.n[1] * p[1] - e.c
    }

    /// How [`Self::region_sample`] scales the variance of independent frame
    /// pixels at uv: Σ w² over its plain filter's taps there (1 at a pixel
    /// centre, 0.41 midway between four).
    pub fn region_noise_gain(&self, uv: [f64; 2]) -> f64 {
        let p = self.homography.apply(uv);
        let axis = |x: f64| {
            let f = x - 0.5;
            super::plane::catmull_rom(f - f.floor()).iter().map(|w| w * w).sum::<f64>()
        };
        axis(p[0]) * axis(p[1])
    }
}

/// The largest phase-alignment residual ([`ViewCalibration::phase_rms_px`])
/// at which a view's straddling pixels are read
/// ([`ViewCalibration::edge_precise`]), px. A calibrated edge δ px off
/// moves a straddling pixel's reading by δ / share of the contrast between
/// sample and holder, ≈ 0.6 % of level per 0.01 px on a textured sample:
/// the straddling reading gains on the outermost texels only where the
/// edges are known to ≈ 0.01 px (docs/benchmarks.md, sessions 73 and 76).
/// The residual is of the size of the edges' true error (0.55–0.85 × its
/// RMS) and ranks the views by it.
pub const EDGE_PRECISE_PX: f64 = 0.01;

/// The least share of a pixel's square on the sample for the region
/// images to read the sample's part of it beside the holder
/// ([`ViewSampler::region_filter_straddling`]): a calibrated edge δ px off
/// moves a pixel's sample estimate by about δ / share of the contrast
/// between sample and holder.
pub const MIN_EDGE_SHARE: f64 = 0.5;

/// The radiance (RGB, frame units) of what surrounds the sample in frame
/// `f`: the median of the [`ViewSampler::holder_band`] pixels per channel
/// (0 where the band is empty).
pub fn holder_radiance(f: &crate::camera::Frame, band: &[u32]) -> [f64; 3] {
    let mut out = [0.0; 3];
    if band.is_empty() {
        return out;
    }
    let mut v: Vec<f32> = Vec::with_capacity(band.len());
    for (c, o) in out.iter_mut().enumerate() {
        v.clear();
        v.extend(band.iter().filter_map(|&i| f.rgb.get(3 * i as usize + c)));
        let mid = v.len() / 2;
        let (_, m, _) = v.select_nth_unstable_by(mid, f32::total_cmp);
        *o = *m as f64;
    }
    out
}

/// Frame pixels kept between a resampled position and the sample's edge
/// where every tap of the filter must lie on the sample (the colour
/// calibration's cell means, the glossy target's flanks).
pub const EDGE_PX: f64 = 2.0;
/// How far inside the sample's edge a frame pixel's square must lie for
/// the region images to use it: several times the calibration's corner
/// error (≈ 0.1 px RMS, docs/benchmarks.md).
pub const CLEAN_MARGIN_PX: f64 = 0.25;
/// The region images' first fallback inset from the sample's edge (frame
/// px) where too few clean pixels surround a position.
pub const REGION_EDGE_PX: f64 = 1.0;

impl Calibration {
    /// Read and check a calibration file.
    pub fn load(path: &std::path::Path) -> Result<Calibration, BuildError> {
        let text = scanner_formats::input::read_to_string(path)
            .map_err(|e| BuildError::Input(format!("{}: {e}", path.display())))?;
        Calibration::parse(&text).map_err(|e| BuildError::Input(format!("{}: {e}", path.display())))
    }

    /// Parse and check a calibration file's text (what [`Calibration::load`]
    /// reads): a calibration whose every number is usable, or why not.
    /// [`Calibration::check_geometry`] then checks it against a scanner.
    pub fn parse(text: &str) -> Result<Calibration, String> {
        let mut c: Calibration =
            serde_json::from_str(text).map_err(|e| format!("not a calibration file: {e}"))?;
        for v in &mut c.views {
            v.located_by.get_or_insert(if v.corners_used > 0 {
                LocatedBy::Corners
            } else {
                LocatedBy::Phase
            });
        }
        if c.format != CALIBRATION_FORMAT || !(1..=CALIBRATION_VERSION).contains(&c.version) {
            return Err(format!(
                "{} version {} (this build reads {CALIBRATION_FORMAT} 1 to {CALIBRATION_VERSION})",
                c.format, c.version
            ));
        }
        c.validate()?;
        Ok(c)
    }

    fn validate(&self) -> Result<(), String> {
        let most = protocol::MAX_MIRRORS;
        if self.views.len() > most || self.lights.len() > most {
            return Err(format!(
                "{} views and {} lights (a scanner has at most {most} mirrors)",
                self.views.len(),
                self.lights.len()
            ));
        }
        let g = self.colour.grid;
        if g == 0 || g > 1024 {
            return Err(format!("colour grid {g}"));
        }
        if self.colour.view_response.len() != self.views.len()
            || self.colour.light_field.len() != self.lights.len()
        {
            return Err("colour fields do not match the views and lights".into());
        }
        if self.colour.view_response.iter().any(|v| v.len() != g * g * 3)
            || self.colour.light_field.iter().any(|v| v.len() != g * g)
        {
            return Err("colour field of the wrong size".into());
        }
        // Every number finite, and within the geometry's ±1e9: a mirror point
        // at 10³⁰⁸ mm put the view's virtual camera at infinity. The checks
        // below take finiteness as given.
        scanner_geometry::check_numbers(self)?;
        let unit = |d: &[f64; 3]| (d.iter().map(|x| x * x).sum::<f64>() - 1.0).abs() < 1e-6;
        for (k, v) in self.views.iter().enumerate() {
            if !unit(&v.direction) || v.homography.inverse().is_none() {
                return Err(format!(
                    "view {}: bad homography or direction (not a finite unit vector)",
                    v.view
                ));
            }
            if v.phase_rms_px.is_some_and(|r| r < 0.0) {
                return Err(format!("view {}: negative phase residual", v.view));
            }
            if v.edge_offsets_px.is_some_and(|o| o.iter().flatten().any(|d| d.abs() > 1.0)) {
                return Err(format!(
                    "view {}: edges more than a pixel from its homography's outline",
                    v.view
                ));
            }
            if !unit(&v.mirror_normal) {
                return Err(format!("view {}: bad phase homography or mirror plane", v.view));
            }
            if self.views[..k].iter().any(|o| o.view == v.view) {
                return Err(format!("view {} calibrated twice", v.view));
            }
        }
        for (k, l) in self.lights.iter().enumerate() {
            if !unit(&l.direction) {
                return Err(format!(
                    "light {}: bad direction (not a finite unit vector) or axes",
                    l.light
                ));
            }
            if self.lights[..k].iter().any(|o| o.light == l.light) {
                return Err(format!("light {} calibrated twice", l.light));
            }
        }
        let fields = self.colour.view_response.iter().chain(&self.colour.light_field);
        if fields.clone().flatten().any(|x| *x < 0.0) {
            return Err("colour field with a negative or non-finite value".into());
        }
        if fields.clone().any(|f| !f.iter().any(|&x| x > 0.0)) {
            return Err("a view's response or a light's field is 0 everywhere".into());
        }
        // The light fields are normalised to a mean of 1 over all lights and cells.
        let (sum, n) = self
            .colour
            .light_field
            .iter()
            .flatten()
            .fold((0.0, 0usize), |(s, n), &x| (s + x as f64, n + 1));
        if n > 0 && (sum / n as f64 - 1.0).abs() > 1e-3 {
            return Err(format!("light fields' mean {:.4}, not 1", sum / n as f64));
        }
        for v in &self.views {
            // Positive depth over the whole sample (w is linear in uv: its
            // corners decide), so the sample maps to one convex quadrilateral.
            let h = &v.homography.0;
            let corners = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
            if corners.iter().any(|c| h[6] * c[0] + h[7] * c[1] + h[8] <= 0.0) {
                return Err(format!("view {}: its homography folds the sample over", v.view));
            }
        }
        if !(self.colour.white_albedo > 0.0 && self.colour.white_albedo <= 1.0) {
            return Err("white albedo outside (0, 1]".into());
        }
        let [cw, ch] = self.camera_px;
        if let Some(d) = self.defects.iter().find(|d| d.x >= cw || d.y >= ch) {
            return Err(format!(
                "sensor defect at ({}, {}) outside the {cw}×{ch} px frame",
                d.x, d.y
            ));
        }
        if crate::defects::union(&self.defects, &[]).len() != self.defects.len() {
            return Err("a sensor defect listed twice".into());
        }
        Ok(())
    }

    /// Check that this calibration is of scanner `g`: the same geometry
    /// hash, camera size and mirrors.
    pub fn check_geometry(&self, g: &ScannerGeometry) -> Result<(), BuildError> {
        if self.geometry_sha256 != g.hash() {
            return Err(BuildError::Input(format!(
                "the calibration is of geometry {}…, the scanner's is {}…",
                &self.geometry_sha256.get(..12).unwrap_or("?"),
                &g.hash()[..12]
            )));
        }
        if self.camera_px != [g.camera.width, g.camera.height] {
            return Err(BuildError::Input(format!(
                "the calibration is of a {}×{} px camera, the scanner's is {}×{} px",
                self.camera_px[0], self.camera_px[1], g.camera.width, g.camera.height
            )));
        }
        let n = g.mirrors.len();
        let labels = self.views.iter().map(|v| v.view).chain(self.lights.iter().map(|l| l.light));
        if let Some(m) = labels.into_iter().find(|&m| m >= n) {
            return Err(BuildError::Input(format!(
                "the calibration names mirror {m}; the scanner has mirrors 0…{}",
                n.saturating_sub(1)
            )));
        }
        let (w, h) = (g.camera.width as f64, g.camera.height as f64);
        for v in &self.views {
            let corners = v.homography.corners();
            if corners.iter().any(|p| !(0.0..=w).contains(&p[0]) || !(0.0..=h).contains(&p[1])) {
                return Err(BuildError::Input(format!(
                    "the calibration's view {} puts the sample outside the {}×{} px frame",
                    v.view, g.camera.width, g.camera.height
                )));
            }
            // Where `calibrate` can have found the view: within the window
            // it searches around the nominal view, at about the nominal
            // size. A damaged file (a view collapsed to a point, or spread
            // over the frame) would otherwise choose the region size and
            // its memory.
            let (Some(nominal), Some(window)) = (
                super::locate::nominal_homography(g, v.view),
                super::locate::search_window(g, v.view),
            ) else {
                return Err(BuildError::Input(format!(
                    "mirror {}: the scanner's geometry does not show the sample through it",
                    v.view
                )));
            };
            let b = v.homography.bounds();
            let inside = b[0] >= window[0] as f64
                && b[1] >= window[1] as f64
                && b[2] <= window[2] as f64
                && b[3] <= window[3] as f64;
            let ratio = v.homography.area() / nominal.area();
            if !inside || !(0.5..=2.0).contains(&ratio) {
                return Err(BuildError::Input(format!(
                    "the calibration's view {} shows the sample over x {:.0}…{:.0}, y {:.0}…{:.0} px \
                     at {ratio:.3} × its nominal area, where calibrating searches x {}…{}, \
                     y {}…{} px at ½ to 2 ×: a damaged file, or not this scanner's",
                    v.view, b[0], b[2], b[1], b[3], window[0], window[2], window[1], window[3]
                )));
            }
        }
        Ok(())
    }

    /// Write atomically (JSON).
    pub fn save(&self, path: &std::path::Path) -> Result<(), BuildError> {
        let mut text = serde_json::to_string(self).expect("calibration serialises");
        text.push('\n');
        crate::fsutil::write_atomic(path, text.as_bytes())
            .map_err(|e| BuildError::Output(format!("{}: {e}", path.display())))
    }

    /// SHA-256 of the canonical JSON, hex.
    pub fn hash(&self) -> String {
        use sha2::Digest;
        let text = serde_json::to_string(self).expect("calibration serialises");
        crate::scan::hex(&sha2::Sha256::digest(text.as_bytes()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::build::scanread::frame_bicubic;
    use crate::camera::Frame;

    /// Beam coverage compares each light's field with the others', cell
    /// by cell: a profile all lights share (vignetting, the factorisation's
    /// free split between view and light) and each light's own level
    /// (cos θi) leave it at 1; a light whose beam leaves a corner of the
    /// sample dim reads that corner's share.
    #[test]
    fn beam_coverage_tells_a_beam_that_misses_part_of_the_sample() {
        let grid = 8;
        let shared = |c: usize| {
            0.6 + 0.4 * ((c % grid) as f64 / grid as f64) * ((c / grid) as f64 / grid as f64)
        };
        let mut fields: Vec<Vec<f32>> = (0..5)
            .map(|l| {
                (0..grid * grid).map(|c| (shared(c) * (0.5 + 0.2 * l as f64)) as f32).collect()
            })
            .collect();
        let colour = |fields: &[Vec<f32>]| ColourCalibration {
            grid,
            white_albedo: 0.98,
            view_response: Vec::new(),
            light_field: fields.to_vec(),
        };
        for c in colour(&fields).beam_coverage() {
            assert!((c - 1.0).abs() < 1e-6, "{c}");
        }
        // Light 3's beam gives the last row 30 % of its light.
        for x in &mut fields[3][grid * (grid - 1)..] {
            *x *= 0.3;
        }
        let coverage = colour(&fields).beam_coverage();
        // (Within 1 %: the dim row moves which cell is the light's 90th
        // percentile, its level, on the shared gradient.)
        assert!((coverage[3] - 0.3).abs() < 0.01, "{coverage:?}");
        for (l, c) in coverage.iter().enumerate().filter(|(l, _)| *l != 3) {
            assert!((c - 1.0).abs() < 1e-6, "light {l}: {c}");
        }
        // Too few lights to compare: nothing told.
        assert_eq!(colour(&fields[..2]).beam_coverage(), [1.0, 1.0]);
    }

    /// Where a beam can be read: everywhere for beams that fall off
    /// smoothly across the sample (a shared gradient, one light's own 30 %
    /// tilt, another's Gaussian 20 mm wide), even where most beams leave
    /// part of it dark; not where a beam's soft edge (a raised cosine over
    /// 4 mm, as the simulator's) crosses it, nor beyond, nor where the
    /// lights leave a cell dark.
    #[test]
    fn a_beam_is_read_where_its_field_is_smooth_not_in_its_soft_edge() {
        let grid = 32;
        let mm = |i: usize| (i as f64 + 0.5) / grid as f64 * 25.4;
        let raised = |x: f64, at: f64| {
            // 1 before `at` − 2 mm, 0 after `at` + 2 mm.
            let t = ((x - at + 2.0) / 4.0).clamp(0.0, 1.0);
            0.5 * (1.0 + (std::f64::consts::PI * t).cos())
        };
        let field = |l: usize, c: usize| -> f64 {
            let (x, y) = (mm(c % grid), mm(c / grid));
            let shared = 0.8 + 0.2 * x / 25.4;
            let own = match l {
                0 => 1.0 - 0.3 * y / 25.4,
                1 => (-((x - 5.0).powi(2) + (y - 8.0).powi(2)) / (2.0 * 20.0f64.powi(2))).exp(),
                // The edge crosses the sample at u = 16 mm.
                2 => raised(x, 16.0),
                _ => 1.0,
            };
            shared * own * (0.6 + 0.01 * l as f64)
        };
        let colour = |n: usize| ColourCalibration {
            grid,
            white_albedo: 0.98,
            view_response: Vec::new(),
            light_field: (0..n)
                .map(|l| (0..grid * grid).map(|c| field(l, c) as f32).collect())
                .collect(),
        };
        let map = colour(40).beam_map();
        let uv = |x: f64, y: f64| [x / 25.4, y / 25.4];
        for l in [0, 1, 3, 39] {
            for c in 0..grid * grid {
                let at = uv(mm(c % grid), mm(c / grid));
                assert!(
                    map.readable(l, at),
                    "light {l} at {at:?}: {:?}",
                    (map.fraction(l, at), map.bend(l, at))
                );
            }
        }
        assert!([0, 1, 3, 39].iter().all(|&l| map.readable_everywhere(l)));
        assert!(!map.readable_everywhere(2));
        // Light 2: read well before its edge, not within it or beyond.
        for c in 0..grid * grid {
            let (x, at) = (mm(c % grid), uv(mm(c % grid), mm(c / grid)));
            if x < 12.5 {
                assert!(
                    map.readable(2, at),
                    "{x} mm: {:?}",
                    (map.fraction(2, at), map.bend(2, at))
                );
            }
            if x > 14.5 {
                assert!(
                    !map.readable(2, at),
                    "{x} mm: {:?}",
                    (map.fraction(2, at), map.bend(2, at))
                );
            }
        }
        // Half the beams' edges crossing the sample: the others still read
        // everywhere, the edges still not.
        let mut half = colour(40);
        for l in 20..40 {
            half.light_field[l] = (0..grid * grid)
                .map(|c| (field(l, c) * raised(mm(c / grid), 20.0)) as f32)
                .collect();
        }
        let map = half.beam_map();
        for c in 0..grid * grid {
            let (y, at) = (mm(c / grid), uv(mm(c % grid), mm(c / grid)));
            assert!(map.readable(3, at) && map.readable(0, at), "{at:?}");
            if y > 18.5 {
                assert!(!map.readable(25, at), "{y} mm");
            }
        }
        // Cells every light leaves dark: not read.
        let mut dark = colour(4);
        for f in &mut dark.light_field {
            f[0] = 0.0;
        }
        assert!(!dark.beam_map().readable(3, [0.0, 0.0]));
        // Too few lights to compare: read everywhere.
        assert!(colour(2).beam_map().readable(1, [0.5, 0.5]));
    }

    /// A pixel's share on the sample is its square's exact area within the
    /// calibrated edges: against 512 × 512 points a square over a rotated,
    /// perspective view's edges and corners (where two edges clip it), and
    /// exactly a straight edge's offset across a square it crosses.
    #[test]
    fn a_pixel_s_share_is_its_square_s_area_on_the_sample() {
        let (c, s) = (0.3f64.cos(), 0.3f64.sin());
        let h = Homography([40.0 * c, -40.0 * s, 30.2, 40.0 * s, 40.0 * c, 10.7, 1e-3, -2e-3, 1.0]);
        let v = ViewSampler::new(h);
        let n = 512;
        let dense = |p: [f64; 2]| {
            let mut on = 0usize;
            for k in 0..n * n {
                let q = [
                    p[0] - 0.5 + ((k % n) as f64 + 0.5) / n as f64,
                    p[1] - 0.5 + ((k / n) as f64 + 0.5) / n as f64,
                ];
                on += usize::from(v.point_on_sample(q));
            }
            on as f64 / (n * n) as f64
        };
        let mut crossed = 0;
        for corner in h.corners() {
            for dy in -2..=2 {
                for dx in -2..=2 {
                    let p = [
                        (corner[0] + dx as f64 * 0.7).floor() + 0.5,
                        (corner[1] + dy as f64 * 0.7).floor() + 0.5,
                    ];
                    let (got, want) = (v.share(p), dense(p));
                    assert!((got - want).abs() < 4.0 / n as f64, "{p:?}: {got} against {want}");
                    crossed += usize::from(got > 0.0 && got < 1.0);
                }
            }
        }
        assert!(crossed > 20, "{crossed}");
        // An edge along the pixel grid, 0.3 px into a column of squares.
        let straight =
            ViewSampler::new(Homography([20.0, 0.0, 10.3, 0.0, 20.0, 10.0, 0.0, 0.0, 1.0]));
        assert!((straight.share([10.5, 20.5]) - 0.7).abs() < 1e-12);
        assert!((straight.share([9.5, 20.5]) - 0.0).abs() < 1e-12);
        assert!((straight.share([11.5, 20.5]) - 1.0).abs() < 1e-12);
    }

    /// The noise gain is the variance a region sample takes from frame
    /// pixels of unit variance: 1 at a pixel centre, 0.640625² midway,
    /// and over a frame of independent noise the mean square of the samples.
    #[test]
    fn region_noise_gain_is_the_filter_s_sum_of_squared_weights() {
        use rand::{Rng, SeedableRng};
        // uv → frame: 40 px across, rotated, off the pixel grid.
        let (c, s) = (0.3f64.cos(), 0.3f64.sin());
        let h = Homography([40.0 * c, -40.0 * s, 30.2, 40.0 * s, 40.0 * c, 10.7, 0.0, 0.0, 1.0]);
        let v = ViewSampler::new(h);
        let inv = h.inverse().unwrap();
        assert!((v.region_noise_gain(inv.apply([40.5, 30.5])) - 1.0).abs() < 1e-9);
        assert!((v.region_noise_gain(inv.apply([41.0, 31.0])) - 0.640625f64.powi(2)).abs() < 1e-9);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let (w, hgt) = (96usize, 96usize);
        let rgb = (0..w * hgt * 3).map(|_| (rng.random::<f32>() - 0.5) * 12f32.sqrt()).collect();
        let f = Frame { width: w as u32, height: hgt as u32, rgb };
        let (mut square, mut gain) = (0.0, 0.0);
        let n = 4000;
        for _ in 0..n {
            let uv = [0.1 + 0.8 * rng.random::<f64>(), 0.1 + 0.8 * rng.random::<f64>()];
            square += v.region_sample(&f, uv).iter().map(|x| x * x).sum::<f64>() / 3.0;
            gain += v.region_noise_gain(uv);
        }
        let (square, gain) = (square / n as f64, gain / n as f64);
        assert!((square / gain - 1.0).abs() < 0.05, "{square} against {gain}");
    }

    /// A frame in which the sample (a rotated, non-pixel-aligned square)
    /// shows a smooth ramp and every pixel that reaches outside it shows a
    /// bright holder: the region sampler must read the ramp up to the
    /// sample's edge, never the holder, and closer to the truth than the
    /// plain filter 2 px inside.
    #[test]
    fn region_samples_reach_the_edge_without_the_holder() {
        let (c, s) = (20f64.to_radians().cos(), 20f64.to_radians().sin());
        let k = 30.0;
        // uv → frame: rotate, scale to 30 px, offset off the pixel grid.
        let h = Homography([k * c, -k * s, 20.3, k * s, k * c, 8.6, 0.0, 0.0, 1.0]);
        let ramp = |p: [f64; 2]| 1.0 + 0.02 * p[0] + 0.01 * p[1];
        let inside = |p: [f64; 2]| {
            let (x, y) = (p[0] - 20.3, p[1] - 8.6);
            let (u, v) = ((c * x + s * y) / k, (-s * x + c * y) / k);
            (0.0..=1.0).contains(&u) && (0.0..=1.0).contains(&v)
        };
        let (w, hgt) = (64usize, 64usize);
        let mut rgb = vec![0f32; w * hgt * 3];
        for y in 0..hgt {
            for x in 0..w {
                let (x0, y0) = (x as f64, y as f64);
                let clean = [[x0, y0], [x0 + 1.0, y0], [x0, y0 + 1.0], [x0 + 1.0, y0 + 1.0]]
                    .into_iter()
                    .all(inside);
                let v = if clean { ramp([x0 + 0.5, y0 + 0.5]) } else { 50.0 };
                rgb[3 * (y * w + x)..][..3].fill(v as f32);
            }
        }
        let f = Frame { width: w as u32, height: hgt as u32, rgb };
        let sampler = ViewSampler::new(h);
        let n = 64;
        let (mut err_new, mut err_old, mut edge) = (0.0, 0.0, 0);
        for i in 0..n * n {
            let uv = crate::build::plane::cell_uv(i, n);
            let truth = ramp(h.apply(uv));
            let got = sampler.region_sample(&f, uv)[0];
            assert!((got - truth).abs() < 0.06, "uv {uv:?}: {got} against {truth}");
            let near = uv.iter().any(|&x| x.min(1.0 - x) < 3.0 / k);
            if near {
                let q = sampler.frame_point(uv);
                err_new += (got - truth).abs();
                err_old += (frame_bicubic(&f, q[0], q[1])[0] - truth).abs();
                edge += 1;
            }
        }
        let (err_new, err_old) = (err_new / edge as f64, err_old / edge as f64);
        eprintln!("near the edge: mean error {err_new:.4} against {err_old:.4}");
        assert!(err_new < 0.5 * err_old, "near the edge: {err_new} against {err_old}");
    }

    /// A grey frame of `dims` px whose pixels integrate `at` (frame px)
    /// over their squares (16 × 16 points).
    fn integrated_frame(dims: [usize; 2], at: impl Fn([f64; 2]) -> f64) -> Frame {
        let [w, hgt] = dims;
        let mut rgb = vec![0f32; w * hgt * 3];
        for y in 0..hgt {
            for x in 0..w {
                let mut sum = 0.0;
                for k in 0..256 {
                    let (i, j) = ((k % 16) as f64, (k / 16) as f64);
                    sum += at([x as f64 + (i + 0.5) / 16.0, y as f64 + (j + 0.5) / 16.0]);
                }
                rgb[3 * (y * w + x)..][..3].fill((sum / 256.0) as f32);
            }
        }
        Frame { width: w as u32, height: hgt as u32, rgb }
    }

    /// A frame whose pixels integrate a rotated, non-pixel-aligned sample
    /// (a pattern of 8 px period) beside a holder of another radiance,
    /// each pixel the mean of 16 × 16 points over its square: the holder's
    /// band finds the holder's radiance, and the filter that reads the
    /// pixels straddling the edge comes closer to the sample at its
    /// outermost positions than the one that reads only the pixels wholly
    /// inside.
    #[test]
    fn straddling_pixels_are_read_for_their_part_on_the_sample() {
        let (c, s) = (20f64.to_radians().cos(), 20f64.to_radians().sin());
        let k = 30.0;
        let (ox, oy) = (20.3, 8.6);
        let h = Homography([k * c, -k * s, ox, k * s, k * c, oy, 0.0, 0.0, 1.0]);
        let uv_of = |p: [f64; 2]| {
            let (x, y) = (p[0] - ox, p[1] - oy);
            [(c * x + s * y) / k, (-s * x + c * y) / k]
        };
        let pattern = |p: [f64; 2]| {
            1.0 + 0.4 * (std::f64::consts::TAU * p[0] / 8.0).sin() * (p[1] / 11.0).cos()
        };
        let holder = 0.3;
        let (w, hgt) = (64usize, 64usize);
        let f = integrated_frame([w, hgt], |p| {
            let on = uv_of(p).iter().all(|t| (0.0..=1.0).contains(t));
            if on { pattern(p) } else { holder }
        });
        // The outermost texels of a 32² image (each ≈ 0.94 px) through a
        // calibration whose edges lie `off` px along x and y from the
        // sample's: RMS error against the pattern at the calibrated
        // position, with and without the straddling pixels.
        let outermost = |off: f64| {
            let h = Homography([k * c, -k * s, ox + off, k * s, k * c, oy + off, 0.0, 0.0, 1.0]);
            let sampler = ViewSampler::new(h);
            let found = holder_radiance(&f, &sampler.holder_band([w, hgt]));
            let n = 32;
            let (mut err_new, mut err_old, mut edge) = (0.0, 0.0, 0);
            for i in 0..n * n {
                let uv = crate::build::plane::cell_uv(i, n);
                if !uv.iter().any(|&x| x.min(1.0 - x) < 1.0 / n as f64) {
                    continue;
                }
                let truth = pattern(h.apply(uv));
                let new = sampler.region_filter_straddling([w, hgt], uv).apply_beside(&f, found)[0];
                err_new += (new - truth).powi(2);
                err_old += (sampler.region_sample(&f, uv)[0] - truth).powi(2);
                edge += 1;
            }
            ((err_new / edge as f64).sqrt(), (err_old / edge as f64).sqrt())
        };
        let sampler = ViewSampler::new(h);
        let band = sampler.holder_band([w, hgt]);
        assert!(band.len() > 100, "{} pixels beside the sample", band.len());
        let found = holder_radiance(&f, &band);
        assert!(found.iter().all(|v| (v - holder).abs() < 1e-6), "holder {found:?}");
        let (new, old) = outermost(0.0);
        eprintln!("outermost texels: RMS error {new:.4} against {old:.4}");
        assert!(new < 0.6 * old, "outermost texels: {new} against {old}");
        // An edge 0.1 px off (about twice the simulator's calibration
        // error) still leaves them better read; 0.2 px does not
        // (docs/calibration-format.md).
        let (new, old) = outermost(0.1);
        eprintln!("edges 0.1 px off: {new:.4} against {old:.4}");
        assert!(new < old, "edges 0.1 px off: {new} against {old}");
        let (new, old) = outermost(0.2);
        eprintln!("edges 0.2 px off: {new:.4} against {old:.4}");
    }

    /// A thick sample's side shows beyond one edge, brighter than the
    /// face: with that side closed, the holder's radiance is read beyond
    /// the others alone and no pixel across it is read for its share, so
    /// the outermost texels along it are read from the face alone while
    /// the other edges' still straddle.
    #[test]
    fn no_pixel_is_read_across_a_closed_side() {
        let k = 30.0;
        // The edge at u = 1 crosses its pixels at 0.7 of their width.
        let (ox, oy) = (17.7, 9.6);
        let h = Homography([k, 0.0, ox, 0.0, k, oy, 0.0, 0.0, 1.0]);
        let (w, hgt) = (56usize, 56usize);
        let (face, side, holder) = (1.0, 3.0, 0.2);
        // The side: 2.5 px beyond the edge at u = 1.
        let at = |p: [f64; 2]| {
            let uv = [(p[0] - ox) / k, (p[1] - oy) / k];
            let across = (0.0..=1.0).contains(&uv[1]);
            if across && (0.0..=1.0).contains(&uv[0]) {
                face
            } else if across && uv[0] > 1.0 && uv[0] < 1.0 + 2.5 / k {
                side
            } else {
                holder
            }
        };
        let f = integrated_frame([w, hgt], at);
        // The outermost texels of a 32² image along each edge: the largest
        // error against the face's level.
        let worst = |sampler: ViewSampler| -> [f64; 4] {
            let found = holder_radiance(&f, &sampler.holder_band([w, hgt]));
            let mut err = [0.0f64; 4];
            let n = 32;
            for i in 0..n * n {
                let uv = crate::build::plane::cell_uv(i, n);
                let edge = [uv[1], 1.0 - uv[0], 1.0 - uv[1], uv[0]];
                let Some(e) = (0..4).find(|&e| edge[e] < 1.0 / n as f64) else {
                    continue;
                };
                let v = sampler.region_filter_straddling([w, hgt], uv).apply_beside(&f, found)[0];
                err[e] = err[e].max((v - face).abs());
            }
            err
        };
        let open = ViewSampler::new(h);
        let closed = open.with_closed_sides([false, true, false, false]);
        let found = holder_radiance(&f, &closed.holder_band([w, hgt]));
        assert!(found.iter().all(|v| (v - holder).abs() < 1e-6), "holder {found:?}");
        assert!(holder_radiance(&f, &open.holder_band([w, hgt]))[0] >= holder);
        // A pixel across the closed side is not read; one across another is.
        let beyond = |uv: [f64; 2]| h.apply(uv);
        assert_eq!(closed.share(beyond([1.0 + 0.3 / k, 0.5])), 0.0);
        assert!((open.share(beyond([1.0 + 0.3 / k, 0.5])) - 0.2).abs() < 1e-9);
        assert!((closed.share(beyond([-0.3 / k, 0.5])) - 0.2).abs() < 1e-9);
        let (o, c) = (worst(open), worst(closed));
        eprintln!("outermost texels' worst error per edge: open {o:.4?}, closed {c:.4?}");
        // (The corner texels at u = 1 count with the edge at v = 0.)
        assert!(o[1] > 0.5, "the side read as the face: {o:?}");
        assert!(c[0] < 0.05 && c[1] < 0.05 && c[2..] == o[2..], "{c:?} against {o:?}");
    }
}
