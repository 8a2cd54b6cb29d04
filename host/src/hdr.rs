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
    let shortest =
        frames.iter().enumerate().min_by_key(|(_, (_, t))| *t).map(|(i, _)| i).unwrap_or(0);
    let mut out = vec![0.0f32; first.rgb.len()];
    use rayon::prelude::*;
    let chunk = 3 * w as usize;
    let stats = out
        .par_chunks_mut(chunk.max(1))
        .enumerate()
        .map(|(row, line)| {
            let mut stats = MergeStats::default();
            for (j, o) in line.iter_mut().enumerate() {
                let i = row * chunk + j;
                let (mut num, mut den) = (0.0f64, 0.0f64);
                let mut all_clipped = true;
                for &(f, t_us) in frames {
                    let v = f.rgb[i] as f64;
                    let code = (v * max).round();
                    if code >= max {
                        continue;
                    }
                    all_clipped = false;
                    if code <= 0.0 {
                        continue;
                    }
                    let t = t_us as f64 * 1e-6;
                    let e = code / gain;
                    let var_code = gain * gain * (e + read2) + 1.0 / 12.0;
                    let var_rate = var_code / (max * t).powi(2);
                    let wgt = 1.0 / var_rate;
                    num += wgt * v / t;
                    den += wgt;
                }
                *o = if den > 0.0 {
                    (num / den * reference_us as f64 * 1e-6) as f32
                } else if all_clipped {
                    stats.clipped += 1;
                    let (f, t) = frames[shortest];
                    (f.rgb[i] as f64 * reference_us as f64 / t as f64) as f32
                } else {
                    stats.black += 1;
                    0.0
                };
            }
            stats
        })
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
    fn the_longer_unsaturated_exposure_weighs_more() {
        let s = sensor();
        // 0.2 at 1 ms and 0.21 at 10 ms ×⅒: the merge sits near the long one.
        let (short, long) = (frame(&[0.02, 0.02, 0.02]), frame(&[0.21, 0.21, 0.21]));
        let (m, _) = merge(&[(&short, 1_000), (&long, 10_000)], &s, 10_000).unwrap();
        assert!(m.rgb[0] > 0.208 && m.rgb[0] < 0.21, "{}", m.rgb[0]);
    }
}
