//! HDR merging of an exposure bracket into one linear frame, weighted by
//! the sensor's noise model (docs/scan-format.md, "HDR").
//!
//! For each pixel and channel, every exposure k whose ADC code c_k is
//! neither black (0: clipped at zero, biased) nor saturated (the top code:
//! clipped at the full well) estimates the rate r_k = v_k / t_k. Its
//! variance follows the sensor: electrons e = c / g (g = codes per
//! electron), Var(c) = g² (e + σ_read²) + 1/12 (quantisation), so
//! Var(r_k) = Var(c_k) / (max_code · t_k)². The merged rate is the
//! inverse-variance weighted mean; the output is it times the reference
//! exposure, in the frames' units (ADC code / max code). A pixel black in
//! every exposure is 0; one saturated in every exposure keeps the shortest
//! exposure's (clipped) value and is counted.

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

/// Per ADC code of one exposure: (weight, weight / exposure time).
type CodeWeights = Vec<(f32, f32)>;

/// The ADC code of a stored value (fraction of full scale), rounded, since
/// half-float storage may leave it off by a fraction of a code; NaN → 0,
/// at most `top` (the sensor's max code, saturation).
#[inline(always)]
pub fn adc_code(v: f32, max_code: f32, top: usize) -> usize {
    ((v * max_code + 0.5) as usize).min(top)
}

/// Merge `frames` (each with its exposure in µs; all the same size) into
/// one frame in units of the `reference_us` exposure. The pixels of
/// `defects` are not counted in the stats and are replaced by their
/// neighbours' mean ([`DefectMap::patch`]).
pub fn merge(
    frames: &[(&Frame, u32)],
    sensor: &SensorSpec,
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
    let max = sensor.max_code();
    let gain = max / sensor.full_well_e;
    let read2 = sensor.read_noise_e * sensor.read_noise_e;
    let top = max as usize;
    let shortest =
        frames.iter().enumerate().min_by_key(|(_, (_, t))| *t).map(|(i, _)| i).unwrap_or(0);
    // Per exposure, per ADC code c: the weight 1/Var(r) and the weight
    // over t (for Σ w·v/t); 0 for black (0) and saturated (top) codes.
    let tables: Vec<(&[f32], CodeWeights)> = frames
        .iter()
        .map(|&(f, t_us)| {
            let t = t_us as f64 * 1e-6;
            let table = (0..=top)
                .map(|c| {
                    if c == 0 || c == top {
                        return (0.0, 0.0);
                    }
                    let wgt = (max * t).powi(2) / code_variance(c as f64, gain, read2);
                    (wgt as f32, (wgt / t) as f32)
                })
                .collect();
            (f.rgb.as_slice(), table)
        })
        .collect();
    let to_reference = (reference_us as f64 * 1e-6) as f32;
    let maxf = max as f32;
    let mut out = vec![0.0f32; first.rgb.len()];
    use rayon::prelude::*;
    let chunk = (3 * w as usize).max(1);
    // Row by row, exposure by exposure (short loops over one row's values).
    let stats = out
        .par_chunks_mut(chunk)
        .enumerate()
        .map_init(
            || (vec![0.0f32; chunk], vec![0.0f32; chunk], vec![true; chunk]),
            |(num, den, all_clipped), (row, line)| {
                let start = row * chunk;
                let n = line.len();
                let (num, den, all_clipped) = (&mut num[..n], &mut den[..n], &mut all_clipped[..n]);
                num.fill(0.0);
                den.fill(0.0);
                all_clipped.fill(true);
                for (rgb, table) in &tables {
                    let table: &[(f32, f32)] = table;
                    for (j, &v) in rgb[start..start + n].iter().enumerate() {
                        let code = adc_code(v, maxf, top);
                        let (wgt, wgt_over_t) = table[code];
                        all_clipped[j] &= code == top;
                        num[j] += wgt_over_t * v;
                        den[j] += wgt;
                    }
                }
                let mut stats = MergeStats::default();
                for (j, o) in line.iter_mut().enumerate() {
                    // Looked up only for the few values no exposure measured.
                    let counted = || usize::from(!defects.contains(first, (start + j) / 3));
                    *o = if den[j] > 0.0 {
                        num[j] / den[j] * to_reference
                    } else if all_clipped[j] {
                        stats.clipped += counted();
                        let (f, t) = frames[shortest];
                        (f.rgb[start + j] as f64 * reference_us as f64 / t as f64) as f32
                    } else {
                        stats.black += counted();
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

/// The variance of ADC code `c` (codes²): shot noise of its electrons, read
/// noise (`read2`, electrons²) and quantisation, at `gain` codes per
/// electron.
fn code_variance(c: f64, gain: f64, read2: f64) -> f64 {
    let e = c.max(0.0) / gain;
    gain * gain * (e + read2) + 1.0 / 12.0
}

/// The variance of a merged value as a rate, `rate` in full scale per
/// second (a frame [`crate::build::scanread::ScanFrames::read`] returns),
/// measured with `exposures_us`: the inverse of the merge's summed weights
/// over the exposures that did not saturate at that rate (a black one
/// counts with its read noise). `None`: every exposure saturated, or none
/// given.
pub fn rate_variance(rate: f64, exposures_us: &[u32], sensor: &SensorSpec) -> Option<f64> {
    let max = sensor.max_code();
    let (gain, read2) = (max / sensor.full_well_e, sensor.read_noise_e * sensor.read_noise_e);
    let weight: f64 = exposures_us
        .iter()
        .map(|&t_us| t_us as f64 * 1e-6)
        .filter_map(|t| {
            let c = (rate * t * max).round();
            (c < max).then(|| (max * t).powi(2) / code_variance(c, gain, read2))
        })
        .sum();
    (weight > 0.0).then(|| 1.0 / weight)
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
/// two pixels along ([`AGREEMENT_PROXY`]), puts the shorter exposure at
/// least at this fraction of full scale (≥ 500 electrons on the default
/// sensor: shot noise ≤ 4.5 %) and the longer at most at
/// [`AGREEMENT_HIGH`].
const AGREEMENT_LOW: f32 = 0.05;
/// See [`AGREEMENT_LOW`]: clear of saturation.
const AGREEMENT_HIGH: f32 = 0.9;
/// The longer exposure's own value must be below this (not clipped).
const AGREEMENT_CLIP: f32 = 0.95;
/// The pixel whose longer exposure judges a value's level: two pixels
/// along (the same channel), so that its noise is not the value's own
/// (nor shared through a Bayer sensor's demosaicing). Judged by its own
/// values, a level just below [`AGREEMENT_LOW`] (or just above
/// [`AGREEMENT_HIGH`]) would let in only the values noise lifted over the
/// threshold, and the ratio would carry that noise: 1.15 for a white
/// sample seen through a grazing mirror, where the light is 1.
const AGREEMENT_PROXY: usize = 6;
/// Fewer values than this give no ratio.
pub const AGREEMENT_MIN_VALUES: usize = 100;

/// For each exposure of `frames` (each with its exposure in µs) but the
/// longest, its [`ExposureRatio`] to the next longer one; `None` where
/// fewer than [`AGREEMENT_MIN_VALUES`] values were measured well by both.
pub fn exposure_ratios(frames: &[(&Frame, u32)]) -> Vec<Option<ExposureRatio>> {
    let mut order: Vec<&(&Frame, u32)> = frames.iter().collect();
    order.sort_by_key(|(_, t)| *t);
    order
        .windows(2)
        .map(|w| {
            let ((short, ts), (long, tl)) = (w[0], w[1]);
            let scale = *tl as f64 / *ts as f64;
            let (a, b) = (&short.rgb, &long.rgb);
            let n = a.len().min(b.len());
            if n <= AGREEMENT_PROXY {
                return None;
            }
            let low = (AGREEMENT_LOW as f64 * scale) as f32;
            let mut ratios: Vec<f32> = (0..n)
                .step_by(AGREEMENT_STRIDE)
                .filter(|&i| {
                    let j = if i + AGREEMENT_PROXY < n {
                        i + AGREEMENT_PROXY
                    } else {
                        i - AGREEMENT_PROXY
                    };
                    let level = b[j];
                    (low..=AGREEMENT_HIGH).contains(&level)
                        && a[i] > 0.0
                        && b[i] > 0.0
                        && b[i] < AGREEMENT_CLIP
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
        let r = exposure_ratios(&[(&long, 10_000), (&dim, 100), (&mid, 1_000)]);
        assert_eq!(r.len(), 2);
        let r0 = r[0].unwrap();
        assert_eq!((r0.shorter_us, r0.longer_us), (100, 1_000));
        assert!((r0.ratio - 0.8).abs() < 1e-4 && r0.values >= AGREEMENT_MIN_VALUES, "{r0:?}");
        let r1 = r[1].unwrap();
        assert_eq!((r1.shorter_us, r1.longer_us), (1_000, 10_000));
        assert!((r1.ratio - 1.0).abs() < 1e-4, "{r1:?}");
        // Too few values measured well by both: no ratio.
        let few = frame(&scene[..60]);
        assert_eq!(exposure_ratios(&[(&few, 1_000), (&few, 2_000)]), vec![None]);
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
            let r = exposure_ratios(&[(&frame(&short_v), 2_000), (&frame(&long_v), 10_000)]);
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
            merge(&[(&short, 1_000), (&long, 10_000)], &s, 10_000, &DefectMap::default()).unwrap();
        assert!((m.rgb[0] - 5.0).abs() < 1e-5, "{}", m.rgb[0]);
        assert!((m.rgb[3] - 0.01).abs() < 1e-6, "{}", m.rgb[3]);
        assert_eq!(stats, MergeStats::default());
        // Saturated everywhere: counted, the shortest exposure scaled.
        let saturated = frame(&[1.0; 3]);
        let (m, stats) =
            merge(&[(&saturated, 1_000), (&saturated, 10_000)], &s, 10_000, &DefectMap::default())
                .unwrap();
        assert_eq!(stats.clipped, 3);
        assert!((m.rgb[0] - 10.0).abs() < 1e-5);
        // A stuck pixel of the sensor (the middle one) is neither counted
        // nor kept: its neighbours' mean stands in.
        let short = frame(&[0.02, 0.02, 0.02, 1.0, 1.0, 1.0, 0.04, 0.04, 0.04]);
        let long = frame(&[0.2, 0.2, 0.2, 1.0, 1.0, 1.0, 0.4, 0.4, 0.4]);
        use crate::defects::{DefectKind, PixelDefect};
        let map = DefectMap::new(&[PixelDefect { x: 1, y: 0, kind: DefectKind::Stuck }], 3, 1);
        let (m, stats) = merge(&[(&short, 1_000), (&long, 10_000)], &s, 10_000, &map).unwrap();
        assert_eq!(stats, MergeStats::default());
        assert!((m.rgb[3] - 0.3).abs() < 1e-3 && (m.rgb[0] - 0.2).abs() < 1e-3, "{:?}", m.rgb);
    }

    #[test]
    fn merges_as_the_inverse_variance_weighted_mean() {
        let s = sensor();
        let max = s.max_code();
        let gain = max / s.full_well_e;
        let exposures = [500u32, 4_000, 20_000];
        // Codes over the whole range, each exposure a different one.
        let codes: Vec<[u32; 3]> = (0..200u32)
            .map(|i| [i * 7 % 4096, (i * 131 + 5) % 4096, (i * 977 + 11) % 4096])
            .collect();
        let frames: Vec<Frame> = (0..3)
            .map(|k| {
                let v: Vec<f32> =
                    codes.iter().flat_map(|c| [c[k] as f32 / max as f32; 3]).collect();
                frame(&v)
            })
            .collect();
        let inputs: Vec<(&Frame, u32)> = frames.iter().zip(exposures).collect();
        let (m, _) = merge(&inputs, &s, 20_000, &DefectMap::default()).unwrap();
        for (i, c) in codes.iter().enumerate() {
            let (mut num, mut den) = (0.0f64, 0.0f64);
            for k in 0..3 {
                if c[k] == 0 || c[k] == 4095 {
                    continue;
                }
                let t = exposures[k] as f64 * 1e-6;
                let var_code = gain * gain * (c[k] as f64 / gain + 9.0) + 1.0 / 12.0;
                let wgt = (max * t).powi(2) / var_code;
                num += wgt * (c[k] as f64 / max) / t;
                den += wgt;
            }
            let want = if den > 0.0 { num / den * 0.02 } else { 0.0 };
            let got = m.rgb[3 * i] as f64;
            let clipped = c.iter().all(|&c| c == 4095);
            if !clipped {
                assert!((got - want).abs() <= 1e-5 * want.abs() + 1e-9, "{c:?}: {got} vs {want}");
            }
        }
    }

    #[test]
    fn merged_values_vary_as_rate_variance_says() {
        // 20 000 values per rate drawn from the sensor's model (shot and
        // read noise, quantised, clipped), merged: their variance as rates.
        use rand::{Rng, SeedableRng};
        let s = sensor();
        let max = s.max_code();
        let gain = max / s.full_well_e;
        let exposures = [1_000u32, 8_000, 40_000];
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut gauss = move || {
            let (a, b): (f64, f64) = (rng.random::<f64>().max(1e-300), rng.random());
            (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
        };
        // Rates in full scale per second: every exposure measures the first;
        // the 40 ms one saturates at the last.
        for rate in [0.5f64, 5.0, 40.0] {
            let n = 20_000;
            let frames: Vec<Frame> = exposures
                .iter()
                .map(|&t_us| {
                    let e = rate * t_us as f64 * 1e-6 * s.full_well_e;
                    let sd = (e + s.read_noise_e.powi(2)).sqrt();
                    let v: Vec<f32> = (0..n)
                        .map(|_| ((e + sd * gauss()) * gain).round().clamp(0.0, max) / max)
                        .flat_map(|v| [v as f32; 3])
                        .collect();
                    frame(&v)
                })
                .collect();
            let inputs: Vec<(&Frame, u32)> = frames.iter().zip(exposures).collect();
            let (m, _) = merge(&inputs, &s, 40_000, &DefectMap::default()).unwrap();
            let rates: Vec<f64> = m.rgb.iter().step_by(3).map(|&v| v as f64 / 0.04).collect();
            let mean = rates.iter().sum::<f64>() / n as f64;
            let var = rates.iter().map(|r| (r - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
            let want = rate_variance(rate, &exposures, &s).unwrap();
            assert!((mean / rate - 1.0).abs() < 0.01, "rate {rate}: mean {mean}");
            assert!((var / want - 1.0).abs() < 0.05, "rate {rate}: variance {var} against {want}");
        }
        // Every exposure saturated: no variance to give.
        assert_eq!(rate_variance(1e4, &exposures, &s), None);
        assert_eq!(rate_variance(1.0, &[], &s), None);
    }

    #[test]
    fn the_longer_unsaturated_exposure_weighs_more() {
        let s = sensor();
        // 0.2 at 1 ms and 0.21 at 10 ms ×⅒: the merge sits near the long one.
        let (short, long) = (frame(&[0.02, 0.02, 0.02]), frame(&[0.21, 0.21, 0.21]));
        let (m, _) =
            merge(&[(&short, 1_000), (&long, 10_000)], &s, 10_000, &DefectMap::default()).unwrap();
        assert!(m.rgb[0] > 0.208 && m.rgb[0] < 0.21, "{}", m.rgb[0]);
    }
}
