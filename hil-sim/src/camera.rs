//! The simulated camera: at every honoured trigger pulse it renders the frame
//! of the physical axis positions (not the commanded ones), the pulse's
//! length as exposure and the light's duty.

use firmware::hal::{TICK_HZ, TICKS_PER_US};

use crate::device::{TriggerRecord, Truth};
use crate::geometry::AxisValues;
use crate::optics::{Exposure, Frame, OpticalSim};
use scanner_geometry::{IntegerCodes, SensorSpec};

/// Physical axis values of motor positions (steps from the home/index
/// switch edges; the geometry's zero offsets apply in its kinematics) on a
/// scanner built with the drives `axes` describes.
pub fn axis_values(steps: [i64; 3], axes: &[protocol::AxisConfig; 3]) -> AxisValues {
    AxisValues::from_steps(steps, axes)
}

/// The exposure a finished, honoured trigger pulse made (None otherwise)
/// on a camera that exposes for the pulse's length (trigger-width mode),
/// `latency` ticks after its edges: the light it collects is the light's
/// output ([`light_output`] of the duty `light` logged as (tick, ‰)
/// changes) over that window, as a mean over it. With no latency and the
/// light steady through the pulse, the light at the pulse's duty.
pub fn exposure_of(
    record: &TriggerRecord,
    light: &[(u64, u16)],
    latency: u64,
    axes: &[protocol::AxisConfig; 3],
) -> Option<Exposure> {
    let fall = record.fall?;
    if !record.honoured {
        return None;
    }
    let (start, end) = record.exposure_window(latency);
    let end = end?;
    let output = |duty: u16| light_output(duty, record.light_edge_loss_ns);
    // The duty in force at the start (the last change at or before it),
    // and the changes within the window.
    let k = light.partition_point(|&(tick, _)| tick <= start);
    let mut duty = if k == 0 { 0 } else { light[k - 1].1 };
    let changes = &light[k..];
    let changes = &changes[..changes.partition_point(|&(tick, _)| tick < end)];
    let mean = if changes.is_empty() {
        output(duty)
    } else {
        let mut sum = 0.0;
        let mut t = start;
        for &(tick, next) in changes {
            sum += output(duty) * (tick - t) as f64;
            (t, duty) = (tick, next);
        }
        (sum + output(duty) * (end - t) as f64) / (end - start) as f64
    };
    Some(Exposure {
        axes: axis_values(record.positions, axes),
        exposure_s: (fall - record.rise) as f64 / TICK_HZ as f64,
        light: mean,
    })
}

/// The light's output at `duty` ‰, relative to full light, from a driver
/// that loses `edge_loss_ns` of light at every pulse of the board's
/// [`protocol::LIGHT_PWM_HZ`] PWM (0: an ideal driver, output = duty). At
/// full duty the light is on without edges.
pub fn light_output(duty: u16, edge_loss_ns: u32) -> f64 {
    if duty >= protocol::FULL_DUTY_PERMILLE {
        return 1.0;
    }
    let period_ns = 1e9 / protocol::LIGHT_PWM_HZ as f64;
    let on_ns = duty as f64 / protocol::FULL_DUTY_PERMILLE as f64 * period_ns;
    (on_ns - edge_loss_ns as f64).max(0.0) / period_ns
}

/// A camera wired to the simulated board's trigger output.
#[derive(Debug, Clone)]
pub struct SimCamera {
    optics: OpticalSim,
    next: usize,
    /// Trigger latency, ticks.
    latency: u64,
    /// The drives the scanner is built with.
    axes: [protocol::AxisConfig; 3],
}

impl SimCamera {
    /// A camera seeing through `optics`, exposing exactly while its trigger
    /// is high.
    pub fn new(optics: OpticalSim) -> SimCamera {
        SimCamera { optics, next: 0, latency: 0, axes: protocol::default_axes() }
    }

    /// The same camera on a scanner built with the drives `axes` describes
    /// (`SimConfig::axes`): its frames see the physical step positions
    /// through them.
    pub fn with_axes(mut self, axes: [protocol::AxisConfig; 3]) -> SimCamera {
        self.axes = axes;
        self
    }

    /// The same camera exposing `us` µs after each edge of its trigger
    /// pulse (an opto-isolated input's delay, a trigger debounce): it
    /// still exposes for the pulse's length, but later than the board's
    /// light, which follows the pulse.
    pub fn with_trigger_latency(mut self, us: u32) -> SimCamera {
        self.latency = us as u64 * TICKS_PER_US;
        self
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
            // Its exposure is over, and the light's record with it.
            if record.fall.is_none_or(|fall| truth.now < fall + self.latency) {
                break;
            }
            if let Some(e) = exposure_of(record, &truth.light, self.latency, &self.axes) {
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

/// Encode `frame` as OpenEXR (32-bit float RGB).
fn encode_exr(frame: &Frame) -> std::io::Result<Vec<u8>> {
    let img = image::Rgb32FImage::from_raw(frame.width, frame.height, frame.rgb.clone())
        .ok_or_else(|| std::io::Error::other("frame size mismatch"))?;
    let mut bytes = std::io::Cursor::new(Vec::new());
    img.write_to(&mut bytes, image::ImageFormat::OpenExr).map_err(std::io::Error::other)?;
    Ok(bytes.into_inner())
}

/// Write `frame` to `path` as OpenEXR (32-bit float RGB), durably and
/// atomically (`scanner_formats::atomic::write_atomic`: a temporary file in
/// the same folder, fsync, rename, fsync of the folder). A device node, a
/// symlink or a directory at `path` is refused, not replaced. Every error's
/// message names `path`.
pub fn write_frame_exr(frame: &Frame, path: &std::path::Path) -> std::io::Result<()> {
    scanner_formats::atomic::check_output(path, &[])?;
    encode_exr(frame)
        .and_then(|bytes| scanner_formats::atomic::write_atomic(path, &bytes))
        .map_err(|e| std::io::Error::new(e.kind(), format!("{}: {e}", path.display())))
}

/// The files a camera's capture program writes its frames as.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FrameFiles {
    /// OpenEXR, 32-bit float RGB, in the frames' unit (code / top code).
    #[default]
    Exr,
    /// 16-bit RGB PNG of the sensor's codes, stored as `IntegerCodes` says.
    Png(IntegerCodes),
    /// 16-bit RGB TIFF (uncompressed) of the codes, likewise.
    Tiff(IntegerCodes),
}

impl FrameFiles {
    /// The files' extension.
    pub fn extension(self) -> &'static str {
        match self {
            FrameFiles::Exr => "exr",
            FrameFiles::Png(_) => "png",
            FrameFiles::Tiff(_) => "tiff",
        }
    }

    /// `frame` of a `sensor` encoded as such a file.
    pub fn encode(self, frame: &Frame, sensor: &SensorSpec) -> std::io::Result<Vec<u8>> {
        let (format, codes) = match self {
            FrameFiles::Exr => return encode_exr(frame),
            FrameFiles::Png(codes) => (image::ImageFormat::Png, codes),
            FrameFiles::Tiff(codes) => (image::ImageFormat::Tiff, codes),
        };
        let full = sensor.integer_full_scale(codes, 16).ok_or_else(|| {
            std::io::Error::other(format!(
                "a {}-bit sensor's codes need more than 16 bits",
                sensor.bits
            ))
        })? as f64;
        let values = frame.rgb.iter().map(|&v| (v as f64 * full).round().clamp(0.0, full) as u16);
        let img = image::ImageBuffer::<image::Rgb<u16>, _>::from_raw(
            frame.width,
            frame.height,
            values.collect::<Vec<u16>>(),
        )
        .ok_or_else(|| std::io::Error::other("frame size mismatch"))?;
        let mut bytes = std::io::Cursor::new(Vec::new());
        img.write_to(&mut bytes, format).map_err(std::io::Error::other)?;
        Ok(bytes.into_inner())
    }
}

/// Drop `frame` into a camera's spool folder as `path`, encoded as `files`
/// says: a uniquely named temporary file in the same folder, then a rename,
/// so that a folder watcher never sees a partial frame — as a camera's
/// capture program writes. Not fsynced: after a crash the host retakes a
/// lost frame.
pub fn drop_frame(
    frame: &Frame,
    sensor: &SensorSpec,
    files: FrameFiles,
    path: &std::path::Path,
) -> std::io::Result<()> {
    let dir = path.parent().unwrap_or(std::path::Path::new("."));
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("frame");
    let tmp = dir.join(format!(".{name}.{}.tmp", std::process::id()));
    let bytes = files.encode(frame, sensor)?;
    std::fs::write(&tmp, bytes).and_then(|()| std::fs::rename(&tmp, path)).inspect_err(|_| {
        let _ = std::fs::remove_file(&tmp);
    })
}
