//! `scanner`: the command-line front end of the host library.
//!
//! Exit codes: 0 success, 2 bad usage (clap), 3 unreadable or invalid input
//! file, 4 output could not be written, 1 anything else.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;
use clap::{Parser, Subcommand};
use host::brdf::fit::{FitOptions, GVariant, Samples, Weighting, fit};
use host::brdf::merl::MerlTable;
use host::brdf::npf::NpfModel;
use host::brdf::{Brdf, plot, render};
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
    /// Fit an NPF model to a MERL table.
    Fit {
        /// MERL binary table (.binary).
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
    /// Lambert base under a GGX dielectric coat.
    Coated,
    /// Two-lobe GGX mixture.
    TwoLobe,
}

/// An error with its exit code.
struct Failure(u8, anyhow::Error);

fn input<T>(r: anyhow::Result<T>) -> Result<T, Failure> {
    r.map_err(|e| Failure(3, e))
}

fn output<T>(r: anyhow::Result<T>) -> Result<T, Failure> {
    r.map_err(|e| Failure(4, e))
}

fn load_brdf(path: &Path) -> anyhow::Result<Box<dyn Brdf>> {
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or_default();
    if ext.eq_ignore_ascii_case("json") {
        Ok(Box::new(NpfModel::load(path)?))
    } else {
        Ok(Box::new(MerlTable::read(path)?))
    }
}

fn run(cli: Cli) -> Result<(), Failure> {
    match cli.command {
        Command::Fit { input: path, output: out, g, p, max_iterations } => {
            if !(1.0..=2.0).contains(&p) {
                return Err(Failure(2, anyhow::anyhow!("--p must be in [1, 2], got {p}")));
            }
            let table = input(MerlTable::read(&path).map_err(anyhow::Error::from))?;
            let samples =
                input(Samples::from_merl(&table).context("no usable sample in the table"))?;
            let opts = FitOptions {
                g,
                weighting: Weighting::Compressive { p },
                max_iterations,
                ..FitOptions::default()
            };
            let bar = ProgressBar::new((3 * max_iterations) as u64);
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
            output(model.save(&out).with_context(|| format!("cannot write {}", out.display())))?;
            println!(
                "fitted {} samples in {:.2} s ({:?} G, p = {p})",
                samples.len(),
                report.seconds,
                g
            );
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
            use host::brdf::analytic::*;
            let b = match material {
                Material::Ggx => ggx_conductor(0.2),
                Material::Beckmann => beckmann_conductor(0.3),
                Material::Coated => coated_plastic(),
                Material::TwoLobe => two_lobe_ggx(),
            };
            let table = MerlTable::from_fn(|wi, wo| b.eval(wi, wo));
            output(table.write(&out).with_context(|| format!("cannot write {}", out.display())))?;
            println!("{material:?} table written to {}", out.display());
        }
        Command::PlotNpf { input: path, output: out } => {
            let model = input(NpfModel::load(&path).map_err(anyhow::Error::from))?;
            output(plot::plot_factors(&model, &out).map_err(anyhow::Error::from))?;
            println!("factor plot written to {}", out.display());
        }
    }
    Ok(())
}

fn main() -> ExitCode {
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(Failure(code, e)) => {
            eprintln!("scanner: {e:#}");
            ExitCode::from(code)
        }
    }
}
