//! Serve the simulated scanner on a pseudo-terminal until stopped (Ctrl-C).
//!
//! ```text
//! hil-sim [--seed N] [--speed X] [--corrupt P] [--drop P] [--fault SPEC]...
//! ```
//! Prints the pty path; point the host at it like at `/dev/ttyACM0`.

use std::io::Write;

use clap::Parser;
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
}

fn main() -> std::process::ExitCode {
    let args = Args::parse();
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
