//! Reading a scan directory for the builder: its manifest checked against
//! the nominal geometry, frames by lit mirror, values per second of
//! exposure.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, PoisonError};

use scanner_geometry::ScannerGeometry;

use super::error::BuildError;
use crate::camera::Frame;
use crate::defects::{DefectMap, PixelDefect};
use crate::exrio::{PixelRect, rects_overlap};
use crate::scan::{FrameRecord, Manifest};

/// A scan ready to be read.
#[derive(Debug, Clone)]
pub struct ScanFrames {
    /// The directory.
    pub dir: PathBuf,
    /// Its manifest.
    pub manifest: Manifest,
    /// SHA-256 of the manifest file.
    pub manifest_sha256: String,
    /// The sensor's defective pixels: those its metering found, and any
    /// added ([`ScanFrames::add_defects`]); replaced in every frame read.
    defects: DefectMap,
    /// Lit mirrors whose frame file matched its checksum: each file is
    /// checked the first time it is read.
    checked: Arc<Mutex<Vec<usize>>>,
}

impl ScanFrames {
    /// Open the scan in `dir`, taken with the scanner `geometry` describes:
    /// complete, of this geometry, frames of the camera's size.
    pub fn open(dir: &Path, geometry: &ScannerGeometry) -> Result<ScanFrames, BuildError> {
        let (manifest, manifest_sha256) =
            Manifest::load_hashed(dir).map_err(|e| BuildError::Input(e.to_string()))?;
        let want = geometry.hash();
        if manifest.settings.geometry_sha256 != want {
            return Err(BuildError::Input(format!(
                "{}: taken with geometry {}…, not this scanner's {}…",
                dir.display(),
                &manifest.settings.geometry_sha256.get(..12).unwrap_or("?"),
                &want[..12]
            )));
        }
        let count = manifest.settings.mirror_count;
        if count > geometry.mirrors.len() {
            return Err(BuildError::Input(format!(
                "{}: a scan of {count} mirrors; the scanner has {}",
                dir.display(),
                geometry.mirrors.len()
            )));
        }
        let missing: Vec<usize> =
            (0..count).filter(|l| !manifest.frames.iter().any(|f| f.mirror == *l)).collect();
        if !missing.is_empty() || !manifest.complete {
            return Err(BuildError::Input(format!(
                "{}: incomplete scan, frames missing for {} (finish it with --resume)",
                dir.display(),
                crate::scan::mirror_list(&missing)
            )));
        }
        for f in &manifest.frames {
            if (f.width, f.height) != (geometry.camera.width, geometry.camera.height) {
                return Err(BuildError::Input(format!(
                    "{}: {} is {}×{} px, the camera has {}×{}",
                    dir.display(),
                    f.file,
                    f.width,
                    f.height,
                    geometry.camera.width,
                    geometry.camera.height
                )));
            }
        }
        let found = manifest.settings.defects();
        let defects = DefectMap::new(&found, geometry.camera.width, geometry.camera.height);
        let checked = Arc::default();
        Ok(ScanFrames { dir: dir.to_path_buf(), manifest, manifest_sha256, defects, checked })
    }

    /// Replace `defects` too in the frames read from now on (the sensor's
    /// defects a calibration found).
    pub fn add_defects(&mut self, defects: &[PixelDefect]) {
        self.defects.extend(defects);
    }

    /// The sensor's defective pixels replaced in the frames read.
    pub fn defects(&self) -> &[PixelDefect] {
        self.defects.defects()
    }

    /// Lit mirrors, in order.
    pub fn lights(&self) -> Vec<usize> {
        let mut l: Vec<usize> = self.manifest.frames.iter().map(|f| f.mirror).collect();
        l.sort_unstable();
        l.dedup();
        l
    }

    fn record(&self, light: usize) -> Result<&FrameRecord, BuildError> {
        self.manifest.frames.iter().find(|f| f.mirror == light).ok_or_else(|| {
            BuildError::Input(format!("{}: no frame for mirror {light}", self.dir.display()))
        })
    }

    /// The exposure of the frame lit by `light`, s (what [`ScanFrames::read`]
    /// divides by); an exposure of 0 is refused.
    pub fn exposure_s(&self, light: usize) -> Result<f32, BuildError> {
        let rec = self.record(light)?;
        if rec.exposure_us == 0 {
            let path = self.dir.join(&rec.file);
            return Err(BuildError::Input(format!("{}: exposure 0", path.display())));
        }
        Ok(rec.exposure_us as f32 * 1e-6)
    }

    /// The exposures merged into the frame lit by `light`, µs: the frame's
    /// own bracket (auto exposure's extended ones), else the scan's, else
    /// its one exposure.
    pub fn exposures_us(&self, light: usize) -> Result<Vec<u32>, BuildError> {
        let rec = self.record(light)?;
        Ok(if !rec.bracket_us.is_empty() {
            rec.bracket_us.clone()
        } else if !self.manifest.settings.bracket_us.is_empty() {
            self.manifest.settings.bracket_us.clone()
        } else {
            vec![rec.exposure_us]
        })
    }

    /// The frame lit by mirror `light`, values divided by its exposure (s).
    pub fn read(&self, light: usize) -> Result<Frame, BuildError> {
        self.read_within(light, &[[0, 0, usize::MAX, usize::MAX]])
    }

    /// The same, decoding only the blocks of the file that meet one of
    /// `windows` (frame pixels `[x0, y0, x1, y1)`); other pixels are 0.
    pub fn read_within(&self, light: usize, windows: &[PixelRect]) -> Result<Frame, BuildError> {
        self.read_within_where(light, windows, &|_| true)
    }

    /// [`ScanFrames::read_within`] decoding, of the blocks that meet
    /// `windows`, only those `also` accepts (other pixels are 0). A value
    /// is as `read_within` gives it where its block and those of the
    /// pixels within [`crate::defects::PATCH_RADIUS`] were decoded.
    pub fn read_within_where(
        &self,
        light: usize,
        windows: &[PixelRect],
        also: &(dyn Fn(PixelRect) -> bool + Sync),
    ) -> Result<Frame, BuildError> {
        let rec = self.record(light)?;
        let path = self.dir.join(&rec.file);
        let t = self.exposure_s(light)?;
        let wanted =
            |block: PixelRect| windows.iter().any(|w| rects_overlap(*w, block)) && also(block);
        // The manifest's size (which `open` checked against the camera's):
        // a file of another is refused before its pixels are read.
        let size = Some([rec.width as usize, rec.height as usize]);
        let checked = self.checked.lock().unwrap_or_else(PoisonError::into_inner).contains(&light);
        let decoded = if checked {
            crate::exrio::read_rgb_within(&path, &wanted, t, size)
        } else {
            // The first read of this file: all of it, checked against the
            // manifest (whose SHA-256 a material's provenance records)
            // while its blocks decode from memory.
            let bytes = scanner_formats::input::read(&path)
                .map_err(|e| BuildError::Input(format!("{}: {e}", path.display())))?;
            let (sha256, decoded) = rayon::join(
                || crate::scan::sha256_hex(&bytes),
                || {
                    let source = std::io::Cursor::new(&bytes[..]);
                    crate::exrio::decode_rgb_within(source, &wanted, t, size)
                },
            );
            if sha256 != rec.sha256 {
                return Err(BuildError::Input(format!(
                    "{}: not the frame the scan recorded: its SHA-256 differs from the \
                     manifest's (changed or damaged since; `scanner verify {}` checks every \
                     frame)",
                    path.display(),
                    self.dir.display()
                )));
            }
            self.checked.lock().unwrap_or_else(PoisonError::into_inner).push(light);
            decoded
        };
        let mut f = decoded.map_err(|e| BuildError::Input(format!("{}: {e}", path.display())))?;
        // Within the windows only: the rest of the frame was not decoded.
        let inside = |x: usize, y: usize| {
            windows.iter().any(|w| (w[0]..w[2]).contains(&x) && (w[1]..w[3]).contains(&y))
        };
        self.defects.patch_where(&mut f, inside);
        Ok(f)
    }

    /// The commanded axis values of the frame lit by `light`.
    pub fn axes(&self, light: usize) -> Result<[f64; 3], BuildError> {
        Ok(self.record(light)?.axis_units)
    }
}

/// Bilinear RGB sample of a frame at continuous (x, y) (pixel centres at
/// half-integers), edges clamped.
#[inline]
pub fn frame_bilinear(f: &Frame, x: f64, y: f64) -> [f64; 3] {
    let (i, w) = super::plane::bilinear_taps(f.width as usize, f.height as usize, [x, y]);
    std::array::from_fn(|k| (0..4).map(|t| f.rgb[3 * i[t] + k] as f64 * w[t]).sum())
}

/// Catmull–Rom bicubic RGB sample of a frame at continuous (x, y).
#[inline]
pub fn frame_bicubic(f: &Frame, x: f64, y: f64) -> [f64; 3] {
    BicubicFilter::new(frame_dims(f), x, y).apply(f)
}

/// A frame's width and height, px.
pub fn frame_dims(f: &Frame) -> [usize; 2] {
    [f.width as usize, f.height as usize]
}

/// A Catmull–Rom filter at one position of frames of one size, its taps
/// found once ([`frame_bicubic`]) and applied to any frame of that size:
/// the region images sample every light's frame at the same positions.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BicubicFilter {
    /// The frame's size, px.
    dims: [usize; 2],
    /// The top-left tap's pixel (edges clamped when applied).
    corner: [isize; 2],
    /// Weights along x and y.
    wx: [f64; 4],
    wy: [f64; 4],
    /// Which of the 4 × 4 taps (bit 4 j + i) are used.
    taps: u16,
    /// The used taps' weight (renormalised over when masked).
    norm: Option<f64>,
    /// Per tap (4 j + i), the share of its pixel's square on the sample
    /// where the filter reads pixels that straddle the sample's edge
    /// ([`BicubicFilter::straddling`]); `None`: every used pixel is read as
    /// it is. In 64ths of the square (what 8 × 8 points of it tell; 64: all).
    shares: Option<[u8; 16]>,
}

impl BicubicFilter {
    /// The plain filter at (x, y) of `dims` frames, edges clamped.
    pub fn new(dims: [usize; 2], x: f64, y: f64) -> Self {
        BicubicFilter::over(dims, x, y, |_, _| true)
    }

    /// The filter's taps whose pixel centres `usable` accepts, not
    /// renormalised.
    fn over(dims: [usize; 2], x: f64, y: f64, usable: impl Fn(f64, f64) -> bool) -> Self {
        let (fx, fy) = (x - 0.5, y - 0.5);
        let (x0, y0) = (fx.floor(), fy.floor());
        let wx = super::plane::catmull_rom(fx - x0);
        let wy = super::plane::catmull_rom(fy - y0);
        let (x0, y0) = (x0 as isize, y0 as isize);
        let mut taps = 0u16;
        for j in 0..4 {
            for i in 0..4 {
                let (tx, ty) = (x0 + i as isize - 1, y0 + j as isize - 1);
                if usable(tx as f64 + 0.5, ty as f64 + 0.5) {
                    taps |= 1 << (4 * j + i);
                }
            }
        }
        BicubicFilter { dims, corner: [x0 - 1, y0 - 1], wx, wy, taps, norm: None, shares: None }
    }

    /// The used taps' weight.
    fn used_weight(&self) -> f64 {
        let mut sum = 0.0;
        for (j, wyj) in self.wy.iter().enumerate() {
            for (i, wxi) in self.wx.iter().enumerate() {
                if self.taps & (1 << (4 * j + i)) != 0 {
                    sum += wyj * wxi;
                }
            }
        }
        sum
    }

    /// The filter over only the taps whose pixel centres `usable` accepts,
    /// the weights renormalised over them; `None` when those carry less
    /// than `min_weight` of the filter (the rest would be extrapolation).
    pub fn masked(
        dims: [usize; 2],
        x: f64,
        y: f64,
        usable: impl Fn(f64, f64) -> bool,
        min_weight: f64,
    ) -> Option<Self> {
        let b = BicubicFilter::over(dims, x, y, usable);
        let sum = b.used_weight();
        (sum >= min_weight).then_some(BicubicFilter { norm: Some(sum), ..b })
    }

    /// The filter over the pixels of which at least `min_share` of the
    /// square lies on the sample (`share` of a pixel centre), each read as
    /// the sample's part of it: a pixel holding the sample in share s and
    /// the holder (radiance H) in the rest reads (value − (1 − s) H) / s
    /// ([`BicubicFilter::apply_beside`]). The weights are renormalised
    /// over those pixels; `None` when they carry less than `min_weight`.
    pub fn straddling(
        dims: [usize; 2],
        x: f64,
        y: f64,
        share: impl Fn(f64, f64) -> f64,
        min_share: f64,
        min_weight: f64,
    ) -> Option<Self> {
        let mut b = BicubicFilter::new(dims, x, y);
        let mut shares = [0u8; 16];
        for (t, s) in shares.iter_mut().enumerate() {
            let (px, py) = (b.corner[0] + (t % 4) as isize, b.corner[1] + (t / 4) as isize);
            let v = share(px as f64 + 0.5, py as f64 + 0.5);
            if v >= min_share {
                *s = (v.min(1.0) * 64.0).round() as u8;
            } else {
                b.taps &= !(1 << t);
            }
        }
        let sum = b.used_weight();
        b.norm = Some(sum);
        b.shares = Some(shares);
        (sum >= min_weight).then_some(b)
    }

    /// How the filter scales the variance of independent frame pixels:
    /// Σ (w / s)² over its used taps (w renormalised, s the share a
    /// straddling pixel is divided by).
    pub fn noise_gain(&self) -> f64 {
        let norm = self.norm.unwrap_or(1.0);
        let mut sum = 0.0;
        for (j, wyj) in self.wy.iter().enumerate() {
            for (i, wxi) in self.wx.iter().enumerate() {
                let t = 4 * j + i;
                if self.taps & (1 << t) != 0 {
                    let s = self.shares.map_or(1.0, |s| s[t] as f64 / 64.0);
                    sum += (wyj * wxi / norm / s).powi(2);
                }
            }
        }
        sum
    }

    /// Whether the filter reads pixels that straddle the sample's edge
    /// (and so needs the holder's radiance, [`BicubicFilter::apply_beside`]).
    pub fn straddles(&self) -> bool {
        self.shares.is_some()
    }

    /// The filter's sum over `f` (a frame of its size); a filter over
    /// pixels that straddle the sample's edge takes the holder as black.
    #[inline]
    pub fn apply(&self, f: &Frame) -> [f64; 3] {
        self.apply_beside(f, [0.0; 3])
    }

    /// The filter's sum over `f` (a frame of its size), the pixels that
    /// straddle the sample's edge read without the share of `holder` (the
    /// radiance of what surrounds the sample there) they hold.
    #[inline]
    pub fn apply_beside(&self, f: &Frame, holder: [f64; 3]) -> [f64; 3] {
        debug_assert_eq!(frame_dims(f), self.dims);
        let (w, h) = (self.dims[0] as isize, self.dims[1] as isize);
        let mut out = [0.0; 3];
        for (j, wyj) in self.wy.iter().enumerate() {
            let yy = (self.corner[1] + j as isize).clamp(0, h - 1);
            for (i, wxi) in self.wx.iter().enumerate() {
                if self.taps & (1 << (4 * j + i)) == 0 {
                    continue;
                }
                let xx = (self.corner[0] + i as isize).clamp(0, w - 1);
                let k = 3 * (yy * w + xx) as usize;
                let wgt = wyj * wxi;
                match self.shares {
                    Some(s) if s[4 * j + i] < 64 => {
                        let s = s[4 * j + i] as f64 / 64.0;
                        for c in 0..3 {
                            out[c] += wgt * (f.rgb[k + c] as f64 - (1.0 - s) * holder[c]) / s;
                        }
                    }
                    _ => {
                        out[0] += wgt * f.rgb[k] as f64;
                        out[1] += wgt * f.rgb[k + 1] as f64;
                        out[2] += wgt * f.rgb[k + 2] as f64;
                    }
                }
            }
        }
        match self.norm {
            Some(w) => out.map(|v| v / w),
            None => out,
        }
    }
}
