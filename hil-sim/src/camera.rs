//! The simulated camera: at every honoured trigger pulse it renders the frame
//! of the physical axis positions (not the commanded ones), the pulse's
//! length as exposure and the light's duty.

use firmware::config;
use firmware::hal::TICK_HZ;

use crate::device::{TriggerRecord, Truth};
use crate::geometry::AxisValues;
use crate::optics::{Exposure, Frame, OpticalSim};

/// Physical axis values of motor positions (steps from the home/index
/// switch edges; the geometry's zero offsets apply in its kinematics).
pub fn axis_values(steps: [i64; 3]) -> AxisValues {
    AxisValues::from_steps(steps, &default_axes())
}

/// The simulated mechanics' axis configurations (the firmware defaults).
pub fn default_axes() -> [protocol::AxisConfig; 3] {
    [config::disk_default(), config::track_default(), config::tilt_default()]
}

/// The exposure a finished, honoured trigger pulse made (None otherwise).
pub fn exposure_of(record: &TriggerRecord) -> Option<Exposure> {
    let fall = record.fall?;
    if !record.honoured {
        return None;
    }
    Some(Exposure {
        axes: axis_values(record.positions),
        exposure_s: (fall - record.rise) as f64 / TICK_HZ as f64,
        light: record.light_duty as f64 / 1000.0,
    })
}

/// A camera wired to the simulated board's trigger output.
#[derive(Debug, Clone)]
pub struct SimCamera {
    optics: OpticalSim,
    next: usize,
}

impl SimCamera {
    /// A camera seeing through `optics`.
    pub fn new(optics: OpticalSim) -> SimCamera {
        SimCamera { optics, next: 0 }
    }

    /// The optics (ground truth).
    pub fn optics(&self) -> &OpticalSim {
        &self.optics
    }

    /// Trigger pulses seen so far.
    pub fn pulses_seen(&self) -> usize {
        self.next
    }

    /// Exposures of the trigger pulses completed since the last call, with
    /// the pulse's index in `truth.triggers`; an ignored trigger makes none.
    pub fn take_exposures(&mut self, truth: &Truth) -> Vec<(usize, Exposure)> {
        let mut out = Vec::new();
        while let Some(record) = truth.triggers.get(self.next) {
            if record.fall.is_none() {
                break;
            }
            if let Some(e) = exposure_of(record) {
                out.push((self.next, e));
            }
            self.next += 1;
        }
        out
    }

    /// Frames of the trigger pulses completed since the last call (see
    /// [`SimCamera::take_exposures`]).
    pub fn collect(&mut self, truth: &Truth) -> Vec<(usize, Frame)> {
        self.take_exposures(truth).into_iter().map(|(i, e)| (i, self.optics.render(&e))).collect()
    }
}

/// Write `frame` to `path` as OpenEXR (32-bit float RGB), atomically: a
/// temporary file in the same folder, then a rename — a folder watcher
/// never sees a partial frame.
pub fn write_frame_exr(frame: &Frame, path: &std::path::Path) -> std::io::Result<()> {
    let dir = path.parent().unwrap_or(std::path::Path::new("."));
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("frame.exr");
    let tmp = dir.join(format!(".{name}.tmp"));
    let img = image::Rgb32FImage::from_raw(frame.width, frame.height, frame.rgb.clone())
        .ok_or_else(|| std::io::Error::other("frame size mismatch"))?;
    img.save_with_format(&tmp, image::ImageFormat::OpenExr).map_err(std::io::Error::other)?;
    std::fs::rename(&tmp, path)
}
