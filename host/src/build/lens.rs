//! A photograph's lens distortion, for `scanner rectify --lens`
//! (docs/direct-images.md, "Lens distortion").
//!
//! A camera's lens bends the straight lines a pinhole would show. The
//! model is the scanner camera's own ([`scanner_geometry::radial_distort`],
//! the Brown–Conrady radial terms, OpenCV's k1 and k2) about the
//! photograph's centre: a pinhole image point p shows at
//!
//! q = c + S · n · (1 + k1 |n|² + k2 |n|⁴),  n = (p − c) / S,
//!
//! c the principal point (a calibration's, or the photograph's centre), S
//! the focal length in px when the coefficients are a calibration's
//! (OpenCV's), else half the photograph's diagonal (the scale `--lens
//! auto` estimates k1 in). k1 < 0 is barrel distortion, k1 > 0
//! pincushion.

use scanner_geometry::{radial_distort, radial_slope, radial_undistort};

/// A lens' radial distortion, as a user gives it or the corners' finder
/// estimates it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lens {
    /// k1, k2.
    pub k: [f64; 2],
    /// The focal length, px, that normalises the radius (OpenCV's
    /// coefficients); `None`: half the photograph's diagonal.
    pub focal_px: Option<f64>,
    /// The principal point, the distortion's centre, px (OpenCV's cx, cy);
    /// `None`: the photograph's centre.
    pub centre_px: Option<[f64; 2]>,
}

impl Lens {
    /// No distortion.
    pub const PINHOLE: Lens = Lens::radial([0.0; 2]);

    /// k1, k2 about the photograph's centre, the radius in half-diagonals.
    pub const fn radial(k: [f64; 2]) -> Lens {
        Lens { k, focal_px: None, centre_px: None }
    }

    /// Whether it leaves every point where it is.
    pub fn is_pinhole(&self) -> bool {
        self.k == [0.0; 2]
    }

    /// `K1[,K2[,FOCAL_PX[,CX,CY]]]`, as `--lens` takes it.
    pub fn parse(text: &str) -> Result<Lens, String> {
        let form = "auto, or K1[,K2[,FOCAL_PX[,CX,CY]]]";
        let v: Vec<f64> = text
            .split(',')
            .map(|s| s.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|_| format!("--lens {text}: {form} (numbers)"))?;
        let lens = match v[..] {
            [k1] => Lens::radial([k1, 0.0]),
            [k1, k2] => Lens::radial([k1, k2]),
            [k1, k2, f] => Lens { focal_px: Some(f), ..Lens::radial([k1, k2]) },
            [k1, k2, f, cx, cy] => {
                Lens { focal_px: Some(f), centre_px: Some([cx, cy]), ..Lens::radial([k1, k2]) }
            }
            _ => return Err(format!("--lens {text}: {form} (1, 2, 3 or 5 numbers)")),
        };
        if !lens.k.iter().all(|k| k.is_finite() && k.abs() <= MAX_K) {
            return Err(format!("--lens {text}: k1 and k2 within ±{MAX_K}"));
        }
        if let Some(f) = lens.focal_px
            && !(f.is_finite() && f >= 1.0)
        {
            return Err(format!("--lens {text}: a focal length ≥ 1 px"));
        }
        if let Some(c) = lens.centre_px
            && !c.iter().all(|v| v.is_finite())
        {
            return Err(format!("--lens {text}: a principal point of two numbers, px"));
        }
        Ok(lens)
    }
}

/// The largest |k1|, |k2| taken.
pub const MAX_K: f64 = 10.0;

/// How a lens is to be known: given, or estimated from the piece's own
/// straight sides.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LensChoice {
    /// Given (a pinhole: [`Lens::PINHOLE`]).
    Known(Lens),
    /// k1 estimated from the piece's sides (plumb lines), k2 = 0, the
    /// radius normalised by half the photograph's diagonal.
    Estimate,
}

/// Where the points of a pinhole image show in a frame, and back: the
/// region images' frames are pinhole images ([`Pinhole`]), a photograph
/// has its lens ([`LensMap`]).
pub trait FrameMap: Sync {
    /// The frame point, px, of the pinhole point `p`.
    fn in_frame(&self, p: [f64; 2]) -> [f64; 2];
    /// The pinhole point of the frame point `q`, px.
    fn in_pinhole(&self, q: [f64; 2]) -> [f64; 2];
    /// The most pinhole px that one frame px spans, in any direction.
    fn stretch(&self) -> f64;
}

/// A frame that is a pinhole image.
#[derive(Debug, Clone, Copy)]
pub struct Pinhole;

impl FrameMap for Pinhole {
    #[inline(always)]
    fn in_frame(&self, p: [f64; 2]) -> [f64; 2] {
        p
    }
    #[inline(always)]
    fn in_pinhole(&self, q: [f64; 2]) -> [f64; 2] {
        q
    }
    #[inline(always)]
    fn stretch(&self) -> f64 {
        1.0
    }
}

/// A lens on a photograph of a given size.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LensMap {
    lens: Lens,
    centre: [f64; 2],
    scale: f64,
    stretch: f64,
}

impl LensMap {
    /// `lens` on a `width × height` px photograph: its principal point
    /// must lie in the photograph, and it must map the photograph one to
    /// one (its radius growing with the pinhole's out to the photograph's
    /// farthest corner).
    pub fn new(lens: Lens, width: u32, height: u32) -> Result<LensMap, String> {
        let (w, h) = (width as f64, height as f64);
        let half_diagonal = 0.5 * w.hypot(h);
        let scale = lens.focal_px.unwrap_or(half_diagonal);
        let centre = lens.centre_px.unwrap_or([0.5 * w, 0.5 * h]);
        if !((0.0..=w).contains(&centre[0]) && (0.0..=h).contains(&centre[1])) {
            return Err(format!(
                "the principal point ({}, {}) px lies outside the {width} × {height} px photograph",
                centre[0], centre[1]
            ));
        }
        let corner = [0.0, w]
            .iter()
            .flat_map(|&x| [0.0, h].map(|y| (x - centre[0]).hypot(y - centre[1])))
            .fold(0.0, f64::max)
            / scale;
        let k = lens.k;
        // Out along the pinhole's radius until the photograph's corner:
        // the slope stays clear of 0, and the most a frame px stretches.
        let step = corner / 200.0;
        let mut stretch: f64 = 1.0;
        let mut r = 0.0;
        loop {
            let slope = radial_slope(k, r);
            let rd = radial_distort(k, [r, 0.0])[0];
            if !(slope > 0.05 && rd >= 0.0) || r > 20.0 * corner.max(1.0) {
                return Err(format!(
                    "lens k1 {}, k2 {} does not map the {width} × {height} px photograph one to \
                     one",
                    k[0], k[1]
                ));
            }
            stretch = stretch.max(1.0 / slope);
            if r > 0.0 {
                stretch = stretch.max(r / rd);
            }
            if rd >= corner {
                break;
            }
            r += step;
        }
        Ok(LensMap { lens, centre, scale, stretch })
    }

    /// The lens.
    pub fn lens(&self) -> Lens {
        self.lens
    }

    /// `p` (px) in the distortion's normalised coordinates.
    fn normalised(&self, p: [f64; 2]) -> [f64; 2] {
        [(p[0] - self.centre[0]) / self.scale, (p[1] - self.centre[1]) / self.scale]
    }

    fn denormalised(&self, n: [f64; 2]) -> [f64; 2] {
        [self.centre[0] + self.scale * n[0], self.centre[1] + self.scale * n[1]]
    }

    /// How the frame point moves with the pinhole point at `p`:
    /// ∂q/∂p = s I + 2 (k1 + 2 k2 |n|²) n nᵀ.
    pub fn jacobian(&self, p: [f64; 2]) -> [[f64; 2]; 2] {
        let n = self.normalised(p);
        let [k1, k2] = self.lens.k;
        let r2 = n[0] * n[0] + n[1] * n[1];
        let s = 1.0 + r2 * (k1 + k2 * r2);
        let g = 2.0 * (k1 + 2.0 * k2 * r2);
        [[s + g * n[0] * n[0], g * n[0] * n[1]], [g * n[1] * n[0], s + g * n[1] * n[1]]]
    }
}

impl FrameMap for LensMap {
    fn in_frame(&self, p: [f64; 2]) -> [f64; 2] {
        if self.lens.is_pinhole() {
            return p;
        }
        self.denormalised(radial_distort(self.lens.k, self.normalised(p)))
    }
    fn in_pinhole(&self, q: [f64; 2]) -> [f64; 2] {
        if self.lens.is_pinhole() {
            return q;
        }
        self.denormalised(radial_undistort(self.lens.k, self.normalised(q)))
    }
    fn stretch(&self) -> f64 {
        self.stretch
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parse_takes_one_to_three_numbers_in_range() {
        assert_eq!(Lens::parse("-0.1").unwrap(), Lens::radial([-0.1, 0.0]));
        assert_eq!(Lens::parse("-0.1, 0.02").unwrap(), Lens::radial([-0.1, 0.02]));
        assert_eq!(
            Lens::parse("-0.1,0.02,3000").unwrap(),
            Lens { focal_px: Some(3000.0), ..Lens::radial([-0.1, 0.02]) }
        );
        assert_eq!(
            Lens::parse("-0.1,0.02,3000,2012.5,1490").unwrap(),
            Lens {
                focal_px: Some(3000.0),
                centre_px: Some([2012.5, 1490.0]),
                ..Lens::radial([-0.1, 0.02])
            }
        );
        for bad in [
            "",
            "x",
            "1,2,3,4",
            "1,2,3,4,5,6",
            "nan",
            "11",
            "0.1,0.1,0",
            "0.1,0,inf",
            "0,0,9,1,nan",
        ] {
            assert!(Lens::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn the_map_goes_there_and_back_and_its_jacobian_is_the_derivative() {
        let map = LensMap::new(Lens::radial([-0.12, 0.03]), 600, 400).unwrap();
        assert!(map.stretch() > 1.0);
        for p in [[10.0, 20.0], [300.0, 200.0], [590.0, 390.0], [450.5, 33.25]] {
            let q = map.in_frame(p);
            let back = map.in_pinhole(q);
            assert!((back[0] - p[0]).abs() < 1e-9 && (back[1] - p[1]).abs() < 1e-9, "{p:?}");
            let j = map.jacobian(p);
            let e = 1e-5;
            for (i, d) in [[e, 0.0], [0.0, e]].iter().enumerate() {
                let a = map.in_frame([p[0] + d[0], p[1] + d[1]]);
                let b = map.in_frame([p[0] - d[0], p[1] - d[1]]);
                for r in 0..2 {
                    let num = (a[r] - b[r]) / (2.0 * e);
                    assert!((num - j[r][i]).abs() < 1e-6, "{p:?}: {num} against {}", j[r][i]);
                }
            }
        }
        // The centre stays; barrel distortion pulls the corners in.
        assert_eq!(map.in_frame([300.0, 200.0]), [300.0, 200.0]);
        assert!(map.in_frame([0.0, 0.0])[0] > 0.0);
    }

    #[test]
    fn a_principal_point_off_the_centre_stays_and_must_lie_in_the_photograph() {
        let lens = Lens { centre_px: Some([150.0, 320.0]), ..Lens::radial([-0.05, 0.0]) };
        let map = LensMap::new(lens, 600, 400).unwrap();
        assert_eq!(map.in_frame([150.0, 320.0]), [150.0, 320.0]);
        // The farthest corner from it pulled in along its radius.
        let q = map.in_frame([600.0, 0.0]);
        let (a, b) = ((600.0f64 - 150.0).hypot(320.0), (q[0] - 150.0).hypot(q[1] - 320.0));
        assert!(b < a && ((q[1] - 320.0) / (q[0] - 150.0) + 320.0 / 450.0).abs() < 1e-9);
        let outside = Lens { centre_px: Some([-1.0, 200.0]), ..Lens::radial([-0.2, 0.0]) };
        assert!(LensMap::new(outside, 600, 400).unwrap_err().contains("principal point"));
        // Measured to its farthest corner: a lens mild enough about the
        // centre folds the photograph about a corner.
        let k = Lens::radial([-0.1, 0.0]);
        assert!(LensMap::new(k, 600, 400).is_ok());
        let corner = Lens { centre_px: Some([0.0, 0.0]), ..k };
        assert!(LensMap::new(corner, 600, 400).unwrap_err().contains("one to one"));
    }

    #[test]
    fn a_lens_that_folds_the_photograph_is_refused() {
        let err = LensMap::new(Lens::radial([-0.5, 0.0]), 600, 400).unwrap_err();
        assert!(err.contains("one to one"), "{err}");
        // The same coefficients on a long focal length's scale are mild.
        assert!(
            LensMap::new(Lens { focal_px: Some(2000.0), ..Lens::radial([-0.5, 0.0]) }, 600, 400)
                .is_ok()
        );
    }
}
