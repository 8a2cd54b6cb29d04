//! Region images (Fig. 6 steps 2–3): for every (light, view), the view's
//! part of the frame lit by that light, rectified onto an S × S grid over
//! sample uv (Catmull–Rom bicubic resampling — every view is magnified at
//! the default S, so no view is undersampled) and turned by the colour
//! calibration into f · cos θi: radiance reflected per unit irradiance, in
//! absolute units.

use std::path::Path;

use rayon::prelude::*;
use scanner_geometry::ScannerGeometry;

use super::calibrate::{BuildProgress, Calibration, EDGE_PRECISE_PX};
use super::error::BuildError;
use super::height::{HeightFit, SampleHeight, measure_height, sides_beyond, view_parallax};
use super::outline::side_reach;
use super::plane::{cell_taps, cell_uv};
use super::scanread::{BicubicFilter, ScanFrames, frame_dims};
use super::superres::{
    Denoiser, DetailLayer, Footprints, Image, SharpenOptions, detail_layer, near_unlit,
    sharpen_light,
};
use crate::hdr;
use scanner_geometry::{DVec3, SampleFace};

/// Region images of one scan.
#[derive(Debug, Clone, PartialEq)]
pub struct RegionSet {
    /// Side of every region image, px.
    pub size: usize,
    /// Lit mirrors, in order.
    pub lights: Vec<usize>,
    /// Seen mirrors, in order.
    pub views: Vec<usize>,
    /// Calibrated direction towards each light, sample-local.
    pub light_dirs: Vec<[f64; 3]>,
    /// Calibrated direction towards each viewer from the sample's centre,
    /// sample-local.
    pub view_dirs: Vec<[f64; 3]>,
    /// Each view's virtual camera, sample-local mm from the sample's centre
    /// ([`super::calibrate::ViewCalibration::viewer_mm`]): the viewer is
    /// ≈ 1.2 m away, so its direction varies over the sample by up to
    /// ≈ 0.6° ([`Self::view_dir_at`]).
    pub viewers_mm: Vec<[f64; 3]>,
    /// Side of the sample, mm (uv ∈ [0, 1]² spans it).
    pub sample_mm: f64,
    /// `images[li * views.len() + vi]`: S × S RGB, row t = v, column s = u,
    /// pixel (s, t) at uv ((s + 0.5)/S, (t + 0.5)/S).
    pub images: Vec<Vec<[f32; 3]>>,
    /// The detail the views resolve together beyond S × S: a 2S × 2S RGB
    /// factor per light (laid out like the images) that multiplies a pair's
    /// S × S image looked up bilinearly, itself looked up bilinearly
    /// ([`Self::detail_at`]); `None` without multi-view detail.
    pub detail: Option<DetailLayer>,
    /// Where the images were read the sample's face to lie
    /// ([`RegionOptions::height`]); the directions and viewers above are in
    /// its frame.
    pub face: SampleFace,
    /// The measurement it came from, if it was measured.
    pub height_fit: Option<HeightFit>,
    /// Whether they were read as a thick sample's, its sides showing
    /// ([`RegionOptions::sides`], resolved: never `Auto`).
    pub sides: SampleSides,
    /// The band beyond the sample's edges at `face`, where it was read
    /// ([`super::outline::beyond_edges`]): the measurement's, or a given
    /// face's when asked to look ([`SampleSides::Auto`]).
    pub beyond: Option<super::outline::Beyond>,
    /// Per light (like `lights`), the texels its beam left unlit or in the
    /// part of its soft edge the calibration cannot follow
    /// ([`super::calibrate::BeamMap::readable`]), row-major S × S; empty
    /// for a light that lit every texel. Nothing was measured there:
    /// [`extract_regions`] fills them
    /// ([`RegionSet::fill_unlit`]), the texel model is fitted without them
    /// and [`RegionSet::write_exr`] writes them as 0.
    pub unlit: Vec<Vec<bool>>,
}

/// Bilinear lookup at uv (clamped to the sample) in an S × S image laid
/// out like a region image.
pub fn bilinear(size: usize, img: &[[f32; 3]], uv: [f64; 2]) -> [f64; 3] {
    let (x0, x1, tx) = cell_taps(size, uv[0]);
    let (y0, y1, ty) = cell_taps(size, uv[1]);
    let at = |i: usize, j: usize, k: usize| img[j * size + i][k] as f64;
    std::array::from_fn(|k| {
        (at(x0, y0, k) * (1.0 - tx) + at(x1, y0, k) * tx) * (1.0 - ty)
            + (at(x0, y1, k) * (1.0 - tx) + at(x1, y1, k) * tx) * ty
    })
}

impl RegionSet {
    /// The image of (light index, view index).
    pub fn image(&self, li: usize, vi: usize) -> &[[f32; 3]] {
        &self.images[li * self.views.len() + vi]
    }

    /// Unit direction from sample position `uv` towards view `vi`'s virtual
    /// camera, sample-local: the direction region image (·, vi) saw the
    /// sample at there ([`Self::view_dirs`] is the one from the centre).
    pub fn view_dir_at(&self, vi: usize, uv: [f64; 2]) -> [f64; 3] {
        let c = self.viewers_mm[vi];
        let d =
            [c[0] - (uv[0] - 0.5) * self.sample_mm, c[1] - (uv[1] - 0.5) * self.sample_mm, c[2]];
        let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        d.map(|x| x / l)
    }

    /// uv of texel `t` (row-major, centre of the texel).
    pub fn texel_uv(&self, t: usize) -> [f64; 2] {
        cell_uv(t, self.size)
    }

    /// The detail layer's factors for light `li` at uv (its parts bilinear
    /// on the 2S × 2S grid, clamped to the sample); 1 without a layer.
    pub fn detail_at(&self, li: usize, uv: [f64; 2]) -> [f64; 3] {
        let Some(d) = &self.detail else {
            return [1.0; 3];
        };
        d.factor(li, |img| bilinear(2 * self.size, img, uv).map(|x| x as f32)).map(f64::from)
    }

    /// Bilinear lookup at uv (clamped to the sample).
    pub fn sample(&self, li: usize, vi: usize, uv: [f64; 2]) -> [f64; 3] {
        bilinear(self.size, self.image(li, vi), uv)
    }

    /// Whether light `li`'s beam left texel `t` unlit ([`Self::unlit`]).
    pub fn is_unlit(&self, li: usize, t: usize) -> bool {
        self.unlit.get(li).and_then(|u| u.get(t)).copied().unwrap_or(false)
    }

    /// Fill the texels each light left unlit ([`Self::unlit`]) from the
    /// lights that lit them, as the default interpolation reads between
    /// lights: f at the light's direction, barycentric over the Delaunay
    /// triangles of those lights' directions (the shading's own weights,
    /// `scanner_shading::locate::TriangleLocator`; beyond their outer ring,
    /// the nearest arc), times the light's cos θi. With fewer than three
    /// such lights, the nearest one's f; a texel no other light lit stays
    /// 0. With a `model` (the value it predicts for light, view and texel
    /// indices), only what the model leaves is read between the lights and
    /// the model's own value is added: a highlight the unlit light would
    /// have seen is kept. Returns how many (light, texel) it filled.
    pub fn fill_unlit(&mut self, model: Option<&UnlitModel<'_>>) -> usize {
        use scanner_shading::locate::{TriangleLocator, Weights3};
        use std::collections::HashMap;
        let (nl, nv) = (self.lights.len(), self.views.len());
        if self.unlit.iter().all(|u| u.is_empty()) || nv == 0 {
            return 0;
        }
        let dirs: Vec<[f64; 3]> = self
            .light_dirs
            .iter()
            .map(|&d| scanner_geometry::DVec3::from_array(d).normalize().to_array())
            .collect();
        // Per (light, texel) to fill, the other lights that lit the texel
        // as a bit set; each distinct set's weights are found once.
        let words = nl.div_ceil(64);
        let mut wanted: HashMap<(usize, Vec<u64>), Vec<usize>> = HashMap::new();
        for li in 0..nl {
            for t in 0..self.size * self.size {
                if !self.is_unlit(li, t) {
                    continue;
                }
                let mut bits = vec![0u64; words];
                for l in (0..nl).filter(|&l| l != li && !self.is_unlit(l, t)) {
                    bits[l / 64] |= 1 << (l % 64);
                }
                wanted.entry((li, bits)).or_default().push(t);
            }
        }
        let weights = |li: usize, bits: &[u64]| -> Vec<(usize, f64)> {
            let others: Vec<usize> =
                (0..nl).filter(|&l| bits[l / 64] >> (l % 64) & 1 == 1).collect();
            let d = dirs[li];
            let angle = |l: usize| {
                let e = dirs[l];
                (d[0] * e[0] + d[1] * e[1] + d[2] * e[2]).clamp(-1.0, 1.0).acos()
            };
            let nearest = || {
                others
                    .iter()
                    .copied()
                    .min_by(|&a, &b| angle(a).total_cmp(&angle(b)))
                    .map(|l| vec![(l, 1.0)])
            };
            let f = |v: [f64; 3]| v.map(|x| x as f32);
            let od: Vec<[f64; 3]> = others.iter().map(|&l| dirs[l]).collect();
            let od32: Vec<[f32; 3]> = od.iter().map(|&v| f(v)).collect();
            let located = (others.len() >= 3)
                .then(|| super::material::triangulate(&od, "the lights that lit a texel").ok())
                .flatten()
                .and_then(|tris| {
                    TriangleLocator::new(&od32, &tris, "the lights that lit a texel").ok()
                });
            let Some(locator) = located else {
                return nearest().unwrap_or_default();
            };
            let mut w: Weights3 = [(0, 0.0); 3];
            locator.weights(f(d), &mut w);
            w.iter()
                .filter(|(_, w)| *w > 0.0)
                .map(|&(i, w)| (others[i as usize], w as f64))
                .collect()
        };
        // Per light and set of lights: their weights, and the texels.
        type Plan = (usize, Vec<(usize, f64)>, Vec<usize>);
        let plan: Vec<Plan> = wanted
            .into_par_iter()
            .map(|((li, bits), texels)| (li, weights(li, &bits), texels))
            .collect();
        let cos = |l: usize| dirs[l][2].max(1e-6);
        let mut filled = 0;
        for (li, w, texels) in plan.iter().filter(|(_, w, _)| !w.is_empty()) {
            let values: Vec<Vec<[f32; 3]>> = (0..nv)
                .map(|vi| {
                    texels
                        .iter()
                        .map(|&t| {
                            let m = |l: usize| model.map_or([0.0; 3], |m| m(l, vi, t));
                            let own = m(*li);
                            let others: Vec<(f64, [f32; 3])> =
                                w.iter().map(|&(l, w)| (w / cos(l), m(l))).collect();
                            std::array::from_fn(|c| {
                                let f: f64 = w
                                    .iter()
                                    .zip(&others)
                                    .map(|(&(l, _), (k, m))| {
                                        k * (self.image(l, vi)[t][c] - m[c]) as f64
                                    })
                                    .sum();
                                ((f * cos(*li)) as f32 + own[c]).max(0.0)
                            })
                        })
                        .collect()
                })
                .collect();
            for (vi, v) in values.into_iter().enumerate() {
                let img = &mut self.images[li * nv + vi];
                for (&t, v) in texels.iter().zip(v) {
                    img[t] = v;
                }
            }
            filled += texels.len();
        }
        filled
    }

    /// Write every region as `l{LL}-v{VV}.exr` (half float, uncompressed:
    /// PIZ gains 11 % on these noisy values at ×6 the writing time) into `dir`, and
    /// the detail layer, if any: its shared factor as `detail.exr`, and with
    /// light components each light's whole factor as `detail-l{LL}.exr`
    /// (2S × 2S).
    pub fn write_exr(&self, dir: &Path) -> Result<(), BuildError> {
        let out = |e: String| BuildError::Output(e);
        std::fs::create_dir_all(dir).map_err(|e| out(format!("{}: {e}", dir.display())))?;
        let index = serde_json::to_vec_pretty(&self.index()).map_err(|e| out(e.to_string()))?;
        let path = dir.join(INDEX_FILE);
        crate::fsutil::write_atomic(&path, &index)
            .map_err(|e| out(format!("{}: {e}", path.display())))?;
        (0..self.images.len()).into_par_iter().try_for_each(|i| {
            let (li, vi) = (i / self.views.len(), i % self.views.len());
            let frame = crate::camera::Frame {
                width: self.size as u32,
                height: self.size as u32,
                rgb: (self.images[i].iter().enumerate())
                    .flat_map(|(t, px)| if self.is_unlit(li, t) { [0.0; 3] } else { *px })
                    .collect(),
            };
            let bytes = crate::exrio::encode_half_uncompressed(&frame).map_err(out)?;
            let path = dir.join(format!("l{:02}-v{:02}.exr", self.lights[li], self.views[vi]));
            crate::fsutil::write_atomic(&path, &bytes)
                .map_err(|e| out(format!("{}: {e}", path.display())))
        })?;
        let Some(d) = &self.detail else {
            return Ok(());
        };
        let f = 2 * self.size;
        let write = |name: String, rgb: Vec<f32>| -> Result<(), BuildError> {
            let frame = crate::camera::Frame { width: f as u32, height: f as u32, rgb };
            let bytes = crate::exrio::encode_half_uncompressed(&frame).map_err(out)?;
            let path = dir.join(name);
            crate::fsutil::write_atomic(&path, &bytes)
                .map_err(|e| out(format!("{}: {e}", path.display())))
        };
        write("detail.exr".into(), d.shared.iter().flatten().copied().collect())?;
        if d.bases.is_empty() {
            return Ok(());
        }
        (0..self.lights.len()).into_par_iter().try_for_each(|li| {
            let rgb = (0..f * f).flat_map(|t| d.factor(li, |img| img[t])).collect();
            write(format!("detail-l{:02}.exr", self.lights[li]), rgb)
        })
    }
}

/// The file beside the region images that says what they are
/// (docs/calibration-format.md, "Region images").
pub const INDEX_FILE: &str = "regions.json";

/// What [`INDEX_FILE`] holds.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RegionIndex {
    /// `"scanner-regions"`.
    pub format: String,
    /// 3 (2 before session 81: no `face.sides_shown`; 1 before session
    /// 80: no `face.measured_on`, `sigma_mm`, `slope_sigma`).
    pub version: u32,
    /// S, px.
    pub size: usize,
    /// Side of the sample, mm.
    pub sample_mm: f64,
    /// Where the images were read the sample's face to lie: its centre's
    /// height above the holder's plane, mm, and its rise along u and v.
    pub face: FaceRecord,
    /// The lit mirrors, with their light directions (in the face's frame).
    pub lights: Vec<DirectionRecord>,
    /// The seen mirrors, with their view directions and virtual cameras
    /// (in the face's frame, mm from its centre).
    pub views: Vec<DirectionRecord>,
}

/// [`RegionIndex::face`].
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FaceRecord {
    pub height_mm: f64,
    pub slope: [f64; 2],
    /// The face measured on the sample's frames (`false`: given).
    pub measured: bool,
    /// What the measurement read (version 2): `"chroma"`, `"outline"`,
    /// `"chroma and outline"`, or `"none"` / `"disagreeing"` (no face
    /// measured: read in the holder's plane).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub measured_on: Option<String>,
    /// The measured height's and slopes' standard uncertainties, where
    /// measured (version 2).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slope_sigma: Option<[f64; 2]>,
    /// The images were read as a thick sample's, its sides showing beyond
    /// the edges facing each view: no pixel across those read, the face
    /// not measured on the outline (version 3; absent: `false`).
    #[serde(default)]
    pub sides_shown: bool,
}

/// A mirror of [`RegionIndex`] and its direction.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DirectionRecord {
    pub mirror: usize,
    pub direction: [f64; 3],
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub viewer_mm: Option<[f64; 3]>,
}

impl RegionSet {
    /// The face these images were read on, as the material's provenance
    /// records it.
    pub fn face_record(&self) -> scanner_shading::format::FaceRecord {
        scanner_shading::format::FaceRecord {
            height_mm: self.face.height_mm,
            slope: self.face.slope,
            measured_on: self.height_fit.map_or("given", |f| f.cue.name()).into(),
            sides_shown: self.sides == SampleSides::Shown,
        }
    }

    /// What [`INDEX_FILE`] holds for these images.
    pub fn index(&self) -> RegionIndex {
        RegionIndex {
            format: "scanner-regions".into(),
            version: 3,
            size: self.size,
            sample_mm: self.sample_mm,
            face: FaceRecord {
                height_mm: self.face.height_mm,
                slope: self.face.slope,
                measured: self.height_fit.is_some(),
                measured_on: self.height_fit.map(|f| f.cue.name().into()),
                sigma_mm: self.height_fit.map(|f| f.sigma_mm).filter(|s| s.is_finite()),
                slope_sigma: self
                    .height_fit
                    .map(|f| f.slope_sigma)
                    .filter(|s| s.iter().all(|v| v.is_finite())),
                sides_shown: self.sides == SampleSides::Shown,
            },
            lights: self
                .lights
                .iter()
                .zip(&self.light_dirs)
                .map(|(&mirror, &direction)| DirectionRecord { mirror, direction, viewer_mm: None })
                .collect(),
            views: self
                .views
                .iter()
                .zip(self.view_dirs.iter().zip(&self.viewers_mm))
                .map(|(&mirror, (&direction, &c))| DirectionRecord {
                    mirror,
                    direction,
                    viewer_mm: Some(c),
                })
                .collect(),
        }
    }
}

/// The smallest power of two no view is undersampled at: ≥ the longest
/// side of any view's quadrilateral in the frame, px.
pub fn default_size(cal: &Calibration) -> usize {
    let longest = cal
        .views
        .iter()
        .map(|v| {
            let p = v.homography.corners();
            (0..4)
                .map(|k| {
                    let (a, b) = (p[k], p[(k + 1) % 4]);
                    (a[0] - b[0]).hypot(a[1] - b[1])
                })
                .fold(0.0, f64::max)
        })
        .fold(0.0, f64::max);
    (longest.ceil() as usize).max(8).next_power_of_two()
}

/// A texel model's value for (light index, view index, texel) that
/// [`RegionSet::fill_unlit`] reads the lights' residuals against.
pub type UnlitModel<'a> = dyn Fn(usize, usize, usize) -> [f32; 3] + Sync + 'a;

/// How [`extract_regions`] extracts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RegionOptions {
    /// Side of the region images (default: [`default_size`]).
    pub size: Option<usize>,
    /// Give every light's images the detail all views hold together
    /// ([`super::superres`]); `None`: each view's own resampling alone.
    pub sharpen: Option<SharpenOptions>,
    /// Which frame pixels at the sample's edge the region images read.
    pub edge: EdgePixels,
    /// Where the sample's face lies: measured on its frames, or given.
    pub height: SampleHeight,
    /// Whether the sample's sides show beyond its edges.
    pub sides: SampleSides,
}

/// Whether a view sees the sample's sides beyond the edges that face it
/// (docs/calibration-format.md, "Region images").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SampleSides {
    /// Seen on the sample's frames ([`super::outline::Beyond::seen`], at
    /// the face measured or given): [`Self::Shown`] where the band beyond
    /// the edges facing the views is brighter than beyond the others,
    /// [`Self::Hidden`] otherwise.
    #[default]
    Auto,
    /// Beyond the sample's outline lies the holder in every view: a sample
    /// sunk flush into it, or thin.
    Hidden,
    /// A thick sample standing on the holder: beyond the edges facing a
    /// view lie its own sides, as bright as they are lit. No frame pixel
    /// across those edges is read (each view reads its straddling pixels
    /// across the edges facing away alone, and the holder's radiance
    /// beyond them), and the face is not measured on the outline (its
    /// sides move the facing edges out; the chroma still measures it).
    Shown,
}

impl Default for RegionOptions {
    fn default() -> Self {
        RegionOptions {
            size: None,
            sharpen: Some(SharpenOptions::default()),
            edge: EdgePixels::default(),
            height: SampleHeight::default(),
            sides: SampleSides::default(),
        }
    }
}

/// Which frame pixels at the sample's edge the region images read
/// (docs/calibration-format.md, "Region images").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum EdgePixels {
    /// Also the pixels that straddle the calibrated edge, each for its
    /// part on the sample, beside the holder's radiance measured next to
    /// it ([`super::calibrate::ViewSampler::region_filter_straddling`]).
    /// In every view: it needs the edge to ≈ 0.01 px, and a view placed
    /// less precisely reads a textured sample's outermost texels off
    /// (leather at 1024²: −0.64 dB; docs/benchmarks.md, sessions 72, 73
    /// and 76).
    Straddling,
    /// Only the pixels whose squares lie [`super::calibrate::CLEAN_MARGIN_PX`]
    /// inside the calibrated edge ([`super::calibrate::ViewSampler::region_filter`]).
    Inside,
    /// [`Self::Straddling`] in the views whose edges the calibration
    /// places precisely ([`super::calibrate::ViewCalibration::edge_precise`]),
    /// [`Self::Inside`] in the others.
    #[default]
    Precise,
}

impl EdgePixels {
    /// Whether the region images read `view`'s straddling pixels.
    pub fn straddles(self, view: &super::calibrate::ViewCalibration) -> bool {
        match self {
            EdgePixels::Straddling => true,
            EdgePixels::Inside => false,
            EdgePixels::Precise => view.edge_precise(),
        }
    }
}

/// What a view's region image takes from one texel under every light.
struct TexelView {
    /// The frame pixels the texel is resampled from.
    filter: BicubicFilter,
    /// The colour calibration's view response there.
    response: [f64; 3],
    /// The filter's noise gain.
    noise_gain: f64,
}

/// What the region images of side `size` need, bytes, about: every view's
/// per-texel filters and the images themselves (f32 RGB per light, view and
/// texel), × 1.4 for the working copies beside them, and each thread's
/// frame of `frame_px` pixels (f32 RGB). Measured on the demo's 4096²
/// scan: 1.15 GB peak at the default 128² (this gives 1.00 GB), 2.90 GB
/// at 256² (2.78 GB).
fn region_memory(
    size: usize,
    lights: usize,
    views: usize,
    frame_px: usize,
    threads: usize,
) -> u128 {
    let per_texel = (views * std::mem::size_of::<TexelView>() + lights * views * 12) as u128;
    (size * size) as u128 * per_texel * 14 / 10 + (threads * frame_px * 12) as u128
}

/// Refuse a region size whose images cannot fit in `available` bytes, rather
/// than be killed when memory runs out.
fn check_memory(need: u128, size: usize, available: Option<u64>) -> Result<(), BuildError> {
    super::memory::check_memory(
        need,
        available,
        &format!("region images of {size}² px need"),
        "choose a smaller --size",
    )
}

/// Extract the calibrated region images of `scan`.
pub fn extract_regions(
    g: &ScannerGeometry,
    cal: &Calibration,
    scan: &ScanFrames,
    opts: &RegionOptions,
    progress: &dyn BuildProgress,
) -> Result<RegionSet, BuildError> {
    cal.check_geometry(g)?;
    if scan.manifest.settings.geometry_sha256 != cal.geometry_sha256 {
        return Err(BuildError::Input(format!(
            "{}: taken with another geometry than the calibration's",
            scan.dir.display()
        )));
    }
    let size = opts.size.unwrap_or_else(|| default_size(cal));
    if !(4..=4096).contains(&size) {
        return Err(BuildError::Input(format!("region size {size} outside 4…4096")));
    }
    // The camera's defects the calibration found are replaced too.
    let mut with_defects;
    let scan = if cal.defects.is_empty() {
        scan
    } else {
        with_defects = scan.clone();
        with_defects.add_defects(&cal.defects);
        &with_defects
    };
    let lights = scan.lights();
    let light_index: Vec<usize> = lights
        .iter()
        .map(|&l| {
            cal.lights.iter().position(|c| c.light == l).ok_or_else(|| {
                BuildError::Input(format!("mirror {l} is lit in the scan but not calibrated"))
            })
        })
        .collect::<Result<_, _>>()?;
    let frame_px = g.camera.width as usize * g.camera.height as usize;
    let need =
        region_memory(size, lights.len(), cal.views.len(), frame_px, rayon::current_num_threads());
    check_memory(need, size, super::memory::available_memory())?;
    let albedo = cal.colour.white_albedo;
    let (face, height_fit, beyond, seen) = match opts.height {
        // A given face's sides are looked for at it, when asked to.
        SampleHeight::Given(face) => {
            let beyond = match opts.sides {
                SampleSides::Auto => sides_beyond(g, cal, scan, face, progress)?,
                SampleSides::Hidden | SampleSides::Shown => None,
            };
            (face, None, beyond, beyond.is_some_and(|b| b.seen()))
        }
        SampleHeight::Measure => {
            let fit = measure_height(g, cal, scan, opts.sides, progress)?;
            (fit.applied_face(), Some(fit), fit.beyond, fit.sides_seen())
        }
    };
    let sides = match opts.sides {
        SampleSides::Auto if seen => SampleSides::Shown,
        SampleSides::Auto => SampleSides::Hidden,
        given => given,
    };
    progress.stage("sample frames", lights.len());
    // A thick sample's sides show beyond the edges facing each view: no
    // pixel across those edges is read.
    let samplers: Vec<_> = cal
        .views
        .iter()
        .map(|v| {
            let s = v.sampler_at_face(g, face);
            match sides {
                SampleSides::Auto | SampleSides::Hidden => s,
                SampleSides::Shown => {
                    s.with_closed_sides(std::array::from_fn(|e| side_reach(v, face, e) > 0.0))
                }
            }
        })
        .collect();
    let windows: Vec<_> = samplers.iter().map(|s| s.homography().window(4.0)).collect();
    // Per view and texel, what is the same under every light: the pixels
    // it is resampled from (the filter), the colour calibration's view
    // response and the filter's noise gain; and which texels each view's
    // pixels see.
    let frame = [g.camera.width as usize, g.camera.height as usize];
    // A measured height moves the edges by its uncertainty times the
    // view's parallax: a view reads its straddling pixels only while that
    // stays within the edges' EDGE_PRECISE_PX.
    let height_sigma = height_fit.map_or(0.0, |f| f.corner_sigma_mm(g.sample.size_mm));
    let straddles: Vec<bool> = cal
        .views
        .iter()
        .map(|v| opts.edge.straddles(v) && height_sigma * view_parallax(g, v) <= EDGE_PRECISE_PX)
        .collect();
    let texel_view: Vec<Vec<TexelView>> = samplers
        .par_iter()
        .enumerate()
        .map(|(vi, s)| {
            (0..size * size)
                .map(|i| {
                    let uv = cell_uv(i, size);
                    let filter = if straddles[vi] {
                        s.region_filter_straddling(frame, uv)
                    } else {
                        s.region_filter(frame, uv)
                    };
                    TexelView {
                        filter,
                        response: cal.colour.view(vi, uv),
                        noise_gain: filter.noise_gain(),
                    }
                })
                .collect()
        })
        .collect();
    // Per view, the pixels beside the sample whose median is the holder's
    // radiance the straddling pixels are read without.
    let bands: Vec<Vec<u32>> = samplers
        .par_iter()
        .zip(&straddles)
        .map(|(s, &on)| if on { s.holder_band(frame) } else { Vec::new() })
        .collect();
    let sharpen = opts
        .sharpen
        .as_ref()
        .map(|o| (o, Footprints::new(&samplers, &straddles, frame, size, o.points)));
    // Where each beam's field can be divided by: not in its soft edge.
    let beams = cal.colour.beam_map();
    let per_light: Vec<(Vec<Image>, Option<Image>, Vec<bool>)> = lights
        .par_iter()
        .zip(&light_index)
        .map(|(&l, &ci)| {
            let f = scan.read_within(l, &windows)?;
            if frame_dims(&f) != frame {
                return Err(BuildError::Input(format!(
                    "{}: mirror {l}'s frame is {}×{} px, the calibration's camera {}×{}",
                    scan.dir.display(),
                    f.width,
                    f.height,
                    frame[0],
                    frame[1]
                )));
            }
            let cos_i = cal.lights[ci].direction[2];
            let scale = albedo / std::f64::consts::PI * cos_i.max(0.0);
            // f · cos θi per frame unit at uv in view `vi`, or `None` where
            // this beam leaves the sample unlit or its field cannot be read
            // (nothing to divide by).
            // (Tested once for a beam that can be read everywhere, not at
            // every pixel the detail reads.)
            let everywhere = beams.readable_everywhere(ci);
            let lit = |uv: [f64; 2], b: f64| {
                b >= super::calibrate::UNLIT_FIELD && (everywhere || beams.readable(ci, uv))
            };
            let unit = |uv: [f64; 2], b: f64, a: [f64; 3]| -> Option<[f64; 3]> {
                if !lit(uv, b) {
                    return None;
                }
                let w = a.map(|a| a * b);
                Some(w.map(|w| if w > 0.0 { scale / w } else { 0.0 }))
            };
            let per_unit = |vi: usize, uv: [f64; 2]| {
                unit(uv, cal.colour.light(ci, uv), cal.colour.view(vi, uv))
            };
            // The same at the texels, from the views' and this light's
            // values there.
            let texel_light: Vec<f64> =
                (0..size * size).map(|i| cal.colour.light(ci, cell_uv(i, size))).collect();
            let unlit: Vec<bool> =
                (0..size * size).map(|t| !lit(cell_uv(t, size), texel_light[t])).collect();
            let texel_unit = |vi: usize, t: usize| {
                unit(cell_uv(t, size), texel_light[t], texel_view[vi][t].response)
            };
            let scaled = |s: [f64; 3], c: [f64; 3]| -> [f32; 3] {
                std::array::from_fn(|k| (s[k] * c[k]) as f32)
            };
            let value = |vi: usize, uv: [f64; 2], s: [f64; 3]| -> Option<[f32; 3]> {
                Some(scaled(s, per_unit(vi, uv)?))
            };
            // The sensor's noise in view `vi`'s region image at texel `t`
            // where it holds `v`: the merged frame value's variance (the
            // exposures that measured it), through the filter and the
            // normalisation.
            let black = scan.manifest.settings.black_level_codes;
            let bracket = hdr::BracketNoise::new(&scan.exposures_us(l)?, &g.sensor, black);
            let noise = |vi: usize, t: usize, v: [f32; 3]| -> [f32; 3] {
                let Some(c) = texel_unit(vi, t) else { return [0.0; 3] };
                let filter = texel_view[vi][t].noise_gain;
                std::array::from_fn(|k| {
                    if c[k] <= 0.0 {
                        return 0.0;
                    }
                    let var = bracket.rate_variance(v[k] as f64 / c[k]);
                    var.map_or(0.0, |var| (var * c[k] * c[k] * filter) as f32)
                })
            };
            let mut images: Vec<Vec<[f32; 3]>> = texel_view
                .iter()
                .enumerate()
                .map(|(vi, view)| {
                    let holder = super::calibrate::holder_radiance(&f, &bands[vi]);
                    let mut img = vec![[0.0f32; 3]; size * size];
                    for (i, (px, texel)) in img.iter_mut().zip(view).enumerate() {
                        if let Some(c) = texel_unit(vi, i) {
                            *px = scaled(texel.filter.apply_beside(&f, holder), c);
                        }
                    }
                    img
                })
                .collect();
            let detail = sharpen.as_ref().and_then(|(o, views)| {
                sharpen_light(views, &value, &noise, &f, o, &mut images, &unlit)
            });
            // Sharpened images are denoised as they are sharpened (where
            // the views' image took out a share of the noise, only what
            // is left), the others here.
            if detail.is_none() {
                let near_unlit = near_unlit(&unlit, size);
                let denoiser = Denoiser::new(size);
                for (vi, img) in images.iter_mut().enumerate() {
                    denoiser.denoise(img, &near_unlit, |t, v| noise(vi, t, v));
                }
            }
            progress.step();
            let unlit = if unlit.contains(&true) { unlit } else { Vec::new() };
            Ok((images, detail, unlit))
        })
        .collect::<Result<_, BuildError>>()?;
    let mut per_light_images = Vec::with_capacity(per_light.len());
    let mut details = Vec::with_capacity(per_light.len());
    let mut unlit = Vec::with_capacity(per_light.len());
    for (images, detail, dark) in per_light {
        per_light_images.push(images);
        details.push(detail);
        unlit.push(dark);
    }
    if opts.sharpen.is_some() {
        progress.stage("detail layer", 1);
    }
    let detail = detail_layer(&details, 2 * size);
    let mut set = RegionSet {
        detail,
        size,
        light_dirs: light_index
            .iter()
            .map(|&ci| face.to_face(DVec3::from(cal.lights[ci].direction)).to_array())
            .collect(),
        view_dirs: cal
            .views
            .iter()
            .map(|v| face.to_face(DVec3::from(v.direction)).to_array())
            .collect(),
        viewers_mm: cal
            .views
            .iter()
            .map(|v| face.to_face_point(DVec3::from(v.viewer_mm(g))).to_array())
            .collect(),
        sample_mm: g.sample.size_mm,
        face,
        height_fit,
        beyond,
        sides,
        views: cal.views.iter().map(|v| v.view).collect(),
        lights,
        images: per_light_images.into_iter().flatten().collect(),
        unlit,
    };
    set.fill_unlit(None);
    Ok(set)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A region size the machine cannot hold is refused before anything is
    /// allocated; the default size of the default scanner passes.
    #[test]
    fn a_region_size_beyond_memory_is_refused_up_front() {
        let gb = 1_000_000_000u64;
        // The default scanner's 40 × 40 pairs, 4096² frames, two threads:
        // ≈ 1 GB at 128² (1.15 GB measured), ≈ 2.7 GB at 256² (2.90 GB).
        let px = 4096 * 4096;
        let at = |s: usize| region_memory(s, 40, 40, px, 2) as f64 / gb as f64;
        assert!((0.9..1.1).contains(&at(128)), "{}", at(128));
        assert!((2.5..2.9).contains(&at(256)), "{}", at(256));
        let need = region_memory(4096, 40, 40, px, 2);
        assert!(check_memory(region_memory(128, 40, 40, px, 2), 128, Some(4 * gb)).is_ok());
        assert!(check_memory(need, 4096, None).is_ok());
        let err = check_memory(need, 4096, Some(24 * gb)).unwrap_err().to_string();
        assert!(err.contains("region images of 4096² px need ≈ 609"), "{err}");
        assert!(err.contains("24.0 GB of memory is available: choose a smaller --size"), "{err}");
        assert!(crate::build::memory::available_memory().is_none_or(|a| a > 0));
    }

    /// Texels a beam left unlit are filled from the lights that lit them:
    /// exactly on a Lambertian sample (f the same for every light), exactly
    /// on a glossy one given its texel model (only the model's residual,
    /// here 0, is read between the lights), and left 0 where no light lit
    /// the texel; `scanner regions` writes them as 0.
    #[test]
    fn unlit_texels_are_filled_from_the_lights_that_lit_them() {
        use scanner_shading::texel::{TexelParams, reflected};
        let (n, s) = (12usize, 4usize);
        let dirs: Vec<[f64; 3]> = (0..n)
            .map(|k| {
                let (th, ph) = ((12.0 + 18.0 * (k % 3) as f64).to_radians(), 0.55 * k as f64);
                [th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()]
            })
            .collect();
        let f32v = |d: [f64; 3]| d.map(|x| x as f32);
        let glossy = TexelParams {
            diffuse: [0.2, 0.15, 0.1],
            specular: [0.6, 0.6, 0.6],
            alpha: 0.2,
            normal: [0.0, 0.0, 1.0],
        };
        let set_of = |value: &dyn Fn(usize, usize, usize) -> [f32; 3]| RegionSet {
            size: s,
            lights: (0..n).collect(),
            views: (0..n).collect(),
            light_dirs: dirs.clone(),
            view_dirs: dirs.clone(),
            viewers_mm: dirs.iter().map(|d| d.map(|x| x * 1e9)).collect(),
            sample_mm: 25.4,
            images: (0..n * n)
                .map(|p| (0..s * s).map(|t| value(p / n, p % n, t)).collect())
                .collect(),
            detail: None,
            face: SampleFace::FLUSH,
            height_fit: None,
            beyond: None,
            sides: SampleSides::Hidden,
            unlit: Vec::new(),
        };
        let lambert =
            |l: usize, _: usize, _: usize| [0.3 / std::f32::consts::PI * dirs[l][2] as f32; 3];
        let gloss = |l: usize, v: usize, _: usize| {
            let wo = f32v(dirs[v]);
            reflected(&glossy, f32v(dirs[l]), wo)
        };
        // Light 4 leaves texels 0–5 unlit, light 7 texels 3–9; texel 15
        // no light lit.
        let unlit: Vec<Vec<bool>> = (0..n)
            .map(|l| match l {
                4 => (0..s * s).map(|t| t <= 5 || t == 15).collect(),
                7 => (0..s * s).map(|t| (3..=9).contains(&t) || t == 15).collect(),
                _ => (0..s * s).map(|t| t == 15).collect(),
            })
            .collect();
        let blank = |set: &mut RegionSet| {
            for (li, dark) in unlit.iter().enumerate() {
                for img in &mut set.images[li * n..(li + 1) * n] {
                    for (px, _) in img.iter_mut().zip(dark).filter(|(_, d)| **d) {
                        *px = [0.0; 3];
                    }
                }
            }
            set.unlit = unlit.clone();
        };
        let worst = |set: &RegionSet, truth: &dyn Fn(usize, usize, usize) -> [f32; 3]| {
            let mut worst = 0.0f32;
            for li in 0..n {
                for vi in 0..n {
                    for t in 0..15 {
                        for (a, b) in set.image(li, vi)[t].iter().zip(truth(li, vi, t)) {
                            worst = worst.max((a / b - 1.0).abs());
                        }
                    }
                    assert_eq!(set.image(li, vi)[15], [0.0; 3], "nothing lit texel 15");
                }
            }
            worst
        };
        let mut matte = set_of(&lambert);
        blank(&mut matte);
        assert_eq!(matte.fill_unlit(None), 6 + 7);
        assert!(worst(&matte, &lambert) < 1e-5, "{}", worst(&matte, &lambert));
        let mut shiny = set_of(&gloss);
        blank(&mut shiny);
        let without = shiny.clone();
        let model = |l: usize, v: usize, _: usize| gloss(l, v, 0);
        shiny.fill_unlit(Some(&model));
        assert!(worst(&shiny, &gloss) < 1e-4, "{}", worst(&shiny, &gloss));
        // Without the model the highlight is read between the lights: off.
        let mut plain = without;
        plain.fill_unlit(None);
        assert!(worst(&plain, &gloss) > 0.05, "{}", worst(&plain, &gloss));
        // The files hold 0 where nothing was measured.
        let dir = tempfile::tempdir().unwrap();
        matte.write_exr(dir.path()).unwrap();
        let img = crate::exrio::read_rgb(&dir.path().join("l04-v02.exr")).unwrap();
        for (t, (px, dark)) in img.rgb.chunks(3).zip(&unlit[4]).enumerate() {
            assert_eq!(px.iter().all(|&c| c == 0.0), *dark, "texel {t}");
        }
    }

    /// `scanner regions`' files: every image, the shared layer, and with
    /// light components each light's whole layer, named by its mirror.
    #[test]
    fn each_light_s_layer_is_written_beside_the_images() {
        let (s, f) = (4usize, 8usize);
        let dirs = vec![[0.0, 0.0, 1.0], [0.5, 0.0, 0.866], [0.0, 0.5, 0.866]];
        let set = RegionSet {
            size: s,
            lights: vec![3, 7, 12],
            views: vec![0, 1, 2],
            light_dirs: dirs.clone(),
            view_dirs: dirs.clone(),
            viewers_mm: dirs.iter().map(|d| d.map(|x| x * 1200.0)).collect(),
            sample_mm: 25.4,
            images: vec![vec![[0.25; 3]; s * s]; 9],
            detail: Some(DetailLayer {
                shared: (0..f * f).map(|t| [1.0 + 0.01 * t as f32; 3]).collect(),
                bases: vec![(0..f * f).map(|t| [(t % 3) as f32 * 0.5 - 0.5; 3]).collect()],
                coefficients: vec![vec![-0.5], vec![0.0], vec![0.75]],
            }),
            face: SampleFace::FLUSH,
            height_fit: None,
            beyond: None,
            unlit: Vec::new(),
            sides: SampleSides::Hidden,
        };
        let dir = tempfile::tempdir().unwrap();
        set.write_exr(dir.path()).unwrap();
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 9 + 1 + 3 + 1);
        // The index: what the images are, their directions and the face.
        let index: RegionIndex =
            serde_json::from_slice(&std::fs::read(dir.path().join(INDEX_FILE)).unwrap()).unwrap();
        assert_eq!(index, set.index());
        assert_eq!((index.size, index.views[2].mirror, index.lights[1].mirror), (4, 2, 7));
        assert_eq!(index.lights[1].direction, dirs[1]);
        assert_eq!(index.views[1].viewer_mm, Some(set.viewers_mm[1]));
        assert!(!index.face.measured && index.face.height_mm == 0.0);
        let d = set.detail.as_ref().unwrap();
        for (li, m) in set.lights.iter().enumerate() {
            let got =
                crate::exrio::read_rgb(&dir.path().join(format!("detail-l{m:02}.exr"))).unwrap();
            assert_eq!((got.width, got.height), (f as u32, f as u32));
            for t in [0, 5, 37, 63] {
                let want = d.factor(li, |img| img[t]);
                for (k, w) in want.iter().enumerate() {
                    let v = got.rgb[3 * t + k];
                    assert!((v - w).abs() < 2e-3 * w, "light {m}, texel {t}: {v} against {w}");
                }
            }
        }
        // Light 7's coefficient is 0: its layer is the shared one.
        let shared = crate::exrio::read_rgb(&dir.path().join("detail.exr")).unwrap();
        let l7 = crate::exrio::read_rgb(&dir.path().join("detail-l07.exr")).unwrap();
        assert_eq!(shared.rgb, l7.rgb);
    }
}
