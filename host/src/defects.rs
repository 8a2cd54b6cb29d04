//! Defective sensor pixels (docs/scan-format.md, "Sensor defects"): found
//! in auto exposure's metering frames (stuck, dead), every scan's dark
//! frame (hot and stuck, [`dark_frame_defects`]) and a calibration's white
//! frames, recorded with the scan (or calibration), and replaced in the
//! frames by the mean of their neighbours.
//!
//! A real sensor has a few pixels stuck at the top code whatever the light
//! and a few dead ones that always read 0. On the sample's views a stuck
//! pixel looks like a highlight no exposure holds: auto HDR would extend
//! every mirror's bracket down to its shortest exposure for it, and the
//! merge would scale its clipped value to thousands of times full scale.
//!
//! The metering frames show the sample lit from several mirrors. A value
//! is a defect when it reads the top code in every metering frame (stuck;
//! anywhere in the frame) or 0 in every one (dead; looked for where the
//! sample is seen, the only place it shows) and, in at least one, stands out
//! from its eight neighbours. Stuck: at most one of them (a pair of
//! defects) at the top code, and they average below half of full scale.
//! Dead: all but at most one read at least [`DEAD_CONTRAST_CODES`] codes (a
//! working pixel lit like them reads 0 with a probability below 10⁻⁷). A
//! highlight moves with the light, and a saturated or dark patch or line of
//! the sample, or the dark side of a view's edge (whose pixels read 0 by
//! read noise alone two times in three), has neighbours like it, so none of
//! them is taken for a defect; nor is any value of a cluster of three or
//! more touching ones, a line's ends included. Only on a uniform target
//! ([`DefectFinder::uniform_target`]: the calibration's white) are dead
//! clusters up to [`MAX_CLUSTER_SIDE`]² taken, when what surrounds them
//! was lit.

use serde::{Deserialize, Serialize};

use crate::camera::Frame;
use crate::exposure::{Span, sample_spans};
use crate::exrio::PixelRect;
use scanner_geometry::ScannerGeometry;

/// Fewest metering frames that can tell a defect from the sample.
pub const MIN_FRAMES: usize = 4;
/// A stuck candidate stands out when its neighbours average below this
/// fraction of full scale.
pub const STUCK_CONTRAST: f32 = 0.5;
/// A dead candidate stands out when its neighbours (all but
/// [`MAX_ALIKE_NEIGHBOURS`]) read at least this many ADC codes.
pub const DEAD_CONTRAST_CODES: f64 = 16.0;
/// A candidate with more neighbours like it than this (at the top code;
/// below [`DEAD_CONTRAST_CODES`]) — more than the other pixel of a pair of
/// defects — is part of a saturated or dark patch or line, not a defect.
pub const MAX_ALIKE_NEIGHBOURS: u32 = 1;
/// More defects than this fraction of the frame's pixels is not a sensor's
/// defects but something the rule does not suit: none are recorded.
pub const MAX_FRACTION: f64 = 0.01;

/// What a defective pixel reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DefectKind {
    /// The top code, whatever the light.
    Stuck,
    /// 0, whatever the light.
    Dead,
    /// A dark signal of its own (dark current) that the light adds to:
    /// found in a dark frame.
    Hot,
}

/// One defective pixel of the camera's frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PixelDefect {
    /// Column.
    pub x: u32,
    /// Row.
    pub y: u32,
    /// What it reads.
    pub kind: DefectKind,
}

/// The largest dead cluster a uniform target's frames can show
/// ([`DefectFinder::uniform_target`]): pixels within a square of this
/// side.
pub const MAX_CLUSTER_SIDE: u32 = 3;

/// How far from a defect [`DefectMap::patch`] looks for working
/// neighbours, pixels.
pub const PATCH_RADIUS: usize = 2;

/// A value (3 · pixel + channel) at the top code or 0 in every frame so far.
#[derive(Debug, Clone, Copy)]
struct Candidate {
    value: u32,
    stuck: bool,
    /// Some frame showed it against its neighbours.
    contrast: bool,
    /// Dead: bit `k` set when neighbour `k` ([`NEIGHBOURS`]) read at least
    /// [`DEAD_CONTRAST_CODES`] in some frame.
    lit: u8,
}

/// The eight neighbours' offsets, in the order of [`Candidate::lit`]'s bits.
const NEIGHBOURS: [(i64, i64); 8] =
    [(-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1)];

/// Finds defective pixels over a series of frames of the same camera.
#[derive(Debug)]
pub struct DefectFinder {
    width: u32,
    height: u32,
    max_code: f64,
    spans: Vec<Span>,
    frames: usize,
    candidates: Vec<Candidate>,
    /// A frame of another size arrived: nothing can be decided.
    mixed: bool,
    /// The frames show a uniform target: dead clusters are looked for.
    clusters: bool,
}

/// Why a finder recorded no defects although it may have seen some.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum NotDecided {
    /// Fewer frames than [`MIN_FRAMES`].
    #[error(
        "{0} metering frames are too few to tell a sensor defect from the sample (at least {MIN_FRAMES})"
    )]
    TooFewFrames(usize),
    /// Frames of different sizes.
    #[error("the metering frames differ in size")]
    Mixed,
    /// More candidates than [`MAX_FRACTION`] of the frame's pixels.
    #[error(
        "{found} pixels of {examined} look defective: more than a sensor's defects, so none are \
         treated as such"
    )]
    TooMany {
        /// Pixels that passed the rule.
        found: usize,
        /// Pixels examined.
        examined: usize,
    },
    /// A dark frame whose typical pixel is above [`DARK_MEDIAN_CODES`]:
    /// the camera's frames carry a black level, or light reaches the
    /// sensor with the scanner's light off.
    #[error(
        "its median pixel reads {median_codes} codes, not 0: the camera's frames carry a black \
         level (scan with --black-level {median_codes} or --black-level auto, or have its capture \
         program subtract it; docs/scan-format.md) or light reaches the sensor with the \
         scanner's light off"
    )]
    NotDark {
        /// The median of every value, ADC codes.
        median_codes: u32,
    },
}

impl DefectFinder {
    /// A finder over `width` × `height` frames: stuck pixels anywhere,
    /// dead ones where `geometry` shows the sample (with
    /// [`crate::exposure::CLIP_MARGIN`] around it), the only place they
    /// can be seen.
    pub fn new(geometry: &ScannerGeometry, width: u32, height: u32) -> DefectFinder {
        DefectFinder {
            width,
            height,
            max_code: geometry.sensor.max_code(),
            spans: sample_spans(geometry, width, height),
            frames: 0,
            candidates: Vec::new(),
            mixed: false,
            clusters: false,
        }
    }

    /// A finder over frames of a uniform target (a calibration's diffuse
    /// white), which finds dead **clusters** too: pixels within a
    /// [`MAX_CLUSTER_SIDE`]-pixel square that read 0 in every frame, and
    /// around which every pixel but [`MAX_ALIKE_NEIGHBOURS`] was lit in
    /// some frame. On a sample that is what a small black spot looks like,
    /// so [`DefectFinder::new`] takes no more than pairs.
    pub fn uniform_target(geometry: &ScannerGeometry, width: u32, height: u32) -> DefectFinder {
        DefectFinder { clusters: true, ..DefectFinder::new(geometry, width, height) }
    }

    /// Whether the next frame's pixels within `rect` (`[x0, y0, x1, y1)`)
    /// can still matter: after the first frame only the candidates and
    /// their neighbours are looked at, so a caller may leave the rest of
    /// the next frames undecoded (values there are never read).
    pub fn examines(&self, rect: PixelRect) -> bool {
        if self.frames == 0 {
            return true;
        }
        let w = self.width as usize;
        // A candidate reads its neighbours within 1 px ([`NEIGHBOURS`]).
        // Candidates are sorted by value, so by row then column.
        let (y0, y1) = (rect[1].saturating_sub(1), rect[3].saturating_add(1));
        let (x0, x1) = (rect[0].saturating_sub(1), rect[2].saturating_add(1));
        let first = self.candidates.partition_point(|c| (c.value as usize / 3) / w < y0);
        self.candidates[first..]
            .iter()
            .map(|c| c.value as usize / 3)
            .take_while(|p| p / w < y1)
            .any(|p| (x0..x1).contains(&(p % w)))
    }

    /// Take one more frame into account (values as stored: fractions of
    /// full scale).
    pub fn add(&mut self, frame: &Frame) {
        self.add_scaled(frame, 1.0);
    }

    /// Take one more frame into account whose values are `1 / scale` of
    /// the sensor's fractions of full scale (a frame read per second of
    /// exposure: `scale` = the exposure in s).
    pub fn add_scaled(&mut self, frame: &Frame, scale: f32) {
        let (w, h) = (self.width as usize, self.height as usize);
        if (frame.width, frame.height) != (self.width, self.height) || frame.rgb.len() != 3 * w * h
        {
            self.mixed = true;
            return;
        }
        let maxf = self.max_code as f32 * scale;
        let top = self.max_code as usize;
        let code = |v: u32| crate::hdr::adc_code(frame.rgb[v as usize], maxf, top);
        if self.frames == 0 {
            // Stuck: anywhere in the frame (the top code is rare where no
            // light is). Dead: where the sample is seen, lit.
            let stuck = frame
                .rgb
                .iter()
                .enumerate()
                .filter(|&(_, &v)| crate::hdr::adc_code(v, maxf, top) == top);
            self.candidates.extend(stuck.map(|(v, _)| Candidate {
                value: v as u32,
                stuck: true,
                contrast: false,
                lit: 0,
            }));
            for &(y, x0, x1) in &self.spans {
                for v in 3 * (y * self.width + x0)..3 * (y * self.width + x1) {
                    if code(v) == 0 {
                        let c = Candidate { value: v, stuck: false, contrast: false, lit: 0 };
                        self.candidates.push(c);
                    }
                }
            }
            self.candidates.sort_unstable_by_key(|c| c.value);
            self.candidates.dedup_by_key(|c| c.value);
        } else {
            self.candidates.retain(|c| code(c.value) == if c.stuck { top } else { 0 });
        }
        let dead_level = (DEAD_CONTRAST_CODES / self.max_code) as f32 / scale;
        for c in &mut self.candidates {
            // On a uniform target a dead value keeps gathering which of its
            // neighbours were lit, for the cluster rule.
            let gathering = self.clusters && !c.stuck;
            if c.contrast && !gathering {
                continue;
            }
            let (p, ch) = ((c.value / 3) as usize, (c.value % 3) as usize);
            let (x, y) = (p % w, p / w);
            // Neighbours like the candidate: at the top code (stuck), or
            // below the dead level (dead: dark, not only at 0).
            let like = |v: f32| {
                if c.stuck { crate::hdr::adc_code(v, maxf, top) == top } else { v < dead_level }
            };
            let (mut sum, mut n, mut alike) = (0.0f32, 0u32, 0u32);
            for (k, (dx, dy)) in NEIGHBOURS.iter().enumerate() {
                let (nx, ny) = (x as i64 + dx, y as i64 + dy);
                if nx < 0 || ny < 0 || nx >= w as i64 || ny >= h as i64 {
                    continue;
                }
                let v = frame.rgb[3 * (ny as usize * w + nx as usize) + ch];
                sum += v;
                n += 1;
                let same = like(v);
                alike += u32::from(same);
                if !c.stuck && !same {
                    c.lit |= 1 << k;
                }
            }
            if n == 0 || alike > MAX_ALIKE_NEIGHBOURS {
                continue;
            }
            c.contrast = !c.stuck || (sum / n as f32) * scale < STUCK_CONTRAST;
        }
        self.frames += 1;
    }

    /// The defective pixels found in the frames so far (a pixel with a
    /// stuck value is stuck), in row-major order.
    pub fn defects(&self) -> Result<Vec<PixelDefect>, NotDecided> {
        if self.mixed {
            return Err(NotDecided::Mixed);
        }
        if self.frames < MIN_FRAMES {
            return Err(NotDecided::TooFewFrames(self.frames));
        }
        let mut found: Vec<PixelDefect> = Vec::new();
        let accepted = self.accepted();
        for c in self.candidates.iter().filter(|c| accepted.binary_search(&c.value).is_ok()) {
            let p = c.value / 3;
            let kind = if c.stuck { DefectKind::Stuck } else { DefectKind::Dead };
            let d = PixelDefect { x: p % self.width, y: p / self.width, kind };
            match found.last_mut() {
                Some(last) if (last.x, last.y) == (d.x, d.y) => {
                    if kind == DefectKind::Stuck {
                        last.kind = kind;
                    }
                }
                _ => found.push(d),
            }
        }
        let examined = self.width as usize * self.height as usize;
        if found.len() as f64 > MAX_FRACTION * examined as f64 {
            return Err(NotDecided::TooMany { found: found.len(), examined });
        }
        Ok(found)
    }

    /// The candidate values (sorted) taken for defects. Candidates group
    /// into 8-connected clusters of one kind and channel. A single or a
    /// pair is a defect when each of its values stood out in some frame
    /// (the pair rule). A larger cluster is a saturated or black patch or
    /// line of the sample, ends included — except, on a uniform target
    /// ([`DefectFinder::uniform_target`]), a dead cluster within a
    /// [`MAX_CLUSTER_SIDE`] square whose surroundings were lit: every pixel
    /// around it but [`MAX_ALIKE_NEIGHBOURS`] read at least
    /// [`DEAD_CONTRAST_CODES`] in some frame.
    fn accepted(&self) -> Vec<u32> {
        let (w, h) = (self.width as i64, self.height as i64);
        let inside = |x: i64, y: i64| x >= 0 && y >= 0 && x < w && y < h;
        let by_value: std::collections::HashMap<u32, &Candidate> =
            self.candidates.iter().map(|c| (c.value, c)).collect();
        let mut seen = std::collections::HashSet::new();
        let mut out = Vec::new();
        for c in &self.candidates {
            if !seen.insert(c.value) {
                continue;
            }
            // The cluster: a flood over candidates of the same kind and
            // channel.
            let ch = c.value % 3;
            let mut cluster = vec![c.value];
            let mut i = 0;
            while i < cluster.len() {
                let p = (cluster[i] / 3) as i64;
                for (dx, dy) in NEIGHBOURS {
                    let (nx, ny) = (p % w + dx, p / w + dy);
                    if !inside(nx, ny) {
                        continue;
                    }
                    let v = 3 * (ny * w + nx) as u32 + ch;
                    if by_value.get(&v).is_some_and(|n| n.stuck == c.stuck) && seen.insert(v) {
                        cluster.push(v);
                    }
                }
                i += 1;
            }
            if cluster.len() <= 2 {
                out.extend(cluster.iter().filter(|v| by_value[v].contrast));
                continue;
            }
            if !self.clusters || c.stuck {
                continue;
            }
            let span = |coord: &dyn Fn(i64) -> i64| {
                let (lo, hi) = cluster
                    .iter()
                    .map(|&v| coord((v / 3) as i64))
                    .fold((i64::MAX, i64::MIN), |(l, h), x| (l.min(x), h.max(x)));
                hi - lo + 1
            };
            let side = MAX_CLUSTER_SIDE as i64;
            if span(&|p| p % w) > side || span(&|p| p / w) > side {
                continue;
            }
            // The pixels around it, and whether some frame lit them.
            let mut around: std::collections::HashMap<i64, bool> = Default::default();
            for &v in &cluster {
                let p = (v / 3) as i64;
                for (k, (dx, dy)) in NEIGHBOURS.iter().enumerate() {
                    let (nx, ny) = (p % w + dx, p / w + dy);
                    let q = ny * w + nx;
                    if inside(nx, ny) && !cluster.contains(&(3 * q as u32 + ch)) {
                        *around.entry(q).or_default() |= by_value[&v].lit & (1 << k) != 0;
                    }
                }
            }
            let unlit = around.values().filter(|&&lit| !lit).count();
            if unlit as u32 <= MAX_ALIKE_NEIGHBOURS {
                out.extend(cluster);
            }
        }
        out.sort_unstable();
        out
    }
}

/// A pixel of a dark frame (the light off, the scan's longest exposure)
/// at this many ADC codes or more is hot: its dark signal alone is what a
/// sample 250× darker than full scale gives (read noise: 1.2 codes RMS).
pub const HOT_CODES: f64 = 16.0;

/// A dark frame's median value above this many ADC codes is not dark (read
/// noise alone: 1.2 codes RMS, a median of 0 or 1).
pub const DARK_MEDIAN_CODES: u32 = 4;

/// The hot pixels a dark frame shows (values as stored: fractions of full
/// scale): any channel at [`HOT_CODES`] or more; at the top code, stuck.
/// A median above [`DARK_MEDIAN_CODES`]: not dark (a black level, stray
/// light). More than [`MAX_FRACTION`] of the frame: not a sensor's defects
/// (a light left on).
pub fn dark_frame_defects(frame: &Frame, max_code: f64) -> Result<Vec<PixelDefect>, NotDecided> {
    let (w, maxf, top) = (frame.width.max(1) as usize, max_code as f32, max_code as usize);
    // One pass: a histogram of every value's code (for the median), and
    // the pixels with a channel at the hot level.
    let mut histogram = vec![0usize; top + 1];
    let mut found: Vec<PixelDefect> = Vec::new();
    for (p, rgb) in frame.rgb.chunks_exact(3).enumerate() {
        let mut code = 0;
        for &v in rgb {
            let c = crate::hdr::adc_code(v, maxf, top);
            histogram[c] += 1;
            code = code.max(c);
        }
        let kind = if code == top {
            DefectKind::Stuck
        } else if code as f64 >= HOT_CODES {
            DefectKind::Hot
        } else {
            continue;
        };
        found.push(PixelDefect { x: (p % w) as u32, y: (p / w) as u32, kind });
    }
    let median = histogram_median(&histogram, frame.rgb.len());
    if median as u32 > DARK_MEDIAN_CODES {
        return Err(NotDecided::NotDark { median_codes: median as u32 });
    }
    let examined = frame.rgb.len() / 3;
    if found.len() as f64 > MAX_FRACTION * examined as f64 {
        return Err(NotDecided::TooMany { found: found.len(), examined });
    }
    Ok(found)
}

/// The median ADC code of a histogram of `count` values.
fn histogram_median(histogram: &[usize], count: usize) -> usize {
    let half = count.div_ceil(2);
    let mut below = 0;
    for (code, &n) in histogram.iter().enumerate() {
        below += n;
        if below >= half {
            return code;
        }
    }
    0
}

/// The black level a frame taken with the light off shows: its median ADC
/// code over every value, or 0 when that is read noise alone (at most
/// [`DARK_MEDIAN_CODES`]: subtracting a code or two of noise would bias a
/// camera without a black level).
pub fn black_level_codes(frame: &Frame, max_code: f64) -> u32 {
    let (maxf, top) = (max_code as f32, max_code as usize);
    let mut histogram = vec![0usize; top + 1];
    for &v in &frame.rgb {
        histogram[crate::hdr::adc_code(v, maxf, top)] += 1;
    }
    let median = histogram_median(&histogram, frame.rgb.len()) as u32;
    if median > DARK_MEDIAN_CODES { median } else { 0 }
}

/// How many of each kind: "3 stuck, 0 hot and 1 dead pixels".
pub fn counts(defects: &[PixelDefect]) -> String {
    let count = |k: DefectKind| defects.iter().filter(|d| d.kind == k).count();
    format!(
        "{} stuck, {} hot and {} dead pixels",
        count(DefectKind::Stuck),
        count(DefectKind::Hot),
        count(DefectKind::Dead)
    )
}

/// `a` and `b` together, in row-major order, one entry per pixel (stuck
/// where either says so).
pub fn union(a: &[PixelDefect], b: &[PixelDefect]) -> Vec<PixelDefect> {
    let mut all: Vec<PixelDefect> = a.iter().chain(b).copied().collect();
    all.sort_by_key(|d| (d.y, d.x, d.kind != DefectKind::Stuck));
    all.dedup_by_key(|d| (d.x, d.y));
    all
}

/// The defective pixels of one camera's frames, for lookups: a bit per
/// pixel (a lookup is one load, for the merge's every unmeasured value).
#[derive(Debug, Clone, Default)]
pub struct DefectMap {
    width: u32,
    height: u32,
    /// The defects, row-major, one per pixel ([`union`]).
    defects: Vec<PixelDefect>,
    /// Bit `i` set: pixel `i` is defective (empty when there are none).
    bits: Vec<u64>,
}

impl DefectMap {
    /// The map of `defects` in `width` × `height` frames (defects outside
    /// them are left out).
    pub fn new(defects: &[PixelDefect], width: u32, height: u32) -> DefectMap {
        let mut map = DefectMap { width, height, ..DefectMap::default() };
        map.extend(defects);
        map
    }

    /// Add `defects` (those outside the map's frame size are left out).
    pub fn extend(&mut self, defects: &[PixelDefect]) {
        let (w, h) = (self.width, self.height);
        let inside: Vec<PixelDefect> =
            defects.iter().filter(|d| d.x < w && d.y < h).copied().collect();
        self.defects = union(&self.defects, &inside);
        if !self.defects.is_empty() {
            self.bits = vec![0; (w as usize * h as usize).div_ceil(64)];
            for d in &self.defects {
                let p = d.y as usize * w as usize + d.x as usize;
                self.bits[p / 64] |= 1 << (p % 64);
            }
        }
    }

    /// The defects, row-major, one per pixel.
    pub fn defects(&self) -> &[PixelDefect] {
        &self.defects
    }

    /// No defects.
    pub fn is_empty(&self) -> bool {
        self.defects.is_empty()
    }

    /// Whether pixel `index` (row-major) of `frame` is defective (never, in
    /// a frame of another size than the map's).
    #[inline]
    pub fn contains(&self, frame: &Frame, index: usize) -> bool {
        (frame.width, frame.height) == (self.width, self.height) && self.contains_pixel(index)
    }

    /// The defects in row `y` of `frame` (none in a frame of another size
    /// than the map's), by column.
    pub fn row(&self, frame: &Frame, y: u32) -> &[PixelDefect] {
        if (frame.width, frame.height) != (self.width, self.height) {
            return &[];
        }
        let start = self.defects.partition_point(|d| d.y < y);
        let end = self.defects.partition_point(|d| d.y <= y);
        &self.defects[start..end]
    }

    /// Whether pixel `index` (row-major) of a frame of the map's size is
    /// defective.
    #[inline]
    pub fn contains_pixel(&self, index: usize) -> bool {
        self.bits.get(index / 64).is_some_and(|b| b & (1 << (index % 64)) != 0)
    }

    /// Replace every defective pixel of `frame` (of this map's size) by the
    /// mean, per channel, of its working neighbours within 1 pixel (2 if
    /// none; 0 if none there either). Returns the pixels replaced.
    pub fn patch(&self, frame: &mut Frame) -> usize {
        self.patch_where(frame, |_, _| true)
    }

    /// [`DefectMap::patch`] for a frame whose pixels hold values only where
    /// `usable(x, y)` (a frame read in windows): the defects there are
    /// replaced, from neighbours there.
    pub fn patch_where(&self, frame: &mut Frame, usable: impl Fn(usize, usize) -> bool) -> usize {
        let (w, h) = (frame.width as usize, frame.height as usize);
        if self.defects.is_empty()
            || (frame.width, frame.height) != (self.width, self.height)
            || frame.rgb.len() != 3 * w * h
        {
            return 0;
        }
        let mut patched = 0;
        for d in &self.defects {
            let (x, y) = (d.x as usize, d.y as usize);
            if !usable(x, y) {
                continue;
            }
            patched += 1;
            let mut value = [0.0f32; 3];
            for r in 1..=PATCH_RADIUS {
                let (mut sum, mut n) = ([0.0f32; 3], 0u32);
                for ny in y.saturating_sub(r)..=(y + r).min(h - 1) {
                    for nx in x.saturating_sub(r)..=(x + r).min(w - 1) {
                        if self.contains_pixel(ny * w + nx) || !usable(nx, ny) {
                            continue;
                        }
                        let i = 3 * (ny * w + nx);
                        for (s, v) in sum.iter_mut().zip(&frame.rgb[i..i + 3]) {
                            *s += v;
                        }
                        n += 1;
                    }
                }
                if n > 0 {
                    value = sum.map(|s| s / n as f32);
                    break;
                }
            }
            frame.rgb[3 * (y * w + x)..][..3].copy_from_slice(&value);
        }
        patched
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn geometry() -> ScannerGeometry {
        ScannerGeometry::default_scanner().with_sensor_scaled(8)
    }

    /// A frame of the sample's views: `level` everywhere, with a seeded
    /// ±3 % texture; frame `k` has a saturated highlight at a pixel of
    /// view 3 that moves with k.
    fn frame(g: &ScannerGeometry, level: f32, k: usize) -> Frame {
        let (w, h) = (g.camera.width, g.camera.height);
        let mut rgb: Vec<f32> = (0..3 * w as u64 * h as u64)
            .map(|i| {
                level * (1.0 + 0.03 * ((i.wrapping_mul(2_654_435_761) >> 7) % 100) as f32 / 100.0)
            })
            .collect();
        let p = g.view_point(3, [0.2 + 0.1 * k as f64, 0.5]).unwrap();
        let i = 3 * (p[1] as usize * w as usize + p[0] as usize);
        rgb[i..i + 3].fill(1.0);
        Frame { width: w, height: h, rgb }
    }

    /// The frame pixel where `view` shows sample point `uv`.
    fn pixel_at(g: &ScannerGeometry, view: usize, uv: [f64; 2]) -> (u32, u32) {
        let p = g.view_point(view, uv).unwrap();
        (p[0] as u32, p[1] as u32)
    }

    #[test]
    fn stuck_and_dead_pixels_are_found_and_the_sample_is_not() {
        let g = geometry();
        let (w, h) = (g.camera.width, g.camera.height);
        let at = |view: usize, uv: [f64; 2]| pixel_at(&g, view, uv);
        // Two single stuck pixels and a pair.
        let pair = at(30, [0.5, 0.5]);
        let stuck = [at(0, [0.5, 0.5]), at(7, [0.1, 0.9]), pair, (pair.0 + 1, pair.1)];
        let dead = at(12, [0.6, 0.3]);
        // A saturated 3 × 3 patch (bright sample) and a black one (dark
        // sample) that stay put: not defects.
        let (bx, by) = at(20, [0.5, 0.5]);
        let (kx, ky) = at(25, [0.5, 0.5]);
        let mut finder = DefectFinder::new(&g, w, h);
        for k in 0..6 {
            let mut f = frame(&g, 0.2 + 0.05 * k as f32, k);
            let mut set = |x: u32, y: u32, v: f32| {
                let i = 3 * (y * w + x) as usize;
                f.rgb[i..i + 3].fill(v);
            };
            for (x, y) in stuck {
                set(x, y, 1.0);
            }
            set(dead.0, dead.1, 0.0);
            for dy in 0..3 {
                for dx in 0..3 {
                    set(bx + dx, by + dy, 1.0);
                    set(kx + dx, ky + dy, 0.0);
                }
            }
            // A dark patch whose pixels read a code or two, and 0 (read
            // noise) on a sparse grid: its zeros on the edge have lit
            // neighbours on one side, dark ones on the other — not dead.
            let (ex, ey) = at(35, [0.3, 0.3]);
            for dy in 0..6 {
                for dx in 0..6 {
                    let zero = (ex + dx) % 3 == 0 && (ey + dy) % 3 == 0;
                    set(
                        ex + dx,
                        ey + dy,
                        if zero { 0.0 } else { 2.0 / g.sensor.max_code() as f32 },
                    );
                }
            }
            // A stuck pixel outside the sample's views is found too, a dead
            // one there cannot be seen.
            set(1, 1, 1.0);
            set(5, 1, 0.0);
            finder.add(&f);
        }
        let found = finder.defects().unwrap();
        let mut want: Vec<PixelDefect> = stuck
            .iter()
            .map(|&(x, y)| PixelDefect { x, y, kind: DefectKind::Stuck })
            .chain([PixelDefect { x: dead.0, y: dead.1, kind: DefectKind::Dead }])
            .chain([PixelDefect { x: 1, y: 1, kind: DefectKind::Stuck }])
            .collect();
        want.sort_by_key(|d| (d.y, d.x));
        assert_eq!(found, want);
        // Too few frames, or frames of two sizes: nothing decided.
        let mut few = DefectFinder::new(&g, w, h);
        for k in 0..3 {
            few.add(&frame(&g, 0.3, k));
        }
        assert_eq!(few.defects().unwrap_err(), NotDecided::TooFewFrames(3));
        let mut mixed = DefectFinder::new(&g, w, h);
        mixed.add(&Frame { width: 2, height: 2, rgb: vec![0.0; 12] });
        assert_eq!(mixed.defects().unwrap_err(), NotDecided::Mixed);
        // A frame black where the sample is: every pixel of it reads 0 but
        // none stands out, so none is a defect.
        let mut black = DefectFinder::new(&g, w, h);
        for _ in 0..5 {
            black.add(&Frame { width: w, height: h, rgb: vec![0.0; (3 * w * h) as usize] });
        }
        assert_eq!(black.defects().unwrap(), vec![]);
    }

    #[test]
    fn a_uniform_targets_frames_show_dead_clusters() {
        let g = geometry();
        let (w, h) = (g.camera.width, g.camera.height);
        let at = |view: usize, uv: [f64; 2]| pixel_at(&g, view, uv);
        let shape = |(x, y): (u32, u32), offsets: &[(u32, u32)]| -> Vec<(u32, u32)> {
            offsets.iter().map(|&(dx, dy)| (x + dx, y + dy)).collect()
        };
        let clusters = [
            shape(at(2, [0.5, 0.5]), &[(0, 0), (1, 0), (2, 0)]), // a row of 3
            shape(at(9, [0.4, 0.6]), &[(0, 0), (1, 0), (0, 1), (1, 1)]), // 2 × 2
            shape(at(14, [0.5, 0.5]), &[(1, 0), (0, 1), (1, 1), (2, 1), (1, 2)]), // a plus
            shape(at(22, [0.5, 0.5]), &[(0, 0), (1, 1), (2, 2)]), // a diagonal
            (0..3)
                .flat_map(|y| (0..3).map(move |x| (x, y)))
                .map(|(x, y)| {
                    let (cx, cy) = at(27, [0.5, 0.5]);
                    (cx + x, cy + y)
                })
                .collect(), // 3 × 3
        ];
        // Too big for a cluster: 4 in a row, and a 4 × 4 block.
        let too_big = [
            shape(at(31, [0.5, 0.5]), &[(0, 0), (1, 0), (2, 0), (3, 0)]),
            (0..4)
                .flat_map(|y| (0..4).map(move |x| (x, y)))
                .map(|(x, y)| {
                    let (cx, cy) = at(36, [0.5, 0.5]);
                    (cx + x, cy + y)
                })
                .collect::<Vec<_>>(),
        ];
        // `blanked`: the pixels of every 2 × 2 block the finder does not
        // examine are 0, as a reader that skips them leaves them.
        let run = |mut finder: DefectFinder, blanked: bool| {
            let mut examined = Vec::new();
            for k in 0..6 {
                let mut f = frame(&g, 0.3 + 0.05 * k as f32, k);
                // The 2 × 2 cluster's surroundings dark (not 0) in the
                // first two frames: it is told from a black spot only by
                // the later frames' neighbours.
                if k < 2 {
                    let (cx, cy) = clusters[1][0];
                    for (x, y) in
                        (cy - 1..cy + 3).flat_map(|y| (cx - 1..cx + 3).map(move |x| (x, y)))
                    {
                        let i = 3 * (y * w + x) as usize;
                        f.rgb[i..i + 3].fill(4.0 / g.sensor.max_code() as f32);
                    }
                }
                for (x, y) in clusters.iter().chain(&too_big).flatten() {
                    let i = 3 * (y * w + x) as usize;
                    f.rgb[i..i + 3].fill(0.0);
                }
                let mut blocks = 0;
                for (bx, by) in
                    (0..h as usize / 2).flat_map(|y| (0..w as usize / 2).map(move |x| (x, y)))
                {
                    let [x, y] = [2 * bx, 2 * by];
                    if finder.examines([x, y, x + 2, y + 2]) {
                        blocks += 1;
                    } else if blanked {
                        for row in y..y + 2 {
                            f.rgb[3 * (row * w as usize + x)..][..6].fill(0.0);
                        }
                    }
                }
                examined.push(blocks as f64 / (w * h / 4) as f64);
                finder.add(&f);
            }
            (finder.defects().unwrap(), examined)
        };
        let mut want: Vec<PixelDefect> = clusters
            .iter()
            .flatten()
            .map(|&(x, y)| PixelDefect { x, y, kind: DefectKind::Dead })
            .collect();
        want.sort_by_key(|d| (d.y, d.x));
        for blanked in [false, true] {
            let (found, examined) = run(DefectFinder::uniform_target(&g, w, h), blanked);
            assert_eq!(found, want, "blanked: {blanked}");
            // All of the first frame, then the candidates' surroundings.
            assert_eq!(examined[0], 1.0);
            assert!(examined[1..].iter().all(|&e| e < 0.01), "{examined:?}");
            // On a sample a cluster is a black spot: none of it is taken,
            // not even the ends of a row, whose one dead neighbour the pair
            // rule allows.
            assert_eq!(run(DefectFinder::new(&g, w, h), blanked).0, vec![]);
        }
    }

    #[test]
    fn a_dark_frame_shows_hot_and_stuck_pixels() {
        let max = 4095.0;
        let code = |c: f64| (c / max) as f32;
        // Read noise: 0–4 codes; a pixel at 20 codes in green, one at the top.
        let mut rgb: Vec<f32> = (0..3 * 64 * 8).map(|i| code((i % 5) as f64)).collect();
        rgb[3 * (3 * 64 + 10) + 1] = code(20.0);
        rgb[3 * (5 * 64 + 40)..][..3].fill(1.0);
        let f = Frame { width: 64, height: 8, rgb };
        assert_eq!(
            dark_frame_defects(&f, max).unwrap(),
            vec![
                PixelDefect { x: 10, y: 3, kind: DefectKind::Hot },
                PixelDefect { x: 40, y: 5, kind: DefectKind::Stuck },
            ]
        );
        // The light left on over a third of the frame (the sample's views):
        // everything there "hot", nothing recorded.
        let mut lit = f.clone();
        lit.rgb[..3 * 64 * 3].fill(0.3);
        assert!(matches!(dark_frame_defects(&lit, max), Err(NotDecided::TooMany { .. })));
        // A black level of 64 codes (or stray light) over the whole frame:
        // not dark, said with its median.
        let offset = Frame { rgb: f.rgb.iter().map(|v| v + code(64.0)).collect(), ..f.clone() };
        assert_eq!(
            dark_frame_defects(&offset, max).unwrap_err(),
            NotDecided::NotDark { median_codes: 66 }
        );
        // A median of a few codes is still dark.
        let low = Frame { rgb: f.rgb.iter().map(|v| v + code(2.0)).collect(), ..f.clone() };
        assert_eq!(dark_frame_defects(&low, max).unwrap().len(), 2);
        // The black level `--black-level auto` takes: the offset frame's
        // median; none for noise of a code or two.
        assert_eq!(black_level_codes(&offset, max), 66);
        assert_eq!(black_level_codes(&low, max), 0);
        assert_eq!(black_level_codes(&f, max), 0);
    }

    #[test]
    fn too_many_are_not_defects_and_patching_takes_the_neighbours_mean() {
        let g = geometry();
        let (w, h) = (g.camera.width, g.camera.height);
        // Every 4th pixel of every 2nd row stuck: a pattern, not a sensor.
        let mut finder = DefectFinder::new(&g, w, h);
        for k in 0..4 {
            let mut f = frame(&g, 0.3, k);
            for p in (0..(w * h) as usize)
                .filter(|p| p.is_multiple_of(4) && (p / w as usize).is_multiple_of(2))
            {
                f.rgb[3 * p..3 * p + 3].fill(1.0);
            }
            finder.add(&f);
        }
        assert!(matches!(finder.defects(), Err(NotDecided::TooMany { .. })));
        // Patching: the mean of working neighbours, two adjacent defects.
        let mut f = Frame { width: 5, height: 4, rgb: (0..60).map(|i| i as f32).collect() };
        let d = |x, y| PixelDefect { x, y, kind: DefectKind::Stuck };
        let map = DefectMap::new(&[d(2, 1), d(3, 1), d(9, 9)], 5, 4);
        assert!(map.contains(&f, 7) && map.contains(&f, 8) && !map.contains(&f, 6));
        let before = f.clone();
        assert_eq!(map.patch(&mut f), 2);
        // (2, 1): neighbours (1..=3, 0..=2) but (3, 1), red channel.
        let red = |x: usize, y: usize| before.rgb[3 * (y * 5 + x)];
        let want = [(1, 0), (2, 0), (3, 0), (1, 1), (1, 2), (2, 2), (3, 2)]
            .iter()
            .map(|&(x, y)| red(x, y))
            .sum::<f32>()
            / 7.0;
        assert_eq!(f.rgb[3 * 7], want);
        let changed: Vec<usize> = (0..20).filter(|&p| f.rgb[3 * p] != before.rgb[3 * p]).collect();
        assert_eq!(changed, vec![7, 8]);
        // Another size: untouched.
        let mut other = Frame { width: 4, height: 5, rgb: vec![1.0; 60] };
        assert_eq!(map.patch(&mut other), 0);
        assert!(!map.contains(&other, 7));
    }
}
