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

    /// Frames of the trigger pulses completed since the last call, with the
    /// pulse's index in `truth.triggers`; an ignored trigger makes no frame.
    pub fn collect(&mut self, truth: &Truth) -> Vec<(usize, Frame)> {
        let mut out = Vec::new();
        while let Some(record) = truth.triggers.get(self.next) {
            if record.fall.is_none() {
                break;
            }
            if let Some(e) = exposure_of(record) {
                out.push((self.next, self.optics.render(&e)));
            }
            self.next += 1;
        }
        out
    }
}
