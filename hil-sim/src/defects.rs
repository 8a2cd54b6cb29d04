//! Defective pixels of the simulated sensor: a real sensor ships with a
//! few pixels stuck at the top code (whatever the light) and a few dead
//! ones (always 0). The simulated camera has none unless asked
//! (`scanner … --sim-defect SPEC`):
//!
//! - `stuck:X,Y` — pixel (X, Y) of the frame reads the top code in every
//!   channel at every exposure;
//! - `dead:X,Y` — it reads 0;
//! - `random:N` — N stuck and N dead pixels at positions drawn from the
//!   simulator's seed over the whole frame.
//!
//! Positions are in the frames the camera delivers (after binning).

use std::str::FromStr;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::optics::Frame;

/// One defective pixel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PixelDefect {
    /// Reads the top code in every channel.
    Stuck {
        /// Column.
        x: u32,
        /// Row.
        y: u32,
    },
    /// Reads 0 in every channel.
    Dead {
        /// Column.
        x: u32,
        /// Row.
        y: u32,
    },
}

/// A `--sim-defect` argument.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DefectSpec {
    /// One pixel.
    Pixel(PixelDefect),
    /// This many stuck and as many dead pixels at seeded positions.
    Random(u32),
}

/// A `--sim-defect` argument that does not parse.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("sensor defect `{spec}`: {why} (stuck:X,Y, dead:X,Y or random:N)")]
pub struct DefectSpecError {
    spec: String,
    why: &'static str,
}

impl FromStr for DefectSpec {
    type Err = DefectSpecError;

    fn from_str(spec: &str) -> Result<Self, Self::Err> {
        let err = |why| DefectSpecError { spec: spec.to_string(), why };
        let (kind, rest) = spec.split_once(':').ok_or_else(|| err("missing `:`"))?;
        let xy = || -> Result<(u32, u32), DefectSpecError> {
            let (x, y) = rest.split_once(',').ok_or_else(|| err("missing `,`"))?;
            let p = |s: &str| s.trim().parse::<u32>().map_err(|_| err("bad pixel position"));
            Ok((p(x)?, p(y)?))
        };
        Ok(match kind {
            "stuck" => {
                let (x, y) = xy()?;
                DefectSpec::Pixel(PixelDefect::Stuck { x, y })
            }
            "dead" => {
                let (x, y) = xy()?;
                DefectSpec::Pixel(PixelDefect::Dead { x, y })
            }
            "random" => DefectSpec::Random(
                rest.trim()
                    .parse()
                    .ok()
                    .filter(|&n| n <= 1_000_000)
                    .ok_or_else(|| err("bad count (at most 1000000)"))?,
            ),
            _ => return Err(err("unknown kind")),
        })
    }
}

/// The defective pixels of a `width` × `height` sensor that `specs` ask
/// for, random ones drawn from `seed`; pixels outside the frame are
/// refused.
pub fn place(
    specs: &[DefectSpec],
    width: u32,
    height: u32,
    seed: u64,
) -> Result<Vec<PixelDefect>, String> {
    let mut out = Vec::new();
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5E45_0D3F_EC75);
    for spec in specs {
        match *spec {
            DefectSpec::Pixel(d) => {
                let (PixelDefect::Stuck { x, y } | PixelDefect::Dead { x, y }) = d;
                if x >= width || y >= height {
                    return Err(format!(
                        "sensor defect at ({x}, {y}) outside the {width} × {height} frame"
                    ));
                }
                out.push(d);
            }
            DefectSpec::Random(n) => {
                for _ in 0..n {
                    let (x, y) = (rng.random_range(0..width), rng.random_range(0..height));
                    out.push(PixelDefect::Stuck { x, y });
                    let (x, y) = (rng.random_range(0..width), rng.random_range(0..height));
                    out.push(PixelDefect::Dead { x, y });
                }
            }
        }
    }
    Ok(out)
}

/// Apply `defects` to a frame read out by the sensor (values are ADC code /
/// max code: stuck 1, dead 0).
pub fn apply(frame: &mut Frame, defects: &[PixelDefect]) {
    let w = frame.width as usize;
    for d in defects {
        let (PixelDefect::Stuck { x, y } | PixelDefect::Dead { x, y }) = *d;
        let v = if matches!(d, PixelDefect::Stuck { .. }) { 1.0 } else { 0.0 };
        let i = 3 * (y as usize * w + x as usize);
        if x < frame.width
            && let Some(px) = frame.rgb.get_mut(i..i + 3)
        {
            px.fill(v);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn specs_parse_and_place_within_the_frame() {
        assert_eq!(
            "stuck:10,20".parse::<DefectSpec>().unwrap(),
            DefectSpec::Pixel(PixelDefect::Stuck { x: 10, y: 20 })
        );
        assert_eq!(
            "dead:0,7".parse::<DefectSpec>().unwrap(),
            DefectSpec::Pixel(PixelDefect::Dead { x: 0, y: 7 })
        );
        assert_eq!("random:5".parse::<DefectSpec>().unwrap(), DefectSpec::Random(5));
        for bad in ["stuck", "stuck:1", "stuck:a,2", "hot:1,2", "random:x", "dead:-1,2"] {
            let e = bad.parse::<DefectSpec>().unwrap_err().to_string();
            assert!(e.contains(bad), "{e}");
        }
        let specs = ["random:50".parse().unwrap(), "stuck:3,4".parse().unwrap()];
        let a = place(&specs, 64, 32, 9).unwrap();
        assert_eq!(a.len(), 101);
        assert_eq!(a, place(&specs, 64, 32, 9).unwrap(), "seeded");
        assert_ne!(a, place(&specs, 64, 32, 10).unwrap());
        assert!(a.iter().all(|d| {
            let (PixelDefect::Stuck { x, y } | PixelDefect::Dead { x, y }) = *d;
            x < 64 && y < 32
        }));
        assert!(place(&["stuck:64,0".parse().unwrap()], 64, 32, 1).unwrap_err().contains("64"));
        let mut f = Frame { width: 4, height: 2, rgb: vec![0.3; 24] };
        apply(&mut f, &[PixelDefect::Stuck { x: 1, y: 1 }, PixelDefect::Dead { x: 3, y: 0 }]);
        assert_eq!(f.pixel(1, 1), [1.0; 3]);
        assert_eq!(f.pixel(3, 0), [0.0; 3]);
        assert_eq!(f.pixel(0, 0), [0.3; 3]);
    }
}
