//! Cameras: armed for the device's hardware trigger, then asked for the
//! frame. The simulated camera comes with the in-process simulator; the
//! folder source takes the frames a real camera's own capture program drops
//! into a folder, matched to triggers in order, until a native driver exists.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// A linear float RGB frame, row-major, interleaved.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Width, px.
    pub width: u32,
    /// Height, px.
    pub height: u32,
    /// `width × height × 3` values.
    pub rgb: Vec<f32>,
}

/// Why a camera failed.
#[derive(Debug, thiserror::Error)]
pub enum CameraError {
    /// No frame arrived in time.
    #[error("camera: no frame within {0:?}")]
    Timeout(Duration),
    /// The camera's exposure strobe did not rise: it missed its trigger
    /// (no frame will come).
    #[error("camera: missed its trigger (its exposure strobe did not rise)")]
    Missed,
    /// The camera's output could not be read.
    #[error("camera: {0}")]
    Io(String),
    /// A frame arrived that is not one of the scan's (its size, its
    /// values): taking it again would not help.
    #[error("camera: {0}")]
    Unusable(String),
}

/// A camera on the scanner's trigger line.
pub trait Camera: Send {
    /// Get ready for the next trigger; frames from before are stale.
    fn arm(&mut self) -> Result<(), CameraError>;
    /// The device reported the trigger's rising edge: nothing that arrived
    /// before it can be its frame.
    fn triggered(&mut self) {}
    /// An earlier trigger's frame may still arrive (its host was killed):
    /// wait up to `max` for it and set it aside, so it is not taken for the
    /// next trigger's frame.
    fn drain(&mut self, _max: Duration) {}
    /// The frame of the trigger that fired, waiting up to `timeout`.
    fn wait_frame(&mut self, timeout: Duration) -> Result<Frame, CameraError>;
    /// What this is, for messages and manifests.
    fn describe(&self) -> String;
    /// How its integer frame files hold the sensor's codes (recorded in the
    /// scan's settings, so that a resume reads them the same way).
    fn integer_codes(&self) -> scanner_geometry::IntegerCodes {
        scanner_geometry::IntegerCodes::Native
    }
}

/// The scan's view of a camera: every frame checked against the sensor the
/// geometry describes (its size; values within full scale, as
/// docs/scan-format.md defines them) and, for a camera whose capture
/// program leaves a black level of `codes` ADC codes in, that level
/// subtracted from every value below the top code (at 0 at least; the top
/// code stays, as saturated).
pub struct ScanCamera<'a> {
    inner: &'a mut dyn Camera,
    width: u32,
    height: u32,
    /// The black level, as a fraction of full scale.
    offset: f32,
    max_code: f32,
}

impl std::fmt::Debug for ScanCamera<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ScanCamera")
            .field("camera", &self.inner.describe())
            .field("size", &(self.width, self.height))
            .field("black_level_codes", &(self.offset * self.max_code))
            .finish()
    }
}

impl<'a> ScanCamera<'a> {
    /// `inner`'s frames, checked against the camera `geometry` describes
    /// (no black level subtracted until [`ScanCamera::set_black_level`]).
    pub fn new(
        inner: &'a mut dyn Camera,
        geometry: &scanner_geometry::ScannerGeometry,
    ) -> ScanCamera<'a> {
        ScanCamera {
            inner,
            width: geometry.camera.width,
            height: geometry.camera.height,
            offset: 0.0,
            max_code: geometry.sensor.max_code() as f32,
        }
    }

    /// Subtract a black level of `codes` from now on.
    pub fn set_black_level(&mut self, codes: u32) {
        self.offset = (codes as f64 / self.max_code as f64) as f32;
    }
}

/// What is wrong with a frame of `w`×`h` px for a camera of `[width,
/// height]` px.
pub fn wrong_size(w: usize, h: usize, [width, height]: [u32; 2]) -> String {
    format!(
        "a frame of {w}×{h} px; the geometry's camera has {width}×{height} px (set the \
         camera's resolution and binning, or scan with its geometry)"
    )
}

/// Why a frame is not one of the scan's: another size than the sensor's,
/// or values beyond full scale (a capture program that writes ADC codes or
/// another unit, not code / top code) or not numbers.
pub fn check_frame(frame: &Frame, width: u32, height: u32) -> Result<(), CameraError> {
    if (frame.width, frame.height) != (width, height)
        || frame.rgb.len() != width as usize * height as usize * 3
    {
        let (w, h) = (frame.width as usize, frame.height as usize);
        return Err(CameraError::Unusable(wrong_size(w, h, [width, height])));
    }
    // Half float holds the top code's 1.0 exactly; allow a rounding's worth.
    const FULL_SCALE: f32 = 1.0 + 1e-3;
    use rayon::prelude::*;
    // Counted without branches, so that the pass over a frame vectorises:
    // values whose exponent is all ones (NaN, ±∞), and values above full
    // scale (+∞ among them: said as not a number first).
    const EXPONENT: u32 = 0x7f80_0000;
    let (above, not_numbers) = frame
        .rgb
        .par_chunks(1 << 16)
        .map(|values| {
            values.iter().fold((0usize, 0usize), |(above, not_numbers), &v| {
                (
                    above + usize::from(v > FULL_SCALE),
                    not_numbers + usize::from(v.to_bits() & EXPONENT == EXPONENT),
                )
            })
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    if not_numbers > 0 {
        return Err(CameraError::Unusable(format!(
            "{not_numbers} values are not numbers (NaN or infinite)"
        )));
    }
    if above > 0 {
        let largest = frame.rgb.par_iter().copied().reduce(|| 0.0, f32::max);
        return Err(CameraError::Unusable(format!(
            "{above} values above full scale, up to {largest}: frames hold code / top code \
             (1.0 at the top code, docs/scan-format.md), not ADC codes or another unit"
        )));
    }
    Ok(())
}

/// Subtract `offset` (a fraction of full scale) from every value of
/// `frame` below the top code `max_code` (at 0 at least); values at the top
/// code (saturated) are left as they are.
pub fn subtract_black_level(frame: &mut Frame, offset: f32, max_code: f32) {
    if offset <= 0.0 {
        return;
    }
    use rayon::prelude::*;
    let top = max_code as usize;
    frame.rgb.par_chunks_mut(1 << 16).for_each(|values| {
        for v in values {
            if crate::hdr::adc_code(*v, max_code, top) < top {
                *v = (*v - offset).max(0.0);
            }
        }
    });
}

impl Camera for ScanCamera<'_> {
    fn arm(&mut self) -> Result<(), CameraError> {
        self.inner.arm()
    }

    fn triggered(&mut self) {
        self.inner.triggered()
    }

    fn drain(&mut self, max: Duration) {
        self.inner.drain(max)
    }

    fn wait_frame(&mut self, timeout: Duration) -> Result<Frame, CameraError> {
        let mut frame = self.inner.wait_frame(timeout)?;
        check_frame(&frame, self.width, self.height)?;
        subtract_black_level(&mut frame, self.offset, self.max_code);
        Ok(frame)
    }

    fn describe(&self) -> String {
        self.inner.describe()
    }
}

/// The simulator's camera (in-process; frames rendered when the trigger
/// pulse ends; time is the simulator's).
#[cfg(feature = "sim")]
#[derive(Debug, Clone)]
pub struct SimCamera(pub hil_sim::SimRig);

#[cfg(feature = "sim")]
impl Camera for SimCamera {
    fn arm(&mut self) -> Result<(), CameraError> {
        self.0.arm_camera();
        Ok(())
    }

    fn wait_frame(&mut self, timeout: Duration) -> Result<Frame, CameraError> {
        let f = self.0.wait_frame(timeout).ok_or(CameraError::Timeout(timeout))?;
        Ok(Frame { width: f.width, height: f.height, rgb: f.rgb })
    }

    fn describe(&self) -> String {
        "simulated camera".into()
    }
}

/// Frames from a folder another program writes into, matched to triggers by
/// order and time: the first new frame file (in name order: `.exr`, `.png`,
/// `.tif`, `.tiff`; [`crate::frame_file`]) that appears after the device
/// reported the trigger's rising edge is its frame (files landing between
/// arming and the trigger belong to earlier pulses). Hidden files (`.name`)
/// and `*.tmp` are in-progress writes and ignored; a file that does not
/// decode yet is read again until it does. Integer images hold the sensor's
/// codes as `codes` says.
#[derive(Debug)]
pub struct FolderCamera {
    dir: PathBuf,
    seen: BTreeSet<String>,
    sensor: scanner_geometry::SensorSpec,
    codes: scanner_geometry::IntegerCodes,
    /// The camera's frame size, `[width, height]` px.
    size: [u32; 2],
    /// Poll period.
    pub poll: Duration,
}

impl FolderCamera {
    /// Watch `dir` (it must exist) for frames of `size` (`[width, height]`
    /// px) from `sensor`, integer images holding its codes as `codes` says;
    /// a file of another size is refused from its header.
    pub fn new(
        dir: &Path,
        sensor: &scanner_geometry::SensorSpec,
        codes: scanner_geometry::IntegerCodes,
        size: [u32; 2],
    ) -> Result<FolderCamera, CameraError> {
        if !dir.is_dir() {
            return Err(CameraError::Io(format!("{} is not a folder", dir.display())));
        }
        let mut c = FolderCamera {
            dir: dir.to_path_buf(),
            seen: BTreeSet::new(),
            sensor: sensor.clone(),
            codes,
            size,
            poll: Duration::from_millis(20),
        };
        c.seen = c.list()?;
        Ok(c)
    }

    fn list(&self) -> Result<BTreeSet<String>, CameraError> {
        let rd = std::fs::read_dir(&self.dir)
            .map_err(|e| CameraError::Io(format!("{}: {e}", self.dir.display())))?;
        Ok(rd
            .filter_map(|e| e.ok())
            .filter_map(|e| e.file_name().into_string().ok())
            .filter(|n| {
                !n.starts_with('.') && !n.ends_with(".tmp") && crate::frame_file::is_frame_file(n)
            })
            .collect())
    }
}

impl Camera for FolderCamera {
    fn arm(&mut self) -> Result<(), CameraError> {
        self.seen = self.list()?;
        Ok(())
    }

    fn triggered(&mut self) {
        // Frames of earlier pulses (a step cut short by a previous host,
        // a retake) may still be landing; the exposure has only begun.
        if let Ok(names) = self.list() {
            self.seen.extend(names);
        }
    }

    fn drain(&mut self, max: Duration) {
        let end = Instant::now() + max;
        while Instant::now() < end {
            match self.list() {
                Ok(names) if names.difference(&self.seen).next().is_some() => {
                    self.seen.extend(names);
                    return;
                }
                Ok(_) => std::thread::sleep(self.poll),
                Err(_) => return,
            }
        }
    }

    fn wait_frame(&mut self, timeout: Duration) -> Result<Frame, CameraError> {
        let end = Instant::now() + timeout;
        let mut last_error = None;
        loop {
            let names = self.list()?;
            if let Some(name) = names.difference(&self.seen).next().cloned() {
                use crate::frame_file::{FrameFileError, read_frame_file};
                let path = self.dir.join(&name);
                match read_frame_file(&path, &self.sensor, self.codes, Some(self.size)) {
                    Ok(f) => {
                        self.seen.insert(name);
                        return Ok(f);
                    }
                    // Perhaps still being written: try again.
                    Err(FrameFileError::Decode(e)) => last_error = Some(e),
                    Err(FrameFileError::Unusable(e)) => {
                        self.seen.insert(name);
                        return Err(CameraError::Unusable(e));
                    }
                }
            }
            if Instant::now() >= end {
                return Err(match last_error {
                    Some(e) => CameraError::Io(e),
                    None => CameraError::Timeout(timeout),
                });
            }
            std::thread::sleep(self.poll);
        }
    }

    fn describe(&self) -> String {
        format!("folder {}", self.dir.display())
    }

    fn integer_codes(&self) -> scanner_geometry::IntegerCodes {
        self.codes
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_black_level_is_subtracted_below_the_top_code_only() {
        let max = 4095.0f32;
        let code = |c: f32| c / max;
        let mut f = Frame {
            width: 2,
            height: 2,
            rgb: vec![
                code(64.0),
                code(60.0),
                code(1064.0),
                code(4095.0),
                code(4094.0),
                f32::NAN,
                code(0.0),
                code(64.5),
                code(100.0),
                code(3000.0),
                code(70.0),
                code(64.0),
            ],
        };
        subtract_black_level(&mut f, code(64.0), max);
        let codes: Vec<f32> = f.rgb.iter().map(|v| (v * max * 100.0).round() / 100.0).collect();
        // Noise below the level clips at 0, like a camera without one; the
        // top code stays saturated; NaN becomes 0.
        assert_eq!(
            codes,
            [0.0, 0.0, 1000.0, 4095.0, 4030.0, 0.0, 0.0, 0.5, 36.0, 2936.0, 6.0, 0.0]
        );
    }

    #[test]
    fn frames_of_another_size_or_unit_are_unusable() {
        let frame = |w: u32, h: u32, v: f32| Frame {
            width: w,
            height: h,
            rgb: vec![v; (w * h * 3) as usize],
        };
        assert!(check_frame(&frame(4, 2, 0.5), 4, 2).is_ok());
        assert!(check_frame(&frame(4, 2, 1.0), 4, 2).is_ok(), "the top code");
        assert!(check_frame(&frame(4, 2, -0.01), 4, 2).is_ok(), "noise below a subtracted level");
        let e = check_frame(&frame(2, 4, 0.5), 4, 2).unwrap_err().to_string();
        assert!(e.contains("a frame of 2×4 px; the geometry's camera has 4×2 px"), "{e}");
        let mut short = frame(4, 2, 0.5);
        short.rgb.pop();
        assert!(check_frame(&short, 4, 2).is_err());
        // A capture program that writes ADC codes.
        let mut codes = frame(4, 2, 0.5);
        codes.rgb[5] = 4095.0;
        let e = check_frame(&codes, 4, 2).unwrap_err().to_string();
        assert!(e.contains("1 values above full scale, up to 4095"), "{e}");
        let mut nan = frame(4, 2, 0.5);
        nan.rgb[0] = f32::NAN;
        nan.rgb[1] = f32::INFINITY;
        nan.rgb[2] = 4095.0;
        let e = check_frame(&nan, 4, 2).unwrap_err().to_string();
        assert!(e.contains("2 values are not numbers"), "{e}");
        // Over several of the pass's chunks: every kind counted, the largest
        // found wherever it is.
        let mut big = frame(256, 256, 0.25);
        let n = big.rgb.len();
        for (i, v) in [(1, 2.0), (70_000, 9.5), (n - 1, 3.0), (131_072, 1.0 + 2e-3)] {
            big.rgb[i] = v;
        }
        let e = check_frame(&big, 256, 256).unwrap_err().to_string();
        assert!(e.contains("4 values above full scale, up to 9.5:"), "{e}");
        for (i, v) in [(0, f32::NAN), (65_535, f32::NEG_INFINITY), (65_536, -f32::NAN)] {
            big.rgb[i] = v;
        }
        big.rgb[n - 2] = f32::INFINITY;
        let e = check_frame(&big, 256, 256).unwrap_err().to_string();
        assert!(e.contains("4 values are not numbers"), "{e}");
    }
}
