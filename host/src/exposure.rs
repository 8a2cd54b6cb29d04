//! Auto exposure (`scanner scan --exposure-us auto`, docs/scan-format.md,
//! "Auto exposure"): a few metering frames, the sample's values in them,
//! and the exposure or HDR bracket chosen from those values.
//!
//! A fixed exposure suits one brightness only: at the default 50 ms the
//! diffuse-white target reaches ≈ 0.2 of full scale and a near-black
//! sample ≈ 0.01 (a few dozen electrons: shot noise of 10 % per pixel),
//! while a polished metal's highlights pass it 20-fold. Metering puts the
//! bulk of the sample's values high on the sensor's range in the longest
//! exposure and extends the bracket down until its highlights fit.
//!
//! The values are read where the nominal geometry projects the sample's
//! central half (uv 0.25…0.75) in every view, so that neither the holder
//! around it nor the as-built scanner's offsets (≈ 24 px) count.

use serde::{Deserialize, Serialize};

use crate::camera::Frame;
use scanner_geometry::ScannerGeometry;

/// Percentile of the sample's values that sets the longest exposure.
pub const BODY_PERCENTILE: f64 = 0.95;
/// Where the longest exposure of an HDR bracket puts that percentile, as
/// a fraction of full scale (the shorter exposures take what it clips).
pub const HDR_BODY_TARGET: f64 = 0.5;
/// Percentile taken as the sample's peak (robust to a few hot pixels).
pub const PEAK_PERCENTILE: f64 = 0.9999;
/// Where the shortest exposure of a bracket (or a single auto exposure)
/// must keep the peak, as a fraction of full scale.
pub const PEAK_TARGET: f64 = 0.8;
/// Longest exposure auto exposure picks, µs: a 40-mirror scan then spends
/// at most ≈ 40 s more exposing than at the default.
pub const AUTO_MAX_US: u32 = 1_000_000;
/// Ratio between consecutive exposures of an auto bracket.
pub const BRACKET_STEP: u32 = 5;
/// Exposures of an auto bracket: at least this many, for highlights at
/// mirrors that were not metered (25× headroom above the longest's full scale)…
pub const BRACKET_MIN_LEN: usize = 3;
/// … and at most this many.
pub const BRACKET_MAX_LEN: usize = 5;
/// Mirrors metered (spread over those scanned).
pub const METER_MIRRORS: usize = 8;
/// A metering frame whose body is above this fraction of full scale is
/// taken again 10× shorter.
const BODY_TOO_BRIGHT: f64 = 0.9;
/// Values at or above this fraction of full scale are saturated.
pub(crate) const SATURATED: f32 = 0.999;
/// The dimmest light duty, ‰, that stands in for an exposure shorter than
/// the device's shortest ([`protocol::MIN_EXPOSURE_US`]): 1 µs of light
/// per 50 µs period of the board's 20 kHz PWM, which a constant-current
/// LED driver switches cleanly. Exposures below 1 ms reach down to 20 µs.
pub const MIN_DIM_PERMILLE: u16 = 20;

/// The shortest exposure a scan can take at light duty `duty` ‰, µs:
/// at full duty the device's shortest exposure dimmed to
/// [`MIN_DIM_PERMILLE`], else the device's shortest.
///
/// Exposures are counted in µs of light at the scan's duty. One shorter
/// than [`protocol::MIN_EXPOSURE_US`] is taken as that exposure with the
/// light dimmed in proportion ([`realise`]): the camera integrates
/// 1 ms = 20 whole periods of the light's PWM, so it collects exactly
/// the light of a `t` µs exposure at full duty, from the same scene.
pub fn shortest_us(duty: u16) -> u32 {
    if duty == protocol::FULL_DUTY_PERMILLE {
        protocol::MIN_EXPOSURE_US * MIN_DIM_PERMILLE as u32 / protocol::FULL_DUTY_PERMILLE as u32
    } else {
        protocol::MIN_EXPOSURE_US
    }
}

/// How an exposure of `t` µs of light at duty `duty` ‰ is taken: (the
/// device's exposure, µs; its light duty, ‰). Below the device's shortest
/// exposure (at full duty only): 1 ms with the light at `t` ‰.
/// `None` below [`shortest_us`] or above the device's longest.
pub fn realise(t: u32, duty: u16) -> Option<(u32, u16)> {
    if !(shortest_us(duty)..=protocol::MAX_EXPOSURE_US).contains(&t) {
        return None;
    }
    if t >= protocol::MIN_EXPOSURE_US {
        return Some((t, duty));
    }
    // t µs of light in 1 000 µs: t ‰.
    let permille = t * protocol::FULL_DUTY_PERMILLE as u32 / protocol::MIN_EXPOSURE_US;
    Some((protocol::MIN_EXPOSURE_US, permille as u16))
}

/// What metering measured and chose (recorded in the scan's settings).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Metering {
    /// The exposure the metering frames were taken at, µs.
    pub exposure_us: u32,
    /// The mirrors metered.
    pub mirrors: Vec<usize>,
    /// [`BODY_PERCENTILE`] of the sample's values, fraction of full scale
    /// at `exposure_us`.
    pub body: f64,
    /// [`PEAK_PERCENTILE`] of the sample's values, in the same units (above
    /// 1 when it saturated at `exposure_us` and was measured at
    /// `peak_exposure_us`); `None` when it saturated even there.
    pub peak: Option<f64>,
    /// The exposure the peak was measured at, µs (`exposure_us`, or
    /// shorter metering frames when the peak saturated at it).
    #[serde(default)]
    pub peak_exposure_us: u32,
    /// The sensor's defective pixels the metering frames showed
    /// ([`crate::defects`]); the scan's frames have them replaced.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub defects: Vec<crate::defects::PixelDefect>,
}

/// The exposures auto exposure chose.
#[derive(Debug, Clone, PartialEq)]
pub struct Choice {
    /// The (longest) exposure, µs.
    pub exposure_us: u32,
    /// HDR: every exposure per mirror, ascending (empty: one exposure).
    pub bracket_us: Vec<u32>,
}

/// The mirrors to meter among the first `total`: [`METER_MIRRORS`] spread
/// evenly (all of them if fewer).
pub fn meter_mirrors(total: usize) -> Vec<usize> {
    let n = METER_MIRRORS.min(total);
    let mut m: Vec<usize> = (0..n).map(|k| k * total / n).collect();
    m.dedup();
    m
}

/// The sample's pixels in `frame` (index, RGB as fractions of full scale):
/// nearest pixels at 11 × 11 points over the central half of the sample in
/// each of the geometry's views.
pub fn sample_pixels(frame: &Frame, g: &ScannerGeometry) -> Vec<(u32, [f32; 3])> {
    (0..g.mirrors.len()).flat_map(|view| view_pixels(frame, g, view)).collect()
}

/// [`sample_pixels`] of one view: those within the frame.
pub fn view_pixels(frame: &Frame, g: &ScannerGeometry, view: usize) -> Vec<(u32, [f32; 3])> {
    let (w, h) = (frame.width as usize, frame.height as usize);
    let mut out = Vec::new();
    for j in 0..11 {
        for i in 0..11 {
            let uv = [0.25 + 0.05 * i as f64, 0.25 + 0.05 * j as f64];
            let Some(p) = g.view_point(view, uv) else { continue };
            if !(p[0] >= 0.0 && p[1] >= 0.0) {
                continue;
            }
            let (x, y) = (p[0] as usize, p[1] as usize);
            if x < w && y < h && frame.rgb.len() >= 3 * w * h {
                let px = y * w + x;
                let v = &frame.rgb[3 * px..3 * px + 3];
                out.push((px as u32, [v[0], v[1], v[2]]));
            }
        }
    }
    out
}

/// The values (every channel) of `pixels` (of frames of the map's size),
/// the sensor's `defects` left out.
pub fn sample_values(pixels: &[(u32, [f32; 3])], defects: &crate::defects::DefectMap) -> Vec<f32> {
    pixels
        .iter()
        .filter(|(p, _)| !defects.contains_pixel(*p as usize))
        .flat_map(|(_, v)| *v)
        .collect()
}

/// How far around the sample, in sample sides, a saturated value counts
/// against an auto bracket: the as-built scanner's offsets (≈ 24 px, up to
/// ≈ 0.2 of a view's side) and the sample's edge.
pub const CLIP_MARGIN: f64 = 0.25;

/// Frame pixels of one row: (row, first column, end column).
pub type Span = (u32, u32, u32);

/// The pixels of a `width` × `height` frame where the geometry's views show
/// the sample, [`CLIP_MARGIN`] around it included: per view, the rows of
/// the projected square uv ∈ [−m, 1 + m]² (convex: the projection is a
/// homography). Views that do not project are left out.
pub fn sample_spans(g: &ScannerGeometry, width: u32, height: u32) -> Vec<Span> {
    let (lo, hi) = (-CLIP_MARGIN, 1.0 + CLIP_MARGIN);
    let mut out = Vec::new();
    for view in 0..g.mirrors.len() {
        let corners = [[lo, lo], [hi, lo], [hi, hi], [lo, hi]].map(|uv| g.view_point(view, uv));
        let Some(q) = corners.into_iter().collect::<Option<Vec<[f64; 2]>>>() else { continue };
        if q.iter().flatten().any(|c| !c.is_finite()) {
            continue;
        }
        let y_min = q.iter().map(|p| p[1]).fold(f64::INFINITY, f64::min).max(0.0);
        let y_max = q.iter().map(|p| p[1]).fold(f64::NEG_INFINITY, f64::max).min(height as f64);
        let mut y = y_min.floor();
        while y < y_max {
            // Where the row's centre line crosses the quad's edges.
            let yc = y + 0.5;
            let (mut x0, mut x1) = (f64::INFINITY, f64::NEG_INFINITY);
            for k in 0..4 {
                let (a, b) = (q[k], q[(k + 1) % 4]);
                if (a[1] <= yc) != (b[1] <= yc) {
                    let x = a[0] + (yc - a[1]) / (b[1] - a[1]) * (b[0] - a[0]);
                    (x0, x1) = (x0.min(x), x1.max(x));
                }
            }
            let (first, end) = (x0.floor().max(0.0), x1.ceil().min(width as f64));
            if first < end {
                out.push((y as u32, first as u32, end as u32));
            }
            y += 1.0;
        }
    }
    out
}

/// Values (every channel) of `frame` at the sensor's top code within
/// `spans`, the pixels of `defects` left out.
pub fn saturated_in(
    frame: &Frame,
    spans: &[Span],
    max_code: f64,
    defects: &crate::defects::DefectMap,
) -> usize {
    let (w, top) = (frame.width as usize, max_code as usize);
    let maxf = max_code as f32;
    spans
        .iter()
        .filter_map(|&(y, x0, x1)| {
            let first = y as usize * w + x0 as usize;
            frame.rgb.get(3 * first..3 * (y as usize * w + x1 as usize)).map(|row| (first, row))
        })
        .map(|(first, row)| {
            row.iter()
                .enumerate()
                .filter(|&(i, &v)| {
                    crate::hdr::adc_code(v, maxf, top) == top
                        && !defects.contains(frame, first + i / 3)
                })
                .count()
        })
        .sum()
}

/// The exposure an auto HDR bracket adds at a mirror whose shortest
/// exposure so far, `taken_us`, left `saturated` values on the sample
/// (highlights that metering did not see: at a mirror it did not meter,
/// or rarer than its peak percentile): [`BRACKET_STEP`]× shorter, down to
/// `floor_us` ([`shortest_us`]). `None` when nothing saturated or it is there.
pub fn extension(taken_us: u32, saturated: usize, floor_us: u32) -> Option<u32> {
    (saturated > 0 && taken_us > floor_us).then(|| (taken_us / BRACKET_STEP).max(floor_us))
}

/// The `p` quantile of `values` (sorted in place), nearest rank; 0 for none.
fn quantile(values: &mut [f32], p: f64) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    values.sort_unstable_by(f32::total_cmp);
    values[((values.len() - 1) as f64 * p).round() as usize] as f64
}

/// Body and peak of the values of metering frames taken at one exposure;
/// whether the body is too bright to measure at it.
pub fn measure(values: &mut [f32]) -> (f64, Option<f64>, bool) {
    let body = quantile(values, BODY_PERCENTILE);
    let peak = quantile(values, PEAK_PERCENTILE);
    let peak = (peak < SATURATED as f64).then_some(peak);
    (body, peak, body > BODY_TOO_BRIGHT)
}

/// The exposure (or, with `hdr`, the bracket) for what `metering` saw,
/// none shorter than `floor_us` ([`shortest_us`]).
///
/// - One exposure: the peak at [`PEAK_TARGET`] of full scale (the body at
///   [`HDR_BODY_TARGET`] if the peak saturated), within `floor_us`, the
///   device's longest and [`AUTO_MAX_US`].
/// - HDR: the longest exposure puts the body at [`HDR_BODY_TARGET`] of
///   full scale and the shortest the peak at [`PEAK_TARGET`] (a peak that
///   saturated every metering frame: `floor_us`), with
///   equal ratios of at most [`BRACKET_STEP`] between them — so the body
///   and the highlights are each measured high on the sensor's range. At
///   least [`BRACKET_MIN_LEN`] exposures (more, [`BRACKET_STEP`]× shorter,
///   as headroom for highlights at mirrors that were not metered), at most
///   [`BRACKET_MAX_LEN`] (a wider range gives up the top of the peak).
pub fn choose(metering: &Metering, hdr: bool, floor_us: u32) -> Choice {
    let (min, max) = (floor_us as f64, AUTO_MAX_US.min(protocol::MAX_EXPOSURE_US) as f64);
    let t_m = metering.exposure_us as f64;
    // The exposure at which a value `v` (at the metering exposure) reaches `target`.
    let at = |v: f64, target: f64| {
        let t = if v > 0.0 { t_m * target / v } else { f64::INFINITY };
        t.clamp(min, max)
    };
    if !hdr {
        let t = match metering.peak {
            Some(p) => at(p, PEAK_TARGET),
            None => at(metering.body, HDR_BODY_TARGET),
        };
        return Choice { exposure_us: t.round() as u32, bracket_us: Vec::new() };
    }
    let top = at(metering.body, HDR_BODY_TARGET);
    let bottom = metering.peak.map_or(min, |p| at(p, PEAK_TARGET)).min(top);
    let step = BRACKET_STEP as f64;
    let mut steps = ((top / bottom).ln() / step.ln() - 1e-9).ceil().max(0.0) as i32;
    let mut ratio = if steps > 0 { (top / bottom).powf(1.0 / steps as f64) } else { step };
    if steps as usize >= BRACKET_MAX_LEN {
        steps = BRACKET_MAX_LEN as i32 - 1;
        ratio = step;
    }
    let mut bracket: Vec<f64> = (0..=steps).map(|k| top / ratio.powi(k)).collect();
    while bracket.len() < BRACKET_MIN_LEN {
        let shortest = *bracket.last().expect("one exposure");
        bracket.push(shortest / step);
    }
    let mut bracket: Vec<u32> =
        bracket.into_iter().map(|t| t.clamp(min, max).round() as u32).collect();
    bracket.sort_unstable();
    bracket.dedup();
    Choice { exposure_us: *bracket.last().expect("one exposure"), bracket_us: bracket }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The device's shortest exposure as the floor (no dimming).
    const MS: u32 = protocol::MIN_EXPOSURE_US;

    fn metering(body: f64, peak: Option<f64>) -> Metering {
        Metering {
            exposure_us: 50_000,
            mirrors: vec![0],
            body,
            peak,
            peak_exposure_us: 50_000,
            defects: Vec::new(),
        }
    }

    #[test]
    fn a_dark_sample_gets_a_long_exposure_and_a_bright_one_a_short_one() {
        // Body 0.02 of full scale at 50 ms: 0.5 at 1.25 s, capped at 1 s;
        // the peak fits there: two more, 5× shorter each, as headroom.
        let c = choose(&metering(0.02, Some(0.03)), true, MS);
        assert_eq!(c.exposure_us, AUTO_MAX_US);
        assert_eq!(c.bracket_us, vec![40_000, 200_000, 1_000_000]);
        // Body 0.1: 250 ms; the peak (0.2) at 0.8 of full scale at 200 ms.
        let c = choose(&metering(0.1, Some(0.2)), true, MS);
        assert_eq!(c.bracket_us, vec![40_000, 200_000, 250_000]);
        // One exposure: the peak at 0.8 of full scale.
        assert_eq!(choose(&metering(0.1, Some(0.2)), false, MS).exposure_us, 200_000);
        assert!(choose(&metering(0.1, Some(0.2)), false, MS).bracket_us.is_empty());
    }

    #[test]
    fn the_bracket_spans_body_to_peak_in_equal_steps_of_at_most_5() {
        // Body 0.25 at 50 ms: longest 100 ms; peak 20× full scale: 2 ms
        // holds it at 0.8. 50× in three equal steps of 3.68×.
        let c = choose(&metering(0.25, Some(20.0)), true, MS);
        assert_eq!(c.bracket_us, vec![2_000, 7_368, 27_144, 100_000]);
        // Saturated peak: down to the device's shortest, at most five exposures
        // (a range beyond 5⁴ gives up the top of the peak).
        let c = choose(&metering(0.4, None), true, MS);
        assert_eq!(c.bracket_us, vec![1_000, 3_969, 15_749, 62_500]);
        let c = choose(&metering(0.001, None), true, MS);
        assert_eq!(c.bracket_us, vec![1_600, 8_000, 40_000, 200_000, 1_000_000]);
        for c in
            [choose(&metering(0.25, Some(20.0)), true, MS), choose(&metering(0.4, None), true, MS)]
        {
            assert!(c.bracket_us.windows(2).all(|w| w[1] as f64 / w[0] as f64 <= 5.0 + 1e-3));
        }
    }

    #[test]
    fn exposures_below_the_devices_shortest_dim_the_light() {
        let full = protocol::FULL_DUTY_PERMILLE;
        assert_eq!(shortest_us(full), 20);
        assert_eq!(shortest_us(500), protocol::MIN_EXPOSURE_US);
        assert_eq!(realise(50_000, full), Some((50_000, full)));
        assert_eq!(realise(1_000, full), Some((1_000, full)));
        // t µs of light in the device's 1 ms: t ‰.
        assert_eq!(realise(999, full), Some((1_000, 999)));
        assert_eq!(realise(40, full), Some((1_000, 40)));
        assert_eq!(realise(20, full), Some((1_000, MIN_DIM_PERMILLE)));
        assert_eq!(realise(19, full), None);
        assert_eq!(realise(protocol::MAX_EXPOSURE_US + 1, full), None);
        // At a duty of its own the scan is not dimmed further.
        assert_eq!(realise(5_000, 500), Some((5_000, 500)));
        assert_eq!(realise(999, 500), None);
        // A peak that saturates 1 ms gets a bracket down to where it fits,
        // or to the floor; equal steps of at most 5×.
        let c = choose(&metering(0.25, Some(200.0)), true, shortest_us(full));
        assert_eq!(c.bracket_us, vec![200, 946, 4_472, 21_147, 100_000]);
        let c = choose(&metering(0.25, None), true, shortest_us(full));
        assert_eq!(c.bracket_us, vec![160, 800, 4_000, 20_000, 100_000], "five at most");
        let c = choose(&metering(0.25, Some(20.0)), false, shortest_us(full));
        assert_eq!(c.exposure_us, 2_000);
        let c = choose(&metering(0.9, Some(4000.0)), false, shortest_us(full));
        assert_eq!(c.exposure_us, 20);
    }

    #[test]
    fn a_black_frame_gets_the_longest_exposure_and_measure_finds_saturation() {
        let c = choose(&metering(0.0, Some(0.0)), true, MS);
        assert_eq!(c.exposure_us, AUTO_MAX_US);
        let mut v: Vec<f32> = (0..10_000).rev().map(|i| i as f32 / 20_000.0).collect();
        let (body, peak, too_bright) = measure(&mut v);
        assert!((body - 0.475).abs() < 1e-3 && !too_bright, "{body}");
        assert!((peak.unwrap() - 0.49995).abs() < 1e-3, "{peak:?}");
        let mut v = vec![1.0f32; 100];
        assert_eq!(measure(&mut v), (1.0, None, true));
        assert_eq!(meter_mirrors(40), vec![0, 5, 10, 15, 20, 25, 30, 35]);
        assert_eq!(meter_mirrors(3), vec![0, 1, 2]);
    }

    #[test]
    fn saturation_counts_on_the_sample_only_and_extends_the_bracket_down_to_the_device() {
        let g = ScannerGeometry::default_scanner().with_sensor_scaled(8);
        let (w, h) = (g.camera.width, g.camera.height);
        let spans = sample_spans(&g, w, h);
        let inside = |p: [f64; 2]| {
            let (x, y) = (p[0] as u32, p[1] as u32);
            spans.iter().any(|&(r, a, b)| r == y && (a..b).contains(&x))
        };
        // Every view's sample, corners and centre, is covered; the margin
        // is bounded (the views cover a small part of the frame).
        for view in 0..g.mirrors.len() {
            for uv in [[0.0, 0.0], [1.0, 0.0], [0.5, 0.5], [0.0, 1.0], [0.99, 0.99]] {
                assert!(inside(g.view_point(view, uv).unwrap()), "view {view} at {uv:?}");
            }
        }
        let covered: u64 = spans.iter().map(|&(_, a, b)| (b - a) as u64).sum();
        assert!(covered < (w as u64 * h as u64) / 2, "{covered} of {w}×{h}");
        // Top codes count inside the spans only, every channel.
        let mut f = Frame { width: w, height: h, rgb: vec![0.2; (3 * w * h) as usize] };
        let p = g.view_point(7, [0.3, 0.6]).unwrap();
        let at = 3 * (p[1] as usize * w as usize + p[0] as usize);
        f.rgb[at..at + 3].fill(1.0);
        let outside = (0..w * h).find(|&i| !inside([(i % w) as f64, (i / w) as f64])).unwrap();
        f.rgb[3 * outside as usize] = 1.0;
        // Half-float storage leaves the top code a fraction of a code low.
        f.rgb[at + 2] = 1.0 - 0.3 / g.sensor.max_code() as f32;
        let none = crate::defects::DefectMap::default();
        assert_eq!(saturated_in(&f, &spans, g.sensor.max_code(), &none), 3);
        // A defective pixel is left out.
        let stuck = crate::defects::PixelDefect {
            x: p[0] as u32,
            y: p[1] as u32,
            kind: crate::defects::DefectKind::Stuck,
        };
        let map = crate::defects::DefectMap::new(&[stuck], w, h);
        assert_eq!(saturated_in(&f, &spans, g.sensor.max_code(), &map), 0);
        assert_eq!(extension(50_000, 0, MS), None);
        assert_eq!(extension(50_000, 3, MS), Some(10_000));
        assert_eq!(extension(3_000, 1, MS), Some(protocol::MIN_EXPOSURE_US));
        assert_eq!(extension(protocol::MIN_EXPOSURE_US, 9, MS), None);
        // With the light dimmed, on below the device's shortest exposure.
        let floor = shortest_us(protocol::FULL_DUTY_PERMILLE);
        assert_eq!(extension(protocol::MIN_EXPOSURE_US, 9, floor), Some(200));
        assert_eq!(extension(200, 9, floor), Some(40));
        assert_eq!(extension(40, 9, floor), Some(20));
        assert_eq!(extension(20, 9, floor), None);
    }
}
