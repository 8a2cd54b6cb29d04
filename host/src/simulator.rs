//! The simulated scanner as the host uses it: in-process and deterministic
//! (`--device sim`), or served on a pty for interactive use (`scanner sim`).
//! The host hands the simulator a material name, a seed and a sensor
//! binning; it never reads the simulator's ground truth.

use std::path::PathBuf;

use hil_sim::geometry::ScannerGeometry;
use hil_sim::materials::{self, Sample};
use hil_sim::optics::OpticalSim;
use hil_sim::{FaultPlan, SimConfig, SimRig};

/// What to simulate.
#[derive(Debug, Clone)]
pub struct SimSetup {
    /// Sample material ([`materials::MATERIAL_NAMES`]).
    pub material: String,
    /// Seed of the as-built scanner, the board and the sensor noise.
    pub seed: u64,
    /// Sensor binning (1 = the default 4096² sensor).
    pub bin: u32,
    /// Faults to inject.
    pub faults: FaultPlan,
}

impl SimSetup {
    /// `material` with seed 1, full resolution, no faults.
    pub fn new(material: &str) -> SimSetup {
        SimSetup { material: material.into(), seed: 1, bin: 1, faults: FaultPlan::none() }
    }

    /// The nominal geometry of the simulated scanner (what the host gets).
    pub fn nominal(&self) -> Result<ScannerGeometry, String> {
        if self.bin == 0 || self.bin > 64 {
            return Err(format!("sensor binning {} outside 1…64", self.bin));
        }
        Ok(ScannerGeometry::default_scanner().with_sensor_scaled(self.bin))
    }

    fn optics(&self) -> Result<OpticalSim, String> {
        let material = materials::lookup(&self.material)?;
        Ok(OpticalSim::as_built(&self.nominal()?, Sample::small(material), self.seed))
    }

    fn config(&self) -> SimConfig {
        let mut c = SimConfig::new(self.seed);
        c.faults = self.faults.clone();
        c
    }

    /// Board and camera in this process (deterministic).
    pub fn rig(&self) -> Result<SimRig, String> {
        Ok(SimRig::new(self.config(), self.optics()?))
    }

    /// Serve the board on a pty (time running at `speed` × real time), the
    /// camera dropping frames into `frames`.
    pub fn serve(&self, speed: f64, frames: PathBuf) -> Result<hil_sim::PtyServer, String> {
        let camera = hil_sim::camera::SimCamera::new(self.optics()?);
        hil_sim::PtyServer::start_with_camera(
            hil_sim::SimDevice::new(self.config()),
            speed,
            Some((camera, frames)),
        )
        .map_err(|e| format!("cannot serve the simulator on a pty: {e}"))
    }
}
