//! The simulated scanner as the host uses it: in-process and deterministic
//! (`--device sim`), or served on a pty for interactive use (`scanner sim`).
//! The host hands the simulator a material name, a seed and a sensor
//! binning; it never reads the simulator's ground truth.

use std::path::PathBuf;

use hil_sim::defects::DefectSpec;
use hil_sim::geometry::{SampleFace, ScannerGeometry};
use hil_sim::materials::{self, MaterialError, Sample};
use hil_sim::optics::OpticalSim;
use hil_sim::{FaultPlan, SimConfig, SimRig};

/// Why the simulator cannot be set up.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// A setting out of its range (a usage error).
    #[error("{0}")]
    Usage(String),
    /// The sample material: an unknown name, or a bad texture set.
    #[error(transparent)]
    Material(#[from] MaterialError),
    /// The pty could not be served.
    #[error("cannot serve the simulator on a pty: {0}")]
    Serve(String),
}

impl SimError {
    /// Process exit code: 2 usage (unknown name, bad setting), 3 a bad
    /// texture-set file, 1 otherwise.
    pub fn exit_code(&self) -> u8 {
        match self {
            SimError::Usage(_) | SimError::Material(MaterialError::Unknown(_)) => 2,
            SimError::Material(MaterialError::TextureSet(_)) => 3,
            SimError::Serve(_) => 1,
        }
    }
}

/// The largest sample height the simulator takes, mm: beyond it the
/// holder would hide the sample's sides from the outer views.
pub const MAX_SAMPLE_HEIGHT_MM: f64 = 5.0;

/// The largest tilt of the sample's face the simulator takes about either
/// of its axes, degrees (a sample that does not lie flat; more would lift
/// its corners past [`MAX_SAMPLE_HEIGHT_MM`]).
pub const MAX_SAMPLE_TILT_DEG: f64 = 10.0;

/// The thickest sample the simulator takes, mm (its sides below the face).
pub const MAX_SAMPLE_THICKNESS_MM: f64 = 20.0;

/// What to simulate.
#[derive(Debug, Clone)]
pub struct SimSetup {
    /// Sample material ([`materials::MATERIAL_NAMES`] or a texture-set
    /// directory).
    pub material: String,
    /// Seed of the as-built scanner, the board and the sensor noise.
    pub seed: u64,
    /// The scanner simulated, as its nominal geometry (a geometry file:
    /// docs/scanner-geometry.md); `None` is the shipped default scanner.
    /// The as-built scanner is it with the seed's manufacturing errors.
    pub geometry: Option<ScannerGeometry>,
    /// Sensor binning (1 = the geometry's own sensor; the default
    /// scanner's is 4096²).
    pub bin: u32,
    /// Faults to inject.
    pub faults: FaultPlan,
    /// The sensor's defective pixels (`hil_sim::defects`; none by default).
    pub defects: Vec<DefectSpec>,
    /// A black level the camera leaves in its frames, ADC codes (0: none,
    /// as docs/scan-format.md asks).
    pub black_level_codes: u32,
    /// Home / index sensors wired active high, per axis (the board's
    /// default is active low).
    pub home_active_high: [bool; 3],
    /// The drivers' fault line is wired active high (TMC2209 DIAG; the
    /// board's default is active low).
    pub driver_fault_active_high: bool,
    /// The camera's trigger latency, µs (it exposes this long after each
    /// edge of the trigger pulse; the board's light follows the pulse).
    pub trigger_latency_us: u32,
    /// The camera's exposure strobe wired to the board: active high
    /// (`Some(true)`, the default), active low, or not wired
    /// (`hil_sim::SimConfig::strobe_active_high`). The board watches it
    /// only once `scanner config --strobe` says so.
    pub strobe_active_high: Option<bool>,
    /// The camera lens' radial distortion k1, k2
    /// (`scanner_geometry::radial_distort`; the nominal geometry knows
    /// none: calibration measures it).
    pub lens_distortion: [f64; 2],
    /// The sample's face this far proud of the holder's plane (where the
    /// targets lie), towards the mirrors, mm
    /// ([`OpticalSim::with_sample_height`]; 0: in the plane).
    pub sample_height_mm: f64,
    /// The sample's face tilted, degrees: rising along u by the tangent of
    /// the first, along v by that of the second
    /// ([`OpticalSim::with_sample_face`]; 0, 0: parallel to the holder).
    pub sample_tilt_deg: [f64; 2],
    /// The sample's thickness, mm: its four sides show that far below its
    /// face beyond the edges facing a view
    /// ([`OpticalSim::with_sample_thickness`]; 0: no sides, as a sample
    /// sunk flush into the holder).
    pub sample_thickness_mm: f64,
    /// The holder's diffuse albedo around the sample, in every scan (the
    /// targets lie in the same holder;
    /// [`OpticalSim::with_holder_albedo`]; 0: perfectly black).
    pub holder_albedo: f64,
    /// The drives the scanner is built with (`hil_sim::SimConfig::axes`;
    /// docs/axis-config.md); other than the spec's, its board comes with
    /// them saved.
    pub axes: [protocol::AxisConfig; 3],
    /// The axis configuration its board comes with when it is not `axes`
    /// (`hil_sim::SimConfig::flash_axes`): a board still to be
    /// commissioned (`scanner axes --correct`), or configured wrongly.
    pub board_axes: Option<[protocol::AxisConfig; 3]>,
    /// What [`SimSetup::serve`] gives the host to open: the pty, or a link
    /// that follows the board through unplugs as a USB port's does
    /// ([`hil_sim::Port`]).
    pub port: hil_sim::Port,
}

impl SimSetup {
    /// `material` with seed 1, full resolution, no faults.
    pub fn new(material: &str) -> SimSetup {
        SimSetup {
            material: material.into(),
            seed: 1,
            geometry: None,
            bin: 1,
            faults: FaultPlan::none(),
            defects: Vec::new(),
            black_level_codes: 0,
            home_active_high: [false; 3],
            driver_fault_active_high: false,
            trigger_latency_us: 0,
            strobe_active_high: Some(true),
            lens_distortion: [0.0; 2],
            sample_height_mm: 0.0,
            sample_tilt_deg: [0.0; 2],
            sample_thickness_mm: 0.0,
            holder_albedo: 0.0,
            axes: protocol::default_axes(),
            board_axes: None,
            port: hil_sim::Port::Pty,
        }
    }

    /// What is simulated, in words, as scan manifests record it
    /// (`settings.simulator`: a resume on another simulated scanner is
    /// refused): material, seed and binning, and whatever differs from a
    /// default scanner.
    pub fn describe(&self) -> String {
        let mut s =
            format!("simulated {}, seed {}, binning {}", self.material, self.seed, self.bin);
        if let Some(g) = &self.geometry {
            s += &format!(", geometry {}", g.hash());
        }
        if !self.defects.is_empty() {
            s += &format!(", sensor defects {:?}", self.defects);
        }
        if self.black_level_codes > 0 {
            s += &format!(", black level {} codes", self.black_level_codes);
        }
        if self.lens_distortion != [0.0; 2] {
            s += &format!(", lens distortion {:?}", self.lens_distortion);
        }
        if self.sample_height_mm != 0.0 {
            s += &format!(", sample's face {} mm proud of the holder", self.sample_height_mm);
        }
        if self.sample_tilt_deg != [0.0; 2] {
            let [u, v] = self.sample_tilt_deg;
            s += &format!(", sample's face tilted {u}° along u, {v}° along v");
        }
        if self.sample_thickness_mm != 0.0 {
            s += &format!(", sample {} mm thick, its sides showing", self.sample_thickness_mm);
        }
        if self.holder_albedo != 0.0 {
            s += &format!(", holder albedo {}", self.holder_albedo);
        }
        if self.trigger_latency_us > 0 {
            s += &format!(", camera trigger latency {} µs", self.trigger_latency_us);
        }
        for (axis, (c, d)) in
            protocol::Axis::ALL.iter().zip(self.axes.iter().zip(protocol::default_axes()))
        {
            if *c != d {
                s += &format!(", {} {}", axis.name(), scanner_geometry::describe_axis(c));
            }
        }
        if let Some(board) = &self.board_axes {
            for (axis, c) in protocol::Axis::ALL.iter().zip(board) {
                s += &format!(", board's {} {}", axis.name(), scanner_geometry::describe_axis(c));
            }
        }
        s
    }

    /// The nominal geometry of the simulated scanner (what the host gets),
    /// binned.
    pub fn nominal(&self) -> Result<ScannerGeometry, SimError> {
        if self.bin == 0 || self.bin > 64 {
            return Err(SimError::Usage(format!("sensor binning {} outside 1…64", self.bin)));
        }
        let g = match &self.geometry {
            Some(g) => g.clone(),
            None => ScannerGeometry::default_scanner(),
        };
        if g.camera.width < self.bin || g.camera.height < self.bin {
            return Err(SimError::Usage(format!(
                "sensor binning {} exceeds the {}×{} sensor",
                self.bin, g.camera.width, g.camera.height
            )));
        }
        Ok(g.with_sensor_scaled(self.bin))
    }

    /// Refuses what [`SimSetup::rig`] would refuse of the scene (material,
    /// binning, lens, the sample's face and thickness, holder) without
    /// starting a board: a session of several scans checks its last one
    /// before the first.
    pub fn check_scene(&self) -> Result<(), SimError> {
        self.optics().map(drop)
    }

    fn optics(&self) -> Result<OpticalSim, SimError> {
        let material = materials::lookup(&self.material)?;
        let nominal = self.nominal()?;
        let (w, h) = (nominal.camera.width, nominal.camera.height);
        let defects =
            hil_sim::defects::place(&self.defects, w, h, self.seed).map_err(SimError::Usage)?;
        let max = nominal.sensor.max_code();
        if self.black_level_codes as f64 >= max {
            return Err(SimError::Usage(format!(
                "a black level of {} codes is not below the top code {max}",
                self.black_level_codes
            )));
        }
        let mut sim = OpticalSim::as_built(&nominal, Sample::small(material), self.seed)
            .with_defects(defects)
            .with_black_level(self.black_level_codes);
        if self.lens_distortion != [0.0; 2] {
            // Checked as a geometry file's would be.
            let mut lens = nominal.clone();
            lens.camera.distortion = self.lens_distortion;
            lens.validate().map_err(|e| SimError::Usage(format!("lens distortion: {e}")))?;
            sim = sim.with_lens_distortion(self.lens_distortion);
        }
        if !self.sample_height_mm.is_finite() || self.sample_height_mm.abs() > MAX_SAMPLE_HEIGHT_MM
        {
            return Err(SimError::Usage(format!(
                "a sample height of {} mm is outside ±{MAX_SAMPLE_HEIGHT_MM} mm",
                self.sample_height_mm
            )));
        }
        if let Some(t) =
            self.sample_tilt_deg.iter().find(|t| !t.is_finite() || t.abs() > MAX_SAMPLE_TILT_DEG)
        {
            return Err(SimError::Usage(format!(
                "a sample tilt of {t}° is outside ±{MAX_SAMPLE_TILT_DEG}°"
            )));
        }
        let face = SampleFace::tilted(self.sample_height_mm, self.sample_tilt_deg);
        if !face.is_flush() {
            sim = sim.with_sample_face(face);
        }
        let t = self.sample_thickness_mm;
        if !t.is_finite() || !(0.0..=MAX_SAMPLE_THICKNESS_MM).contains(&t) {
            return Err(SimError::Usage(format!(
                "a sample thickness of {t} mm is outside 0…{MAX_SAMPLE_THICKNESS_MM} mm"
            )));
        }
        if t > 0.0 {
            sim = sim.with_sample_thickness(t);
        }
        let a = self.holder_albedo;
        if !(0.0..=1.0).contains(&a) {
            return Err(SimError::Usage(format!("a holder albedo of {a} is outside 0…1")));
        }
        if a > 0.0 {
            sim = sim.with_holder_albedo(a);
        }
        Ok(sim)
    }

    fn config(&self) -> Result<SimConfig, SimError> {
        // Drives the host could not drive, or whose home switch the
        // simulated mechanics cannot place, are refused.
        scanner_geometry::check_axes(&self.axes)
            .map_err(|e| SimError::Usage(format!("simulated axes: {e}")))?;
        if let Some(board) = &self.board_axes {
            scanner_geometry::check_axes(board)
                .map_err(|e| SimError::Usage(format!("the simulated board's axes: {e}")))?;
        }
        let mut c = SimConfig::new(self.seed);
        c.axes = self.axes;
        c.flash_axes = self.board_axes;
        c.faults = self.faults.clone();
        c.home_active_high = self.home_active_high;
        c.driver_fault_active_high = self.driver_fault_active_high;
        c.trigger_latency_us = self.trigger_latency_us;
        c.strobe_active_high = self.strobe_active_high;
        Ok(c)
    }

    /// Board and camera in this process (deterministic).
    pub fn rig(&self) -> Result<SimRig, SimError> {
        Ok(SimRig::new(self.config()?, self.optics()?))
    }

    /// Serve the board on a pty (time running at `speed` × real time), the
    /// camera dropping frames into `frames` as `files`.
    pub fn serve(
        &self,
        speed: f64,
        frames: PathBuf,
        files: hil_sim::camera::FrameFiles,
    ) -> Result<hil_sim::PtyServer, SimError> {
        let camera = hil_sim::camera::SimCamera::new(self.optics()?)
            .with_trigger_latency(self.trigger_latency_us)
            .with_axes(self.axes);
        hil_sim::PtyServer::start_with_camera(
            hil_sim::SimDevice::new(self.config()?),
            speed,
            Some((camera, frames, files)),
            self.port.clone(),
        )
        .map_err(|e| SimError::Serve(e.to_string()))
    }
}
