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
    /// The camera's output could not be read.
    #[error("camera: {0}")]
    Io(String),
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
/// order and time: the first new `.exr` file (in name order) that appears
/// after the device reported the trigger's rising edge is its frame (files
/// landing between arming and the trigger belong to earlier pulses). Hidden
/// files (`.name`) and `*.tmp` are in-progress writes and ignored; a file
/// that does not decode yet is read again until it does.
#[derive(Debug)]
pub struct FolderCamera {
    dir: PathBuf,
    seen: BTreeSet<String>,
    /// Poll period.
    pub poll: Duration,
}

impl FolderCamera {
    /// Watch `dir` (it must exist).
    pub fn new(dir: &Path) -> Result<FolderCamera, CameraError> {
        if !dir.is_dir() {
            return Err(CameraError::Io(format!("{} is not a folder", dir.display())));
        }
        let mut c = FolderCamera {
            dir: dir.to_path_buf(),
            seen: BTreeSet::new(),
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
                !n.starts_with('.')
                    && !n.ends_with(".tmp")
                    && n.to_ascii_lowercase().ends_with(".exr")
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
                match crate::exrio::read_rgb(&self.dir.join(&name)) {
                    Ok(f) => {
                        self.seen.insert(name);
                        return Ok(f);
                    }
                    // Perhaps still being written: try again.
                    Err(e) => last_error = Some(format!("{name}: {e}")),
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
}
