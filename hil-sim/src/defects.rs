//! Defective pixels of the simulated sensor: a real sensor ships with a
//! few pixels stuck at the top code (whatever the light) and a few dead
//! ones (always 0). The simulated camera has none unless asked
//! (`scanner … --sim-defect SPEC`):
//!
//! - `stuck:X,Y` — pixel (X, Y) of the frame reads the top code in every
//!   channel at every exposure;
//! - `dead:X,Y` — it reads 0;
//! - `hot:X,Y,RATE` — it gathers RATE dark electrons per second of
//!   exposure on top of its light (dark current), in every channel;
//! - `random:N` — N stuck and N dead pixels at positions drawn from the
//!   simulator's seed over the whole frame.
//!
//! Positions are in the frames the camera delivers (after binning).

use std::str::FromStr;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::optics::Frame;

/// One defective pixel.
#[derive(Debug, Clone, Copy, PartialEq)]
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
    /// Gathers dark electrons at `e_per_s` per second of exposure.
    Hot {
        /// Column.
        x: u32,
        /// Row.
        y: u32,
        /// Dark current, electrons per second.
        e_per_s: f32,
    },
}

impl PixelDefect {
    /// Its pixel (column, row).
    pub fn position(&self) -> (u32, u32) {
        match *self {
            PixelDefect::Stuck { x, y }
            | PixelDefect::Dead { x, y }
            | PixelDefect::Hot { x, y, .. } => (x, y),
        }
    }
}

/// A `--sim-defect` argument.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DefectSpec {
    /// One pixel.
    Pixel(PixelDefect),
    /// This many stuck and as many dead pixels at seeded positions.
    Random(u32),
}

/// A `--sim-defect` argument that does not parse.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("sensor defect `{spec}`: {why} (stuck:X,Y, dead:X,Y, hot:X,Y,RATE or random:N)")]
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
            "hot" => {
                let parts: Vec<&str> = rest.split(',').collect();
                let [x, y, rate] = parts[..] else {
                    return Err(err("a hot pixel is X,Y,RATE (dark electrons per second)"));
                };
                let e_per_s = rate
                    .trim()
                    .parse::<f32>()
                    .ok()
                    .filter(|r| r.is_finite() && *r > 0.0)
                    .ok_or_else(|| err("bad dark current, electrons per second"))?;
                let p = |s: &str| s.trim().parse::<u32>().map_err(|_| err("bad pixel position"));
                DefectSpec::Pixel(PixelDefect::Hot { x: p(x)?, y: p(y)?, e_per_s })
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
                let (x, y) = d.position();
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

/// Apply `defects` to a frame read out by the sensor after `exposure_s`
/// (values are ADC code / max code: stuck 1, dead 0, hot its dark
/// electrons added, clipped at full scale).
pub fn apply(
    frame: &mut Frame,
    defects: &[PixelDefect],
    exposure_s: f64,
    sensor: &crate::geometry::SensorSpec,
) {
    let w = frame.width as usize;
    for d in defects {
        let (x, y) = d.position();
        let i = 3 * (y as usize * w + x as usize);
        if x >= frame.width {
            continue;
        }
        let Some(px) = frame.rgb.get_mut(i..i + 3) else { continue };
        match *d {
            PixelDefect::Stuck { .. } => px.fill(1.0),
            PixelDefect::Dead { .. } => px.fill(0.0),
            PixelDefect::Hot { e_per_s, .. } => {
                // Electrons to codes and back to a fraction of full scale,
                // on whole codes as the ADC gives them.
                let max = sensor.max_code();
                let dark = e_per_s as f64 * exposure_s / sensor.full_well_e;
                for v in px {
                    *v = ((((*v as f64) + dark) * max).round().min(max) / max) as f32;
                }
            }
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
        assert_eq!(
            "hot:3,4,2500".parse::<DefectSpec>().unwrap(),
            DefectSpec::Pixel(PixelDefect::Hot { x: 3, y: 4, e_per_s: 2500.0 })
        );
        for bad in [
            "stuck",
            "stuck:1",
            "stuck:a,2",
            "warm:1,2",
            "hot:1,2",
            "hot:1,2,-5",
            "random:x",
            "dead:-1,2",
        ] {
            let e = bad.parse::<DefectSpec>().unwrap_err().to_string();
            assert!(e.contains(bad), "{e}");
        }
        let specs = ["random:50".parse().unwrap(), "stuck:3,4".parse().unwrap()];
        let a = place(&specs, 64, 32, 9).unwrap();
        assert_eq!(a.len(), 101);
        assert_eq!(a, place(&specs, 64, 32, 9).unwrap(), "seeded");
        assert_ne!(a, place(&specs, 64, 32, 10).unwrap());
        assert!(a.iter().all(|d| {
            let (x, y) = d.position();
            x < 64 && y < 32
        }));
        assert!(place(&["stuck:64,0".parse().unwrap()], 64, 32, 1).unwrap_err().contains("64"));
        let mut f = Frame { width: 4, height: 2, rgb: vec![0.3; 24] };
        let sensor = crate::geometry::ScannerGeometry::default_scanner().sensor;
        let hot = PixelDefect::Hot { x: 2, y: 1, e_per_s: 10_000.0 };
        let defects = [PixelDefect::Stuck { x: 1, y: 1 }, PixelDefect::Dead { x: 3, y: 0 }, hot];
        apply(&mut f, &defects, 0.1, &sensor);
        assert_eq!(f.pixel(1, 1), [1.0; 3]);
        assert_eq!(f.pixel(3, 0), [0.0; 3]);
        assert_eq!(f.pixel(0, 0), [0.3; 3]);
        // 1 000 dark electrons of a 10 000 e⁻ full well: +0.1 of full scale.
        assert!((f.pixel(2, 1)[0] - 0.4).abs() < 1e-3, "{:?}", f.pixel(2, 1));
    }
}
