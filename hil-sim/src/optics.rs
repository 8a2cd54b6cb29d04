//! The optical simulator: the frame the camera records for given axis
//! positions, from the **as-built** geometry and a ground-truth [`Sample`].
//!
//! Per pixel (2 × 2 sub-pixel rays): camera ray → the first planar mirror it
//! meets (or nothing) → the sample plane → the sample's reflected radiance
//! for that view direction and every beam path that reaches the point: the
//! beam from the fold mirror, reflected by whichever mirror it actually
//! meets, its irradiance from the beam's profile at that ray. Mirror
//! reflectance applies on both bounces. The sensor integrates
//! radiance × exposure × light duty × vignetting into electrons, adds shot
//! and read noise and quantises to its ADC; frames are linear float RGB,
//! ADC code / max code.
//!
//! Noise is seeded by the simulator seed and the exposure's physical
//! parameters, so the same exposure gives the same frame (also when a scan
//! retakes it after a fault), and rows are rendered in parallel with rayon
//! with per-row generators, so the thread count does not change a bit.

use glam::DVec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use rayon::prelude::*;
use std::sync::{Arc, Mutex, OnceLock};

use crate::geometry::{
    AsBuilt, AxisValues, Beam, Facet, SampleFace, ScannerGeometry, Tolerances, sample_to_world,
    world_to_sample,
};
use crate::materials::Sample;

/// Sub-pixel rays per axis (a scan frame's pixel: [`BASE_RAYS`]).
pub const SUPERSAMPLE: usize = 2;
/// Sub-pixel rays per axis over a pixel of a scan frame that an edge
/// crosses (the sample's outline, a printed target's squares, a weave's
/// gaps): its [`BASE_RAYS`] disagree by more than
/// [`REFINE_SPREAD`], or it differs from a neighbour as much (the edge, or
/// a sliver of the sample, may lie between its rays).
pub const EDGE_SUPERSAMPLE: usize = 4;
/// The spread of a pixel's sub-pixel radiances, or of its and a
/// neighbour's (summed over the channels; the least against the most),
/// beyond which it is sampled again with [`EDGE_SUPERSAMPLE`]² rays.
pub const REFINE_SPREAD: f64 = 0.2;
/// The [`SUPERSAMPLE`]² rays a scan frame first traces over a pixel, as
/// points (column, row) of the [`EDGE_SUPERSAMPLE`]² lattice: a rotated
/// grid, one point in each of the lattice's rows and columns (four
/// abscissae and four ordinates where an edge may fall between rays), so
/// that a pixel sampled again traces only the lattice's other points.
pub const BASE_RAYS: [[usize; 2]; SUPERSAMPLE * SUPERSAMPLE] = [[1, 0], [3, 1], [0, 2], [2, 3]];

/// The lattice (per axis) that finds a sliver of the sample between a
/// pixel's [`EDGE_SUPERSAMPLE`]² rays: shares down to ≈ 1/64 of the pixel.
const SLIVER_LATTICE: usize = 32;

/// A pixel the sample's outline crosses ([`OpticalSim::outline`]).
struct Outline {
    /// The share of its square on the sample.
    share: f64,
    /// Per lattice ray (row by row), whether it lands on the face.
    on_face: Vec<bool>,
    /// Where none does: up to four image points within it that do; where
    /// all do and the rest of the pixel may be lit (a light holder, the
    /// sample's sides), up to four that do not.
    sliver: Vec<(f64, f64)>,
}

impl Outline {
    /// How many of its lattice rays land on the face.
    fn on(&self) -> usize {
        self.on_face.iter().filter(|&&b| b).count()
    }
}

/// The radiances of a pixel's [`BASE_RAYS`].
type BaseRadiances = [[f64; 3]; SUPERSAMPLE * SUPERSAMPLE];

/// One exposure of the camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Exposure {
    /// Where the axes physically are.
    pub axes: AxisValues,
    /// Exposure time, s.
    pub exposure_s: f64,
    /// Light duty in [0, 1] (0 = dark frame).
    pub light: f64,
}

impl Exposure {
    /// Exposure time × light duty (s): what the frame's electrons scale with.
    fn dose(&self) -> f64 {
        self.exposure_s * self.light.clamp(0.0, 1.0)
    }
}

/// A linear float RGB image, row-major, interleaved.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Width, px.
    pub width: u32,
    /// Height, px.
    pub height: u32,
    /// `width × height × 3` values, ADC code / max code.
    pub rgb: Vec<f32>,
}

impl Frame {
    /// Pixel (x, y).
    pub fn pixel(&self, x: u32, y: u32) -> [f32; 3] {
        let i = 3 * (y as usize * self.width as usize + x as usize);
        [self.rgb[i], self.rgb[i + 1], self.rgb[i + 2]]
    }

    /// Mean of (R+G+B)/3 over the listed pixels.
    pub fn mean_luminance(&self, pixels: &[(u32, u32)]) -> f64 {
        if pixels.is_empty() {
            return 0.0;
        }
        let s: f64 = pixels
            .iter()
            .map(|&(x, y)| self.pixel(x, y).iter().map(|&v| v as f64).sum::<f64>())
            .sum();
        s / (3.0 * pixels.len() as f64)
    }
}

/// What a camera ray sees of the sample (ground truth, for tests).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewHit {
    /// The mirror the ray reflects in.
    pub mirror: usize,
    /// Sample uv.
    pub uv: [f64; 2],
    /// Point on the sample plane (world, mm).
    pub point: DVec3,
    /// Direction from the sample towards the viewer, in the frame of the
    /// sample's face (sample-local when it lies in the holder's plane).
    pub view: DVec3,
    /// Transmission to the camera (mirror reflectance).
    pub transmission: f64,
    /// What the ray meets: the face, a side or the holder.
    pub surface: Surface,
}

/// The surface a camera ray meets ([`ViewHit::surface`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Surface {
    /// The sample's face.
    Face,
    /// Its side below edge k (0: v = 0, 1: u = 1, 2: v = 1, 3: u = 0),
    /// [`ViewHit::view`] then in the side's frame
    /// ([`OpticalSim::with_sample_thickness`]).
    Side(usize),
    /// The holder around the sample, when it reflects
    /// ([`OpticalSim::with_holder_albedo`]): [`ViewHit::uv`] then the
    /// sample's uv extended to the point (outside [0, 1]²) and
    /// [`ViewHit::view`] sample-local.
    Holder,
}

/// One beam path onto the sample: via `mirror`, light arriving from `light`
/// (unit vector in the frame of the sample's face, sample-local when it
/// lies in the holder's plane) with irradiance `irradiance` perpendicular
/// to it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LightPath {
    /// The mirror the beam reflects in.
    pub mirror: usize,
    /// Direction towards the light, sample-local.
    pub light: DVec3,
    /// Irradiance perpendicular to the beam at the point.
    pub irradiance: f64,
}

/// A mirror the beam meets: its index and the reflected beam.
#[derive(Debug, Clone, Copy)]
struct LitMirror {
    mirror: usize,
    dir: DVec3,
}

/// Noise-free electrons of the last lit exposure per unit of
/// exposure × duty, by the axis positions they were rendered at.
type ElectronCache = Arc<Mutex<Option<(AxisValues, Arc<ElectronRows>)>>>;

/// Expected electrons per camera row (`None`: a row no light reaches).
type ElectronRows = Vec<Option<Vec<[f32; 3]>>>;

/// Per camera row, the runs of pixels [x0, x1), ascending and disjoint, that
/// a frame renders.
type PixelSpans = Vec<Vec<[u32; 2]>>;

/// The optical simulator of one as-built scanner holding one sample.
#[derive(Debug, Clone)]
pub struct OpticalSim {
    /// An HDR bracket exposes the same axis positions several times: the
    /// scene (everything but exposure, duty and noise) is rendered once.
    cache: ElectronCache,
    geometry: ScannerGeometry,
    sample: Sample,
    seed: u64,
    /// Per mirror: image-space bounding box (x0, y0, x1, y1), clipped.
    boxes: Vec<Option<[u32; 4]>>,
    /// The pixels of the boxes where some sub-pixel ray sees the sample
    /// through a mirror: the only ones light can reach. Most of a box sees
    /// the mirror but not the sample. They depend on the geometry alone, so
    /// every frame shares them; found by the first lit frame.
    sees_sample: Arc<OnceLock<PixelSpans>>,
    /// The mirrors, ready for tracing.
    facets: Vec<Facet>,
    /// The sensor's defective pixels (none unless asked for).
    defects: Arc<[crate::defects::PixelDefect]>,
    /// A black level left in the frames, ADC codes (0 unless asked for).
    black_level_codes: u32,
    /// Where the sample's face lies ([`OpticalSim::with_sample_face`]):
    /// in the holder's plane, where the targets lie, unless asked.
    face: SampleFace,
    /// How deep the sample's sides show below its face, mm
    /// ([`OpticalSim::with_sample_thickness`]; 0: no sides).
    thickness_mm: f64,
    /// The holder's diffuse albedo ([`OpticalSim::with_holder_albedo`];
    /// 0: perfectly black).
    holder_albedo: f64,
}

impl OpticalSim {
    /// A simulator rendering `as_built` with `sample` in the holder.
    pub fn new(as_built: ScannerGeometry, sample: Sample, seed: u64) -> OpticalSim {
        let cam = &as_built.camera;
        let boxes = as_built
            .mirrors
            .iter()
            .map(|m| {
                // Points along the edges, not the corners alone: a lens'
                // distortion bends the edges.
                let c = m.corners();
                let pts: Option<Vec<[f64; 2]>> = (0..4)
                    .flat_map(|i| (0..8).map(move |j| (i, j as f64 / 8.0)))
                    .map(|(i, t)| cam.project(c[i] + (c[(i + 1) % 4] - c[i]) * t))
                    .collect();
                let pts = pts?;
                let x0 = pts.iter().map(|p| p[0]).fold(f64::INFINITY, f64::min).floor() - 1.0;
                let y0 = pts.iter().map(|p| p[1]).fold(f64::INFINITY, f64::min).floor() - 1.0;
                let x1 = pts.iter().map(|p| p[0]).fold(f64::NEG_INFINITY, f64::max).ceil() + 1.0;
                let y1 = pts.iter().map(|p| p[1]).fold(f64::NEG_INFINITY, f64::max).ceil() + 1.0;
                let (w, h) = (cam.width as f64, cam.height as f64);
                (x1 > 0.0 && y1 > 0.0 && x0 < w && y0 < h).then(|| {
                    [x0.max(0.0) as u32, y0.max(0.0) as u32, x1.min(w) as u32, y1.min(h) as u32]
                })
            })
            .collect();
        let facets = as_built.mirrors.iter().map(|m| m.facet()).collect();
        OpticalSim {
            geometry: as_built,
            sample,
            seed,
            boxes,
            sees_sample: Default::default(),
            facets,
            cache: Default::default(),
            defects: Arc::new([]),
            black_level_codes: 0,
            face: SampleFace::FLUSH,
            thickness_mm: 0.0,
            holder_albedo: 0.0,
        }
    }

    /// The same scanner whose sensor has `defects` (frames only: the
    /// noise-free [`OpticalSim::expected`] stays the light's truth).
    pub fn with_defects(self, defects: Vec<crate::defects::PixelDefect>) -> OpticalSim {
        OpticalSim { defects: defects.into(), ..self }
    }

    /// The same scanner whose camera leaves a black level of `codes` in its
    /// frames (a capture program that does not subtract it; frames only).
    /// The ADC still clips at its top code.
    pub fn with_black_level(self, codes: u32) -> OpticalSim {
        OpticalSim { black_level_codes: codes, ..self }
    }

    /// The same scanner with the sample's face `height_mm` proud of the
    /// holder's plane, towards the mirrors (a sample thicker than the
    /// targets, or one that does not lie flat against the holder; negative:
    /// recessed). The targets' scans lie in the plane (0); the sample's
    /// outline, every view of it and the light it gets move with its face.
    pub fn with_sample_height(self, height_mm: f64) -> OpticalSim {
        self.with_sample_face(SampleFace::at_height(height_mm))
    }

    /// The same scanner with the sample's face at `face` (its centre's
    /// height above the holder's plane and its tilt; the targets' scans lie
    /// in the plane). The sample's outline, every view of it and the light
    /// it gets move with its face, and its texels see the light and the
    /// views in the face's own frame (`scanner_geometry::face`).
    pub fn with_sample_face(self, face: SampleFace) -> OpticalSim {
        OpticalSim { face, sees_sample: Default::default(), cache: Default::default(), ..self }
    }

    /// Where the sample's face lies ([`OpticalSim::with_sample_face`]).
    pub fn sample_face(&self) -> SampleFace {
        self.face
    }

    /// The same scanner with a sample `thickness_mm` thick: a slab whose
    /// four sides, perpendicular to its face, reach that far below it (a
    /// cut piece of leather, a board; 0: a face without sides, as a sample
    /// sunk flush into the holder). A view sees the sides below the edges
    /// that face it, between the face's outline and the dark holder, down
    /// to the holder's plane: a sample thicker than its face is proud sits
    /// recessed in the holder, which hides the rest of its sides (one
    /// standing on the holder is as thick as its face is proud). Each side
    /// shows the material at the edge above it (its diffuse and specular
    /// albedo and roughness, the texel's normal the side's own).
    pub fn with_sample_thickness(self, thickness_mm: f64) -> OpticalSim {
        OpticalSim {
            thickness_mm: thickness_mm.max(0.0),
            sees_sample: Default::default(),
            cache: Default::default(),
            ..self
        }
    }

    /// How deep the sample's sides reach below its face, mm
    /// ([`OpticalSim::with_sample_thickness`]).
    pub fn sample_thickness(&self) -> f64 {
        self.thickness_mm
    }

    /// The same scanner whose holder (the disc of
    /// `sample.holder_radius_mm` in the holder's plane around the sample)
    /// reflects diffusely with `albedo` in every channel (0, the default:
    /// perfectly black; a real holder's flock or paint is 0.01–0.05, a
    /// light one ≈ 0.8). The views see it around the sample's outline,
    /// lit where the beam reaches; it neither shadows nor is shadowed by a
    /// sample standing proud of it.
    pub fn with_holder_albedo(self, albedo: f64) -> OpticalSim {
        OpticalSim {
            holder_albedo: albedo.clamp(0.0, 1.0),
            sees_sample: Default::default(),
            cache: Default::default(),
            ..self
        }
    }

    /// The holder's albedo ([`OpticalSim::with_holder_albedo`]).
    pub fn holder_albedo(&self) -> f64 {
        self.holder_albedo
    }

    /// The same scanner with a camera lens of radial distortion `k`
    /// (`scanner_geometry::radial_distort`; the default is a pinhole).
    pub fn with_lens_distortion(self, k: [f64; 2]) -> OpticalSim {
        let mut g = self.geometry.clone();
        g.camera.distortion = k;
        let (defects, black_level_codes) = (self.defects.clone(), self.black_level_codes);
        let (face, thickness_mm, holder_albedo) =
            (self.face, self.thickness_mm, self.holder_albedo);
        OpticalSim {
            defects,
            black_level_codes,
            face,
            thickness_mm,
            holder_albedo,
            ..OpticalSim::new(g, self.sample, self.seed)
        }
    }

    /// The simulator of a scanner built to `nominal` with the default
    /// manufacturing errors drawn from `seed` (which also seeds the noise).
    pub fn as_built(nominal: &ScannerGeometry, sample: Sample, seed: u64) -> OpticalSim {
        OpticalSim::new(nominal.perturbed(seed, &Tolerances::default()), sample, seed)
    }

    /// The as-built geometry (ground truth).
    pub fn geometry(&self) -> &ScannerGeometry {
        &self.geometry
    }

    /// The sample (ground truth).
    pub fn sample(&self) -> &Sample {
        &self.sample
    }

    /// The same scanner with another sample in the holder.
    pub fn with_sample(&self, sample: Sample) -> OpticalSim {
        OpticalSim { sample, cache: Default::default(), ..self.clone() }
    }

    fn lit_mirrors(&self, beam: &Beam) -> Vec<LitMirror> {
        let reach = self.geometry.source.beam_radius_mm;
        self.geometry
            .mirrors
            .iter()
            .enumerate()
            .filter(|(_, m)| {
                // Front side, and the beam tube can overlap the square.
                beam.dir.dot(DVec3::from(m.normal)) < 0.0
                    && beam.distance(m.center())
                        < reach + m.size_mm * std::f64::consts::FRAC_1_SQRT_2
            })
            .map(|(l, m)| LitMirror { mirror: l, dir: m.reflect_dir(beam.dir) })
            .collect()
    }

    /// Mirrors whose reflected beam reaches some part of the sample with the
    /// axes at `axes` (ground truth).
    pub fn mirrors_lighting_sample(&self, axes: AxisValues) -> Vec<usize> {
        let size = self.geometry.sample.size_mm;
        let n = 24;
        let mut out: Vec<usize> = Vec::new();
        let beam = self.geometry.beam(axes);
        let lit = self.lit_mirrors(&beam);
        for i in 0..=n {
            for j in 0..=n {
                let uv = [i as f64 / n as f64, j as f64 / n as f64];
                let p = sample_to_world(self.face.point(size, uv));
                for path in self.light_paths_with(&beam, &lit, p) {
                    if path.irradiance > 0.0 && !out.contains(&path.mirror) {
                        out.push(path.mirror);
                    }
                }
            }
        }
        out.sort_unstable();
        out
    }

    /// Every beam path reaching sample point `p` (world, on the sample plane)
    /// with the axes at `axes` (ground truth).
    pub fn light_paths(&self, axes: AxisValues, p: DVec3) -> Vec<LightPath> {
        let beam = self.geometry.beam(axes);
        let lit = self.lit_mirrors(&beam);
        self.light_paths_with(&beam, &lit, p).collect()
    }

    /// The beam paths reaching `p`, lazily: a camera ray's radiance asks for
    /// them once per ray, and most rays meet one.
    fn light_paths_with<'a>(
        &'a self,
        beam: &'a Beam,
        lit: &'a [LitMirror],
        p: DVec3,
    ) -> impl Iterator<Item = LightPath> + 'a {
        lit.iter().filter_map(move |lm| {
            let m = &self.facets[lm.mirror];
            // Light arrives travelling along lm.dir; trace back to the mirror.
            if lm.dir.z <= 0.0 {
                return None; // reflected downwards: never reaches the sample's face
            }
            let (_, q) = m.intersect(p, -lm.dir)?;
            // Only mirrors the beam tube overlaps can shadow this one's light.
            let back = -beam.dir;
            if (q - beam.origin).dot(beam.dir) <= 0.0 {
                return None;
            }
            let shadowed = lit.iter().any(|other| {
                other.mirror != lm.mirror
                    && self.facets[other.mirror].intersect(q + back * 1e-6, back).is_some()
            });
            if shadowed {
                return None;
            }
            let e = self.geometry.source.irradiance
                * self.geometry.mirrors[lm.mirror].reflectance
                * self.geometry.source.profile(beam.distance(q));
            (e > 0.0).then(|| LightPath {
                mirror: lm.mirror,
                light: self.face.to_face(world_to_sample(-lm.dir)),
                irradiance: e,
            })
        })
    }

    /// What the camera ray through image point (x, y) sees of the sample.
    pub fn trace(&self, x: f64, y: f64) -> Option<ViewHit> {
        let cam = &self.geometry.camera;
        let origin = DVec3::from(cam.position_mm);
        let dir = cam.ray(x, y);
        self.trace_ray(origin, dir, None)
    }

    fn trace_ray(
        &self,
        origin: DVec3,
        dir: DVec3,
        candidates: Option<&[usize]>,
    ) -> Option<ViewHit> {
        let g = &self.geometry;
        // The holder (z = 0 plane around the sample) blocks rays crossing it.
        if dir.z.abs() > 1e-12 {
            let t0 = -origin.z / dir.z;
            if t0 > 0.0 {
                let c = origin + dir * t0;
                if c.x * c.x + c.y * c.y < g.sample.holder_radius_mm * g.sample.holder_radius_mm {
                    return None;
                }
            }
        }
        let (l, p) = match candidates {
            Some(c) => self.nearest_mirror(origin, dir, c.iter().copied()),
            None => self.nearest_mirror(origin, dir, 0..g.mirrors.len()),
        }?;
        let r = self.facets[l].reflect_dir(dir);
        let transmission = g.mirrors[l].reflectance;
        let on_face = self.onto_sample_plane_along(p, r).and_then(|s| {
            let uv = self.face.uv(g.sample.size_mm, world_to_sample(s));
            uv.iter().all(|t| (0.0..=1.0).contains(t)).then_some((s, uv))
        });
        let view = self.face.to_face(world_to_sample(-r));
        if let Some((point, uv)) = on_face {
            return Some(ViewHit {
                mirror: l,
                uv,
                point,
                view,
                transmission,
                surface: Surface::Face,
            });
        }
        if let Some((side, point, uv)) = self.onto_side(world_to_sample(p), -view) {
            return Some(ViewHit {
                mirror: l,
                uv,
                point: sample_to_world(point),
                view: side_frame(side, view),
                transmission,
                surface: Surface::Side(side),
            });
        }
        let (point, uv) = self.onto_holder(p, r)?;
        let view = world_to_sample(-r);
        Some(ViewHit { mirror: l, uv, point, view, transmission, surface: Surface::Holder })
    }

    /// Where the ray from world point `p` along `dir` meets the holder
    /// around the sample (world), and the sample's uv extended there;
    /// `None` for a black holder, or where the ray passes it or meets the
    /// sample's square.
    fn onto_holder(&self, p: DVec3, dir: DVec3) -> Option<(DVec3, [f64; 2])> {
        if self.holder_albedo <= 0.0 || dir.z.abs() < 1e-12 {
            return None;
        }
        let t = -p.z / dir.z;
        if t <= 0.0 {
            return None;
        }
        let c = p + dir * t;
        let m = &self.geometry.sample;
        let local = world_to_sample(c);
        let half = 0.5 * m.size_mm;
        let beyond = local.x.abs() > half || local.y.abs() > half;
        (beyond && c.x * c.x + c.y * c.y < m.holder_radius_mm * m.holder_radius_mm)
            .then(|| (c, [local.x / m.size_mm + 0.5, local.y / m.size_mm + 0.5]))
    }

    /// Where the ray from sample-local point `origin` along `dir` (in the
    /// face's frame) that misses the face meets the sample's sides (the
    /// slab [−½, ½]² × [−thickness, 0] in the face's frame, sizes by the
    /// sample's): the side, the point (sample-local) and the uv of the edge
    /// above it. `None` without sides, when the ray passes them, or where
    /// it meets them beyond the holder's plane (hidden by the holder).
    fn onto_side(&self, origin: DVec3, dir: DVec3) -> Option<(usize, DVec3, [f64; 2])> {
        if self.thickness_mm <= 0.0 {
            return None;
        }
        let size = self.geometry.sample.size_mm;
        let half = 0.5 * size;
        let o = self.face.to_face_point(origin);
        let mut best: Option<(f64, usize, DVec3)> = None;
        for (side, n) in SIDE_NORMALS.iter().enumerate() {
            let n = DVec3::new(n[0], n[1], 0.0);
            let (from, across) = (o.dot(n), dir.dot(n));
            // From outside the side's plane, towards it.
            if from <= half || across >= 0.0 {
                continue;
            }
            let t = (half - from) / across;
            let q = o + dir * t;
            let along = q.x * n.y.abs() + q.y * n.x.abs();
            if (-self.thickness_mm..=0.0).contains(&q.z)
                && along.abs() <= half
                && best.is_none_or(|b| t < b.0)
            {
                best = Some((t, side, q));
            }
        }
        let (_, side, q) = best?;
        let [eu, ev, en] = self.face.axes();
        let point = DVec3::new(0.0, 0.0, self.face.height_mm) + eu * q.x + ev * q.y + en * q.z;
        // Beyond the holder's plane the holder hides it: the ray crossed the
        // plane outside the sample's square first (a sample thicker than its
        // face is proud sits recessed in the holder).
        if point.z < 0.0 {
            return None;
        }
        // The edge above: uv along it, exactly on it across.
        let [a, b] = SIDE_NORMALS[side];
        let on = |t: f64, n: f64| if n != 0.0 { 0.5 + 0.5 * n } else { t.clamp(0.0, 1.0) };
        let uv = [on(q.x / size + 0.5, a), on(q.y / size + 0.5, b)];
        Some((side, point, uv))
    }

    /// The nearest of the mirrors `candidates` the ray (origin, unit dir)
    /// meets: the mirror and the point (the first of equally near ones).
    fn nearest_mirror(
        &self,
        origin: DVec3,
        dir: DVec3,
        candidates: impl Iterator<Item = usize>,
    ) -> Option<(usize, DVec3)> {
        let mut best: Option<(f64, usize, DVec3)> = None;
        for l in candidates {
            if let Some((t, p)) = self.facets[l].intersect(origin, dir)
                && best.is_none_or(|b| t < b.0)
            {
                best = Some((t, l, p));
            }
        }
        best.map(|(_, l, p)| (l, p))
    }

    /// The ray along `dir` reflected at point `p` of mirror `l`: its new
    /// direction and where it meets the plane of the sample's face (world);
    /// `None` if it leaves away from the plane.
    fn onto_sample_plane(&self, l: usize, p: DVec3, dir: DVec3) -> Option<(DVec3, DVec3)> {
        let r = self.facets[l].reflect_dir(dir);
        Some((r, self.onto_sample_plane_along(p, r)?))
    }

    /// Where the ray reflected at world point `p` along `r` meets the plane
    /// of the sample's face (world); `None` if it leaves away from it.
    fn onto_sample_plane_along(&self, p: DVec3, r: DVec3) -> Option<DVec3> {
        if r.z <= 1e-12 {
            return None;
        }
        let s = self.face.intersect(world_to_sample(p), world_to_sample(r))?;
        Some(sample_to_world(s))
    }

    /// Noise-free scene radiance (RGB) reaching the camera at image point (x, y).
    fn radiance_at(&self, scene: &Scene<'_>, x: f64, y: f64, candidates: &[usize]) -> [f64; 3] {
        let dir = scene.rays.ray(x, y);
        let Some(hit) = self.trace_ray(scene.origin, dir, Some(candidates)) else {
            return [0.0; 3];
        };
        let mut out = [0.0; 3];
        // The texel once, when some path lights the point (on a side, the
        // material at the edge above it, the side's normal its own).
        let mut texel = None;
        for path in self.light_paths_with(&scene.beam, scene.lit, hit.point) {
            let r = match hit.surface {
                Surface::Holder => {
                    // Lambertian, in the holder's (sample-local) frame.
                    let cos = self.face.from_face(path.light).z.max(0.0);
                    [self.holder_albedo / std::f64::consts::PI * cos; 3]
                }
                Surface::Face => texel
                    .get_or_insert_with(|| self.sample.texel(hit.uv))
                    .reflected(path.light, hit.view),
                Surface::Side(k) => texel
                    .get_or_insert_with(|| crate::materials::Texel {
                        normal: DVec3::Z,
                        ..self.sample.texel(hit.uv)
                    })
                    .reflected(side_frame(k, path.light), hit.view),
            };
            for k in 0..3 {
                out[k] += r[k] * path.irradiance * hit.transmission;
            }
        }
        out
    }

    /// Expected electrons per channel for every pixel (noise-free), or
    /// `None` rows that see nothing (all dark).
    fn electrons(&self, exposure: &Exposure) -> ElectronRows {
        if exposure.dose() <= 0.0 {
            return vec![None; self.geometry.camera.height as usize];
        }
        let spans = self.sees_sample.get_or_init(|| self.sample_spans());
        self.electrons_over(exposure, spans)
    }

    /// The mirrors whose boxes cross camera row `y`, each with its box's x
    /// range.
    fn row_mirrors(&self, y: usize) -> Vec<(usize, [u32; 2])> {
        let inside = |b: &[u32; 4]| (b[1] as usize..b[3] as usize).contains(&y);
        self.boxes
            .iter()
            .enumerate()
            .filter_map(|(l, b)| b.filter(inside).map(|b| (l, [b[0], b[2]])))
            .collect()
    }

    /// The mirrors of `row` (from [`Self::row_mirrors`]) whose boxes hold
    /// pixel `x`, into `here`: the candidates of its rays.
    fn mirrors_at(row: &[(usize, [u32; 2])], x: usize, here: &mut Vec<usize>) {
        here.clear();
        here.extend(
            row.iter()
                .filter(|(_, r)| (r[0] as usize..r[1] as usize).contains(&x))
                .map(|&(l, _)| l),
        );
    }

    /// The image points of pixel (x, y)'s sub-pixel rays.
    fn subpixels(x: usize, y: usize) -> impl Iterator<Item = (f64, f64)> {
        Self::subpixels_n(x, y, SUPERSAMPLE)
    }

    /// The image points of an `n` × `n` lattice of rays over pixel (x, y).
    fn subpixels_n(x: usize, y: usize, n: usize) -> impl Iterator<Item = (f64, f64)> {
        (0..n).flat_map(move |sy| (0..n).map(move |sx| Self::lattice_point(x, y, n, [sx, sy])))
    }

    /// The image point of ray (column, row) `at` of an `n` × `n` lattice
    /// over pixel (x, y).
    fn lattice_point(x: usize, y: usize, n: usize, at: [usize; 2]) -> (f64, f64) {
        let k = n as f64;
        (x as f64 + (at[0] as f64 + 0.5) / k, y as f64 + (at[1] as f64 + 0.5) / k)
    }

    /// The image points of pixel (x, y)'s [`BASE_RAYS`].
    fn base_points(x: usize, y: usize) -> impl Iterator<Item = (f64, f64)> {
        BASE_RAYS.iter().map(move |&at| Self::lattice_point(x, y, EDGE_SUPERSAMPLE, at))
    }

    /// [`OpticalSim::sees_sample`]: every box pixel where one of
    /// [`Self::radiance_at`]'s rays reaches the sample, and the pixels
    /// next to those (a sliver of the sample's edge may lie between a
    /// pixel's rays: [`Self::electrons_over`] samples such a pixel again).
    fn sample_spans(&self) -> PixelSpans {
        let cam = &self.geometry.camera;
        let (w, h) = (cam.width as usize, cam.height as usize);
        let origin = DVec3::from(cam.position_mm);
        let rays = CameraRays::new(cam);
        let hits: Vec<Vec<bool>> = (0..h)
            .into_par_iter()
            .map(|y| {
                let mirrors = self.row_mirrors(y);
                let mut here = Vec::with_capacity(mirrors.len());
                (0..w)
                    .map(|x| {
                        Self::mirrors_at(&mirrors, x, &mut here);
                        !here.is_empty()
                            && Self::base_points(x, y).any(|(fx, fy)| {
                                self.trace_ray(origin, rays.ray(fx, fy), Some(&here)).is_some()
                            })
                    })
                    .collect()
            })
            .collect();
        (0..h)
            .into_par_iter()
            .map(|y| {
                let near = &hits[y.saturating_sub(1)..=(y + 1).min(h - 1)];
                let mut spans: Vec<[u32; 2]> = Vec::new();
                for x in 0..w {
                    let (x0, x1) = (x.saturating_sub(1), (x + 1).min(w - 1));
                    if !near.iter().any(|row| row[x0..=x1].contains(&true)) {
                        continue;
                    }
                    let x = x as u32;
                    match spans.last_mut() {
                        Some(span) if span[1] == x => span[1] = x + 1,
                        _ => spans.push([x, x + 1]),
                    }
                }
                spans
            })
            .collect()
    }

    /// `f` of the scene `exposure` lights (`None` if no light reaches a
    /// mirror).
    fn with_scene<R>(&self, exposure: &Exposure, f: impl FnOnce(&Scene<'_>) -> R) -> Option<R> {
        let g = &self.geometry;
        let beam = g.beam(exposure.axes);
        let lit = if exposure.light > 0.0 { self.lit_mirrors(&beam) } else { Vec::new() };
        let scale = exposure.dose() * g.sensor.sensitivity_e;
        if lit.is_empty() || scale <= 0.0 {
            return None;
        }
        let rays = CameraRays::new(&g.camera);
        let origin = DVec3::from(g.camera.position_mm);
        Some(f(&Scene { rays: &rays, origin, beam, lit: &lit, scale }))
    }

    /// Expected electrons of pixel (x, y) whose rays' radiances sum to
    /// `sum` over `rays` rays.
    fn to_electrons(
        &self,
        scene: &Scene<'_>,
        x: usize,
        y: usize,
        sum: [f64; 3],
        rays: usize,
    ) -> [f32; 3] {
        let r = scene.rays;
        let cos = r.ray(x as f64 + 0.5, y as f64 + 0.5).dot(r.forward);
        let vig = cos.powf(self.geometry.sensor.vignetting_exponent);
        let k = scene.scale * vig / rays as f64;
        sum.map(|v| (v * k) as f32)
    }

    /// The radiances of pixel (x, y)'s [`BASE_RAYS`] (`here`: the mirrors
    /// they may meet).
    fn base_radiances(
        &self,
        scene: &Scene<'_>,
        x: usize,
        y: usize,
        here: &[usize],
    ) -> BaseRadiances {
        BASE_RAYS.map(|at| {
            let (fx, fy) = Self::lattice_point(x, y, EDGE_SUPERSAMPLE, at);
            self.radiance_at(scene, fx, fy, here)
        })
    }

    /// Expected electrons of pixel (x, y) from its base rays' radiances
    /// `base`, and whether they disagree by more than [`REFINE_SPREAD`].
    fn base_electrons(
        &self,
        scene: &Scene<'_>,
        x: usize,
        y: usize,
        base: &BaseRadiances,
    ) -> ([f32; 3], bool) {
        let mut acc = [0.0; 3];
        let (mut least, mut most) = (f64::INFINITY, 0.0f64);
        for r in base {
            for k in 0..3 {
                acc[k] += r[k];
            }
            let sum = r[0] + r[1] + r[2];
            (least, most) = (least.min(sum), most.max(sum));
        }
        (self.to_electrons(scene, x, y, acc, base.len()), least < (1.0 - REFINE_SPREAD) * most)
    }

    /// Expected electrons of pixel (x, y), from the mean radiance of an
    /// `n` × `n` lattice of rays over it (`here`: the mirrors they may
    /// meet); `base`, when `n` is [`EDGE_SUPERSAMPLE`], the radiances of
    /// its [`BASE_RAYS`] already traced.
    fn lattice_electrons(
        &self,
        scene: &Scene<'_>,
        x: usize,
        y: usize,
        n: usize,
        here: &[usize],
        base: Option<&BaseRadiances>,
    ) -> [f32; 3] {
        let base = base.filter(|_| n == EDGE_SUPERSAMPLE);
        let mut radiances = Vec::with_capacity(n * n);
        for sy in 0..n {
            for sx in 0..n {
                let known = base
                    .and_then(|b| BASE_RAYS.iter().position(|&at| at == [sx, sy]).map(|i| b[i]));
                radiances.push(known.unwrap_or_else(|| {
                    let (fx, fy) = Self::lattice_point(x, y, n, [sx, sy]);
                    self.radiance_at(scene, fx, fy, here)
                }));
            }
        }
        let rays = n * n;
        // On the outline, the face's rays weigh for its exact share of the
        // pixel and the others (its sides, or the dark holder) for the rest.
        let outline = self.outline(scene, x, y, n, here);
        let (mut face, mut off) = ([0.0; 3], [0.0; 3]);
        for (i, r) in radiances.iter().enumerate() {
            let on = outline.as_ref().is_none_or(|o| o.on_face[i]);
            let sum = if on { &mut face } else { &mut off };
            for k in 0..3 {
                sum[k] += r[k];
            }
        }
        let on = outline.as_ref().map_or(rays, Outline::on);
        let off_weight = |share: f64| {
            if on < rays { (1.0 - share) * rays as f64 / (rays - on) as f64 } else { 0.0 }
        };
        let mut acc: [f64; 3] = std::array::from_fn(|k| face[k] + off[k]);
        let radiance_sum = |points: &[(f64, f64)]| {
            let mut r = [0.0; 3];
            for &(fx, fy) in points {
                let q = self.radiance_at(scene, fx, fy, here);
                for k in 0..3 {
                    r[k] += q[k];
                }
            }
            r
        };
        match outline {
            // Every ray on the face and the rest of the pixel lit: the face's
            // rays for its share, the rest's mean radiance at the points of
            // a finer lattice that land on it for the others.
            Some(Outline { share, ref sliver, .. }) if on == rays && !sliver.is_empty() => {
                let r = radiance_sum(sliver);
                let g = (1.0 - share) * rays as f64 / sliver.len() as f64;
                acc = std::array::from_fn(|k| face[k] * share + r[k] * g);
            }
            Some(Outline { share, .. }) if on > 0 => {
                let f = share * rays as f64 / on as f64;
                let g = off_weight(share);
                acc = std::array::from_fn(|k| face[k] * f + off[k] * g);
            }
            // A sliver of the sample between the rays: its mean radiance
            // at the points of a finer lattice that land on it.
            Some(Outline { share, ref sliver, .. }) if !sliver.is_empty() => {
                let r = radiance_sum(sliver);
                let f = share * rays as f64 / sliver.len() as f64;
                let g = off_weight(share);
                acc = std::array::from_fn(|k| r[k] * f + off[k] * g);
            }
            Some(_) | None => {}
        }
        self.to_electrons(scene, x, y, acc, rays)
    }

    /// For pixel (x, y) on the sample's outline: the exact share of its
    /// square on the sample (its footprint through the mirror on the
    /// sample's plane, clipped to the sample), how many of its `n` × `n`
    /// lattice rays land on the sample, and where none does, up to four
    /// points of a finer lattice that do. A sensor integrates over the
    /// pixel, so where the outline crosses it is not rounded to the
    /// lattice (which, along an outline parallel to the pixel grid, holds
    /// only quarters). `None` elsewhere: wholly on or off the sample, or
    /// seen through two mirrors.
    fn outline(
        &self,
        scene: &Scene<'_>,
        x: usize,
        y: usize,
        n: usize,
        here: &[usize],
    ) -> Option<Outline> {
        // The mirror the pixel's centre sees; each point of the pixel
        // must see it too.
        let centre = scene.rays.ray(x as f64 + 0.5, y as f64 + 0.5);
        let (l, _) = self.nearest_mirror(scene.origin, centre, here.iter().copied())?;
        let on_plane = |fx: f64, fy: f64| -> Option<[f64; 2]> {
            let dir = scene.rays.ray(fx, fy);
            let (m, p) = self.nearest_mirror(scene.origin, dir, here.iter().copied())?;
            if m != l {
                return None;
            }
            let (_, s) = self.onto_sample_plane(l, p, dir)?;
            Some([s.x, s.y])
        };
        let (xf, yf) = (x as f64, y as f64);
        let footprint = [
            on_plane(xf, yf)?,
            on_plane(xf + 1.0, yf)?,
            on_plane(xf + 1.0, yf + 1.0)?,
            on_plane(xf, yf + 1.0)?,
        ];
        let half = self.geometry.sample.size_mm / 2.0;
        let share = square_share(&footprint, half)?;
        if share <= 0.0 || share >= 1.0 {
            return None;
        }
        let on_sample = |(fx, fy): (f64, f64)| {
            on_plane(fx, fy).map(|p| p[0].abs() <= half && p[1].abs() <= half)
        };
        let mut on_face = Vec::with_capacity(n * n);
        for sy in 0..n {
            for sx in 0..n {
                on_face.push(on_sample(Self::lattice_point(x, y, n, [sx, sy]))?);
            }
        }
        let mut sliver = Vec::new();
        // The side no lattice ray lands on, when it matters: the face, or
        // the rest of the pixel if anything there may be lit.
        let unsampled = if !on_face.contains(&true) {
            Some(true)
        } else if !on_face.contains(&false) && (self.holder_albedo > 0.0 || self.thickness_mm > 0.0)
        {
            Some(false)
        } else {
            None
        };
        if let Some(want) = unsampled {
            let fine = SLIVER_LATTICE;
            let points: Vec<(f64, f64)> = (0..fine * fine)
                .map(|k| Self::lattice_point(x, y, fine, [k % fine, k / fine]))
                .filter(|&q| on_sample(q) == Some(want))
                .collect();
            let step = points.len().div_ceil(4).max(1);
            sliver.extend(points.iter().step_by(step));
        }
        Some(Outline { share, on_face, sliver })
    }

    /// [`Self::electrons`] over the pixels of `spans` (the others dark).
    fn electrons_over(&self, exposure: &Exposure, spans: &PixelSpans) -> ElectronRows {
        self.with_scene(exposure, |scene| self.electrons_in(scene, spans))
            .unwrap_or_else(|| vec![None; spans.len()])
    }

    /// [`Self::electrons_over`] in a lit `scene`.
    fn electrons_in(&self, scene: &Scene<'_>, spans: &PixelSpans) -> ElectronRows {
        let w = self.geometry.camera.width as usize;
        // Every pixel by its BASE_RAYS, which of them disagree, and their
        // radiances for a pixel sampled again (per row, the pixels of
        // `spans` in order; zeros for one no mirror's box holds, whose
        // rays meet nothing).
        let based: Vec<_> = spans
            .par_iter()
            .enumerate()
            .map(|(y, spans)| {
                if spans.is_empty() {
                    return (None, Vec::new(), Vec::new());
                }
                let mirrors = self.row_mirrors(y);
                let mut row = vec![[0.0f32; 3]; w];
                let mut mixed = Vec::new();
                let mut known = Vec::new();
                let mut here: Vec<usize> = Vec::with_capacity(mirrors.len());
                for x in spans.iter().flat_map(|&[x0, x1]| x0 as usize..x1 as usize) {
                    Self::mirrors_at(&mirrors, x, &mut here);
                    if here.is_empty() {
                        known.push([[0.0; 3]; SUPERSAMPLE * SUPERSAMPLE]);
                        continue;
                    }
                    let base = self.base_radiances(scene, x, y, &here);
                    let (e, disagree) = self.base_electrons(scene, x, y, &base);
                    row[x] = e;
                    if disagree {
                        mixed.push(x as u32);
                    }
                    known.push(base);
                }
                (row.iter().any(|e| e.iter().any(|&v| v > 0.0)).then_some(row), mixed, known)
            })
            .collect();
        let (mut rows, mut mixed, mut known) = (Vec::new(), Vec::new(), Vec::new());
        for (row, m, k) in based {
            rows.push(row);
            mixed.push(m);
            known.push(k);
        }
        // An edge crosses a pixel whose rays disagree, or that differs from
        // a neighbour as much (an edge, or a sliver of the sample, may lie
        // between its rays): sampled again by EDGE_SUPERSAMPLE² rays, since
        // a sensor integrates over the pixel, and its rays are not to round
        // where the edge lies within it (its base rays among them).
        let h = rows.len();
        let sum = |y: usize, x: usize| -> f32 {
            rows[y].as_ref().map_or(0.0, |r: &Vec<[f32; 3]>| r[x].iter().sum())
        };
        let refined: Vec<Vec<(usize, [f32; 3])>> = spans
            .par_iter()
            .enumerate()
            .map(|(y, spans)| {
                let mirrors = self.row_mirrors(y);
                let mut here: Vec<usize> = Vec::with_capacity(mirrors.len());
                let mut out = Vec::new();
                let xs = spans.iter().flat_map(|&[x0, x1]| x0 as usize..x1 as usize);
                for (x, base) in xs.zip(&known[y]) {
                    let centre = sum(y, x);
                    let differs =
                        |n: f32| n.min(centre) < (1.0 - REFINE_SPREAD as f32) * n.max(centre);
                    // The eight neighbours: a sliver at a corner of the
                    // sample's outline may touch the others diagonally only.
                    let neighbour = |dx: isize, dy: isize| {
                        let (nx, ny) = (x as isize + dx, y as isize + dy);
                        (0..w as isize).contains(&nx)
                            && (0..h as isize).contains(&ny)
                            && differs(sum(ny as usize, nx as usize))
                    };
                    let edge = mixed[y].binary_search(&(x as u32)).is_ok()
                        || (-1..=1)
                            .any(|dy| (-1..=1).any(|dx| (dx, dy) != (0, 0) && neighbour(dx, dy)));
                    if !edge {
                        continue;
                    }
                    Self::mirrors_at(&mirrors, x, &mut here);
                    let e =
                        self.lattice_electrons(scene, x, y, EDGE_SUPERSAMPLE, &here, Some(base));
                    // A row no light reaches stays one (`None`).
                    if e != rows[y].as_ref().map_or([0.0; 3], |r| r[x]) {
                        out.push((x, e));
                    }
                }
                out
            })
            .collect();
        for (y, fixes) in refined.into_iter().enumerate() {
            if fixes.is_empty() {
                continue;
            }
            let row = rows[y].get_or_insert_with(|| vec![[0.0f32; 3]; w]);
            for (x, e) in fixes {
                row[x] = e;
            }
        }
        rows
    }

    /// [`Self::electrons`] as rows and a factor to scale them by, reusing
    /// the scene of the previous lit exposure at the same axis positions
    /// (electrons scale with exposure × duty).
    fn electrons_cached(&self, exposure: &Exposure) -> (Arc<ElectronRows>, f32) {
        let scale = exposure.dose();
        if scale <= 0.0 {
            return (Arc::new(self.electrons(exposure)), 1.0);
        }
        let mut cache = self.cache.lock().unwrap_or_else(|p| p.into_inner());
        if cache.as_ref().is_none_or(|(axes, _)| *axes != exposure.axes) {
            let unit = Exposure { axes: exposure.axes, exposure_s: 1.0, light: 1.0 };
            *cache = Some((exposure.axes, Arc::new(self.electrons(&unit))));
        }
        let (_, unit) = cache.as_ref().expect("filled above");
        (Arc::clone(unit), scale as f32)
    }

    /// Noise seed of an exposure: the simulator seed and the exposure's
    /// physical parameters.
    fn exposure_seed(&self, e: &Exposure) -> u64 {
        let mut h = self.seed ^ 0x000F_71C5;
        for v in [e.axes.disk_deg, e.axes.track_mm, e.axes.tilt_deg, e.exposure_s, e.light] {
            h = (h ^ v.to_bits()).wrapping_mul(0x9E37_79B9_7F4A_7C15).rotate_left(27);
        }
        h
    }

    /// **Ground truth (tests only):** the frame of `exposure` without noise,
    /// clipping or quantisation: expected electrons × ADC gain / max code.
    pub fn expected(&self, exposure: &Exposure) -> Frame {
        let s = &self.geometry.sensor;
        let k = (s.max_code() / s.full_well_e / s.max_code()) as f32;
        let w = self.geometry.camera.width as usize;
        let mut rgb = Vec::with_capacity(w * self.geometry.camera.height as usize * 3);
        let (rows, scale) = self.electrons_cached(exposure);
        let k = k * scale;
        for row in rows.iter() {
            match row {
                Some(r) => rgb.extend(r.iter().flat_map(|p| p.map(|v| v * k))),
                None => rgb.extend(std::iter::repeat_n(0.0, w * 3)),
            }
        }
        Frame { width: self.geometry.camera.width, height: self.geometry.camera.height, rgb }
    }

    /// Render the frame of `exposure`.
    pub fn render(&self, exposure: &Exposure) -> Frame {
        let (electrons, scale) = self.electrons_cached(exposure);
        let seed = self.exposure_seed(exposure);
        let mut frame = sensor_readout(
            &self.geometry.sensor,
            self.geometry.camera.width,
            &electrons,
            scale,
            seed,
        );
        crate::defects::apply(
            &mut frame,
            &self.defects,
            exposure.exposure_s,
            &self.geometry.sensor,
        );
        if self.black_level_codes > 0 {
            let max = self.geometry.sensor.max_code();
            let offset = self.black_level_codes as f64;
            for v in &mut frame.rgb {
                *v = (((*v as f64 * max).round() + offset).min(max) / max) as f32;
            }
        }
        frame
    }

    /// A photograph of `piece` by the pinhole `camera`, lit by a collimated
    /// beam along the camera's direction with the source's irradiance,
    /// through this scanner's sensor without vignetting: what a real
    /// camera set up for a direct image takes before it is rectified. The
    /// view direction varies over the piece (towards the camera's centre
    /// from every point); around the piece lies a matte background of
    /// albedo `background` (the black holder's [`HOLDER_ALBEDO`], or a
    /// light card a dark piece is laid on). A pixel on the piece's outline
    /// holds the piece and the background in the shares of its square each covers
    /// (its footprint on the piece's plane clipped to the piece), as a
    /// sensor integrating over the pixel would, and the piece's mean over
    /// its subpixels that land on it.
    pub fn photograph(
        &self,
        piece: &Sample,
        camera: &PhotoCamera,
        exposure_s: f64,
        background: f64,
    ) -> Frame {
        let light = camera.direction.normalize();
        let centre = camera.basis().0;
        let holder = background / std::f64::consts::PI * light.z.max(0.0);
        let mut keys = vec![light.x, light.y, light.z, camera.distance_mm, camera.focal_px];
        if camera.distortion != [0.0; 2] {
            keys.extend(camera.distortion);
        }
        if background != HOLDER_ALBEDO {
            keys.push(background);
        }
        let n = camera.side_px as usize;
        let half = 0.5 * piece.size_mm;
        let on_piece = |fx: f64, fy: f64| {
            let p = camera.on_plane([fx, fy])?;
            let uv = [p.x / piece.size_mm + 0.5, p.y / piece.size_mm + 0.5];
            uv.iter().all(|u| (0.0..1.0).contains(u)).then_some((p, uv))
        };
        self.square_image(n, exposure_s, 0x9407_0C4A, &keys, |x, y| {
            // Where the pixel's corners lie on the piece's plane, mm.
            let corner = |dx: usize, dy: usize| {
                camera.on_plane([(x + dx) as f64, (y + dy) as f64]).map(|p| [p.x, p.y])
            };
            let footprint = [corner(0, 0), corner(1, 0), corner(1, 1), corner(0, 1)];
            // The share of the pixel's footprint on the piece: a real
            // sensor integrates over the pixel, so the outline's position
            // within it is not rounded to the subpixels.
            let share = match footprint {
                [Some(a), Some(b), Some(c), Some(d)] => square_share(&[a, b, c, d], half),
                _ => None,
            };
            let (mut acc, mut on) = ([0.0; 3], 0usize);
            for (fx, fy) in Self::subpixels(x, y) {
                if let Some((p, uv)) = on_piece(fx, fy) {
                    let r = piece.reflected_radiance(uv, (centre - p).normalize(), light);
                    for k in 0..3 {
                        acc[k] += r[k];
                    }
                    on += 1;
                }
            }
            let all = SUPERSAMPLE * SUPERSAMPLE;
            let share = share.unwrap_or(on as f64 / all as f64);
            if share <= 0.0 {
                return [holder; 3];
            }
            if on == 0 {
                // A sliver of the piece between the subpixels: seen at the
                // pixel's centre, clamped onto the piece.
                let Some(p) = camera.on_plane([x as f64 + 0.5, y as f64 + 0.5]) else {
                    return [holder; 3];
                };
                let inside = |v: f64| (v / piece.size_mm + 0.5).clamp(0.0, 1.0 - 1e-9);
                let q = DVec3::new(
                    (inside(p.x) - 0.5) * piece.size_mm,
                    (inside(p.y) - 0.5) * piece.size_mm,
                    0.0,
                );
                acc = piece.reflected_radiance(
                    [inside(p.x), inside(p.y)],
                    (centre - q).normalize(),
                    light,
                );
                on = 1;
            }
            acc.map(|v| share * v / on as f64 + (1.0 - share) * holder)
        })
    }

    /// The Fig. 9 direct image: `piece` seen straight along `dir`
    /// (sample-local, towards the viewer) and lit from the same direction
    /// with the source's irradiance, rectified onto the piece's uv
    /// (`px_per_mm` pixels per mm), through this scanner's sensor without
    /// vignetting.
    pub fn direct_image(
        &self,
        piece: &Sample,
        dir: DVec3,
        px_per_mm: f64,
        exposure_s: f64,
    ) -> Frame {
        let n = (piece.size_mm * px_per_mm).round().max(1.0) as usize;
        let dir = dir.normalize();
        let keys = [dir.x, dir.y, dir.z, px_per_mm];
        self.square_image(n, exposure_s, 0xD1EC7, &keys, |x, y| {
            let mut acc = [0.0; 3];
            for (fx, fy) in Self::subpixels(x, y) {
                let r = piece.reflected_radiance([fx / n as f64, fy / n as f64], dir, dir);
                for k in 0..3 {
                    acc[k] += r[k];
                }
            }
            acc.map(|v| v / (SUPERSAMPLE * SUPERSAMPLE) as f64)
        })
    }

    /// An `n × n` image lit with the source's irradiance and exposed for
    /// `exposure_s` through this scanner's sensor without vignetting: each
    /// pixel (x, y) the mean radiance `pixel(x, y)` over it, its noise
    /// seeded by the simulator's seed, `salt` and `keys`.
    fn square_image(
        &self,
        n: usize,
        exposure_s: f64,
        salt: u64,
        keys: &[f64],
        pixel: impl Fn(usize, usize) -> [f64; 3] + Sync,
    ) -> Frame {
        let e0 = self.geometry.source.irradiance;
        let scale = exposure_s * self.geometry.sensor.sensitivity_e * e0;
        let electrons = (0..n)
            .into_par_iter()
            .map(|y| {
                let row = (0..n).map(|x| pixel(x, y).map(|v| (v * scale) as f32)).collect();
                Some(row)
            })
            .collect();
        let mut h = self.seed ^ salt;
        for &v in keys.iter().chain([&exposure_s]) {
            h = (h ^ v.to_bits()).wrapping_mul(0x9E37_79B9_7F4A_7C15).rotate_left(27);
        }
        sensor_readout(&self.geometry.sensor, n as u32, &electrons, 1.0, h)
    }
}

/// The share of the quadrilateral `quad` (mm on the piece's plane, in
/// order around it) that lies on the square [−`half`, `half`]²: its area
/// clipped to the square (Sutherland–Hodgman) over its own. `None` for a
/// degenerate quadrilateral.
fn square_share(quad: &[[f64; 2]; 4], half: f64) -> Option<f64> {
    use scanner_geometry::polygon::Polygon;
    let whole = Polygon::quad(*quad).area();
    if whole.is_nan() || whole <= 0.0 {
        return None;
    }
    if quad.iter().all(|p| p.iter().all(|v| v.abs() <= half)) {
        return Some(1.0);
    }
    let mut poly = Polygon::quad(*quad);
    // The square's four half-planes: coordinate `axis` times `sign` ≤ half.
    for (axis, sign) in [(0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0)] {
        poly = poly.clip(|p| half - sign * p[axis]);
        if poly.is_empty() {
            return Some(0.0);
        }
    }
    Some((poly.area() / whole).clamp(0.0, 1.0))
}

/// The outward normals of the sample's sides below its edges 0…3.
const SIDE_NORMALS: [[f64; 2]; 4] = scanner_geometry::face::EDGE_NORMALS;

/// Direction `d` (in the face's frame) in the frame of side `side`: z its
/// outward normal, x the face's normal, y = z × x.
fn side_frame(side: usize, d: DVec3) -> DVec3 {
    let [a, b] = SIDE_NORMALS[side];
    let z = DVec3::new(a, b, 0.0);
    let x = DVec3::Z;
    DVec3::new(d.dot(x), d.dot(z.cross(x)), d.dot(z))
}

/// The albedo of the matte black holder around a photographed piece.
pub const HOLDER_ALBEDO: f64 = 0.04;
/// The albedo of the matte white card a piece too dark for the black
/// holder is photographed on instead.
pub const LIGHT_BACKGROUND_ALBEDO: f64 = 0.8;

/// A pinhole camera photographing a piece from `distance_mm` along
/// `direction` (sample-local, from the piece's centre; the light comes from
/// it too), aimed at the piece's centre, its rows turned so that the
/// piece's u axis runs along them: a square sensor of `side_px` pixels and
/// a focal length of `focal_px` pixels, its lens with radial distortion
/// `distortion` about the photograph's centre.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PhotoCamera {
    /// Direction from the piece's centre to the camera (unit).
    pub direction: DVec3,
    /// Distance from the piece's centre, mm.
    pub distance_mm: f64,
    /// The sensor's side, px.
    pub side_px: u32,
    /// Focal length, px.
    pub focal_px: f64,
    /// The lens' radial distortion k1, k2 about the photograph's centre,
    /// the radius in half-diagonals of the photograph
    /// ([`scanner_geometry::radial_distort`]; 0: a pinhole).
    pub distortion: [f64; 2],
}

impl PhotoCamera {
    /// The camera at `distance_mm` along `direction` whose `side_px` frame
    /// a piece of `size_mm` seen face on would fill to `fill` (0…1).
    pub fn framing(
        direction: DVec3,
        distance_mm: f64,
        side_px: u32,
        size_mm: f64,
        fill: f64,
    ) -> PhotoCamera {
        let focal_px = fill * side_px as f64 * distance_mm / size_mm;
        PhotoCamera {
            direction: direction.normalize(),
            distance_mm,
            side_px,
            focal_px,
            distortion: [0.0; 2],
        }
    }

    /// The photograph's centre, px, and half its diagonal: the lens'
    /// distortion's centre and unit of radius.
    fn lens_frame(&self) -> ([f64; 2], f64) {
        let half = self.side_px as f64 / 2.0;
        ([half, half], half * std::f64::consts::SQRT_2)
    }

    /// The camera's centre (mm, from the piece's centre) and its right,
    /// down and forward axes: right along the piece's u as far as it can,
    /// down = forward × right (a real camera: no mirror image, so the
    /// piece's v runs up the photograph when seen from above).
    fn basis(&self) -> (DVec3, DVec3, DVec3, DVec3) {
        let forward = -self.direction.normalize();
        let u = DVec3::new(1.0, 0.0, 0.0);
        let right = (u - forward * u.dot(forward)).normalize();
        let down = forward.cross(right);
        (self.direction.normalize() * self.distance_mm, right, down, forward)
    }

    /// Where the point `p` (mm, sample-local, from the piece's centre) lies
    /// in the photograph, px (pixel (c, r) spans [c, c + 1) × [r, r + 1)).
    pub fn project(&self, p: DVec3) -> [f64; 2] {
        let (centre, right, down, forward) = self.basis();
        let q = p - centre;
        let z = q.dot(forward);
        let (c, radius) = self.lens_frame();
        let n =
            [self.focal_px * q.dot(right) / z / radius, self.focal_px * q.dot(down) / z / radius];
        let d = scanner_geometry::radial_distort(self.distortion, n);
        [c[0] + radius * d[0], c[1] + radius * d[1]]
    }

    /// Where the ray through the photograph's point `px` meets the piece's
    /// plane (z = 0; mm, sample-local, from the piece's centre), if in
    /// front of the camera.
    pub fn on_plane(&self, px: [f64; 2]) -> Option<DVec3> {
        let (centre, right, down, forward) = self.basis();
        let (c, radius) = self.lens_frame();
        let n = scanner_geometry::radial_undistort(
            self.distortion,
            [(px[0] - c[0]) / radius, (px[1] - c[1]) / radius],
        );
        let k = radius / self.focal_px;
        let ray = forward + right * (n[0] * k) + down * (n[1] * k);
        let t = -centre.z / ray.z;
        (t > 0.0 && t.is_finite()).then(|| centre + ray * t)
    }

    /// The corners of a piece of `size_mm` at uv (0, 0), (1, 0), (1, 1),
    /// (0, 1) in the photograph, px: what `scanner rectify --corners` takes.
    pub fn corners(&self, size_mm: f64) -> [[f64; 2]; 4] {
        [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]
            .map(|[u, v]| self.project(DVec3::new((u - 0.5) * size_mm, (v - 0.5) * size_mm, 0.0)))
    }
}

/// What every pixel of one frame shares.
struct Scene<'a> {
    rays: &'a CameraRays,
    origin: DVec3,
    beam: Beam,
    lit: &'a [LitMirror],
    /// Electrons per unit radiance: exposure × duty × sensitivity.
    scale: f64,
}

/// The camera's ray directions with its basis computed once.
struct CameraRays {
    right: DVec3,
    down: DVec3,
    forward: DVec3,
    camera: crate::geometry::CameraSpec,
}

impl CameraRays {
    fn new(cam: &crate::geometry::CameraSpec) -> CameraRays {
        let (right, down, forward) = cam.basis();
        CameraRays { right, down, forward, camera: cam.clone() }
    }

    fn ray(&self, x: f64, y: f64) -> DVec3 {
        let n = self.camera.undistorted(x, y);
        (self.forward + self.right * n[0] + self.down * n[1]).normalize()
    }
}

/// log₂ of the width of [`DarkCodes::first`]'s buckets of uniform numbers.
const DARK_BUCKET_BITS: u32 = 20;

/// The ADC code distribution of a pixel that receives no light: read noise
/// alone, quantised and clipped at 0. Dark pixels (most of a frame) draw
/// their code from it with one uniform number instead of a Gaussian.
struct DarkCodes {
    /// `cdf[k]` = P(code ≤ k) × 2³², the last entry 2³².
    cdf: Vec<u64>,
    /// `first[b]`: the code drawn by the bucket's smallest u, b ·
    /// 2^[`DARK_BUCKET_BITS`], where the search for any u of the bucket may
    /// start (the code grows with u). Most buckets hold one code, so the
    /// search ends at its first step.
    first: Vec<u32>,
}

impl DarkCodes {
    fn new(read_e: f64, gain: f64, max: f64) -> DarkCodes {
        let sigma = read_e * gain;
        let mut cdf = Vec::new();
        let full = (1u64 << 32) as f64;
        let mut k = 0.0;
        while k < max {
            let p = if sigma > 0.0 {
                0.5 * libm::erfc(-(k + 0.5) / (sigma * std::f64::consts::SQRT_2))
            } else {
                1.0
            };
            let scaled = (p * full).round() as u64;
            cdf.push(scaled);
            if scaled >= 1 << 32 {
                break;
            }
            k += 1.0;
        }
        if cdf.last() != Some(&(1 << 32)) {
            cdf.push(1 << 32);
        }
        let first = (0..1u64 << (32 - DARK_BUCKET_BITS))
            .map(|b| Self::search(&cdf, 0, b << DARK_BUCKET_BITS) as u32)
            .collect();
        DarkCodes { cdf, first }
    }

    fn sample(&self, u: u32) -> usize {
        let from = self.first[(u >> DARK_BUCKET_BITS) as usize] as usize;
        Self::search(&self.cdf, from, u as u64)
    }

    /// The first code k ≥ `from` with u < `cdf[k]`.
    fn search(cdf: &[u64], from: usize, u: u64) -> usize {
        cdf[from..].iter().position(|&c| u < c).map_or(cdf.len() - 1, |k| from + k)
    }
}

/// Shot noise (Gaussian, variance = signal) and read noise (Gaussian) of
/// `electrons` × `scale`, clipping at the full well, quantisation. The two
/// independent Gaussians are drawn as one, of their summed variance.
fn sensor_readout(
    sensor: &crate::geometry::SensorSpec,
    width: u32,
    electrons: &ElectronRows,
    scale: f32,
    seed: u64,
) -> Frame {
    let height = electrons.len() as u32;
    let w = width as usize;
    let max = sensor.max_code();
    let gain = max / sensor.full_well_e;
    let read = sensor.read_noise_e;
    let read2 = read * read;
    let dark = DarkCodes::new(read, gain, max);
    let codes: Vec<f32> = (0..dark.cdf.len()).map(|k| (k as f64 / max) as f32).collect();
    let mut rgb = vec![0.0f32; w * height as usize * 3];
    rgb.par_chunks_mut(w * 3).zip(electrons.par_iter()).enumerate().for_each(|(y, (out, row))| {
        let mut rng =
            ChaCha8Rng::seed_from_u64(seed ^ (y as u64).wrapping_mul(0xA076_1D64_78BD_642F));
        for x in 0..w {
            let e = row.as_ref().map_or([0.0; 3], |r| r[x]);
            for k in 0..3 {
                let s = (e[k] * scale) as f64;
                out[3 * x + k] = if s > 0.0 {
                    let z: f64 = rng.sample(StandardNormal);
                    let noisy = s + (s + read2).sqrt() * z;
                    ((noisy * gain).round().clamp(0.0, max) / max) as f32
                } else {
                    codes[dark.sample(rng.random::<u32>())]
                };
            }
        }
    });
    Frame { width, height, rgb }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rendering only the pixels that see the sample gives the frames that
    /// rendering every pixel gives, bit for bit: on a pinhole and on a
    /// distorting lens, and after another sample takes the holder (the
    /// pixels are the geometry's, shared with the new sample).
    #[test]
    fn pixels_that_cannot_see_the_sample_are_left_out_exactly() {
        let nominal = ScannerGeometry::default_scanner().with_sensor_scaled(8);
        let fabric = crate::materials::by_name("woven-fabric").unwrap();
        let pinhole = OpticalSim::as_built(&nominal, Sample::small(fabric), 3);
        let barrel = pinhole.clone().with_lens_distortion([-0.05, 0.0]);
        let metal =
            pinhole.with_sample(Sample::small(crate::materials::by_name("rough-metal").unwrap()));
        let (w, h) = (nominal.camera.width, nominal.camera.height as usize);
        let every_pixel: PixelSpans = vec![vec![[0, w]]; h];
        for sim in [&pinhole, &barrel, &metal] {
            for l in [0, 7, 22, 39] {
                let axes = sim.geometry.mirror_axes(l).unwrap();
                let exposure = Exposure { axes, exposure_s: 0.05, light: 1.0 };
                let fast = sim.electrons(&exposure);
                assert!(fast.iter().flatten().flatten().any(|e| e[0] > 0.0), "mirror {l}: dark");
                assert_eq!(fast, sim.electrons_over(&exposure, &every_pixel), "mirror {l}");
            }
            // Most of the mirrors' boxes see no sample, and are left out.
            let boxes: u64 =
                sim.boxes.iter().flatten().map(|b| u64::from((b[2] - b[0]) * (b[3] - b[1]))).sum();
            let seen: u64 = sim
                .sees_sample
                .get()
                .unwrap()
                .iter()
                .flatten()
                .map(|s| u64::from(s[1] - s[0]))
                .sum();
            assert!(seen > 0 && 2 * seen < boxes, "{seen} of {boxes} px");
        }
        assert!(Arc::ptr_eq(&pinhole.sees_sample, &metal.sees_sample));
        assert!(!Arc::ptr_eq(&pinhole.sees_sample, &barrel.sees_sample));
    }

    /// Edges are integrated over the pixels they cross, as a sensor
    /// integrates: frames against 24 × 24 rays a pixel, and the base rays
    /// alone against the same, on a printed target and on a weave. A pixel
    /// sampled again by the 4 × 4 lattice reusing its base rays has the
    /// value of all 16 traced.
    #[test]
    fn edges_are_integrated_over_the_pixels_they_cross() {
        let nominal = ScannerGeometry::default_scanner().with_sensor_scaled(8);
        let by_name = |n| Sample::small(crate::materials::by_name(n).unwrap());
        let checker = OpticalSim::as_built(&nominal, by_name("checkerboard"), 3);
        let fabric = checker.with_sample(by_name("woven-fabric"));
        for (sim, l) in [(&checker, 22), (&fabric, 22)] {
            let axes = sim.geometry.mirror_axes(l).unwrap();
            let exposure = Exposure { axes, exposure_s: 0.05, light: 1.0 };
            let rows = sim.electrons(&exposure);
            let spans = sim.sees_sample.get().unwrap();
            // Per pixel: the frame's, the base rays' and 24 × 24 rays' green.
            let mut pixels: Vec<[f32; 3]> = Vec::new();
            sim.with_scene(&exposure, |scene| {
                for (y, spans) in spans.iter().enumerate() {
                    let mirrors = sim.row_mirrors(y);
                    let mut here = Vec::new();
                    for x in spans.iter().flat_map(|&[x0, x1]| x0 as usize..x1 as usize) {
                        OpticalSim::mirrors_at(&mirrors, x, &mut here);
                        let got = rows[y].as_ref().map_or(0.0, |r| r[x][1]);
                        let base = sim.base_radiances(scene, x, y, &here);
                        // A pixel sampled again reuses its base rays: the
                        // same value bit for bit as tracing all 16.
                        let edge = |known| {
                            sim.lattice_electrons(scene, x, y, EDGE_SUPERSAMPLE, &here, known)
                        };
                        assert_eq!(edge(Some(&base)), edge(None), "pixel ({x}, {y})");
                        let base = sim.base_electrons(scene, x, y, &base).0[1];
                        let fine = sim.lattice_electrons(scene, x, y, 24, &here, None)[1];
                        pixels.push([got, base, fine]);
                    }
                }
            })
            .unwrap();
            let top = pixels.iter().map(|p| p[2]).fold(0.0, f32::max);
            let rms = |k: usize| {
                let se: f32 = pixels.iter().map(|p| (p[k] - p[2]).powi(2)).sum();
                (se / pixels.len() as f32).sqrt() / top
            };
            let worst =
                |k: usize| pixels.iter().map(|p| (p[k] - p[2]).abs() / top).fold(0.0, f32::max);
            eprintln!(
                "{} mirror {l}, {} px: the frame within {:.4} RMS, {:.4} at worst; base rays \
                 {:.4} RMS, {:.4} at worst (of the brightest pixel)",
                sim.sample.material.name(),
                pixels.len(),
                rms(0),
                worst(0),
                rms(1),
                worst(1)
            );
            // Measured at this sensor (bin 8: a pixel spans several of the
            // squares' edges, or a weave's threads): RMS 0.039 against
            // 0.082 (checkerboard), 0.092 against 0.204 (weave); the 99th
            // percentile 0.117 against 0.267, 0.280 against 0.590. At
            // worst 0.18 against 0.37, 0.61 against 0.76: the worst are
            // pixels whose base rays agree (a weave's peak that all four
            // see), left as the base rays have them.
            let p99 = |k: usize| {
                let mut e: Vec<f32> = pixels.iter().map(|p| (p[k] - p[2]).abs() / top).collect();
                e.sort_by(f32::total_cmp);
                e[e.len() * 99 / 100]
            };
            assert!(rms(0) < 0.5 * rms(1) && p99(0) < 0.5 * p99(1));
        }
    }

    /// The sample's outline is integrated exactly over the pixels it
    /// crosses: on a diffuse white sample, whose radiance barely varies
    /// within a pixel, every 8th outline pixel of the frame (4 × 4 rays
    /// and the exact share of its square) matches 64 × 64 rays to 1 % of
    /// the brightest pixel (their own share is within 1/128), where the
    /// 4 × 4 rays' own share misses by up to an eighth.
    #[test]
    fn the_sample_s_outline_is_integrated_exactly() {
        let nominal = ScannerGeometry::default_scanner().with_sensor_scaled(8);
        let white = Sample::small(crate::materials::by_name("diffuse-white").unwrap());
        let sim = OpticalSim::as_built(&nominal, white, 4);
        for l in [7, 22] {
            let axes = sim.geometry.mirror_axes(l).unwrap();
            let exposure = Exposure { axes, exposure_s: 0.05, light: 1.0 };
            let rows = sim.electrons(&exposure);
            let spans = sim.sees_sample.get().unwrap();
            let top = rows.iter().flatten().flatten().map(|e| e[1]).fold(0.0, f32::max) as f64;
            let (mut outline, mut worst, mut worst_lattice) = (0, 0.0f64, 0.0f64);
            sim.with_scene(&exposure, |scene| {
                for (y, spans) in spans.iter().enumerate() {
                    let mirrors = sim.row_mirrors(y);
                    let mut here = Vec::new();
                    for x in spans.iter().flat_map(|&[x0, x1]| x0 as usize..x1 as usize) {
                        OpticalSim::mirrors_at(&mirrors, x, &mut here);
                        let Some(o) = sim.outline(scene, x, y, EDGE_SUPERSAMPLE, &here) else {
                            continue;
                        };
                        outline += 1;
                        if outline % 8 != 0 {
                            continue;
                        }
                        let got = rows[y].as_ref().map_or(0.0, |r| r[x][1]) as f64;
                        // 64 × 64 rays, their own share (within 1/128 of
                        // the pixel).
                        let n = 64;
                        let sum: f64 = (0..n * n)
                            .map(|k| {
                                let (fx, fy) = OpticalSim::lattice_point(x, y, n, [k % n, k / n]);
                                sim.radiance_at(scene, fx, fy, &here)[1]
                            })
                            .sum();
                        let fine = sim.to_electrons(scene, x, y, [0.0, sum, 0.0], n * n)[1] as f64;
                        worst = worst.max((got - fine).abs() / top);
                        let lattice =
                            if o.on() > 0 { got * o.on() as f64 / 16.0 / o.share } else { 0.0 };
                        worst_lattice = worst_lattice.max((lattice - fine).abs() / top);
                    }
                }
            })
            .unwrap();
            eprintln!(
                "mirror {l}: {outline} outline px, every 8th within {worst:.4} of 64 × 64 rays \
                 ({worst_lattice:.4} by the 4 × 4 rays' share)"
            );
            assert!(outline > 20, "mirror {l}: {outline} outline pixels");
            assert!(worst < 0.01, "mirror {l}: {worst}");
            assert!(worst_lattice > 0.02, "mirror {l}: {worst_lattice}");
        }
    }

    /// The base rays are points of the edge lattice, one in each of its
    /// rows and columns.
    #[test]
    fn base_rays_are_a_rotated_grid_in_the_edge_lattice() {
        assert_eq!(BASE_RAYS.len(), SUPERSAMPLE * SUPERSAMPLE);
        for axis in 0..2 {
            let mut seen: Vec<usize> = BASE_RAYS.iter().map(|p| p[axis]).collect();
            seen.sort_unstable();
            seen.dedup();
            assert_eq!(seen, (0..EDGE_SUPERSAMPLE).collect::<Vec<_>>(), "axis {axis}");
        }
    }

    #[test]
    fn dark_codes_follow_the_quantised_read_noise() {
        let d = DarkCodes::new(3.0, 4095.0 / 10_000.0, 4095.0);
        // P(code = 0) = Φ(0.5 / σ) with σ = 1.2285 DN.
        let p0 = d.cdf[0] as f64 / (1u64 << 32) as f64;
        assert!((p0 - 0.658).abs() < 0.002, "{p0}");
        assert_eq!(*d.cdf.last().unwrap(), 1 << 32);
        assert!(d.cdf.len() < 12);
        assert_eq!(d.sample(0), 0);
        assert_eq!(d.sample(u32::MAX), d.cdf.len() - 1);
        // The buckets only say where to start: every u draws the code of the
        // search from code 0, at each code's bounds and in between, for this
        // read noise and for one of σ ≈ 50 DN (many codes per bucket).
        for d in [d, DarkCodes::new(120.0, 4095.0 / 10_000.0, 4095.0)] {
            let mut us: Vec<u32> = (0..100_000u64).map(|i| (i * 42_949 + 17) as u32).collect();
            for &c in &d.cdf {
                us.extend([c.saturating_sub(1), c].map(|u| u.min(u32::MAX as u64) as u32));
            }
            for u in us {
                assert_eq!(d.sample(u), DarkCodes::search(&d.cdf, 0, u as u64), "u = {u}");
            }
        }
    }
}
