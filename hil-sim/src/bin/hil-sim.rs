//! Serve the simulated scanner on a pseudo-terminal until stopped (Ctrl-C).
//!
//! ```text
//! hil-sim [--seed N] [--speed X] [--corrupt P] [--drop P] [--fault SPEC]...
//! hil-sim render [--material NAME] [--mirrors N] [--bin K] [--out DIR]
//! hil-sim direct [--material NAME] --out DIR
//! ```
//! Serving prints the pty path; point the host at it like at `/dev/ttyACM0`.
//! `render` renders the frames of a scan at the nominal mirror positions
//! (timing each; optionally writing them as OpenEXR) without a device;
//! `direct` writes the Fig. 9 direct images of the material's large piece.

use std::io::Write;

use clap::{Parser, Subcommand};
use hil_sim::geometry::ScannerGeometry;
use hil_sim::materials::{self, Sample};
use hil_sim::optics::{Exposure, OpticalSim};
use hil_sim::{FaultPlan, FaultSpec, PtyServer, SimConfig, SimDevice};

/// The simulated scanner controller on a pseudo-terminal.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Args {
    /// Seed of every random choice (positions at power-on, boot ids, faults).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Simulated time per wall-clock time (keep ≤ 2: the host's keep-alive).
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
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Render a scan's frames at the nominal mirror positions (no device).
    Render {
        /// Sample material (checkerboard, diffuse-white, woven-fabric,
        /// leather, painted-wood, rough-metal).
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
        /// Sample material.
        #[arg(long, default_value = "woven-fabric")]
        material: String,
        /// Output folder: `direct-K-mirror-LL.exr`.
        #[arg(long)]
        out: std::path::PathBuf,
    },
}

fn direct(seed: u64, material: &str, out: &std::path::Path) -> Result<(), String> {
    let m = materials::lookup(material)?;
    let nominal = ScannerGeometry::default_scanner();
    let sim = OpticalSim::as_built(&nominal, Sample::small(m.clone()), seed);
    std::fs::create_dir_all(out).map_err(|e| format!("{}: {e}", out.display()))?;
    let mut dirs: Vec<(usize, hil_sim::geometry::DVec3)> = (0..nominal.mirrors.len())
        .filter_map(|l| nominal.mirror_direction(l).map(|d| (l, d)))
        .collect();
    dirs.sort_by(|a, b| b.1.z.total_cmp(&a.1.z));
    let px_per_mm = nominal.camera.focal_px / (2.0 * nominal.ellipsoid.semi_major_mm);
    for (k, &(l, d)) in dirs.iter().take(4).enumerate() {
        let frame = sim.direct_image(&Sample::large(m.clone()), d, px_per_mm, 0.05);
        let path = out.join(format!("direct-{k}-mirror-{l:02}.exr"));
        hil_sim::camera::write_frame_exr(&frame, &path)
            .map_err(|e| format!("{}: {e}", path.display()))?;
        eprintln!("{}: {}×{} px", path.display(), frame.width, frame.height);
    }
    Ok(())
}

fn render(
    seed: u64,
    material: &str,
    mirrors: usize,
    bin: u32,
    out: Option<&std::path::Path>,
) -> Result<(), String> {
    let m = materials::lookup(material)?;
    if bin == 0 || bin > 64 {
        return Err("--bin must be in 1…64".into());
    }
    let nominal = ScannerGeometry::default_scanner().with_sensor_scaled(bin);
    if mirrors > nominal.mirrors.len() {
        return Err(format!("--mirrors: the scanner has {}", nominal.mirrors.len()));
    }
    let sim = OpticalSim::as_built(&nominal, Sample::small(m), seed);
    if let Some(dir) = out {
        std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    }
    let started = std::time::Instant::now();
    for l in 0..mirrors {
        let axes = nominal.mirror_axes(l).map_err(|e| e.to_string())?;
        let t = std::time::Instant::now();
        let frame = sim.render(&Exposure { axes, exposure_s: 0.05, light: 1.0 });
        let render_s = t.elapsed().as_secs_f64();
        if let Some(dir) = out {
            let img = image::Rgb32FImage::from_raw(frame.width, frame.height, frame.rgb)
                .ok_or("frame size mismatch")?;
            let path = dir.join(format!("frame-{l:02}.exr"));
            img.save(&path).map_err(|e| format!("{}: {e}", path.display()))?;
        }
        eprintln!("frame {l:2}: rendered in {render_s:.3} s");
    }
    eprintln!("{mirrors} frames in {:.2} s", started.elapsed().as_secs_f64());
    Ok(())
}

fn main() -> std::process::ExitCode {
    let args = Args::parse();
    if let Some(Command::Direct { material, out }) = &args.command {
        return match direct(args.seed, material, out) {
            Ok(()) => std::process::ExitCode::SUCCESS,
            Err(e) => {
                eprintln!("hil-sim direct: {e}");
                std::process::ExitCode::from(2)
            }
        };
    }
    if let Some(Command::Render { material, mirrors, bin, out }) = &args.command {
        return match render(args.seed, material, *mirrors, *bin, out.as_deref()) {
            Ok(()) => std::process::ExitCode::SUCCESS,
            Err(e) => {
                eprintln!("hil-sim render: {e}");
                std::process::ExitCode::from(2)
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
    let server = match PtyServer::start(SimDevice::new(config), args.speed) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("hil-sim: cannot create a pseudo-terminal: {e}");
            return std::process::ExitCode::from(1);
        }
    };
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
