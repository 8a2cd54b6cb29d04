//! Fig. 9: a material scanned on a small sample, enlarged to a large piece
//! of the same material seen in direct images (docs/direct-images.md).
//!
//! Every texel of the large piece is matched to the place on the scanned
//! sample whose **colour signature** is nearest (squared Euclidean
//! distance): the RGB of its 3 × 3 neighbourhood in every direct image,
//! against the same neighbourhood of the material shaded at the images'
//! directions (light and view both along an image's direction, as the
//! direct images are taken). The map is stored in the material (format
//! version 5), and the shading looks every uv of the piece up through it.
//!
//! - Both sides are compared at the material's texel pitch: the direct
//!   images are averaged over each map texel's area, the material over a
//!   texel's area (4 × 4 points) around each candidate point. Candidates
//!   lie at the sample's texel centres and `subtexel − 1` points between,
//!   since the piece's texel grid falls anywhere on the sample's.
//! - The scale: a white reference photographed like the piece gives it
//!   absolutely; without one, the ratio of the means, then the median ratio
//!   of the matches, until it settles (docs/direct-images.md says why the
//!   reference matters).
//! - Signatures compare logarithms (each value plus 2 % of its image's
//!   mean), so that a highlight's texels do not outweigh the rest.
//! - The nearest signature is found exactly among a k-d tree's
//!   [`CANDIDATES`] nearest in the signatures' first [`PCA_DIMS`]
//!   principal components ([`kiddo`]'s immutable tree, the leading
//!   [`DOUBLED`] held twice so that its turns split them more: `tree_point`),
//!   then compared in full.
//! - The patent's other signature, [`Signature::Height`]: the
//!   neighbourhood's heights relative to the texel's, from photometric
//!   stereo over the images and integrated to convergence
//!   (`Stereo::heights`); no scale needed.
//! - Photographs taken in perspective and rectified (`camera_distance_mm`
//!   in the manifest) are first put back at their image's direction by the
//!   material's mean appearance (`view_correction`).

use std::num::NonZero;
use std::path::Path;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;
use scanner_formats::direct::DirectManifest;
use scanner_shading::Material;
use scanner_shading::format::{
    ENLARGEMENT_UNITS, Enlargement, MAX_ENLARGEMENT, MaterialData, VERSION_ENLARGED,
};

use super::BuildError;
use crate::camera::Frame;

/// Principal components the k-d tree searches in.
pub const PCA_DIMS: usize = 12;
/// Nearest candidates in the principal components compared in full.
pub const CANDIDATES: usize = 16;
/// The leading principal components the k-d tree holds twice.
const DOUBLED: usize = 3;
/// The k-d tree's coordinates: the [`DOUBLED`] leading components, each
/// over √2, twice, then the others.
const TREE_DIMS: usize = PCA_DIMS + DOUBLED;
/// The map's fixed-point units of the sample's side.
const MAP_UNITS: f64 = ENLARGEMENT_UNITS as f64;
/// Rounds of the gain from the matches, at most.
const GAIN_ROUNDS: usize = 6;
/// A gain's change (log) below which it has settled.
const GAIN_SETTLED: f64 = 0.002;
/// The log signature's floor: this fraction of each image's mean.
const LOG_FLOOR: f64 = 0.02;
/// A channel of the sample whose mean over the images' directions is below
/// this share of its brightest channel's carries no colour to match by (a
/// colour the material does not reflect, as a pure red's green, or noise):
/// the colour signature leaves it out.
const DARK_CHANNEL: f64 = 1e-3;

/// How texels are matched.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EnlargeOptions {
    /// The signature's neighbourhood: (2 radius + 1)² texels (1: the
    /// patent's 3 × 3).
    pub radius: usize,
    /// Candidate points per texel of the sample along u and v (1…4): a
    /// piece's texel may match a point between the sample's texels.
    pub subtexel: usize,
    /// What the signature holds.
    pub signature: Signature,
}

/// What a texel's signature holds (the patent's two).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Signature {
    /// The colour signature: the neighbourhood's RGB (as logarithms) in
    /// every direct image.
    Colour,
    /// The height signature: the neighbourhood's heights, relative to the
    /// texel's own, from photometric stereo over the direct images
    /// (Lambert: brightness ∝ n · l). It does not depend on the images'
    /// scale, so it needs no white reference.
    Height,
}

impl Signature {
    /// Its name in the material file (`enlargement.signature`) and on the
    /// command line.
    pub fn name(&self) -> &'static str {
        match self {
            Signature::Colour => "colour",
            Signature::Height => "height",
        }
    }
}

impl std::str::FromStr for Signature {
    type Err = String;

    fn from_str(s: &str) -> Result<Signature, String> {
        match s {
            "colour" => Ok(Signature::Colour),
            "height" => Ok(Signature::Height),
            _ => Err(format!("signature {s:?}: colour or height")),
        }
    }
}

impl EnlargeOptions {
    /// The defaults (docs/benchmarks.md, "Enlargement", measures them).
    pub const DEFAULT: EnlargeOptions =
        EnlargeOptions { radius: 1, subtexel: 2, signature: Signature::Colour };

    /// The options in range: radius 0…3 (1…3 for heights), subtexel 1…4.
    pub fn check(&self) -> Result<(), String> {
        if self.radius > 3 {
            return Err(format!("--radius {}: 0…3", self.radius));
        }
        if !(1..=4).contains(&self.subtexel) {
            return Err(format!("--subtexel {}: 1…4", self.subtexel));
        }
        if self.signature == Signature::Height && self.radius == 0 {
            return Err("--radius 0 leaves the height signature empty: 1…3".into());
        }
        Ok(())
    }
}

impl Default for EnlargeOptions {
    fn default() -> Self {
        EnlargeOptions::DEFAULT
    }
}

/// A set of direct images, read and checked.
#[derive(Debug, Clone)]
pub struct DirectSet {
    /// Its manifest.
    pub manifest: DirectManifest,
    /// The images in the manifest's order, all of one size, values finite
    /// and ≥ 0.
    pub images: Vec<Frame>,
    /// The white reference's image, when the manifest names one.
    pub white: Option<Frame>,
    /// SHA-256 of `direct.toml`.
    pub sha256: String,
}

/// Read the direct images in `dir` (docs/direct-images.md).
pub fn read_direct_set(dir: &Path) -> Result<DirectSet, BuildError> {
    let (manifest, bytes) =
        DirectManifest::read_with_bytes(dir).map_err(|e| BuildError::Input(e.to_string()))?;
    let sha256 = crate::scan::sha256_hex(&bytes);
    let read = |file: &str| -> Result<Frame, BuildError> {
        let path = dir.join(file);
        let frame = crate::exrio::read_rgb(&path)
            .map_err(|e| BuildError::Input(format!("{}: {e}", path.display())))?;
        if let Some(i) = frame.rgb.iter().position(|v| !(v.is_finite() && *v >= 0.0)) {
            let p = i / 3;
            return Err(BuildError::Input(format!(
                "{}: pixel ({}, {}) holds {}, not a radiance ≥ 0",
                path.display(),
                p % frame.width as usize,
                p / frame.width as usize,
                frame.rgb[i]
            )));
        }
        Ok(frame)
    };
    let white = manifest.white.as_ref().map(|w| read(&w.file)).transpose()?;
    let mut images: Vec<Frame> = Vec::new();
    for im in &manifest.image {
        let path = dir.join(&im.file);
        let frame = read(&im.file)?;
        if let Some(first) = images.first()
            && (frame.width, frame.height) != (first.width, first.height)
        {
            return Err(BuildError::Input(format!(
                "{}: {} × {} px, but {} is {} × {} px: the images of a set cover the piece \
                 alike",
                path.display(),
                frame.width,
                frame.height,
                manifest.image[0].file,
                first.width,
                first.height
            )));
        }
        images.push(frame);
    }
    Ok(DirectSet { manifest, images, white, sha256 })
}

/// How the enlargement went.
#[derive(Debug, Clone, PartialEq)]
pub struct EnlargeReport {
    /// The map's texels along u and v.
    pub columns: u32,
    /// See `columns`.
    pub rows: u32,
    /// The gain per channel that put the direct images on the material's
    /// scale (the colour signature): from the white reference, or without
    /// one first the ratio of their means, then the median ratio of the
    /// texels' matches to them until it settles. The height signature
    /// needs none.
    pub gain: Option<[f64; 3]>,
    /// The matches' signature distance, RMS per signature value (a log
    /// ratio: 0.1 ≈ 10 %), median and 90th percentile.
    pub distance: [f64; 2],
    /// Distinct points of the sample the map uses.
    pub points_used: usize,
    /// The channels (r, g, b) the colour signature matched by: those the
    /// sample reflects ([`DARK_CHANNEL`]). None: the sample is black at
    /// the images' directions, there is nothing to match by, and the piece
    /// is the sample tiled. The height signature: all three.
    pub channels: [bool; 3],
}

/// What enlarging to a map of `texels` texels from `images` direct images
/// needs, bytes, about: the piece's images at the map's pitch (before and
/// after their view correction), their signatures and the matches, ≈ 40 B
/// a texel and image. Measured with four images: 156 MB peak at 504² texels,
/// 755 MB at 2016² (157 B a texel beyond the first).
fn enlarge_memory(texels: usize, images: usize) -> u128 {
    texels as u128 * images.max(1) as u128 * 40
}

/// Refuse a map that cannot fit in `available` bytes (`need`, for a map of
/// `texels` over a piece of `size_mm`), rather than be killed when memory
/// runs out.
fn check_memory(
    need: u128,
    texels: [usize; 2],
    size_mm: [f64; 2],
    available: Option<u64>,
) -> Result<(), BuildError> {
    super::memory::check_memory(
        need,
        available,
        &format!(
            "a piece of {} × {} mm is {} × {} texels of the material: enlarging it needs",
            size_mm[0], size_mm[1], texels[0], texels[1]
        ),
        "enlarge a smaller part of the piece",
    )
}

/// `data` (a material of the small sample) enlarged to the piece of the
/// direct images `set`.
pub fn enlarge(
    data: &MaterialData,
    set: &DirectSet,
    opts: &EnlargeOptions,
) -> Result<(MaterialData, EnlargeReport), BuildError> {
    opts.check().map_err(BuildError::Input)?;
    if data.meta.enlargement.is_some() {
        return Err(BuildError::Input(
            "the material is enlarged already: enlarge the material of the sample".into(),
        ));
    }
    // Shaded as its file stores it (float16 palettes), as renderers will.
    let material = data
        .to_bytes()
        .and_then(|b| Material::from_bytes(&b))
        .map_err(|e| BuildError::Input(format!("the material: {e}")))?;
    let s = data.meta.resolution as usize;
    let pitch = data.meta.sample_size_mm / s as f64;
    let size_mm = set.manifest.size_mm;
    let texels = |mm: f64| (mm / pitch).round().max(1.0);
    let (columns, rows) = (texels(size_mm[0]), texels(size_mm[1]));
    if columns > MAX_ENLARGEMENT as f64 || rows > MAX_ENLARGEMENT as f64 {
        return Err(BuildError::Input(format!(
            "a piece of {} × {} mm is {columns} × {rows} texels of the material's {pitch:.3} mm: \
             at most {MAX_ENLARGEMENT} a side",
            size_mm[0], size_mm[1]
        )));
    }
    let (columns, rows) = (columns as usize, rows as usize);
    check_memory(
        enlarge_memory(columns * rows, set.images.len()),
        [columns, rows],
        size_mm,
        super::memory::available_memory(),
    )?;
    let directions: Vec<[f64; 3]> = set
        .manifest
        .image
        .iter()
        .map(|im| {
            let d = im.direction;
            let len = d.iter().map(|x| x * x).sum::<f64>().sqrt();
            d.map(|x| x / len)
        })
        .collect();

    // The piece at the map's pitch, on one scale (÷ exposure).
    let piece: Vec<Vec<[f64; 3]>> = set
        .images
        .iter()
        .zip(&set.manifest.image)
        .map(|(f, im)| {
            area_resample(f, columns, rows)
                .into_iter()
                .map(|v| v.map(|x| x / im.exposure_s))
                .collect()
        })
        .collect();
    // Photographs from a camera at a finite distance saw each point of the
    // piece from its own direction: each is put back at its image's.
    let piece: Vec<Vec<[f64; 3]>> = piece
        .into_iter()
        .zip(&set.manifest.image)
        .zip(&directions)
        .map(|((img, im), &d)| match im.camera_distance_mm {
            None => img,
            Some(distance) => {
                let f = view_correction(&material, d, distance, size_mm, columns, rows);
                img.into_iter().zip(f).map(|(v, f)| std::array::from_fn(|c| v[c] * f[c])).collect()
            }
        })
        .collect();
    // The sample: the material at each image's direction, averaged over a
    // texel's area (4 × 4 points) around each point of a grid `sub` times
    // finer than its texels (its texel centres and the points between), so
    // that a match may lie between texels.
    let sub = opts.subtexel;
    let fine = sub * s;
    let sample: Vec<Vec<[f64; 3]>> = directions
        .iter()
        .map(|d| {
            let d = d.map(|x| x as f32);
            (0..fine * fine)
                .into_par_iter()
                .map(|i| {
                    // In texels: the texel centres and `sub − 1` points after each.
                    let centre =
                        [(i % fine) as f32, (i / fine) as f32].map(|c| c / sub as f32 + 0.5);
                    let mut acc = [0.0f64; 3];
                    for a in 0..4 {
                        for b in 0..4 {
                            let off = |k: usize| (k as f32 + 0.5) / 4.0 - 0.5;
                            let uv =
                                [(centre[0] + off(a)) / s as f32, (centre[1] + off(b)) / s as f32]
                                    .map(|u| u.clamp(0.0, 1.0 - f32::EPSILON));
                            let v = material.eval(uv, d, d);
                            for c in 0..3 {
                                acc[c] += v[c] as f64 / 16.0;
                            }
                        }
                    }
                    acc
                })
                .collect()
        })
        .collect();

    let (matches, gain, dims, channels) = match opts.signature {
        Signature::Colour => colour_matches(&sample, &piece, set, opts, [columns, rows, fine])?,
        Signature::Height => {
            let (matches, dims) =
                height_matches(&sample, &piece, &directions, opts, pitch, [columns, rows, fine])?;
            (matches, None, dims, [true; 3])
        }
    };
    // Each match as the sample's uv in 16-bit fixed point.
    let fixed = |k: usize| {
        let uv = (k as f64 / sub as f64 + 0.5) / s as f64;
        (uv * MAP_UNITS - 0.5).round().clamp(0.0, MAP_UNITS - 1.0) as u16
    };
    let matches: Vec<([u16; 2], f32)> =
        matches.into_iter().map(|(i, d)| ([fixed(i % fine), fixed(i / fine)], d)).collect();

    let mut dist: Vec<f64> =
        matches.iter().map(|m| (m.1.max(0.0) as f64 / dims as f64).sqrt()).collect();
    dist.sort_by(f64::total_cmp);
    let pct = |p: f64| dist[((dist.len() - 1) as f64 * p).round() as usize];
    let mut used: Vec<[u16; 2]> = matches.iter().map(|m| m.0).collect();
    used.sort_unstable();
    used.dedup();
    let report = EnlargeReport {
        columns: columns as u32,
        rows: rows as u32,
        gain,
        distance: [pct(0.5), pct(0.9)],
        points_used: used.len(),
        channels,
    };
    let mut out = data.clone();
    out.meta.version = VERSION_ENLARGED;
    out.meta.extent_mm = size_mm;
    out.meta.enlargement = Some(Enlargement {
        columns: columns as u32,
        rows: rows as u32,
        signature: opts.signature.name().into(),
        directions,
        direct_sha256: set.sha256.clone(),
    });
    out.enlargement = matches.into_iter().map(|m| m.0).collect();
    Ok((out, report))
}

/// The piece's and the sample's sizes: the map's columns and rows, and the
/// sample's candidate grid's side.
type Sizes = [usize; 3];

/// Matches by the colour signature, with the gain that put the piece on the
/// material's scale, the signature's length and the channels it used.
#[allow(clippy::type_complexity)]
fn colour_matches(
    sample: &[Vec<[f64; 3]>],
    piece: &[Vec<[f64; 3]>],
    set: &DirectSet,
    opts: &EnlargeOptions,
    [columns, rows, fine]: Sizes,
) -> Result<(Vec<(usize, f32)>, Option<[f64; 3]>, usize, [bool; 3]), BuildError> {
    let (sample_mean, piece_mean) = (means(sample), means(piece));
    let n_img = sample.len();
    let total = |means: &[[f64; 3]]| -> [f64; 3] {
        std::array::from_fn(|c| means.iter().map(|m| m[c]).sum())
    };
    let (a, b) = (total(&sample_mean), total(&piece_mean));
    // Channels above DARK_CHANNEL of the brightest (none if all are black).
    let lit = |t: [f64; 3]| -> [bool; 3] {
        let brightest = t.into_iter().fold(0.0, f64::max);
        t.map(|x| x > DARK_CHANNEL * brightest)
    };
    // The channels the sample reflects carry its colour; the others only
    // noise, whatever the piece shows in them.
    let (channels, piece_lit) = (lit(a), lit(b));
    if channels == [false; 3] {
        // A black sample (at these directions) looks alike everywhere:
        // any place matches, and the piece is the sample tiled.
        let s = fine / opts.subtexel;
        let tiled = (0..columns * rows)
            .map(|p| {
                let (x, y) = ((p % columns) % s, (p / columns) % s);
                (y * opts.subtexel * fine + x * opts.subtexel, 0.0)
            })
            .collect();
        return Ok((tiled, None, 1, channels));
    }
    // The gain that puts the piece on the material's scale: absolute from
    // the white reference (its radiance albedo/π · cos θ), else the ratio
    // of the means, refined from the matches below.
    let white_gain = match (&set.white, &set.manifest.white) {
        (Some(frame), Some(w)) => Some(white_scale(frame, w)?),
        _ => None,
    };
    let mut gain = [1.0; 3];
    for c in (0..3).filter(|&c| channels[c]) {
        if !piece_lit[c] {
            let brightest = a.into_iter().fold(0.0, f64::max);
            return Err(BuildError::Input(format!(
                "channel {c} is black in the direct images but not on the sample ({:.3} of its \
                 brightest channel there): nothing to match it by",
                a[c] / brightest
            )));
        }
        gain[c] = white_gain.map_or(a[c] / b[c], |w| w[c]);
    }
    // Log values, each over a floor of its image's mean; a channel the
    // sample does not reflect is left out (0 everywhere).
    let floor: Vec<[f64; 3]> = sample_mean.iter().map(|m| m.map(|x| LOG_FLOOR * x)).collect();
    let logs = |imgs: &[Vec<[f64; 3]>], scale: [f64; 3]| -> Vec<Vec<[f32; 3]>> {
        imgs.iter()
            .enumerate()
            .map(|(k, img)| {
                img.iter()
                    .map(|v| {
                        std::array::from_fn(|c| {
                            if !channels[c] {
                                return 0.0;
                            }
                            ((v[c] * scale[c]).max(0.0) + floor[k][c].max(1e-30)).ln() as f32
                        })
                    })
                    .collect()
            })
            .collect()
    };
    let sample_log = logs(sample, [1.0; 3]);
    let r = opts.radius;
    let index = Index::new(&Colours {
        logs: &sample_log,
        w: fine,
        h: fine,
        radius: r,
        step: opts.subtexel,
    });
    // The gain again from the matches: the median log ratio of each
    // texel's match to it, until it settles. The means' gain is off where
    // the piece is brighter or darker on average than the sample, and its
    // matches then all lean one way.
    let mut piece_log = logs(piece, gain);
    let match_piece = |logs: &[Vec<[f32; 3]>]| {
        index.nearest(&Colours { logs, w: columns, h: rows, radius: r, step: 1 })
    };
    let mut matches = match_piece(&piece_log);
    for _ in 0..if white_gain.is_some() { 0 } else { GAIN_ROUNDS } {
        let mut change = [0.0f64; 3];
        for (c, ch) in change.iter_mut().enumerate() {
            let mut ratios: Vec<f32> = matches
                .iter()
                .enumerate()
                .map(|(p, &(i, _))| {
                    (0..n_img).map(|k| sample_log[k][i][c] - piece_log[k][p][c]).sum::<f32>()
                        / n_img as f32
                })
                .collect();
            let mid = ratios.len() / 2;
            *ch = *ratios.select_nth_unstable_by(mid, f32::total_cmp).1 as f64;
        }
        if change.iter().all(|x| x.abs() < GAIN_SETTLED) {
            break;
        }
        for (g, ch) in gain.iter_mut().zip(change) {
            *g *= ch.exp();
        }
        piece_log = logs(piece, gain);
        matches = match_piece(&piece_log);
    }
    Ok((matches, Some(gain), index.dims, channels))
}

/// Matches by the height signature, and the signature's length.
fn height_matches(
    sample: &[Vec<[f64; 3]>],
    piece: &[Vec<[f64; 3]>],
    directions: &[[f64; 3]],
    opts: &EnlargeOptions,
    pitch: f64,
    [columns, rows, fine]: Sizes,
) -> Result<(Vec<(usize, f32)>, usize), BuildError> {
    let stereo = Stereo::new(directions)?;
    let sub = opts.subtexel;
    let sample_h = stereo.heights(sample, fine, fine, pitch / sub as f64);
    let piece_h = stereo.heights(piece, columns, rows, pitch);
    let r = opts.radius;
    let index = Index::new(&Heights { h: &sample_h, w: fine, radius: r, step: sub, pitch });
    let matches = index.nearest(&Heights { h: &piece_h, w: columns, radius: r, step: 1, pitch });
    Ok((matches, index.dims))
}

/// Grid points along each side of the piece at which [`view_correction`]
/// is evaluated (bilinear between).
const CORRECTION_GRID: usize = 17;
/// Points along each side of the sample its mean appearance is taken over.
const CORRECTION_POINTS: usize = 16;
/// The largest correction either way: beyond it the material's mean at
/// one of the two directions is too dark to divide by.
const MAX_CORRECTION: f64 = 8.0;

/// For a photograph taken from `distance` mm along `d` from the piece's
/// centre, per texel of the `columns × rows` map: the factor that takes the
/// piece's brightness there from the direction it was seen from (towards
/// the camera) to `d` — the material's mean over the sample with light
/// and view along `d` over its mean with light along `d` and view towards
/// the camera from that point. First order: it follows how the material
/// changes with the view on average, not texel by texel.
fn view_correction(
    material: &Material,
    d: [f64; 3],
    distance: f64,
    size_mm: [f64; 2],
    columns: usize,
    rows: usize,
) -> Vec<[f64; 3]> {
    let n = CORRECTION_POINTS;
    let mean = |v: [f64; 3]| -> [f64; 3] {
        let (l, v) = (d.map(|x| x as f32), v.map(|x| x as f32));
        let mut acc = [0.0f64; 3];
        for i in 0..n * n {
            let uv = [(i % n) as f32, (i / n) as f32].map(|k| (k + 0.5) / n as f32);
            let f = material.eval(uv, l, v);
            for c in 0..3 {
                acc[c] += f[c] as f64 / (n * n) as f64;
            }
        }
        acc
    };
    let along_d = mean(d);
    let g = CORRECTION_GRID;
    let grid: Vec<[f64; 3]> = (0..g * g)
        .into_par_iter()
        .map(|i| {
            let at = |k: usize, side: f64| (k as f64 / (g - 1) as f64 - 0.5) * side;
            let p = [at(i % g, size_mm[0]), at(i / g, size_mm[1]), 0.0];
            let to_camera: [f64; 3] = std::array::from_fn(|k| d[k] * distance - p[k]);
            let len = to_camera.iter().map(|x| x * x).sum::<f64>().sqrt();
            let seen = mean(to_camera.map(|x| x / len));
            std::array::from_fn(|c| {
                if seen[c] > 0.0 && along_d[c] > 0.0 {
                    (along_d[c] / seen[c]).clamp(1.0 / MAX_CORRECTION, MAX_CORRECTION)
                } else {
                    1.0
                }
            })
        })
        .collect();
    (0..columns * rows)
        .map(|p| {
            let x = ((p % columns) as f64 + 0.5) / columns as f64 * (g - 1) as f64;
            let y = ((p / columns) as f64 + 0.5) / rows as f64 * (g - 1) as f64;
            let (x0, y0) = ((x as usize).min(g - 2), (y as usize).min(g - 2));
            let (fx, fy) = (x - x0 as f64, y - y0 as f64);
            let at = |x: usize, y: usize| grid[y * g + x];
            std::array::from_fn(|c| {
                (1.0 - fy) * ((1.0 - fx) * at(x0, y0)[c] + fx * at(x0 + 1, y0)[c])
                    + fy * ((1.0 - fx) * at(x0, y0 + 1)[c] + fx * at(x0 + 1, y0 + 1)[c])
            })
        })
        .collect()
}

/// Each image's mean per channel.
fn means(imgs: &[Vec<[f64; 3]>]) -> Vec<[f64; 3]> {
    let mean = |img: &Vec<[f64; 3]>, c: usize| {
        img.iter().map(|v| v[c]).sum::<f64>() / img.len().max(1) as f64
    };
    imgs.iter().map(|img| std::array::from_fn(|c| mean(img, c))).collect()
}

/// A grid of texels with a signature each.
trait Signatures: Sync {
    /// The grid's width and height.
    fn size(&self) -> [usize; 2];
    /// Values in a signature.
    fn dims(&self) -> usize;
    /// Texel (x, y)'s signature into `out` ([`Signatures::dims`] values).
    fn signature(&self, x: usize, y: usize, out: &mut [f32]);
}

/// The colour signature: log images on a `w × h` grid whose points'
/// signatures are their (2 radius + 1)² neighbourhoods `step` points apart
/// (clamped at the border).
struct Colours<'a> {
    logs: &'a [Vec<[f32; 3]>],
    w: usize,
    h: usize,
    radius: usize,
    step: usize,
}

impl Signatures for Colours<'_> {
    fn size(&self) -> [usize; 2] {
        [self.w, self.h]
    }

    fn dims(&self) -> usize {
        let side = 2 * self.radius + 1;
        3 * side * side * self.logs.len()
    }

    /// `[image][dy][dx][channel]`.
    fn signature(&self, x: usize, y: usize, out: &mut [f32]) {
        let (r, step) = (self.radius as isize, self.step as isize);
        let mut k = 0;
        for img in self.logs {
            for dy in -r..=r {
                let yy = (y as isize + dy * step).clamp(0, self.h as isize - 1) as usize;
                for dx in -r..=r {
                    let xx = (x as isize + dx * step).clamp(0, self.w as isize - 1) as usize;
                    out[k..k + 3].copy_from_slice(&img[yy * self.w + xx]);
                    k += 3;
                }
            }
        }
    }
}

/// The height signature: a height map's (2 radius + 1)² − 1 neighbours
/// `step` points apart (clamped at the border), each relative to the
/// point's own height and over the distance `pitch` of one step × `step`,
/// i.e. in units of the texel pitch.
struct Heights<'a> {
    h: &'a [f32],
    w: usize,
    radius: usize,
    step: usize,
    pitch: f64,
}

impl Signatures for Heights<'_> {
    fn size(&self) -> [usize; 2] {
        [self.w, self.h.len() / self.w]
    }

    fn dims(&self) -> usize {
        let side = 2 * self.radius + 1;
        side * side - 1
    }

    /// `[dy][dx]` without the centre.
    fn signature(&self, x: usize, y: usize, out: &mut [f32]) {
        let (r, step) = (self.radius as isize, self.step as isize);
        let rows = (self.h.len() / self.w) as isize;
        let at = |x: usize, y: usize| self.h[y * self.w + x];
        let own = at(x, y);
        let unit = 1.0 / self.pitch as f32;
        let mut k = 0;
        for dy in -r..=r {
            let yy = (y as isize + dy * step).clamp(0, rows - 1) as usize;
            for dx in -r..=r {
                if (dx, dy) == (0, 0) {
                    continue;
                }
                let xx = (x as isize + dx * step).clamp(0, self.w as isize - 1) as usize;
                out[k] = (at(xx, yy) - own) * unit;
                k += 1;
            }
        }
    }
}

/// The sample's signatures, and a k-d tree over their first [`PCA_DIMS`]
/// principal components.
struct Index {
    sig: Vec<f32>,
    dims: usize,
    components: Components,
    tree: ImmutableKdTree<f32, TREE_DIMS>,
}

/// The signatures' mean and first [`PCA_DIMS`] principal axes.
struct Components {
    centre: Vec<f32>,
    axes: Vec<Vec<f32>>,
}

impl Components {
    /// A signature's first [`PCA_DIMS`] principal components (0 beyond the
    /// signature's length).
    fn project(&self, sig: &[f32]) -> [f32; PCA_DIMS] {
        std::array::from_fn(|p| {
            self.axes.get(p).map_or(0.0, |a| {
                sig.iter().zip(&self.centre).zip(a).map(|((x, m), w)| (x - m) * w).sum()
            })
        })
    }
}

/// A point's coordinates in the k-d tree ([`TREE_DIMS`]): distances are
/// those of the principal components, but the tree, which splits its
/// coordinates in turn, splits the leading components twice as often.
fn tree_point(p: &[f32; PCA_DIMS]) -> [f32; TREE_DIMS] {
    std::array::from_fn(|i| {
        if i < 2 * DOUBLED {
            p[i % DOUBLED] * std::f32::consts::FRAC_1_SQRT_2
        } else {
            p[i - DOUBLED]
        }
    })
}

impl Index {
    fn new(grid: &impl Signatures) -> Index {
        let [w, h] = grid.size();
        let dims = grid.dims();
        let n = w * h;
        let mut sig = vec![0.0f32; n * dims];
        sig.par_chunks_mut(dims).enumerate().for_each(|(i, s)| grid.signature(i % w, i / w, s));
        let mut centre = vec![0.0f64; dims];
        for s in sig.chunks_exact(dims) {
            for (m, &x) in centre.iter_mut().zip(s) {
                *m += x as f64 / n as f64;
            }
        }
        let cov = sig
            .par_chunks(dims * 256)
            .map(|block| {
                let mut c = vec![0.0f64; dims * dims];
                let mut d = vec![0.0f64; dims];
                for s in block.chunks_exact(dims) {
                    for (di, (&x, m)) in d.iter_mut().zip(s.iter().zip(&centre)) {
                        *di = x as f64 - m;
                    }
                    for i in 0..dims {
                        let di = d[i];
                        for j in i..dims {
                            c[i * dims + j] += di * d[j];
                        }
                    }
                }
                c
            })
            .reduce(
                || vec![0.0; dims * dims],
                |mut a, b| {
                    for (x, y) in a.iter_mut().zip(b) {
                        *x += y;
                    }
                    a
                },
            );
        let mut sym = cov;
        for i in 0..dims {
            for j in 0..i {
                sym[i * dims + j] = sym[j * dims + i];
            }
        }
        let (_, vectors) = super::linalg::symmetric_eigen(dims, &sym);
        let axes: Vec<Vec<f32>> = vectors
            .into_iter()
            .take(PCA_DIMS)
            .map(|v| v.iter().map(|&x| x as f32).collect())
            .collect();
        let components = Components { centre: centre.iter().map(|&x| x as f32).collect(), axes };
        let points: Vec<[f32; TREE_DIMS]> =
            sig.par_chunks(dims).map(|s| tree_point(&components.project(s))).collect();
        let tree = ImmutableKdTree::new_from_slice(&points);
        Index { sig, dims, components, tree }
    }

    /// For every texel of `grid`, the sample's point whose signature is
    /// nearest, and the squared distance: exact among the tree's
    /// [`CANDIDATES`] nearest in the principal components (ties to the
    /// lower index).
    fn nearest(&self, grid: &impl Signatures) -> Vec<(usize, f32)> {
        let [w, h] = grid.size();
        let dims = self.dims;
        let want =
            NonZero::new(CANDIDATES.min(self.sig.len() / dims)).expect("a material has texels");
        (0..w * h)
            .into_par_iter()
            .map_init(
                || vec![0.0f32; dims],
                |sig, p| {
                    grid.signature(p % w, p / w, sig);
                    let q = tree_point(&self.components.project(sig));
                    let mut best = (0usize, f32::INFINITY);
                    for nn in self.tree.nearest_n::<SquaredEuclidean>(&q, want) {
                        let i = nn.item as usize;
                        let d: f32 = self.sig[i * dims..][..dims]
                            .iter()
                            .zip(sig.iter())
                            .map(|(a, b)| (a - b) * (a - b))
                            .sum();
                        if d < best.1 || (d == best.1 && i < best.0) {
                            best = (i, d);
                        }
                    }
                    best
                },
            )
            .collect()
    }
}

/// Photometric stereo over a set of directions (each image lit and seen
/// along one): the least-squares solution of `L g = I`, g = albedo · n,
/// brightness ∝ n · l (Lambert).
struct Stereo {
    /// (Lᵀ L)⁻¹ Lᵀ, 3 × images, row-major.
    solve: Vec<[f64; 3]>,
}

/// Iterations of the height integration, at least (4 × the grid's width +
/// height, if more).
const HEIGHT_ITERATIONS: usize = 1000;
/// The integration's residual, relative to its start, at which it stops.
const HEIGHT_RESIDUAL: f64 = 1e-6;
/// Steepest slope a normal may give (80° from the surface normal): a
/// texel's normal comes from brightness at ≤ 80°, and a steeper one is
/// noise.
const MAX_SLOPE: f64 = 5.67;

impl Stereo {
    fn new(directions: &[[f64; 3]]) -> Result<Stereo, BuildError> {
        let mut ata = [0.0f64; 9];
        for d in directions {
            for i in 0..3 {
                for j in 0..3 {
                    ata[3 * i + j] += d[i] * d[j];
                }
            }
        }
        // Three directions not in one plane give a well-posed system; the
        // smallest eigenvalue says how well.
        let (values, vectors) = super::linalg::symmetric_eigen(3, &ata);
        let smallest = values.iter().copied().fold(f64::INFINITY, f64::min);
        if directions.len() < 3 || smallest.is_nan() || smallest <= 1e-3 * directions.len() as f64 {
            return Err(BuildError::Input(format!(
                "the height signature needs photometric stereo: at least 3 direct images whose \
                 directions are not in one plane (these {} span {:.1e} in their narrowest \
                 direction)",
                directions.len(),
                smallest.max(0.0)
            )));
        }
        let inv: [f64; 9] = std::array::from_fn(|ij| {
            let (i, j) = (ij / 3, ij % 3);
            values.iter().zip(&vectors).map(|(l, v)| v[i] * v[j] / l).sum()
        });
        let solve = directions
            .iter()
            .map(|d| std::array::from_fn(|i| (0..3).map(|j| inv[3 * i + j] * d[j]).sum()))
            .collect();
        Ok(Stereo { solve })
    }

    /// The height map (mm, up to a constant) of a `w × h` grid `pitch` mm
    /// apart seen in `images` (one per direction): slopes from the
    /// normals, then the heights the patent's iteration converges to —
    /// from zero, each point's height made the mean over its neighbours of
    /// their height less the rise the slopes predict, until nothing
    /// changes: the least-squares fit of the heights' differences to the
    /// slopes. Conjugate gradients reach it in far fewer steps than that
    /// iteration (which, stopped early, leaves the heights of one place
    /// depending on how far it lies from the border).
    fn heights(&self, images: &[Vec<[f64; 3]>], w: usize, h: usize, pitch: f64) -> Vec<f32> {
        let slopes: Vec<[f64; 2]> = (0..w * h)
            .into_par_iter()
            .map(|p| {
                let mut g = [0.0f64; 3];
                for (img, m) in images.iter().zip(&self.solve) {
                    let i = img[p].iter().sum::<f64>() / 3.0;
                    for c in 0..3 {
                        g[c] += m[c] * i;
                    }
                }
                if g[2] > 0.0 {
                    [-g[0] / g[2], -g[1] / g[2]].map(|s| s.clamp(-MAX_SLOPE, MAX_SLOPE) * pitch)
                } else {
                    [0.0; 2]
                }
            })
            .collect();
        // Each point's equation: its height is the mean over its neighbours
        // of their height less the rise to them (the mean of the two
        // points' slopes along the step) — A h = b, A the grid's Laplacian.
        let neighbours = |p: usize| {
            let (x, y) = (p % w, p / w);
            [
                (x > 0).then(|| (p - 1, 0, -1.0)),
                (x + 1 < w).then(|| (p + 1, 0, 1.0)),
                (y > 0).then(|| (p - w, 1, -1.0)),
                (y + 1 < h).then(|| (p + w, 1, 1.0)),
            ]
            .into_iter()
            .flatten()
        };
        let b: Vec<f64> = (0..w * h)
            .into_par_iter()
            .map(|p| {
                neighbours(p)
                    .map(|(q, axis, sign)| -sign * 0.5 * (slopes[p][axis] + slopes[q][axis]))
                    .sum()
            })
            .collect();
        let laplacian = |v: &[f64], out: &mut [f64]| {
            out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
                for (x, o) in row.iter_mut().enumerate() {
                    let p = y * w + x;
                    *o = neighbours(p).map(|(q, _, _)| v[p] - v[q]).sum();
                }
            })
        };
        // Dot products summed by rows, in order: the same answer on any
        // number of threads.
        let dot = |a: &[f64], b: &[f64]| -> f64 {
            let rows: Vec<f64> = a
                .par_chunks(w)
                .zip(b.par_chunks(w))
                .map(|(a, b)| a.iter().zip(b).map(|(x, y)| x * y).sum())
                .collect();
            rows.iter().sum()
        };
        // Conjugate gradients from zero (A is symmetric and positive
        // semi-definite; b sums to zero, so the system is consistent).
        let mut height = vec![0.0f64; w * h];
        let mut r = b.clone();
        let mut d = r.clone();
        let mut ad = vec![0.0f64; w * h];
        let mut rr = dot(&r, &r);
        let goal = HEIGHT_RESIDUAL * HEIGHT_RESIDUAL * rr;
        for _ in 0..HEIGHT_ITERATIONS.max(4 * (w + h)) {
            if rr <= goal || rr == 0.0 {
                break;
            }
            laplacian(&d, &mut ad);
            let dad = dot(&d, &ad);
            if dad.is_nan() || dad <= 0.0 {
                break;
            }
            let alpha = rr / dad;
            height.par_iter_mut().zip(&d).for_each(|(x, di)| *x += alpha * di);
            r.par_iter_mut().zip(&ad).for_each(|(x, a)| *x -= alpha * a);
            let next = dot(&r, &r);
            let beta = next / rr;
            rr = next;
            d.par_iter_mut().zip(&r).for_each(|(x, ri)| *x = ri + beta * *x);
        }
        height.into_iter().map(|v| v as f32).collect()
    }
}

/// The factor that takes a direct image's values ÷ its exposure to
/// f · cos θi: the white reference's radiance over its central half's mean.
fn white_scale(
    frame: &Frame,
    w: &scanner_formats::direct::WhiteImage,
) -> Result<[f64; 3], BuildError> {
    let (fw, fh) = (frame.width as usize, frame.height as usize);
    let (x0, x1, y0, y1) = (fw / 4, (3 * fw).div_ceil(4), fh / 4, (3 * fh).div_ceil(4));
    let mut sum = [0.0f64; 3];
    for y in y0..y1 {
        for x in x0..x1 {
            for (c, s) in sum.iter_mut().enumerate() {
                *s += frame.rgb[3 * (y * fw + x) + c] as f64;
            }
        }
    }
    let n = ((x1 - x0) * (y1 - y0)).max(1) as f64;
    let cos = w.direction[2] / w.direction.iter().map(|x| x * x).sum::<f64>().sqrt();
    let radiance = w.albedo / std::f64::consts::PI * cos;
    let mut out = [0.0; 3];
    for c in 0..3 {
        let level = sum[c] / n / w.exposure_s;
        if level.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
            return Err(BuildError::Input(format!(
                "{}: channel {c} is black: not a white reference",
                w.file
            )));
        }
        out[c] = radiance / level;
    }
    Ok(out)
}

/// `frame` averaged over each cell of a `w × h` grid laid over it (each
/// pixel weighted by the share of its area inside the cell).
pub fn area_resample(frame: &Frame, w: usize, h: usize) -> Vec<[f64; 3]> {
    let (fw, fh) = (frame.width as usize, frame.height as usize);
    let xs = area_weights(fw, w);
    let ys = area_weights(fh, h);
    (0..w * h)
        .into_par_iter()
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let mut acc = [0.0f64; 3];
            let mut total = 0.0;
            for &(py, wy) in &ys[y] {
                for &(px, wx) in &xs[x] {
                    let wgt = wx * wy;
                    let p = 3 * (py * fw + px);
                    for (a, &v) in acc.iter_mut().zip(&frame.rgb[p..p + 3]) {
                        *a += wgt * v as f64;
                    }
                    total += wgt;
                }
            }
            acc.map(|v| v / total)
        })
        .collect()
}

/// For each of `n_out` equal cells over `n_in` pixels: the pixels it
/// overlaps and how much of each (in pixels).
fn area_weights(n_in: usize, n_out: usize) -> Vec<Vec<(usize, f64)>> {
    let step = n_in as f64 / n_out as f64;
    (0..n_out)
        .map(|o| {
            let (a, b) = (o as f64 * step, (o + 1) as f64 * step);
            let first = a.floor() as usize;
            let last = (b.ceil() as usize).min(n_in);
            (first..last)
                .filter_map(|p| {
                    let cover = (b.min(p as f64 + 1.0) - a.max(p as f64)).max(0.0);
                    (cover > 1e-12).then_some((p, cover))
                })
                .collect()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The tree's coordinates keep the principal components' squared
    /// distances, and hold the leading ones twice, first.
    #[test]
    fn the_tree_s_coordinates_keep_the_distances() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let mut point = || -> [f32; PCA_DIMS] {
            std::array::from_fn(|i| rng.random_range(-1.0..1.0) * (13 - i) as f32)
        };
        let d2 =
            |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f32>();
        for _ in 0..100 {
            let (a, b) = (point(), point());
            let (ta, tb) = (tree_point(&a), tree_point(&b));
            assert!((d2(&ta, &tb) - d2(&a, &b)).abs() <= 1e-5 * d2(&a, &b), "{a:?} {b:?}");
            for i in 0..DOUBLED {
                assert_eq!(ta[i], ta[i + DOUBLED]);
                assert!((ta[i] - a[i] * std::f32::consts::FRAC_1_SQRT_2).abs() < 1e-6);
            }
            assert_eq!(ta[2 * DOUBLED..], a[DOUBLED..]);
        }
    }

    /// A piece whose map the machine cannot hold is refused before anything
    /// is allocated; the demo's 80 mm piece passes.
    #[test]
    fn a_piece_beyond_memory_is_refused_up_front() {
        let gb = 1_000_000_000u64;
        // Four images: ≈ 0.65 GB for 2016² texels (0.76 GB peak measured,
        // the material and the sample's grid included).
        let need = |side: usize| enlarge_memory(side * side, 4);
        assert!((0.6..0.7).contains(&(need(2016) as f64 / gb as f64)));
        assert!(check_memory(need(404), [404; 2], [80.0; 2], Some(gb)).is_ok());
        assert!(check_memory(need(16384), [16384; 2], [3250.0; 2], None).is_ok());
        let err = check_memory(need(16384), [16384; 2], [3250.0; 2], Some(24 * gb))
            .unwrap_err()
            .to_string();
        assert!(err.contains("3250 × 3250 mm is 16384 × 16384 texels"), "{err}");
        assert!(err.contains("needs ≈ 42.9 GB; 24.0 GB of memory is available"), "{err}");
    }

    #[test]
    fn area_resampling_keeps_the_mean_at_any_ratio() {
        let (w, h) = (37u32, 23u32);
        let rgb: Vec<f32> = (0..w * h * 3).map(|i| ((i * 7919) % 101) as f32 / 100.0).collect();
        let f = Frame { width: w, height: h, rgb };
        let mean_in: f64 = f.rgb.iter().map(|&v| v as f64).sum::<f64>() / f.rgb.len() as f64;
        for (ow, oh) in [(37, 23), (10, 7), (5, 23), (74, 46), (13, 51)] {
            let out = area_resample(&f, ow, oh);
            let mean_out: f64 = out.iter().flatten().sum::<f64>() / (out.len() * 3) as f64;
            assert!((mean_out - mean_in).abs() < 1e-9, "{ow} × {oh}: {mean_out} vs {mean_in}");
        }
        // At the same size every pixel is itself.
        let same = area_resample(&f, 37, 23);
        for (v, px) in same.iter().zip(f.rgb.chunks_exact(3)) {
            for (a, &b) in v.iter().zip(px) {
                assert!((a - b as f64).abs() < 1e-6);
            }
        }
        // Halving averages 2 × 2 blocks.
        let g = Frame { width: 4, height: 2, rgb: (0..24).map(|i| i as f32).collect() };
        let half = area_resample(&g, 2, 1);
        assert_eq!(half[0], [(0.0 + 3.0 + 12.0 + 15.0) / 4.0, 8.5, 9.5]);
    }

    /// The four mirror directions nearest the axis of the default scanner:
    /// 15° from the normal, a quarter turn apart.
    fn ring() -> Vec<[f64; 3]> {
        let t = 15f64.to_radians();
        (0..4)
            .map(|k| {
                let a = k as f64 * std::f64::consts::FRAC_PI_2 + 0.3;
                [t.sin() * a.cos(), t.sin() * a.sin(), t.cos()]
            })
            .collect()
    }

    /// Images of a Lambertian surface of height `z(x, y)` (mm, x and y in
    /// mm) and albedo `rho(x, y)` over a `w × h` grid `pitch` mm apart, lit
    /// along `dirs`.
    fn lambert(
        dirs: &[[f64; 3]],
        w: usize,
        h: usize,
        pitch: f64,
        z: &dyn Fn(f64, f64) -> f64,
        rho: &dyn Fn(f64, f64) -> f64,
    ) -> Vec<Vec<[f64; 3]>> {
        dirs.iter()
            .map(|d| {
                (0..w * h)
                    .map(|p| {
                        let (x, y) = ((p % w) as f64 * pitch, (p / w) as f64 * pitch);
                        let e = 1e-5;
                        let gx = (z(x + e, y) - z(x - e, y)) / (2.0 * e);
                        let gy = (z(x, y + e) - z(x, y - e)) / (2.0 * e);
                        let len = (gx * gx + gy * gy + 1.0).sqrt();
                        let cos = (-gx * d[0] - gy * d[1] + d[2]) / len;
                        [rho(x, y) * cos.max(0.0); 3]
                    })
                    .collect()
            })
            .collect()
    }

    #[test]
    fn photometric_stereo_and_integration_recover_a_height_field() {
        let dirs = ring();
        let stereo = Stereo::new(&dirs).unwrap();
        let (w, h, pitch) = (96usize, 80usize, 0.2);
        // Bumps of 1–4 mm and an albedo that varies on its own.
        let z = |x: f64, y: f64| {
            0.05 * (x * 2.1).sin() * (y * 1.3).cos() + 0.03 * (x * 0.7 + y * 1.9).sin()
        };
        let rho = |x: f64, y: f64| 0.3 + 0.2 * (x * 5.0 + y * 3.0).sin().abs();
        let images = lambert(&dirs, w, h, pitch, &z, &rho);
        let heights = stereo.heights(&images, w, h, pitch);
        // Neighbour differences (the signature's values) against the
        // truth's, over the interior.
        let (mut err, mut norm) = (0.0f64, 0.0f64);
        for y in 1..h - 1 {
            for x in 1..w - 1 {
                let p = y * w + x;
                let (px, py) = (x as f64 * pitch, y as f64 * pitch);
                for (q, dx, dy) in [(p + 1, pitch, 0.0), (p + w, 0.0, pitch)] {
                    let want = z(px + dx, py + dy) - z(px, py);
                    let got = (heights[q] - heights[p]) as f64;
                    err += (got - want).powi(2);
                    norm += want * want;
                }
            }
        }
        let rel = (err / norm).sqrt();
        assert!(rel < 0.02, "relative RMS error of the neighbour differences {rel}");
        // The albedo and the scale do not enter: ten times brighter, the
        // same heights.
        let brighter: Vec<Vec<[f64; 3]>> =
            images.iter().map(|im| im.iter().map(|v| v.map(|c| 10.0 * c)).collect()).collect();
        let again = stereo.heights(&brighter, w, h, pitch);
        for (a, b) in heights.iter().zip(&again) {
            assert!((a - b).abs() < 1e-4, "{a} {b}");
        }
    }

    #[test]
    fn heights_need_three_directions_not_in_one_plane() {
        let t = 15f64.to_radians();
        let plane: Vec<[f64; 3]> =
            [-1.0, 0.0, 1.0].iter().map(|&k| [k * t.sin(), 0.0, (k * t).cos()]).collect();
        let plane: Vec<[f64; 3]> = plane
            .iter()
            .map(|d| {
                let l = (d[0] * d[0] + d[2] * d[2]).sqrt();
                [d[0] / l, 0.0, d[2] / l]
            })
            .collect();
        for dirs in [plane, ring()[..2].to_vec()] {
            let Err(BuildError::Input(e)) = Stereo::new(&dirs) else { panic!("{dirs:?}") };
            assert!(e.contains("not in one plane"), "{e}");
        }
        assert!(Stereo::new(&ring()[..3]).is_ok());
    }
}
