//! Finding a flat piece's four corners in a photograph of it lying on a
//! plain background darker or lighter than all of it (`scanner rectify
//! --corners auto`; docs/direct-images.md, "Finding the corners").
//!
//! 1. The photograph's luminance (the channels' mean, as calibration uses),
//!    lightly blurred, is split into two levels by Otsu's threshold on its
//!    logarithm: radiance spans decades, and a textured piece's dark gaps
//!    sit between the two levels.
//! 2. The largest 8-connected bright component that lies whole in the
//!    photograph and is a quadrilateral is the piece (if that fails, the
//!    largest such dark one: a dark piece on a white table; if that fails
//!    too, or its quadrilateral is only part of a larger one, the largest
//!    region distinct from the background either way: a glossy piece's
//!    highlights and shade); larger ones that reach the photograph's edge
//!    or are of another shape are passed over. Its convex hull gives the
//!    quadrilateral of largest area with corners on the hull: the piece's
//!    outline to a pixel or two.
//! 3. Each side is then found to a fraction of a pixel: across it, every
//!    pixel along its length, the unblurred luminance's outermost crossing
//!    of the level halfway between the piece just inside and the
//!    background just outside; a line fitted to the crossings (total least
//!    squares, points beyond three robust deviations dropped, refitted).
//!    Twice, the second time from the first's corners. The corners are
//!    where adjacent lines meet.
//!
//! A pinhole photograph shows the piece's straight sides straight. With a
//! lens given ([`super::lens`]), the profiles are read through it: the
//! sides are lines of the pinhole image, curves of the photograph. With
//! the lens to be estimated, its k1 is the one that makes the sides'
//! edge points straightest (the plumb-line method, on the piece's own
//! four sides), and the sides are fitted again through it, three times.
//! Sides that are still not straight are refused by their residual and
//! their bow.

use super::BuildError;
use super::lens::{FrameMap, Lens, LensChoice, LensMap};
use super::plane::Plane;
use crate::camera::Frame;

/// Where, in the photograph, the piece's corner uv (0, 0) lies; the others
/// follow counter-clockwise as one sees the photograph (a camera shows the
/// piece's face without mirroring it): (1, 0), (1, 1), (0, 1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Origin {
    /// The piece face up, u to the right and v up the photograph (the
    /// simulator's photographs).
    BottomLeft,
    /// Turned a quarter: u up, v to the left.
    BottomRight,
    /// Turned a half: u to the left, v down.
    TopRight,
    /// Turned three quarters: u down, v to the right.
    TopLeft,
}

impl Origin {
    /// Every origin, by its command-line name.
    pub const ALL: [(&'static str, Origin); 4] = [
        ("bottom-left", Origin::BottomLeft),
        ("bottom-right", Origin::BottomRight),
        ("top-right", Origin::TopRight),
        ("top-left", Origin::TopLeft),
    ];

    /// By its command-line name.
    pub fn from_name(name: &str) -> Option<Origin> {
        Self::ALL.iter().find(|(n, _)| *n == name).map(|&(_, o)| o)
    }

    /// How far `p` (px) lies towards this corner of the photograph, along
    /// its diagonal (larger: nearer).
    fn towards(self, p: [f64; 2]) -> f64 {
        match self {
            Origin::BottomLeft => p[1] - p[0],
            Origin::BottomRight => p[0] + p[1],
            Origin::TopRight => p[0] - p[1],
            Origin::TopLeft => -p[0] - p[1],
        }
    }
}

/// What [`find_corners`] found.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FoundCorners {
    /// The piece's corners uv (0, 0), (1, 0), (1, 1), (0, 1), px (pixel
    /// (c, r) spans [c, c + 1) × [r, r + 1)): what
    /// [`super::rectify::RectifyOptions::corners`] takes.
    pub corners: [[f64; 2]; 4],
    /// Whether the piece is brighter or darker than its background.
    pub polarity: Polarity,
    /// How many times the piece's median luminance stands out of the
    /// background's, just inside and outside its outline (≥ 1).
    pub contrast: f64,
    /// RMS distance of the sides' kept edge points from their lines, px.
    pub edge_rms_px: f64,
    /// The most a side bows: its middle third's median distance from its
    /// line against its outer thirds', px.
    pub bow_px: f64,
    /// Edge points the four lines were fitted to.
    pub edge_points: usize,
    /// The lens the sides are straight through: as given, or estimated.
    pub lens: Lens,
    /// The estimated lens' k1's standard error, from how well the sides'
    /// edge points fix it (`None`: the lens was given).
    pub lens_k1_sigma: Option<f64>,
    /// Larger regions of the piece's brightness passed over: they reach
    /// the photograph's edge or are not quadrilaterals (0 with marked
    /// corners).
    pub passed_over: usize,
}

/// The least contrast between piece and background.
pub const MIN_CONTRAST: f64 = 2.0;
/// The largest RMS distance of a side's edge points from its line, px.
pub const MAX_EDGE_RMS_PX: f64 = 0.75;
/// The most a side may bow ([`FoundCorners::bow_px`]), px.
pub const MAX_BOW_PX: f64 = 0.5;
/// The smallest side, px.
pub const MIN_SIDE_PX: f64 = 16.0;
/// The fewest pixels of a region that may be the piece (a square of the
/// smallest side).
const MIN_REGION_PX: usize = (MIN_SIDE_PX * MIN_SIDE_PX) as usize;
/// The least share of the quadrilateral the piece's component covers (and
/// its reciprocal the most).
const MIN_FILL: f64 = 0.85;
/// Blur of the luminance before thresholding, px.
const MASK_SIGMA_PX: f64 = 1.0;
/// Half the span of an edge profile, px, in the first and second pass.
const PROFILE_HALF_PX: [f64; 2] = [4.0, 2.5];
/// Steps along an edge profile, px.
const PROFILE_STEP_PX: f64 = 0.25;
/// Half the window about a level's crossing over which an edge is placed
/// by its area, px: a pixel-integrated edge, interpolated, spans ±1.5 px.
const EDGE_WINDOW_PX: f64 = 1.5;
/// Steps of the profile just inside that window that must be flat for the
/// area to place the edge (2 px)…
const EDGE_FLAT_STEPS: usize = 8;
/// …within this share of the edge's contrast…
const EDGE_FLAT: f64 = 0.05;
/// …at this share of a pass's profiles, or else every edge is placed by
/// its level's crossing.
const EDGE_FLAT_SHARE: f64 = 0.9;
/// The least piece-over-background ratio across one edge profile for its
/// crossing to count.
const MIN_LOCAL_CONTRAST: f64 = 1.5;
/// How much larger (by area) the quadrilateral of a piece differing from
/// its background either way must be than the one found brighter or
/// darker to be taken for the piece instead.
const MIXED_LARGER: f64 = 1.2;
/// Gaps in a distinct region up to twice this wide are closed, px.
const CLOSE_PX: usize = 2;
/// The photograph's border the background's level is read on, px.
const BORDER_PX: usize = 2;

/// Which way the piece differs from its background.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Polarity {
    /// The piece brighter than its background (a dark holder).
    Brighter,
    /// The piece darker than its background (a white table).
    Darker,
    /// Parts of the piece brighter and parts darker than its background
    /// (a glossy textured piece: its highlights above a black holder's
    /// level, its shade below a white card's): each edge profile the way
    /// its own two sides differ.
    Mixed,
}

impl Polarity {
    /// How many times the piece stands out of the background.
    fn ratio(self, piece: f64, background: f64) -> f64 {
        match self {
            Polarity::Brighter => piece / background,
            Polarity::Darker => background / piece,
            Polarity::Mixed => (piece / background).max(background / piece),
        }
    }

    /// Brighter or darker: as `piece` differs from `background` if mixed.
    fn at(self, piece: f64, background: f64) -> Polarity {
        match self {
            Polarity::Mixed if piece >= background => Polarity::Brighter,
            Polarity::Mixed => Polarity::Darker,
            p => p,
        }
    }

    /// How the piece compares with its background, in words: `brighter`,
    /// `darker` or `brighter and darker` (than the background).
    pub fn comparison(self) -> &'static str {
        match self {
            Polarity::Brighter => "brighter",
            Polarity::Darker => "darker",
            Polarity::Mixed => "brighter and darker",
        }
    }

    /// Its regions' name: `bright`, `dark` or `distinct`.
    pub fn name(self) -> &'static str {
        match self {
            Polarity::Brighter => "bright",
            Polarity::Darker => "dark",
            Polarity::Mixed => "distinct",
        }
    }
}

/// The piece's corners in `photo` (linear RGB, the piece brighter or
/// darker than a plain background all round it), its uv (0, 0) at
/// `origin`, its sides straight through `lens`. A bright piece is looked
/// for first, then a dark one, then one that differs from the background
/// either way ([`Polarity::Mixed`]).
pub fn find_corners(
    photo: &Frame,
    origin: Origin,
    lens: LensChoice,
) -> Result<FoundCorners, BuildError> {
    super::rectify::check_photo(photo)?;
    let lum = luminance(photo);
    let fail = |m: String| {
        BuildError::Input(format!(
            "finding the piece's corners: {m} (or mark them: --corners X0,Y0,…,X3,Y3)"
        ))
    };
    let blurred = lum.blurred(MASK_SIGMA_PX);
    let Some(above) = bright(&blurred) else {
        return Err(fail("the photograph is uniform".into()));
    };
    let distinct = distinct(&blurred);
    // A piece both brighter and darker than its background shows only a
    // part of itself as either (a square of a checker at its corner, say):
    // where the piece differing either way makes a larger quadrilateral,
    // that is the piece.
    let larger = |found: &FoundCorners| {
        first_quad(&distinct, lum.width, lum.height, Polarity::Mixed)
            .is_some_and(|q| shoelace(&q).abs() > MIXED_LARGER * shoelace(&found.corners).abs())
    };
    let mixed = || find_in(&lum, &distinct, Polarity::Mixed, origin, lens);
    let either =
        |polarity: Polarity, mask: &[bool]| match find_in(&lum, mask, polarity, origin, lens) {
            Ok(found) if larger(&found) => Ok(mixed().unwrap_or(found)),
            other => other,
        };
    let as_bright = match either(Polarity::Brighter, &above) {
        Ok(found) => return Ok(found),
        Err(why) => why,
    };
    let below: Vec<bool> = above.iter().map(|a| !a).collect();
    let as_dark = match either(Polarity::Darker, &below) {
        Ok(found) => return Ok(found),
        Err(why) => why,
    };
    mixed().map_err(|as_mixed| {
        fail(format!(
            "as a piece brighter than its background: {as_bright}; as a piece darker than its \
             background: {as_dark}; as a piece differing from it either way: {as_mixed}"
        ))
    })
}

/// The first region of `mask` that may be the piece ([`find_in`]'s order):
/// its quadrilateral before refinement.
fn first_quad(mask: &[bool], w: usize, h: usize, polarity: Polarity) -> Option<[[f64; 2]; 4]> {
    components(mask, w, h, MIN_REGION_PX).1.find_map(|piece| outline(&piece, polarity).ok())
}

/// Pixels that differ from the background by more than
/// [`MIN_LOCAL_CONTRAST`] times either way, the background's level being
/// the median of the photograph's border (the piece lies whole within it,
/// background all round).
fn distinct(lum: &Plane) -> Vec<bool> {
    let (w, h) = (lum.width, lum.height);
    let border: Vec<f64> = (0..w * h)
        .filter(|i| {
            let (x, y) = (i % w, i / w);
            x < BORDER_PX || y < BORDER_PX || x + BORDER_PX >= w || y + BORDER_PX >= h
        })
        .map(|i| lum.data[i] as f64)
        .collect();
    let level = median(&border);
    let ln = MIN_LOCAL_CONTRAST.ln();
    let mask: Vec<bool> = lum
        .data
        .iter()
        .map(|&v| level > 0.0 && v > 0.0 && ((v as f64) / level).ln().abs() > ln)
        .collect();
    // Lines of the piece as bright as the background (a dark stripe of a
    // near-mirror on the black holder) would cut it into bands, each a
    // quadrilateral of its own: closed over.
    let grown = spread(&mask, w, h, CLOSE_PX, false);
    spread(&grown, w, h, CLOSE_PX, true)
}

/// A square window of `2r + 1` px over `mask`: each pixel set where any
/// pixel within it is (`all` false: dilation) or where every one within
/// the photograph is (`all` true: erosion).
fn spread(mask: &[bool], w: usize, h: usize, r: usize, all: bool) -> Vec<bool> {
    // Along rows, then along columns: a square window is both in turn.
    let pass = |src: &[bool], len: usize, lines: usize, at: &dyn Fn(usize, usize) -> usize| {
        let mut out = vec![false; src.len()];
        for line in 0..lines {
            let mut count = 0usize; // set pixels within the window
            let get = |i: usize| usize::from(src[at(line, i)]);
            for i in 0..r.min(len) {
                count += get(i);
            }
            for i in 0..len {
                if i + r < len {
                    count += get(i + r);
                }
                if i > r {
                    count -= get(i - r - 1);
                }
                let span = (i + r).min(len - 1) + 1 - i.saturating_sub(r);
                out[at(line, i)] = if all { count == span } else { count > 0 };
            }
        }
        out
    };
    let rows = pass(mask, w, h, &|y, x| y * w + x);
    pass(&rows, h, w, &|x, y| y * w + x)
}

/// [`find_corners`] for a piece of `polarity` on the pixels of `mask`:
/// its regions tried largest first, passing over those that reach the
/// photograph's edge or are not quadrilaterals; the first that is both
/// is the piece, found or refused.
fn find_in(
    lum: &Plane,
    mask: &[bool],
    polarity: Polarity,
    origin: Origin,
    lens: LensChoice,
) -> Result<FoundCorners, String> {
    let region = polarity.name();
    let (count, regions) = components(mask, lum.width, lum.height, MIN_REGION_PX);
    let mut passed: Option<String> = None;
    for (passed_over, piece) in regions.enumerate() {
        let quad = match outline(&piece, polarity) {
            Ok(quad) => quad,
            Err(why) => {
                passed.get_or_insert(why);
                continue;
            }
        };
        let found = through(lum, quad, polarity, lens, &PROFILE_HALF_PX)?;
        return Ok(FoundCorners { corners: ordered(found.corners, origin)?, passed_over, ..found });
    }
    Err(match passed {
        None => format!("no {region} region of {MIN_REGION_PX} px or more"),
        Some(why) if count == 1 => format!("the {region} region {why}"),
        Some(why) => format!(
            "the largest {region} region {why}, and no smaller one (of {}) lies whole in the \
             photograph as a quadrilateral",
            count - 1
        ),
    })
}

/// A region's quadrilateral, or why it is not the piece: it reaches the
/// photograph's edge, or its area is not that of the largest quadrilateral
/// inside its outline.
fn outline(piece: &Component, polarity: Polarity) -> Result<[[f64; 2]; 4], String> {
    if piece.touches_edge {
        return Err("reaches the photograph's edge (the piece must lie whole in the \
                    photograph, with background all round it)"
            .into());
    }
    let hull = convex_hull(&piece.outline);
    let Some(quad) = largest_quadrilateral(&hull) else {
        return Err("has no area".into());
    };
    let area = shoelace(&quad).abs();
    // A mixed piece's pixels as near its background as the background
    // itself are holes in it: its rows' spans measure it.
    let covered = match polarity {
        Polarity::Mixed => piece.spans,
        _ => piece.pixels as f64,
    };
    let fill = covered / area.max(1.0);
    if !(MIN_FILL..=1.0 / MIN_FILL).contains(&fill) {
        return Err(format!(
            "is not a quadrilateral: its area is {:.0} % of the largest one inside its outline \
             ({:.0}–{:.0} %)",
            100.0 * fill,
            100.0 * MIN_FILL,
            100.0 / MIN_FILL
        ));
    }
    Ok(quad)
}

/// Hand-marked corners (in any order around the piece, kept) moved onto
/// the piece's edges as [`find_corners`] fits them: each side refound from
/// profiles 6, 4 and then 2.5 px either side of it, so marks within a few
/// pixels of the true corners do. Whether the piece is brighter or darker
/// than its background is read across the marked outline.
pub fn refine_corners(
    photo: &Frame,
    marked: [[f64; 2]; 4],
    lens: LensChoice,
) -> Result<FoundCorners, BuildError> {
    super::rectify::check_photo(photo)?;
    let fail = |m: String| BuildError::Input(format!("refining the marked corners: {m}"));
    super::rectify::check_corners(&marked, photo.width, photo.height).map_err(fail)?;
    let lum = luminance(photo);
    let seen = Seen::new(&lum, Lens::PINHOLE).map_err(fail)?;
    let brighter = contrast(&seen, &marked, Polarity::Brighter);
    // Neither 2× brighter nor 2× darker, but differing 2× either way: mixed.
    let polarity = if brighter.max(1.0 / brighter) < MIN_CONTRAST
        && contrast(&seen, &marked, Polarity::Mixed) >= MIN_CONTRAST
    {
        Polarity::Mixed
    } else if brighter >= 1.0 {
        Polarity::Brighter
    } else {
        Polarity::Darker
    };
    through(&lum, marked, polarity, lens, &[6.0, 4.0, 2.5]).map_err(fail)
}

/// A photograph's luminance as its pinhole image: read through a lens.
struct Seen<'a> {
    lum: &'a Plane,
    lens: LensMap,
}

impl<'a> Seen<'a> {
    fn new(lum: &'a Plane, lens: Lens) -> Result<Seen<'a>, String> {
        Ok(Seen { lum, lens: LensMap::new(lens, lum.width as u32, lum.height as u32)? })
    }

    /// The luminance at the pinhole image's point `p`, px.
    fn at(&self, p: [f64; 2]) -> f64 {
        let q = self.lens.in_frame(p);
        self.lum.bilinear(q[0], q[1])
    }
}

/// Rounds of estimating the lens and refitting the sides through it.
const LENS_ROUNDS: usize = 3;
/// The k1 searched when the lens is estimated (half-diagonal scale).
const LENS_K1_RANGE: f64 = 0.6;
/// Edge points in a row per block of k1's standard error.
const LENS_BLOCK: usize = 32;

/// [`settle`] through the lens `choice`, from a quadrilateral `quad` of
/// the photograph's px near the piece's outline: the corners in the
/// photograph's px.
fn through(
    lum: &Plane,
    quad: [[f64; 2]; 4],
    polarity: Polarity,
    choice: LensChoice,
    halves: &[f64],
) -> Result<FoundCorners, String> {
    let (lens, sigma) = match choice {
        LensChoice::Known(lens) => (lens, None),
        LensChoice::Estimate => {
            let (mut lens, mut sigma) = (Lens::PINHOLE, f64::INFINITY);
            for _ in 0..LENS_ROUNDS {
                let seen = Seen::new(lum, lens)?;
                let mut pinhole = quad.map(|c| seen.lens.in_pinhole(c));
                let mut sides = Vec::new();
                for half in [6.0, 4.0] {
                    (pinhole, _, sides) = refine(&seen, &pinhole, half, polarity)?;
                }
                let edges: Vec<Vec<[f64; 2]>> = sides
                    .iter()
                    .map(|pts| pts.iter().map(|&p| seen.lens.in_frame(p)).collect())
                    .collect();
                (lens, sigma) = estimate_lens(&edges, lum.width as u32, lum.height as u32);
            }
            (lens, Some(sigma))
        }
    };
    let seen = Seen::new(lum, lens)?;
    let found = settle(&seen, quad.map(|c| seen.lens.in_pinhole(c)), polarity, halves)?;
    Ok(FoundCorners {
        corners: found.corners.map(|c| seen.lens.in_frame(c)),
        lens_k1_sigma: sigma,
        ..found
    })
}

/// The k1 (k2 = 0, half-diagonal scale) that makes each side's edge points
/// (photograph px) straightest: the least sum of squared distances from
/// their total-least-squares lines in the pinhole image, each distance in
/// the photograph's px (divided by the lens' local stretch there, so that
/// shrinking the image does not pass for straightening it). A grid over
/// ±[`LENS_K1_RANGE`], then a golden-section search around its best.
///
/// With it, k1's standard error, from blocks of [`LENS_BLOCK`] edge points
/// in a row along a side (a texture's edge wanders over several points,
/// so single points are not independent, blocks nearly are): each block's
/// share g_b of the cost's slope at the best k1 moves the best by about
/// g_b / cost'' when the block is left out, and the variance is
/// B / (B − 1) · Σ (g_b / cost'')² over the B blocks (the jackknife, to
/// first order). The same over the four sides as blocks, and the larger of
/// the two: a texture whose pattern beats with the pixels (a weave seen in
/// perspective) moves a whole side's edge slowly, which blocks of a side do
/// not see and leaving the side out does.
fn estimate_lens(edges: &[Vec<[f64; 2]>], width: u32, height: u32) -> (Lens, f64) {
    // Each side's distances from its line, in order along it.
    let residuals = |k1: f64| -> Option<Vec<Vec<f64>>> {
        let lens = Lens::radial([k1, 0.0]);
        let map = LensMap::new(lens, width, height).ok()?;
        let mut out = Vec::with_capacity(edges.len());
        for side in edges {
            let pts: Vec<[f64; 2]> = side.iter().map(|&q| map.in_pinhole(q)).collect();
            let ((c, d), _) = tls(&pts)?;
            let off = |p: &[f64; 2]| {
                let j = map.jacobian(*p);
                let det = (j[0][0] * j[1][1] - j[0][1] * j[1][0]).abs().sqrt();
                ((p[0] - c[0]) * d[1] - (p[1] - c[1]) * d[0]) * det
            };
            out.push(pts.iter().map(off).collect());
        }
        Some(out)
    };
    let cost = |k1: f64| -> f64 {
        residuals(k1).map_or(f64::INFINITY, |r| r.iter().flatten().map(|e| e * e).sum())
    };
    const GRID: usize = 48;
    let at = |i: usize| LENS_K1_RANGE * (2.0 * i as f64 / GRID as f64 - 1.0);
    let best = (0..=GRID).min_by(|&a, &b| cost(at(a)).total_cmp(&cost(at(b)))).unwrap_or(GRID / 2);
    let (mut a, mut b) = (at(best.saturating_sub(1)), at((best + 1).min(GRID)));
    let g = 0.5 * (5f64.sqrt() - 1.0);
    let (mut x1, mut x2) = (b - g * (b - a), a + g * (b - a));
    let (mut f1, mut f2) = (cost(x1), cost(x2));
    while b - a > 1e-7 {
        if f1 <= f2 {
            (b, x2, f2) = (x2, x1, f1);
            x1 = b - g * (b - a);
            f1 = cost(x1);
        } else {
            (a, x1, f1) = (x1, x2, f2);
            x2 = a + g * (b - a);
            f2 = cost(x2);
        }
    }
    let k1 = 0.5 * (a + b);
    let h = 1e-3;
    let curvature = (cost(k1 + h) - 2.0 * cost(k1) + cost(k1 - h)) / (h * h);
    let sigma = match (residuals(k1 + h), residuals(k1 - h)) {
        (Some(up), Some(down)) => {
            // Each block's share of the cost's slope, side by side.
            let slopes: Vec<Vec<f64>> = up
                .iter()
                .zip(&down)
                .map(|(u, d)| {
                    let (u, d) = (u.chunks(LENS_BLOCK), d.chunks(LENS_BLOCK));
                    u.zip(d)
                        .map(|(u, d)| {
                            u.iter().zip(d).map(|(u, d)| (u * u - d * d) / (2.0 * h)).sum::<f64>()
                        })
                        .collect()
                })
                .collect();
            let jackknife = |groups: &[f64]| {
                let n = groups.len() as f64;
                let spread = groups.iter().map(|g| (g / curvature).powi(2)).sum::<f64>();
                (n / (n - 1.0) * spread).sqrt()
            };
            let blocks: Vec<f64> = slopes.iter().flatten().copied().collect();
            let sides: Vec<f64> = slopes.iter().map(|b| b.iter().sum()).collect();
            jackknife(&blocks).max(jackknife(&sides))
        }
        _ => f64::INFINITY,
    };
    (Lens::radial([k1, 0.0]), if sigma.is_finite() { sigma } else { f64::INFINITY })
}

/// The photograph's luminance: the mean of its channels.
fn luminance(photo: &Frame) -> Plane {
    let mut lum = Plane::new(photo.width as usize, photo.height as usize);
    for (l, px) in lum.data.iter_mut().zip(photo.rgb.chunks_exact(3)) {
        *l = (px[0] + px[1] + px[2]) / 3.0;
    }
    lum
}

/// A quadrilateral near the piece's outline refitted to its sides (passes
/// of profiles `halves` px either side), then checked: sides of some
/// length, straight, corners within the photograph, the piece standing
/// out.
fn settle(
    seen: &Seen<'_>,
    mut quad: [[f64; 2]; 4],
    polarity: Polarity,
    halves: &[f64],
) -> Result<FoundCorners, String> {
    let mut fit = Fit::default();
    for &half in halves {
        (quad, fit, _) = refine(seen, &quad, half, polarity)?;
    }
    for k in 0..4 {
        let side = dist(quad[k], quad[(k + 1) % 4]);
        if side < MIN_SIDE_PX {
            return Err(format!("a side of {side:.1} px: at least {MIN_SIDE_PX} px"));
        }
    }
    if fit.rms > MAX_EDGE_RMS_PX || fit.bow > MAX_BOW_PX {
        return Err(format!(
            "the sides are not straight: their edge points lie {:.2} px RMS from lines (at most \
             {MAX_EDGE_RMS_PX}), a side bows by {:.2} px (its middle third against its outer \
             thirds; at most {MAX_BOW_PX}); remove the lens's distortion first",
            fit.rms, fit.bow
        ));
    }
    let (w, h) = (seen.lum.width as f64, seen.lum.height as f64);
    let in_photo = |c: &[f64; 2]| {
        let q = seen.lens.in_frame(*c);
        (0.0..=w).contains(&q[0]) && (0.0..=h).contains(&q[1])
    };
    if let Some(c) = quad.iter().find(|c| !in_photo(c)).map(|c| seen.lens.in_frame(*c)) {
        return Err(format!(
            "a corner, where two sides meet, lies outside the photograph at ({:.1}, {:.1}) px",
            c[0], c[1]
        ));
    }
    let contrast = contrast(seen, &quad, polarity);
    if contrast.is_nan() || contrast < MIN_CONTRAST {
        return Err(format!(
            "the piece stands out of its background by only × {contrast:.2} (at least × \
             {MIN_CONTRAST}): lay it on a plain background of another brightness"
        ));
    }
    Ok(FoundCorners {
        corners: quad,
        polarity,
        contrast,
        edge_rms_px: fit.rms,
        bow_px: fit.bow,
        edge_points: fit.points,
        lens: seen.lens.lens(),
        lens_k1_sigma: None,
        passed_over: 0,
    })
}

/// Pixels above Otsu's threshold on the logarithm of `lum`; `None` if it
/// is uniform.
fn bright(lum: &Plane) -> Option<Vec<bool>> {
    let top = lum.data.iter().copied().fold(0.0f32, f32::max) as f64;
    if top <= 0.0 {
        return None;
    }
    let floor = top * 1e-6;
    let log = |v: f32| (v as f64).max(floor).ln();
    let (lo, hi) = (floor.ln(), top.ln());
    let low = lum.data.iter().map(|&v| log(v)).fold(hi, f64::min);
    if hi - low < 1e-9 {
        return None;
    }
    const BINS: usize = 256;
    let bin = |x: f64| (((x - lo) / (hi - lo) * BINS as f64) as usize).min(BINS - 1);
    let mut hist = [0u64; BINS];
    for &v in &lum.data {
        hist[bin(log(v))] += 1;
    }
    // Otsu: the split maximising the between-class variance.
    let total: u64 = hist.iter().sum();
    let sum: f64 = hist.iter().enumerate().map(|(i, &c)| i as f64 * c as f64).sum();
    let (mut n0, mut s0, mut best, mut split) = (0u64, 0.0, -1.0, 0);
    for (i, &c) in hist.iter().enumerate().take(BINS - 1) {
        n0 += c;
        s0 += i as f64 * c as f64;
        let n1 = total - n0;
        if n0 == 0 || n1 == 0 {
            continue;
        }
        let (m0, m1) = (s0 / n0 as f64, (sum - s0) / n1 as f64);
        let between = n0 as f64 * n1 as f64 * (m0 - m1) * (m0 - m1);
        if between > best {
            (best, split) = (between, i);
        }
    }
    (best > 0.0).then(|| lum.data.iter().map(|&v| bin(log(v)) > split).collect())
}

/// An 8-connected component of a mask.
struct Component {
    /// Its pixels.
    pixels: usize,
    /// The pixels from each row's leftmost to its rightmost, holes and all.
    spans: f64,
    /// Whether it has a pixel on the image's border.
    touches_edge: bool,
    /// Its outline's extreme points: each row's leftmost and rightmost
    /// pixels' outer corners, px.
    outline: Vec<[f64; 2]>,
}

/// A mask's 8-connected components of at least `min_pixels`: how many, and
/// each, largest first (ties: the first met in row order), its outline
/// traced only when the iterator reaches it.
fn components(
    mask: &[bool],
    w: usize,
    h: usize,
    min_pixels: usize,
) -> (usize, impl Iterator<Item = Component>) {
    let mut label = vec![u32::MAX; w * h];
    let mut stack = Vec::new();
    // Each labelled component's size and bounding box (x0, y0, x1, y1).
    let mut found: Vec<(usize, [usize; 4])> = Vec::new();
    for start in 0..w * h {
        if !mask[start] || label[start] != u32::MAX {
            continue;
        }
        let id = found.len() as u32;
        let (mut size, mut bbox) = (0usize, [start % w, start / w, start % w, start / w]);
        label[start] = id;
        stack.push(start);
        while let Some(i) = stack.pop() {
            size += 1;
            let (x, y) = (i % w, i / w);
            bbox = [bbox[0].min(x), bbox[1].min(y), bbox[2].max(x), bbox[3].max(y)];
            for ny in y.saturating_sub(1)..=(y + 1).min(h - 1) {
                for nx in x.saturating_sub(1)..=(x + 1).min(w - 1) {
                    let j = ny * w + nx;
                    if mask[j] && label[j] == u32::MAX {
                        label[j] = id;
                        stack.push(j);
                    }
                }
            }
        }
        found.push((size, bbox));
    }
    let mut order: Vec<usize> = (0..found.len()).filter(|&i| found[i].0 >= min_pixels).collect();
    order.sort_by_key(|&i| std::cmp::Reverse(found[i].0));
    let count = order.len();
    let each = order.into_iter().map(move |i| {
        let (pixels, [x0, y0, x1, y1]) = found[i];
        let (mut outline, mut spans) = (Vec::new(), 0.0);
        for y in y0..=y1 {
            let row = &label[y * w + x0..=y * w + x1];
            let (Some(a), Some(b)) =
                (row.iter().position(|&l| l == i as u32), row.iter().rposition(|&l| l == i as u32))
            else {
                continue;
            };
            let (a, b, y) = ((x0 + a) as f64, (x0 + b) as f64 + 1.0, y as f64);
            spans += b - a;
            outline.extend([[a, y], [a, y + 1.0], [b, y], [b, y + 1.0]]);
        }
        let touches_edge = x0 == 0 || y0 == 0 || x1 == w - 1 || y1 == h - 1;
        Component { pixels, spans, touches_edge, outline }
    });
    (count, each)
}

fn cross(o: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
}

fn dist(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]).hypot(a[1] - b[1])
}

/// The signed area (positive: counter-clockwise in x-right, y-up
/// axes, so clockwise as the photograph is seen).
fn shoelace(p: &[[f64; 2]]) -> f64 {
    let n = p.len();
    0.5 * (0..n).map(|k| cross([0.0, 0.0], p[k], p[(k + 1) % n])).sum::<f64>()
}

/// A side of a quadrilateral: from corner `a` to the next, `b`, `len` px
/// long along the unit `t`, its outward unit normal `n`.
struct Side {
    a: [f64; 2],
    b: [f64; 2],
    len: f64,
    t: [f64; 2],
    n: [f64; 2],
}

/// The quadrilateral's sides, side k from corner k to corner k + 1; which
/// way is out follows from its orientation.
fn sides(quad: &[[f64; 2]; 4]) -> [Side; 4] {
    let turn = shoelace(quad).signum();
    std::array::from_fn(|k| {
        let (a, b) = (quad[k], quad[(k + 1) % 4]);
        let len = dist(a, b);
        let t = [(b[0] - a[0]) / len, (b[1] - a[1]) / len];
        Side { a, b, len, t, n: [turn * t[1], -turn * t[0]] }
    })
}

/// Andrew's monotone chain: the hull's vertices in order, no three on a
/// line.
fn convex_hull(points: &[[f64; 2]]) -> Vec<[f64; 2]> {
    let mut p = points.to_vec();
    p.sort_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
    p.dedup();
    if p.len() < 3 {
        return p;
    }
    // The lower chain left to right, then the upper right to left; each
    // chain's last point is the next one's first.
    let mut hull: Vec<[f64; 2]> = Vec::with_capacity(2 * p.len());
    let mut chain = |points: &mut dyn Iterator<Item = &[f64; 2]>| {
        let start = hull.len();
        for &q in points {
            while hull.len() >= start + 2
                && cross(hull[hull.len() - 2], hull[hull.len() - 1], q) <= 0.0
            {
                hull.pop();
            }
            hull.push(q);
        }
        hull.pop();
    };
    chain(&mut p.iter());
    chain(&mut p.iter().rev());
    hull
}

/// The quadrilateral of largest area with its corners among a convex
/// polygon's vertices, in the polygon's order: for each first corner, the
/// opposite one swept round while the two others follow it (each
/// triangle's area is unimodal along a convex polygon), O(n²).
fn largest_quadrilateral(hull: &[[f64; 2]]) -> Option<[[f64; 2]; 4]> {
    let n = hull.len();
    if n < 4 {
        return None;
    }
    let at = |i: usize| hull[i % n];
    let tri = |a: usize, b: usize, c: usize| cross(at(a), at(b), at(c)).abs();
    let mut best = (0.0, [0usize; 4]);
    for i in 0..n {
        let mut j = i + 1;
        let mut l = i + 3;
        for k in i + 2..i + n - 1 {
            while j + 1 < k && tri(i, j + 1, k) >= tri(i, j, k) {
                j += 1;
            }
            l = l.max(k + 1);
            while l + 1 < i + n && tri(i, k, l + 1) >= tri(i, k, l) {
                l += 1;
            }
            let area = tri(i, j, k) + tri(i, k, l);
            if area > best.0 {
                best = (area, [i, j, k, l]);
            }
        }
    }
    (best.0 > 0.0).then(|| best.1.map(at))
}

/// The quadrilateral's sides refound from the luminance across them
/// (profiles `half` px either side): the corners where the fitted lines
/// meet, how well the lines fit, and each side's kept edge points.
fn refine(
    seen: &Seen<'_>,
    quad: &[[f64; 2]; 4],
    half: f64,
    polarity: Polarity,
) -> Result<Refit, String> {
    let mut lines: [Line; 4] = [([0.0; 2], [0.0; 2]); 4];
    let (mut ss, mut fit) = (0.0, Fit::default());
    let mut kept = Vec::with_capacity(4);
    // Every side's profiles first, then one way of placing them all.
    let profiles: Vec<(Side, Vec<Profile>)> = sides(quad)
        .into_iter()
        .map(|side| {
            let steps = (half / PROFILE_STEP_PX).round() as isize;
            let margin = 2.0 * half + 1.0;
            let mut found = Vec::new();
            let mut s = margin;
            while s <= side.len - margin {
                let p = [side.a[0] + s * side.t[0], side.a[1] + s * side.t[1]];
                if let Some(c) = crossing(seen, p, side.n, steps, polarity) {
                    found.push((p, c));
                }
                s += 1.0;
            }
            (side, found)
        })
        .collect();
    let all = profiles.iter().map(|(_, f)| f.len()).sum::<usize>();
    let flat = profiles.iter().flat_map(|(_, f)| f).filter(|(_, c)| c.area.is_some()).count();
    let by_area = all > 0 && flat as f64 >= EDGE_FLAT_SHARE * all as f64;
    for (k, (Side { a, b, n, .. }, found)) in profiles.into_iter().enumerate() {
        let points: Vec<[f64; 2]> = found
            .iter()
            .map(|(p, c)| {
                let e = if by_area { c.area.unwrap_or(c.level) } else { c.level };
                [p[0] + e * n[0], p[1] + e * n[1]]
            })
            .collect();
        let Some((line, side, on_line)) = fit_line(&points) else {
            return Err(format!(
                "side {k} ({:.1}, {:.1})–({:.1}, {:.1}) px: no clear edge along it",
                a[0], a[1], b[0], b[1]
            ));
        };
        lines[k] = line;
        kept.push(on_line);
        ss += side.rms * side.rms * side.points as f64;
        fit.points += side.points;
        fit.bow = fit.bow.max(side.bow);
    }
    let mut out = [[0.0; 2]; 4];
    for k in 0..4 {
        // Corner k joins side k − 1 and side k.
        let Some(p) = meet(lines[(k + 3) % 4], lines[k]) else {
            return Err(format!("sides {} and {k} are parallel", (k + 3) % 4));
        };
        if dist(p, quad[k]) > 2.0 * half {
            return Err(format!(
                "corner {k} moved {:.1} px from the outline's ({:.1}, {:.1}) px: its sides are \
                 not clear",
                dist(p, quad[k]),
                quad[k][0],
                quad[k][1]
            ));
        }
        out[k] = p;
    }
    fit.rms = (ss / fit.points.max(1) as f64).sqrt();
    Ok((out, fit, kept))
}

/// An edge profile: the point of the side it crosses (px) and its crossing.
type Profile = ([f64; 2], Crossing);

/// Where an edge profile passes from the piece to the background, px
/// along its outward normal ([`crossing`]).
struct Crossing {
    /// Where the luminance passes the level halfway between the two.
    level: f64,
    /// Where the piece's share of the profile puts the edge, if the piece
    /// is flat up to it.
    area: Option<f64>,
}

/// Where, along the outward normal `n` from `p` (px), the luminance passes
/// the level halfway between the piece just inside and the background just
/// outside: the outermost such crossing, by linear interpolation between
/// profile steps.
fn crossing(
    seen: &Seen<'_>,
    p: [f64; 2],
    n: [f64; 2],
    steps: isize,
    polarity: Polarity,
) -> Option<Crossing> {
    // The luminance `s` px along the normal.
    let v = |s: f64| seen.at([p[0] + s * n[0], p[1] + s * n[1]]);
    let profile: Vec<f64> = (-steps..=steps).map(|k| v(k as f64 * PROFILE_STEP_PX)).collect();
    let quarter = (steps / 2).max(1) as usize;
    let inside = median(&profile[..quarter + 1]);
    let outside = median(&profile[profile.len() - quarter - 1..]);
    let ratio = polarity.ratio(inside, outside);
    if ratio.is_nan() || ratio < MIN_LOCAL_CONTRAST {
        return None;
    }
    let polarity = polarity.at(inside, outside);
    let level = 0.5 * (inside + outside);
    let mut best: Option<f64> = None;
    for i in 0..profile.len() - 1 {
        let (v0, v1) = (profile[i], profile[i + 1]);
        // From the piece's side of the level to the background's.
        let across = match polarity {
            Polarity::Brighter | Polarity::Mixed => v0 >= level && v1 < level,
            Polarity::Darker => v0 < level && v1 >= level,
        };
        if across {
            let s = (i as f64 + (v0 - level) / (v0 - v1) - steps as f64) * PROFILE_STEP_PX;
            if best.is_none_or(|b| s > b) {
                best = Some(s);
            }
        }
    }
    let s0 = best?;
    // Where the piece is flat up to its edge, the edge by its area too:
    // the piece's share of the profile over a window about the crossing.
    let lo = s0 - EDGE_WINDOW_PX;
    let near: Vec<f64> =
        (0..=EDGE_FLAT_STEPS).map(|j| v(lo - j as f64 * PROFILE_STEP_PX)).collect();
    let (low, high) = near.iter().fold((f64::MAX, f64::MIN), |(a, b), &x| (a.min(x), b.max(x)));
    if high - low > EDGE_FLAT * (inside - outside).abs() {
        return Some(Crossing { level: s0, area: None });
    }
    // The piece's level carried into the window: a line fitted to the
    // profile just inside it (light falling off across the piece).
    let (mut sx, mut sy, mut sxx, mut sxy) = (0.0, 0.0, 0.0, 0.0);
    for (j, y) in near.iter().enumerate() {
        let x = -(j as f64) * PROFILE_STEP_PX;
        (sx, sy, sxx, sxy) = (sx + x, sy + y, sxx + x * x, sxy + x * y);
    }
    let k = near.len() as f64;
    let slope = (k * sxy - sx * sy) / (k * sxx - sx * sx);
    let level0 = (sy - slope * sx) / k;
    let m = (2.0 * EDGE_WINDOW_PX / PROFILE_STEP_PX).round() as usize;
    let share = |j: usize| {
        let x = j as f64 * PROFILE_STEP_PX;
        (v(lo + x) - outside) / (level0 + slope * x - outside)
    };
    let area =
        lo + PROFILE_STEP_PX * (0.5 * (share(0) + share(m)) + (1..m).map(share).sum::<f64>());
    Some(Crossing { level: s0, area: ((area - s0).abs() <= 1.0).then_some(area) })
}

/// A line (a point on it, its unit direction) fitted to `points` by total
/// least squares, refitted without the points beyond three robust
/// deviations (at least 0.1 px): the line and how well it fits the kept
/// points (`points` in order along the line), and those points. `None`
/// for fewer than 8.
fn fit_line(points: &[[f64; 2]]) -> Option<(Line, Fit, Vec<[f64; 2]>)> {
    let mut kept: Vec<[f64; 2]> = points.to_vec();
    let mut line = None;
    for _ in 0..4 {
        if kept.len() < 8 {
            return None;
        }
        let ((c, d), m) = tls(&kept)?;
        let signed = |p: &[f64; 2]| (p[0] - c[0]) * d[1] - (p[1] - c[1]) * d[0];
        let off = |p: &[f64; 2]| signed(p).abs();
        let devs: Vec<f64> = kept.iter().map(off).collect();
        let rms = (devs.iter().map(|e| e * e).sum::<f64>() / m).sqrt();
        let third = kept.len() / 3;
        let (mut middle, mut outer): (Vec<f64>, Vec<f64>) = (Vec::new(), Vec::new());
        for (i, p) in kept.iter().enumerate() {
            if (third..kept.len() - third).contains(&i) { &mut middle } else { &mut outer }
                .push(signed(p));
        }
        let bow = (median(&middle) - median(&outer)).abs();
        line = Some(((c, d), Fit { rms, bow, points: kept.len() }));
        let cut = (3.0 * 1.4826 * median(&devs)).max(0.1);
        let before = kept.len();
        kept.retain(|p| off(p) <= cut);
        if kept.len() == before {
            break;
        }
    }
    line.map(|(l, f)| (l, f, kept))
}

/// The total-least-squares line through `points` (their centroid, the
/// direction of largest spread), and how many; `None` if empty.
fn tls(points: &[[f64; 2]]) -> Option<(Line, f64)> {
    if points.is_empty() {
        return None;
    }
    let m = points.len() as f64;
    let c = [
        points.iter().map(|p| p[0]).sum::<f64>() / m,
        points.iter().map(|p| p[1]).sum::<f64>() / m,
    ];
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for p in points {
        let (x, y) = (p[0] - c[0], p[1] - c[1]);
        sxx += x * x;
        sxy += x * y;
        syy += y * y;
    }
    let angle = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    Some(((c, [angle.cos(), angle.sin()]), m))
}

/// What [`refine`] gives: the corners, how well the sides fit, and each
/// side's kept edge points.
type Refit = ([[f64; 2]; 4], Fit, Vec<Vec<[f64; 2]>>);

/// A line: a point on it and its unit direction, px.
type Line = ([f64; 2], [f64; 2]);

/// How well lines fit edge points.
#[derive(Debug, Clone, Copy, Default)]
struct Fit {
    /// RMS distance, px.
    rms: f64,
    /// The most a line's points bow away from it, px.
    bow: f64,
    /// Points kept.
    points: usize,
}

/// The upper median of `v` (NaN if empty).
fn median(v: &[f64]) -> f64 {
    crate::stats::median(v.to_vec()).unwrap_or(f64::NAN)
}

/// Where two lines meet; `None` if nearly parallel.
fn meet(a: Line, b: Line) -> Option<[f64; 2]> {
    let ((p, d), (q, e)) = (a, b);
    let den = d[0] * e[1] - d[1] * e[0];
    if den.abs() < 1e-3 {
        return None;
    }
    let t = ((q[0] - p[0]) * e[1] - (q[1] - p[1]) * e[0]) / den;
    Some([p[0] + t * d[0], p[1] + t * d[1]])
}

/// How many times the median luminance within 2–6 px inside the outline
/// stands out of the median within 2–6 px outside it.
fn contrast(seen: &Seen<'_>, quad: &[[f64; 2]; 4], polarity: Polarity) -> f64 {
    let (mut inside, mut outside) = (Vec::new(), Vec::new());
    for Side { a, len, t, n, .. } in sides(quad) {
        let mut s = 8.0;
        while s <= len - 8.0 {
            for o in [2.0, 4.0, 6.0] {
                let p = |o: f64| seen.at([a[0] + s * t[0] + o * n[0], a[1] + s * t[1] + o * n[1]]);
                inside.push(p(-o));
                outside.push(p(o));
            }
            s += 2.0;
        }
    }
    match polarity {
        // Each place the way it differs.
        Polarity::Mixed => median(
            &inside.iter().zip(&outside).map(|(&i, &o)| polarity.ratio(i, o)).collect::<Vec<_>>(),
        ),
        _ => polarity.ratio(median(&inside), median(&outside)),
    }
}

/// The corners counter-clockwise as the photograph is seen, from the one
/// nearest `origin`'s corner of the photograph; an error if two are about
/// as near (the piece turned by about 45°).
fn ordered(quad: [[f64; 2]; 4], origin: Origin) -> Result<[[f64; 2]; 4], String> {
    let mut q = quad;
    // Counter-clockwise as seen (y down): negative signed area in (x, y).
    if shoelace(&q) > 0.0 {
        q.reverse();
    }
    let mut by: Vec<(f64, usize)> = (0..4).map(|k| (origin.towards(q[k]), k)).collect();
    by.sort_by(|a, b| b.0.total_cmp(&a.0));
    let side = (0..4).map(|k| dist(q[k], q[(k + 1) % 4])).sum::<f64>() / 4.0;
    if by[0].0 - by[1].0 < 0.2 * side {
        return Err(format!(
            "two corners, ({:.1}, {:.1}) and ({:.1}, {:.1}) px, are about as near the \
             photograph's corner where uv (0, 0) should be (the piece is turned by about 45°): \
             turn the piece",
            q[by[0].1][0], q[by[0].1][1], q[by[1].1][0], q[by[1].1][1]
        ));
    }
    Ok(std::array::from_fn(|k| q[(by[0].1 + k) % 4]))
}
