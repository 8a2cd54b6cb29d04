//! The `scanner` commands that talk to a scanner (real or simulated).

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use crate::camera::{Camera, FolderCamera};
use crate::discovery::{self, DeviceChoice};
use crate::link::{Device, LinkError, SerialTransport, Transport, UsbTransport};
use crate::scan::{self, ScanError, ScanOptions, ScanProgress, ScanReport};
use anyhow::anyhow;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use scanner_geometry::{AxisValues, ScannerGeometry, unit_suffix};

#[cfg(feature = "sim")]
use crate::{camera::SimCamera, link::SimTransport, simulator::SimSetup};
#[cfg(feature = "sim")]
use hil_sim::{FaultPlan, FaultSpec, SimRig, defects::DefectSpec};
/// Built without the simulator: there is never a simulated rig.
#[cfg(not(feature = "sim"))]
type SimRig = std::convert::Infallible;
/// Built without the simulator: `--sim-fault` is parsed, then refused.
#[cfg(not(feature = "sim"))]
type FaultSpec = String;
/// Built without the simulator: `--sim-defect` is parsed, then refused.
#[cfg(not(feature = "sim"))]
type DefectSpec = String;

#[cfg(feature = "sim")]
fn sim_failure(e: crate::simulator::SimError) -> Failure {
    Failure(e.exit_code(), anyhow!(e))
}

#[cfg(not(feature = "sim"))]
fn no_simulator() -> Failure {
    Failure(2, anyhow!("this scanner was built without the simulator (cargo feature `sim`)"))
}
use protocol::{Axis, AxisSet, Event, FaultFlags, LightState, MoveMode, Request};

use super::Failure;

/// Which device, and the simulator's settings when it is `sim`.
#[derive(Debug, Clone, Args)]
pub struct DeviceArgs {
    /// `sim` (the in-process simulator), a serial port path, `usb:SERIAL`,
    /// or a serial number.
    #[arg(long, default_value = "sim")]
    pub device: String,
    /// Simulator: sample material, a library name or a texture-set
    /// directory (docs/texture-set.md).
    #[arg(long, default_value = "woven-fabric")]
    pub sim_material: String,
    /// Simulator: seed (as-built errors, board, noise).
    #[arg(long, default_value_t = 1)]
    pub sim_seed: u64,
    /// Simulator: sensor binning (1 = 4096², 8 = 512²).
    #[arg(long, default_value_t = 1)]
    pub sim_bin: u32,
    /// Simulator: the scanner to simulate, a geometry file
    /// (docs/scanner-geometry.md; default: the shipped default scanner).
    /// Pass the same file as `--geometry` to `calibrate`, `regions` and
    /// `build`.
    #[arg(long, value_name = "FILE")]
    pub sim_geometry: Option<PathBuf>,
    /// Simulator: per-byte bit-flip probability on the link.
    #[arg(long, default_value_t = 0.0)]
    pub sim_corrupt: f64,
    /// Simulator: a fault to inject, e.g. `reset@trigger=10` (repeatable).
    #[arg(long = "sim-fault")]
    pub sim_faults: Vec<FaultSpec>,
    /// Simulator: a defective sensor pixel, `stuck:X,Y`, `dead:X,Y`,
    /// `hot:X,Y,E_PER_S` or `random:N` (N stuck and N dead, seeded)
    /// (repeatable).
    #[arg(long = "sim-defect")]
    pub sim_defects: Vec<DefectSpec>,
    /// Simulator: a black level of CODES left in the camera's frames (a
    /// capture program that does not subtract it).
    #[arg(long, default_value_t = 0, value_name = "CODES")]
    pub sim_black_level: u32,
    /// Simulator: these axes' home / index sensors are wired active high
    /// (comma-separated; the board reads them as `scanner config
    /// --home-sensor` says).
    #[arg(long, value_delimiter = ',', value_parser = super::parse_axis, value_name = "AXES")]
    pub sim_home_active_high: Vec<Axis>,
    /// Simulator: the drivers' fault line is wired active-high (TMC2209
    /// DIAG) or active-low (DRV8825 nFAULT, the default), whatever the
    /// board is set to read.
    #[arg(long, value_parser = super::parse_polarity, value_name = "POLARITY")]
    pub sim_driver_fault: Option<bool>,
    /// Simulator: the camera exposes US µs after each edge of its trigger
    /// pulse (the board's light follows the pulse: short exposures lose
    /// light, which the HDR merge's exposure agreement reports).
    #[arg(long, default_value_t = 0, value_name = "US")]
    pub sim_trigger_latency_us: u32,
    /// Simulator: the camera's exposure strobe is wired to the board
    /// active-high (the default), active-low, or not at all (none); the
    /// board watches it once `scanner config --strobe` says so.
    #[arg(long, value_parser = ["active-high", "active-low", "none"], value_name = "POLARITY")]
    pub sim_strobe: Option<String>,
    #[command(flatten)]
    pub scene: SceneArgs,
    /// Simulator: the drives the scanner is built with, an axis
    /// configuration file (docs/axis-config.md; default: the spec's). Its
    /// board comes with them saved (unless --sim-board-axes).
    #[arg(long, value_name = "FILE")]
    pub sim_axes: Option<PathBuf>,
    /// Simulator: the axis configuration its board comes with when it is
    /// not the drives it is built with (--sim-axes), an axis configuration
    /// file: a board still to be commissioned (`scanner axes --correct`;
    /// with this option `scanner sim` prints where the axes physically
    /// stop after each motion, as a ruler on the machine would read).
    #[arg(long, value_name = "FILE")]
    pub sim_board_axes: Option<PathBuf>,
}

/// The simulated scene around the sample: the lens and the holder (the
/// same for every scan of a session) and how the sample lies on it.
#[derive(Debug, Clone, Default, Args)]
pub struct SceneArgs {
    /// Simulator: the camera lens' radial distortion K1,K2 (the nominal
    /// geometry knows none: calibration measures K1).
    #[arg(long, value_parser = parse_k1_k2, allow_hyphen_values = true, value_name = "K1,K2")]
    pub sim_lens_distortion: Option<[f64; 2]>,
    /// Simulator: the sample's face stands MM proud of the holder's plane,
    /// where the targets lie (a thicker sample; negative: recessed).
    /// `scanner regions` and `build` measure it (`--sample-height`).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true, value_name = "MM")]
    pub sim_sample_height: f64,
    /// Simulator: the sample's face tilted DEG_U,DEG_V degrees (rising
    /// along u, along v; a sample that does not lie flat). `scanner
    /// regions` and `build` measure it with the height.
    #[arg(long, value_parser = parse_tilt, allow_hyphen_values = true, value_name = "DEG_U,DEG_V")]
    pub sim_sample_tilt: Option<[f64; 2]>,
    /// Simulator: the sample is MM thick, its sides showing below its face
    /// beyond the edges that face a view (default 0: no sides, a sample
    /// sunk flush into the holder).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true, value_name = "MM")]
    pub sim_sample_thickness: f64,
    /// Simulator: the holder around the sample (and the targets) reflects
    /// diffusely with this albedo (default 0: perfectly black; a real
    /// holder's flock 0.01–0.05, a light one ≈ 0.8).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true, value_name = "ALBEDO")]
    pub sim_holder_albedo: f64,
}

impl SceneArgs {
    /// The scene of the calibration targets scanned in the same session:
    /// the same lens and holder, the targets lying flat in it.
    pub fn for_targets(&self) -> SceneArgs {
        SceneArgs {
            sim_lens_distortion: self.sim_lens_distortion,
            sim_holder_albedo: self.sim_holder_albedo,
            ..SceneArgs::default()
        }
    }
}

impl DeviceArgs {
    #[cfg(feature = "sim")]
    pub fn sim_setup(&self) -> Result<SimSetup, Failure> {
        if !(0.0..=1.0).contains(&self.sim_corrupt) {
            return Err(Failure(2, anyhow!("--sim-corrupt is a probability in [0, 1]")));
        }
        let mut faults = FaultPlan::none().corrupt(self.sim_corrupt);
        for f in &self.sim_faults {
            faults = faults.with(f.when, f.event);
        }
        let geometry = match &self.sim_geometry {
            Some(p) => Some(ScannerGeometry::load(p).map_err(|e| Failure(3, anyhow!(e)))?),
            None => None,
        };
        Ok(SimSetup {
            material: self.sim_material.clone(),
            seed: self.sim_seed,
            geometry,
            bin: self.sim_bin,
            faults,
            defects: self.sim_defects.clone(),
            black_level_codes: self.sim_black_level,
            home_active_high: Axis::ALL.map(|a| self.sim_home_active_high.contains(&a)),
            driver_fault_active_high: self.sim_driver_fault.unwrap_or(false),
            trigger_latency_us: self.sim_trigger_latency_us,
            strobe_active_high: match self.sim_strobe.as_deref() {
                Some("none") => None,
                Some(p) => Some(p == "active-high"),
                None => Some(true),
            },
            lens_distortion: self.scene.sim_lens_distortion.unwrap_or([0.0; 2]),
            sample_height_mm: self.scene.sim_sample_height,
            sample_tilt_deg: self.scene.sim_sample_tilt.unwrap_or([0.0; 2]),
            sample_thickness_mm: self.scene.sim_sample_thickness,
            holder_albedo: self.scene.sim_holder_albedo,
            axes: match &self.sim_axes {
                Some(p) => scanner_geometry::load_axes(p).map_err(|e| Failure(3, anyhow!(e)))?,
                None => protocol::default_axes(),
            },
            board_axes: self
                .sim_board_axes
                .as_deref()
                .map(|p| scanner_geometry::load_axes(p).map_err(|e| Failure(3, anyhow!(e))))
                .transpose()?,
            port: hil_sim::Port::Pty,
        })
    }
}

/// `K1,K2`: two numbers.
fn parse_k1_k2(s: &str) -> Result<[f64; 2], String> {
    parse_pair(s, "K1,K2")
}

pub(super) fn parse_tilt(s: &str) -> Result<[f64; 2], String> {
    parse_pair(s, "DEG_U,DEG_V")
}

/// Two finite numbers separated by a comma (`form` names them).
fn parse_pair(s: &str, form: &str) -> Result<[f64; 2], String> {
    let k: Vec<f64> = s
        .split(',')
        .map(|x| x.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("{s:?}: {e}"))?;
    match k[..] {
        [a, b] if a.is_finite() && b.is_finite() => Ok([a, b]),
        _ => Err(format!("{s:?}: give two finite numbers, {form}")),
    }
}

fn scan_failure(e: ScanError) -> Failure {
    Failure(e.exit_code(), anyhow!(e))
}

fn link_failure(e: LinkError) -> Failure {
    let latched =
        matches!(e, LinkError::Refused { error: protocol::DeviceError::FaultLatched, .. });
    let f = scan_failure(ScanError::from(e));
    // A latched fault needs a person: exit 7, as the fault itself did.
    if latched {
        Failure(7, anyhow!("{} (`scanner status` names it, `scanner clear` clears it)", f.1))
    } else {
        f
    }
}

/// `scanner clear`: clear the device's latched faults.
pub fn clear(args: &DeviceArgs) -> Result<(), Failure> {
    let mut o = open(args)?;
    let faults = o.device.status().map_err(link_failure)?.faults;
    if faults.is_empty() {
        println!("no fault latched");
        return Ok(());
    }
    let names = faults.names().collect::<Vec<_>>().join(", ");
    if clear_fault(&mut o.device)? {
        println!("cleared: {names}");
        return Ok(());
    }
    // What still holds it, as far as the device can tell (protocol 1.2).
    let why = match inputs_of(&mut o.device) {
        Ok(i) if i.estop_open => "the emergency stop is still open: release it first".to_string(),
        Ok(i) if i.driver_fault => {
            let high = board_config_of(&mut o.device)?.driver_fault_active_high;
            format!(
                "the driver fault line is still {}, read {} as a fault: a driver reports a \
                 fault (power it down and find why) — or, if nothing is wrong, the drivers \
                 signal the other way round and `scanner config --driver-fault {}` sets it",
                if i.driver_fault_line_high { "high" } else { "low" },
                polarity_name(high),
                if high { "active-low" } else { "active-high" }
            )
        }
        _ => "the emergency stop is still open or a driver still reports a fault; release it \
              first"
            .to_string(),
    };
    Err(Failure(7, anyhow!("{names}: not cleared — {why}")))
}

/// Set the drivers' fault-line polarity to `high` (`faults`: those latched
/// before) — unless the line reads a fault under it now (the wrong
/// polarity, or a driver really is faulted): then it is put back and
/// nothing changes, exit 7. A driver fault latched only because the line
/// was read the wrong way round is cleared. The device reads the line the
/// new way at once; since protocol 1.2 (`inputs`) it says how it reads,
/// before, only whether the fault now clears.
fn set_driver_fault_polarity(
    device: &mut Device,
    high: bool,
    faults: FaultFlags,
    inputs: bool,
) -> Result<(), Failure> {
    let before = board_config_of(device)?;
    let board = protocol::BoardConfig { driver_fault_active_high: high };
    device.command(Request::SetBoardConfig(board)).map_err(link_failure)?;
    let rescue = faults == FaultFlags::DRIVER_FAULT;
    let line = if inputs { Some(inputs_of(device)?) } else { None };
    let cleared = match line {
        Some(i) if i.driver_fault => false,
        _ => !rescue || clear_fault(device)?,
    };
    if cleared {
        if rescue {
            println!(
                "cleared: driver fault (its line reads no fault read {})",
                polarity_name(high)
            );
        }
        return Ok(());
    }
    device.command(Request::SetBoardConfig(before)).map_err(link_failure)?;
    // Read the wrong way for a moment, it may have latched a fault of its
    // own: cleared, as it was before.
    if faults.is_empty() && !clear_fault(device)? {
        return Err(Failure(7, anyhow!("a driver fault latched while the polarity changed")));
    }
    let level = match line {
        Some(i) if !i.driver_fault => {
            return Err(Failure(7, anyhow!("the driver fault did not clear; nothing changed")));
        }
        Some(i) if i.driver_fault_line_high => "is high",
        Some(_) => "is low",
        None => "still reads a fault",
    };
    Err(Failure(
        7,
        anyhow!(
            "the driver fault line {level}, a fault read {}: the drivers signal the other way \
             round, or one is faulted (`scanner inputs` shows the line); nothing changed",
            polarity_name(high)
        ),
    ))
}

/// Ask the device to clear its latched faults: false if an input still
/// holds one (the emergency stop, a driver's fault line). Asked twice 20 ms
/// apart: firmware before the polarity change read at once took its
/// 0.4 ms debounce to see a just-changed polarity.
fn clear_fault(device: &mut Device) -> Result<bool, Failure> {
    for attempt in 0..2 {
        match device.command(Request::ClearFault) {
            Ok(()) => return Ok(true),
            Err(LinkError::Refused { error: protocol::DeviceError::FaultLatched, .. }) => {
                if attempt == 0 {
                    std::thread::sleep(Duration::from_millis(20));
                }
            }
            Err(e) => return Err(link_failure(e)),
        }
    }
    Ok(false)
}

fn polarity_name(high: bool) -> &'static str {
    if high { "active high" } else { "active low" }
}

/// An open device (and the simulator behind it, if simulated).
pub struct Opened {
    pub device: Device,
    pub rig: Option<SimRig>,
    pub geometry_default: Option<ScannerGeometry>,
    /// What the simulated scanner simulates, recorded in scan manifests.
    pub simulator: Option<String>,
}

pub fn open(args: &DeviceArgs) -> Result<Opened, Failure> {
    let choice = discovery::choose(&args.device).map_err(|e| Failure(5, anyhow!(e)))?;
    // Assigned only when the simulator is built in.
    #[cfg_attr(not(feature = "sim"), allow(unused_mut))]
    let mut simulator = None;
    let (transport, rig, geometry): (Box<dyn Transport>, _, _) = match choice {
        #[cfg(not(feature = "sim"))]
        DeviceChoice::Simulator => return Err(no_simulator()),
        #[cfg(feature = "sim")]
        DeviceChoice::Simulator => {
            let setup = args.sim_setup()?;
            let rig = setup.rig().map_err(sim_failure)?;
            let nominal = setup.nominal().map_err(sim_failure)?;
            simulator = Some(setup.describe());
            (Box::new(SimTransport(rig.clone())), Some(rig), Some(nominal))
        }
        DeviceChoice::Serial(path) => {
            let t =
                SerialTransport::open(&path).map_err(|e| Failure(5, anyhow!("no device: {e}")))?;
            (Box::new(t), None, None)
        }
        DeviceChoice::Usb(serial) => {
            let t =
                UsbTransport::open(&serial).map_err(|e| Failure(5, anyhow!("no device: {e}")))?;
            (Box::new(t), None, None)
        }
    };
    let device = Device::connect(transport).map_err(|e| match e {
        LinkError::Timeout { device, .. } => {
            Failure(5, anyhow!("no device: {device} does not answer the handshake"))
        }
        e => link_failure(e),
    })?;
    Ok(Opened { device, rig, geometry_default: geometry, simulator })
}

fn load_geometry(path: Option<&Path>, opened: &Opened) -> Result<ScannerGeometry, Failure> {
    match path {
        Some(p) => {
            let g = ScannerGeometry::load(p).map_err(|e| Failure(3, anyhow!(e)))?;
            // The scanner is built: its design's faults are worth knowing
            // before scanning with it, but they are warnings here. Its axes'
            // travel is the device's, checked when the mirror table is
            // written, not the default axes'.
            let problems: Vec<_> = g
                .check_design()
                .problems
                .into_iter()
                .filter(|p| !matches!(p, scanner_geometry::DesignProblem::OutOfTravel { .. }))
                .collect();
            for problem in &problems {
                eprintln!("scanner: warning: {}: {problem}", p.display());
            }
            if !problems.is_empty() {
                eprintln!(
                    "scanner: warning: `scanner geometry --geometry {}` describes the design",
                    p.display()
                );
            }
            Ok(g)
        }
        None => {
            Ok(opened.geometry_default.clone().unwrap_or_else(ScannerGeometry::default_scanner))
        }
    }
}

/// `scanner devices`
pub fn devices() -> Result<(), Failure> {
    match discovery::serial_scanners() {
        Ok(list) if list.is_empty() => println!(
            "serial: no scanner (VID:PID {:04x}:{:04x})",
            protocol::USB_VID,
            protocol::USB_PID
        ),
        Ok(list) => {
            for p in list {
                let in_use = p.serial.as_deref().and_then(crate::link::scanner_in_use);
                println!(
                    "serial  {}  serial number {}{}",
                    p.path,
                    p.serial.as_deref().unwrap_or("?"),
                    in_use.map(|h| format!("  (in use by {h})")).unwrap_or_default()
                );
                // Its stable names (they follow it when it re-enumerates).
                let by_id = std::path::Path::new("/dev/serial/by-id");
                for link in discovery::links_to(&p.path, by_id) {
                    println!("        also {link}");
                }
            }
        }
        Err(e) => println!("serial: {e}"),
    }
    match discovery::usb_devices() {
        Ok(list) if list.is_empty() => println!("usb: no scanner"),
        Ok(list) => {
            for d in list {
                let bulk = if d.vendor_interface.is_some() {
                    "bulk interface"
                } else {
                    "no bulk interface"
                };
                let in_use = crate::link::scanner_in_use(&d.serial)
                    .map(|h| format!(", in use by {h}"))
                    .unwrap_or_default();
                println!("usb     {}  serial number {}  ({bulk}{in_use})", d.location, d.serial);
            }
        }
        Err(e) => println!("usb: cannot list devices ({e})"),
    }
    Ok(())
}

/// `scanner config`: show the board's wiring options, or set and save them.
pub fn board_config(
    args: &DeviceArgs,
    driver_fault_active_high: Option<bool>,
    home_sensors: &[(Axis, bool)],
    strobe: StrobeChange,
) -> Result<(), Failure> {
    let mut o = open(args)?;
    // The camera's strobe: since protocol 1.4, on a board with the input.
    let info = o.device.info();
    let strobe_input = info.protocol.minor >= 4
        && info.capabilities.contains(protocol::Capabilities::EXPOSURE_STROBE);
    if strobe.changes() && info.protocol.minor < 4 {
        return Err(Failure(
            6,
            anyhow!(
                "the device's firmware (protocol {}) cannot watch a camera's exposure strobe: \
                 update it",
                info.protocol
            ),
        ));
    }
    if strobe.changes() && !strobe_input && strobe.watch != Some(None) {
        return Err(Failure(6, anyhow!("this board has no exposure strobe input")));
    }
    // Home sensors' polarity: since protocol 1.2.
    let theirs = o.device.info().protocol;
    let has_home_sensors = theirs.minor >= 2;
    if !home_sensors.is_empty() && !has_home_sensors {
        return Err(Failure(
            6,
            anyhow!(
                "the device's firmware (protocol {theirs}) reads every home sensor active low: \
                 update it to set their polarity"
            ),
        ));
    }
    let changes =
        driver_fault_active_high.is_some() || !home_sensors.is_empty() || strobe.changes();
    let persistent =
        o.device.info().capabilities.contains(protocol::Capabilities::PERSISTENT_CONFIG);
    let faults = o.device.status().map_err(link_failure)?.faults;
    // A driver fault latched because its line is read the wrong way round
    // (drivers that signal the other way: it latches at power-on and no
    // `scanner clear` clears it) is what setting the polarity is for.
    let rescue = driver_fault_active_high.is_some() && faults == FaultFlags::DRIVER_FAULT;
    // Otherwise the device saves nothing while a fault is latched: change
    // nothing rather than a setting that would not survive a reset.
    if changes && persistent && !rescue && !faults.is_empty() {
        return Err(saves_nothing_while(faults));
    }
    if let Some(high) = driver_fault_active_high {
        set_driver_fault_polarity(&mut o.device, high, faults, has_home_sensors)?;
    }
    if !home_sensors.is_empty() {
        let mut home = home_sensors_of(&mut o.device)?;
        let before = home;
        for &(axis, high) in home_sensors {
            home.active_high[axis.index()] = high;
        }
        o.device.command(Request::SetHomeSensors(home)).map_err(link_failure)?;
        let changed: Vec<&str> = Axis::ALL
            .iter()
            .filter(|a| home.active_high[a.index()] != before.active_high[a.index()])
            .map(|a| a.name())
            .collect();
        if !changed.is_empty() {
            println!("{} must be homed again (scanner home)", changed.join(", "));
        }
    }
    if strobe.changes() {
        let mut s = strobe_of(&mut o.device)?;
        if let Some(watch) = strobe.watch {
            s.enabled = watch.is_some();
            s.active_high = watch.unwrap_or(s.active_high);
        }
        s.max_delay_us = strobe.max_delay_us.unwrap_or(s.max_delay_us);
        o.device.command(Request::SetStrobe(s)).map_err(link_failure)?;
    }
    if changes {
        if persistent {
            o.device.command(Request::SaveConfig).map_err(link_failure)?;
            println!("saved to the device's flash");
        } else {
            println!("this device cannot save it: it lasts until the device resets");
        }
    }
    println!(
        "driver fault line: {}",
        if board_config_of(&mut o.device)?.driver_fault_active_high {
            "active high (TMC2209 DIAG)"
        } else {
            "active low (DRV8825 nFAULT)"
        }
    );
    let home = if has_home_sensors {
        home_sensors_of(&mut o.device)?
    } else {
        protocol::HomeSensors::default()
    };
    println!(
        "home sensors: {}{}",
        Axis::ALL
            .iter()
            .map(|a| format!("{} {}", a.name(), polarity_name(home.active_high[a.index()])))
            .collect::<Vec<_>>()
            .join(", "),
        if has_home_sensors { "" } else { " (fixed by this firmware)" }
    );
    let strobe = if strobe_input { Some(strobe_of(&mut o.device)?) } else { None };
    println!("camera exposure strobe: {}", describe_strobe(strobe.as_ref()));
    Ok(())
}

/// A change of the camera strobe's setting (`scanner config --strobe`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct StrobeChange {
    /// Watch it with this polarity (`Some(None)`: stop watching).
    pub watch: Option<Option<bool>>,
    /// How far it may lag its pulse, µs.
    pub max_delay_us: Option<u32>,
}

impl StrobeChange {
    fn changes(&self) -> bool {
        self.watch.is_some() || self.max_delay_us.is_some()
    }
}

/// The strobe's setting in words (`None`: no input to watch).
fn describe_strobe(s: Option<&protocol::StrobeConfig>) -> String {
    match s {
        None => "no input on this board (or firmware before protocol 1.4)".into(),
        Some(s) if !s.enabled => "not watched".into(),
        Some(s) => format!(
            "watched, {}; a trigger whose strobe has not risen {:.1} ms after the pulse is a \
             missed frame",
            polarity_name(s.active_high),
            s.max_delay_us as f64 / 1000.0
        ),
    }
}

fn strobe_of(dev: &mut Device) -> Result<protocol::StrobeConfig, Failure> {
    match dev.request(Request::GetStrobe).map_err(link_failure)? {
        protocol::Reply::Strobe(s) => Ok(s),
        reply => Err(link_failure(LinkError::Unexpected { request: "GetStrobe", reply })),
    }
}

/// A device with persistent storage saves nothing while `faults` are
/// latched: the refusal to change a setting that would not survive a reset.
fn saves_nothing_while(faults: FaultFlags) -> Failure {
    Failure(
        7,
        anyhow!(
            "{} latched: the device saves no settings until it is cleared (`scanner clear`); \
             nothing changed",
            faults.names().collect::<Vec<_>>().join(", ")
        ),
    )
}

/// `scanner axes`: print the device's axis configurations; with `set`, make
/// them the file's first (saved to flash), with `correct` corrected by
/// measured moves (the device's own, or the file's); with `output`, write
/// them to a file (docs/axis-config.md).
pub fn axes(
    args: &DeviceArgs,
    set: Option<&Path>,
    correct: &[scanner_geometry::Measured],
    output: Option<&Path>,
) -> Result<(), Failure> {
    if let Some(twice) =
        Axis::ALL.into_iter().find(|&a| correct.iter().filter(|m| m.axis == a).count() > 1)
    {
        return Err(Failure(2, anyhow!("--correct: {} given twice", twice.name())));
    }
    let file = set
        .map(|p| scanner_geometry::load_axes(p).map_err(|e| Failure(3, anyhow!(e))))
        .transpose()?;
    let mut o = open(args)?;
    // What to make the device's axes: the file's, or the device's own or
    // the file's corrected by measured moves.
    let change = if file.is_some() || !correct.is_empty() {
        let current = scan::axis_configs(&mut o.device).map_err(scan_failure)?;
        let mut wanted = file.unwrap_or(current);
        for m in correct {
            let was = wanted[m.axis.index()];
            let now =
                scanner_geometry::correct_axis(&was, *m).map_err(|e| Failure(3, anyhow!(e)))?;
            wanted[m.axis.index()] = now;
            let (u, units) = match was.unit {
                protocol::Unit::Degree => ("°", "degrees"),
                protocol::Unit::Millimetre => (" mm", "mm"),
            };
            println!(
                "{}: {} → {} steps/{} (told {}{u}, moved {}{u}); travel, home position and \
                 homing distances kept in {units}, speeds in steps/s",
                m.axis.name(),
                was.steps_per_unit,
                now.steps_per_unit,
                u.trim_start(),
                m.commanded,
                m.measured,
            );
        }
        scanner_geometry::check_axes(&wanted).map_err(|e| Failure(3, anyhow!(e)))?;
        for w in scanner_geometry::axes_warnings(&wanted) {
            eprintln!("scanner: warning: {w}");
        }
        Some((current, wanted))
    } else {
        None
    };
    if let Some((current, wanted)) = change {
        let persistent =
            o.device.info().capabilities.contains(protocol::Capabilities::PERSISTENT_CONFIG);
        let faults = o.device.status().map_err(link_failure)?.faults;
        if current != wanted && persistent && !faults.is_empty() {
            return Err(saves_nothing_while(faults));
        }
        let set = scan::set_axis_configs(&mut o.device, &current, &wanted).map_err(scan_failure)?;
        if set.changed.is_empty() {
            println!("the device's axes are already these");
        } else {
            let names: Vec<&str> = set.changed.iter().map(|a| a.name()).collect();
            println!(
                "set {}: {}; must be homed again (scanner home)",
                names.join(", "),
                if set.saved {
                    "saved to the device's flash"
                } else {
                    "this device cannot save it: it lasts until the device resets"
                }
            );
            if set.mirrors > 0 {
                println!(
                    "mirror table: {} of {} entries in the new steps, the same axis positions \
                     (`scanner setup` writes them exactly from the design)",
                    set.mirrors_moved, set.mirrors
                );
            }
            // One line per reason (a ring's mirrors share theirs).
            let mut reasons: Vec<(String, Vec<usize>)> = Vec::new();
            for (l, why) in &set.unreachable {
                let why = why.to_string();
                match reasons.iter_mut().find(|(w, _)| *w == why) {
                    Some((_, mirrors)) => mirrors.push(*l),
                    None => reasons.push((why, vec![*l])),
                }
            }
            for (why, mirrors) in &reasons {
                eprintln!("scanner: warning: {}: {why}: left unset", scan::mirror_list(mirrors));
            }
            if !set.unreachable.is_empty() {
                eprintln!(
                    "scanner: warning: {} of {} mirror-table entries lie outside the new \
                     travel; `scanner setup` writes the table again once the design fits it \
                     (`scanner geometry --device`)",
                    set.unreachable.len(),
                    set.mirrors
                );
            }
        }
    }
    let axes = scan::axis_configs(&mut o.device).map_err(scan_failure)?;
    for (axis, c) in Axis::ALL.iter().zip(&axes) {
        println!("{:5}  {}", axis.name(), scanner_geometry::describe_axis(c));
    }
    if let Some(out) = output {
        crate::fsutil::write_atomic(out, scanner_geometry::axes_to_toml(&axes).as_bytes())
            .map_err(|e| Failure(4, anyhow!("{}: {e}", out.display())))?;
        println!("written to {}", out.display());
    }
    Ok(())
}

/// The axis configurations of the device named `device` (`scanner geometry
/// --device`); for the simulator, `sim` are its options that bear on them
/// (option, file), the others at their defaults.
pub fn device_axes(
    device: &str,
    sim: &[(&str, &Option<PathBuf>)],
) -> Result<[protocol::AxisConfig; 3], Failure> {
    #[derive(clap::Parser)]
    struct Named {
        #[command(flatten)]
        device: DeviceArgs,
    }
    let mut argv = vec!["scanner".to_string(), format!("--device={device}")];
    for (option, file) in sim {
        if let Some(file) = file {
            if device != "sim" {
                return Err(Failure(2, anyhow!("{option} is for --device sim")));
            }
            argv.push(format!("{option}={}", file.display()));
        }
    }
    let args = <Named as clap::Parser>::try_parse_from(argv)
        .map_err(|e| Failure(2, anyhow!("--device {device}: {e}")))?
        .device;
    let mut o = open(&args)?;
    scan::axis_configs(&mut o.device).map_err(scan_failure)
}

/// `scanner inputs`
pub fn inputs(args: &DeviceArgs, watch: Option<f64>) -> Result<(), Failure> {
    if let Some(s) = watch
        && !(s.is_finite() && (0.0..=86_400.0).contains(&s))
    {
        return Err(Failure(2, anyhow!("--watch takes 0…86400 s (0 or none: until Ctrl-C)")));
    }
    let mut o = open(args)?;
    let theirs = o.device.info().protocol;
    if theirs.minor < 2 {
        return Err(Failure(
            6,
            anyhow!(
                "the device's firmware (protocol {theirs}) cannot report its inputs: update it"
            ),
        ));
    }
    let home = home_sensors_of(&mut o.device)?;
    let fault_high = board_config_of(&mut o.device)?.driver_fault_active_high;
    let mut last = inputs_of(&mut o.device)?;
    for line in describe_inputs(&last, &home, fault_high) {
        println!("{line}");
    }
    let Some(seconds) = watch else { return Ok(()) };
    let started = Instant::now();
    let end = (seconds > 0.0).then(|| started + Duration::from_secs_f64(seconds));
    println!("watching{} …", if end.is_some() { "" } else { " (Ctrl-C stops)" });
    while end.is_none_or(|end| Instant::now() < end) {
        std::thread::sleep(Duration::from_millis(20));
        let now = inputs_of(&mut o.device)?;
        if now != last {
            let before = describe_inputs(&last, &home, fault_high);
            for (line, was) in describe_inputs(&now, &home, fault_high).iter().zip(&before) {
                if line != was {
                    println!("{:8.3} s  {line}", started.elapsed().as_secs_f64());
                }
            }
            last = now;
        }
    }
    Ok(())
}

/// The device's inputs (protocol 1.2).
fn inputs_of(device: &mut Device) -> Result<protocol::InputState, Failure> {
    match device.request(Request::GetInputs).map_err(link_failure)? {
        protocol::Reply::Inputs(i) => Ok(i),
        reply => Err(link_failure(LinkError::Unexpected { request: "GetInputs", reply })),
    }
}

/// One line per input: its level and what the board makes of it.
fn describe_inputs(
    i: &protocol::InputState,
    home: &protocol::HomeSensors,
    fault_high: bool,
) -> Vec<String> {
    let level = |high: bool| if high { "high" } else { "low " };
    let read_as = |high: bool| if high { "read active high" } else { "read active low" };
    let mut out: Vec<String> = Axis::ALL
        .iter()
        .map(|a| {
            let k = a.index();
            let sensor = if *a == Axis::Disk { "index flag " } else { "home switch" };
            format!(
                "{:5} {sensor}   line {} → {} ({})",
                a.name(),
                level(i.home_line_high[k]),
                if i.home_actuated[k] { "ACTUATED" } else { "not actuated" },
                read_as(home.active_high[k])
            )
        })
        .collect();
    out.push(format!(
        "emergency stop      {}",
        if i.estop_open { "OPEN → stop" } else { "closed (run)" }
    ));
    out.push(format!(
        "driver fault        line {} → {} ({})",
        level(i.driver_fault_line_high),
        if i.driver_fault { "FAULT" } else { "no fault" },
        read_as(fault_high)
    ));
    out
}

fn board_config_of(dev: &mut Device) -> Result<protocol::BoardConfig, Failure> {
    match dev.request(Request::GetBoardConfig).map_err(link_failure)? {
        protocol::Reply::BoardConfig(b) => Ok(b),
        reply => Err(link_failure(LinkError::Unexpected { request: "GetBoardConfig", reply })),
    }
}

fn home_sensors_of(dev: &mut Device) -> Result<protocol::HomeSensors, Failure> {
    match dev.request(Request::GetHomeSensors).map_err(link_failure)? {
        protocol::Reply::HomeSensors(h) => Ok(h),
        reply => Err(link_failure(LinkError::Unexpected { request: "GetHomeSensors", reply })),
    }
}

/// `scanner verify`
pub fn verify(dir: &Path) -> Result<(), Failure> {
    let v = scan::verify(dir).map_err(scan_failure)?;
    println!("{}: {} of {} frames intact", dir.display(), v.intact, v.mirror_count);
    if !v.missing.is_empty() {
        println!("missing: {}", scan::mirror_list(&v.missing));
    }
    if !v.damaged.is_empty() {
        println!("damaged: {}", scan::mirror_list(&v.damaged));
    }
    if v.is_complete() {
        Ok(())
    } else {
        Err(Failure(
            3,
            anyhow!(
                "{} is not a complete scan; `scanner scan --resume` completes it",
                dir.display()
            ),
        ))
    }
}

/// `scanner info`
pub fn info(args: &DeviceArgs) -> Result<(), Failure> {
    let mut o = open(args)?;
    let i = *o.device.info();
    println!("device   {} on {}", scan::hex(&i.device_id), o.device.describe());
    println!("firmware {}  protocol {}  board {:#06x}", i.firmware, i.protocol, i.board);
    let entries = scan::mirror_entries(&mut o.device).map_err(scan_failure)?;
    let unset: Vec<usize> = (0..entries.len()).filter(|&l| entries[l].is_none()).collect();
    println!(
        "boot id  {:08x}  mirrors {}{}  capabilities {:#06x} ({})",
        i.boot_id,
        i.mirror_count,
        if unset.is_empty() {
            String::new()
        } else {
            format!(" ({} unset: `scanner setup` writes them)", scan::mirror_list(&unset))
        },
        i.capabilities.0,
        i.capabilities.names().collect::<Vec<_>>().join(", ")
    );
    let axes = scan::axis_configs(&mut o.device).map_err(scan_failure)?;
    for (axis, c) in Axis::ALL.iter().zip(&axes) {
        println!("{:5}  {}", axis.name(), scanner_geometry::describe_axis(c));
    }
    Ok(())
}

/// `scanner status`
pub fn status(args: &DeviceArgs) -> Result<(), Failure> {
    let mut o = open(args)?;
    let s = o.device.status().map_err(link_failure)?;
    println!("state {:?}, trigger {}, uptime {} ms", s.state, s.trigger_seq, s.uptime_ms);
    for (axis, a) in Axis::ALL.iter().zip(s.axes) {
        println!(
            "{:5}  {:>8} steps = {:>9.3}  {}{}",
            axis.name(),
            a.position_steps,
            a.position_units,
            if a.homed { "homed" } else { "not homed" },
            if a.moving { ", moving" } else { "" }
        );
    }
    println!(
        "light {}",
        if s.light.on { format!("on, {} ‰", s.light.duty_permille) } else { "off".into() }
    );
    let faults: Vec<&str> = s.faults.names().collect();
    println!("faults {}", if faults.is_empty() { "none".into() } else { faults.join(", ") });
    Ok(())
}

/// Wait for the end of the motion just commanded ([`scan::wait_motion_end`]:
/// its event, or the status should the link have lost the event).
fn wait_motion(dev: &mut Device, what: &str) -> Result<(), Failure> {
    match scan::wait_motion_end(dev, Duration::from_secs(120)).map_err(link_failure)? {
        Some(scan::MotionEnd::Reported { outcome, positions, .. }) => {
            motion_outcome(what, outcome, positions)
        }
        Some(scan::MotionEnd::Unreported(s)) if s.faults.is_empty() => {
            let positions = s.axes.map(|a| a.position_steps);
            println!("{what}: done at {positions:?} steps (its report was lost on the link)");
            Ok(())
        }
        Some(scan::MotionEnd::Unreported(s)) => {
            let faults: Vec<&str> = s.faults.names().collect();
            Err(Failure(
                7,
                anyhow!("{what}: stopped ({}; its report was lost on the link)", faults.join(", ")),
            ))
        }
        None => Err(Failure(7, anyhow!("{what}: no end of motion within 120 s"))),
    }
}

/// What a `MotionDone` event says of the motion: exit 7 unless completed.
fn motion_outcome(
    what: &str,
    outcome: protocol::MotionOutcome,
    positions: [i32; 3],
) -> Result<(), Failure> {
    match outcome {
        protocol::MotionOutcome::Completed => {
            println!("{what}: done at {positions:?} steps");
            Ok(())
        }
        protocol::MotionOutcome::HomingFailed(axis, why) => {
            use protocol::HomingFailure;
            let hint = match why {
                HomingFailure::SwitchStuck | HomingFailure::SwitchNotFound => format!(
                    " (or its sensor's polarity is set the wrong way round: `scanner config` \
                     shows it, `--home-sensor {}=active-high` or `=active-low` sets it)",
                    axis.name()
                ),
                HomingFailure::Timeout => String::new(),
            };
            Err(Failure(7, anyhow!("{what}: {} failed: {why}{hint}", axis.name())))
        }
        outcome => Err(Failure(7, anyhow!("{what}: {outcome:?}"))),
    }
}

/// `scanner home`
pub fn home(args: &DeviceArgs, axes: &[Axis], repeat: Option<u32>) -> Result<(), Failure> {
    let mut o = open(args)?;
    let set = if axes.is_empty() {
        AxisSet::ALL
    } else {
        axes.iter().fold(AxisSet::NONE, |s, a| s.with(*a))
    };
    let Some(cycles) = repeat else {
        o.device.clear_events();
        o.device.command(Request::Home { axes: set }).map_err(link_failure)?;
        return wait_motion(&mut o.device, "homing");
    };
    let configs = scan::axis_configs(&mut o.device).map_err(scan_failure)?;
    let in_units = |i: usize, steps: i32| {
        let c = &configs[i];
        format!("{:.2}{}", scanner_geometry::steps_to_unit(steps.into(), c), unit_suffix(c.unit))
    };
    let mut print = |c: usize, cycle: &scan::HomingCycle| {
        let parts: Vec<String> = Axis::ALL
            .into_iter()
            .filter_map(|a| {
                let (to, e) = (cycle.went_to[a.index()]?, cycle.error_steps[a.index()]);
                let e = e.map_or("not measured".into(), |e| format!("{e:+} steps"));
                Some(format!("{} from {}: {e}", a.name(), in_units(a.index(), to)))
            })
            .collect();
        println!("homing {}: {}", c + 1, parts.join(", "));
    };
    let cycles = scan::homing_repeatability(&mut o.device, set, cycles as usize, &mut print)
        .map_err(scan_failure)?;
    let tolerance = protocol::POSITION_TOLERANCE_STEPS;
    let mut lost = Vec::new();
    for r in scan::repeatability(&cycles, set) {
        let ok = r.kept && r.measured == cycles.len();
        let Some((lo, hi)) = r.range else {
            println!("{:5}  not measured", r.axis.name());
            lost.push(r.axis.name());
            continue;
        };
        println!(
            "{:5}  count at the switch {lo:+} … {hi:+} steps over {} homings (tolerance ±{tolerance}): {}",
            r.axis.name(),
            r.measured,
            if ok { "keeps its steps" } else { "LOST STEPS" }
        );
        if !ok {
            lost.push(r.axis.name());
        }
    }
    if lost.is_empty() {
        return Ok(());
    }
    Err(Failure(
        7,
        anyhow!(
            "{} lost steps (the switch measures the net of what was lost both ways): lower \
             its v_max or a_max (`scanner axes`), or check the motor's current, its coupling \
             and what it drives",
            lost.join(", ")
        ),
    ))
}

/// `scanner move`
pub fn move_axes(
    args: &DeviceArgs,
    targets: [Option<f64>; 3],
    relative: bool,
    steps: bool,
) -> Result<(), Failure> {
    if targets.iter().all(Option::is_none) {
        return Err(Failure(2, anyhow!("give at least one of --disk, --track, --tilt")));
    }
    let mut o = open(args)?;
    let configs = scan::axis_configs(&mut o.device).map_err(scan_failure)?;
    let mut out = [None; 3];
    for i in 0..3 {
        if let Some(v) = targets[i] {
            let axis = Axis::ALL[i];
            let s = if steps {
                if !(v.is_finite() && v.fract() == 0.0 && v.abs() <= i32::MAX as f64) {
                    return Err(Failure(2, anyhow!("{}: {v} is not a step count", axis.name())));
                }
                v as i32
            } else if relative {
                scanner_geometry::offset_to_steps(axis, v, &configs[i])
                    .map_err(|e| Failure(2, anyhow!(e)))?
            } else {
                // Absolute, in units: the continuous disk wraps (−90° = 270°).
                scanner_geometry::unit_to_steps(axis, v, &configs[i])
                    .map_err(|e| Failure(2, anyhow!(e)))?
            };
            out[i] = Some(s);
        }
    }
    let mode = if relative { MoveMode::Relative } else { MoveMode::Absolute };
    o.device.clear_events();
    let moving = out.map(|t| t.is_some());
    let result = o.device.command(Request::Move { mode, targets: out });
    result.map_err(|e| move_failure(&mut o.device, e, moving))?;
    wait_motion(&mut o.device, "move")
}

/// A refused move: an axis not homed named, exit 2 (nothing moved, the
/// command is early), else as any link failure.
fn move_failure(dev: &mut Device, e: LinkError, axes: [bool; 3]) -> Failure {
    if !matches!(e, LinkError::Refused { error: protocol::DeviceError::NotHomed, .. }) {
        return link_failure(e);
    }
    let names: Vec<&str> = match dev.status() {
        Ok(s) => Axis::ALL
            .into_iter()
            .filter(|a| axes[a.index()] && !s.axes[a.index()].homed)
            .map(|a| a.name())
            .collect(),
        Err(_) => Vec::new(),
    };
    let which = if names.is_empty() { "an axis".to_string() } else { names.join(", ") };
    Failure(
        2,
        anyhow!(
            "the device refused the move: {which} not homed since it powered on or was \
             reconfigured (`scanner home` first)"
        ),
    )
}

/// `scanner move --mirror`: to mirror `mirror`'s entry of the device's
/// mirror table.
pub fn move_to_mirror(args: &DeviceArgs, mirror: u8) -> Result<(), Failure> {
    let mut o = open(args)?;
    let count = o.device.info().mirror_count;
    let position = if mirror < count {
        scan::mirror_entry(&mut o.device, mirror).map_err(scan_failure)?
    } else {
        None
    };
    let Some(position) = position else {
        return Err(Failure(
            2,
            anyhow!(
                "mirror {mirror} is not set in the device's mirror table ({count} entries): \
                 `scanner setup` writes it"
            ),
        ));
    };
    let axes = scan::axis_configs(&mut o.device).map_err(scan_failure)?;
    println!("{}", mirror_line(mirror as usize, &position, &axes));
    o.device.clear_events();
    let result = o.device.command(Request::GoToMirror { mirror });
    result.map_err(|e| move_failure(&mut o.device, e, [true; 3]))?;
    wait_motion(&mut o.device, &format!("mirror {mirror}"))
}

/// One mirror-table entry in units and steps.
fn mirror_line(
    mirror: usize,
    position: &protocol::MirrorPosition,
    axes: &[protocol::AxisConfig; 3],
) -> String {
    let v = AxisValues::from_steps(position.steps.map(i64::from), axes);
    format!(
        "mirror {mirror:2}: disk {:8.3}°  track {:7.3} mm  tilt {:7.3}°  = {:?} steps",
        v.disk_deg, v.track_mm, v.tilt_deg, position.steps
    )
}

/// `scanner bootloader`: the controller into its chip's ROM bootloader
/// (USB DFU), to be flashed without a probe.
pub fn bootloader(args: &DeviceArgs) -> Result<(), Failure> {
    let mut o = open(args)?;
    let info = *o.device.info();
    let by_hand = "hold the board's BOOT0 button while pressing and releasing its reset (NRST) \
                   button, then flash as README \"Flashing over USB\" says";
    if info.protocol.minor < 5
        || !info.capabilities.contains(protocol::Capabilities::SYSTEM_BOOTLOADER)
    {
        return Err(Failure(
            6,
            anyhow!(
                "this controller (firmware {}, protocol {}) cannot enter its bootloader on \
                 command: {by_hand}",
                info.firmware,
                info.protocol
            ),
        ));
    }
    o.device.command(Request::EnterBootloader).map_err(link_failure)?;
    // It resets once its answer is out: it must fall silent, and a USB
    // board's serial port goes away (not to be waited for).
    std::thread::sleep(Duration::from_millis(500));
    o.device.timings_mut().reconnect_for = Duration::ZERO;
    if o.device.request(Request::Ping { token: 0x0B00_710A }).is_ok() {
        return Err(Failure(
            1,
            anyhow!("the controller still answers after accepting to enter its bootloader"),
        ));
    }
    println!("the controller left its firmware for the chip's ROM bootloader (USB DFU)");
    let dfu = discovery::STM32_DFU;
    match discovery::dfu_bootloaders() {
        Ok(found) if !found.is_empty() => {
            println!("USB DFU {:04x}:{:04x} at {}", dfu.0, dfu.1, found.join(", "))
        }
        Ok(_) => println!(
            "no USB DFU device ({:04x}:{:04x}) seen yet: it enumerates within a second or two",
            dfu.0, dfu.1
        ),
        Err(why) => println!("USB not listed ({why})"),
    }
    println!(
        "flash it and start the new firmware (the saved configuration is kept):\n  \
         scripts/firmware-bin.sh\n  \
         dfu-util -a 0 -s 0x08000000:leave -D firmware/board/target/scanner-fw.bin"
    );
    Ok(())
}

/// `scanner light`
pub fn light(args: &DeviceArgs, on: bool, duty: u16) -> Result<(), Failure> {
    if duty == 0 || duty > 1000 {
        return Err(Failure(2, anyhow!("--duty is per mille, 1…1000")));
    }
    let mut o = open(args)?;
    o.device
        .command(Request::SetLight(LightState { on, duty_permille: duty }))
        .map_err(link_failure)?;
    println!("light {}", if on { "on" } else { "off" });
    Ok(())
}

/// `scanner trigger`
pub fn trigger(args: &DeviceArgs, exposure_us: u32) -> Result<(), Failure> {
    let mut o = open(args)?;
    o.device.clear_events();
    o.device.command(Request::Trigger { exposure_us }).map_err(link_failure)?;
    match o
        .device
        .wait_event(Duration::from_secs(5), |e| matches!(e, Event::TriggerFired(_)))
        .map_err(link_failure)?
    {
        Some(Event::TriggerFired(t)) => {
            println!(
                "trigger {} at {} µs, exposure {} µs",
                t.trigger_seq, t.timestamp_us, t.exposure_us
            );
            Ok(())
        }
        _ => Err(Failure(7, anyhow!("no trigger event within 5 s"))),
    }
}

/// `scanner setup`
pub fn setup(args: &DeviceArgs, geometry: Option<&Path>) -> Result<(), Failure> {
    let mut o = open(args)?;
    let g = load_geometry(geometry, &o)?;
    let setup = scan::setup(&mut o.device, &g).map_err(scan_failure)?;
    for (l, p) in setup.table.iter().enumerate() {
        println!("{}", mirror_line(l, p, &setup.axes));
    }
    println!("{} entries written; geometry {}", setup.written, g.hash());
    Ok(())
}

/// Progress on an indicatif bar (hidden when stderr is not a terminal).
struct Bar {
    bar: ProgressBar,
    label: String,
}

impl ScanProgress for Bar {
    fn start(&mut self, total: usize, done: usize) {
        self.bar.set_length(total as u64);
        self.bar.set_position(done as u64);
        if done > 0 {
            self.bar.println(format!(
                "{}: resuming, {done} of {total} frames already stored",
                self.label
            ));
        }
        self.bar.reset_eta();
    }
    fn frame(&mut self, mirror: usize) {
        self.bar.inc(1);
        self.bar.set_message(format!("mirror {mirror}"));
    }
    fn retaking(&mut self, mirrors: &[usize]) {
        self.bar.set_position(self.bar.position().saturating_sub(mirrors.len() as u64));
    }
    fn note(&mut self, message: &str) {
        // A hidden bar (stderr not a terminal) would swallow the line.
        if self.bar.is_hidden() {
            eprintln!("{}: {message}", self.label);
        } else {
            self.bar.println(format!("{}: {message}", self.label));
        }
    }
}

/// The scanner's geometry and camera, for the commands that take frames.
#[derive(Debug, Clone, Args)]
pub struct RigArgs {
    /// Nominal geometry file (default: the shipped default scanner, or the
    /// simulated one's).
    #[arg(long)]
    pub geometry: Option<PathBuf>,
    /// Camera: `folder:DIR` (frames a capture program drops into DIR);
    /// the simulator brings its own.
    #[arg(long)]
    pub camera: Option<String>,
    /// How the folder camera's 16-bit PNG and TIFF frames hold the
    /// sensor's codes: as they are (0…4095 for 12 bits), shifted left
    /// (0…65520), or scaled to 0…65535. A frame that contradicts it stops
    /// the scan and names the one that reads it.
    #[arg(long, value_enum, default_value_t = CameraCodes::Native)]
    pub camera_codes: CameraCodes,
}

impl RigArgs {
    /// The geometry, and the camera: the folder's, the simulator's own, or
    /// none (a real scanner without `--camera`).
    fn open(&self, opened: &Opened) -> Result<(ScannerGeometry, Option<Box<dyn Camera>>), Failure> {
        let geometry = load_geometry(self.geometry.as_deref(), opened)?;
        let camera = match (&self.camera, &opened.rig) {
            (None, None) if self.camera_codes == CameraCodes::Native => None,
            (spec, rig) => {
                Some(camera_for(spec.as_deref(), self.camera_codes, &geometry, rig.as_ref())?)
            }
        };
        Ok((geometry, camera))
    }
}

/// Scan parameters on the command line.
#[derive(Debug, Clone, Args)]
pub struct ScanArgs {
    /// Sample name (recorded in the manifest).
    #[arg(long)]
    pub sample_name: String,
    /// Scan directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Complete the scan already in `--out`.
    #[arg(long)]
    pub resume: bool,
    /// Scan into a non-empty `--out` that holds no scan (its files may be
    /// overwritten).
    #[arg(long)]
    pub force: bool,
    #[command(flatten)]
    pub rig: RigArgs,
    /// Scan only mirrors 0 … N−1.
    #[arg(long)]
    pub mirrors: Option<usize>,
    /// Exposure, µs (20 … 2 000 000; below the device's 1 000 the light is
    /// dimmed in proportion), or `auto`: metered on a few mirrors first,
    /// then the exposure (with --hdr, the bracket) that suits the sample
    /// (docs/scan-format.md, "Auto exposure").
    #[arg(long, default_value_t = OrAuto::Fixed(protocol::DEFAULT_EXPOSURE_US))]
    pub exposure_us: OrAuto,
    /// HDR: take these exposures (µs, comma-separated) per mirror and
    /// store their merge (docs/scan-format.md, "HDR").
    #[arg(long, value_delimiter = ',', conflicts_with = "hdr")]
    pub exposures: Vec<u32>,
    /// HDR with the default bracket around --exposure-us (×1/25, ×1/5, ×1),
    /// or the metered one with `--exposure-us auto`.
    #[arg(long)]
    pub hdr: bool,
    /// Camera timeout per frame, s.
    #[arg(long, default_value_t = 10.0)]
    pub frame_timeout: f64,
    /// Check every axis against its switch (by homing) after every N
    /// frames, and once all are taken (0: only then). A check that finds
    /// lost steps retakes the frames since the last good one.
    #[arg(long, default_value_t = scan::DEFAULT_CHECK_EVERY)]
    pub check_every: usize,
    /// Wait this long after each move before the light and the trigger,
    /// ms (0 … 60 000): long enough for the mirror arm and the sample to
    /// stop ringing on your build (a frame blurred or doubled along the
    /// disk's motion says it is too short).
    #[arg(long, default_value_t = protocol::DEFAULT_SETTLE_MS, value_name = "MS",
          value_parser = clap::value_parser!(u16).range(0..=60_000))]
    pub settle_ms: u16,
    /// The camera's frames carry a black level of CODES ADC codes (its
    /// capture program leaves it in; the dark frame says the median it
    /// reads): subtract it from every value as frames arrive. `auto`: take
    /// the median of a frame with the light off at the scan's start (0 when
    /// that is read noise alone).
    #[arg(long, default_value_t = OrAuto::Fixed(0), value_name = "CODES|auto")]
    pub black_level: OrAuto,
    /// Switch the light on US µs before each trigger pulse and off as long
    /// after it (0 … 10 000; firmware of protocol 1.3): for a camera that
    /// exposes later than its trigger's edges, which would otherwise miss
    /// the light's last µs (the HDR merge's exposure agreement shows it).
    #[arg(long, default_value_t = 0, value_name = "US")]
    pub light_margin_us: u16,
}

/// How a capture program stores the sensor's codes in integer images
/// ([`scanner_geometry::IntegerCodes`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum CameraCodes {
    /// The codes as they are: 0…4095 for a 12-bit sensor.
    Native,
    /// Shifted left to the top bits: 0…65520 for 12 bits in 16.
    Shifted,
    /// Stretched over the integer's range: 0…65535.
    Scaled,
}

impl From<CameraCodes> for scanner_geometry::IntegerCodes {
    fn from(c: CameraCodes) -> Self {
        match c {
            CameraCodes::Native => scanner_geometry::IntegerCodes::Native,
            CameraCodes::Shifted => scanner_geometry::IntegerCodes::Shifted,
            CameraCodes::Scaled => scanner_geometry::IntegerCodes::Scaled,
        }
    }
}

/// `--exposure-us` (microseconds) and `--black-level` (ADC codes): a
/// number, or `auto`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OrAuto {
    /// Measured by the scan (`--exposure-us`: metered, [`crate::exposure`];
    /// `--black-level`: from a frame with the light off).
    Auto,
    /// Given: µs, or ADC codes.
    Fixed(u32),
}

impl std::fmt::Display for OrAuto {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            OrAuto::Auto => f.write_str("auto"),
            OrAuto::Fixed(us) => write!(f, "{us}"),
        }
    }
}

impl std::str::FromStr for OrAuto {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if s.eq_ignore_ascii_case("auto") {
            return Ok(OrAuto::Auto);
        }
        s.parse().map(OrAuto::Fixed).map_err(|_| format!("{s:?} is neither a number nor `auto`"))
    }
}

impl ScanArgs {
    /// Auto exposure asked for, if any.
    pub fn auto_exposure(&self) -> Option<scan::AutoExposure> {
        (self.exposure_us == OrAuto::Auto).then_some(if self.hdr {
            scan::AutoExposure::Hdr
        } else {
            scan::AutoExposure::Single
        })
    }

    /// The fixed exposure, or the metering frames' with `auto`, µs.
    pub fn base_exposure_us(&self) -> u32 {
        match self.exposure_us {
            OrAuto::Auto => protocol::DEFAULT_EXPOSURE_US,
            OrAuto::Fixed(us) => us,
        }
    }

    /// The HDR bracket asked for (empty: a single exposure, or a metered
    /// one), checked before anything moves.
    pub fn bracket(&self) -> Result<Vec<u32>, Failure> {
        // The CLI scans at full light duty: exposures below the device's
        // shortest are taken with the light dimmed.
        let floor = crate::exposure::shortest_us(protocol::FULL_DUTY_PERMILLE);
        let range = floor..=protocol::MAX_EXPOSURE_US;
        let exposure_us = self.base_exposure_us();
        if !range.contains(&exposure_us) {
            return Err(Failure(
                2,
                anyhow!("--exposure-us {exposure_us} outside {}…{}", range.start(), range.end()),
            ));
        }
        if self.exposure_us == OrAuto::Auto {
            if !self.exposures.is_empty() {
                return Err(Failure(
                    2,
                    anyhow!(
                        "--exposures names fixed exposures; it does not go with --exposure-us auto"
                    ),
                ));
            }
            return Ok(Vec::new());
        }
        let mut b = if self.hdr {
            crate::hdr::default_bracket(exposure_us)
        } else {
            self.exposures.clone()
        };
        if let Some(bad) = b.iter().find(|e| !range.contains(e)) {
            return Err(Failure(
                2,
                anyhow!("--exposures: {bad} µs outside {}…{}", range.start(), range.end()),
            ));
        }
        b.sort_unstable();
        b.dedup();
        if b.len() > 8 {
            return Err(Failure(2, anyhow!("--exposures: at most 8 exposures")));
        }
        Ok(if b.len() == 1 && !self.hdr && b[0] == exposure_us { Vec::new() } else { b })
    }
}

fn camera_for(
    spec: Option<&str>,
    codes: CameraCodes,
    geometry: &ScannerGeometry,
    rig: Option<&SimRig>,
) -> Result<Box<dyn Camera>, Failure> {
    let (sensor, camera) = (&geometry.sensor, &geometry.camera);
    match (spec, rig) {
        (Some(spec), _) => {
            let dir = spec
                .strip_prefix("folder:")
                .ok_or_else(|| Failure(2, anyhow!("--camera must be folder:DIR, got {spec:?}")))?;
            let size = [camera.width, camera.height];
            let camera = FolderCamera::new(Path::new(dir), sensor, codes.into(), size)
                .map_err(|e| Failure(8, anyhow!(e)))?;
            Ok(Box::new(camera))
        }
        (None, _) if codes != CameraCodes::Native => Err(Failure(
            2,
            anyhow!("--camera-codes is for a camera's frame files (--camera folder:DIR)"),
        )),
        #[cfg(feature = "sim")]
        (None, Some(rig)) => Ok(Box::new(SimCamera(rig.clone()))),
        #[cfg(not(feature = "sim"))]
        (None, Some(rig)) => match *rig {},
        (None, None) => Err(Failure(2, anyhow!("a real scanner needs --camera folder:DIR"))),
    }
}

/// `scanner check`'s options.
#[derive(Debug, Clone, Args)]
pub struct CheckArgs {
    #[command(flatten)]
    pub rig: RigArgs,
    /// Homing cycles of the homing check (out along the travel and back to
    /// the switches).
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=100))]
    pub homings: u32,
    /// Capture steps at every mirror whose reflection faces a view (with a
    /// glossy target each one's highlight is checked), not only the first,
    /// middle and last of them.
    #[arg(long)]
    pub capture_all: bool,
    /// The target on the holder is glossy (the glossy black one): a capture
    /// step whose views are alike fails instead of passing untold.
    #[arg(long)]
    pub glossy: bool,
    /// Exposure of the camera and capture checks, µs (1 000 … 2 000 000).
    #[arg(long, default_value_t = protocol::DEFAULT_EXPOSURE_US)]
    pub exposure_us: u32,
    /// Camera timeout per frame, s.
    #[arg(long, default_value_t = 10.0)]
    pub frame_timeout: f64,
    /// Wait after each move, ms, as for `scanner scan`.
    #[arg(long, default_value_t = protocol::DEFAULT_SETTLE_MS, value_name = "MS",
          value_parser = clap::value_parser!(u16).range(0..=60_000))]
    pub settle_ms: u16,
    /// Light around each pulse, µs, as for `scanner scan`.
    #[arg(long, default_value_t = 0, value_name = "US")]
    pub light_margin_us: u16,
    /// Also write the run's record to FILE (JSON, docs/check-report.md),
    /// for a test rig's log.
    #[arg(long, value_name = "FILE")]
    pub report: Option<PathBuf>,
    /// Also write the run to FILE as JUnit XML (a test case a check), which
    /// CI systems show as test results.
    #[arg(long, value_name = "FILE")]
    pub junit: Option<PathBuf>,
}

/// `scanner check`: every check, a line each; exit 10 if any failed.
pub fn check(args: &DeviceArgs, c: &CheckArgs) -> Result<(), Failure> {
    if !(0.0..=3600.0).contains(&c.frame_timeout) {
        return Err(Failure(2, anyhow!("--frame-timeout must be 0…3600 s")));
    }
    if !(protocol::MIN_EXPOSURE_US..=protocol::MAX_EXPOSURE_US).contains(&c.exposure_us) {
        return Err(Failure(
            2,
            anyhow!(
                "--exposure-us {}: {}…{} µs",
                c.exposure_us,
                protocol::MIN_EXPOSURE_US,
                protocol::MAX_EXPOSURE_US
            ),
        ));
    }
    if c.light_margin_us > protocol::MAX_LIGHT_MARGIN_US {
        return Err(Failure(
            2,
            anyhow!("--light-margin-us: at most {} µs", protocol::MAX_LIGHT_MARGIN_US),
        ));
    }
    // Refused before anything moves, not after the run.
    for path in c.report.iter().chain(&c.junit) {
        crate::fsutil::check_output(path, &[])
            .map_err(|e| Failure(4, anyhow!("{}: {e}", path.display())))?;
    }
    if let (Some(a), Some(b)) = (&c.report, &c.junit)
        && a == b
    {
        return Err(Failure(2, anyhow!("--report and --junit name the same file")));
    }
    let mut opened = open(args)?;
    let (geometry, mut camera) = c.rig.open(&opened)?;
    let info = *opened.device.info();
    let mut scan = ScanOptions::new("check", Path::new("."));
    scan.exposure_us = c.exposure_us;
    scan.frame_timeout = Duration::from_secs_f64(c.frame_timeout);
    scan.settle_ms = c.settle_ms;
    scan.light_margin_us = c.light_margin_us;
    let o = crate::check::CheckOptions {
        geometry,
        homings: c.homings as usize,
        capture_all: c.capture_all,
        glossy: c.glossy,
        scan,
    };
    let outcomes = crate::check::run(
        &mut opened.device,
        camera.as_mut().map(|c| &mut **c as &mut dyn Camera),
        &o,
        &mut |outcome| println!("{} {}: {}", outcome.verdict.word(), outcome.name, outcome.detail),
    );
    let report = crate::check::Report::new(&info, &outcomes);
    let (passed, failed, skipped) = (report.passed, report.failed, report.skipped);
    println!("{} checks: {passed} passed, {failed} failed, {skipped} skipped", outcomes.len());
    if let Some(path) = &c.report {
        let json = serde_json::to_vec_pretty(&report).map_err(|e| Failure(1, anyhow!(e)))?;
        crate::fsutil::write_atomic(path, &json)
            .map_err(|e| Failure(4, anyhow!("{}: {e}", path.display())))?;
    }
    if let Some(path) = &c.junit {
        let xml = junit(&report).map_err(|e| Failure(1, anyhow!(e)))?;
        crate::fsutil::write_atomic(path, xml.as_bytes())
            .map_err(|e| Failure(4, anyhow!("{}: {e}", path.display())))?;
    }
    if failed == 0 {
        return Ok(());
    }
    use crate::check::Verdict;
    let names: Vec<&str> =
        outcomes.iter().filter(|o| o.verdict == Verdict::Fail).map(|o| o.name).collect();
    Err(Failure(10, anyhow!("failed: {}", names.join(", "))))
}

/// A check run as JUnit XML: one test suite, `scanner check`, with the
/// device as properties, and a test case a check (class `scanner-check`):
/// a failed check a `failure` with its detail as message, a skipped one
/// `skipped`, a passed one its detail as system-out.
pub fn junit(report: &crate::check::Report<'_>) -> Result<String, quick_junit::SerializeError> {
    use crate::check::Verdict;
    use quick_junit::{NonSuccessKind, TestCase, TestCaseStatus, TestSuite};
    let d = &report.device;
    let mut suite = TestSuite::new("scanner check");
    suite.add_properties([
        ("device_id", d.device_id.as_str()),
        ("firmware", d.firmware.as_str()),
        ("protocol", d.protocol.as_str()),
        ("board", &format!("0x{:04x}", d.board)),
        ("boot_id", d.boot_id.as_str()),
        ("unix_time_s", &report.unix_time_s.to_string()),
    ]);
    let mut total = Duration::ZERO;
    for o in report.checks {
        let status = match o.verdict {
            Verdict::Pass => TestCaseStatus::success(),
            Verdict::Fail => {
                let mut s = TestCaseStatus::non_success(NonSuccessKind::Failure);
                s.set_message(o.detail.as_str());
                s
            }
            Verdict::Skip => {
                let mut s = TestCaseStatus::skipped();
                s.set_message(o.detail.as_str());
                s
            }
        };
        let mut case = TestCase::new(o.name, status);
        let took = Duration::from_secs_f64(o.seconds.max(0.0));
        total += took;
        case.set_classname("scanner-check").set_time(took);
        if o.verdict == Verdict::Pass {
            case.set_system_out(o.detail.as_str());
        }
        suite.add_test_case(case);
    }
    suite.set_time(total);
    let mut all = quick_junit::Report::new("scanner-check");
    all.set_time(total).add_test_suite(suite);
    all.to_string()
}

/// Run one scan with a progress bar; print the summary.
pub fn run_scan(
    opened: &mut Opened,
    scan_args: &ScanArgs,
    label: &str,
) -> Result<ScanReport, Failure> {
    if !(0.0..=3600.0).contains(&scan_args.frame_timeout) {
        return Err(Failure(2, anyhow!("--frame-timeout must be 0…3600 s")));
    }
    let (geometry, camera) = scan_args.rig.open(opened)?;
    let mut camera =
        camera.ok_or_else(|| Failure(2, anyhow!("a real scanner needs --camera folder:DIR")))?;
    if let Some(n) = scan_args.mirrors
        && !(1..=geometry.mirrors.len()).contains(&n)
    {
        return Err(Failure(
            2,
            anyhow!("--mirrors {n}: this scanner has mirrors 1…{}", geometry.mirrors.len()),
        ));
    }
    let top = geometry.sensor.max_code();
    if let OrAuto::Fixed(codes) = scan_args.black_level
        && codes as f64 >= top
    {
        return Err(Failure(
            2,
            anyhow!("--black-level {codes}: at or above the sensor's top code {top}"),
        ));
    }
    let mut opts = ScanOptions::new(&scan_args.sample_name, &scan_args.out);
    opts.resume = scan_args.resume;
    opts.mirrors = scan_args.mirrors;
    opts.exposure_us = scan_args.base_exposure_us();
    opts.auto_exposure = scan_args.auto_exposure();
    opts.frame_timeout = Duration::from_secs_f64(scan_args.frame_timeout);
    opts.bracket_us = scan_args.bracket()?;
    opts.check_every = scan_args.check_every;
    opts.settle_ms = scan_args.settle_ms;
    match scan_args.black_level {
        OrAuto::Auto => opts.black_level_auto = true,
        OrAuto::Fixed(codes) => opts.black_level_codes = codes,
    }
    opts.force = scan_args.force;
    opts.light_margin_us = scan_args.light_margin_us;
    opts.simulator = opened.simulator.clone();
    opts.interrupt = Some(interrupt_flag());
    let bar = super::progress_bar(geometry.mirrors.len() as u64);
    bar.set_style(
        ProgressStyle::with_template(
            "{prefix} [{bar:30}] {pos}/{len} frames, {elapsed} elapsed, ETA {eta} {msg}",
        )
        .expect("valid template"),
    );
    bar.set_prefix(label.to_string());
    let mut progress = Bar { bar: bar.clone(), label: label.to_string() };
    let report = scan::scan(&mut opened.device, camera.as_mut(), &geometry, &opts, &mut progress);
    bar.finish_and_clear();
    let report = report.map_err(|e| match e {
        ScanError::Interrupted { .. } => {
            Failure(e.exit_code(), anyhow!("{e}; continue with:\n  {}", resume_command()))
        }
        e => scan_failure(e),
    })?;
    let t = report.timings;
    println!(
        "{label}: {} frames taken, {} kept, {} retaken, {} resets survived, {} position checks; {:.1} s (link {:.1} s, camera {:.1} s, disk {:.1} s) → {}",
        report.captured,
        report.kept,
        report.retakes,
        report.resets,
        report.checks,
        t.total.as_secs_f64(),
        t.link.as_secs_f64(),
        t.camera.as_secs_f64(),
        t.disk.as_secs_f64(),
        scan_args.out.display()
    );
    if let Some(strobe) = report.strobe.describe(scan_args.light_margin_us) {
        println!("{label}: {strobe}");
    }
    let s = opened.device.stats;
    if s.retransmissions + s.reconnects + s.bad_frames > 0 {
        println!(
            "{label}: link: {} requests, {} retransmissions, {} bad frames, {} reconnects",
            s.requests, s.retransmissions, s.bad_frames, s.reconnects
        );
    }
    Ok(report)
}

/// Set by the first Ctrl-C: the scan stops after the frame in progress,
/// keeping every frame; a second Ctrl-C quits at once.
fn interrupt_flag() -> std::sync::Arc<std::sync::atomic::AtomicBool> {
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::{Arc, OnceLock};
    static FLAG: OnceLock<Arc<AtomicBool>> = OnceLock::new();
    FLAG.get_or_init(|| {
        let flag = Arc::new(AtomicBool::new(false));
        let set = flag.clone();
        let installed = ctrlc::set_handler(move || {
            if set.swap(true, Ordering::SeqCst) {
                std::process::exit(130);
            }
            eprintln!(
                "\nscanner: stopping after the frame in progress (Ctrl-C again quits at once)"
            );
        });
        if let Err(e) = installed {
            tracing::warn!("Ctrl-C will stop at once, not between frames: {e}");
        }
        flag
    })
    .clone()
}

/// The command that continues an interrupted scan: this one with
/// `--resume` (for the demo, the demo again: it resumes by itself).
fn resume_command() -> String {
    let args: Vec<String> = std::env::args().collect();
    let quoted: Vec<String> = args
        .iter()
        .map(|a| {
            if a.chars().all(|c| c.is_ascii_alphanumeric() || "-_./:=,@".contains(c)) {
                a.clone()
            } else {
                format!("'{}'", a.replace('\'', "'\\''"))
            }
        })
        .collect();
    let mut cmd = quoted.join(" ");
    if args.get(1).is_some_and(|a| a == "scan") && !args.iter().any(|a| a == "--resume") {
        cmd.push_str(" --resume");
    }
    cmd
}

/// `scanner scan`
pub fn scan_cmd(args: &DeviceArgs, scan_args: &ScanArgs) -> Result<(), Failure> {
    let mut opened = open(args)?;
    run_scan(&mut opened, scan_args, &scan_args.sample_name).map(|_| ())
}

/// `scanner demo` without the simulator: refused.
#[cfg(not(feature = "sim"))]
pub fn demo(
    _: &Path,
    _: &str,
    _: u32,
    _: Option<usize>,
    _: u64,
    _: Option<&Path>,
    _: &SceneArgs,
) -> Result<(), Failure> {
    Err(no_simulator())
}

/// Exposure of the demo's glossy-target scan, µs: its highlight flanks
/// stay below full scale.
#[cfg(feature = "sim")]
const GLOSSY_EXPOSURE_US: u32 = 2_000;

/// The lens of the demo's camera for direct images: 2 % barrel distortion
/// at the photographs' corners (k1 with the radius in half-diagonals), as
/// a stock lens has; `scanner rectify --lens auto` estimates it.
#[cfg(feature = "sim")]
const DEMO_LENS_K1: f64 = -0.02;

/// `scanner demo`: a complete simulated session — the three calibration
/// targets and a material sample, then calibration and region images —
/// into `out`.
#[cfg(feature = "sim")]
pub fn demo(
    out: &Path,
    material: &str,
    bin: u32,
    mirrors: Option<usize>,
    seed: u64,
    geometry: Option<&Path>,
    scene: &SceneArgs,
) -> Result<(), Failure> {
    // Refuse a bad material or geometry before scanning the calibration
    // targets.
    hil_sim::materials::lookup(material)
        .map_err(|e| sim_failure(crate::simulator::SimError::Material(e)))?;
    let targets_scene = scene.for_targets();
    // Another scanner than the default: its geometry as binned, written
    // beside the scans for calibrate and build (and the user).
    let geometry_file = match geometry {
        None => None,
        Some(p) => {
            let g = ScannerGeometry::load(p).map_err(|e| Failure(3, anyhow!(e)))?;
            // A design that cannot scan (`scanner geometry`'s check) is
            // refused now, not after minutes of simulated scanning.
            let problems = g.check_design().problems;
            if let Some(first) = problems.first() {
                return Err(Failure(
                    3,
                    anyhow!(
                        "{}: {first}{}; `scanner geometry --geometry {}` lists what else",
                        p.display(),
                        match problems.len() {
                            1 => String::new(),
                            n => format!(
                                " (and {} more problem{})",
                                n - 1,
                                if n > 2 { "s" } else { "" }
                            ),
                        },
                        p.display()
                    ),
                ));
            }
            let setup = crate::simulator::SimSetup {
                bin,
                geometry: Some(g),
                ..crate::simulator::SimSetup::new(material)
            };
            let nominal = setup.nominal().map_err(sim_failure)?;
            std::fs::create_dir_all(out)
                .map_err(|e| Failure(4, anyhow!("{}: {e}", out.display())))?;
            let file = out.join("geometry.toml");
            crate::fsutil::write_atomic(&file, nominal.to_toml().as_bytes())
                .map_err(|e| Failure(4, anyhow!("{}: {e}", file.display())))?;
            Some(file)
        }
    };
    let started = std::time::Instant::now();
    // A texture-set directory is named after its folder.
    let name = Path::new(material)
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .filter(|n| !n.is_empty())
        .map(|n| {
            // A texture set named like a target gets a scan directory of its own.
            let taken = ["checkerboard", "diffuse-white", "glossy-black"];
            if taken.contains(&n.as_str()) { format!("sample-{n}") } else { n }
        })
        .unwrap_or_else(|| "sample".into());
    // The glossy target's highlights are ≈ 40× the white's: a short exposure.
    // The sample: metered, HDR.
    let fixed = |us| OrAuto::Fixed(us);
    let device = |sample: &str, scene: &SceneArgs| DeviceArgs {
        device: "sim".into(),
        sim_material: sample.into(),
        sim_seed: seed,
        sim_bin: bin,
        sim_corrupt: 0.0,
        sim_faults: Vec::new(),
        sim_defects: Vec::new(),
        sim_black_level: 0,
        sim_home_active_high: Vec::new(),
        sim_driver_fault: None,
        sim_trigger_latency_us: 0,
        sim_strobe: None,
        scene: scene.clone(),
        sim_geometry: geometry.map(Path::to_path_buf),
        sim_axes: None,
        sim_board_axes: None,
    };
    // A scene the simulator refuses (a sample tilted too far, say) is
    // refused before the targets are scanned.
    device(material, scene).sim_setup()?.check_scene().map_err(sim_failure)?;
    for (sample, label, hdr, exposure_us, scene) in [
        (
            "checkerboard",
            "checkerboard",
            false,
            fixed(protocol::DEFAULT_EXPOSURE_US),
            &targets_scene,
        ),
        (
            "diffuse-white",
            "diffuse-white",
            false,
            fixed(protocol::DEFAULT_EXPOSURE_US),
            &targets_scene,
        ),
        ("glossy-black", "glossy-black", false, fixed(GLOSSY_EXPOSURE_US), &targets_scene),
        (material, name.as_str(), true, OrAuto::Auto, scene),
    ] {
        let args = device(sample, scene);
        let mut opened = open(&args)?;
        let scan_args = ScanArgs {
            sample_name: label.into(),
            out: out.join(label),
            resume: true,
            force: false,
            rig: RigArgs {
                geometry: geometry_file.clone(),
                camera: None,
                camera_codes: CameraCodes::Native,
            },
            mirrors,
            exposure_us,
            exposures: Vec::new(),
            hdr,
            frame_timeout: 10.0,
            check_every: scan::DEFAULT_CHECK_EVERY,
            settle_ms: protocol::DEFAULT_SETTLE_MS,
            black_level: OrAuto::Fixed(0),
            light_margin_us: 0,
        };
        run_scan(&mut opened, &scan_args, label)?;
    }
    let scanned = started.elapsed().as_secs_f64();
    let calibration = out.join("calibration.json");
    let calibrate = |glossy: Option<&Path>| {
        super::build::calibrate_cmd(
            &out.join("checkerboard"),
            &out.join("diffuse-white"),
            glossy,
            &calibration,
            geometry_file.as_deref(),
            crate::build::calibrate::DEFAULT_WHITE_ALBEDO,
            8,
        )
    };
    match (calibrate(Some(&out.join("glossy-black"))), mirrors) {
        // A few mirrors may show too few highlights to place the source:
        // the nominal source positions then, said so.
        (Err(Failure(3, e)), Some(n)) => {
            eprintln!(
                "demo: {}; with only {n} mirrors, calibrating with the nominal source \
                 positions instead",
                super::message(&e)
            );
            calibrate(None)?;
        }
        (r, _) => r?,
    }
    let material_file = out.join(format!("{name}.material"));
    let input = super::build::ScanInputs {
        scan: out.join(&name),
        calibration: calibration.clone(),
        geometry: geometry_file.clone(),
        size: None,
        detail: super::build::Detail::AllViews,
        edge_pixels: super::build::EdgeArg::Precise,
        sample_height: crate::build::height::SampleHeight::Measure,
        sample_tilt: None,
        sample_sides: super::build::SidesArg::Auto,
    };
    let built = super::build::build_cmd(
        &input,
        &material_file,
        &crate::build::material::MaterialOptions::default(),
    )?;
    let sheet = out.join(format!("regions-{name}.png"));
    super::build::contact_sheet(&built.regions, &sheet)?;
    // The preview's lower row is the simulator's ground truth, rendered
    // here for the picture only: the material above never saw it.
    let sample = hil_sim::materials::Sample::small(
        hil_sim::materials::lookup(material)
            .map_err(|e| sim_failure(crate::simulator::SimError::Material(e)))?,
    );
    let truth = |q: &[scanner_formats::queries::Query]| hil_sim::truth::answer(&sample, q);
    let (view, off) = super::build::novel_view(&built.regions.view_dirs);
    let picture = out.join(format!("{name}-preview.png"));
    super::build::preview(&built.material, (view, off), Some(&truth), &picture)?;
    // PBR maps of the material's texel model, for other renderers (PNG:
    // what a person opens), and the same as a glTF asset for any viewer.
    if built.material.metadata().texel_model {
        let maps = out.join(format!("{name}-maps"));
        use super::build::ExportFormat;
        let png = ExportFormat::Set(crate::build::export::MapFormat::Png);
        super::build::export_cmd(&material_file, &maps, png)?;
        let glb = out.join(format!("{name}.glb"));
        super::build::export_cmd(&material_file, &glb, ExportFormat::Glb)?;
    }
    // Fig. 9: the material widened to the large piece the sample was cut
    // from, through direct images the simulator takes as a camera would.
    let large = out.join(format!("{name}-large.material"));
    let large_picture = out.join(format!("{name}-large-preview.png"));
    let enlarged = {
        let m = hil_sim::materials::lookup(material)
            .map_err(|e| sim_failure(crate::simulator::SimError::Material(e)))?;
        let setup = crate::simulator::SimSetup {
            bin,
            seed,
            geometry: match &geometry_file {
                Some(p) => Some(ScannerGeometry::load(p).map_err(|e| Failure(3, anyhow!(e)))?),
                None => None,
            },
            ..crate::simulator::SimSetup::new(material)
        };
        let nominal = setup.nominal().map_err(sim_failure)?;
        let sim = hil_sim::optics::OpticalSim::as_built(
            &nominal,
            hil_sim::materials::Sample::small(m.clone()),
            seed,
        );
        // Photographed in perspective as a camera on a tripod would, then
        // rectified into direct images by the piece's corners, found in each
        // photograph (the simulator's own corners are not read).
        let photos = out.join(format!("{name}-photographs"));
        let direct = out.join(format!("{name}-direct"));
        let scale = hil_sim::direct::mirror_view_scale(&nominal);
        std::fs::create_dir_all(&direct)
            .map_err(|e| Failure(4, anyhow!("{}: {e}", direct.display())))?;
        // On the black holder first; a piece that does not stand out of it
        // (as dark as the holder, or a glossy one sending the light away)
        // is photographed again on a white card, as a photographer would
        // lay it (what `scanner rectify` advises). One found on neither
        // (a texture as fine as the photographs' pixels, half of it darker
        // and half brighter than either) would have its corners marked by
        // hand: the demo says so and ends without the enlargement.
        let at =
            DemoPhotos { sim: &sim, nominal: &nominal, scale, photos: &photos, direct: &direct };
        let mut lens = crate::build::lens::LensChoice::Estimate;
        let mut shots = None;
        for background in [hil_sim::optics::HOLDER_ALBEDO, hil_sim::optics::LIGHT_BACKGROUND_ALBEDO]
        {
            match at.take(&m, background, &mut lens)? {
                Ok(taken) => {
                    shots = Some(taken);
                    break;
                }
                Err(e) if background == hil_sim::optics::HOLDER_ALBEDO => println!(
                    "{e:#}\n→ the piece photographed again on a white card (albedo {})",
                    hil_sim::optics::LIGHT_BACKGROUND_ALBEDO
                ),
                Err(e) => println!(
                    "{e:#}\n→ the piece's corners found on neither the black holder nor a white \
                     card: no enlargement (mark them by hand: scanner rectify --corners, \
                     docs/direct-images.md)"
                ),
            }
        }
        if let Some(shots) = &shots {
            let manifest = shots.manifest();
            crate::fsutil::write_atomic(
                &direct.join(scanner_formats::direct::MANIFEST),
                manifest.to_toml().as_bytes(),
            )
            .map_err(|e| Failure(4, anyhow!("{}: {e}", direct.display())))?;
            let opts = crate::build::enlarge::EnlargeOptions::DEFAULT;
            super::build::enlarge_cmd(&material_file, &direct, &large, &opts)?;
            let enlarged =
                scanner_shading::Material::open(&large).map_err(|e| Failure(4, anyhow!(e)))?;
            let piece = hil_sim::materials::Sample::large(m);
            let truth = |q: &[scanner_formats::queries::Query]| hil_sim::truth::answer(&piece, q);
            super::build::preview(&enlarged, (view, off), Some(&truth), &large_picture)?;
        }
        shots.is_some()
    };
    let (theta, phi) = super::build::angles(view);
    println!(
        "demo: four scans in {scanned:.1} s, calibration and material in {:.1} s under {}\n\
         look at {}: the material over the sample (top) and the simulator's ground truth \
         (bottom), seen from θ {theta:.0}°, φ {phi:.0}° ({off:.1}° from the nearest mirror), lit from \
         (θ, φ) = {}{}",
        started.elapsed().as_secs_f64() - scanned,
        out.display(),
        picture.display(),
        super::build::PREVIEW_LIGHTS
            .iter()
            .map(|(t, p)| format!("({t:.0}°, {p:.0}°)"))
            .collect::<Vec<_>>()
            .join(", "),
        if enlarged {
            format!(
                ";\nand at {}: the material enlarged to the large piece the sample was cut from \
                 (photographed in perspective through a lens in {name}-photographs, rectified into \
                 the direct images of {name}-direct by the corners found in each and the lens' \
                 distortion found on the white card: {name}-photographs/photo-0-corners.png), \
                 over the same truth",
                large_picture.display()
            )
        } else {
            String::new()
        },
    );
    Ok(())
}

/// Where the demo photographs its large piece and rectifies the
/// photographs into direct images.
#[cfg(feature = "sim")]
struct DemoPhotos<'a> {
    sim: &'a hil_sim::optics::OpticalSim,
    nominal: &'a ScannerGeometry,
    scale: f64,
    photos: &'a Path,
    direct: &'a Path,
}

#[cfg(feature = "sim")]
impl DemoPhotos<'_> {
    /// Photographs of `m`'s large piece on a background of albedo
    /// `background`, rectified by the corners found in each: the set, or
    /// why a photograph's corners were not found (`Ok(Err(_))`). The lens
    /// is estimated on the white card's clean sides first (a textured
    /// piece's own edges shift with its texture: docs/direct-images.md,
    /// "Lens distortion") unless `lens` knows it already (the white card
    /// lies on the black holder whatever the piece's background), then
    /// every photograph of the piece goes through it.
    fn take(
        &self,
        m: &std::sync::Arc<dyn hil_sim::materials::Material>,
        background: f64,
        lens: &mut crate::build::lens::LensChoice,
    ) -> Result<Result<hil_sim::direct::Photographs, anyhow::Error>, Failure> {
        use crate::build::lens::LensChoice;
        let setup = hil_sim::direct::PhotoSetup {
            distance_mm: hil_sim::direct::PHOTO_DISTANCE_MM,
            distortion: [DEMO_LENS_K1, 0.0],
            background_albedo: background,
        };
        let shots = hil_sim::direct::write_photographs(
            self.sim,
            self.nominal,
            m.clone(),
            4,
            self.scale,
            setup,
            self.photos,
        )
        .map_err(|e| Failure(4, anyhow!(e)))?;
        let outline = self.photos.join("photo-0-corners.png");
        let white = (*lens == LensChoice::Estimate).then_some(&shots.white);
        for ph in white.into_iter().chain(&shots.photo) {
            let rectified = super::build::rectify_cmd(
                &self.photos.join(&ph.file),
                crate::build::rectify::Corners::Auto(crate::build::corners::Origin::BottomLeft),
                *lens,
                [shots.size_mm; 2],
                Some(self.scale),
                super::build::RectifyOutputs {
                    picture: &self.direct.join(&ph.file),
                    show: (ph.file == shots.photo[0].file).then_some(outline.as_path()),
                },
            );
            match rectified {
                Ok(used) => *lens = LensChoice::Known(used),
                // The piece not found (the white card, whose failure is
                // not the piece's background's, stays an error).
                Err(Failure(3, e)) if ph.mirror.is_some() => return Ok(Err(e)),
                Err(e) => return Err(e),
            }
        }
        Ok(Ok(shots))
    }
}

/// The files `scanner sim`'s camera writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum FrameFormat {
    /// OpenEXR, 32-bit float.
    Exr,
    /// 16-bit PNG.
    Png,
    /// 16-bit TIFF.
    Tiff,
}

/// `scanner sim` without the simulator: refused.
#[cfg(not(feature = "sim"))]
pub fn sim(
    _: &DeviceArgs,
    _: f64,
    _: &Path,
    _: FrameFormat,
    _: CameraCodes,
    _: Option<&Path>,
) -> Result<(), Failure> {
    Err(no_simulator())
}

/// `scanner sim`: serve the simulated scanner on a pty until Ctrl-C.
#[cfg(feature = "sim")]
pub fn sim(
    args: &DeviceArgs,
    speed: f64,
    frames: &Path,
    format: FrameFormat,
    codes: CameraCodes,
    link: Option<&Path>,
) -> Result<(), Failure> {
    use hil_sim::camera::FrameFiles;
    if !(speed > 0.0 && speed <= 4.0) {
        return Err(Failure(2, anyhow!("--speed must be in (0, 4]")));
    }
    let files = match format {
        FrameFormat::Exr if codes != CameraCodes::Native => {
            return Err(Failure(2, anyhow!("--frame-codes is for PNG and TIFF frames")));
        }
        FrameFormat::Exr => FrameFiles::Exr,
        FrameFormat::Png => FrameFiles::Png(codes.into()),
        FrameFormat::Tiff => FrameFiles::Tiff(codes.into()),
    };
    let mut setup = args.sim_setup()?;
    if let Some(link) = link {
        setup.port = hil_sim::Port::Usb(Some(link.to_path_buf()));
    }
    let server = setup.serve(speed, frames.to_path_buf(), files).map_err(sim_failure)?;
    if setup.board_axes.is_some() {
        // A board to commission: the moves are to be measured.
        server.print_where_axes_stop();
    }
    // The scanner's nominal geometry (binning included) for the host.
    let geometry_file = frames.join("geometry.toml");
    let nominal = setup.nominal().map_err(sim_failure)?;
    crate::fsutil::write_atomic(&geometry_file, nominal.to_toml().as_bytes())
        .map_err(|e| Failure(4, anyhow!("{}: {e}", geometry_file.display())))?;
    println!("{}", server.path());
    use std::io::Write;
    let _ = std::io::stdout().flush();
    eprintln!(
        "scanner sim: {} on {}, frames into {} (seed {}, binning {}); Ctrl-C stops it\n  \
         e.g. scanner scan --device {} --camera folder:{} --geometry {} --sample-name S --out DIR",
        setup.material,
        server.path(),
        frames.display(),
        setup.seed,
        setup.bin,
        server.path(),
        frames.display(),
        geometry_file.display()
    );
    loop {
        std::thread::park();
    }
}
