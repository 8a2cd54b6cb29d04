//! `scanner`: the command-line front end of the host library (the binary
//! is `fn main() { host::cli::main() }`, so end-to-end tests can build the
//! same program).
//!
//! Exit codes: 0 success, 1 anything else, 2 bad usage, 3 unreadable or
//! invalid input file (or a scan directory holding another scan), 4 output
//! could not be written, 5 no device, 6 incompatible firmware, 7 device
//! fault, 8 camera timeout, 9 disk full, 10 a `scanner check` failed.

mod build;
mod commands;
mod plot;

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use crate::brdf::fit::{FitOptions, GVariant, Samples, Weighting, fit};
use crate::brdf::merl::MerlTable;
use crate::brdf::npf::NpfModel;
use crate::brdf::{BINS, Brdf, render};
use anyhow::Context;
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};

#[derive(Debug, Parser)]
#[command(
    name = "scanner",
    version,
    about = "Material scanner host: capture, materials, BRDF fitting"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run the main job: a complete simulated scan of the three calibration
    /// targets and a material sample, the calibration, the material file and
    /// a preview.
    Demo {
        /// Output folder (one scan directory per sample).
        #[arg(long, default_value = "demo-out")]
        out: PathBuf,
        /// Sample material (woven-fabric, leather, painted-wood, rough-metal,
        /// or a texture-set directory: docs/texture-set.md).
        #[arg(long, default_value = "woven-fabric")]
        material: String,
        /// Sensor binning (1 = the default 4096² sensor; 4 = 1024², faster).
        #[arg(long, default_value_t = 1)]
        bin: u32,
        /// Scan only mirrors 0 … N−1.
        #[arg(long)]
        mirrors: Option<usize>,
        /// Seed of the simulated scanner.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Simulate this scanner, a geometry file (docs/scanner-geometry.md;
        /// default: the shipped default scanner). Its binned geometry is
        /// written to OUT/geometry.toml.
        #[arg(long, value_name = "FILE")]
        geometry: Option<PathBuf>,
        /// The simulated lens and holder (every scan) and how the sample
        /// lies (the sample's scan; the targets lie flat in the holder).
        #[command(flatten)]
        scene: commands::SceneArgs,
    },
    /// Capture a scan into a scan directory.
    Scan {
        #[command(flatten)]
        device: commands::DeviceArgs,
        #[command(flatten)]
        scan: commands::ScanArgs,
    },
    /// Check a scanner end to end, a line each: the link, faults, homing
    /// (repeated), the mirror table, every mirror, the light, the camera,
    /// capture steps with a sample on the holder — a built scanner's
    /// acceptance, or a hardware-in-the-loop test. Moves and homes the
    /// axes, writes nothing to the device. Exit 10 if a check fails.
    Check {
        #[command(flatten)]
        device: commands::DeviceArgs,
        #[command(flatten)]
        check: commands::CheckArgs,
    },
    /// Print the completion script of a shell (bash, zsh, fish, elvish,
    /// powershell), e.g. `scanner completions bash >
    /// ~/.local/share/bash-completion/completions/scanner`.
    Completions {
        /// The shell.
        shell: clap_complete::Shell,
    },
    /// Write the manual pages (`scanner.1`, `scanner-COMMAND.1`, roff) into
    /// DIR, e.g. `scanner man ~/.local/share/man/man1` (then `man scanner-scan`).
    Man {
        /// Output directory: new, or one holding only manual pages of ours
        /// (replaced whole).
        dir: PathBuf,
    },
    /// Check a scan directory: every frame recorded and matching its checksum.
    Verify {
        /// Scan directory.
        dir: PathBuf,
    },
    /// Geometry and colour calibration from a checkerboard scan and a
    /// diffuse-white scan (docs/calibration-format.md).
    Calibrate {
        /// Scan of the checkerboard target.
        #[arg(long)]
        checkerboard: PathBuf,
        /// Scan of the diffuse-white target.
        #[arg(long)]
        white: PathBuf,
        /// Scan of a glossy black target (short exposure): its highlights
        /// fix the light directions (the source's home offsets).
        #[arg(long)]
        glossy: Option<PathBuf>,
        /// Output calibration file (.json).
        #[arg(short, long)]
        output: PathBuf,
        /// Nominal geometry file (default: the shipped scanner, at the scan's sensor size).
        #[arg(long)]
        geometry: Option<PathBuf>,
        /// Albedo of the white target (from its certificate).
        #[arg(long, default_value_t = crate::build::calibrate::DEFAULT_WHITE_ALBEDO)]
        white_albedo: f64,
        /// Squares along each side of the checkerboard (the one at uv 0 light).
        #[arg(long, default_value_t = 8)]
        squares: u32,
    },
    /// Calibrated, rectified region images of a scan, as OpenEXR
    /// (`l{LL}-v{VV}.exr`: f · cos θi per pixel).
    Regions {
        #[command(flatten)]
        input: build::ScanInputs,
        /// Output directory.
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Build a material file from a scan (docs/material-format.md): region
    /// images, palettes and direction tables.
    Build {
        #[command(flatten)]
        input: build::ScanInputs,
        /// Output material file (e.g. NAME.material).
        #[arg(short, long)]
        output: PathBuf,
        /// Colours per palette (1…256).
        #[arg(long, default_value_t = 256)]
        colours: usize,
        /// Lights sharing one index image, the fewest (1…4; each light keeps
        /// its own palette); more share where the file would exceed
        /// --max-size-mb (a 40 × 40 scan at 128² px: 2 or 3).
        #[arg(long, default_value_t = 1)]
        lights_per_index: usize,
        /// Largest file, MB (10⁶ bytes; 0: no limit): where the file would be
        /// larger, more lights share an index image (up to 4).
        #[arg(long, default_value_t = 16.0)]
        max_size_mb: f64,
        /// How directions between the captured ones are shaded.
        #[arg(long, value_parser = ["default", "patent"], default_value = "default")]
        interpolation: String,
        /// Patent table: cells along the azimuth.
        #[arg(long, default_value_t = 1025)]
        patent_columns: u32,
        /// Patent table: cells along the polar angle.
        #[arg(long, default_value_t = 256)]
        patent_rows: u32,
        /// Patent table: random points per cell.
        #[arg(long, default_value_t = 1000)]
        patent_points: u32,
        /// Default interpolation: fit a texel model (Lambert + GGX per
        /// texel) and interpolate the captured images' residuals from it —
        /// `auto` when it predicts held-out lights better.
        #[arg(long, value_parser = ["auto", "on", "off"], default_value = "auto")]
        texel_model: String,
    },
    /// Shade a material at the queries of a query file (docs/query-format.md).
    Shade {
        /// Material file.
        material: PathBuf,
        /// Query file (.npy or .csv).
        #[arg(long)]
        queries: PathBuf,
        /// Answer file (.npy or .csv).
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Enlarge a material scanned on a small sample to a large piece of the
    /// same material seen in direct images (Fig. 9, docs/direct-images.md):
    /// each texel of the piece is matched to the sample's texel whose
    /// colours around it look most alike in every direct image. The output
    /// material's uv spans the piece.
    Enlarge {
        /// Material file of the sample (from `scanner build`).
        material: PathBuf,
        /// Directory of direct images with their `direct.toml`
        /// (`hil-sim direct` writes one).
        #[arg(long)]
        direct: PathBuf,
        /// Output material file.
        #[arg(short, long)]
        output: PathBuf,
        /// The signature's neighbourhood: (2 R + 1)² texels (1: the
        /// patent's 3 × 3; 0…3).
        #[arg(long, default_value_t = crate::build::enlarge::EnlargeOptions::DEFAULT.radius)]
        radius: usize,
        /// Candidate points per texel of the sample along u and v (1…4): a
        /// texel of the piece may match a point between the sample's texels.
        #[arg(long, default_value_t = crate::build::enlarge::EnlargeOptions::DEFAULT.subtexel)]
        subtexel: usize,
        /// What a texel's signature holds: `colour`, its neighbourhood's
        /// RGB in every direct image; `height`, its neighbourhood's heights
        /// from photometric stereo over them (≥ 3 images whose directions
        /// are not in one plane; needs no white reference).
        #[arg(long, value_parser = ["colour", "height"],
              default_value = crate::build::enlarge::EnlargeOptions::DEFAULT.signature.name())]
        signature: String,
    },
    /// Rectify a photograph of a flat piece, taken in perspective, onto the
    /// piece: a direct image for `scanner enlarge` (docs/direct-images.md).
    /// Mark the piece's four corners in the photograph.
    Rectify {
        /// The photograph: linear OpenEXR (RGB).
        photo: PathBuf,
        /// The piece's corners in the photograph, px (pixel (c, r) spans
        /// [c, c + 1) × [r, r + 1)): X0,Y0,X1,Y1,X2,Y2,X3,Y3 for the
        /// piece's (0, 0), (1, 0), (1, 1), (0, 1) — u along the output's
        /// columns, v down its rows. Or `auto`: found in the photograph,
        /// the piece lying on a plain background darker or lighter than
        /// all of it (see --origin).
        #[arg(long, value_delimiter = ',', allow_hyphen_values = true, required = true)]
        corners: Vec<String>,
        /// With `--corners auto`: where in the photograph the piece's
        /// (0, 0) corner lies; (1, 0), (1, 1), (0, 1) follow
        /// counter-clockwise as the photograph is seen [default:
        /// bottom-left: the piece face up, u to the right, v up].
        #[arg(long, value_parser = clap::builder::PossibleValuesParser::new(
            crate::build::corners::Origin::ALL.map(|(name, _)| name)))]
        origin: Option<String>,
        /// With marked corners: move them onto the piece's edges, fitted
        /// as `--corners auto` fits them (marks within a few px).
        #[arg(long)]
        refine: bool,
        /// The lens' radial distortion: K1[,K2[,FOCAL_PX[,CX,CY]]]
        /// (Brown–Conrady, OpenCV's k1, k2 when FOCAL_PX is the
        /// calibration's focal length, about its principal point CX, CY,
        /// px; without them the radius is in half-diagonals of the
        /// photograph, about its centre), or `auto`: k1 estimated from the
        /// piece's own straight sides (with found or refined corners; a
        /// plain card's sides give it best) [default: none, a pinhole].
        #[arg(long, allow_hyphen_values = true)]
        lens: Option<String>,
        /// The piece's width and height, mm: W,H (one number: a square).
        #[arg(long, value_delimiter = ',', required = true)]
        size_mm: Vec<f64>,
        /// Output pixels per mm [default: the photograph's own, where it
        /// resolves the piece least].
        #[arg(long)]
        px_per_mm: Option<f64>,
        /// Output picture (.exr: linear, half float).
        #[arg(short, long)]
        output: PathBuf,
        /// Also write the photograph with the piece's outline and corners
        /// drawn on it (.png), to check them.
        #[arg(long)]
        show: Option<PathBuf>,
    },
    /// A preview PNG of a material: the sample's extent under three light
    /// directions, seen from the direction farthest from every captured view
    /// (20°…45° from the normal).
    Preview {
        /// Material file.
        material: PathBuf,
        /// Output picture (.png).
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Export a material's fitted texel model as a texture set
    /// (docs/texture-set.md): diffuse albedo, F0, roughness and normal maps
    /// for physically based renderers, which the simulator also scans; or
    /// as a glTF 2.0 asset that any glTF viewer opens. What the model does
    /// not explain stays in the material file only.
    Export {
        /// Material file (built with a texel model).
        material: PathBuf,
        /// Output directory (created, or replaced if it holds only a
        /// texture set's or a glTF asset's files); with `--format glb`, the
        /// output file (.glb).
        #[arg(short, long)]
        output: PathBuf,
        /// Map files: `exr` (32-bit float, linear) or `png` (16-bit; diffuse
        /// and specular sRGB-encoded); or `gltf`: a glTF 2.0 asset
        /// (material.gltf, its buffer and four 8-bit PNG maps: base colour,
        /// metallic-roughness, normal, KHR_materials_specular's specular
        /// colour); or `glb`: the same as one binary
        /// glTF file (the output is then a .glb file).
        #[arg(long, value_parser = ["exr", "png", "gltf", "glb"], default_value = "exr")]
        format: String,
    },
    /// Check a scanner's design before building or scanning with it: per
    /// mirror its view and light directions, the axis positions, where the
    /// sample appears on the sensor and how many pixels it covers, and
    /// whatever would make a scan fail — views off the sensor or too close
    /// to each other, mirrors too small or in each other's way, light that
    /// does not cover the sample or lights two mirrors at once. Exit 3 if
    /// anything would.
    Geometry {
        /// Geometry file (default: the shipped default scanner); with
        /// --rings, the scanner whose mirrors they replace.
        #[arg(long)]
        geometry: Option<PathBuf>,
        /// Mirrors on rings instead, tangent to the ellipsoid:
        /// THETA:COUNT,… (polar angle from the sample normal in degrees,
        /// mirrors on that ring; the odd rings staggered by half a
        /// mirror, as the default's, 15:4,31.667:9,48.333:12,65:15).
        #[arg(long, value_delimiter = ',', value_parser = parse_ring, value_name = "THETA:COUNT")]
        rings: Vec<(f64, usize)>,
        /// Write the geometry checked (.toml) here, if it is sound.
        #[arg(short, long)]
        output: Option<PathBuf>,
        /// Check the axes' travel against this axis configuration file
        /// (docs/axis-config.md; `scanner axes -o` writes a device's)
        /// instead of the spec's default axes.
        #[arg(long, value_name = "FILE", conflicts_with = "device")]
        axes: Option<PathBuf>,
        /// Check the axes' travel against this connected device's axis
        /// configuration (`sim`, a serial port, `usb:SERIAL`, a serial
        /// number).
        #[arg(long)]
        device: Option<String>,
        /// With `--device sim`: the drives the simulated scanner is built
        /// with (as `--sim-axes` elsewhere).
        #[arg(long, value_name = "FILE", requires = "device")]
        sim_axes: Option<PathBuf>,
        /// With `--device sim`: its board's axis configuration (as
        /// `--sim-board-axes` elsewhere).
        #[arg(long, value_name = "FILE", requires = "device")]
        sim_board_axes: Option<PathBuf>,
    },
    /// Write the mirror table (from the geometry's inverse kinematics) to the device.
    Setup {
        #[command(flatten)]
        device: commands::DeviceArgs,
        /// Nominal geometry file (default: the shipped default scanner).
        #[arg(long)]
        geometry: Option<PathBuf>,
    },
    /// List connected scanners (serial ports and USB).
    Devices,
    /// Show or set the board's wiring options (saved to the device's flash).
    Config {
        #[command(flatten)]
        device: commands::DeviceArgs,
        /// Polarity of the drivers' fault line: active-low (DRV8825 nFAULT,
        /// the default) or active-high (TMC2209 DIAG). A driver fault latched
        /// because the line was read the wrong way round is cleared by setting
        /// the right one; a polarity under which the line reads a fault is
        /// not saved.
        #[arg(long, value_parser = ["active-low", "active-high"])]
        driver_fault: Option<String>,
        /// Polarity of an axis' home / index sensor, `AXIS=active-low`
        /// (a switch or open-collector sensor to ground; the default) or
        /// `AXIS=active-high` (a push-pull optical or Hall sensor whose
        /// output is high when actuated); comma-separated or repeated. An
        /// axis whose polarity changes must be homed again.
        #[arg(long, value_delimiter = ',', value_parser = parse_home_sensor, value_name = "AXIS=POLARITY")]
        home_sensor: Vec<(protocol::Axis, bool)>,
        /// Watch the camera's "exposure active" strobe, wired to the
        /// board's strobe input: active-high (a push-pull output, high
        /// while exposing), active-low (open collector), or off (the
        /// default). Watched, every capture step's exposure is checked: a
        /// missed trigger is taken again at once, and a camera exposing
        /// for another time than its pulse, or past the light, stops the
        /// scan with what to set.
        #[arg(long, value_parser = ["off", "active-low", "active-high"])]
        strobe: Option<String>,
        /// How far the strobe may lag its trigger pulse before the camera
        /// counts as having missed it, µs (default 10000).
        #[arg(long, value_name = "US", value_parser = clap::value_parser!(u32).range(1..=protocol::MAX_STROBE_DELAY_US as i64))]
        strobe_max_delay_us: Option<u32>,
    },
    /// Show or set the device's axis configurations — steps per unit,
    /// travel, speeds, homing (docs/axis-config.md) — for a scanner built
    /// with other drives than the spec's.
    Axes {
        #[command(flatten)]
        device: commands::DeviceArgs,
        /// Make the device's axes this file's (checked first; saved to the
        /// device's flash). Changed axes must be homed again.
        #[arg(long, value_name = "FILE")]
        set: Option<PathBuf>,
        /// Correct an axis by a move measured on the machine: told to move
        /// COMMANDED (°, mm), it moved MEASURED (`track=100:98.7`). Scales
        /// its steps per unit by COMMANDED / MEASURED, keeping its travel,
        /// home position and homing distances in units and its speeds in
        /// steps/s; applied to the device's axes (or to --set's file), then
        /// set and saved like --set. Repeatable, one per axis.
        #[arg(long, value_name = "AXIS=COMMANDED:MEASURED")]
        correct: Vec<scanner_geometry::Measured>,
        /// Write the device's axis configurations (.toml) here.
        #[arg(short, long)]
        output: Option<PathBuf>,
    },
    /// Clear the device's latched faults (a failed homing, a lost link, an
    /// emergency stop once released…).
    Clear {
        #[command(flatten)]
        device: commands::DeviceArgs,
    },
    /// Handshake and print the device's identity and axes.
    Info {
        #[command(flatten)]
        device: commands::DeviceArgs,
    },
    /// Print the device status.
    Status {
        #[command(flatten)]
        device: commands::DeviceArgs,
    },
    /// Print the board's inputs — home sensors, emergency stop, driver
    /// fault: each line's level and what the board makes of it — for
    /// wiring a board up.
    Inputs {
        #[command(flatten)]
        device: commands::DeviceArgs,
        /// Then print every change for SECONDS (no value: until Ctrl-C):
        /// press a switch by hand and see it.
        #[arg(long, num_args = 0..=1, default_missing_value = "0", value_name = "SECONDS")]
        watch: Option<f64>,
    },
    /// Home axes (all by default).
    Home {
        #[command(flatten)]
        device: commands::DeviceArgs,
        /// Axes to home (disk, track, tilt).
        #[arg(long, value_delimiter = ',', value_parser = parse_axis)]
        axes: Vec<protocol::Axis>,
        /// Then N times: send the axes far along their travel at their
        /// configured speed and home them again, reporting each axis' step
        /// count at its switch — a check that the drives keep their steps
        /// and the switches repeat (exit 7 if steps were lost).
        #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=1000))]
        repeat: Option<u32>,
    },
    /// Move axes (degrees / mm, or steps with --steps), or to a mirror's
    /// table entry (--mirror).
    Move {
        #[command(flatten)]
        device: commands::DeviceArgs,
        /// Disk target.
        #[arg(long, allow_negative_numbers = true)]
        disk: Option<f64>,
        /// Track target.
        #[arg(long, allow_negative_numbers = true)]
        track: Option<f64>,
        /// Tilt target.
        #[arg(long, allow_negative_numbers = true)]
        tilt: Option<f64>,
        /// Targets are offsets from the current position.
        #[arg(long)]
        relative: bool,
        /// Targets are in steps.
        #[arg(long)]
        steps: bool,
        /// Go to this mirror's entry of the device's mirror table (where
        /// the light lands on mirror N: with `scanner light on`, to check
        /// the table against the machine).
        #[arg(long, value_name = "N", conflicts_with_all = ["disk", "track", "tilt", "relative", "steps"])]
        mirror: Option<u8>,
    },
    /// Send the controller into its chip's ROM bootloader (USB DFU), to
    /// flash new firmware without a probe (README "Flashing over USB").
    Bootloader {
        #[command(flatten)]
        device: commands::DeviceArgs,
    },
    /// Switch the light on or off.
    Light {
        #[command(flatten)]
        device: commands::DeviceArgs,
        /// on or off.
        #[arg(value_parser = ["on", "off"])]
        state: String,
        /// Duty, per mille.
        #[arg(long, default_value_t = 1000)]
        duty: u16,
    },
    /// Fire one camera trigger pulse.
    Trigger {
        #[command(flatten)]
        device: commands::DeviceArgs,
        /// Exposure (pulse length), µs.
        #[arg(long, default_value_t = protocol::DEFAULT_EXPOSURE_US)]
        exposure_us: u32,
    },
    /// Serve the simulated scanner on a pty for interactive use; its camera
    /// drops frames into a folder.
    Sim {
        #[command(flatten)]
        device: commands::DeviceArgs,
        /// Simulated time per real time.
        #[arg(long, default_value_t = 1.0)]
        speed: f64,
        /// Folder for the camera's frames.
        #[arg(long, default_value = "sim-frames")]
        frames: PathBuf,
        /// The files the simulated camera writes: OpenEXR (floats), or
        /// 16-bit PNG or TIFF of its codes (as --frame-codes says).
        #[arg(long, value_enum, default_value_t = commands::FrameFormat::Exr)]
        frame_format: commands::FrameFormat,
        /// How PNG and TIFF frames hold the codes (scan them with the same
        /// --camera-codes).
        #[arg(long, value_enum, default_value_t = commands::CameraCodes::Native)]
        frame_codes: commands::CameraCodes,
        /// Serve the board as a USB port: PATH is a symbolic link to its
        /// pty, removed while the board is unplugged (a disconnect fault,
        /// a reset: the host's port fails as on a real unplug) and made to
        /// a new pty when it is back, as udev's /dev/serial/by-id links
        /// are. An existing PATH is replaced only if it is a link, and not
        /// while another simulator serves there.
        #[arg(long, value_name = "PATH")]
        link: Option<PathBuf>,
    },
    /// Fit an NPF model to a MERL table.
    Fit {
        /// MERL binary table (.binary), or scattered measurements (.csv:
        /// wi_x,wi_y,wi_z,wo_x,wo_y,wo_z,r,g,b; docs/npf-format.md).
        input: PathBuf,
        /// Output model (.json).
        #[arg(short, long)]
        output: PathBuf,
        /// How G is obtained.
        #[arg(long, value_enum, default_value_t = GVariant::Smith)]
        g: GVariant,
        /// Compressive weighting exponent p ∈ [1, 2].
        #[arg(long, default_value_t = 1.4)]
        p: f64,
        /// Iteration limit.
        #[arg(long, default_value_t = 60)]
        max_iterations: usize,
    },
    /// Render a sphere of a model or a MERL table under the built-in environment.
    RenderBrdf {
        /// NPF model (.json) or MERL table (.binary).
        input: PathBuf,
        /// Output image (.png tone-mapped, or .exr linear).
        #[arg(short, long)]
        output: PathBuf,
        /// Image side, pixels.
        #[arg(long, default_value_t = 256)]
        size: usize,
    },
    /// Write an analytic reference material as a MERL table (for trying the
    /// pipeline without measured data).
    SynthMerl {
        /// Which material.
        #[arg(long, value_enum)]
        material: Material,
        /// Output table (.binary).
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Plot an NPF model's D, F and G per channel.
    PlotNpf {
        /// NPF model (.json).
        input: PathBuf,
        /// Output image (.png).
        #[arg(short, long)]
        output: PathBuf,
    },
}

/// Analytic reference materials.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum Material {
    /// GGX conductor, α = 0.2.
    Ggx,
    /// Beckmann conductor, α = 0.3.
    Beckmann,
    /// Lambert base under a GGX dielectric coat, energy-coupled.
    Coated,
    /// The same, seen through the smooth-interface Fresnel transmission.
    CoatedFresnel,
    /// Two-lobe GGX mixture.
    TwoLobe,
}

/// An error with its exit code.
#[derive(Debug)]
pub struct Failure(pub u8, pub anyhow::Error);

/// `AXIS=active-high|active-low` → (axis, active high).
/// `THETA:COUNT` → (polar angle in degrees, mirrors on the ring).
fn parse_ring(s: &str) -> Result<(f64, usize), String> {
    let bad = || format!("{s:?}: give THETA:COUNT, e.g. 31.7:9 (0 < THETA < 90, COUNT ≥ 1)");
    let (theta, count) = s.split_once(':').ok_or_else(bad)?;
    let theta: f64 = theta.trim().parse().map_err(|_| bad())?;
    let count: usize = count.trim().parse().map_err(|_| bad())?;
    if !(theta > 0.0 && theta < 90.0) || count == 0 || count > protocol::MAX_MIRRORS {
        return Err(bad());
    }
    Ok((theta, count))
}

fn parse_home_sensor(s: &str) -> Result<(protocol::Axis, bool), String> {
    let (axis, polarity) = s
        .split_once('=')
        .ok_or_else(|| format!("{s:?}: give AXIS=active-high or AXIS=active-low"))?;
    Ok((parse_axis(axis)?, parse_polarity(polarity)?))
}

/// `active-high|active-low` → active high.
pub(crate) fn parse_polarity(s: &str) -> Result<bool, String> {
    match s {
        "active-high" => Ok(true),
        "active-low" => Ok(false),
        other => Err(format!("{other:?}: active-high or active-low")),
    }
}

pub(crate) fn parse_axis(s: &str) -> Result<protocol::Axis, String> {
    protocol::Axis::ALL
        .into_iter()
        .find(|a| a.name() == s)
        .ok_or_else(|| format!("unknown axis {s:?} (disk, track, tilt)"))
}

fn input<T>(r: anyhow::Result<T>) -> Result<T, Failure> {
    r.map_err(|e| Failure(3, e))
}

fn output<T>(r: anyhow::Result<T>) -> Result<T, Failure> {
    r.map_err(|e| Failure(4, e))
}

/// `scanner rectify`'s corners, lens and size from its arguments (exit 2:
/// their count, a number that is not one, `--origin` with marked corners,
/// `--refine` with `auto`, `--lens auto` with marked corners, a lens out
/// of range).
fn rectify_options(
    corners: &[String],
    origin: Option<&str>,
    refine: bool,
    lens: Option<&str>,
    size_mm: &[f64],
) -> Result<(crate::build::rectify::Corners, crate::build::lens::LensChoice, [f64; 2]), Failure> {
    use crate::build::corners::Origin;
    use crate::build::lens::{Lens, LensChoice};
    use crate::build::rectify::Corners;
    let bad = |m: String| Failure(2, anyhow::anyhow!(m));
    let corners = if let [auto] = corners
        && auto == "auto"
    {
        if refine {
            return Err(bad("--refine goes with marked corners: found ones are refined".into()));
        }
        let origin = origin.map_or(Some(Origin::BottomLeft), Origin::from_name);
        Corners::Auto(origin.ok_or_else(|| bad(format!("--origin {origin:?}")))?)
    } else {
        if origin.is_some() {
            return Err(bad(
                "--origin goes with --corners auto: marked corners say their order".into()
            ));
        }
        let numbers = corners
            .iter()
            .map(|c| {
                c.trim()
                    .parse::<f64>()
                    .map_err(|_| bad(format!("--corners: {c:?} is not a number")))
            })
            .collect::<Result<Vec<f64>, Failure>>()?;
        let n: [f64; 8] = numbers.as_slice().try_into().map_err(|_| {
            bad(format!("--corners: auto, or 8 numbers (X0,Y0,…,X3,Y3), not {}", numbers.len()))
        })?;
        let marked = std::array::from_fn(|k| [n[2 * k], n[2 * k + 1]]);
        if refine { Corners::Refined(marked) } else { Corners::Marked(marked) }
    };
    let lens = match lens {
        None => LensChoice::Known(Lens::PINHOLE),
        Some("auto") => {
            if let Corners::Marked(_) = corners {
                return Err(bad("--lens auto estimates the lens from the piece's sides: with \
                                --corners auto or --refine"
                    .into()));
            }
            LensChoice::Estimate
        }
        Some(text) => LensChoice::Known(Lens::parse(text).map_err(bad)?),
    };
    let size_mm = match *size_mm {
        [side] => [side, side],
        [w, h] => [w, h],
        _ => return Err(bad(format!("--size-mm: W,H or one side, not {} numbers", size_mm.len()))),
    };
    Ok((corners, lens, size_mm))
}

/// Before any work: the output may be written (not a device node, symlink,
/// directory or the input: exit 4), then has one of the file types the
/// command writes (exit 2).
fn check_output(out: &Path, inputs: &[&Path], types: &[&str]) -> Result<(), Failure> {
    crate::fsutil::check_output(out, inputs).map_err(|e| Failure(4, anyhow::anyhow!(e)))?;
    let ext = out.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
    if !types.is_empty() && !ext.as_deref().is_some_and(|e| types.contains(&e)) {
        return Err(Failure(
            2,
            anyhow::anyhow!("{}: the output must be .{}", out.display(), types.join(" or .")),
        ));
    }
    Ok(())
}

fn load_brdf(path: &Path) -> anyhow::Result<Box<dyn Brdf>> {
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or_default();
    if ext.eq_ignore_ascii_case("json") {
        Ok(Box::new(NpfModel::load(path)?))
    } else {
        Ok(Box::new(MerlTable::read(path)?))
    }
}

/// Fitting samples from a MERL table or (`.csv`) scattered measurements.
fn load_samples(path: &Path) -> anyhow::Result<Samples> {
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or_default();
    if ext.eq_ignore_ascii_case("csv") {
        let m = crate::brdf::measurements::read_csv(path)?;
        Samples::from_measurements(&m)
            .with_context(|| format!("no usable measurement in {}", path.display()))
    } else {
        let table = MerlTable::read(path)?;
        Samples::from_merl(&table).context("no usable sample in the table")
    }
}

fn run(cli: Cli) -> Result<(), Failure> {
    match cli.command {
        Command::Demo { out, material, bin, mirrors, seed, geometry, scene } => {
            commands::demo(&out, &material, bin, mirrors, seed, geometry.as_deref(), &scene)?
        }
        Command::Scan { device, scan } => commands::scan_cmd(&device, &scan)?,
        Command::Check { device, check } => commands::check(&device, &check)?,
        Command::Bootloader { device } => commands::bootloader(&device)?,
        Command::Geometry { geometry, rings, output, axes, device, sim_axes, sim_board_axes } => {
            if let Some(out) = &output {
                let inputs: Vec<&Path> =
                    geometry.iter().chain(&axes).map(PathBuf::as_path).collect();
                check_output(out, &inputs, &["toml"])?;
            }
            let travel = match (&axes, &device) {
                (Some(file), _) => Some((
                    scanner_geometry::load_axes(file)
                        .map_err(|e| Failure(3, anyhow::anyhow!(e)))?,
                    format!("the axes of {}", file.display()),
                )),
                (None, Some(name)) => {
                    let sim = [("--sim-axes", &sim_axes), ("--sim-board-axes", &sim_board_axes)];
                    let axes = commands::device_axes(name, &sim)?;
                    Some((axes, format!("the axes of device {name}")))
                }
                (None, None) => None,
            };
            build::geometry_cmd(geometry.as_deref(), &rings, output.as_deref(), travel)?
        }
        Command::Axes { device, set, correct, output } => {
            if let Some(out) = &output {
                let inputs: Vec<&Path> = set.iter().map(PathBuf::as_path).collect();
                check_output(out, &inputs, &["toml"])?;
            }
            commands::axes(&device, set.as_deref(), &correct, output.as_deref())?
        }
        Command::Setup { device, geometry } => commands::setup(&device, geometry.as_deref())?,
        Command::Devices => commands::devices()?,
        Command::Config { device, driver_fault, home_sensor, strobe, strobe_max_delay_us } => {
            let strobe = commands::StrobeChange {
                watch: strobe.map(|s| (s != "off").then_some(s == "active-high")),
                max_delay_us: strobe_max_delay_us,
            };
            let driver_fault = driver_fault.map(|p| p == "active-high");
            commands::board_config(&device, driver_fault, &home_sensor, strobe)?
        }
        Command::Completions { shell } => {
            use clap::CommandFactory;
            let mut out = std::io::stdout().lock();
            clap_complete::generate(shell, &mut Cli::command(), "scanner", &mut out);
            std::io::Write::flush(&mut out).map_err(|e| Failure(1, e.into()))?;
        }
        Command::Man { dir } => man_pages(&dir)?,
        Command::Verify { dir } => commands::verify(&dir)?,
        Command::Clear { device } => commands::clear(&device)?,
        Command::Calibrate {
            checkerboard,
            white,
            glossy,
            output,
            geometry,
            white_albedo,
            squares,
        } => build::calibrate_cmd(
            &checkerboard,
            &white,
            glossy.as_deref(),
            &output,
            geometry.as_deref(),
            white_albedo,
            squares,
        )?,
        Command::Regions { input, output } => build::regions_cmd(&input, &output).map(|_| ())?,
        Command::Build {
            input,
            output,
            colours,
            lights_per_index,
            max_size_mb,
            interpolation,
            patent_columns,
            patent_rows,
            patent_points,
            texel_model,
        } => {
            let interpolation = if interpolation == "patent" {
                scanner_shading::Interpolation::Patent {
                    columns: patent_columns,
                    rows: patent_rows,
                    points: patent_points,
                }
            } else {
                scanner_shading::Interpolation::Default
            };
            if !(max_size_mb.is_finite() && max_size_mb >= 0.0) {
                return Err(Failure(
                    2,
                    anyhow::anyhow!("--max-size-mb {max_size_mb}: a size in MB, or 0 for no limit"),
                ));
            }
            let opts = crate::build::material::MaterialOptions {
                colours,
                lights_per_index,
                max_bytes: (max_size_mb > 0.0).then_some((max_size_mb * 1e6) as usize),
                interpolation,
                texel_model: texel_model.parse().map_err(|e| Failure(2, anyhow::anyhow!("{e}")))?,
                ..Default::default()
            };
            build::build_cmd(&input, &output, &opts).map(|_| ())?
        }
        Command::Shade { material, queries, output } => {
            build::shade_cmd(&material, &queries, &output)?
        }
        Command::Enlarge { material, direct, output, radius, subtexel, signature } => {
            let signature = signature.parse().map_err(|e| Failure(2, anyhow::anyhow!("{e}")))?;
            let opts = crate::build::enlarge::EnlargeOptions { radius, subtexel, signature };
            build::enlarge_cmd(&material, &direct, &output, &opts)?
        }
        Command::Rectify {
            photo,
            corners,
            origin,
            refine,
            lens,
            size_mm,
            px_per_mm,
            output,
            show,
        } => {
            check_output(&output, &[&photo], &["exr"])?;
            if let Some(show) = &show {
                check_output(show, &[&photo, &output], &["png"])?;
            }
            let (corners, lens, size_mm) =
                rectify_options(&corners, origin.as_deref(), refine, lens.as_deref(), &size_mm)?;
            let out = build::RectifyOutputs { picture: &output, show: show.as_deref() };
            build::rectify_cmd(&photo, corners, lens, size_mm, px_per_mm, out)?;
        }
        Command::Preview { material, output } => build::preview_cmd(&material, &output)?,
        Command::Export { material, output, format } => {
            let format = format.parse().map_err(|e| Failure(2, anyhow::anyhow!("{e}")))?;
            build::export_cmd(&material, &output, format)?
        }
        Command::Info { device } => commands::info(&device)?,
        Command::Status { device } => commands::status(&device)?,
        Command::Inputs { device, watch } => commands::inputs(&device, watch)?,
        Command::Home { device, axes, repeat } => commands::home(&device, &axes, repeat)?,
        Command::Move { device, mirror: Some(mirror), .. } => {
            commands::move_to_mirror(&device, mirror)?
        }
        Command::Move { device, disk, track, tilt, relative, steps, mirror: None } => {
            commands::move_axes(&device, [disk, track, tilt], relative, steps)?
        }
        Command::Light { device, state, duty } => commands::light(&device, state == "on", duty)?,
        Command::Trigger { device, exposure_us } => commands::trigger(&device, exposure_us)?,
        Command::Sim { device, speed, frames, frame_format, frame_codes, link } => {
            commands::sim(&device, speed, &frames, frame_format, frame_codes, link.as_deref())?
        }
        Command::Fit { input: path, output: out, g, p, max_iterations } => {
            if !(1.0..=2.0).contains(&p) {
                return Err(Failure(2, anyhow::anyhow!("--p must be in [1, 2], got {p}")));
            }
            check_output(&out, &[&path], &["json"])?;
            let samples = input(load_samples(&path))?;
            for c in samples.black_channels() {
                eprintln!(
                    "scanner: warning: channel {c} is zero wherever measured: its model is black"
                );
            }
            let opts = FitOptions {
                g,
                weighting: Weighting::Compressive { p },
                max_iterations,
                ..FitOptions::default()
            };
            let bar = progress_bar((3 * max_iterations) as u64);
            bar.set_style(
                ProgressStyle::with_template(
                    "{spinner} fitting [{bar:30}] {pos}/{len} iterations {msg}",
                )
                .expect("valid template"),
            );
            let progress = |c: usize, it: usize, e: f64| {
                bar.inc(1);
                bar.set_message(format!("{} #{it}: E = {e:.4e}", ["R", "G", "B"][c]));
            };
            let (model, report) = fit(&samples, &opts, &progress);
            bar.finish_and_clear();
            // The measurements leave the factors' peaks where no sample is:
            // the model would predict beyond any BRDF there.
            input(model.check().map_err(|why| {
                anyhow::anyhow!(
                    "the fitted model is out of range ({why}): the measurements do not determine it; measure more directions"
                )
            }))?;
            output(model.save(&out).with_context(|| format!("cannot write {}", out.display())))?;
            println!(
                "fitted {} samples in {:.2} s ({:?} G, p = {p})",
                samples.len(),
                report.seconds,
                g
            );
            let [d, f] = samples.bins_without_samples();
            if d + f > 0 {
                println!(
                    "  {d} of {BINS} θh bins (D) and {f} of {BINS} θd bins (F) hold no \
                     measurement: interpolated from their neighbours"
                );
            }
            for c in 0..3 {
                println!(
                    "  {}: objective {:.4e}, {} iterations, {} line searches",
                    ["R", "G", "B"][c],
                    report.objective[c],
                    report.iterations[c],
                    report.line_searches[c]
                );
            }
            println!("model written to {}", out.display());
        }
        Command::RenderBrdf { input: path, output: out, size } => {
            if !(8..=4096).contains(&size) {
                return Err(Failure(2, anyhow::anyhow!("--size must be in 8..=4096")));
            }
            check_output(&out, &[&path], &["png", "exr"])?;
            let brdf =
                input(load_brdf(&path).with_context(|| format!("cannot load {}", path.display())))?;
            let image = render::render_sphere(brdf.as_ref(), &render::Environment::builtin(), size);
            output(
                render::save(&image, &out)
                    .with_context(|| format!("cannot write {}", out.display())),
            )?;
            println!("sphere written to {}", out.display());
        }
        Command::SynthMerl { material, output: out } => {
            crate::fsutil::check_output(&out, &[]).map_err(|e| Failure(4, anyhow::anyhow!(e)))?;
            use crate::brdf::analytic::*;
            let b = match material {
                Material::Ggx => ggx_conductor(0.2),
                Material::Beckmann => beckmann_conductor(0.3),
                Material::Coated => coated_plastic(),
                Material::CoatedFresnel => coated_plastic_fresnel(),
                Material::TwoLobe => two_lobe_ggx(),
            };
            let table = MerlTable::from_fn(|wi, wo| b.eval(wi, wo));
            output(table.write(&out).with_context(|| format!("cannot write {}", out.display())))?;
            println!("{material:?} table written to {}", out.display());
        }
        Command::PlotNpf { input: path, output: out } => {
            check_output(&out, &[&path], &["png"])?;
            let model = input(NpfModel::load(&path).map_err(anyhow::Error::from))?;
            output(plot::plot_factors(&model, &out).map_err(anyhow::Error::from))?;
            println!("factor plot written to {}", out.display());
        }
    }
    Ok(())
}

/// Every progress bar is drawn through this, so that log lines are printed
/// above the bars instead of across them.
fn bars() -> &'static indicatif::MultiProgress {
    static BARS: std::sync::OnceLock<indicatif::MultiProgress> = std::sync::OnceLock::new();
    BARS.get_or_init(indicatif::MultiProgress::new)
}

/// A progress bar on stderr (hidden when stderr is not a terminal).
fn progress_bar(len: u64) -> ProgressBar {
    bars().add(ProgressBar::new(len))
}

/// Log lines (tracing) on stderr, with the bars lifted out of the way.
struct LogWriter;

impl std::io::Write for LogWriter {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        bars().suspend(|| std::io::stderr().write_all(buf))?;
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        std::io::stderr().flush()
    }
}

/// Whether `name` is one of the manual pages `scanner man` writes.
fn is_man_page(name: &str) -> bool {
    (name == "scanner.1" || name.starts_with("scanner-")) && name.ends_with(".1")
}

/// `scanner man DIR`: a page for the program and one for every command,
/// rendered by clap_mangen from the parser itself, written into a fresh
/// directory that then replaces DIR whole (as `scanner regions` does).
fn man_pages(dir: &Path) -> Result<(), Failure> {
    use clap::CommandFactory;
    crate::fsutil::check_output_dir(dir, is_man_page)
        .map_err(|e| Failure(4, anyhow::anyhow!(e)))?;
    let mut cli = Cli::command().disable_help_subcommand(true);
    cli.build();
    // Every command's page, its own commands' first (as clap_mangen's
    // `generate_to` orders them).
    fn render(cmd: clap::Command, pages: &mut Vec<(String, Vec<u8>)>) -> std::io::Result<()> {
        for sub in cmd.get_subcommands().filter(|s| !s.is_hide_set()).cloned() {
            render(sub, pages)?;
        }
        let man = clap_mangen::Man::new(cmd);
        let mut roff = Vec::new();
        man.render(&mut roff)?;
        pages.push((man.get_filename(), roff));
        Ok(())
    }
    let place = |e: std::io::Error| Failure(4, anyhow::anyhow!("{}: {e}", dir.display()));
    let mut pages = Vec::new();
    render(cli, &mut pages).map_err(place)?;
    let staging = crate::fsutil::staging_dir(dir).map_err(place)?;
    for (name, roff) in &pages {
        std::fs::write(staging.path().join(name), roff).map_err(place)?;
    }
    crate::fsutil::replace_dir(staging, dir).map_err(place)?;
    println!(
        "{} manual pages in {}: man -l {}",
        pages.len(),
        dir.display(),
        dir.join("scanner.1").display()
    );
    Ok(())
}

/// The `scanner` program.
pub fn main() -> ExitCode {
    use std::io::IsTerminal;
    // Rust ignores SIGPIPE, so that printing into a closed pipe (`scanner
    // geometry | head`) panics. Restored, the program ends as Unix tools
    // do. Only this program's main: the library never touches signals.
    #[cfg(unix)]
    // SAFETY: at the start of main, before any thread; SIG_DFL is a valid
    // disposition for SIGPIPE.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    tracing_subscriber::fmt()
        // Colour codes only for a person at a terminal.
        .with_ansi(std::io::stderr().is_terminal())
        .with_writer(|| LogWriter)
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .init();
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(Failure(code, e)) => {
            eprintln!("scanner: {}", message(&e));
            ExitCode::from(code)
        }
    }
}

/// An error and its causes on one line, each cause once: many errors
/// already quote their source in their own message.
pub(crate) fn message(e: &anyhow::Error) -> String {
    let mut text = String::new();
    for cause in e.chain() {
        let part = cause.to_string();
        if !text.contains(&part) {
            if !text.is_empty() {
                text.push_str(": ");
            }
            text.push_str(&part);
        }
    }
    text
}
