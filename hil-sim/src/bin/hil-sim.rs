//! Serve the simulated scanner on a pseudo-terminal until stopped (Ctrl-C).
//!
//! ```text
//! hil-sim [--seed N] [--speed X] [--corrupt P] [--drop P] [--fault SPEC]... [--axes FILE]
//!         [--board-axes FILE]
//! hil-sim render [--material NAME] [--mirrors N] [--bin K] [--out DIR]
//! hil-sim direct [--material NAME] --out DIR
//! hil-sim truth --material NAME|DIR --queries Q.npy|Q.csv -o OUT.npy|OUT.csv
//! ```
//! A material is a library name or a texture-set directory
//! (docs/texture-set.md). Exit codes: 2 bad usage (an unknown material
//! name), 3 bad input file (texture set, queries), 4 output not written.
//! Serving prints the pty path; point the host at it like at `/dev/ttyACM0`.
//! `render` renders the frames of a scan at the nominal mirror positions
//! (timing each; optionally writing them as OpenEXR) without a device;
//! `direct` writes the Fig. 9 direct images of the material's large piece;
//! `truth` answers shading queries from the ground truth (f · cos θi of the
//! small sample, docs/query-format.md) — for scoring materials built from
//! simulated scans.

use std::io::Write;

use clap::{Parser, Subcommand};
use hil_sim::geometry::ScannerGeometry;
use hil_sim::materials::{self, MaterialError, Sample};
use hil_sim::optics::{Exposure, OpticalSim};
use hil_sim::{FaultPlan, FaultSpec, Port, PtyServer, SimConfig, SimDevice};

/// The simulated scanner controller on a pseudo-terminal.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Args {
    /// Seed of every random choice (positions at power-on, boot ids, faults).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Simulated time per wall-clock time (keep ≤ 4, as `scanner sim` does:
    /// the host's keep-alive, 50 ms after each answer, must stay inside the
    /// device's 500 ms link timeout).
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    /// Per-byte probability of a flipped bit on the link.
    #[arg(long, default_value_t = 0.0)]
    corrupt: f64,
    /// Per-byte probability of a lost byte on the link.
    #[arg(long, default_value_t = 0.0)]
    drop: f64,
    /// A fault, e.g. `reset@trigger=10` or `estop:on@ms=5000` (repeatable).
    #[arg(long = "fault")]
    faults: Vec<FaultSpec>,
    /// The drives the scanner is built with, an axis configuration file
    /// (docs/axis-config.md; default: the spec's); its board comes with
    /// them saved.
    #[arg(long, value_name = "FILE")]
    axes: Option<std::path::PathBuf>,
    /// The axis configuration the board comes with when it is not the
    /// drives it is built with: a board still to be commissioned. Where the
    /// axes physically stop is then printed after each motion (what a
    /// ruler on the machine reads).
    #[arg(long, value_name = "FILE")]
    board_axes: Option<std::path::PathBuf>,
    /// Serve the board as a USB port: PATH is a symbolic link to its pty,
    /// removed while the board is unplugged (a disconnect fault, a reset)
    /// and made to a new pty when it is back, as udev's /dev/serial/by-id
    /// links are. An existing PATH is replaced only if it is a link, and not
    /// while another simulator serves there.
    #[arg(long, value_name = "PATH")]
    link: Option<std::path::PathBuf>,
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Render a scan's frames at the nominal mirror positions (no device).
    Render {
        /// Sample material (checkerboard, diffuse-white, glossy-black,
        /// woven-fabric, leather, painted-wood, rough-metal, or a
        /// texture-set directory).
        #[arg(long, default_value = "woven-fabric")]
        material: String,
        /// Frames (mirrors 0 … N−1).
        #[arg(long, default_value_t = 40)]
        mirrors: usize,
        /// Sensor binning (1 = the default 4096² sensor).
        #[arg(long, default_value_t = 1)]
        bin: u32,
        /// Write the frames here as `frame-LL.exr` (32-bit float RGB).
        #[arg(long)]
        out: Option<std::path::PathBuf>,
    },
    /// Write the direct images of the material's large piece (≈10× the
    /// sample's area), seen and lit from the four mirror directions nearest
    /// the camera axis, rectified at the mirror views' scale.
    Direct {
        /// Sample material (a library name or a texture-set directory).
        #[arg(long, default_value = "woven-fabric")]
        material: String,
        /// Output folder: `direct-K-mirror-LL.exr` and `direct.toml`
        /// (docs/direct-images.md).
        #[arg(long)]
        out: std::path::PathBuf,
        /// Take photographs in perspective instead, as a real camera at
        /// this distance (mm; 400 without a value) from the piece's centre
        /// would: `photo-K-mirror-LL.exr`, `white.exr` and
        /// `photographs.toml` with the piece's corners in each, for
        /// `scanner rectify`.
        #[arg(long, value_name = "DISTANCE_MM", num_args = 0..=1,
              default_missing_value = "400")] // hil_sim::direct::PHOTO_DISTANCE_MM
        photographs: Option<f64>,
        /// With --photographs: the camera lens' radial distortion K1[,K2]
        /// about the photograph's centre, the radius in half-diagonals
        /// (K1 < 0: barrel) [default: none, a pinhole].
        #[arg(long, value_delimiter = ',', allow_hyphen_values = true, requires = "photographs")]
        lens: Vec<f64>,
        /// With --photographs: the albedo of the matte background the piece
        /// lies on, in [0, 1] (a dark piece on a light card: 0.8) [default:
        /// the black holder's 0.04]. The white target stays on the holder.
        #[arg(long, value_name = "ALBEDO", requires = "photographs")]
        background: Option<f64>,
    },
    /// Ground truth f · cos θi of the small sample (or the large piece) for
    /// shading queries.
    Truth {
        /// Sample material: a library name or a texture-set directory.
        #[arg(long)]
        material: String,
        /// Which piece uv spans: `small` (the 25.4 mm sample the scanner
        /// scans) or `large` (the piece of the direct images, to score an
        /// enlarged material).
        #[arg(long, value_enum, default_value = "small")]
        piece: Piece,
        /// Query file (.npy N × 8 or .csv u,v,wi_x,…,wo_z).
        #[arg(long)]
        queries: std::path::PathBuf,
        /// Answer file (.npy N × 3 float32 or .csv r,g,b).
        #[arg(short, long)]
        output: std::path::PathBuf,
    },
}

/// The piece `hil-sim truth` answers for.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum Piece {
    Small,
    Large,
}

/// A failure with its exit code.
struct Fail(u8, String);

impl From<MaterialError> for Fail {
    fn from(e: MaterialError) -> Fail {
        let code = match e {
            MaterialError::Unknown(_) => 2,
            MaterialError::TextureSet(_) => 3,
        };
        Fail(code, e.to_string())
    }
}

impl From<String> for Fail {
    fn from(e: String) -> Fail {
        Fail(2, e)
    }
}

fn truth(
    material: &str,
    piece: Piece,
    queries: &std::path::Path,
    output: &std::path::Path,
) -> Result<(), Fail> {
    use scanner_formats::queries as q;
    // Check the output before any work.
    q::check_extension(output).map_err(|e| Fail(2, e.to_string()))?;
    scanner_formats::check_output(output, &[queries]).map_err(|e| Fail(4, e.to_string()))?;
    let m = materials::lookup(material)?;
    let sample = match piece {
        Piece::Small => Sample::small(m),
        Piece::Large => Sample::large(m),
    };
    let rows = q::read_queries(queries).map_err(|e| Fail(3, e.to_string()))?;
    let answers = hil_sim::truth::answer(&sample, &rows);
    q::write_answers(output, &answers).map_err(|e| Fail(4, e.to_string()))?;
    eprintln!("{} answers written to {}", answers.len(), output.display());
    Ok(())
}

fn direct(
    seed: u64,
    material: &str,
    out: &std::path::Path,
    photographs: Option<f64>,
    lens: &[f64],
    background: Option<f64>,
) -> Result<(), Fail> {
    let m = materials::lookup(material)?;
    let nominal = ScannerGeometry::default_scanner();
    let sim = OpticalSim::as_built(&nominal, Sample::small(m.clone()), seed);
    let scale = hil_sim::direct::mirror_view_scale(&nominal);
    if let Some(distance) = photographs {
        if !(distance.is_finite() && (100.0..=10_000.0).contains(&distance)) {
            return Err(Fail(2, format!("--photographs {distance}: a distance in 100…10 000 mm")));
        }
        let distortion = match *lens {
            [] => [0.0; 2],
            [k1] => [k1, 0.0],
            [k1, k2] => [k1, k2],
            _ => return Err(Fail(2, format!("--lens: K1[,K2], not {} numbers", lens.len()))),
        };
        let setup = hil_sim::direct::PhotoSetup {
            distance_mm: distance,
            distortion,
            background_albedo: background.unwrap_or(hil_sim::optics::HOLDER_ALBEDO),
        };
        setup.check().map_err(|e| Fail(2, format!("--lens or --background: {e}")))?;
        let set = hil_sim::direct::write_photographs(&sim, &nominal, m, 4, scale, setup, out)
            .map_err(|e| Fail(4, e))?;
        for ph in set.photo.iter().chain([&set.white]) {
            let c: Vec<String> = ph.corners.iter().flatten().map(|v| format!("{v:.2}")).collect();
            eprintln!(
                "{}: exposure {} s, corners {}",
                out.join(&ph.file).display(),
                ph.exposure_s,
                c.join(",")
            );
        }
        eprintln!("{}", out.join(hil_sim::direct::PHOTOGRAPHS).display());
        return Ok(());
    }
    let manifest =
        hil_sim::direct::write_set(&sim, &nominal, m, 4, scale, out).map_err(|e| Fail(4, e))?;
    for im in &manifest.image {
        eprintln!("{}: exposure {} s", out.join(&im.file).display(), im.exposure_s);
    }
    eprintln!("{}", out.join(scanner_formats::direct::MANIFEST).display());
    Ok(())
}

fn render(
    seed: u64,
    material: &str,
    mirrors: usize,
    bin: u32,
    out: Option<&std::path::Path>,
) -> Result<(), Fail> {
    let m = materials::lookup(material)?;
    if bin == 0 || bin > 64 {
        return Err(Fail(2, "--bin must be in 1…64".into()));
    }
    let nominal = ScannerGeometry::default_scanner().with_sensor_scaled(bin);
    if mirrors > nominal.mirrors.len() {
        return Err(Fail(2, format!("--mirrors: the scanner has {}", nominal.mirrors.len())));
    }
    let sim = OpticalSim::as_built(&nominal, Sample::small(m), seed);
    if let Some(dir) = out {
        std::fs::create_dir_all(dir).map_err(|e| Fail(4, format!("{}: {e}", dir.display())))?;
    }
    let started = std::time::Instant::now();
    for l in 0..mirrors {
        let axes = nominal.mirror_axes(l).map_err(|e| Fail(1, e.to_string()))?;
        let t = std::time::Instant::now();
        let frame = sim.render(&Exposure { axes, exposure_s: 0.05, light: 1.0 });
        let render_s = t.elapsed().as_secs_f64();
        if let Some(dir) = out {
            let path = dir.join(format!("frame-{l:02}.exr"));
            hil_sim::camera::write_frame_exr(&frame, &path).map_err(|e| Fail(4, e.to_string()))?;
        }
        eprintln!("frame {l:2}: rendered in {render_s:.3} s");
    }
    eprintln!("{mirrors} frames in {:.2} s", started.elapsed().as_secs_f64());
    Ok(())
}

fn main() -> std::process::ExitCode {
    let args = Args::parse();
    let done = match &args.command {
        Some(Command::Direct { material, out, photographs, lens, background }) => {
            Some(("direct", direct(args.seed, material, out, *photographs, lens, *background)))
        }
        Some(Command::Render { material, mirrors, bin, out }) => {
            Some(("render", render(args.seed, material, *mirrors, *bin, out.as_deref())))
        }
        Some(Command::Truth { material, piece, queries, output }) => {
            Some(("truth", truth(material, *piece, queries, output)))
        }
        None => None,
    };
    if let Some((what, result)) = done {
        return match result {
            Ok(()) => std::process::ExitCode::SUCCESS,
            Err(Fail(code, e)) => {
                eprintln!("hil-sim {what}: {e}");
                std::process::ExitCode::from(code)
            }
        };
    }
    if !(0.0..=1.0).contains(&args.corrupt) || !(0.0..=1.0).contains(&args.drop) {
        eprintln!("hil-sim: --corrupt and --drop are probabilities in [0, 1]");
        return std::process::ExitCode::from(2);
    }
    if !(args.speed > 0.0 && args.speed <= 100.0) {
        eprintln!("hil-sim: --speed must be in (0, 100]");
        return std::process::ExitCode::from(2);
    }
    let mut plan = FaultPlan::none().corrupt(args.corrupt).drop_bytes(args.drop);
    for f in args.faults {
        plan = plan.with(f.when, f.event);
    }
    let mut config = SimConfig::new(args.seed);
    config.faults = plan;
    let mut board = protocol::default_axes();
    for (path, axes) in [(&args.axes, &mut config.axes), (&args.board_axes, &mut board)] {
        let Some(path) = path else { continue };
        match scanner_geometry::load_axes(path) {
            Ok(a) => *axes = a,
            Err(e) => {
                eprintln!("hil-sim: {e}");
                return std::process::ExitCode::from(3);
            }
        }
    }
    config.flash_axes = args.board_axes.is_some().then_some(board);
    let port = args.link.map_or(Port::Pty, |p| Port::Usb(Some(p)));
    let server = match PtyServer::start_with_camera(SimDevice::new(config), args.speed, None, port)
    {
        Ok(s) => s,
        Err(e) => {
            eprintln!("hil-sim: cannot serve the board: {e}");
            return std::process::ExitCode::from(1);
        }
    };
    if args.board_axes.is_some() {
        server.print_where_axes_stop();
    }
    println!("{}", server.path());
    let _ = std::io::stdout().flush();
    eprintln!(
        "hil-sim: simulated scanner on {} (seed {}); Ctrl-C stops it",
        server.path(),
        args.seed
    );
    loop {
        std::thread::park();
    }
}
