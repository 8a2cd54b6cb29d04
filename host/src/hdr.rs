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
/// one frame in units of the `reference_us` exposure.
pub fn merge(
    frames: &[(&Frame, u32)],
    sensor: &SensorSpec,
    reference_us: u32,
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
                    let e = c as f64 / gain;
                    let var_code = gain * gain * (e + read2) + 1.0 / 12.0;
                    let wgt = (max * t).powi(2) / var_code;
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
                    *o = if den[j] > 0.0 {
                        num[j] / den[j] * to_reference
                    } else if all_clipped[j] {
                        stats.clipped += 1;
                        let (f, t) = frames[shortest];
                        (f.rgb[start + j] as f64 * reference_us as f64 / t as f64) as f32
                    } else {
                        stats.black += 1;
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
    Ok((Frame { width: w, height: h, rgb: out }, stats))
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
    fn saturated_and_black_values_are_left_out() {
        let s = sensor();
        // Pixel 0: saturated at 10 ms, 0.5 at 1 ms → 5.0 at 10 ms.
        // Pixel 1: black at 1 ms, 0.01 at 10 ms.
        let short = frame(&[0.5, 0.5, 0.5, 0.0, 0.0, 0.0]);
        let long = frame(&[1.0, 1.0, 1.0, 0.01, 0.01, 0.01]);
        let (m, stats) = merge(&[(&short, 1_000), (&long, 10_000)], &s, 10_000).unwrap();
        assert!((m.rgb[0] - 5.0).abs() < 1e-5, "{}", m.rgb[0]);
        assert!((m.rgb[3] - 0.01).abs() < 1e-6, "{}", m.rgb[3]);
        assert_eq!(stats, MergeStats::default());
        // Saturated everywhere: counted, the shortest exposure scaled.
        let saturated = frame(&[1.0; 3]);
        let (m, stats) = merge(&[(&saturated, 1_000), (&saturated, 10_000)], &s, 10_000).unwrap();
        assert_eq!(stats.clipped, 3);
        assert!((m.rgb[0] - 10.0).abs() < 1e-5);
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
        let (m, _) = merge(&inputs, &s, 20_000).unwrap();
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
    fn the_longer_unsaturated_exposure_weighs_more() {
        let s = sensor();
        // 0.2 at 1 ms and 0.21 at 10 ms ×⅒: the merge sits near the long one.
        let (short, long) = (frame(&[0.02, 0.02, 0.02]), frame(&[0.21, 0.21, 0.21]));
        let (m, _) = merge(&[(&short, 1_000), (&long, 10_000)], &s, 10_000).unwrap();
        assert!(m.rgb[0] > 0.208 && m.rgb[0] < 0.21, "{}", m.rgb[0]);
    }
}
