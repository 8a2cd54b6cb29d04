//! A photograph of a flat piece, taken in perspective, rectified onto the
//! piece: the direct images `scanner enlarge` reads are pictures of the
//! piece over its own coordinates (docs/direct-images.md, "Rectifying
//! photographs").
//!
//! The piece is a plane, so a pinhole camera sees it through a homography:
//! the four corners the user marks in the photograph fix it. A real lens
//! bends that pinhole image ([`super::lens`]): with the lens given, the
//! homography maps onto the pinhole image and the lens onto the
//! photograph. Each output pixel averages the photograph over its
//! footprint on the piece — k × k points spread over the pixel, k from the
//! photograph's pixels per output pixel there, each read by the region
//! images' edge-aware Catmull–Rom filter through the lens
//! ([`ViewSampler::region_filter_through`]), so that nothing outside the
//! marked quadrilateral (the holder, the table) mixes into the piece's
//! border.

use rayon::prelude::*;

use super::BuildError;
use super::calibrate::ViewSampler;
use super::lens::{FrameMap, Lens, LensChoice, LensMap};
use super::linalg::Homography;
use crate::camera::Frame;

/// The largest output side, px (as for exported maps).
pub const MAX_SIDE: usize = super::export::MAX_SIDE;
/// Points per output pixel along each axis, at most.
pub const MAX_SUPERSAMPLING: usize = 8;
/// The largest piece side, mm.
pub const MAX_SIZE_MM: f64 = 10_000.0;

/// What to rectify.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RectifyOptions {
    /// The piece's corners in the photograph, px (pixel (c, r) spans
    /// [c, c + 1) × [r, r + 1)), in the order of the piece's (u, v) = (0, 0),
    /// (1, 0), (1, 1), (0, 1): u along the output's columns, v down its rows.
    pub corners: [[f64; 2]; 4],
    /// The piece's width (along u) and height (along v), mm.
    pub size_mm: [f64; 2],
    /// Output pixels per mm; `None`: the photograph's own density where it
    /// resolves the piece least.
    pub px_per_mm: Option<f64>,
    /// The camera lens' distortion ([`Lens::PINHOLE`]: none).
    pub lens: Lens,
}

/// The piece's corners in a photograph: marked, or found in it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Corners {
    /// As [`RectifyOptions::corners`].
    Marked([[f64; 2]; 4]),
    /// Marked, then moved onto the piece's edges by
    /// [`super::corners::refine_corners`].
    Refined([[f64; 2]; 4]),
    /// Found by [`super::corners::find_corners`], uv (0, 0) there.
    Auto(super::corners::Origin),
}

/// The corners in a photograph and its lens ([`Corners::locate`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Located {
    /// As [`RectifyOptions::corners`].
    pub corners: [[f64; 2]; 4],
    /// As [`RectifyOptions::lens`].
    pub lens: Lens,
    /// What [`super::corners`] found, if it looked.
    pub found: Option<super::corners::FoundCorners>,
}

impl Corners {
    /// The corners in `photo` and its lens: as marked, or found or refined
    /// there (with what [`super::corners`] found). Only found or refined
    /// corners estimate the lens.
    pub fn locate(self, photo: &Frame, lens: LensChoice) -> Result<Located, BuildError> {
        let found = match (self, lens) {
            (Corners::Marked(corners), LensChoice::Known(lens)) => {
                return Ok(Located { corners, lens, found: None });
            }
            (Corners::Marked(_), LensChoice::Estimate) => {
                return Err(BuildError::Input(
                    "the lens is estimated from the piece's sides: its corners found or refined, \
                     not only marked"
                        .into(),
                ));
            }
            (Corners::Auto(origin), _) => super::corners::find_corners(photo, origin, lens)?,
            (Corners::Refined(marked), _) => super::corners::refine_corners(photo, marked, lens)?,
        };
        Ok(Located { corners: found.corners, lens: found.lens, found: Some(found) })
    }
}

/// What [`rectify`] made.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RectifyReport {
    /// Output pixels per mm.
    pub px_per_mm: f64,
    /// The photograph's pixels per mm on the piece, least and most (along
    /// the piece's axes, at its corners and centre).
    pub photo_px_per_mm: [f64; 2],
    /// Points averaged per output pixel along each axis.
    pub supersampling: usize,
}

impl RectifyOptions {
    /// The options in range for a photograph of `width × height` px, the
    /// homography from the piece's uv to the pinhole image's pixels and
    /// the lens from those to the photograph's.
    pub fn check(&self, width: u32, height: u32) -> Result<(Homography, LensMap), String> {
        let [w, h] = self.size_mm;
        if !(w.is_finite() && h.is_finite() && w > 0.0 && h > 0.0)
            || w > MAX_SIZE_MM
            || h > MAX_SIZE_MM
        {
            return Err(format!("--size-mm {w},{h}: each in (0, {MAX_SIZE_MM}] mm"));
        }
        if let Some(d) = self.px_per_mm
            && !(d.is_finite() && d > 0.0)
        {
            return Err(format!("--px-per-mm {d}: a density > 0"));
        }
        check_corners(&self.corners, width, height)?;
        let lens = LensMap::new(self.lens, width, height)?;
        let pinhole = self.corners.map(|c| lens.in_pinhole(c));
        let square = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
        let h = Homography::fit(&square, &pinhole)
            .ok_or_else(|| format!("corners {:?}: no homography fits them", self.corners))?;
        Ok((h, lens))
    }
}

/// Corners within a `width × height` px photograph that make a convex
/// quadrilateral of ≥ 16 px², in order around it (either way round).
pub fn check_corners(corners: &[[f64; 2]; 4], width: u32, height: u32) -> Result<(), String> {
    for (k, c) in corners.iter().enumerate() {
        let inside = c.iter().all(|v| v.is_finite())
            && (0.0..=width as f64).contains(&c[0])
            && (0.0..=height as f64).contains(&c[1]);
        if !inside {
            return Err(format!(
                "corner {k} at ({}, {}) px lies outside the {width} × {height} px photograph",
                c[0], c[1]
            ));
        }
    }
    // A convex quadrilateral, its corners in order around it (either
    // way round), of some size.
    let cross: Vec<f64> = (0..4)
        .map(|k| {
            let [a, b, c] = [0, 1, 2].map(|i| corners[(k + i) % 4]);
            (b[0] - a[0]) * (c[1] - b[1]) - (b[1] - a[1]) * (c[0] - b[0])
        })
        .collect();
    let area = 0.5
        * (0..4)
            .map(|k| {
                let (a, b) = (corners[k], corners[(k + 1) % 4]);
                a[0] * b[1] - b[0] * a[1]
            })
            .sum::<f64>()
            .abs();
    if !(cross.iter().all(|&c| c > 0.0) || cross.iter().all(|&c| c < 0.0)) || area < 16.0 {
        return Err(format!(
            "corners {:?}: not a convex quadrilateral of ≥ 16 px² with its corners in order \
             around it ((0, 0), (1, 0), (1, 1), (0, 1) of the piece)",
            corners
        ));
    }
    Ok(())
}

/// A photograph's values: as many as its pixels' channels, each a radiance
/// ≥ 0.
pub fn check_photo(photo: &Frame) -> Result<(), BuildError> {
    let n = photo.width as usize * photo.height as usize * 3;
    if photo.rgb.len() != n || photo.width == 0 || photo.height == 0 {
        return Err(BuildError::Input(format!(
            "the {} × {} px photograph holds {} values, not {n}",
            photo.width,
            photo.height,
            photo.rgb.len()
        )));
    }
    if let Some(i) = photo.rgb.iter().position(|v| !(v.is_finite() && *v >= 0.0)) {
        let p = i / 3;
        return Err(BuildError::Input(format!(
            "pixel ({}, {}) of the photograph holds {}, not a radiance ≥ 0",
            p % photo.width as usize,
            p / photo.width as usize,
            photo.rgb[i]
        )));
    }
    Ok(())
}

/// `photo` rectified onto the piece: W × H px, W = width · density and
/// H = height · density (rounded, ≥ 1), pixel (c, r) covering the piece's
/// point ((c + ½)/W · width, (r + ½)/H · height) mm.
pub fn rectify(photo: &Frame, opts: &RectifyOptions) -> Result<(Frame, RectifyReport), BuildError> {
    let (h, lens) = opts.check(photo.width, photo.height).map_err(BuildError::Input)?;
    check_photo(photo)?;
    // The photograph's px per mm along u and v at the corners and centre.
    let [wmm, hmm] = opts.size_mm;
    let densities: Vec<[f64; 2]> = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [0.5, 0.5]]
        .iter()
        .map(|&p| {
            let j = mul(lens.jacobian(h.apply(p)), h.jacobian(p));
            [j[0][0].hypot(j[1][0]) / wmm, j[0][1].hypot(j[1][1]) / hmm]
        })
        .collect();
    let least = densities.iter().flatten().copied().fold(f64::INFINITY, f64::min);
    let most = densities.iter().flatten().copied().fold(0.0, f64::max);
    let px_per_mm = opts.px_per_mm.unwrap_or(least);
    let side = |mm: f64| (mm * px_per_mm).round().max(1.0);
    let (w, ht) = (side(wmm), side(hmm));
    if w > MAX_SIDE as f64 || ht > MAX_SIDE as f64 {
        return Err(BuildError::Input(format!(
            "{wmm} × {hmm} mm at {px_per_mm:.3} px/mm is {w} × {ht} px: at most {MAX_SIDE} a side \
             (lower --px-per-mm)"
        )));
    }
    let (w, ht) = (w as usize, ht as usize);
    // Enough points that every photograph pixel under an output pixel
    // counts: the most photograph px per output px, rounded up.
    let k = ((most / px_per_mm).ceil() as usize).clamp(1, MAX_SUPERSAMPLING);
    let sampler = ViewSampler::new(h);
    let dims = [photo.width as usize, photo.height as usize];
    let mut rgb = vec![0.0f32; w * ht * 3];
    rgb.par_chunks_mut(w * 3).enumerate().for_each(|(r, row)| {
        for (c, px) in row.chunks_exact_mut(3).enumerate() {
            let mut acc = [0.0f64; 3];
            for a in 0..k {
                for b in 0..k {
                    let uv = [
                        (c as f64 + (a as f64 + 0.5) / k as f64) / w as f64,
                        (r as f64 + (b as f64 + 0.5) / k as f64) / ht as f64,
                    ];
                    let v = sampler.region_filter_through(&lens, dims, uv).apply(photo);
                    for i in 0..3 {
                        acc[i] += v[i];
                    }
                }
            }
            // Catmull–Rom overshoots at sharp edges: radiance stays ≥ 0.
            for i in 0..3 {
                px[i] = (acc[i] / (k * k) as f64).max(0.0) as f32;
            }
        }
    });
    let report = RectifyReport { px_per_mm, photo_px_per_mm: [least, most], supersampling: k };
    Ok((Frame { width: w as u32, height: ht as u32, rgb }, report))
}

/// The 2 × 2 product a · b.
fn mul(a: [[f64; 2]; 2], b: [[f64; 2]; 2]) -> [[f64; 2]; 2] {
    std::array::from_fn(|r| std::array::from_fn(|c| a[r][0] * b[0][c] + a[r][1] * b[1][c]))
}
