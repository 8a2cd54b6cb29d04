//! Scan capture: the device's mirror table from the nominal geometry, then
//! one capture step per mirror, each frame stored as OpenEXR and recorded in
//! a manifest written atomically after every frame (`docs/scan-format.md`).
//!
//! Faults survived: link noise and disconnects (the link retransmits and
//! reconnects), a device reset (re-home, restore the mirror table, carry on
//! from the last completed frame), latched link-timeout/watchdog faults
//! (cleared), a camera that misses a frame (the step is taken again). Faults
//! a person must look at (emergency stop, driver fault) end the scan with
//! its own exit code. After the process is killed at any moment, `resume`
//! keeps every frame whose file matches its checksum and takes the rest.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use protocol::{
    Axis, AxisConfig, AxisSet, CaptureStep, DeviceState, Event, FaultFlags, MirrorPosition,
    MotionOutcome, MoveMode, Reply, Request, TimedCaptureStep, TriggerFired,
};
use scanner_geometry::{AxisValues, GeometryError, ScannerGeometry};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::camera::{Camera, CameraError};
use crate::exrio;
use crate::fsutil::write_atomic;
use crate::link::{Device, LinkError};

/// Manifest format name.
pub const MANIFEST_FORMAT: &str = "material-scanner/scan";
/// Manifest version.
pub const MANIFEST_VERSION: u32 = 1;
/// Manifest file name in a scan directory.
pub const MANIFEST_FILE: &str = "manifest.json";
/// The manifest before the last update (rotated atomically on every save):
/// `--resume` recovers from it when `manifest.json` is damaged.
pub const PREVIOUS_MANIFEST_FILE: &str = "manifest.json.prev";
/// Lock file in a scan directory: a scan holds an exclusive lock on it
/// (`flock`) while it runs.
pub const LOCK_FILE: &str = ".lock";

/// Why a scan stopped. Each kind has its own process exit code.
#[derive(Debug, thiserror::Error)]
pub enum ScanError {
    /// No device, or it went away and did not come back.
    #[error("{0}")]
    NoDevice(String),
    /// The firmware speaks another protocol version.
    #[error("{0}")]
    Incompatible(String),
    /// A fault on the device that a person must clear.
    #[error("device fault: {0}")]
    DeviceFault(String),
    /// The camera delivered no frame, repeatedly.
    #[error("camera timeout at mirror {mirror} after {attempts} attempts: {detail}")]
    CameraTimeout {
        /// Mirror.
        mirror: usize,
        /// Attempts.
        attempts: u32,
        /// Last error.
        detail: String,
    },
    /// No space left on the output device.
    #[error("disk full writing {0}")]
    DiskFull(String),
    /// Other output trouble.
    #[error("cannot write {0}")]
    Io(String),
    /// The directory holds a scan and `--resume` was not given, or holds a
    /// different scan.
    #[error("{0}")]
    Conflict(String),
    /// Anything else the link reported.
    #[error("link: {0}")]
    Link(LinkError),
    /// Stopped on request (Ctrl-C) after the frame in progress.
    #[error("interrupted: {kept} of {total} frames kept in {}", dir.display())]
    Interrupted {
        /// Frames stored and recorded.
        kept: usize,
        /// Frames the scan is for.
        total: usize,
        /// The scan directory.
        dir: PathBuf,
    },
}

impl ScanError {
    /// Process exit code (see the `scanner` binary's documentation).
    pub fn exit_code(&self) -> u8 {
        match self {
            ScanError::NoDevice(_) => 5,
            ScanError::Incompatible(_) => 6,
            ScanError::DeviceFault(_) => 7,
            ScanError::CameraTimeout { .. } => 8,
            ScanError::DiskFull(_) => 9,
            ScanError::Io(_) => 4,
            ScanError::Conflict(_) => 3,
            ScanError::Link(_) => 1,
            ScanError::Interrupted { .. } => 130,
        }
    }
}

impl From<LinkError> for ScanError {
    fn from(e: LinkError) -> ScanError {
        match e {
            LinkError::NoDevice(_) | LinkError::Timeout { .. } => {
                ScanError::NoDevice(e.to_string())
            }
            LinkError::Incompatible { .. } => ScanError::Incompatible(e.to_string()),
            e => ScanError::Link(e),
        }
    }
}

fn io_error(path: &Path, e: std::io::Error) -> ScanError {
    // ENOSPC / EDQUOT: the disk is full.
    if matches!(e.raw_os_error(), Some(28) | Some(122))
        || e.kind() == std::io::ErrorKind::StorageFull
    {
        ScanError::DiskFull(format!("{}: {e}", path.display()))
    } else {
        ScanError::Io(format!("{}: {e}", path.display()))
    }
}

/// The device a scan was taken with.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct DeviceRecord {
    /// Unique id (hex of the 12 bytes).
    pub device_id: String,
    /// Firmware version.
    pub firmware: String,
    /// Protocol version.
    pub protocol: String,
    /// Board id.
    pub board: u16,
}

/// What a scan is: a resumed scan must match it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScanSettings {
    /// Sample name.
    pub sample_name: String,
    /// SHA-256 of the nominal geometry file.
    pub geometry_sha256: String,
    /// Mirrors scanned: 0 … count − 1.
    pub mirror_count: usize,
    /// Exposure, µs.
    pub exposure_us: u32,
    /// Settle time after moving, ms.
    pub settle_ms: u16,
    /// Light duty, per mille.
    pub light_duty_permille: u16,
    /// HDR: the exposures taken per mirror, µs (empty: one exposure of
    /// `exposure_us`). The stored frame is their merge, in units of the
    /// longest.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub bracket_us: Vec<u32>,
    /// A simulated scanner: what it simulates (material, seed, binning), so
    /// a resume on another simulated scanner is refused.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub simulator: Option<String>,
    /// Auto exposure: `exposure_us` and `bracket_us` are chosen by
    /// metering (docs/scan-format.md, "Auto exposure").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub auto_exposure: Option<AutoExposure>,
    /// What metering measured (auto exposure, once metered).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub metering: Option<crate::exposure::Metering>,
    /// The dark frame the scan took for hot pixels (absent: none taken
    /// yet, or it could not be).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dark: Option<DarkRecord>,
    /// The black level (ADC codes) the camera's frames carried and the
    /// scan subtracted from every value as it arrived (`--black-level`);
    /// the stored frames are without it.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub black_level_codes: u32,
    /// `--black-level auto`: the level is the median of a frame taken with
    /// the light off at the scan's start (docs/scan-format.md).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub black_level_auto: Option<AutoBlackLevel>,
    /// How the camera's integer frame files held the sensor's codes
    /// (`--camera-codes`; absent: native).
    #[serde(default, skip_serializing_if = "is_native")]
    pub camera_codes: scanner_geometry::IntegerCodes,
    /// The light went on this long before each trigger pulse and off as
    /// long after it, µs (`--light-margin-us`; absent: 0, the light on
    /// exactly during the pulse).
    #[serde(default, skip_serializing_if = "is_zero_u16")]
    pub light_margin_us: u16,
}

fn is_zero_u16(v: &u16) -> bool {
    *v == 0
}

fn is_native(c: &scanner_geometry::IntegerCodes) -> bool {
    *c == scanner_geometry::IntegerCodes::Native
}

/// How `--black-level auto` measured the black level.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct AutoBlackLevel {
    /// The exposure of the frame it was measured in, µs of the device;
    /// absent until it is measured (a scan interrupted before measures it
    /// on resuming).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub exposure_us: Option<u32>,
    /// That frame's exposure as the camera's strobe showed it; absent
    /// when the strobe is not watched.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub strobe: Option<crate::strobe::Exposure>,
}

fn is_zero(v: &u32) -> bool {
    *v == 0
}

/// A scan's dark frame: the light off, a bare trigger of the longest
/// exposure the scan takes (docs/scan-format.md, "Sensor defects").
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct DarkRecord {
    /// Its exposure, µs of the device.
    pub exposure_us: u32,
    /// The hot (and stuck) pixels it showed.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub defects: Vec<crate::defects::PixelDefect>,
    /// Its exposure as the camera's strobe showed it; absent when the
    /// strobe is not watched.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub strobe: Option<crate::strobe::Exposure>,
}

/// What auto exposure chooses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AutoExposure {
    /// One exposure per mirror.
    Single,
    /// An HDR bracket per mirror.
    Hdr,
}

impl PositionCheck {
    /// A failed check of `kind` (nothing measured yet) over no frames yet.
    fn failed(kind: CheckKind) -> PositionCheck {
        PositionCheck { kind, error_steps: [None; 3], passed: false, mirrors: Vec::new() }
    }
}

impl ScanSettings {
    /// The sensor's defective pixels the scan found and replaces in its
    /// frames: its metering's and its dark frame's.
    pub fn defects(&self) -> Vec<crate::defects::PixelDefect> {
        crate::defects::union(
            self.metering.as_ref().map_or(&[][..], |m| &m.defects),
            self.dark.as_ref().map_or(&[][..], |d| &d.defects),
        )
    }

    /// The settings that differ from `other`, in words ("exposure_us 50000
    /// here, 20000 there").
    pub fn differences(&self, other: &ScanSettings) -> Vec<String> {
        let mut out = Vec::new();
        let mut field = |name: &str, a: String, b: String| {
            if a != b {
                out.push(format!("{name} {a} (the directory's) vs {b} (this run's)"));
            }
        };
        field("sample name", format!("{:?}", self.sample_name), format!("{:?}", other.sample_name));
        field("geometry", self.geometry_sha256.clone(), other.geometry_sha256.clone());
        field("mirrors", self.mirror_count.to_string(), other.mirror_count.to_string());
        let auto = |a: Option<AutoExposure>| match a {
            None => "fixed".to_string(),
            Some(AutoExposure::Single) => "auto, one exposure".to_string(),
            Some(AutoExposure::Hdr) => "auto, HDR".to_string(),
        };
        field("exposure choice", auto(self.auto_exposure), auto(other.auto_exposure));
        // Auto exposure: the directory's metered exposures are the scan's.
        let metered = self.auto_exposure.is_some() && other.auto_exposure.is_some();
        if !metered {
            field(
                "exposure",
                format!("{} µs", self.exposure_us),
                format!("{} µs", other.exposure_us),
            );
        }
        field("settle", format!("{} ms", self.settle_ms), format!("{} ms", other.settle_ms));
        field(
            "light duty",
            format!("{} ‰", self.light_duty_permille),
            format!("{} ‰", other.light_duty_permille),
        );
        if !metered {
            field(
                "HDR bracket",
                format!("{:?} µs", self.bracket_us),
                format!("{:?} µs", other.bracket_us),
            );
        }
        // Auto: the directory's measured level is the scan's.
        let level = |s: &ScanSettings| match s.black_level_auto {
            Some(_) => "auto".to_string(),
            None => format!("{} codes", s.black_level_codes),
        };
        field("black level", level(self), level(other));
        field("camera codes", self.camera_codes.name().into(), other.camera_codes.name().into());
        field(
            "light margin",
            format!("{} µs", self.light_margin_us),
            format!("{} µs", other.light_margin_us),
        );
        let sim = |s: &Option<String>| s.clone().unwrap_or_else(|| "a real scanner".into());
        field("scanner", sim(&self.simulator), sim(&other.simulator));
        out
    }
}

/// One stored frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameRecord {
    /// Mirror lit.
    pub mirror: usize,
    /// File, relative to the scan directory.
    pub file: String,
    /// SHA-256 of the file.
    pub sha256: String,
    /// Width, px.
    pub width: u32,
    /// Height, px.
    pub height: u32,
    /// The device's trigger sequence number.
    pub trigger_seq: u32,
    /// Device time of the trigger's rising edge, µs since its boot.
    pub device_timestamp_us: u64,
    /// Exposure, µs.
    pub exposure_us: u32,
    /// Axis positions at the trigger, steps (disk, track, tilt).
    pub axis_steps: [i32; 3],
    /// The same in degrees, mm, degrees.
    pub axis_units: [f64; 3],
    /// Whether a position check after this frame found every axis where its
    /// count said (no steps lost before the frame). Manifests written before
    /// position checks existed read as verified.
    #[serde(default = "verified_by_default")]
    pub verified: bool,
    /// HDR: the exposures merged into this frame, µs, ascending, when they
    /// are not the scan's `bracket_us` (auto exposure adds shorter ones at a
    /// mirror whose highlights the bracket clipped); empty otherwise.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub bracket_us: Vec<u32>,
    /// The light's duty during this exposure, ‰, when it is not the
    /// scan's: an exposure shorter than the device's shortest, taken as
    /// that with the light dimmed ([`crate::exposure::realise`]);
    /// `exposure_us` is then the equivalent at the scan's duty.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub light_duty_permille: Option<u16>,
    /// The exposure as the camera's strobe showed it (a device watching
    /// it, protocol 1.4); an HDR merge's is its reference exposure's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub strobe: Option<crate::strobe::Exposure>,
    /// HDR: how each exposure merged into this frame agreed with the next
    /// longer one ([`crate::hdr::exposure_ratios`]; those with too few
    /// values measured well by both are left out); empty otherwise.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub exposure_ratios: Vec<crate::hdr::ExposureRatio>,
}

/// An HDR exposure whose light per µs differs from the next longer one's
/// by more than this (relative) is reported: the merge assumes none.
pub const EXPOSURE_RATIO_TOLERANCE: f64 = 0.03;

fn verified_by_default() -> bool {
    true
}

/// How a position check was made (`checks[].kind` in the manifest).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CheckKind {
    /// Every axis homed and its count compared at its switch.
    Homing,
    /// The firmware caught a moving axis off its count at a switch edge.
    Index,
    /// The device lost its homing (a reset, a fault): nothing to compare.
    HomingLost,
}

/// Whether a count error (steps) is within the switches' tolerance.
pub(crate) fn within_tolerance(error_steps: i32) -> bool {
    error_steps.unsigned_abs() <= protocol::POSITION_TOLERANCE_STEPS as u32
}

/// A comparison of the axes' step counts with their switches during a scan.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct PositionCheck {
    /// How: `homing` (the scan homed every axis and compared the counts at
    /// the switches), `index` (the firmware caught a moving axis' count off
    /// at its switch edge), `homing-lost` (the device lost its homing — a
    /// reset or a fault — so the frames since the last check cannot be
    /// verified).
    pub kind: CheckKind,
    /// Count minus switch per axis (disk, track, tilt), steps, where measured.
    pub error_steps: [Option<i32>; 3],
    /// Every measured error within `protocol::POSITION_TOLERANCE_STEPS` and
    /// every axis measured.
    pub passed: bool,
    /// The frames taken since the previous passed check: verified by this
    /// one if it passed, taken again if not.
    pub mirrors: Vec<usize>,
}

/// The scan directory's manifest.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// [`MANIFEST_FORMAT`].
    pub format: String,
    /// [`MANIFEST_VERSION`].
    pub version: u32,
    /// What is being scanned, how.
    pub settings: ScanSettings,
    /// The device.
    pub device: DeviceRecord,
    /// The camera.
    pub camera: String,
    /// Frames stored so far, by mirror.
    pub frames: Vec<FrameRecord>,
    /// Whether every mirror has its frame.
    pub complete: bool,
    /// HDR: single exposures of mirrors whose merged frame is not stored
    /// yet (`frames/raw/`), kept so an interrupted scan resumes per
    /// exposure; removed once the merge is stored.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub exposures: Vec<FrameRecord>,
    /// Position checks, in order.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub checks: Vec<PositionCheck>,
}

impl Manifest {
    /// Read a scan directory's manifest. Every failure is exit 3: no scan
    /// there, or a damaged manifest.
    pub fn load(dir: &Path) -> Result<Manifest, ScanError> {
        Manifest::load_hashed(dir).map(|(m, _)| m)
    }

    /// [`Manifest::load`], with the SHA-256 (hex) of the very bytes parsed.
    pub fn load_hashed(dir: &Path) -> Result<(Manifest, String), ScanError> {
        let path = dir.join(MANIFEST_FILE);
        let parsed = Manifest::read_bytes(&path).and_then(|bytes| {
            let sha = sha256_hex(&bytes);
            Ok((Manifest::parse(&path, bytes)?, sha))
        });
        parsed.map_err(|e| match e {
            LoadError::Missing => {
                ScanError::Conflict(format!("no scan at {} (no {MANIFEST_FILE})", dir.display()))
            }
            LoadError::Damaged(why) => ScanError::Conflict(why),
        })
    }

    fn load_file(path: &Path) -> Result<Manifest, LoadError> {
        Manifest::parse(path, Manifest::read_bytes(path)?)
    }

    fn read_bytes(path: &Path) -> Result<Vec<u8>, LoadError> {
        match scanner_formats::input::read(path) {
            Ok(b) => Ok(b),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Err(LoadError::Missing),
            Err(e) if e.kind() == std::io::ErrorKind::NotADirectory => Err(LoadError::Missing),
            Err(e) => Err(LoadError::Damaged(format!("{}: cannot read: {e}", path.display()))),
        }
    }

    /// The manifest in `bytes`, read from `path` (named in errors).
    fn parse(path: &Path, bytes: Vec<u8>) -> Result<Manifest, LoadError> {
        let damaged =
            |why: String| LoadError::Damaged(format!("{}: damaged: {why}", path.display()));
        let text = String::from_utf8(bytes).map_err(|_| damaged("not UTF-8 text".into()))?;
        let m: Manifest = serde_json::from_str(&text)
            .map_err(|e| damaged(format!("not a scan manifest ({e})")))?;
        if m.format != MANIFEST_FORMAT || m.version != MANIFEST_VERSION {
            return Err(LoadError::Damaged(format!(
                "{}: {} version {} (this build reads {MANIFEST_FORMAT} {MANIFEST_VERSION})",
                path.display(),
                m.format,
                m.version
            )));
        }
        let n = m.settings.mirror_count;
        if !(1..=protocol::MAX_MIRRORS).contains(&n) {
            return Err(damaged(format!(
                "a scan of {n} mirrors (a device has 1…{})",
                protocol::MAX_MIRRORS
            )));
        }
        if let Some(f) = m.frames.iter().chain(&m.exposures).find(|f| f.mirror >= n) {
            return Err(damaged(format!(
                "it lists a frame of mirror {} in a scan of mirrors 0…{}",
                f.mirror,
                n.saturating_sub(1)
            )));
        }
        if let Some(f) = m.frames.iter().chain(&m.exposures).find(|f| !safe_relative(&f.file)) {
            return Err(damaged(format!("frame file {:?} is outside frames/", f.file)));
        }
        // One file per entry: two entries on one file would read one
        // mirror's light as another's.
        let mut files: Vec<&str> = m.frames.iter().chain(&m.exposures).map(|f| &*f.file).collect();
        files.sort_unstable();
        if let Some(w) = files.windows(2).find(|w| w[0] == w[1]) {
            return Err(damaged(format!("frame file {:?} is listed twice", w[0])));
        }
        // Brackets are exposures, µs, ascending (docs/scan-format.md).
        let brackets = std::iter::once((None, &m.settings.bracket_us))
            .chain(m.frames.iter().map(|f| (Some(f.mirror), &f.bracket_us)));
        for (mirror, b) in brackets {
            if b.first() == Some(&0) || b.windows(2).any(|w| w[0] >= w[1]) {
                let whose = mirror.map_or("the scan's".to_string(), |l| format!("mirror {l}'s"));
                return Err(damaged(format!(
                    "{whose} bracket {b:?} µs is not of ascending exposures above 0"
                )));
            }
        }
        Ok(m)
    }

    /// Store atomically, after rotating the current manifest to
    /// [`PREVIOUS_MANIFEST_FILE`] (a hard link renamed into place: atomic,
    /// no copy; a copy where the file system has no hard links).
    fn save(&self, dir: &Path) -> Result<(), ScanError> {
        let path = dir.join(MANIFEST_FILE);
        let prev = dir.join(PREVIOUS_MANIFEST_FILE);
        if path.is_file() {
            let tmp = dir.join(format!(".tmp-prev-{}", std::process::id()));
            let _ = std::fs::remove_file(&tmp);
            let rotated = match std::fs::hard_link(&path, &tmp) {
                Ok(()) => std::fs::rename(&tmp, &prev),
                Err(_) => scanner_formats::input::read(&path).and_then(|b| write_atomic(&prev, &b)),
            };
            rotated.and_then(|()| crate::fsutil::sync_dir(dir)).map_err(|e| io_error(&prev, e))?;
        }
        let mut text = serde_json::to_string_pretty(self).expect("manifest serialises");
        text.push('\n');
        write_atomic(&path, text.as_bytes()).map_err(|e| io_error(&path, e))
    }
}

/// A directory with files but neither manifest is someone else's: refused
/// unless `--force`.
fn refuse_foreign(opts: &ScanOptions) -> Result<(), ScanError> {
    let dir = &opts.out;
    if opts.force
        || dir.join(MANIFEST_FILE).exists()
        || (opts.resume && dir.join(PREVIOUS_MANIFEST_FILE).exists())
    {
        return Ok(());
    }
    let Ok(entries) = std::fs::read_dir(dir) else { return Ok(()) };
    let foreign = entries
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .find(|n| n != LOCK_FILE && !n.starts_with(".tmp-"));
    match foreign {
        Some(name) => Err(ScanError::Conflict(format!(
            "{} is not empty ({name} …) and holds no scan (no {MANIFEST_FILE}); choose an \
             empty or new --out, or pass --force to scan into it anyway",
            dir.display()
        ))),
        None => Ok(()),
    }
}

/// Why a manifest file could not be read.
enum LoadError {
    /// No such file (or no such directory).
    Missing,
    /// There, but not a manifest this build reads.
    Damaged(String),
}

/// A frame path a manifest may name: relative, under `frames/`, no `..`.
fn safe_relative(file: &str) -> bool {
    let p = Path::new(file);
    p.starts_with("frames") && p.components().all(|c| matches!(c, std::path::Component::Normal(_)))
}

/// How to scan.
#[derive(Debug, Clone)]
pub struct ScanOptions {
    /// Sample name.
    pub sample_name: String,
    /// Output directory.
    pub out: PathBuf,
    /// Continue a scan in `out`.
    pub resume: bool,
    /// Scan only mirrors 0 … n − 1 (default: all).
    pub mirrors: Option<usize>,
    /// Exposure, µs.
    pub exposure_us: u32,
    /// Settle, ms.
    pub settle_ms: u16,
    /// Light duty, per mille.
    pub light_duty_permille: u16,
    /// Wait this long for a frame after the trigger.
    pub frame_timeout: Duration,
    /// Attempts per mirror when the camera misses the frame.
    pub attempts: u32,
    /// HDR bracket, µs (empty: one exposure of `exposure_us`).
    pub bracket_us: Vec<u32>,
    /// Auto exposure: meter first (at `exposure_us`), then choose the
    /// exposure or bracket ([`crate::exposure`]); `bracket_us` is ignored.
    pub auto_exposure: Option<AutoExposure>,
    /// Check the axes against their switches after every this many frames
    /// (0: only once every frame is taken). A failed check retakes the
    /// frames since the last passed one.
    pub check_every: usize,
    /// Scan into a non-empty directory that holds no scan.
    pub force: bool,
    /// What the simulated scanner simulates (recorded in the settings).
    pub simulator: Option<String>,
    /// The camera's frames carry this black level (ADC codes): subtract it
    /// from every value ([`crate::camera::ScanCamera`]).
    pub black_level_codes: u32,
    /// Measure the black level (`black_level_codes` is then ignored) in a
    /// frame with the light off at the scan's start.
    pub black_level_auto: bool,
    /// Light on this long before each trigger pulse and off as long after
    /// it, µs (0 ..= `protocol::MAX_LIGHT_MARGIN_US`; firmware of protocol
    /// 1.3): for a camera that exposes later than its trigger's edges.
    pub light_margin_us: u16,
    /// Set (e.g. by Ctrl-C) to stop after the frame in progress, keeping
    /// every frame taken.
    pub interrupt: Option<std::sync::Arc<std::sync::atomic::AtomicBool>>,
}

impl ScanOptions {
    /// Defaults of spec/hardware.md for `sample_name` into `out`.
    pub fn new(sample_name: &str, out: &Path) -> ScanOptions {
        ScanOptions {
            sample_name: sample_name.to_string(),
            out: out.to_path_buf(),
            resume: false,
            mirrors: None,
            exposure_us: protocol::DEFAULT_EXPOSURE_US,
            settle_ms: protocol::DEFAULT_SETTLE_MS,
            light_duty_permille: protocol::FULL_DUTY_PERMILLE,
            frame_timeout: Duration::from_secs(10),
            attempts: 3,
            bracket_us: Vec::new(),
            auto_exposure: None,
            check_every: DEFAULT_CHECK_EVERY,
            force: false,
            simulator: None,
            black_level_codes: 0,
            black_level_auto: false,
            light_margin_us: 0,
            interrupt: None,
        }
    }
}

/// Default frames between position checks.
pub const DEFAULT_CHECK_EVERY: usize = 10;

/// Failed position checks in a row before the scan gives up (exit 7).
const MAX_FAILED_CHECKS: usize = 3;

/// Where the time went.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ScanTimings {
    /// Talking to the device and waiting for it (moves, settle, exposure).
    pub link: Duration,
    /// Waiting for frames (the simulator renders them here).
    pub camera: Duration,
    /// Encoding and writing frames and manifests.
    pub disk: Duration,
    /// The whole scan.
    pub total: Duration,
}

/// What a scan did.
#[derive(Debug, Clone, Default)]
pub struct ScanReport {
    /// Frames taken now.
    pub captured: usize,
    /// Frames kept from before (resume).
    pub kept: usize,
    /// Capture steps taken again (missed frames, resets).
    pub retakes: usize,
    /// Device resets survived.
    pub resets: usize,
    /// Position checks made.
    pub checks: usize,
    /// The exposures taken now as the camera's strobe showed them (none
    /// when the device does not watch it).
    pub strobe: crate::strobe::Summary,
    /// Time split.
    pub timings: ScanTimings,
}

/// Progress callbacks.
pub trait ScanProgress {
    /// The scan will take `total` frames, `done` of them already there.
    fn start(&mut self, _total: usize, _done: usize) {}
    /// Frame of `mirror` stored.
    fn frame(&mut self, _mirror: usize) {}
    /// Something worth telling the user.
    fn note(&mut self, _message: &str) {}
    /// Stored frames of `mirrors` will be taken again.
    fn retaking(&mut self, _mirrors: &[usize]) {}
}

/// No progress output.
#[derive(Debug)]
pub struct Quiet;
impl ScanProgress for Quiet {}

/// The axis configurations of the device.
pub fn axis_configs(dev: &mut Device) -> Result<[AxisConfig; 3], ScanError> {
    let mut out = Vec::new();
    for axis in Axis::ALL {
        match dev.request(Request::GetAxisConfig { axis })? {
            Reply::AxisConfig { config, .. } => out.push(config),
            reply => return Err(LinkError::Unexpected { request: "GetAxisConfig", reply }.into()),
        }
    }
    Ok([out[0], out[1], out[2]])
}

/// The device's mirror table as it holds it: an entry per mirror up to its
/// count, `None` where unset.
pub fn mirror_entries(dev: &mut Device) -> Result<Vec<Option<MirrorPosition>>, ScanError> {
    (0..dev.info().mirror_count).map(|mirror| mirror_entry(dev, mirror)).collect()
}

/// The device's entry for `mirror` (`None`: unset, or beyond its count).
pub fn mirror_entry(dev: &mut Device, mirror: u8) -> Result<Option<MirrorPosition>, ScanError> {
    match dev.request(Request::GetMirror { mirror })? {
        Reply::Mirror { position, .. } => Ok(position),
        reply => Err(LinkError::Unexpected { request: "GetMirror", reply }.into()),
    }
}

/// What [`set_axis_configs`] did.
#[derive(Debug, Clone, Default)]
pub struct AxesSet {
    /// The axes whose configuration was written (the device un-homed them).
    pub changed: Vec<Axis>,
    /// The device's mirror-table entries (set ones).
    pub mirrors: usize,
    /// Entries whose steps changed and were written: the same axis
    /// positions in the new drives' steps.
    pub mirrors_moved: usize,
    /// Entries the new travel cannot reach, left unset (`MirrorNotSet`
    /// for a `GoToMirror`): mirror and why.
    pub unreachable: Vec<(usize, scanner_geometry::StepsError)>,
    /// Saved to the device's flash.
    pub saved: bool,
}

/// Make the device's axis configurations `axes` (protocol axis order;
/// `scanner axes --set`), `current` being its own as [`axis_configs`] read
/// them: the axes whose configuration differs are written (the device
/// un-homes them), and the whole saved to flash when anything changed and
/// the device has persistent storage.
///
/// The device's mirror table keeps its axis *positions*: an entry's steps
/// under `current` are taken to degrees and mm and back to steps under
/// `axes` (a step of the old drive at most from what `scanner setup` would
/// write for the same design). Entries outside the new travel are left
/// unset, so that no stored step count means another place than it did,
/// even when the link is lost half-way.
pub fn set_axis_configs(
    dev: &mut Device,
    current: &[AxisConfig; 3],
    axes: &[AxisConfig; 3],
) -> Result<AxesSet, ScanError> {
    let changed: Vec<Axis> =
        Axis::ALL.into_iter().filter(|a| current[a.index()] != axes[a.index()]).collect();
    if changed.is_empty() {
        return Ok(AxesSet::default());
    }
    // The device refuses a configuration while anything moves: refused here
    // before the table is touched.
    let status = dev.status()?;
    if !matches!(status.state, DeviceState::Idle | DeviceState::Faulted)
        || status.axes.iter().any(|a| a.moving)
    {
        let error = protocol::DeviceError::Busy;
        return Err(LinkError::Refused { request: "SetAxisConfig", error }.into());
    }
    let count = dev.info().mirror_count;
    let table = mirror_entries(dev)?;
    let mut carried = Vec::new();
    let mut set = AxesSet { mirrors: table.iter().flatten().count(), ..AxesSet::default() };
    for (l, position) in table.iter().enumerate() {
        let Some(position) = position else { continue };
        match AxisValues::from_steps(position.steps.map(i64::from), current).to_steps(axes) {
            Ok(steps) => carried.push((l, steps != position.steps, MirrorPosition { steps })),
            Err(e) => set.unreachable.push((l, e)),
        }
    }
    // The table is emptied first and written again after the axes, so that
    // at no moment (a link lost half-way included) does an entry hold steps
    // of the other configuration: an interrupted change leaves entries
    // unset, never wrong, and the flash the old, consistent pair.
    if count > 0 {
        dev.command(Request::SetMirrorCount { count: 0 })?;
    }
    for &axis in &changed {
        dev.command(Request::SetAxisConfig { axis, config: axes[axis.index()] })?;
    }
    for &(l, moved, position) in &carried {
        dev.command(Request::SetMirror { mirror: l as u8, position })?;
        set.mirrors_moved += usize::from(moved);
    }
    if count > 0 {
        // Unset entries (and the unreachable ones) up to the old count.
        dev.command(Request::SetMirrorCount { count })?;
    }
    if dev.info().capabilities.contains(protocol::Capabilities::PERSISTENT_CONFIG) {
        dev.command(Request::SaveConfig)?;
        set.saved = true;
    }
    set.changed = changed;
    Ok(set)
}

/// The mirror table of `geometry` for the device's axes (inverse kinematics).
pub fn mirror_table(
    geometry: &ScannerGeometry,
    axes: &[AxisConfig; 3],
) -> Result<Vec<MirrorPosition>, ScanError> {
    geometry.mirror_table(axes).map_err(|e: GeometryError| ScanError::Conflict(e.to_string()))
}

/// The device's mirror table after [`setup`].
#[derive(Debug, Clone)]
pub struct MirrorSetup {
    /// The device's axis configurations.
    pub axes: [AxisConfig; 3],
    /// The table, per mirror.
    pub table: Vec<MirrorPosition>,
    /// Entries that had to be written.
    pub written: usize,
}

/// Make the device's mirror table the geometry's (`scanner setup`): entries
/// that differ are written, the count set, and the table saved to flash when
/// the device has persistent storage.
pub fn setup(dev: &mut Device, geometry: &ScannerGeometry) -> Result<MirrorSetup, ScanError> {
    let axes = axis_configs(dev)?;
    let table = mirror_table(geometry, &axes)?;
    let mut written = 0;
    for (l, position) in table.iter().enumerate() {
        if mirror_entry(dev, l as u8)? != Some(*position) {
            dev.command(Request::SetMirror { mirror: l as u8, position: *position })?;
            written += 1;
        }
    }
    if dev.info().mirror_count as usize != table.len() || written > 0 {
        dev.command(Request::SetMirrorCount { count: table.len() as u8 })?;
        if dev.info().capabilities.contains(protocol::Capabilities::PERSISTENT_CONFIG) {
            dev.command(Request::SaveConfig)?;
        }
        // Refresh the handshake's copy of the count.
        dev.check_boot()?;
    }
    Ok(MirrorSetup { axes, table, written })
}

/// Faults the scan clears by itself: they record that the host or the
/// board went away, which the scan has just recovered from, or a homing
/// that [`prepare`] runs again.
const CLEARABLE: FaultFlags = FaultFlags(
    FaultFlags::LINK_TIMEOUT.0
        | FaultFlags::WATCHDOG_RESET.0
        | FaultFlags::HOMING_FAILED.0
        | FaultFlags::POSITION_LOST.0
        | FaultFlags::STORAGE_FAILED.0,
);

/// `faults` named, comma-separated.
pub(crate) fn fault_list(faults: FaultFlags) -> String {
    faults.names().collect::<Vec<_>>().join(", ")
}

/// All of `faults` named, if any of them needs a person (emergency stop,
/// driver fault, an unexpected home switch).
fn faults_needing_a_person(faults: FaultFlags) -> Option<String> {
    let serious = FaultFlags(faults.0 & !CLEARABLE.0);
    (!serious.is_empty()).then(|| fault_list(faults))
}

/// Bring the device to a state where capture steps run: faults that only
/// record a lost link or a reset cleared, mirror table in place, homed.
/// Returns the device's axis configurations.
pub fn prepare(
    dev: &mut Device,
    geometry: &ScannerGeometry,
    progress: &mut dyn ScanProgress,
) -> Result<Prepared, ScanError> {
    for _ in 0..4 {
        match prepare_once(dev, geometry, progress) {
            Err(ScanError::Link(LinkError::Reset { .. })) => {
                progress.note("device reset while preparing; again");
                continue;
            }
            other => return other,
        }
    }
    Err(ScanError::DeviceFault("the device keeps resetting".into()))
}

/// What [`prepare`] found and did.
#[derive(Debug, Clone, Copy)]
pub struct Prepared {
    /// The device's axis configurations.
    pub axes: [AxisConfig; 3],
    /// Some axis was not homed and was homed now: step counts from before
    /// cannot be checked any more.
    pub homed: bool,
}

fn prepare_once(
    dev: &mut Device,
    geometry: &ScannerGeometry,
    progress: &mut dyn ScanProgress,
) -> Result<Prepared, ScanError> {
    let mut status = dev.status()?;
    if !status.faults.is_empty() {
        if let Some(names) = faults_needing_a_person(status.faults) {
            return Err(ScanError::DeviceFault(names));
        }
        progress.note(&format!("clearing {}", fault_list(status.faults)));
        dev.command(Request::ClearFault)?;
        // A faulted device reports "faulted", not what its axes do: a
        // link timeout decelerates them, and they may still be moving.
        status = dev.status()?;
    }
    // A move the previous host left running (killed mid-step) must end.
    if matches!(status.state, DeviceState::Moving | DeviceState::Capturing | DeviceState::Homing) {
        dev.command(Request::Stop)?;
        wait_idle(dev, Duration::from_secs(30))?;
    }
    let mirrors = setup(dev, geometry)?;
    if mirrors.written > 0 {
        progress.note(&format!("wrote {} mirror table entries", mirrors.written));
    }
    let status = dev.status()?;
    let homed = status.axes.iter().any(|a| !a.homed);
    if homed {
        progress.note("homing");
        home_all(dev)?;
    }
    Ok(Prepared { axes: mirrors.axes, homed })
}

/// Home every axis and wait for the end; returns the events that came
/// meanwhile (position checks of axes that were homed already).
fn home_all(dev: &mut Device) -> Result<Vec<Event>, ScanError> {
    home_axes(dev, AxisSet::ALL)
}

/// One cycle of [`homing_repeatability`]: where the axes went, and each
/// homed axis' step count at its switch minus the switch's position.
#[derive(Debug, Clone, PartialEq)]
pub struct HomingCycle {
    /// The positions the axes were sent to before homing, steps.
    pub went_to: [Option<i32>; 3],
    /// Count minus switch per axis (disk, track, tilt), steps.
    pub error_steps: [Option<i32>; 3],
}

/// A commissioning check of the axes in `axes` (`scanner home --repeat`):
/// home those not homed yet, then `cycles` times send them far along their travel at
/// their configured speed and acceleration (a limited axis 90 % of the
/// way from its home switch to the other end, the disk half a turn and a
/// seventh more each cycle) and home them again. Each homing of a homed
/// axis measures its step count against its switch: a switch that repeats
/// and a drive that keeps its steps give errors within
/// [`protocol::POSITION_TOLERANCE_STEPS`]. An axis whose count is off when
/// it passes its home edge on the way out is measured there (the firmware
/// latches a lost-position fault and stops it; the fault is cleared so that
/// every cycle runs). `cycle` is told each cycle's result.
pub fn homing_repeatability(
    dev: &mut Device,
    axes: AxisSet,
    cycles: usize,
    cycle: &mut dyn FnMut(usize, &HomingCycle),
) -> Result<Vec<HomingCycle>, ScanError> {
    let configs = axis_configs(dev)?;
    let status = dev.status()?;
    let unhomed = axes.iter().filter(|a| !status.axes[a.index()].homed);
    let unhomed = unhomed.fold(AxisSet::NONE, AxisSet::with);
    if !unhomed.is_empty() {
        home_axes(dev, unhomed)?;
    }
    let mut out = Vec::with_capacity(cycles);
    for c in 0..cycles {
        let went_to: [Option<i32>; 3] = std::array::from_fn(|i| {
            let (axis, k) = (Axis::ALL[i], &configs[i]);
            axes.contains(axis).then(|| {
                if k.continuous && k.steps_per_rev > 0 {
                    let rev = k.steps_per_rev as i64;
                    (rev / 2 + c as i64 * rev / 7).rem_euclid(rev) as i32
                } else {
                    let (home, far) = match k.homing.direction {
                        protocol::Direction::Negative => (k.homing.home_position, k.max_steps),
                        protocol::Direction::Positive => (k.homing.home_position, k.min_steps),
                    };
                    (home as f64 + 0.9 * (far as f64 - home as f64)).round() as i32
                }
            })
        });
        dev.clear_events();
        dev.command(Request::Move { mode: MoveMode::Absolute, targets: went_to })?;
        let status = wait_idle(dev, Duration::from_secs(300))?;
        // An axis that passes its home edge on the way out is checked
        // there (the firmware reports only an error beyond the tolerance,
        // latches the fault and stops): that error is the one measured.
        let mut error_steps = [None; 3];
        let checked = |events: Vec<Event>, errors: &mut [Option<i32>; 3]| {
            for e in events {
                if let Event::PositionChecked { axis, error_steps: error } = e {
                    errors[axis.index()].get_or_insert(error);
                }
            }
        };
        checked(dev.take_events(), &mut error_steps);
        if status.faults.contains(FaultFlags::POSITION_LOST) {
            dev.command(Request::ClearFault)?;
        }
        checked(home_axes(dev, axes)?, &mut error_steps);
        let result = HomingCycle { went_to, error_steps };
        cycle(c, &result);
        out.push(result);
    }
    Ok(out)
}

/// What [`homing_repeatability`]'s cycles say of one axis.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AxisRepeatability {
    /// The axis.
    pub axis: Axis,
    /// The least and most its count was off at its switch, steps (`None`:
    /// never measured).
    pub range: Option<(i32, i32)>,
    /// Cycles that measured it.
    pub measured: usize,
    /// Measured, and always within [`protocol::POSITION_TOLERANCE_STEPS`]
    /// (an axis is not measured in a cycle that another one's lost steps
    /// stopped on its way out).
    pub kept: bool,
}

/// Per axis of `axes`, what `cycles` of [`homing_repeatability`] say.
pub fn repeatability(cycles: &[HomingCycle], axes: AxisSet) -> Vec<AxisRepeatability> {
    axes.iter()
        .map(|axis| {
            let errors: Vec<i32> =
                cycles.iter().filter_map(|c| c.error_steps[axis.index()]).collect();
            let range = errors.iter().min().copied().zip(errors.iter().max().copied());
            let kept = range.is_some_and(|(lo, hi)| within_tolerance(lo) && within_tolerance(hi));
            AxisRepeatability { axis, range, measured: errors.len(), kept }
        })
        .collect()
}

/// Home the axes of `axes` and wait for the end; returns the events that
/// came meanwhile (position checks of axes that were homed already).
pub(crate) fn home_axes(dev: &mut Device, axes: AxisSet) -> Result<Vec<Event>, ScanError> {
    dev.clear_events();
    dev.command(Request::Home { axes })?;
    let failed = |outcome: Option<MotionOutcome>, faults: FaultFlags| {
        let by =
            if faults.is_empty() { String::new() } else { format!(" ({})", fault_list(faults)) };
        let what = outcome.map_or("failed".to_string(), |o| o.to_string());
        Err(ScanError::DeviceFault(format!("homing {what}{by}")))
    };
    match wait_motion_end(dev, Duration::from_secs(90))? {
        Some(MotionEnd::Reported { outcome: MotionOutcome::Completed, .. }) => {
            Ok(dev.take_events())
        }
        Some(MotionEnd::Reported { outcome, .. }) => failed(Some(outcome), dev.status()?.faults),
        Some(MotionEnd::Unreported(status)) => {
            let homed =
                Axis::ALL.into_iter().all(|a| !axes.contains(a) || status.axes[a.index()].homed);
            if homed && status.faults.is_empty() {
                return Ok(dev.take_events());
            }
            failed(None, status.faults)
        }
        None => Err(ScanError::DeviceFault("homing did not finish in 90 s".into())),
    }
}

/// How a commanded motion (homing, a move) ended.
#[derive(Debug, Clone, PartialEq)]
pub enum MotionEnd {
    /// As its `MotionDone` event says.
    Reported {
        /// The axes that were moving.
        axes: AxisSet,
        /// How it ended.
        outcome: MotionOutcome,
        /// The axes' step counts then.
        positions: [i32; 3],
    },
    /// Its event was lost on the link: the device's status once it was
    /// neither homing nor moving any more. No latched fault means it
    /// completed (a motion ends otherwise only on a fault or on `Stop`).
    Unreported(protocol::Status),
}

/// Wait up to `max` for the end of the motion just commanded: its
/// `MotionDone` event, or — a noisy link can lose that event — after each
/// half second without it, the status of a device that is neither homing
/// nor moving any more. `None` if the motion is still going at `max`.
pub fn wait_motion_end(dev: &mut Device, max: Duration) -> Result<Option<MotionEnd>, LinkError> {
    let done = |e: &Event| matches!(e, Event::MotionDone { .. });
    let reported = |e| match e {
        Event::MotionDone { axes, outcome, positions } => {
            MotionEnd::Reported { axes, outcome, positions }
        }
        other => unreachable!("only MotionDone is waited for, not {other:?}"),
    };
    let end = dev.now() + max;
    while dev.now() < end {
        let left = end.saturating_sub(dev.now());
        if let Some(e) = dev.wait_event(Duration::from_millis(500).min(left), done)? {
            return Ok(Some(reported(e)));
        }
        let status = dev.status()?;
        if matches!(status.state, DeviceState::Homing | DeviceState::Moving) {
            continue;
        }
        // The event may have come with the status' reply after all.
        return Ok(Some(match dev.wait_event(Duration::ZERO, done)? {
            Some(e) => reported(e),
            None => MotionEnd::Unreported(status),
        }));
    }
    Ok(None)
}

/// Check every axis' step count against its switch by homing it (the
/// firmware reports the count's error for each axis that was homed).
/// `mirrors` are the frames taken since the last passed check.
fn check_position(
    dev: &mut Device,
    geometry: &ScannerGeometry,
    mirrors: &[usize],
    progress: &mut dyn ScanProgress,
) -> Result<PositionCheck, ScanError> {
    let mut check =
        PositionCheck { mirrors: mirrors.to_vec(), ..PositionCheck::failed(CheckKind::Homing) };
    if prepare(dev, geometry, progress)?.homed {
        check.kind = CheckKind::HomingLost;
        return Ok(check);
    }
    match home_all(dev) {
        Ok(events) => {
            for e in events {
                if let Event::PositionChecked { axis, error_steps } = e {
                    check.error_steps[axis.index()] = Some(error_steps);
                }
            }
            check.passed = check.error_steps.iter().all(|e| e.is_some_and(within_tolerance));
            Ok(check)
        }
        // A reset during the check: homing is lost with it.
        Err(ScanError::Link(LinkError::Reset { .. })) => {
            progress.note("device reset during the position check");
            check.kind = CheckKind::HomingLost;
            prepare(dev, geometry, progress)?;
            Ok(check)
        }
        Err(e) => Err(e),
    }
}

/// The words for a failed check, e.g. "track off by 400 steps".
fn describe_check(check: &PositionCheck) -> String {
    if check.kind == CheckKind::HomingLost {
        return "the device lost its homing, so the frames before cannot be checked".into();
    }
    let off: Vec<String> = Axis::ALL
        .iter()
        .zip(check.error_steps)
        .filter_map(|(a, e)| match e {
            Some(e) if !within_tolerance(e) => Some(format!("{} off by {e} steps", a.name())),
            Some(_) => None,
            None => Some(format!("{} not measured", a.name())),
        })
        .collect();
    off.join(", ")
}

/// Poll the status until the device is idle or faulted; an error after `max`.
pub fn wait_idle(dev: &mut Device, max: Duration) -> Result<protocol::Status, ScanError> {
    let end = dev.now() + max;
    loop {
        let s = dev.status()?;
        if matches!(s.state, DeviceState::Idle | DeviceState::Faulted) {
            return Ok(s);
        }
        if dev.now() >= end {
            return Err(ScanError::DeviceFault(format!(
                "device still {:?} after {max:?}",
                s.state
            )));
        }
        dev.sleep(Duration::from_millis(20))?;
    }
}

/// Frame file of mirror `l`, relative to the scan directory.
pub fn frame_file(l: usize) -> String {
    format!("frames/mirror-{l:02}.exr")
}

/// File of one exposure of an HDR bracket, relative to the scan directory.
pub fn raw_file(l: usize, exposure_us: u32) -> String {
    format!("frames/raw/mirror-{l:02}-e{exposure_us:07}.exr")
}

/// The folder of [`raw_file`]s in scan directory `dir`, created when an
/// HDR bracket will use it.
fn raw_dir(dir: &Path, bracket_us: &[u32]) -> Result<PathBuf, ScanError> {
    let raw = dir.join("frames").join("raw");
    if !bracket_us.is_empty() {
        std::fs::create_dir_all(&raw).map_err(|e| io_error(&raw, e))?;
    }
    Ok(raw)
}

/// Lower-case hex of `bytes` (device ids, checksums).
pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// The SHA-256 of `bytes`, in lower-case hex (as manifests record it).
pub(crate) fn sha256_hex(bytes: &[u8]) -> String {
    hex(&Sha256::digest(bytes))
}

/// Open or create the scan directory, locked for this scan; returns the
/// manifest with only the frames whose files are intact, and the lock
/// (held until it is dropped).
fn open_directory(
    opts: &ScanOptions,
    settings: &ScanSettings,
    device: &DeviceRecord,
    camera: &str,
    progress: &mut dyn ScanProgress,
) -> Result<(Manifest, std::fs::File), ScanError> {
    let dir = &opts.out;
    if std::fs::metadata(dir).is_ok_and(|m| !m.is_dir()) {
        return Err(ScanError::Conflict(format!("{} is not a directory", dir.display())));
    }
    // A folder holding something else is refused before anything is
    // created in it (checked again under the lock).
    refuse_foreign(opts)?;
    std::fs::create_dir_all(dir).map_err(|e| io_error(dir, e))?;
    // One writer per scan directory, for the whole scan.
    let lock_path = dir.join(LOCK_FILE);
    let lock =
        scanner_formats::input::open_lock_file(&lock_path).map_err(|e| io_error(&lock_path, e))?;
    match lock.try_lock() {
        Ok(()) => {}
        Err(std::fs::TryLockError::WouldBlock) => {
            return Err(ScanError::Conflict(format!(
                "another scan is using {} (it holds {LOCK_FILE}); wait for it or stop it first",
                dir.display()
            )));
        }
        Err(std::fs::TryLockError::Error(e)) => return Err(io_error(&lock_path, e)),
    }
    let fresh = Manifest {
        format: MANIFEST_FORMAT.into(),
        version: MANIFEST_VERSION,
        settings: settings.clone(),
        device: device.clone(),
        camera: camera.into(),
        frames: Vec::new(),
        complete: false,
        exposures: Vec::new(),
        checks: Vec::new(),
    };
    let previous = || Manifest::load_file(&dir.join(PREVIOUS_MANIFEST_FILE)).ok();
    let loaded = match Manifest::load_file(&dir.join(MANIFEST_FILE)) {
        Ok(_) if !opts.resume => {
            return Err(ScanError::Conflict(format!(
                "{} already holds a scan; pass --resume to complete it, or choose another --out",
                dir.display()
            )));
        }
        Ok(m) => Some(m),
        Err(LoadError::Damaged(why)) => match previous() {
            Some(prev) if opts.resume => {
                // Keep the damaged file for whoever wants to look at it.
                let kept = dir.join(format!("{MANIFEST_FILE}.damaged"));
                std::fs::rename(dir.join(MANIFEST_FILE), &kept).map_err(|e| io_error(&kept, e))?;
                progress.note(&format!(
                    "{why}; recovering from {PREVIOUS_MANIFEST_FILE} (the damaged one is kept as {})",
                    kept.display()
                ));
                Some(prev)
            }
            Some(_) => {
                return Err(ScanError::Conflict(format!(
                    "{why}; `--resume` recovers the frames {PREVIOUS_MANIFEST_FILE} lists"
                )));
            }
            None => return Err(ScanError::Conflict(why)),
        },
        Err(LoadError::Missing) => match previous() {
            Some(prev) if opts.resume => {
                progress.note(&format!(
                    "{MANIFEST_FILE} is missing; recovering from {PREVIOUS_MANIFEST_FILE}"
                ));
                Some(prev)
            }
            _ => {
                refuse_foreign(opts)?;
                None
            }
        },
    };
    let frames_dir = dir.join("frames");
    std::fs::create_dir_all(&frames_dir).map_err(|e| io_error(&frames_dir, e))?;
    let raw_dir = raw_dir(dir, &settings.bracket_us)?;
    // Leftovers of an interrupted atomic write (no other scan runs here).
    for d in [dir.as_path(), frames_dir.as_path(), raw_dir.as_path()] {
        if !d.is_dir() {
            continue;
        }
        for entry in std::fs::read_dir(d).map_err(|e| io_error(d, e))?.flatten() {
            if entry.file_name().to_string_lossy().starts_with(".tmp-") {
                let _ = std::fs::remove_file(entry.path());
            }
        }
    }
    let Some(mut m) = loaded else {
        fresh.save(dir)?;
        return Ok((fresh, lock));
    };
    let differences = m.settings.differences(settings);
    if !differences.is_empty() {
        return Err(ScanError::Conflict(format!(
            "{} holds a different scan: {}; cannot resume it with these settings",
            dir.display(),
            differences.join("; ")
        )));
    }
    if m.device.device_id != device.device_id {
        return Err(ScanError::Conflict(format!(
            "{} was scanned with device {}, this is {}",
            dir.display(),
            m.device.device_id,
            device.device_id
        )));
    }
    let (mut missing, mut damaged) = (0, 0);
    m.frames.retain(|f| match frame_state(dir, f) {
        FrameState::Intact => true,
        FrameState::Missing => {
            missing += 1;
            false
        }
        FrameState::Damaged => {
            damaged += 1;
            false
        }
    });
    let done: Vec<usize> = m.frames.iter().map(|f| f.mirror).collect();
    m.exposures.retain(|f| !done.contains(&f.mirror) && frame_intact(dir, f));
    if missing + damaged > 0 {
        progress.note(&format!(
            "recorded frames: {missing} missing, {damaged} damaged; taking them again"
        ));
    }
    m.device = device.clone();
    m.camera = camera.into();
    m.complete = false;
    m.save(dir)?;
    Ok((m, lock))
}

/// Capture a scan.
pub fn scan(
    dev: &mut Device,
    camera: &mut dyn Camera,
    geometry: &ScannerGeometry,
    opts: &ScanOptions,
    progress: &mut dyn ScanProgress,
) -> Result<ScanReport, ScanError> {
    let started = Instant::now();
    let mut report = ScanReport::default();
    let total = opts.mirrors.unwrap_or(geometry.mirrors.len());
    if total == 0 || total > geometry.mirrors.len() {
        return Err(ScanError::Conflict(format!("--mirrors must be 1…{}", geometry.mirrors.len())));
    }
    let info = *dev.info();
    let settings = ScanSettings {
        sample_name: opts.sample_name.clone(),
        geometry_sha256: geometry.hash(),
        mirror_count: total,
        exposure_us: opts.exposure_us,
        settle_ms: opts.settle_ms,
        light_duty_permille: opts.light_duty_permille,
        bracket_us: if opts.auto_exposure.is_some() { Vec::new() } else { opts.bracket_us.clone() },
        simulator: opts.simulator.clone(),
        auto_exposure: opts.auto_exposure,
        metering: None,
        dark: None,
        black_level_codes: if opts.black_level_auto { 0 } else { opts.black_level_codes },
        black_level_auto: opts
            .black_level_auto
            .then_some(AutoBlackLevel { exposure_us: None, strobe: None }),
        camera_codes: camera.integer_codes(),
        light_margin_us: opts.light_margin_us,
    };
    if opts.light_margin_us > protocol::MAX_LIGHT_MARGIN_US {
        return Err(ScanError::Conflict(format!(
            "light margin {} µs: at most {} µs",
            opts.light_margin_us,
            protocol::MAX_LIGHT_MARGIN_US
        )));
    }
    if opts.light_margin_us > 0 && info.protocol.minor < 3 {
        return Err(ScanError::Incompatible(format!(
            "the device's firmware (protocol {}) cannot light around the trigger pulse \
             (--light-margin-us): update it",
            info.protocol
        )));
    }
    let max_code = geometry.sensor.max_code();
    if opts.black_level_codes as f64 >= max_code {
        return Err(ScanError::Conflict(format!(
            "black level {} codes: at or above the sensor's top code {max_code}",
            opts.black_level_codes
        )));
    }
    // Frames checked as they arrive; the black level is set once it is
    // known (the directory's, or measured below).
    let mut checked = crate::camera::ScanCamera::new(camera, geometry);
    let camera: &mut dyn Camera = &mut checked;
    let floor_us = crate::exposure::shortest_us(opts.light_duty_permille);
    if let Some(&bad) = opts
        .bracket_us
        .iter()
        .find(|&&e| crate::exposure::realise(e, opts.light_duty_permille).is_none())
    {
        return Err(ScanError::Conflict(format!(
            "exposure {bad} µs outside {floor_us}…{} µs",
            protocol::MAX_EXPOSURE_US
        )));
    }
    let device = DeviceRecord {
        device_id: hex(&info.device_id),
        firmware: info.firmware.to_string(),
        protocol: info.protocol.to_string(),
        board: info.board,
    };
    let t = Instant::now();
    let (mut manifest, _lock) =
        open_directory(opts, &settings, &device, &camera.describe(), progress)?;
    report.timings.disk += t.elapsed();
    report.kept = manifest.frames.len();
    progress.start(total, report.kept);

    let t = Instant::now();
    let prepared = prepare(dev, geometry, progress)?;
    let axes = prepared.axes;
    await_stray_frame(dev, camera, opts, progress)?;
    report.timings.link += t.elapsed();

    // `--black-level auto`: measured once per scan, before metering, in a
    // frame with the light off (a resumed scan keeps what its first run
    // measured); every frame from then on has it subtracted.
    if manifest.settings.black_level_auto.is_some_and(|a| a.exposure_us.is_none()) {
        let exposure_us = protocol::MIN_EXPOSURE_US;
        let bias = DarkFrame { geometry, opts, exposure_us };
        let frame = bias.take_with_retries(dev, camera, &mut report, progress, "black level")?;
        let (frame, strobe) = frame.map_err(|why| {
            ScanError::Conflict(format!("black level: no frame with the light off ({why})"))
        })?;
        let codes = crate::defects::black_level_codes(&frame, geometry.sensor.max_code());
        progress.note(&format!(
            "black level: {codes} codes (the median of a {exposure_us} µs frame with the light \
             off), subtracted from every frame"
        ));
        manifest.settings.black_level_codes = codes;
        manifest.settings.black_level_auto =
            Some(AutoBlackLevel { exposure_us: Some(exposure_us), strobe });
        let t = Instant::now();
        manifest.save(&opts.out)?;
        report.timings.disk += t.elapsed();
    }
    checked.set_black_level(manifest.settings.black_level_codes);
    let camera: &mut dyn Camera = &mut checked;

    // Auto exposure: metered once per scan (a resumed scan keeps what its
    // first run chose); the exposures chosen stand in for the options'.
    let metered_opts;
    let opts = match opts.auto_exposure {
        None => opts,
        Some(mode) => {
            if manifest.settings.metering.is_none() {
                let metering = meter(dev, camera, geometry, opts, total, &mut report, progress)?;
                let choice =
                    crate::exposure::choose(&metering, mode == AutoExposure::Hdr, floor_us);
                progress.note(&format!(
                    "metered {}: the sample's 95th percentile at {:.3} and its peak at {} of full \
                     scale at {} µs → {}",
                    mirror_list(&metering.mirrors),
                    metering.body,
                    metering.peak.map_or("saturation".into(), |p| format!("{p:.3}")),
                    metering.exposure_us,
                    if choice.bracket_us.is_empty() {
                        format!("{} µs", choice.exposure_us)
                    } else {
                        format!("bracket {:?} µs", choice.bracket_us)
                    }
                ));
                manifest.settings.exposure_us = choice.exposure_us;
                manifest.settings.bracket_us = choice.bracket_us;
                manifest.settings.metering = Some(metering);
                let t = Instant::now();
                raw_dir(&opts.out, &manifest.settings.bracket_us)?;
                manifest.save(&opts.out)?;
                report.timings.disk += t.elapsed();
            }
            metered_opts = ScanOptions {
                exposure_us: manifest.settings.exposure_us,
                bracket_us: manifest.settings.bracket_us.clone(),
                ..opts.clone()
            };
            &metered_opts
        }
    };

    // Hot pixels: once per scan, a dark frame at the longest exposure it
    // takes (a scan interrupted before it has one takes it on resuming;
    // the frames stored before are replaced when read).
    if manifest.settings.dark.is_none() {
        let longest = opts.bracket_us.iter().copied().max().unwrap_or(opts.exposure_us);
        let dark = DarkFrame { geometry, opts, exposure_us: realised(opts, longest)?.exposure_us };
        if let Some(record) = dark.find_hot_pixels(dev, camera, &mut report, progress)? {
            manifest.settings.dark = Some(record);
            let t = Instant::now();
            manifest.save(&opts.out)?;
            report.timings.disk += t.elapsed();
        }
    }

    // Frames are encoded and written, and the manifest updated, on a second
    // thread while the next frame is captured; the manifest names a frame
    // as soon as its file is durable, and only then. Frames are verified by
    // position checks (every `check_every` frames and at the end); a failed
    // check, or homing lost in between, retakes the frames since the last
    // passed one.
    let mut todo: VecDeque<usize> =
        (0..total).filter(|l| !manifest.frames.iter().any(|f| f.mirror == *l)).collect();
    let (width, height) = (geometry.camera.width, geometry.camera.height);
    let per_frame = frame_bytes(width, height, !opts.bracket_us.is_empty());
    if let Some(free) = scanner_formats::atomic::free_bytes(&opts.out)
        && let Some(note) = disk_space_note(free, todo.len(), per_frame)
    {
        progress.note(&note);
    }
    let mut unverified: Vec<usize> =
        manifest.frames.iter().filter(|f| !f.verified).map(|f| f.mirror).collect();
    let mut raw_kept: Vec<FrameRecord> = manifest.exposures.clone();
    let extend_bracket = opts.auto_exposure == Some(AutoExposure::Hdr);
    let mut spans: Option<Vec<crate::exposure::Span>> = None;
    // The sensor's defective pixels metering and the dark frame found: left
    // out of the saturation counts and replaced in the frames.
    let defects = crate::defects::DefectMap::new(
        &manifest.settings.defects(),
        geometry.camera.width,
        geometry.camera.height,
    );
    // What the camera subtracts from every value (the merge's top is the
    // top code less it).
    let black = manifest.settings.black_level_codes;
    // Stored frames not verified before the device lost its homing (the
    // scan was interrupted, the device reset) cannot be verified now.
    let mut pending_check = (prepared.homed && !unverified.is_empty())
        .then(|| PositionCheck::failed(CheckKind::HomingLost));
    let manifest = std::thread::scope(|scope| -> Result<Manifest, ScanError> {
        let (jobs, job_rx) = std::sync::mpsc::sync_channel::<Job>(1);
        let (done_tx, done) =
            std::sync::mpsc::channel::<Result<(Option<usize>, Duration), ScanError>>();
        let out = opts.out.as_path();
        let writer = scope.spawn(move || {
            let mut buffer = Vec::new();
            for job in job_rx {
                let t = Instant::now();
                let job = match job {
                    Job::Frame(job) => job,
                    Job::Check(check) => {
                        if check.passed {
                            for f in &mut manifest.frames {
                                f.verified |= check.mirrors.contains(&f.mirror);
                            }
                        }
                        manifest.checks.push(check);
                        let result = manifest.save(out).map(|()| (None, t.elapsed()));
                        let failed = result.is_err();
                        if done_tx.send(result).is_err() || failed {
                            break;
                        }
                        continue;
                    }
                };
                let raw = job.raw;
                let result = write_frame(out, job, &mut buffer).and_then(|record| {
                    let mirror = record.mirror;
                    if raw {
                        manifest.exposures.retain(|f| f.file != record.file);
                        manifest.exposures.push(record);
                        manifest.save(out)?;
                        return Ok((None, t.elapsed()));
                    }
                    manifest.frames.retain(|f| f.mirror != mirror);
                    manifest.frames.push(record);
                    manifest.frames.sort_by_key(|f| f.mirror);
                    // The merge is durable: its single exposures can go.
                    let (gone, kept): (Vec<FrameRecord>, Vec<FrameRecord>) =
                        manifest.exposures.drain(..).partition(|f| f.mirror == mirror);
                    manifest.exposures = kept;
                    manifest.save(out)?;
                    for f in gone {
                        let _ = std::fs::remove_file(out.join(&f.file));
                    }
                    Ok((Some(mirror), t.elapsed()))
                });
                let failed = result.is_err();
                if done_tx.send(result).is_err() || failed {
                    break;
                }
            }
            manifest
        });
        let stored = |result: Result<(Option<usize>, Duration), ScanError>,
                      report: &mut ScanReport,
                      progress: &mut dyn ScanProgress|
         -> Result<(), ScanError> {
            let (mirror, took) = result?;
            report.timings.disk += took;
            if let Some(mirror) = mirror {
                report.captured += 1;
                progress.frame(mirror);
            }
            Ok(())
        };
        let mut failure = None;
        let mut failed_checks = 0;
        'mirrors: loop {
            for result in done.try_iter() {
                if let Err(e) = stored(result, &mut report, progress) {
                    failure = Some(e);
                }
            }
            if failure.is_some() {
                break;
            }
            if opts.interrupt.as_ref().is_some_and(|f| f.load(std::sync::atomic::Ordering::SeqCst))
            {
                failure = Some(ScanError::Interrupted { kept: 0, total, dir: opts.out.clone() });
                break;
            }
            // Homing lost, or steps lost and caught at a switch: the frames
            // since the last passed check are taken again.
            if let Some(mut check) = pending_check.take() {
                check.mirrors = unverified.clone();
                progress.note(&format!(
                    "{}: taking {} again",
                    describe_check(&check),
                    mirror_list(&check.mirrors)
                ));
                if jobs.send(Job::Check(check)).is_err() {
                    break;
                }
                retake(&mut unverified, &mut todo, &mut raw_kept, &mut report, progress);
            }
            let due = !unverified.is_empty()
                && (todo.is_empty()
                    || (opts.check_every > 0 && unverified.len() >= opts.check_every));
            if due {
                let t = Instant::now();
                let check = check_position(dev, geometry, &unverified, progress);
                report.timings.link += t.elapsed();
                let check = match check {
                    Ok(c) => c,
                    Err(e) => {
                        failure = Some(e);
                        break;
                    }
                };
                report.checks += 1;
                let passed = check.passed;
                if !passed {
                    failed_checks += 1;
                    progress.note(&format!(
                        "position check: {}; taking {} again",
                        describe_check(&check),
                        mirror_list(&unverified)
                    ));
                }
                if jobs.send(Job::Check(check)).is_err() {
                    break;
                }
                if passed {
                    unverified.clear();
                    failed_checks = 0;
                } else if failed_checks >= MAX_FAILED_CHECKS {
                    failure = Some(ScanError::DeviceFault(format!(
                        "steps lost at {failed_checks} position checks in a row: a motor \
                         stalls or a belt slips; the scanner needs looking at \
                         (`--resume` continues once it is fixed)"
                    )));
                    break;
                } else {
                    retake(&mut unverified, &mut todo, &mut raw_kept, &mut report, progress);
                }
                continue;
            }
            let Some(l) = todo.pop_front() else { break };
            let mut bracket = if opts.bracket_us.is_empty() {
                vec![opts.exposure_us]
            } else {
                opts.bracket_us.clone()
            };
            // Shared with the writer: a raw exposure is stored and merged.
            let mut taken: Vec<(Arc<crate::camera::Frame>, u32, FrameRecord)> = Vec::new();
            let mut next = 0;
            loop {
                if next == bracket.len() {
                    // Auto HDR: highlights the bracket clipped on the sample
                    // get shorter exposures (decided from the stored
                    // frames alone, so a resume decides the same).
                    if !extend_bracket {
                        break;
                    }
                    let Some((f, e, _)) = taken.iter().min_by_key(|(_, e, _)| *e) else { break };
                    let spans = spans.get_or_insert_with(|| {
                        crate::exposure::sample_spans(geometry, f.width, f.height)
                    });
                    let n = crate::exposure::saturated_in(
                        f,
                        spans,
                        geometry.sensor.max_code(),
                        &defects,
                    );
                    let Some(t) = crate::exposure::extension(*e, n, floor_us) else { break };
                    progress.note(&format!(
                        "mirror {l}: {n} values saturated on the sample at {e} µs; adding {t} µs"
                    ));
                    bracket.push(t);
                }
                let exposure_us = bracket[next];
                next += 1;
                let file = if opts.bracket_us.is_empty() {
                    frame_file(l)
                } else {
                    raw_file(l, exposure_us)
                };
                if let Some(rec) = raw_kept.iter().find(|r| r.file == file) {
                    // Resumed: this exposure is on disk already.
                    let t = Instant::now();
                    let frame = exrio::read_rgb(&opts.out.join(&rec.file))
                        .map_err(|e| ScanError::Io(format!("{}: {e}", rec.file)));
                    report.timings.disk += t.elapsed();
                    match frame {
                        Ok(f) => {
                            taken.push((Arc::new(f), exposure_us, rec.clone()));
                            continue;
                        }
                        Err(e) => {
                            failure = Some(e);
                            break 'mirrors;
                        }
                    }
                }
                let o = realised(opts, exposure_us)?;
                let ((frame, fired, status, window), lost) =
                    match capture_with_retries(dev, camera, geometry, l, &o, &mut report, progress)
                    {
                        Ok(c) => c,
                        Err(e) => {
                            failure = Some(e);
                            break 'mirrors;
                        }
                    };
                if let Some(check) = lost {
                    // Taken after homing again: good. What came before (and
                    // this mirror's earlier exposures) is taken again.
                    pending_check = Some(check);
                    if !taken.is_empty() {
                        unverified.push(l);
                        continue 'mirrors;
                    }
                }
                let steps = status.axes.map(|a| a.position_steps);
                let record = FrameRecord {
                    mirror: l,
                    file,
                    sha256: String::new(),
                    width: 0,
                    height: 0,
                    trigger_seq: fired.trigger_seq,
                    device_timestamp_us: fired.timestamp_us,
                    exposure_us,
                    axis_steps: steps,
                    axis_units: AxisValues::from_steps(steps.map(i64::from), &axes).to_array(),
                    verified: false,
                    bracket_us: Vec::new(),
                    light_duty_permille: (o.light_duty_permille != opts.light_duty_permille)
                        .then_some(o.light_duty_permille),
                    strobe: window,
                    exposure_ratios: Vec::new(),
                };
                if let Some(e) = &record.strobe {
                    report.strobe.add(e, fired.exposure_us);
                }
                if opts.bracket_us.is_empty() {
                    let mut frame = frame;
                    defects.patch(&mut frame);
                    taken.push((Arc::new(frame), exposure_us, record));
                    break;
                }
                // Merge what is stored: the half-float frame, so a resumed
                // mirror merges to the same bytes.
                let frame = Arc::new(exrio::quantise_half(frame));
                if jobs
                    .send(Job::Frame(WriteJob {
                        frame: Arc::clone(&frame),
                        record: record.clone(),
                        raw: true,
                    }))
                    .is_err()
                {
                    break 'mirrors;
                }
                taken.push((frame, exposure_us, record));
            }
            let job = if opts.bracket_us.is_empty() {
                let (frame, _, record) = taken.pop().expect("one exposure taken");
                WriteJob { frame, record, raw: false }
            } else {
                let reference = *bracket.iter().max().expect("a bracket");
                let inputs: Vec<(&crate::camera::Frame, u32)> =
                    taken.iter().map(|(f, e, _)| (&**f, *e)).collect();
                let merged =
                    crate::hdr::merge(&inputs, &geometry.sensor, black, reference, &defects);
                let (merged, stats) = match merged {
                    Ok(m) => m,
                    Err(e) => {
                        failure = Some(ScanError::Io(format!("mirror {l}: {e}")));
                        break 'mirrors;
                    }
                };
                if stats.clipped > 0 {
                    progress.note(&format!(
                        "mirror {l}: {} values saturated even at {} µs",
                        stats.clipped,
                        bracket.iter().min().expect("a bracket")
                    ));
                }
                let ratios: Vec<crate::hdr::ExposureRatio> =
                    crate::hdr::exposure_ratios(&inputs, &geometry.sensor, black)
                        .into_iter()
                        .flatten()
                        .collect();
                for r in &ratios {
                    if (r.ratio - 1.0).abs() > EXPOSURE_RATIO_TOLERANCE {
                        let duty = |us: u32| {
                            taken
                                .iter()
                                .find(|(_, e, _)| *e == us)
                                .and_then(|(_, _, rec)| rec.light_duty_permille)
                        };
                        let dimmed = duty(r.shorter_us)
                            .map(|d| format!(" (taken at 1 ms with the light at {d} ‰)"))
                            .unwrap_or_default();
                        // The trigger pulses' lengths: a dimmed exposure's is 1 ms.
                        let pulse = |us: u32| {
                            if duty(us).is_some() { protocol::MIN_EXPOSURE_US } else { us }
                        };
                        let delay = r
                            .trigger_delay_us(pulse(r.shorter_us), pulse(r.longer_us))
                            .map(|d| {
                                // A margin a quarter over it, in 10 µs.
                                let margin = ((d * 1.25 / 10.0).ceil() * 10.0)
                                    .min(protocol::MAX_LIGHT_MARGIN_US as f64);
                                format!(
                                    "; as a delay it is ≈ {d:.0} µs, and --light-margin-us \
                                     {margin:.0} lights around it"
                                )
                            })
                            .unwrap_or_default();
                        progress.note(&format!(
                            "mirror {l}: the {} µs exposure{dimmed} measured {:.3}× the light per \
                             µs of the {} µs one over {} values; the merge assumes 1: check the \
                             light's linearity{}, the exposure times, and that the camera \
                             exposes while its trigger is high (one that starts later — a trigger \
                             delay or debounce set in it — misses the light's last µs{delay})",
                            r.shorter_us,
                            r.ratio,
                            r.longer_us,
                            r.values,
                            if dimmed.is_empty() { "" } else { " at low duty" },
                        ));
                    }
                }
                let (_, _, longest) = taken
                    .iter()
                    .find(|(_, e, _)| *e == reference)
                    .expect("the reference exposure was taken");
                let mut record = longest.clone();
                record.exposure_ratios = ratios;
                record.file = frame_file(l);
                record.exposure_us = reference;
                if bracket != opts.bracket_us {
                    bracket.sort_unstable();
                    record.bracket_us = bracket;
                }
                WriteJob { frame: Arc::new(merged), record, raw: false }
            };
            if jobs.send(Job::Frame(job)).is_err() {
                break; // the writer stopped on an error, reported below
            }
            unverified.push(l);
        }
        // Frames already taken are stored and recorded even when the scan
        // stops: a resume will not take them again.
        drop(jobs);
        for result in done.iter() {
            if let Err(e) = stored(result, &mut report, progress) {
                failure.get_or_insert(e);
            }
        }
        let manifest =
            writer.join().map_err(|_| ScanError::Io("the frame writer panicked".into()))?;
        if let Some(ScanError::Interrupted { kept, .. }) = &mut failure {
            *kept = manifest.frames.len();
        }
        failure.map_or(Ok(manifest), Err)
    })?;
    let mut manifest = manifest;
    if manifest.frames.len() < total || manifest.frames.iter().any(|f| !f.verified) {
        return Err(ScanError::Io("frames were not written or not verified".into()));
    }
    // Read every frame back before calling the scan complete.
    let t = Instant::now();
    let damaged: Vec<usize> =
        manifest.frames.iter().filter(|f| !frame_intact(&opts.out, f)).map(|f| f.mirror).collect();
    if !damaged.is_empty() {
        return Err(ScanError::Io(format!(
            "frames of mirrors {damaged:?} do not match their checksums after writing; `--resume` takes them again"
        )));
    }
    manifest.complete = true;
    manifest.save(&opts.out)?;
    report.timings.disk += t.elapsed();
    report.timings.total = started.elapsed();
    Ok(report)
}

/// Whether a frame's file exists and has its recorded checksum.
fn frame_intact(dir: &Path, f: &FrameRecord) -> bool {
    frame_state(dir, f) == FrameState::Intact
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum FrameState {
    Intact,
    /// No file.
    Missing,
    /// A file that differs from its checksum (or cannot be read).
    Damaged,
}

fn frame_state(dir: &Path, f: &FrameRecord) -> FrameState {
    match scanner_formats::input::read(&dir.join(&f.file)) {
        Ok(bytes) if sha256_hex(&bytes) == f.sha256 => FrameState::Intact,
        Ok(_) => FrameState::Damaged,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => FrameState::Missing,
        Err(_) => FrameState::Damaged,
    }
}

/// What [`verify`] found in a scan directory.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Verification {
    /// Mirrors the scan is for.
    pub mirror_count: usize,
    /// Frames present with their checksum.
    pub intact: usize,
    /// Mirrors without a recorded frame, or whose file is gone.
    pub missing: Vec<usize>,
    /// Mirrors whose file differs from its checksum.
    pub damaged: Vec<usize>,
}

impl Verification {
    /// Every frame there and intact.
    pub fn is_complete(&self) -> bool {
        self.missing.is_empty() && self.damaged.is_empty()
    }
}

/// Check a scan directory: manifest readable, every mirror's frame recorded,
/// every file matching its checksum.
pub fn verify(dir: &Path) -> Result<Verification, ScanError> {
    let m = Manifest::load(dir)?;
    let mut v = Verification {
        mirror_count: m.settings.mirror_count,
        intact: 0,
        missing: Vec::new(),
        damaged: Vec::new(),
    };
    for l in 0..m.settings.mirror_count {
        match m.frames.iter().find(|f| f.mirror == l).map(|f| frame_state(dir, f)) {
            None | Some(FrameState::Missing) => v.missing.push(l),
            Some(FrameState::Intact) => v.intact += 1,
            Some(FrameState::Damaged) => v.damaged.push(l),
        }
    }
    Ok(v)
}

enum Attempt {
    /// The camera missed: take the step again.
    Camera(CameraError),
    /// The device reset (`reset`) or latched a recoverable fault: prepare,
    /// retake.
    Recover {
        /// What happened.
        why: String,
        /// Whether it was a device reset.
        reset: bool,
        /// An axis caught off its count at its switch, and by how much.
        position: Option<(Axis, i32)>,
    },
    /// Stop the scan.
    Fatal(ScanError),
}

impl From<ScanError> for Attempt {
    fn from(e: ScanError) -> Attempt {
        match e {
            ScanError::Link(l) => l.into(),
            e => Attempt::Fatal(e),
        }
    }
}

impl From<LinkError> for Attempt {
    fn from(e: LinkError) -> Attempt {
        match e {
            LinkError::Reset { .. } => {
                Attempt::Recover { why: e.to_string(), reset: true, position: None }
            }
            LinkError::Refused { error: protocol::DeviceError::NotHomed, .. }
            | LinkError::Refused { error: protocol::DeviceError::FaultLatched, .. }
            | LinkError::Refused { error: protocol::DeviceError::MirrorNotSet, .. } => {
                Attempt::Recover { why: e.to_string(), reset: false, position: None }
            }
            e => Attempt::Fatal(e.into()),
        }
    }
}

/// A frame, its trigger, the device's status after it and its exposure as
/// the strobe showed it (none unwatched).
pub(crate) type Captured =
    (crate::camera::Frame, TriggerFired, protocol::Status, Option<crate::strobe::Exposure>);

/// A dark frame and its exposure as the strobe showed it (none unwatched).
pub(crate) type DarkTaken = (crate::camera::Frame, Option<crate::strobe::Exposure>);

/// Work for the writer thread, in order.
enum Job {
    /// Store a frame.
    Frame(WriteJob),
    /// Record a position check (and mark its frames verified if it passed).
    Check(PositionCheck),
}

/// A host killed during a capture step leaves the device exposing: that
/// trigger's frame may still be on its way to the camera. Wait for it (up
/// to the frame timeout after the exposure's end) and set it aside.
fn await_stray_frame(
    dev: &mut Device,
    camera: &mut dyn Camera,
    opts: &ScanOptions,
    progress: &mut dyn ScanProgress,
) -> Result<(), ScanError> {
    let Reply::Trigger(Some(t)) = dev.request(Request::GetLastTrigger)? else { return Ok(()) };
    let now_us = dev.status()?.uptime_ms as u64 * 1000;
    let exposure_us = t.exposure_us.min(protocol::MAX_EXPOSURE_US) as u64;
    let end_us = t.timestamp_us.saturating_add(exposure_us);
    let wait_until = end_us.saturating_add(opts.frame_timeout.as_micros() as u64);
    if now_us < wait_until {
        // Never longer than the longest exposure and the frame timeout,
        // whatever the device's clock says (a trigger "from the future" is
        // a report corrupted or from before the uptime counter wrapped).
        let most = Duration::from_micros(protocol::MAX_EXPOSURE_US as u64) + opts.frame_timeout;
        progress.note("waiting for the frame of an earlier trigger to set it aside");
        camera.drain(Duration::from_micros(wait_until - now_us).min(most));
    }
    Ok(())
}

/// Queue the unverified frames to be taken again (first, in order).
fn retake(
    unverified: &mut Vec<usize>,
    todo: &mut VecDeque<usize>,
    raw_kept: &mut Vec<FrameRecord>,
    report: &mut ScanReport,
    progress: &mut dyn ScanProgress,
) {
    let mut again = std::mem::take(unverified);
    again.sort_unstable();
    again.dedup();
    for &m in again.iter().rev() {
        if !todo.contains(&m) {
            todo.push_front(m);
        }
    }
    raw_kept.retain(|r| !again.contains(&r.mirror));
    report.retakes += again.len();
    progress.retaking(&again);
}

/// "mirror 3", "mirrors 0–9" or "mirrors 1, 4–7, 9": runs of consecutive
/// mirrors, at most [`MIRROR_LIST_RUNS`] of them.
pub fn mirror_list(mirrors: &[usize]) -> String {
    // Runs of consecutive mirrors, as `a` or `a–b`.
    let mut runs: Vec<(usize, usize)> = Vec::new();
    for &m in mirrors {
        match runs.last_mut() {
            Some((_, last)) if m == *last + 1 => *last = m,
            _ => runs.push((m, m)),
        }
    }
    let say = |&(a, b): &(usize, usize)| if a == b { a.to_string() } else { format!("{a}–{b}") };
    let shown: Vec<String> = runs.iter().take(MIRROR_LIST_RUNS).map(say).collect();
    let more = if runs.len() > MIRROR_LIST_RUNS {
        format!(", … ({} mirrors in all)", mirrors.len())
    } else {
        String::new()
    };
    match mirrors {
        [] => "no mirror".into(),
        [m] => format!("mirror {m}"),
        _ => format!("mirrors {}{more}", shown.join(", ")),
    }
}

/// About how many bytes a stored frame of `width` × `height` px takes:
/// half-float PIZ EXR, ≈ 0.8 byte a pixel for a single exposure's integer
/// codes and ≈ 3.0 for an HDR merge (the default 4096² frames: 13 and 51
/// MB), with a margin.
fn frame_bytes(width: u32, height: u32, hdr: bool) -> u64 {
    let per_pixel = if hdr { 3.2 } else { 1.0 };
    (width as f64 * height as f64 * per_pixel) as u64
}

/// What to say when `frames` more frames of ≈ `per_frame` bytes will not fit
/// in `free` bytes (nothing when they fit).
fn disk_space_note(free: u64, frames: usize, per_frame: u64) -> Option<String> {
    let need = per_frame.saturating_mul(frames as u64);
    let size = |b: u64| {
        if b >= 1_000_000_000 {
            format!("{:.2} GB", b as f64 / 1e9)
        } else {
            format!("{:.1} MB", b as f64 / 1e6)
        }
    };
    (need > free).then(|| {
        format!(
            "the disk has {} free; the {frames} frames still to take need ≈ {}: the scan stops \
             when it is full (exit 9), and `--resume` goes on once there is room",
            size(free),
            size(need)
        )
    })
}

/// [`mirror_list`] names this many runs at most.
const MIRROR_LIST_RUNS: usize = 12;

/// A frame to encode and store, with its record (checksum and size to fill).
struct WriteJob {
    frame: Arc<crate::camera::Frame>,
    record: FrameRecord,
    /// One exposure of an HDR bracket (recorded in `Manifest::exposures`).
    raw: bool,
}

/// Encode and store one frame atomically; complete its record. `bytes` is
/// the encoder's buffer, kept from frame to frame (its memory reused); the
/// file's checksum is computed while it is written.
fn write_frame(dir: &Path, job: WriteJob, bytes: &mut Vec<u8>) -> Result<FrameRecord, ScanError> {
    let WriteJob { frame, mut record, raw } = job;
    use exr::prelude::Compression;
    let compression = if raw { Compression::Uncompressed } else { Compression::PIZ };
    exrio::encode_half_into(&frame, compression, bytes)
        .map_err(|e| ScanError::Io(format!("{}: {e}", record.file)))?;
    let path = dir.join(&record.file);
    let bytes = bytes.as_slice();
    let (sha256, written) = std::thread::scope(|s| {
        let sha256 = s.spawn(|| sha256_hex(bytes));
        let written = write_atomic(&path, bytes);
        (sha256.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic)), written)
    });
    written.map_err(|e| io_error(&path, e))?;
    record.sha256 = sha256;
    record.width = frame.width;
    record.height = frame.height;
    Ok(record)
}

/// Auto exposure's metering frames ([`crate::exposure`]): the metering
/// mirrors at `opts.exposure_us`, taken again 10× shorter while the
/// sample's body saturates; then, if its peak saturated, 25× shorter (and
/// at the device's shortest) for the peak. Nothing is stored.
fn meter(
    dev: &mut Device,
    camera: &mut dyn Camera,
    geometry: &ScannerGeometry,
    opts: &ScanOptions,
    total: usize,
    report: &mut ScanReport,
    progress: &mut dyn ScanProgress,
) -> Result<crate::exposure::Metering, ScanError> {
    use crate::defects::{DefectFinder, DefectMap};
    use crate::exposure::{Metering, measure, meter_mirrors, sample_pixels, sample_values};
    let mirrors = meter_mirrors(total);
    // Every metering frame, whatever its exposure, also looks for the
    // sensor's defective pixels; those found so far are left out of the
    // sample's values (a stuck pixel is no highlight).
    let mut finder: Option<DefectFinder> = None;
    let mut take = |exposure_us: u32,
                    report: &mut ScanReport,
                    progress: &mut dyn ScanProgress|
     -> Result<(f64, Option<f64>, bool), ScanError> {
        let o = realised(opts, exposure_us)?;
        let mut pixels = Vec::new();
        let mut size = (0, 0);
        for &l in &mirrors {
            // A reset or lost steps on the way do not matter: nothing is kept.
            let ((frame, _, _, _), _) =
                capture_with_retries(dev, camera, geometry, l, &o, report, progress)?;
            size = (frame.width, frame.height);
            pixels.extend(sample_pixels(&frame, geometry));
            finder
                .get_or_insert_with(|| DefectFinder::new(geometry, frame.width, frame.height))
                .add(&frame);
        }
        let defects = finder.as_ref().and_then(|f| f.defects().ok()).unwrap_or_default();
        let mut values = sample_values(&pixels, &DefectMap::new(&defects, size.0, size.1));
        if values.is_empty() {
            return Err(ScanError::Conflict(
                "auto exposure: the geometry projects the sample outside the camera's frames"
                    .into(),
            ));
        }
        Ok(measure(&mut values))
    };
    let min = crate::exposure::shortest_us(opts.light_duty_permille);
    let mut exposure_us = opts.exposure_us;
    let (body, mut peak) = loop {
        let (body, peak, too_bright) = take(exposure_us, report, progress)?;
        if too_bright && exposure_us > min {
            exposure_us = (exposure_us / 10).max(min);
            continue;
        }
        break (body, peak);
    };
    let mut peak_exposure_us = exposure_us;
    while peak.is_none() && peak_exposure_us > min {
        peak_exposure_us = (peak_exposure_us / 25).max(min);
        let (_, p, _) = take(peak_exposure_us, report, progress)?;
        // In the units of the body's metering exposure.
        peak = p.map(|p| p * exposure_us as f64 / peak_exposure_us as f64);
    }
    let defects = match finder.map(|f| f.defects()) {
        Some(Ok(found)) => found,
        Some(Err(why)) => {
            progress.note(&format!("sensor defects: {why}; none are replaced"));
            Vec::new()
        }
        None => Vec::new(),
    };
    if !defects.is_empty() {
        progress.note(&format!(
            "sensor defects: {} in the metering frames; the frames have them replaced by their \
             neighbours' mean",
            crate::defects::counts(&defects)
        ));
    }
    Ok(Metering { exposure_us, mirrors: mirrors.clone(), body, peak, peak_exposure_us, defects })
}

/// A dark frame: the light off, a bare trigger (docs/scan-format.md,
/// "Sensor defects").
pub(crate) struct DarkFrame<'a> {
    pub(crate) geometry: &'a ScannerGeometry,
    pub(crate) opts: &'a ScanOptions,
    /// The device's exposure, µs.
    pub(crate) exposure_us: u32,
}

impl DarkFrame<'_> {
    /// Take the dark frame and find the hot (and stuck) pixels it shows; a
    /// dark frame that cannot be taken is said (`None`: the scan goes on
    /// without it), one that shows too much is recorded with none; a frame
    /// of another size or unit stops the scan.
    fn find_hot_pixels(
        &self,
        dev: &mut Device,
        camera: &mut dyn Camera,
        report: &mut ScanReport,
        progress: &mut dyn ScanProgress,
    ) -> Result<Option<DarkRecord>, ScanError> {
        let (frame, strobe) =
            match self.take_with_retries(dev, camera, report, progress, "dark frame")? {
                Ok(f) => f,
                Err(why) => {
                    progress.note(&format!("no dark frame ({why}): hot pixels are not looked for"));
                    return Ok(None);
                }
            };
        let defects =
            match crate::defects::dark_frame_defects(&frame, self.geometry.sensor.max_code()) {
                Ok(found) => {
                    if !found.is_empty() {
                        progress.note(&format!(
                            "sensor defects: {} in a dark frame of {} µs; the frames have them \
                         replaced by their neighbours' mean",
                            crate::defects::counts(&found),
                            self.exposure_us
                        ));
                    }
                    found
                }
                Err(why) => {
                    progress.note(&format!("sensor defects: dark frame: {why}; none replaced"));
                    Vec::new()
                }
            };
        Ok(Some(DarkRecord { exposure_us: self.exposure_us, defects, strobe }))
    }

    /// [`Self::take`], taken again after a failure (said as `what`'s) up
    /// to the scan's attempts; the last failure in words, with their count.
    fn take_with_retries(
        &self,
        dev: &mut Device,
        camera: &mut dyn Camera,
        report: &mut ScanReport,
        progress: &mut dyn ScanProgress,
        what: &str,
    ) -> Result<Result<DarkTaken, String>, ScanError> {
        let mut attempt = 0;
        loop {
            attempt += 1;
            match self.take(dev, camera, report)? {
                Ok(f) => return Ok(Ok(f)),
                Err(why) if attempt >= self.opts.attempts.max(1) => {
                    return Ok(Err(format!("after {attempt} attempts: {why}")));
                }
                Err(why) => {
                    report.retakes += 1;
                    progress.note(&format!("{what}: {why}; taking it again"));
                }
            }
        }
    }

    /// The frame and its exposure as the strobe showed it (`None`: not
    /// watched); a failure in words (the scan may go on); a frame the
    /// camera delivers that is not one of the scan's stops it (another size
    /// or unit: [`crate::camera::check_frame`]), as does a camera whose
    /// exposure strobe says it exposes otherwise than its pulse.
    pub(crate) fn take(
        &self,
        dev: &mut Device,
        camera: &mut dyn Camera,
        report: &mut ScanReport,
    ) -> Result<Result<DarkTaken, String>, ScanError> {
        let (opts, exposure_us) = (self.opts, self.exposure_us);
        let t = Instant::now();
        let fired = (|| -> Result<Option<(TriggerFired, crate::strobe::Report)>, String> {
            let strobe = crate::strobe::watched(dev).map_err(|e| e.to_string())?;
            let off = protocol::LightState { on: false, duty_permille: opts.light_duty_permille };
            dev.command(Request::SetLight(off)).map_err(|e| e.to_string())?;
            camera.arm().map_err(|e| e.to_string())?;
            dev.clear_events();
            dev.command(Request::Trigger { exposure_us }).map_err(|e| e.to_string())?;
            let wait = Duration::from_secs(5) + Duration::from_micros(exposure_us as u64);
            let Some(Event::TriggerFired(fired)) = dev
                .wait_event(wait, |e| matches!(e, Event::TriggerFired(t) if t.mirror.is_none()))
                .map_err(|e| e.to_string())?
            else {
                return Ok(None);
            };
            camera.triggered();
            let exposed = match &strobe {
                Some(s) => crate::strobe::report(dev, &fired, s).map_err(|e| e.to_string())?,
                None => crate::strobe::Report::Unknown,
            };
            Ok(Some((fired, exposed)))
        })();
        report.timings.link += t.elapsed();
        let (fired, exposed) = match fired {
            Ok(Some(f)) => f,
            Ok(None) => return Ok(Err("the device did not fire the trigger".into())),
            Err(why) => return Ok(Err(why)),
        };
        let t = Instant::now();
        let frame = await_frame(camera, exposed, opts.frame_timeout);
        report.timings.camera += t.elapsed();
        // A camera that exposes otherwise than its pulse would do so at
        // every frame of the scan (the light is off: its latency does not
        // matter here).
        let mut window = None;
        if let crate::strobe::Report::Exposed(w) = exposed {
            if let Some(why) = crate::strobe::problem(&w, fired.exposure_us, None) {
                return Err(ScanError::Conflict(format!("a frame with the light off: {why}")));
            }
            window = crate::strobe::Exposure::of(&w);
        }
        let t = Instant::now();
        let idle = wait_idle(dev, Duration::from_secs(10));
        report.timings.link += t.elapsed();
        let frame = match frame {
            Err(e @ CameraError::Unusable(_)) => {
                return Err(ScanError::Conflict(format!("a frame with the light off: {e}")));
            }
            frame => frame.map_err(|e| e.to_string()),
        };
        let status = match idle {
            Ok(status) => status,
            Err(e) => return Ok(Err(e.to_string())),
        };
        if !status.faults.is_empty() {
            return Ok(Err(format!("{} during the dark frame", fault_list(status.faults))));
        }
        Ok(frame.map(|f| (f, window)))
    }
}

/// `opts` for an exposure of `t` µs of light at its duty
/// ([`crate::exposure::realise`]: dimmed below the device's shortest).
fn realised(opts: &ScanOptions, t: u32) -> Result<ScanOptions, ScanError> {
    let (exposure_us, light_duty_permille) = crate::exposure::realise(t, opts.light_duty_permille)
        .ok_or_else(|| {
            ScanError::Conflict(format!(
                "exposure {t} µs outside {}…{} µs",
                crate::exposure::shortest_us(opts.light_duty_permille),
                protocol::MAX_EXPOSURE_US
            ))
        })?;
    Ok(ScanOptions { exposure_us, light_duty_permille, ..opts.clone() })
}

/// How long a frame the camera's strobe says it did not take is waited
/// for, to be set aside, before the step is taken again.
const STRAY_FRAME_WAIT: Duration = Duration::from_millis(200);

/// The frame of the trigger the strobe reported as `exposed`, up to
/// `timeout`; at once [`CameraError::Missed`] when the strobe says the
/// camera did not expose (whatever it delivers after all is set aside then,
/// not taken as the next trigger's frame).
fn await_frame(
    camera: &mut dyn Camera,
    exposed: crate::strobe::Report,
    timeout: Duration,
) -> Result<crate::camera::Frame, CameraError> {
    if exposed == crate::strobe::Report::Missed {
        camera.drain(STRAY_FRAME_WAIT);
        Err(CameraError::Missed)
    } else {
        camera.wait_frame(timeout)
    }
}

/// Capture mirror `l`, taking the step again after a missed frame and
/// recovering from resets and recoverable faults.
pub(crate) fn capture_with_retries(
    dev: &mut Device,
    camera: &mut dyn Camera,
    geometry: &ScannerGeometry,
    l: usize,
    opts: &ScanOptions,
    report: &mut ScanReport,
    progress: &mut dyn ScanProgress,
) -> Result<(Captured, Option<PositionCheck>), ScanError> {
    let mut misses = 0;
    let mut recoveries = 0;
    // Set when the device had to be homed again: the frames before it
    // cannot be verified any more (or were found wrong).
    let mut lost: Option<PositionCheck> = None;
    loop {
        match capture_one(dev, camera, l, opts, &mut report.timings) {
            Ok(r) => return Ok((r, lost)),
            Err(Attempt::Camera(e)) => {
                misses += 1;
                report.retakes += 1;
                progress.note(&format!("mirror {l}: {e}; taking it again"));
                if misses >= opts.attempts {
                    return Err(ScanError::CameraTimeout {
                        mirror: l,
                        attempts: misses,
                        detail: e.to_string(),
                    });
                }
            }
            Err(Attempt::Recover { why, reset, position }) => {
                recoveries += 1;
                report.retakes += 1;
                if reset {
                    report.resets += 1;
                }
                progress.note(&format!("mirror {l}: {why}; recovering"));
                if recoveries > 5 {
                    return Err(ScanError::DeviceFault(format!(
                        "mirror {l}: {why}, again and again"
                    )));
                }
                let t = Instant::now();
                let prepared = prepare(dev, geometry, progress)?;
                report.timings.link += t.elapsed();
                if prepared.homed || position.is_some() {
                    let check =
                        lost.get_or_insert_with(|| PositionCheck::failed(CheckKind::HomingLost));
                    if let Some((axis, error)) = position {
                        check.kind = CheckKind::Index;
                        check.error_steps[axis.index()] = Some(error);
                    }
                }
            }
            Err(Attempt::Fatal(e)) => return Err(e),
        }
    }
}

fn capture_one(
    dev: &mut Device,
    camera: &mut dyn Camera,
    l: usize,
    opts: &ScanOptions,
    timings: &mut ScanTimings,
) -> Result<Captured, Attempt> {
    let t = Instant::now();
    let result = crate::strobe::watched(dev).map_err(Attempt::from).and_then(|strobe| {
        let fired = trigger_step(dev, camera, l, opts)?;
        let status = wait_idle(dev, Duration::from_secs(10))?;
        // The strobe's word on the exposure, before waiting for a frame it
        // may say will not come.
        let exposed = match &strobe {
            Some(s) => crate::strobe::report(dev, &fired, s)?,
            None => crate::strobe::Report::Unknown,
        };
        Ok((fired, status, exposed))
    });
    timings.link += t.elapsed();
    let (fired, status, exposed) = result?;
    let t = Instant::now();
    let frame = if status.faults.is_empty() {
        await_frame(camera, exposed, opts.frame_timeout)
    } else {
        camera.wait_frame(opts.frame_timeout)
    };
    timings.camera += t.elapsed();
    // The device takes no step with a fault latched, so a fault now was
    // raised during this one — an E-stop or a driver fault turns the light
    // off, perhaps in the middle of the exposure. The frame is discarded
    // (taken from the camera first, so that it cannot pass for the next
    // trigger's).
    if !status.faults.is_empty() {
        return Err(match faults_needing_a_person(status.faults) {
            Some(why) => Attempt::Fatal(ScanError::DeviceFault(format!(
                "{why} during mirror {l}'s exposure (its frame is discarded)"
            ))),
            None => Attempt::Recover {
                why: format!(
                    "{} during the exposure; its frame is discarded",
                    fault_list(status.faults)
                ),
                reset: false,
                position: None,
            },
        });
    }
    let frame = frame.map_err(|e| match e {
        // Another size or unit: every retake would be the same.
        CameraError::Unusable(_) => Attempt::Fatal(ScanError::Conflict(format!("mirror {l}: {e}"))),
        e => Attempt::Camera(e),
    })?;
    // A camera that exposes otherwise than the step asks would do so at
    // every retake.
    let window = match exposed {
        crate::strobe::Report::Exposed(w) => Some(w),
        _ => None,
    };
    if let Some(w) = &window
        && let Some(why) = crate::strobe::problem(w, fired.exposure_us, Some(opts.light_margin_us))
    {
        return Err(Attempt::Fatal(ScanError::Conflict(format!("mirror {l}: {why}"))));
    }
    // A window that did not end was refused above.
    Ok((frame, fired, status, window.as_ref().and_then(crate::strobe::Exposure::of)))
}

/// Arm the camera, run the capture step and return its trigger. Events can
/// be lost on a noisy or interrupted link: when the step is over without
/// the event, the device's record of its last trigger is asked for.
fn trigger_step(
    dev: &mut Device,
    camera: &mut dyn Camera,
    l: usize,
    opts: &ScanOptions,
) -> Result<TriggerFired, Attempt> {
    camera.arm().map_err(Attempt::Camera)?;
    let before = dev.status()?.trigger_seq;
    dev.clear_events();
    let step = CaptureStep {
        mirror: l as u8,
        settle_ms: opts.settle_ms,
        exposure_us: opts.exposure_us,
        light_duty_permille: opts.light_duty_permille,
    };
    dev.command(match opts.light_margin_us {
        // Firmware before protocol 1.3 knows only the plain step.
        0 => Request::CaptureStep(step),
        light_margin_us => Request::TimedCaptureStep(TimedCaptureStep { step, light_margin_us }),
    })?;
    // Longest move (half a disk turn, full track) + settle + exposure, with margin.
    let end = dev.now() + Duration::from_secs(30) + Duration::from_micros(opts.exposure_us as u64);
    while dev.now() < end {
        let event = dev.wait_event(Duration::from_millis(500), |e| {
            matches!(e, Event::TriggerFired(t) if t.mirror == Some(l as u8))
                || matches!(e, Event::FaultRaised { .. })
                || matches!(e, Event::MotionDone { outcome: MotionOutcome::Aborted, .. })
        })?;
        match event {
            Some(Event::TriggerFired(t)) => {
                camera.triggered();
                return Ok(t);
            }
            Some(other) => {
                let status = dev.status()?;
                if let Some(names) = faults_needing_a_person(status.faults) {
                    return Err(Attempt::Fatal(ScanError::DeviceFault(names)));
                }
                let position = dev.take_events().into_iter().find_map(|e| match e {
                    Event::PositionChecked { axis, error_steps } => Some((axis, error_steps)),
                    _ => None,
                });
                let why = match (position, other) {
                    (Some((axis, e)), _) => {
                        format!("the {} axis lost steps (off by {e} at its switch)", axis.name())
                    }
                    (None, Event::FaultRaised { faults, .. }) => {
                        format!("capture step stopped by {}", fault_list(faults))
                    }
                    (None, _) => "capture step aborted".into(),
                };
                return Err(Attempt::Recover { why, reset: false, position });
            }
            None => {
                let status = dev.status()?;
                if matches!(status.state, DeviceState::Idle | DeviceState::Faulted) {
                    if status.trigger_seq > before
                        && let Reply::Trigger(Some(t)) = dev.request(Request::GetLastTrigger)?
                        && t.mirror == Some(l as u8)
                        && t.trigger_seq > before
                    {
                        return Ok(t);
                    }
                    return Err(Attempt::Recover {
                        why: "the capture step ended without its trigger".into(),
                        reset: false,
                        position: None,
                    });
                }
            }
        }
    }
    Err(Attempt::Recover {
        why: "no trigger within the step's time".into(),
        reset: false,
        position: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_scan_that_will_not_fit_on_the_disk_is_said_at_its_start() {
        // The default 4096² camera: 13 MB a single frame, 51 MB an HDR merge.
        let (single, hdr) = (frame_bytes(4096, 4096, false), frame_bytes(4096, 4096, true));
        assert!((13_000_000..20_000_000).contains(&single), "{single}");
        assert!((51_000_000..60_000_000).contains(&hdr), "{hdr}");
        assert_eq!(disk_space_note(10_000_000_000, 40, hdr), None);
        let note = disk_space_note(1_000_000_000, 40, hdr).unwrap();
        assert!(
            note.starts_with(
                "the disk has 1.00 GB free; the 40 frames still to take need ≈ 2.15 GB"
            ),
            "{note}"
        );
        assert_eq!(disk_space_note(0, 0, hdr), None, "nothing left to take");
        let note = disk_space_note(5_000_000, 40, frame_bytes(512, 512, true)).unwrap();
        assert!(
            note.starts_with(
                "the disk has 5.0 MB free; the 40 frames still to take need ≈ 33.6 MB"
            ),
            "{note}"
        );
        assert!(scanner_formats::atomic::free_bytes(&std::env::temp_dir()).is_some_and(|b| b > 0));
    }

    #[test]
    fn mirror_lists_name_runs_and_stay_short() {
        assert_eq!(mirror_list(&[]), "no mirror");
        assert_eq!(mirror_list(&[3]), "mirror 3");
        assert_eq!(mirror_list(&[0, 1, 2, 3]), "mirrors 0–3");
        assert_eq!(mirror_list(&[1, 4, 5, 6, 7, 9]), "mirrors 1, 4–7, 9");
        // A damaged manifest's 100 000 mirrors: one run, not 100 000 numbers.
        let many: Vec<usize> = (40..100_000).collect();
        assert_eq!(mirror_list(&many), "mirrors 40–99999");
        let every_other: Vec<usize> = (0..40).step_by(2).collect();
        assert_eq!(
            mirror_list(&every_other),
            "mirrors 0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, … (20 mirrors in all)"
        );
    }

    #[test]
    fn a_full_disk_has_its_own_error_and_exit_code() {
        let e = io_error(Path::new("x.exr"), std::io::Error::from_raw_os_error(28));
        assert!(matches!(e, ScanError::DiskFull(_)), "{e:?}");
        assert_eq!(e.exit_code(), 9);
        let e = io_error(Path::new("x.exr"), std::io::Error::from_raw_os_error(13));
        assert_eq!(e.exit_code(), 4);
    }
}
