//! HDR merging of an exposure bracket into one linear frame, weighted by
//! the sensor's noise model (docs/scan-format.md, "HDR").
//!
//! For each pixel and channel, the exposures whose ADC code c_k is neither
//! black (0: clipped at zero) nor saturated (the top code: clipped at the
//! full well), and clear of both by 3σ where the same channel two pixels
//! along says so, each estimate the rate r_k = v_k / t_k. Its variance
//! follows the sensor: electrons e = c / g (g = codes per electron),
//! Var(c) = g² (e + σ_read²) + 1/12 (quantisation), so Var(r_k) =
//! Var(c_k) / (max_code · t_k)², with c_k the mean code two pixels along.
//! The merged rate is the inverse-variance weighted mean; the output is it
//! times the reference exposure, in the frames' units (ADC code / max
//! code). A pixel black in every exposure is 0; one saturated in every
//! exposure keeps the shortest exposure's (clipped) value and is counted.

use scanner_geometry::SensorSpec;

use crate::camera::Frame;
use crate::defects::DefectMap;

/// What a merge found.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MergeStats {
    /// Values saturated in every exposure (still clipped after merging).
    pub clipped: usize,
    /// Values black in every exposure.
    pub black: usize,
}

/// How many standard deviations of its predicted code an exposure must
/// keep from either clip (0 and the top code) to count, where another
/// exposure measures the value. Values kept only while noise leaves them
/// short of a clip are a truncated draw: their mean is off (−0.37 % at
/// the longest exposure's full scale, session 42).
pub const CLEAR_SIGMAS: f64 = 3.0;

/// The most exposures one merge takes: one bit each in the masks of its
/// steps (`u32`).
pub const MAX_EXPOSURES: usize = u32::BITS as usize;

/// A value's level is judged from the pixels two along (the same channel:
/// 6 values), not from its own noisy value: by the merge (whether an
/// exposure is clear of its clips, how much its code varies) and by the
/// exposures' agreement (which values to compare). A choice or a weight
/// that follows the value's own noise biases the result: +0.66 % at 0.94
/// of the longest exposure's full scale when the merge predicted the clip
/// from the shorter exposures (session 42); a ratio of 1.15 for a white
/// sample seen through a grazing mirror, where the light is 1, when the
/// agreement judged the level by the value itself (session 41). Two
/// pixels, so that a Bayer sensor's demosaicing shares none of the value's
/// noise with them.
const ALONG: usize = 6;

/// The sensor's noise in ADC codes: Var(c) = g·c + g²σ_read² + 1/12 for a
/// code (or a predicted mean code) c: shot noise of its c/g electrons,
/// read noise and quantisation, at g codes per electron.
#[derive(Debug, Clone, Copy)]
struct CodeNoise {
    gain: f32,
    floor: f32,
    /// The top code less the black level: where a value saturates.
    top: f32,
    /// The highest mean code [`CLEAR_SIGMAS`] of its noise below the top.
    clear_top: f32,
    /// The lowest mean code [`CLEAR_SIGMAS`] of its noise above 0.
    clear_black: f32,
}

impl CodeNoise {
    /// The noise of `sensor`'s codes after the camera subtracted
    /// `black_codes` from every value (docs/scan-format.md,
    /// `settings.black_level_codes`): a value then clips at the top code
    /// minus the black level.
    fn new(sensor: &SensorSpec, black_codes: u32) -> CodeNoise {
        let max = sensor.max_code();
        let top = (max - black_codes as f64).max(0.0);
        let gain = max / sensor.full_well_e;
        let floor = gain * gain * sensor.read_noise_e * sensor.read_noise_e + 1.0 / 12.0;
        // (top − μ)² = z²(gμ + F), the root below the top; μ² = z²(gμ + F).
        let z2 = CLEAR_SIGMAS * CLEAR_SIGMAS;
        let b = 2.0 * top + z2 * gain;
        let clear_top = (b - (b * b - 4.0 * (top * top - z2 * floor)).max(0.0).sqrt()) / 2.0;
        let clear_black = (z2 * gain + (z2 * z2 * gain * gain + 4.0 * z2 * floor).sqrt()) / 2.0;
        CodeNoise {
            gain: gain as f32,
            floor: floor as f32,
            top: top as f32,
            clear_top: clear_top as f32,
            clear_black: clear_black as f32,
        }
    }

    #[inline(always)]
    fn variance(&self, code: f32) -> f32 {
        self.gain * code.max(0.0) + self.floor
    }
}

/// The ADC code of a stored value (fraction of full scale), rounded, since
/// half-float storage may leave it off by a fraction of a code; NaN → 0,
/// at most `top` (the sensor's max code, saturation).
#[inline(always)]
pub fn adc_code(v: f32, max_code: f32, top: usize) -> usize {
    ((v * max_code + 0.5) as usize).min(top)
}

/// `out[j]` = `both(l, r)` of the values [`ALONG`] before and after
/// value j in its row `values`, leaving out the pixels at the columns
/// `broken` (the sensor's defects in the row: a stuck pixel is no guide to
/// its neighbours' level); `both(x, x)` where there is one (a row's ends),
/// and the value itself where there is none.
#[inline(always)]
fn along(values: &[f32], out: &mut [f32], broken: &[usize], both: impl Fn(f32, f32) -> f32) {
    let n = values.len();
    const P: usize = ALONG;
    let one = |j: usize| {
        let works = |i: usize| !broken.contains(&(i / 3));
        let l = j.checked_sub(P).filter(|&i| works(i)).map(|i| values[i]);
        let r = Some(j + P).filter(|&i| i < n && works(i)).map(|i| values[i]);
        match (l, r) {
            (Some(l), Some(r)) => both(l, r),
            (Some(x), None) | (None, Some(x)) => both(x, x),
            (None, None) => values[j],
        }
    };
    if n > 2 * P {
        for (o, (&l, &r)) in out[P..n - P].iter_mut().zip(values.iter().zip(&values[2 * P..])) {
            *o = both(l, r);
        }
    }
    for j in (0..P.min(n)).chain(n.saturating_sub(P).max(P.min(n))..n) {
        out[j] = one(j);
    }
    // The values whose pixels two along are broken.
    for &x in broken {
        for pixel in [x.checked_sub(P / 3), Some(x + P / 3)].into_iter().flatten() {
            for j in (3 * pixel..3 * pixel + 3).filter(|&j| j < n) {
                out[j] = one(j);
            }
        }
    }
}

/// Merge `frames` (each with its exposure in µs; all the same size, the
/// camera's black level of `black_codes` subtracted) into one frame in
/// units of the `reference_us` exposure. The pixels of
/// `defects` are not counted in the stats and are replaced by their
/// neighbours' mean ([`DefectMap::patch`]). At most [`MAX_EXPOSURES`].
///
/// Per value, in three steps (docs/scan-format.md, "HDR"):
/// 1. An exposure counts if its code is neither 0 nor the top and, unless
///    no shorter one counts, its codes two pixels along on either side
///    ([`ALONG`]) are [`CLEAR_SIGMAS`] of their noise below the top.
///    Whether an exposure counts thus never depends on the value's own
///    noise, nor on that of the exposures it is merged with.
/// 2. A counted exposure whose darker code two pixels along is not
///    [`CLEAR_SIGMAS`] of its noise above 0 is dropped, unless none is
///    left: then the longest exposure that is counted or read black (code
///    0) is kept — near black the longest exposure says most, and its 0
///    is a reading: a shorter exposure's code 1 there is read noise times
///    the ratio of the exposures.
/// 3. The merge is the mean of the kept ones' rates weighted by the inverse
///    variance of the mean of their codes two pixels along: a weight taken
///    from a value's own noisy code favours the values noise moved down
///    (−0.6 % at 0.006 of the longest exposure's full scale, session 42).
pub fn merge(
    frames: &[(&Frame, u32)],
    sensor: &SensorSpec,
    black_codes: u32,
    reference_us: u32,
    defects: &DefectMap,
) -> Result<(Frame, MergeStats), String> {
    let Some((first, _)) = frames.first() else { return Err("no exposures to merge".into()) };
    let (w, h) = (first.width, first.height);
    if frames.iter().any(|(f, _)| (f.width, f.height) != (w, h) || f.rgb.len() != first.rgb.len()) {
        return Err("exposures of different sizes".into());
    }
    if frames.iter().any(|&(_, t)| t == 0) || reference_us == 0 {
        return Err("an exposure of 0 µs".into());
    }
    if frames.len() > MAX_EXPOSURES {
        return Err(format!("{} exposures to merge; at most {MAX_EXPOSURES}", frames.len()));
    }
    let noise = CodeNoise::new(sensor, black_codes);
    let max = sensor.max_code() as f32;
    // Shortest first: values, t·max (a rate's code), 1/t.
    let mut order: Vec<(&[f32], u32)> =
        frames.iter().map(|&(f, t)| (f.rgb.as_slice(), t)).collect();
    order.sort_by_key(|&(_, t)| t);
    let shortest = order[0];
    let exposures: Vec<(&[f32], f32, f32)> = order
        .iter()
        .map(|&(rgb, t_us)| (rgb, (max as f64 * t_us as f64 * 1e-6) as f32, 1e6 / t_us as f32))
        .collect();
    // A stored value's code is a measurement (neither 0 nor the top) when
    // it rounds within these; a proxy level below `clear_top` is clear.
    let (lowest, highest) = (0.5 / max, (max - 0.5) / max);
    let (clear_top, clear_black) = (noise.clear_top / max, noise.clear_black / max);
    let to_reference = (reference_us as f64 * 1e-6) as f32;
    let mut out = vec![0.0f32; first.rgb.len()];
    use rayon::prelude::*;
    let chunk = (3 * w as usize).max(1);
    // Row by row, exposure by exposure (short loops over one row's values).
    let stats = out
        .par_chunks_mut(chunk)
        .enumerate()
        .map_init(
            || {
                (
                    vec![0.0f32; chunk],
                    [vec![0.0f32; chunk], vec![0.0f32; chunk]],
                    [(); 4].map(|_| vec![0u32; chunk]),
                )
            },
            |(den, [dark, bright], [counted, kept, saturated, black]), (row, line)| {
                let start = row * chunk;
                let n = line.len();
                let broken: Vec<usize> =
                    defects.row(first, row as u32).iter().map(|d| d.x as usize).collect();
                let (den, dark, bright) = (&mut den[..n], &mut dark[..n], &mut bright[..n]);
                let (counted, kept, saturated, black) =
                    (&mut counted[..n], &mut kept[..n], &mut saturated[..n], &mut black[..n]);
                // By exposure bit: counted (step 1), clear of black (step 2),
                // saturated, black.
                counted.fill(0);
                kept.fill(0);
                saturated.fill(0);
                black.fill(0);
                for (bit, &(rgb, _, _)) in exposures.iter().enumerate() {
                    let values = &rgb[start..start + n];
                    let bit = 1u32 << bit;
                    along(values, dark, &broken, f32::min);
                    along(values, bright, &broken, f32::max);
                    for ((&v, (&dk, &br)), ((c, z), (k, sat))) in
                        values.iter().zip(dark.iter().zip(bright.iter())).zip(
                            counted
                                .iter_mut()
                                .zip(black.iter_mut())
                                .zip(kept.iter_mut().zip(saturated.iter_mut())),
                        )
                    {
                        let measured = (v >= lowest) & (v < highest);
                        let take = measured & ((*c == 0) | (br < clear_top));
                        *c |= if take { bit } else { 0 };
                        *z |= if v < lowest { bit } else { 0 };
                        *k |= if dk > clear_black { bit } else { 0 };
                        *sat |= if v >= highest { bit } else { 0 };
                    }
                }
                // Step 2: the counted exposures clear of black, else the
                // longest exposure that is counted or black (a black one
                // read 0: no shorter exposure's noise says more).
                for ((&c, &z), k) in counted.iter().zip(black.iter()).zip(kept.iter_mut()) {
                    let both = c & *k;
                    let either = c | z;
                    *k = if both != 0 || either == 0 { both } else { 1 << either.ilog2() };
                }
                // Step 3: weights from the codes along (their mean).
                line.fill(0.0);
                den.fill(0.0);
                for (bit, &(rgb, tm, over_t)) in exposures.iter().enumerate() {
                    let values = &rgb[start..start + n];
                    let bit = 1u32 << bit;
                    along(values, dark, &broken, |a, b| 0.5 * (a + b));
                    for ((o, d), ((&v, &level), &k)) in line
                        .iter_mut()
                        .zip(den.iter_mut())
                        .zip(values.iter().zip(dark.iter()).zip(kept.iter()))
                    {
                        let wgt = tm * tm / noise.variance(level * max);
                        let wgt = if k & bit != 0 { wgt } else { 0.0 };
                        *o += wgt * over_t * v;
                        *d += wgt;
                    }
                }
                let every = u32::MAX >> (MAX_EXPOSURES - exposures.len());
                let mut stats = MergeStats::default();
                for (j, o) in line.iter_mut().enumerate() {
                    // Looked up only for the few values no exposure measured.
                    let counted = || usize::from(!defects.contains(first, (start + j) / 3));
                    if black[j] == every {
                        stats.black += counted();
                    }
                    *o = if den[j] > 0.0 {
                        *o / den[j] * to_reference
                    } else if saturated[j] == every {
                        stats.clipped += counted();
                        let (rgb, t) = shortest;
                        (rgb[start + j] as f64 * reference_us as f64 / t as f64) as f32
                    } else {
                        0.0
                    };
                }
                stats
            },
        )
        .reduce(MergeStats::default, |a, b| MergeStats {
            clipped: a.clipped + b.clipped,
            black: a.black + b.black,
        });
    let mut merged = Frame { width: w, height: h, rgb: out };
    defects.patch(&mut merged);
    Ok((merged, stats))
}

/// The noise of values merged from one bracket of exposures, for many
/// rates ([`BracketNoise::rate_variance`] is called for every texel of
/// every region image).
#[derive(Debug, Clone)]
pub struct BracketNoise {
    noise: CodeNoise,
    /// max · t per exposure, ascending.
    codes: Vec<f64>,
}

impl BracketNoise {
    /// The bracket `exposures_us` on `sensor`, `black_codes` subtracted.
    pub fn new(exposures_us: &[u32], sensor: &SensorSpec, black_codes: u32) -> BracketNoise {
        let max = sensor.max_code();
        let mut codes: Vec<f64> = exposures_us.iter().map(|&t| t as f64 * 1e-6 * max).collect();
        codes.sort_by(f64::total_cmp);
        BracketNoise { noise: CodeNoise::new(sensor, black_codes), codes }
    }

    /// The variance of a merged value as a rate, `rate` in full scale per
    /// second (a frame [`crate::build::scanread::ScanFrames::read`]
    /// returns): the inverse of the merge's summed weights over the
    /// exposures it keeps at `rate` ([`merge`]'s steps, with the rate
    /// itself as every level along). `None`: every exposure saturated, or
    /// none given.
    pub fn rate_variance(&self, rate: f64) -> Option<f64> {
        let noise = &self.noise;
        let mu = |tm: f64| (rate * tm) as f32;
        let weight = |tm: f64| tm * tm / noise.variance(mu(tm)) as f64;
        // Step 1: the shortest unsaturated exposure, and the longer ones
        // clear of the top.
        let mut unsaturated =
            self.codes.iter().copied().filter(|&tm| (rate * tm).round() < noise.top as f64);
        let shortest = unsaturated.next()?;
        let counted =
            std::iter::once(shortest).chain(unsaturated.filter(|&tm| mu(tm) < noise.clear_top));
        // Step 2: those clear of black, else the longest counted.
        let (mut kept, mut longest) = (0.0, shortest);
        for tm in counted {
            longest = tm;
            if mu(tm) > noise.clear_black {
                kept += weight(tm);
            }
        }
        Some(1.0 / if kept > 0.0 { kept } else { weight(longest) })
    }
}

/// How two exposures of a bracket agree: the rate (value per µs) the
/// shorter one measured over the longer one's, median over the values both
/// measured well. 1 when the light and the exposure times are what the
/// merge assumes; a dimmed light (exposures below 1 ms) that gives more or
/// less than its duty, or an exposure that lasts longer or shorter than
/// asked, moves it.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ExposureRatio {
    /// The shorter exposure, µs of light.
    pub shorter_us: u32,
    /// The next longer exposure, µs of light.
    pub longer_us: u32,
    /// Median over the values of (shorter's rate) / (longer's rate).
    pub ratio: f64,
    /// Values compared.
    pub values: usize,
}

impl ExposureRatio {
    /// The camera's trigger delay that would explain the ratio, µs, for
    /// exposures whose trigger pulses lasted `shorter_pulse_us` and
    /// `longer_pulse_us` (a dimmed exposure's pulse is the device's 1 ms):
    /// a camera exposing d late for a pulse of t, the light following the
    /// pulse, collects (t − d)/t of it, so the ratio is
    /// (1 − d/tₛ)/(1 − d/tₗ) and d = (1 − r)/(1/tₛ − r/tₗ). None unless it
    /// is a delay shorter than the shorter pulse (a ratio below 1).
    pub fn trigger_delay_us(&self, shorter_pulse_us: u32, longer_pulse_us: u32) -> Option<f64> {
        let (ts, tl, r) = (shorter_pulse_us as f64, longer_pulse_us as f64, self.ratio);
        let d = (1.0 - r) / (1.0 / ts - r / tl);
        (r < 1.0 && d.is_finite() && d > 0.0 && d < ts).then_some(d)
    }
}

/// Only one value in this many is compared (coprime with 3: every channel).
const AGREEMENT_STRIDE: usize = 7;
/// A value is compared where its level, judged from the longer exposure
/// two pixels along ([`ALONG`]), puts the shorter exposure at
/// least at this fraction of full scale (≥ 500 electrons on the default
/// sensor: shot noise ≤ 4.5 %) and the longer at most at
/// [`AGREEMENT_HIGH`].
const AGREEMENT_LOW: f32 = 0.05;
/// See [`AGREEMENT_LOW`]: clear of saturation, a fraction of where values
/// saturate (the top code less the camera's black level).
const AGREEMENT_HIGH: f32 = 0.9;
/// The longer exposure's own value must be below this fraction of where
/// values saturate (not clipped).
const AGREEMENT_CLIP: f32 = 0.95;
/// Fewer values than this give no ratio.
pub const AGREEMENT_MIN_VALUES: usize = 100;

/// For each exposure of `frames` (each with its exposure in µs) but the
/// longest, its [`ExposureRatio`] to the next longer one; `None` where
/// fewer than [`AGREEMENT_MIN_VALUES`] values were measured well by both.
/// `sensor` and `black_codes` as for [`merge`]: values saturate at the top
/// code less the black level.
pub fn exposure_ratios(
    frames: &[(&Frame, u32)],
    sensor: &SensorSpec,
    black_codes: u32,
) -> Vec<Option<ExposureRatio>> {
    let saturation = CodeNoise::new(sensor, black_codes).top / sensor.max_code() as f32;
    let (high, clip) = (AGREEMENT_HIGH * saturation, AGREEMENT_CLIP * saturation);
    let mut order: Vec<&(&Frame, u32)> = frames.iter().collect();
    order.sort_by_key(|(_, t)| *t);
    order
        .windows(2)
        .map(|w| {
            let ((short, ts), (long, tl)) = (w[0], w[1]);
            let scale = *tl as f64 / *ts as f64;
            let (a, b) = (&short.rgb, &long.rgb);
            let n = a.len().min(b.len());
            if n <= ALONG {
                return None;
            }
            let low = (AGREEMENT_LOW as f64 * scale) as f32;
            let mut ratios: Vec<f32> = (0..n)
                .step_by(AGREEMENT_STRIDE)
                .filter(|&i| {
                    let j = if i + ALONG < n { i + ALONG } else { i - ALONG };
                    let level = b[j];
                    (low..=high).contains(&level) && a[i] > 0.0 && b[i] > 0.0 && b[i] < clip
                })
                .map(|i| (a[i] as f64 / b[i] as f64 * scale) as f32)
                .collect();
            if ratios.len() < AGREEMENT_MIN_VALUES {
                return None;
            }
            let mid = ratios.len() / 2;
            let (_, median, _) = ratios.select_nth_unstable_by(mid, f32::total_cmp);
            Some(ExposureRatio {
                shorter_us: *ts,
                longer_us: *tl,
                ratio: *median as f64,
                values: ratios.len(),
            })
        })
        .collect()
}

/// The bracket `--hdr` takes around `exposure_us`: ×1/25, ×1/5, ×1 (a 25×
/// wider range above the base exposure's full scale), within the device's
/// exposure limits.
pub fn default_bracket(exposure_us: u32) -> Vec<u32> {
    let mut b: Vec<u32> = [25, 5, 1]
        .iter()
        .map(|d| (exposure_us / d).clamp(protocol::MIN_EXPOSURE_US, protocol::MAX_EXPOSURE_US))
        .collect();
    b.dedup();
    b
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sensor() -> SensorSpec {
        SensorSpec {
            bits: 12,
            full_well_e: 10_000.0,
            read_noise_e: 3.0,
            sensitivity_e: 1.0,
            vignetting_exponent: 0.0,
        }
    }

    fn frame(v: &[f32]) -> Frame {
        Frame { width: v.len() as u32 / 3, height: 1, rgb: v.to_vec() }
    }

    #[test]
    fn exposure_ratios_measure_a_light_that_gives_less_than_its_duty() {
        // A scene of 30 000 values from 0.001 to 36 (of the 10 ms exposure's
        // full scale); the 100 µs exposure's light gives 0.8 of its duty.
        let scene: Vec<f32> = (0..30_000).map(|i| 0.001 * 1.00035f32.powi(i)).collect();
        let at =
            |t: f32, k: f32| frame(&scene.iter().map(|v| (v * t * k).min(1.0)).collect::<Vec<_>>());
        let (dim, mid, long) = (at(0.01, 0.8), at(0.1, 1.0), at(1.0, 1.0));
        let r = exposure_ratios(&[(&long, 10_000), (&dim, 100), (&mid, 1_000)], &sensor(), 0);
        assert_eq!(r.len(), 2);
        let r0 = r[0].unwrap();
        assert_eq!((r0.shorter_us, r0.longer_us), (100, 1_000));
        assert!((r0.ratio - 0.8).abs() < 1e-4 && r0.values >= AGREEMENT_MIN_VALUES, "{r0:?}");
        let r1 = r[1].unwrap();
        assert_eq!((r1.shorter_us, r1.longer_us), (1_000, 10_000));
        assert!((r1.ratio - 1.0).abs() < 1e-4, "{r1:?}");
        // Too few values measured well by both: no ratio.
        let few = frame(&scene[..60]);
        assert_eq!(exposure_ratios(&[(&few, 1_000), (&few, 2_000)], &sensor(), 0), vec![None]);
    }

    /// A camera that subtracts a black level of b codes itself saturates at
    /// the top code less b: those values are clipped, not measured, and
    /// left out (with b = 410 of 4 095 they sit at 0.9 of full scale, below
    /// the thresholds for a camera without one, and moved the ratio).
    #[test]
    fn exposure_ratios_leave_out_what_saturates_below_the_top_code() {
        let s = sensor();
        let black = 410;
        let saturation = ((s.max_code() - black as f64) / s.max_code()) as f32;
        let scene: Vec<f32> = (0..30_000).map(|i| 0.001 * 1.00035f32.powi(i)).collect();
        let at = |t: f32| frame(&scene.iter().map(|v| (v * t).min(saturation)).collect::<Vec<_>>());
        let (short, long) = (at(0.2), at(1.0));
        let r = exposure_ratios(&[(&short, 2_000), (&long, 10_000)], &s, black)[0].unwrap();
        assert!((r.ratio - 1.0).abs() < 1e-4 && r.values >= AGREEMENT_MIN_VALUES, "{r:?}");
        let unaware = exposure_ratios(&[(&short, 2_000), (&long, 10_000)], &s, 0)[0].unwrap();
        assert!(unaware.ratio > 1.05, "the clipped values count without it: {unaware:?}");
    }

    /// Levels just outside the compared range, under the sensor's noise:
    /// only the noise's tail crosses into it, and that must not move the
    /// ratio (it did by +15 % at the low end when the values were judged
    /// by their own exposures).
    #[test]
    fn levels_at_the_thresholds_do_not_bias_the_ratio() {
        use rand::{Rng, SeedableRng};
        let s = sensor();
        let (max, gain) = (s.max_code(), s.max_code() / s.full_well_e);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut gauss = move || {
            let (a, b): (f64, f64) = (rng.random::<f64>().max(1e-300), rng.random());
            (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
        };
        let mut read = |level: f64| -> f32 {
            let e = level * s.full_well_e;
            let sd = (e + s.read_noise_e.powi(2)).sqrt();
            (((e + sd * gauss()) * gain).round().clamp(0.0, max) / max) as f32
        };
        // The longer exposure 5×, its level a smooth ramp over the frame:
        // just below the compared range (the shorter's 0.03…0.05, under
        // AGREEMENT_LOW), just above it, and inside it.
        for (lo, hi, inside) in [(0.15, 0.25, false), (0.9, 0.95, false), (0.3, 0.8, true)] {
            let n = 600_000;
            let level = |i: usize| lo + (hi - lo) * i as f64 / n as f64;
            let long_v: Vec<f32> = (0..n).map(|i| read(level(i))).collect();
            let short_v: Vec<f32> = (0..n).map(|i| read(level(i) / 5.0)).collect();
            let pair = [(&frame(&short_v), 2_000), (&frame(&long_v), 10_000)];
            let r = exposure_ratios(&pair, &s, 0);
            // What is compared has the ratio of 1, however few.
            if let Some(r) = r[0] {
                assert!((r.ratio - 1.0).abs() < 0.01, "{lo}…{hi}: {r:?}");
            }
            assert_eq!(r[0].is_some_and(|r| r.values > n / 20), inside, "{lo}…{hi}: {r:?}");
        }
    }

    #[test]
    fn a_ratio_below_1_gives_the_trigger_delay_that_would_explain_it() {
        let late = |d: f64, ts: f64, tl: f64| ExposureRatio {
            shorter_us: ts as u32,
            longer_us: tl as u32,
            ratio: (1.0 - d / ts) / (1.0 - d / tl),
            values: 1_000,
        };
        let r = late(2_000.0, 20_000.0, 100_000.0);
        assert!((r.trigger_delay_us(20_000, 100_000).unwrap() - 2_000.0).abs() < 1e-6);
        // A dimmed 100 µs exposure is a 1 ms pulse.
        let r = late(50.0, 1_000.0, 10_000.0);
        assert!((r.trigger_delay_us(1_000, 10_000).unwrap() - 50.0).abs() < 1e-9);
        // More light than asked, or a loss beyond the pulse: no delay.
        let more = ExposureRatio { ratio: 1.05, ..r };
        assert_eq!(more.trigger_delay_us(1_000, 10_000), None);
        let all = ExposureRatio { ratio: 0.0, ..r };
        assert_eq!(all.trigger_delay_us(1_000, 10_000), None);
    }

    #[test]
    fn saturated_and_black_values_are_left_out() {
        let s = sensor();
        // Pixel 0: saturated at 10 ms, 0.5 at 1 ms → 5.0 at 10 ms.
        // Pixel 1: black at 1 ms, 0.01 at 10 ms.
        let short = frame(&[0.5, 0.5, 0.5, 0.0, 0.0, 0.0]);
        let long = frame(&[1.0, 1.0, 1.0, 0.01, 0.01, 0.01]);
        let (m, stats) =
            merge(&[(&short, 1_000), (&long, 10_000)], &s, 0, 10_000, &DefectMap::default())
                .unwrap();
        assert!((m.rgb[0] - 5.0).abs() < 1e-5, "{}", m.rgb[0]);
        assert!((m.rgb[3] - 0.01).abs() < 1e-6, "{}", m.rgb[3]);
        assert_eq!(stats, MergeStats::default());
        // Saturated everywhere: counted, the shortest exposure scaled.
        let saturated = frame(&[1.0; 3]);
        let (m, stats) = merge(
            &[(&saturated, 1_000), (&saturated, 10_000)],
            &s,
            0,
            10_000,
            &DefectMap::default(),
        )
        .unwrap();
        assert_eq!(stats.clipped, 3);
        assert!((m.rgb[0] - 10.0).abs() < 1e-5);
        // A stuck pixel of the sensor (the middle one) is neither counted
        // nor kept: its neighbours' mean stands in.
        let short = frame(&[0.02, 0.02, 0.02, 1.0, 1.0, 1.0, 0.04, 0.04, 0.04]);
        let long = frame(&[0.2, 0.2, 0.2, 1.0, 1.0, 1.0, 0.4, 0.4, 0.4]);
        use crate::defects::{DefectKind, PixelDefect};
        let map = DefectMap::new(&[PixelDefect { x: 1, y: 0, kind: DefectKind::Stuck }], 3, 1);
        let (m, stats) = merge(&[(&short, 1_000), (&long, 10_000)], &s, 0, 10_000, &map).unwrap();
        assert_eq!(stats, MergeStats::default());
        assert!((m.rgb[3] - 0.3).abs() < 1e-3 && (m.rgb[0] - 0.2).abs() < 1e-3, "{:?}", m.rgb);
    }

    /// The merge against docs/scan-format.md's three steps written out in
    /// double precision, on codes over the whole range that disagree
    /// between exposures and from pixel to pixel.
    #[test]
    fn merges_as_the_documented_three_steps() {
        let s = sensor();
        let max = s.max_code();
        let gain = max / s.full_well_e;
        let var = |c: f64| gain * c.max(0.0) + gain * gain * 9.0 + 1.0 / 12.0;
        let exposures = [500u32, 4_000, 20_000];
        let codes: Vec<[u32; 3]> =
            (0..400u32)
                .map(|i| [i * 7 % 4096, (i * 131 + 5) % 4096, (i * 977 + 11) % 4096])
                .map(|c| if c[0] % 5 == 0 { [c[0] / 40, c[1] / 8, c[2]] } else { c })
                .enumerate()
                // A dark patch whose longest exposure reads black.
                .map(|(i, c)| {
                    if (200..212).contains(&i) { [i as u32 % 3, (i as u32 / 3) % 2, 0] } else { c }
                })
                .collect();
        let frames: Vec<Frame> = (0..3)
            .map(|k| {
                let v: Vec<f32> =
                    codes.iter().flat_map(|c| [c[k] as f32 / max as f32; 3]).collect();
                frame(&v)
            })
            .collect();
        let inputs: Vec<(&Frame, u32)> = frames.iter().zip(exposures).collect();
        let (m, _) = merge(&inputs, &s, 0, 20_000, &DefectMap::default()).unwrap();
        let (mut three, mut dropped_high, mut dropped_low, mut black_longest) = (0, 0, 0, 0);
        for (p, c) in codes.iter().enumerate() {
            let tm = |k: usize| max * exposures[k] as f64 * 1e-6;
            // The codes two pixels along, at either end the one there is.
            let along = |k: usize| {
                let l = p.checked_sub(2).map(|q| codes[q][k] as f64);
                let r = codes.get(p + 2).map(|c| c[k] as f64);
                let (l, r) = (l.or(r).unwrap(), r.or(l).unwrap());
                (l.min(r), l.max(r), (l + r) / 2.0)
            };
            // 1.
            let mut counted = vec![];
            for (k, &code) in c.iter().enumerate() {
                let mu = along(k).1;
                let clear = max - mu > 0.0 && (max - mu).powi(2) > 9.0 * var(mu);
                if code > 0 && code < 4095 && (counted.is_empty() || clear) {
                    counted.push(k);
                }
            }
            dropped_high += usize::from(counted.len() < 3 && c.iter().all(|&c| c > 0 && c < 4095));
            // 2.
            let mut kept: Vec<usize> = counted
                .iter()
                .copied()
                .filter(|&k| along(k).0 > 0.0 && along(k).0.powi(2) > 9.0 * var(along(k).0))
                .collect();
            // None clear of black: the longest counted or black one.
            let black = (0..3).filter(|&k| c[k] == 0);
            if kept.is_empty() {
                kept.extend(counted.iter().copied().chain(black).max());
            }
            dropped_low += counted.len().saturating_sub(kept.len());
            black_longest += usize::from(kept.len() == 1 && c[kept[0]] == 0 && !counted.is_empty());
            three += usize::from(kept.len() == 3);
            // 3.
            let (mut num, mut den) = (0.0, 0.0);
            for &k in &kept {
                let w = tm(k).powi(2) / var(along(k).2);
                num += w * c[k] as f64 / tm(k);
                den += w;
            }
            let want = if den > 0.0 { num / den * 0.02 } else { 0.0 };
            let got = m.rgb[3 * p] as f64;
            if !c.iter().all(|&c| c == 4095) {
                assert!(
                    (got - want).abs() <= 1e-5 * want.abs() + 1e-9,
                    "{p} {c:?}: {got} vs {want}"
                );
            }
        }
        // Every step decided something.
        assert!(
            three > 10 && dropped_high > 10 && dropped_low > 10 && black_longest > 0,
            "{three} {dropped_high} {dropped_low} {black_longest}"
        );
    }

    /// `n` values at `rate` (full scale per second) through each of
    /// `exposures_us`, drawn from the sensor's model (shot and read noise,
    /// quantised, clipped at 0 and the top code), stored as half floats as
    /// a scan stores them; seeded.
    fn draws(rate: f64, exposures_us: &[u32], n: usize, seed: u64) -> Vec<Frame> {
        draws_above(rate, exposures_us, n, seed, 0)
    }

    /// [`draws`] by a camera with a black level of `black` codes, which it
    /// subtracts (the top code stays: saturated).
    fn draws_above(rate: f64, exposures_us: &[u32], n: usize, seed: u64, black: u32) -> Vec<Frame> {
        use rand::{Rng, SeedableRng};
        let s = sensor();
        let max = s.max_code();
        let gain = max / s.full_well_e;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut gauss = move || {
            let (a, b): (f64, f64) = (rng.random::<f64>().max(1e-300), rng.random());
            (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
        };
        exposures_us
            .iter()
            .map(|&t_us| {
                let e = rate * t_us as f64 * 1e-6 * s.full_well_e;
                let sd = (e + s.read_noise_e.powi(2)).sqrt();
                let raw: Vec<f32> = (0..n)
                    .map(|_| ((e + sd * gauss()) * gain + black as f64).round().clamp(0.0, max))
                    .flat_map(|c| [(c / max) as f32; 3])
                    .collect();
                let mut f = frame(&raw);
                crate::camera::subtract_black_level(&mut f, black as f32 / max as f32, max as f32);
                f.rgb.iter_mut().for_each(|v| *v = half::f16::from_f32(*v).to_f32());
                f
            })
            .collect()
    }

    /// The merged rates of `draws`, full scale per second.
    fn merged_rates(frames: &[Frame], exposures_us: &[u32], black: u32) -> Vec<f64> {
        let longest = *exposures_us.iter().max().unwrap();
        let inputs: Vec<(&Frame, u32)> = frames.iter().zip(exposures_us.iter().copied()).collect();
        let (m, _) = merge(&inputs, &sensor(), black, longest, &DefectMap::default()).unwrap();
        m.rgb.iter().step_by(3).map(|&v| v as f64 / (longest as f64 * 1e-6)).collect()
    }

    #[test]
    fn merged_values_vary_as_rate_variance_says() {
        let s = sensor();
        let exposures = [1_000u32, 8_000, 40_000];
        // Rates in full scale per second: every exposure measures the first;
        // the 40 ms one saturates at the last.
        for (i, rate) in [0.5f64, 5.0, 40.0].into_iter().enumerate() {
            let n = 20_000;
            let rates = merged_rates(&draws(rate, &exposures, n, 3 + i as u64), &exposures, 0);
            let mean = rates.iter().sum::<f64>() / n as f64;
            let var = rates.iter().map(|r| (r - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
            let want = BracketNoise::new(&exposures, &s, 0).rate_variance(rate).unwrap();
            assert!((mean / rate - 1.0).abs() < 0.01, "rate {rate}: mean {mean}");
            assert!((var / want - 1.0).abs() < 0.05, "rate {rate}: variance {var} against {want}");
        }
        // Every exposure saturated: no variance to give.
        assert_eq!(BracketNoise::new(&exposures, &s, 0).rate_variance(1e4), None);
        assert_eq!(BracketNoise::new(&[], &s, 0).rate_variance(1.0), None);
    }

    /// The merge's mean against the true rate, over levels from 0.005 of
    /// the longest exposure's full scale to 0.96 of the shortest's, three
    /// exposures 5× apart: the bias of a whole scan's highlights and
    /// shadows at that level.
    /// The merge's mean against the true rate, at 81 levels from 0.005 of
    /// the longest exposure's full scale to 0.96 of the shortest's (three
    /// exposures 5× apart), and densely around the clip of each: the bias
    /// a scan's highlights and shadows get at that level. Within 0.05 %
    /// plus four standard errors of the mean everywhere. The half-float
    /// storage of the single exposures alone costs −0.024 % between 0.25
    /// and 0.5 of full scale (code k stored as k/4096). The merge before
    /// session 42 fails this: −0.63 % at 0.006 and −0.37 % at 1.0 of the
    /// longest's full scale; judging the top clip from the shorter
    /// exposures fails it too (+0.66 % at 0.94).
    #[test]
    fn the_merge_is_unbiased_at_every_level() {
        let exposures = [1_000u32, 5_000, 25_000];
        let n = 100_000;
        // Levels as fractions of the longest exposure's full scale.
        let sweep = |lo: f64, hi: f64, steps: usize| {
            (0..=steps).map(move |i| lo * (hi / lo).powf(i as f64 / steps as f64))
        };
        let levels = sweep(0.005, 24.0, 80).chain(sweep(0.85, 1.05, 12)).chain(sweep(4.3, 5.3, 6));
        // A camera without a black level, and one that subtracts 200 codes
        // (its values clip at 0.95 of full scale) around the clips.
        let cameras = levels.map(|l| (l, 0)).chain(sweep(0.85, 1.05, 12).map(|l| (l, 200)));
        for (i, (level, black)) in cameras.enumerate() {
            let rate = level / 0.025;
            let frames = draws_above(rate, &exposures, n, 100 + i as u64, black);
            let rates = merged_rates(&frames, &exposures, black);
            let mean = rates.iter().sum::<f64>() / n as f64;
            let sd =
                (rates.iter().map(|r| (r - mean).powi(2)).sum::<f64>() / (n - 1) as f64).sqrt();
            let (bias, sem) = (mean / rate - 1.0, sd / (n as f64).sqrt() / rate);
            assert!(
                bias.abs() < 5e-4 + 4.0 * sem,
                "bias {:+.4} % (± {:.4} %) at {level:.4} of the longest's full scale, black {black}",
                bias * 100.0,
                sem * 100.0
            );
        }
    }

    /// Near black, below what even the longest exposure tells from its
    /// read noise, the merge is the longest exposure's reading, 0 codes
    /// included: a bracket a glossy sample's highlights extended down to
    /// 64 µs holds exposures 15 600× shorter, and a black pixel's code 1
    /// there (its read noise, 1.2 codes) is 15 600 codes of the longest.
    /// Before session 93, step 2 kept the longest exposure that read
    /// above 0, whatever a longer one's 0 said: the black holder around
    /// chrome, merged from such brackets at 4096², read 0.2 of full scale
    /// per second (20 % of the longest exposure's full scale), brighter
    /// than the sample, and its face was measured 8.5 mm off.
    #[test]
    fn a_black_pixel_merges_to_the_longest_exposures_reading() {
        let exposures = [64u32, 320, 1_600, 8_000, 40_000, 200_000, 1_000_000];
        let n = 100_000;
        let code = 1.0 / 4095.0; // one code of the longest exposure, per second
        for (i, codes) in [0.0f64, 0.5, 2.0, 8.0].into_iter().enumerate() {
            let rate = codes * code;
            let frames = draws(rate, &exposures, n, 900 + i as u64);
            let rates = merged_rates(&frames, &exposures, 0);
            let mean = rates.iter().sum::<f64>() / n as f64;
            // The longest exposure's reading clipped at 0: within half a code.
            assert!(
                (mean - rate).abs() < 0.5 * code,
                "{codes} codes of the longest exposure: merged {:.3} codes",
                mean / code
            );
        }
    }

    /// Auto exposure may add shorter exposures down to the device's 20 µs
    /// at a mirror: a bracket of more than 8 merges (one bit per exposure
    /// of a 32-bit mask); more than 32 is refused.
    #[test]
    fn a_long_bracket_merges() {
        let s = sensor();
        let times: Vec<u32> = (0..12).map(|k| 20 << k).collect();
        // 0.3 of full scale per ms: every exposure from 4 ms on saturates.
        let frames: Vec<Frame> = times
            .iter()
            .map(|&t| {
                let v = ((0.3 * t as f64 / 1000.0 * 4095.0).round().min(4095.0) / 4095.0) as f32;
                frame(&[v; 15])
            })
            .collect();
        let inputs: Vec<(&Frame, u32)> = frames.iter().zip(times.iter().copied()).collect();
        let (m, stats) = merge(&inputs, &s, 0, 40_960, &DefectMap::default()).unwrap();
        assert_eq!(stats, MergeStats::default());
        assert!(m.rgb.iter().all(|&v| (v / 12.288 - 1.0).abs() < 1e-3), "{:?}", m.rgb);
        let many: Vec<(&Frame, u32)> = (0..33).map(|k| (&frames[0], 20 + k)).collect();
        assert!(merge(&many, &s, 0, 20, &DefectMap::default()).unwrap_err().contains("at most 32"));
    }

    /// A stuck pixel is no guide to the level two pixels along: stuck at
    /// the top, it would leave its neighbours the shortest exposure alone
    /// (a cross of noisy pixels around every hot pixel).
    #[test]
    fn a_stuck_pixel_does_not_judge_its_neighbours() {
        use crate::defects::{DefectKind, PixelDefect};
        let s = sensor();
        // 0.02 at 1 ms and 0.21 at 10 ms: merged ≈ 0.209 with the long
        // exposure, 0.2 without it. Pixel 3 is stuck at the top.
        let mut short = vec![0.02f32; 21];
        let mut long = vec![0.21f32; 21];
        short[9..12].fill(1.0);
        long[9..12].fill(1.0);
        let (short, long) = (frame(&short), frame(&long));
        let map = DefectMap::new(&[PixelDefect { x: 3, y: 0, kind: DefectKind::Stuck }], 7, 1);
        let (m, _) = merge(&[(&short, 1_000), (&long, 10_000)], &s, 0, 10_000, &map).unwrap();
        for p in [0, 1, 2, 4, 5, 6] {
            assert!(m.rgb[3 * p] > 0.208, "pixel {p}: {:?}", &m.rgb[3 * p..3 * p + 3]);
        }
        // Unknown to the map, it does judge them.
        let (m, _) =
            merge(&[(&short, 1_000), (&long, 10_000)], &s, 0, 10_000, &DefectMap::default())
                .unwrap();
        assert!((m.rgb[3] - 0.2).abs() < 1e-4 && (m.rgb[15] - 0.2).abs() < 1e-4, "{:?}", m.rgb);
    }

    #[test]
    fn the_longer_unsaturated_exposure_weighs_more() {
        let s = sensor();
        // 0.2 at 1 ms and 0.21 at 10 ms ×⅒: the merge sits near the long one.
        let (short, long) = (frame(&[0.02, 0.02, 0.02]), frame(&[0.21, 0.21, 0.21]));
        let (m, _) =
            merge(&[(&short, 1_000), (&long, 10_000)], &s, 0, 10_000, &DefectMap::default())
                .unwrap();
        assert!(m.rgb[0] > 0.208 && m.rgb[0] < 0.21, "{}", m.rgb[0]);
    }
}
