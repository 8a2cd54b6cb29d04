//! `scanner calibrate`, `regions`, `build`, `shade` and `preview`: the
//! material builder on scan directories, and material files.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::anyhow;
use indicatif::{ProgressBar, ProgressStyle};
use scanner_geometry::{SampleFace, ScannerGeometry};

use super::Failure;
use super::plot::{Caption, draw_captions};
use crate::build::calibrate::{BuildProgress, CalibrateOptions, Calibration};
use crate::build::height::{PATCHES, SampleHeight};
use crate::build::locate::Checkerboard;
use crate::build::regions::{EdgePixels, SampleSides};
use crate::build::scanread::ScanFrames;
use crate::build::superres::SharpenOptions;
use crate::build::{BuildError, RegionOptions, calibrate, extract_regions};

/// A progress bar per builder stage, and how long each stage took.
pub struct StageBar {
    bar: ProgressBar,
    /// Each stage's name and start, in order.
    started: std::sync::Mutex<Vec<(String, Instant)>>,
}

impl StageBar {
    pub fn new() -> StageBar {
        let bar = super::progress_bar(0);
        bar.set_style(
            ProgressStyle::with_template("{msg:>20} [{bar:30}] {pos}/{len}, {elapsed}")
                .expect("valid template"),
        );
        StageBar { bar, started: Default::default() }
    }

    /// Clear the bar; the stages' wall times, e.g. "sample frames 35.2 s,
    /// palettes 20.1 s" (each from its start to the next one's or to now).
    pub fn finish(&self) -> String {
        self.bar.finish_and_clear();
        let started = self.started.lock().unwrap_or_else(|e| e.into_inner());
        let now = Instant::now();
        let ends = started.iter().skip(1).map(|s| s.1).chain([now]);
        started
            .iter()
            .zip(ends)
            .map(|((name, t0), t1)| format!("{name} {:.1} s", (t1 - *t0).as_secs_f64()))
            .collect::<Vec<_>>()
            .join(", ")
    }
}

impl BuildProgress for StageBar {
    fn stage(&self, name: &str, total: usize) {
        self.started
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push((name.to_string(), Instant::now()));
        self.bar.set_message(name.to_string());
        self.bar.set_length(total as u64);
        self.bar.set_position(0);
    }
    fn step(&self) {
        self.bar.inc(1);
    }
}

fn build_failure(e: BuildError) -> Failure {
    Failure(e.exit_code(), anyhow!(e))
}

/// The nominal geometry a scan was taken with: `--geometry` (or the
/// shipped default without it), binned as the scan's sensor was (the
/// simulator's `--sim-bin`). A `--geometry` the scan was not taken with
/// under any binning is returned as given: the calibration and the scan
/// then say which geometry differs.
pub fn geometry_for(path: Option<&Path>, scan: &Path) -> Result<ScannerGeometry, Failure> {
    let base = match path {
        Some(p) => ScannerGeometry::load(p).map_err(|e| Failure(3, anyhow!(e)))?,
        None => ScannerGeometry::default_scanner(),
    };
    let m = match crate::scan::Manifest::load(scan) {
        Ok(m) => m,
        Err(_) if path.is_some() => return Ok(base),
        Err(e) => return Err(Failure(3, anyhow!(e))),
    };
    for bin in 1..=64 {
        let g = base.with_sensor_scaled(bin);
        if g.hash() == m.settings.geometry_sha256 {
            return Ok(g);
        }
    }
    match path {
        Some(_) => Ok(base),
        None => Err(Failure(
            3,
            anyhow!(
                "{}: taken with a geometry other than the shipped default: pass it with \
                 --geometry",
                scan.display()
            ),
        )),
    }
}

/// `scanner geometry`: check a design (`--geometry FILE`, the default
/// scanner, or either with its mirrors on `rings`), print what each mirror
/// does and what is wrong, and write it to `output` if it is sound.
pub fn geometry_cmd(
    path: Option<&Path>,
    rings: &[(f64, usize)],
    output: Option<&Path>,
    axes: Option<([protocol::AxisConfig; 3], String)>,
) -> Result<(), Failure> {
    let base = match path {
        Some(p) => ScannerGeometry::load(p).map_err(|e| Failure(3, anyhow!(e)))?,
        None => ScannerGeometry::default_scanner(),
    };
    let g = if rings.is_empty() { base } else { base.with_rings(rings) };
    let name = match (path, rings.is_empty()) {
        (Some(p), true) => p.display().to_string(),
        (None, true) => "the default scanner".into(),
        (Some(p), false) => format!("{} with mirrors on rings", p.display()),
        (None, false) => "the default scanner with mirrors on rings".into(),
    };
    g.validate().map_err(|e| Failure(3, anyhow!("{name}: {e}")))?;
    let (axes, travel_of) = axes.unwrap_or_else(|| {
        (
            protocol::default_axes(),
            "the default travel (spec/hardware.md; `--axes` or `--device` for a built scanner's)"
                .into(),
        )
    });
    let check = g.check_design_on(&axes);
    println!(
        "{name}: {} mirrors, sensor {} × {} px, f = {:.0} px; geometry hash {}",
        g.mirrors.len(),
        g.camera.width,
        g.camera.height,
        g.camera.focal_px,
        g.hash()
    );
    let [_, track, tilt] = axes;
    let travel = |c: protocol::AxisConfig| {
        let per = c.steps_per_unit as f64;
        let unit = scanner_geometry::unit_suffix(c.unit);
        format!("{:.1} … {:.1}{unit}", c.min_steps as f64 / per, c.max_steps as f64 / per)
    };
    println!("axes: checked against {travel_of}: track {}, tilt {}", travel(track), travel(tilt));
    println!(
        "mirror | view θ, φ (°) | light θ, φ (°) | disk (°), track (mm), tilt (°) | \
         sample on the sensor: x, y (px) | px/mm | lit"
    );
    let angles = |d: scanner_geometry::DVec3| {
        let phi = d.y.atan2(d.x).to_degrees().rem_euclid(360.0) + 0.0;
        format!("{:5.1}, {:5.1}", d.z.clamp(-1.0, 1.0).acos().to_degrees(), phi)
    };
    for m in &check.mirrors {
        let light = m.light.map_or_else(|| "—".into(), angles);
        let axes = m.axes.map_or_else(
            || "—".into(),
            |a| format!("{:7.2}, {:6.2}, {:6.3}", a.disk_deg, a.track_mm, a.tilt_deg),
        );
        let place = m.corners_px.map_or_else(
            || "—".into(),
            |c| {
                let (x, y) = (c.map(|p| p[0]), c.map(|p| p[1]));
                let lo = |v: [f64; 4]| v.iter().copied().fold(f64::INFINITY, f64::min);
                let hi = |v: [f64; 4]| v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                format!("{:.0}–{:.0}, {:.0}–{:.0}", lo(x), hi(x), lo(y), hi(y))
            },
        );
        let res = m.px_per_mm.map_or_else(|| "—".into(), |r| format!("{r:.2}"));
        let lit = m.lit.map_or_else(|| "—".into(), |l| format!("{:.0} %", 100.0 * l));
        println!(
            "{:6} | {} | {light} | {axes} | {place} | {res} | {lit}",
            m.mirror,
            angles(m.view)
        );
    }
    if let Some((a, b, gap)) = check.closest_views {
        println!(
            "closest views: mirrors {a} and {b}, {gap:.0} px apart (each needs {:.0} px around it: \
             a built scanner's view may lie that far from the design's)",
            g.view_margin_px()
        );
    }
    for w in &check.warnings {
        eprintln!("scanner: warning: {w}");
    }
    if !check.problems.is_empty() {
        for p in &check.problems {
            eprintln!("scanner: {p}");
        }
        return Err(Failure(
            3,
            anyhow!(
                "{name}: {} problem{} found{}",
                check.problems.len(),
                if check.problems.len() == 1 { "" } else { "s" },
                if output.is_some() { "; nothing written" } else { "" }
            ),
        ));
    }
    println!("no problem found");
    if let Some(out) = output {
        crate::fsutil::write_atomic(out, g.to_toml().as_bytes())
            .map_err(|e| Failure(4, anyhow!("{}: {e}", out.display())))?;
        println!("→ {}", out.display());
    }
    Ok(())
}

/// `scanner calibrate` warns of a light whose beam gives part of the
/// sample less than this share of what the other beams give it
/// ([`crate::build::calibrate::ColourCalibration::beam_coverage`]).
const BEAM_COVERAGE_WARN: f64 = 0.7;

/// `scanner calibrate`
pub fn calibrate_cmd(
    checkerboard: &Path,
    white: &Path,
    glossy: Option<&Path>,
    output: &Path,
    geometry: Option<&Path>,
    white_albedo: f64,
    squares: u32,
) -> Result<(), Failure> {
    if !(white_albedo > 0.0 && white_albedo <= 1.0) {
        return Err(Failure(2, anyhow!("--white-albedo must be in (0, 1], got {white_albedo}")));
    }
    if !(2..=64).contains(&squares) {
        return Err(Failure(2, anyhow!("--squares must be in 2…64, got {squares}")));
    }
    let inputs: Vec<&Path> = [checkerboard, white].into_iter().chain(glossy).collect();
    crate::fsutil::check_output(output, &inputs).map_err(|e| Failure(4, anyhow!(e)))?;
    let started = Instant::now();
    let g = geometry_for(geometry, checkerboard)?;
    let checker = ScanFrames::open(checkerboard, &g).map_err(build_failure)?;
    let white_scan = ScanFrames::open(white, &g).map_err(build_failure)?;
    let glossy_scan = glossy.map(|d| ScanFrames::open(d, &g)).transpose().map_err(build_failure)?;
    let opts = CalibrateOptions {
        target: Checkerboard { squares },
        white_albedo,
        ..CalibrateOptions::default()
    };
    let bar = StageBar::new();
    let cal = calibrate(&g, &checker, &white_scan, glossy_scan.as_ref(), &opts, &bar);
    let stages = bar.finish();
    let cal = cal.map_err(build_failure)?;
    cal.save(output).map_err(build_failure)?;
    use crate::build::calibrate::LocatedBy;
    let by_corners: Vec<_> =
        cal.views.iter().filter(|v| v.located_by == Some(LocatedBy::Corners)).collect();
    let rms = by_corners.iter().map(|v| v.corner_rms_px).fold(0.0, f64::max);
    // Views whose corners were found but explained the checker worse.
    let outdone = cal
        .views
        .iter()
        .filter(|v| v.corners_used > 0 && v.located_by == Some(LocatedBy::Phase))
        .count();
    let outdone = match outdone {
        0 => String::new(),
        n => format!(" ({n} of them explained better by it than by their corners)"),
    };
    let located = match by_corners.len() {
        0 => format!("every view by Fourier phase{outdone}"),
        n if n == cal.views.len() => {
            format!("every view by its checker corners (largest fit residual {rms:.3} px)")
        }
        1 => format!(
            "1 view by its checker corners (fit residual {rms:.3} px), the rest by Fourier \
             phase{outdone}"
        ),
        n => format!(
            "{n} views by their checker corners (largest fit residual {rms:.3} px), the rest by \
             Fourier phase{outdone}"
        ),
    };
    // The views whose straddling pixels `regions` and `build` read by
    // default: edges measured on the white target, or else placed
    // precisely by the phase alignment.
    let measured = cal.views.iter().filter(|v| v.edge_offsets_px.is_some()).count();
    let precise = cal.views.iter().filter(|v| v.edge_precise()).count() - measured;
    let located = match precise {
        0 => format!("{located}; {measured} views' edges measured on the white target"),
        _ => format!(
            "{located}; {measured} views' edges measured on the white target, {precise} more \
             placed to {} px by the phase alignment",
            crate::build::calibrate::EDGE_PRECISE_PX
        ),
    };
    let lights = match &cal.source_offsets {
        Some(o) => format!(
            "source home offsets disk {:+.3}°, tilt {:+.3}° from {} highlights of {} lights",
            o.disk_deg, o.tilt_deg, o.pairs, o.lights
        ),
        None => "nominal source home positions (no --glossy scan)".into(),
    };
    let lens = match cal.lens_k1_held {
        true => format!(
            "lens distortion k1 {:+.4}, the geometry file's (held: no view's corners found to \
             measure it)",
            cal.lens_distortion[0]
        ),
        false => format!("lens distortion k1 {:+.4}", cal.lens_distortion[0]),
    };
    println!(
        "calibrated {} views and {} lights in {:.1} s: {located}; {lights}; {lens} → {}",
        cal.views.len(),
        cal.lights.len(),
        started.elapsed().as_secs_f64(),
        output.display()
    );
    println!("  time by stage: {stages}");
    let relocked: Vec<String> = cal
        .views
        .iter()
        .filter_map(|v| {
            v.phase_relocked_squares.map(|s| format!("{} ({}, {})", v.view, s[0], s[1]))
        })
        .collect();
    if !relocked.is_empty() {
        println!(
            "  whole-square locks: the checker's phase had settled whole squares (u, v) off at \
             mirrors {}, put back by the sample's outline (a holder lighter than the dark \
             squares misleads the search)",
            relocked.join(", ")
        );
    }
    // Far beyond its prior, the fitted k1 is pulled towards the file's.
    let k1 = (cal.lens_distortion[0], g.camera.distortion[0]);
    if (k1.0 - k1.1).abs() > 2.0 * opts.tolerances.lens_k1 {
        eprintln!(
            "scanner: warning: the lens distorts more than the geometry file says (k1 {:+.3} \
             against {:+.3}): set its [camera] distortion near the value found and calibrate \
             again",
            k1.0, k1.1
        );
    }
    // How fully each beam lights the sample, against the others.
    let coverage = cal.colour.beam_coverage();
    if let Some((li, worst)) =
        coverage.iter().copied().enumerate().min_by(|a, b| a.1.total_cmp(&b.1))
    {
        println!(
            "  beam coverage: every light's field over the sample within {:.0} % of the others' \
             (least: mirror {}'s)",
            100.0 * (1.0 - worst),
            cal.lights[li].light
        );
        let short: Vec<String> = coverage
            .iter()
            .zip(&cal.lights)
            .filter(|(c, _)| **c < BEAM_COVERAGE_WARN)
            .map(|(c, l)| format!("{} ({:.0} %)", l.light, 100.0 * c))
            .collect();
        if !short.is_empty() {
            eprintln!(
                "scanner: warning: the beams of mirrors {} give part of the sample less than \
                 {:.0} % of what the other mirrors' beams give it: they land off their mirrors' \
                 centres (the mirror table, the axes' home positions or steps per unit: `scanner \
                 move --mirror N` and look). The calibration divides it out, with more noise \
                 there.",
                short.join(", "),
                100.0 * BEAM_COVERAGE_WARN
            );
        }
    }
    if !cal.defects.is_empty() {
        println!(
            "sensor defects: {}, found in the white target's frames; replaced in every frame \
             read with this calibration",
            crate::defects::counts(&cal.defects)
        );
    }
    Ok(())
}

/// Warn of the lights whose beam, as the calibration saw it, left part of
/// the sample unlit or in its soft edge ([`crate::build::RegionSet::unlit`]):
/// nothing was measured there under them. `filled`: the images in memory
/// were filled there (`scanner build`); else they are written as 0.
fn say_unlit(regions: &crate::build::RegionSet, filled: bool) {
    let texels = (regions.size * regions.size).max(1);
    let shares: Vec<String> = regions
        .lights
        .iter()
        .zip(&regions.unlit)
        .map(|(l, u)| (l, u.iter().filter(|&&d| d).count() as f64 / texels as f64))
        .filter(|(_, share)| *share > 0.0)
        .map(|(l, share)| match 100.0 * share {
            p if p < 1.0 => format!("{l} (< 1 %)"),
            p => format!("{l} ({p:.0} %)"),
        })
        .collect();
    if shares.is_empty() {
        return;
    }
    let dark = (0..regions.size * regions.size)
        .filter(|&t| (0..regions.lights.len()).all(|li| regions.is_unlit(li, t)))
        .count();
    let what = if filled {
        "the material holds there what the lights that lit it give, read between them as \
         between captured lights"
    } else {
        "their region images are 0 (black) there (`scanner build` fills them from the lights \
         that lit it)"
    };
    let dark = if dark > 0 {
        format!(
            " No beam lit {:.1} % of the sample: it stays 0.",
            100.0 * dark as f64 / texels as f64
        )
    } else {
        String::new()
    };
    eprintln!(
        "scanner: warning: in the calibration the beams of mirrors {} leave that share of the \
         sample unlit or in their soft edge (where the calibration cannot follow their field): \
         nothing was measured there under them, and {what}.{dark} Place the beams on their mirrors \
         (`scanner calibrate` names those off centre) and scan the targets again.",
        shares.join(", ")
    );
}

/// Say which of the camera's defective pixels the frames of `scan` will
/// have replaced (those it recorded itself — its metering's, its dark
/// frame's — and the calibration's), if any.
fn say_defects(scan: &ScanFrames, cal: &Calibration) {
    let all = crate::defects::union(scan.defects(), &cal.defects);
    if !all.is_empty() {
        println!(
            "sensor defects replaced in {}'s frames: {} ({} recorded by the scan, {} by the \
             calibration)",
            scan.manifest.settings.sample_name,
            crate::defects::counts(&all),
            scan.defects().len(),
            cal.defects.len()
        );
    }
}

/// The inputs of `scanner regions` and `scanner build`: a sample scan and
/// its calibration.
#[derive(Debug, Clone, clap::Args)]
pub struct ScanInputs {
    /// Scan directory of the sample.
    #[arg(long)]
    pub scan: PathBuf,
    /// Calibration file (`scanner calibrate`).
    #[arg(long)]
    pub calibration: PathBuf,
    /// Nominal geometry file (default: the shipped scanner, at the scan's sensor size).
    #[arg(long)]
    pub geometry: Option<PathBuf>,
    /// Side of the region images, px (default: the smallest power of two
    /// no view is undersampled at).
    #[arg(long)]
    pub size: Option<usize>,
    /// Where each region image's detail comes from: `all-views` solves,
    /// per light, for the image every view's pixels agree on, and gives
    /// each view's image its detail (finer than any one view resolves);
    /// `own-view` resamples each view's pixels alone.
    #[arg(long, value_enum, default_value_t = Detail::AllViews)]
    pub detail: Detail,
    /// Which frame pixels at the sample's edge the region images read:
    /// `inside` only those wholly inside the calibrated edge; `straddling`
    /// also the pixels the edge crosses, each for its part on the sample
    /// beside the holder (needs the sample's edge where the calibration
    /// puts it, to ≈ 0.01 px on a textured sample); `precise` (the
    /// default) straddling in the views whose edges the calibration places
    /// that precisely, inside in the others.
    #[arg(long, value_enum, default_value_t = EdgeArg::Precise)]
    pub edge_pixels: EdgeArg,
    /// Where the sample's face lies: `auto` (the default) measures it on
    /// the sample's frames, where the views agree, and reads the region
    /// images there when it is significantly off the holder's plane the
    /// targets lay in; MM gives it (above the holder's plane, towards the
    /// mirrors; 0: in it).
    #[arg(long, value_parser = parse_sample_height, allow_hyphen_values = true,
          default_value = "auto", value_name = "auto|MM")]
    pub sample_height: SampleHeight,
    /// The sample's face tilted DEG_U,DEG_V degrees (rising along u, along
    /// v), with a given --sample-height; `auto` measures the tilt with the
    /// height.
    #[arg(long, value_parser = super::commands::parse_tilt, allow_hyphen_values = true,
          value_name = "DEG_U,DEG_V")]
    pub sample_tilt: Option<[f64; 2]>,
    /// Whether a thick sample's sides show beyond the edges facing each
    /// view: `auto` (the default) looks beyond the edges, at the face
    /// measured or given (and reads an outline pulled part-way from the
    /// chroma's face towards the holder's plane as thin sides); `shown`
    /// says they do (no pixel across those edges is
    /// read, the face is measured on its colour texture alone, not on its
    /// outline); `hidden` that the holder lies beyond every edge.
    #[arg(long, value_enum, default_value = "auto", value_name = "auto|shown|hidden")]
    pub sample_sides: SidesArg,
}

/// `--sample-sides` of `scanner regions` and `scanner build`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SidesArg {
    Auto,
    Shown,
    Hidden,
}

/// A face this far off the holder's plane somewhere, mm, is told that
/// the lights' beams were measured elsewhere.
const FAR_FACE_MM: f64 = 1.0;

/// `--sample-height`: `auto` or a height in mm within
/// ±[`crate::build::height::MAX_HEIGHT_MM`] (the range `auto` searches).
fn parse_sample_height(s: &str) -> Result<SampleHeight, String> {
    if s == "auto" {
        return Ok(SampleHeight::Measure);
    }
    let max = crate::build::height::MAX_HEIGHT_MM;
    match s.parse::<f64>() {
        Ok(h) if h.is_finite() && h.abs() <= max => {
            Ok(SampleHeight::Given(SampleFace::at_height(h)))
        }
        _ => Err(format!("{s:?}: `auto` or a height in mm within ±{max}")),
    }
}

/// The largest tilt `--sample-tilt` takes about either axis, degrees.
const MAX_TILT_GIVEN_DEG: f64 = 20.0;

/// Say where the region images took the sample's face to lie.
fn say_height(regions: &crate::build::RegionSet) {
    use crate::build::height::{FaceCue, HeightFit};
    let face = regions.face;
    let tilt = scanner_geometry::face::angles_of;
    // What the face was measured on.
    let cue = |f: &HeightFit| -> String {
        let outline = |f: &HeightFit| {
            f.outline.map_or(String::new(), |o| {
                format!(
                    "its outline ({} edge points in {} views, {:.2} px rms)",
                    o.points, o.views, o.rms_px
                )
            })
        };
        match f.cue {
            FaceCue::Chroma => format!("on the views' chroma, from {} lights' frames", f.lights),
            FaceCue::Outline => format!("on {}, from {} lights' frames", outline(f), f.lights),
            FaceCue::Both => {
                format!("on the views' chroma and {}, from {} lights' frames", outline(f), f.lights)
            }
            FaceCue::None | FaceCue::Conflict => format!("from {} lights' frames", f.lights),
        }
    };
    // A tilt measured and found level.
    let level = |f: &HeightFit| -> String {
        if !f.sigma_mm.is_finite() {
            return String::new();
        }
        if !f.slope_sigma[0].is_finite() {
            return format!(
                ", its tilt not measured ({} of {} patches agree, 4 needed; up to {}° is searched)",
                f.patches,
                PATCHES * PATCHES,
                crate::build::height::MAX_TILT_DEG
            );
        }
        let ([tu, tv], [su, sv]) = (tilt(f.slope), tilt(f.slope_sigma));
        format!(", level: tilted {tu:.3}° ± {su:.3}° along u and {tv:.3}° ± {sv:.3}° along v")
    };
    match regions.height_fit {
        Some(f) if !face.is_level() => {
            let [tu, tv] = tilt(face.slope);
            let [su, sv] = tilt(f.slope_sigma);
            let patches = if f.patches > 0 {
                format!(
                    ", {} of {} patches {:.3} mm from a plane",
                    f.patches,
                    PATCHES * PATCHES,
                    f.flatness_mm
                )
            } else {
                String::new()
            };
            println!(
                "sample's face measured {:.3} ± {:.3} mm above the holder's plane at its centre, \
                 tilted {tu:.3}° ± {su:.3}° along u and {tv:.3}° ± {sv:.3}° along v ({}{patches}; \
                 up to {:.2} px of parallax at the corners): region images read on that plane, \
                 directions in its frame",
                f.height_mm,
                f.sigma_mm,
                cue(&f),
                f.tilt_px + f.height_mm.abs() * f.parallax_px_per_mm
            )
        }
        Some(f) if !face.is_flush() => println!(
            "sample's face measured {:.3} ± {:.3} mm above the holder's plane ({}; up to {:.2} \
             px of parallax){}: region images read there, the edges' straddling pixels where \
             that places them to 0.01 px",
            f.height_mm,
            f.sigma_mm,
            cue(&f),
            f.height_mm.abs() * f.parallax_px_per_mm,
            level(&f)
        ),
        Some(f) if f.sigma_mm.is_finite() => println!(
            "sample's face in the holder's plane: measured {:.4} ± {:.4} mm ({:.3} px of \
             parallax; {}){}",
            f.height_mm,
            f.sigma_mm,
            f.height_mm.abs() * f.parallax_px_per_mm,
            cue(&f),
            level(&f)
        ),
        Some(f) if f.cue == FaceCue::Conflict => {
            let o = f.outline.map_or([f64::NAN; 2], |o| [o.face.height_mm, o.sigma[0]]);
            println!(
                "sample's face read in the holder's plane: its height not measured (the views' \
                 chroma put it at {:.3} mm, its outline at {:.3} ± {:.3} mm: they disagree, and \
                 which one erred cannot be told; a thick sample's sides, showing beyond the \
                 edges that face the views, move its outline: --sample-sides shown reads it on \
                 the chroma alone)",
                f.height_mm, o[0], o[1]
            )
        }
        Some(f) => println!(
            "sample's face read in the holder's plane: its height not measured (no colour \
             texture whose views agree, agreement {:.2} < {}; {})",
            f.agreement,
            crate::build::height::MIN_AGREEMENT,
            if regions.sides == SampleSides::Shown {
                "its outline not read, its sides showing: give --sample-height MM, a board \
                 standing on the holder its thickness"
                    .to_string()
            } else {
                format!(
                    "no outline against the holder in {} views",
                    crate::build::outline::MIN_VIEWS
                )
            }
        ),
        None if !face.is_flush() => {
            let [tu, tv] = tilt(face.slope);
            println!(
                "region images read {} mm above the holder's plane, tilted {tu}° along u and \
                 {tv}° along v",
                face.height_mm
            )
        }
        None => {}
    }
    let beyond = regions.beyond;
    if regions.sides == SampleSides::Shown {
        let thin = regions.height_fit.filter(|f| f.thin_sides).and_then(|f| Some((f, f.outline?)));
        let seen = match (beyond, thin) {
            (Some(b), _) if b.seen() => format!(
                " (seen: {:.1} % ± {:.1} % of the face's contrast beyond them, in {} views)",
                100.0 * b.excess,
                100.0 * b.sigma,
                b.views
            ),
            (Some(b), Some((f, o))) => format!(
                " (thin: {:.2} % ± {:.2} % of the face's contrast beyond them, in {} views, and \
                 the outline at {:.3} ± {:.3} mm against the chroma's {:.3} mm, pulled towards \
                 the holder's plane as the sides of a sample standing on it pull it)",
                100.0 * b.excess,
                100.0 * b.sigma,
                b.views,
                o.face.height_mm,
                o.sigma[0],
                f.height_mm
            ),
            _ => String::new(),
        };
        let outline = if regions.height_fit.is_some() {
            ", the face not measured on its outline"
        } else {
            ""
        };
        println!(
            "sample's sides show beyond the edges facing each view{seen}: no pixel across those \
             edges read{outline}"
        );
    } else if let Some(b) = beyond.filter(|b| b.seen()) {
        println!(
            "sample's sides seem to show beyond the edges facing each view ({:.1} % ± {:.1} % of \
             the face's contrast beyond them), read as hidden (--sample-sides hidden)",
            100.0 * b.excess,
            100.0 * b.sigma
        );
    }
    // The colour calibration measured each light's beam on the targets in
    // the holder's plane; a face far off it is lit, texel by texel, by the
    // part of the beam that far aside along the light's azimuth.
    let half = regions.sample_mm / 2.0;
    let off = [[-half, -half], [half, -half], [half, half], [-half, half]]
        .iter()
        .map(|&[x, y]| face.height_at(x, y).abs())
        .fold(0.0, f64::max);
    if off >= FAR_FACE_MM {
        let tan = regions
            .light_dirs
            .iter()
            .map(|d| d[0].hypot(d[1]) / d[2].max(1e-6))
            .fold(0.0, f64::max);
        println!(
            "the face lies up to {off:.1} mm off the holder's plane, where the white target \
             measured the lights' beams: its texels are lit by the beams' parts up to {:.1} mm \
             aside of those (a beam's edge near the sample shows in its images; for such samples, \
             calibrate with the targets raised to the face)",
            off * tan
        );
    }
}

/// `--edge-pixels` of `scanner regions` and `scanner build`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum EdgeArg {
    /// Also the pixels the calibrated edge crosses.
    Straddling,
    /// Only the pixels wholly inside the calibrated edge.
    Inside,
    /// Straddling in the views whose edges are placed to ≈ 0.01 px.
    Precise,
}

/// `--detail` of `scanner regions` and `scanner build`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Detail {
    /// Every view's pixels together (multi-view super-resolution).
    AllViews,
    /// Each view's own pixels.
    OwnView,
}

impl ScanInputs {
    /// The region size in range (a usage error otherwise).
    fn check(&self) -> Result<(), Failure> {
        if let Some(t) = self.sample_tilt {
            if self.sample_height == SampleHeight::Measure {
                return Err(Failure(
                    2,
                    anyhow!("--sample-tilt needs a given --sample-height (auto measures the tilt)"),
                ));
            }
            if t.iter().any(|t| t.abs() > MAX_TILT_GIVEN_DEG) {
                return Err(Failure(
                    2,
                    anyhow!("--sample-tilt {t:?}: within ±{MAX_TILT_GIVEN_DEG}° about each axis"),
                ));
            }
        }
        match self.size {
            Some(s) if !(4..=4096).contains(&s) => {
                Err(Failure(2, anyhow!("--size must be in 4…4096, got {s}")))
            }
            _ => Ok(()),
        }
    }

    /// How to extract the region images.
    fn region_options(&self) -> RegionOptions {
        RegionOptions {
            size: self.size,
            sharpen: (self.detail == Detail::AllViews).then(SharpenOptions::default),
            edge: match self.edge_pixels {
                EdgeArg::Straddling => EdgePixels::Straddling,
                EdgeArg::Inside => EdgePixels::Inside,
                EdgeArg::Precise => EdgePixels::Precise,
            },
            height: match (self.sample_height, self.sample_tilt) {
                (SampleHeight::Given(face), Some(t)) => SampleHeight::Given(SampleFace {
                    slope: scanner_geometry::face::slopes_of(t),
                    ..face
                }),
                (height, _) => height,
            },
            sides: match self.sample_sides {
                SidesArg::Auto => SampleSides::Auto,
                SidesArg::Shown => SampleSides::Shown,
                SidesArg::Hidden => SampleSides::Hidden,
            },
        }
    }

    /// The calibration, the scan's geometry and its frames.
    fn open(&self) -> Result<(Calibration, ScannerGeometry, ScanFrames), Failure> {
        let cal = Calibration::load(&self.calibration).map_err(build_failure)?;
        let g = geometry_for(self.geometry.as_deref(), &self.scan)?;
        let frames = ScanFrames::open(&self.scan, &g).map_err(build_failure)?;
        Ok((cal, g, frames))
    }
}

/// `scanner regions`
pub fn regions_cmd(input: &ScanInputs, output: &Path) -> Result<crate::build::RegionSet, Failure> {
    input.check()?;
    let check = || {
        crate::fsutil::check_output_dir(output, is_region_file).map_err(|e| Failure(4, anyhow!(e)))
    };
    check()?;
    let started = Instant::now();
    let (cal, g, frames) = input.open()?;
    say_defects(&frames, &cal);
    let bar = StageBar::new();
    let regions = extract_regions(&g, &cal, &frames, &input.region_options(), &bar);
    let stages = bar.finish();
    let regions = regions.map_err(build_failure)?;
    say_unlit(&regions, false);
    say_height(&regions);
    let extracted = started.elapsed().as_secs_f64();
    // Written into a fresh sibling directory, then swapped into place: no
    // partial output on failure, and never a mixture of two runs.
    let place = |e: std::io::Error| Failure(4, anyhow!("{}: {e}", output.display()));
    let staging = crate::fsutil::staging_dir(output).map_err(place)?;
    regions.write_exr(staging.path()).map_err(build_failure)?;
    check()?;
    crate::fsutil::replace_dir(staging, output).map_err(place)?;
    println!(
        "{} region images of {}² px ({} lights × {} views) in {extracted:.1} s (+ {:.1} s writing) → {}",
        regions.images.len(),
        regions.size,
        regions.lights.len(),
        regions.views.len(),
        started.elapsed().as_secs_f64() - extracted,
        output.display()
    );
    println!("  time by stage: {stages}");
    Ok(regions)
}

/// A PNG contact sheet of region images: up to 6 lights (rows) × 10 views
/// (columns) spread over the scan, f · cos θi · π (a white target's albedo)
/// tone-mapped (Reinhard) and sRGB-encoded.
#[cfg_attr(not(feature = "sim"), allow(dead_code))]
pub fn contact_sheet(regions: &crate::build::RegionSet, path: &Path) -> Result<(), Failure> {
    let pick = |n: usize, k: usize| -> Vec<usize> {
        let k = k.min(n);
        (0..k).map(|i| i * n / k).collect()
    };
    let rows = pick(regions.lights.len(), 6);
    let cols = pick(regions.views.len(), 10);
    let s = regions.size as u32;
    let gap = 4u32;
    // Bands for the labels: the views above their columns, the lights left
    // of their rows.
    const TOP: u32 = 22;
    const LEFT: u32 = 64;
    let (w, h) =
        (LEFT + cols.len() as u32 * (s + gap) + gap, TOP + rows.len() as u32 * (s + gap) + gap);
    let mut img = image::RgbImage::from_pixel(w, h, image::Rgb([40, 40, 40]));
    let mut captions = Vec::new();
    for (r, &li) in rows.iter().enumerate() {
        let y0 = TOP + gap + r as u32 * (s + gap);
        captions.push(Caption {
            text: format!("light {li}"),
            at: (6, (y0 + s / 2) as i32),
            centred: false,
            size: 13.0,
        });
        for (c, &vi) in cols.iter().enumerate() {
            let src = regions.image(li, vi);
            let x0 = LEFT + gap + c as u32 * (s + gap);
            for (i, px) in src.iter().enumerate() {
                let (x, y) = (i as u32 % s, i as u32 / s);
                img.put_pixel(x0 + x, y0 + y, image::Rgb(px.map(encode_srgb)));
            }
        }
    }
    for (c, &vi) in cols.iter().enumerate() {
        let x = LEFT + gap + c as u32 * (s + gap) + s / 2;
        captions.push(Caption {
            // Columns of small region images have room for the number only.
            text: if s >= 64 { format!("view {vi}") } else { vi.to_string() },
            at: (x as i32, (TOP / 2 + 2) as i32),
            centred: true,
            size: 13.0,
        });
    }
    draw_captions(&mut img, &captions).map_err(|e| Failure(4, anyhow!(e)))?;
    write_png(path, &img)
}

/// A file `scanner regions` writes: `l{LL}-v{VV}.exr` (two digits or more),
/// the detail layer's `detail.exr` and `detail-l{LL}.exr`, or the index
/// `regions.json`.
fn is_region_file(name: &str) -> bool {
    let digits = |s: &str| s.len() >= 2 && s.bytes().all(|b| b.is_ascii_digit());
    name == "detail.exr"
        || name == crate::build::regions::INDEX_FILE
        || name.strip_prefix("detail-l").and_then(|r| r.strip_suffix(".exr")).is_some_and(digits)
        || name
            .strip_prefix('l')
            .and_then(|r| r.strip_suffix(".exr"))
            .and_then(|r| r.split_once("-v"))
            .is_some_and(|(l, v)| digits(l) && digits(v))
}

/// What `scanner build` made.
#[cfg_attr(not(feature = "sim"), allow(dead_code))]
pub struct Built {
    /// The material, as a renderer opens it.
    pub material: scanner_shading::Material,
    /// The region images it was built from.
    pub regions: crate::build::RegionSet,
}

fn sha256_file(path: &Path) -> Result<String, Failure> {
    use sha2::Digest;
    let bytes = scanner_formats::input::read(path)
        .map_err(|e| Failure(3, anyhow!("{}: {e}", path.display())))?;
    Ok(crate::scan::hex(&sha2::Sha256::digest(&bytes)))
}

/// `scanner build`
pub fn build_cmd(
    input: &ScanInputs,
    output: &Path,
    opts: &crate::build::material::MaterialOptions,
) -> Result<Built, Failure> {
    use crate::build::fidelity::{captured_pair_answers, material_psnr};
    use crate::build::material::build_material;
    opts.check().map_err(|e| Failure(2, anyhow!(e)))?;
    input.check()?;
    let (scan, calibration) = (input.scan.as_path(), input.calibration.as_path());
    crate::fsutil::check_output(output, &[scan, calibration])
        .map_err(|e| Failure(4, anyhow!(e)))?;
    let started = Instant::now();
    let (cal, g, frames) = input.open()?;
    say_defects(&frames, &cal);
    let provenance = scanner_shading::format::Provenance {
        scan_manifest_sha256: sha256_file(&scan.join(crate::scan::MANIFEST_FILE))?,
        geometry_sha256: g.hash(),
        calibration_sha256: sha256_file(calibration)?,
        builder: format!("scanner {}", env!("CARGO_PKG_VERSION")),
        face: None,
    };
    let bar = StageBar::new();
    let regions = extract_regions(&g, &cal, &frames, &input.region_options(), &bar);
    let data = regions.and_then(|r| {
        build_material(
            &r,
            &frames.manifest.settings.sample_name,
            g.sample.size_mm,
            provenance,
            opts,
            &bar,
        )
        .map(|d| (r, d))
    });
    let stages = bar.finish();
    let (regions, data) = data.map_err(build_failure)?;
    say_unlit(&regions, true);
    say_height(&regions);
    let beyond = data.palettes_beyond_float16();
    if beyond > 0 {
        eprintln!(
            "warning: {beyond} palette values lie above float16's largest, {}: stored at it \
             (a near-mirror's highlights; docs/material-format.md)",
            scanner_shading::format::PALETTE_MAX
        );
    }
    let bytes = data.to_bytes().map_err(|e| Failure(4, anyhow!("material not written: {e}")))?;
    let material = scanner_shading::Material::from_bytes(&bytes)
        .map_err(|e| Failure(4, anyhow!("material not written: {e}")))?;
    crate::fsutil::write_atomic(output, &bytes)
        .map_err(|e| Failure(4, anyhow!("{}: {e}", output.display())))?;
    let built = started.elapsed().as_secs_f64();
    if let Some(max) = opts.max_bytes.filter(|&m| bytes.len() > m) {
        eprintln!(
            "warning: {} is {:.2} MB, over --max-size-mb {:.2}: at most 4 lights share an index \
             image, and the patent's cell tables are not shrunk",
            output.display(),
            bytes.len() as f64 / 1e6,
            max as f64 / 1e6
        );
    }
    let (m, r) = captured_pair_answers(&material, &regions, &data.texels);
    let (psnr, _, _) = material_psnr(&m, &r);
    let palettes = if psnr.is_nan() || psnr == f64::NEG_INFINITY {
        // No peak to score against (the metric's 99th percentile is 0).
        "not scored, the region images being black almost everywhere".to_string()
    } else if psnr == f64::INFINITY {
        "identical to the region images".to_string()
    } else {
        format!("{psnr:.1} dB against the region images")
    };
    println!(
        "{}: {} lights × {} views at {}² px, {} (up to {} per index image), {} \
         interpolation (half-vector shift {}{}{}), {:.1} MB, in {built:.1} s; palettes at the \
         captured pairs: {palettes}",
        output.display(),
        regions.lights.len(),
        regions.views.len(),
        regions.size,
        count(opts.colours, "colour"),
        count(material.metadata().lights_per_index as usize, "light"),
        match opts.interpolation {
            scanner_shading::Interpolation::Default => "default".to_string(),
            scanner_shading::Interpolation::Patent { columns, rows, points } =>
                format!("patent ({columns} × {rows} cells, {points} points)"),
        },
        material.metadata().half_vector_shift,
        if material.metadata().texel_model { ", texel model" } else { "" },
        match material.metadata() {
            m if m.detail_components > 0 => format!(
                ", detail layer with {}",
                count(m.detail_components as usize, "light component")
            ),
            m if m.detail => ", detail layer".to_string(),
            _ => String::new(),
        },
        bytes.len() as f64 / 1e6,
    );
    println!("  time by stage: {stages}");
    Ok(Built { material, regions })
}

/// "1 colour", "256 colours".
fn count(n: usize, what: &str) -> String {
    format!("{n} {what}{}", if n == 1 { "" } else { "s" })
}

/// `scanner shade`
pub fn shade_cmd(material: &Path, queries: &Path, output: &Path) -> Result<(), Failure> {
    use scanner_formats::queries::{QueryError, check_extension, read_queries, write_answers};
    let query_failure = |e: QueryError| match e {
        QueryError::Extension(_) => Failure(2, anyhow!(e)),
        _ => Failure(3, anyhow!(e)),
    };
    check_extension(queries).map_err(query_failure)?;
    check_extension(output).map_err(query_failure)?;
    crate::fsutil::check_output(output, &[material, queries])
        .map_err(|e| Failure(4, anyhow!(e)))?;
    let m = open_material(material)?;
    let q = read_queries(queries).map_err(query_failure)?;
    let started = Instant::now();
    let answers = crate::build::material::shade(&m, &q);
    let secs = started.elapsed().as_secs_f64();
    write_answers(output, &answers).map_err(|e| Failure(4, anyhow!(e)))?;
    println!(
        "{} queries shaded in {:.3} s ({:.1} M queries/s on {} threads) → {}",
        answers.len(),
        secs,
        answers.len() as f64 / secs.max(1e-9) / 1e6,
        rayon::current_num_threads(),
        output.display()
    );
    Ok(())
}

/// `scanner enlarge`
pub fn enlarge_cmd(
    material: &Path,
    direct: &Path,
    output: &Path,
    opts: &crate::build::enlarge::EnlargeOptions,
) -> Result<(), Failure> {
    use crate::build::enlarge::{enlarge, read_direct_set};
    opts.check().map_err(|e| Failure(2, anyhow!(e)))?;
    // Every input, the manifest's images too, before any work: the output
    // may replace none of them.
    let manifest = scanner_formats::direct::DirectManifest::read(direct)
        .map_err(|e| Failure(3, anyhow!(e)))?;
    let mut inputs = vec![material.to_path_buf(), direct.join(scanner_formats::direct::MANIFEST)];
    inputs.extend(manifest.image.iter().map(|im| direct.join(&im.file)));
    inputs.extend(manifest.white.iter().map(|w| direct.join(&w.file)));
    let inputs: Vec<&Path> = inputs.iter().map(PathBuf::as_path).collect();
    crate::fsutil::check_output(output, &inputs).map_err(|e| Failure(4, anyhow!(e)))?;
    let started = Instant::now();
    let bytes = scanner_formats::input::read(material)
        .map_err(|e| Failure(3, anyhow!("{}: {e}", material.display())))?;
    let data = scanner_shading::MaterialData::from_bytes(&bytes)
        .map_err(|e| Failure(3, anyhow!("{}: {e}", material.display())))?;
    let set = read_direct_set(direct).map_err(build_failure)?;
    let (enlarged, report) = enlarge(&data, &set, opts).map_err(build_failure)?;
    let bytes =
        enlarged.to_bytes().map_err(|e| Failure(4, anyhow!("material not written: {e}")))?;
    crate::fsutil::write_atomic(output, &bytes)
        .map_err(|e| Failure(4, anyhow!("{}: {e}", output.display())))?;
    let s = data.meta.resolution as usize;
    let by = match report.channels {
        [true, true, true] => opts.signature.name().to_string(),
        [false, false, false] => "colour, but the sample is black at the images' directions: \
                                  nothing to match by, the piece is the sample tiled"
            .to_string(),
        used => {
            let names = ["red", "green", "blue"];
            let pick = |on: bool| {
                (0..3)
                    .filter(|&c| used[c] == on)
                    .map(|c| names[c])
                    .collect::<Vec<_>>()
                    .join(" and ")
            };
            format!("{} alone ({} black on the sample)", pick(true), pick(false))
        }
    };
    let scale = match report.gain {
        Some(g) => format!(
            "scale {} ({})",
            (0..3)
                .map(|c| if report.channels[c] { format!("{:.3e}", g[c]) } else { "–".into() })
                .collect::<Vec<_>>()
                .join(" "),
            if set.white.is_some() {
                "from the white reference"
            } else {
                "no white reference: from the matches"
            }
        ),
        None if report.channels == [false; 3] => "no scale".into(),
        None => "heights need no scale".into(),
    };
    println!(
        "{}: {} × {} texels over {} × {} mm from {}, each matched to a place on the sample by \
         {by} ({} distinct of {}² candidates); signature distance median {:.3}, 90th percentile \
         {:.3}; {scale}; {:.1} MB in {:.1} s",
        output.display(),
        report.columns,
        report.rows,
        set.manifest.size_mm[0],
        set.manifest.size_mm[1],
        count(set.images.len(), "direct image"),
        report.points_used,
        s * opts.subtexel,
        report.distance[0],
        report.distance[1],
        bytes.len() as f64 / 1e6,
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

/// What `scanner rectify` writes.
pub struct RectifyOutputs<'a> {
    /// The rectified picture (.exr).
    pub picture: &'a Path,
    /// The photograph with the outline (.png), if asked for.
    pub show: Option<&'a Path>,
}

/// `scanner rectify`: the lens it rectified through (given or estimated).
pub fn rectify_cmd(
    photo: &Path,
    corners: crate::build::rectify::Corners,
    lens: crate::build::lens::LensChoice,
    size_mm: [f64; 2],
    px_per_mm: Option<f64>,
    out: RectifyOutputs<'_>,
) -> Result<crate::build::lens::Lens, Failure> {
    use crate::build::lens::LensChoice;
    use crate::build::rectify::{Corners, RectifyOptions, rectify};
    let RectifyOutputs { picture: output, show } = out;
    let frame = crate::exrio::read_rgb(photo)
        .map_err(|e| Failure(3, anyhow!("{}: {e}", photo.display())))?;
    if let Corners::Refined(marked) = corners {
        // Marks that do not fit the photograph: exit 2, as for any option.
        crate::build::rectify::check_corners(&marked, frame.width, frame.height)
            .map_err(|e| Failure(2, anyhow!(e)))?;
    }
    if let LensChoice::Known(lens) = lens {
        // A lens that folds this photograph: exit 2 too.
        crate::build::lens::LensMap::new(lens, frame.width, frame.height)
            .map_err(|e| Failure(2, anyhow!("--lens: {e}")))?;
    }
    let crate::build::rectify::Located { corners: located, lens: lens_used, found } = corners
        .locate(&frame, lens)
        .map_err(|e| Failure(3, anyhow!("{}: {e}", photo.display())))?;
    if lens == LensChoice::Estimate {
        let sigma = found.and_then(|f| f.lens_k1_sigma).unwrap_or(f64::INFINITY);
        println!(
            "{}: the lens estimated from the piece's sides: k1 {:.5} ± {sigma:.5} (k2 0; the \
             radius in half-diagonals of the photograph: --lens {:.5})",
            photo.display(),
            lens_used.k[0],
            lens_used.k[0]
        );
    }
    if let Corners::Refined(marked) = corners {
        let moved: Vec<String> = (0..4)
            .map(|k| {
                format!("{:.2}", (located[k][0] - marked[k][0]).hypot(located[k][1] - marked[k][1]))
            })
            .collect();
        println!(
            "{}: the marked corners moved {} px onto the piece's edges",
            photo.display(),
            moved.join(", ")
        );
    }
    if let Some(found) = found {
        let polarity = found.polarity.comparison();
        println!(
            "{}: the piece's corners at {} px (its sides straight within {:.2} px RMS over {} \
             edge points, bowed ≤ {:.2} px; {polarity} than the background × {:.1})",
            photo.display(),
            found.corners.map(|p| format!("({:.2}, {:.2})", p[0], p[1])).join(", "),
            found.edge_rms_px,
            found.edge_points,
            found.bow_px,
            found.contrast
        );
        if found.passed_over > 0 {
            println!(
                "{}: {} larger {} region{} passed over (reaching the photograph's edge or not a \
                 quadrilateral): check the outline (--show)",
                photo.display(),
                found.passed_over,
                found.polarity.name(),
                if found.passed_over == 1 { "" } else { "s" }
            );
        }
    }
    let opts = RectifyOptions { corners: located, size_mm, px_per_mm, lens: lens_used };
    // Options that do not fit this photograph: exit 2, as for any option.
    opts.check(frame.width, frame.height).map_err(|e| Failure(2, anyhow!(e)))?;
    let (out, report) =
        rectify(&frame, &opts).map_err(|e| Failure(3, anyhow!("{}: {e}", photo.display())))?;
    if let Some(show) = show {
        outline_picture(&frame, located, lens_used, show)?;
        println!("{}: the photograph with the piece's outline", show.display());
    }
    let bytes = crate::exrio::encode_half(&out)
        .map_err(|e| Failure(4, anyhow!("{}: {e}", output.display())))?;
    crate::fsutil::write_atomic(output, &bytes)
        .map_err(|e| Failure(4, anyhow!("{}: {e}", output.display())))?;
    println!(
        "{}: {} × {} px over {} × {} mm at {:.2} px/mm (the photograph: {:.2}–{:.2} px/mm on the \
         piece; {}² points a pixel)",
        output.display(),
        out.width,
        out.height,
        size_mm[0],
        size_mm[1],
        report.px_per_mm,
        report.photo_px_per_mm[0],
        report.photo_px_per_mm[1],
        report.supersampling
    );
    Ok(lens_used)
}

/// The largest side of [`outline_picture`]'s PNG, px.
const OUTLINE_MAX_SIDE: u32 = 1600;

/// A PNG of `photo` with the piece's outline through `corners` drawn on
/// it: reduced by a whole factor to at most [`OUTLINE_MAX_SIDE`] a side,
/// its 99th percentile of luminance shown near white, sRGB.
fn outline_picture(
    photo: &crate::camera::Frame,
    corners: [[f64; 2]; 4],
    lens: crate::build::lens::Lens,
    path: &Path,
) -> Result<(), Failure> {
    use crate::build::lens::{FrameMap, LensMap};
    let k = photo.width.max(photo.height).div_ceil(OUTLINE_MAX_SIDE).max(1);
    let (w, h) = (photo.width.div_ceil(k), photo.height.div_ceil(k));
    let mut lum: Vec<f32> = photo.rgb.chunks_exact(3).map(|p| (p[0] + p[1] + p[2]) / 3.0).collect();
    let top = {
        let i = (lum.len() - 1) * 99 / 100;
        *lum.select_nth_unstable_by(i, f32::total_cmp).1
    };
    let scale = if top > 0.0 { 0.9 / top } else { 1.0 };
    let mut img = image::RgbImage::new(w, h);
    for (x, y, px) in img.enumerate_pixels_mut() {
        let (mut sum, mut n) = ([0.0f32; 3], 0.0f32);
        for yy in y * k..((y + 1) * k).min(photo.height) {
            for xx in x * k..((x + 1) * k).min(photo.width) {
                let i = 3 * (yy * photo.width + xx) as usize;
                (0..3).for_each(|c| sum[c] += photo.rgb[i + c]);
                n += 1.0;
            }
        }
        *px = image::Rgb(sum.map(|s| srgb8(s / n * scale)));
    }
    let lens = LensMap::new(lens, photo.width, photo.height).map_err(|e| Failure(2, anyhow!(e)))?;
    let pinhole = corners.map(|c| lens.in_pinhole(c));
    // Each side straight in the pinhole image, through the lens.
    const STEPS: usize = 32;
    let outline: Vec<[f64; 2]> = (0..4 * STEPS)
        .map(|i| {
            let (a, b, t) = (pinhole[i / STEPS], pinhole[(i / STEPS + 1) % 4], i % STEPS);
            let t = t as f64 / STEPS as f64;
            let q = lens.in_frame([a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])]);
            [q[0] / k as f64, q[1] / k as f64]
        })
        .collect();
    let shown = corners.map(|c| [c[0] / k as f64, c[1] / k as f64]);
    super::plot::draw_outline(&mut img, shown, &outline).map_err(|e| Failure(4, anyhow!(e)))?;
    write_png(path, &img)
}

/// The encoding of previews and contact sheets: π·value (a white target's
/// albedo), Reinhard, sRGB.
fn encode_srgb(v: f32) -> u8 {
    let x = (v * std::f32::consts::PI).max(0.0);
    srgb8(x / (1.0 + x))
}

/// A linear value in [0, 1] (clamped) encoded as an 8-bit sRGB value.
fn srgb8(t: f32) -> u8 {
    (crate::build::export::srgb(t) * 255.0).round() as u8
}

/// A direction from polar and azimuth angles, degrees.
fn polar(theta: f64, phi: f64) -> [f64; 3] {
    let (t, p) = (theta.to_radians(), phi.to_radians());
    [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()]
}

/// Polar and azimuth angles of a unit direction, degrees (φ in [0, 360)).
pub fn angles(d: [f64; 3]) -> (f64, f64) {
    (d[2].clamp(-1.0, 1.0).acos().to_degrees(), d[1].atan2(d[0]).to_degrees().rem_euclid(360.0))
}

/// The angle between two unit directions, degrees.
fn angle_deg(a: [f64; 3], b: [f64; 3]) -> f64 {
    (a[0] * b[0] + a[1] * b[1] + a[2] * b[2]).clamp(-1.0, 1.0).acos().to_degrees()
}

/// The view of the preview: the direction within 20°…45° of the normal
/// farthest from every captured view, and its angle to the nearest.
pub fn novel_view(views: &[[f64; 3]]) -> ([f64; 3], f64) {
    let mut best = ([0.0, 0.0, 1.0], -1.0);
    for t in (20..=45).step_by(1) {
        for p in (0..360).step_by(2) {
            let d = polar(t as f64, p as f64);
            let near = views.iter().map(|&v| angle_deg(d, v)).fold(f64::INFINITY, f64::min);
            if near > best.1 {
                best = (d, near);
            }
        }
    }
    best
}

/// Answers to queries from another source than the material.
pub type Truth<'a> = dyn Fn(&[scanner_formats::queries::Query]) -> Vec<[f32; 3]> + 'a;

/// Points per preview pixel, per axis.
pub const PREVIEW_SUB: u32 = 3;

/// Preview lights: (θ, φ) in degrees.
pub const PREVIEW_LIGHTS: [(f64, f64); 3] = [(25.0, 60.0), (45.0, 200.0), (60.0, 320.0)];

/// A preview PNG: the material over its extent (uv 0…1; a scanned sample
/// need not tile without a seam) under [`PREVIEW_LIGHTS`] seen from `view`
/// (columns), and under it the same from `truth` when given (the
/// simulator's ground truth for a simulated sample). Each pixel is the
/// mean of [`PREVIEW_SUB`]² points over it, so that neither row aliases a
/// texture finer than the preview's pixels. `view` comes with its angle to
/// the nearest captured view, degrees ([`novel_view`]), for the title.
pub fn preview(
    material: &scanner_shading::Material,
    (view, nearest): ([f64; 3], f64),
    truth: Option<&Truth<'_>>,
    path: &Path,
) -> Result<(), Failure> {
    use scanner_formats::queries::Query;
    const PX: u32 = 256;
    const GAP: u32 = 6;
    // Bands for the labels: a line of title (two beside the ground truth),
    // and a caption above each row of panels.
    const LABEL: u32 = 20;
    let rows = if truth.is_some() { 2 } else { 1 };
    let title = 4 + 19 * rows;
    let (w, h) =
        (PREVIEW_LIGHTS.len() as u32 * (PX + GAP) + GAP, title + rows * (LABEL + PX + GAP));
    let mut img = image::RgbImage::from_pixel(w, h, image::Rgb([40, 40, 40]));
    let (theta, phi) = angles(view);
    let mut captions = vec![Caption {
        text: format!(
            "Seen from θ {theta:.0}°, φ {phi:.0}° ({nearest:.1}° from the nearest captured view), \
             under {} lights",
            PREVIEW_LIGHTS.len()
        ),
        at: (GAP as i32, 12),
        centred: false,
        size: 14.0,
    }];
    if truth.is_some() {
        captions.push(Caption {
            text: "Top: the material file. Bottom: the simulator's ground truth (never read by \
                   the builder)."
                .into(),
            at: (GAP as i32, 31),
            centred: false,
            size: 14.0,
        });
    }
    const SUB: u32 = PREVIEW_SUB;
    let n = PX * SUB;
    for (c, &(t, p)) in PREVIEW_LIGHTS.iter().enumerate() {
        let wi = polar(t, p);
        for r in 0..rows {
            captions.push(Caption {
                text: format!("light θ {t:.0}°, φ {p:.0}°"),
                at: (
                    (GAP + c as u32 * (PX + GAP) + PX / 2) as i32,
                    (title + r * (LABEL + PX + GAP) + LABEL / 2) as i32,
                ),
                centred: true,
                size: 13.0,
            });
        }
        // Sub-point (sx, sy) of pixel (x, y) at query x·SUB + sx + n·(…).
        let queries: Vec<Query> = (0..n * n)
            .map(|i| {
                let (x, y) = ((i % n) as f64 + 0.5, (i / n) as f64 + 0.5);
                Query { uv: [x / n as f64, y / n as f64], wi, wo: view }
            })
            .collect();
        let mut panels = vec![crate::build::material::shade(material, &queries)];
        if let Some(t) = truth {
            panels.push(t(&queries));
        }
        for (r, vals) in panels.iter().enumerate() {
            let y0 = title + r as u32 * (LABEL + PX + GAP) + LABEL;
            let x0 = GAP + c as u32 * (PX + GAP);
            for (y, x) in (0..PX).flat_map(|y| (0..PX).map(move |x| (y, x))) {
                let mut sum = [0.0f32; 3];
                for (sy, sx) in (0..SUB).flat_map(|sy| (0..SUB).map(move |sx| (sy, sx))) {
                    let v = vals[((y * SUB + sy) * n + x * SUB + sx) as usize];
                    (0..3).for_each(|k| sum[k] += v[k]);
                }
                let mean = sum.map(|s| s / (SUB * SUB) as f32);
                img.put_pixel(x0 + x, y0 + y, image::Rgb(mean.map(encode_srgb)));
            }
        }
    }
    draw_captions(&mut img, &captions).map_err(|e| Failure(4, anyhow!(e)))?;
    write_png(path, &img)
}

/// `scanner preview`
pub fn preview_cmd(material: &Path, output: &Path) -> Result<(), Failure> {
    super::check_output(output, &[material], &["png"])?;
    let m = open_material(material)?;
    let views: Vec<[f64; 3]> = m.metadata().views.iter().map(|v| v.direction).collect();
    let (view, off) = novel_view(&views);
    preview(&m, (view, off), None, output)?;
    let (theta, phi) = angles(view);
    println!(
        "{}: seen from θ {theta:.0}°, φ {phi:.0}° ({off:.1}° from the nearest captured view)",
        output.display(),
    );
    Ok(())
}

/// What `scanner export` writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ExportFormat {
    /// A texture set's directory, maps in this format.
    Set(crate::build::export::MapFormat),
    /// A glTF asset's directory (`material.gltf`, its buffer, its maps).
    Gltf,
    /// One binary glTF file.
    Glb,
}

impl std::str::FromStr for ExportFormat {
    type Err = String;
    fn from_str(s: &str) -> Result<ExportFormat, String> {
        match s {
            "gltf" => Ok(ExportFormat::Gltf),
            "glb" => Ok(ExportFormat::Glb),
            maps => maps.parse().map(ExportFormat::Set),
        }
    }
}

/// `scanner export`
pub fn export_cmd(material: &Path, output: &Path, format: ExportFormat) -> Result<(), Failure> {
    use crate::build::export::{is_texture_set_file, texture_set};
    use crate::build::gltf::{glb, gltf_files, is_gltf_file};
    let ours = |name: &str| match format {
        ExportFormat::Set(_) => is_texture_set_file(name),
        _ => is_gltf_file(name),
    };
    let check = || match format {
        ExportFormat::Glb => super::check_output(output, &[material], &["glb"]),
        _ => crate::fsutil::check_output_dir(output, ours).map_err(|e| Failure(4, anyhow!(e))),
    };
    check()?;
    let bytes = scanner_formats::input::read(material)
        .map_err(|e| Failure(3, anyhow!("{}: {e}", material.display())))?;
    let damaged = |e| Failure(3, anyhow!("{}: {e}", material.display()));
    let data = scanner_shading::format::MaterialData::from_bytes(&bytes).map_err(damaged)?;
    let set = texture_set(&data)
        .map_err(|e| Failure(e.exit_code(), anyhow!("{}: {e}", material.display())))?;
    let (name, components) = (data.meta.name.clone(), data.meta.detail_components);
    // Only a file the shading opens: its direction tables checked too.
    scanner_shading::Material::from_data(data).map_err(damaged)?;
    let what = match format {
        ExportFormat::Glb => {
            let bytes = glb(&set).map_err(|e| Failure(4, anyhow!("{}: {e}", output.display())))?;
            check()?;
            crate::fsutil::write_atomic(output, &bytes)
                .map_err(|e| Failure(4, anyhow!("{}: {e}", output.display())))?;
            "binary glTF 2.0 asset (mesh; base colour, metallic-roughness, normal, specular colour)"
                .into()
        }
        // A directory: written into a fresh sibling, then swapped into
        // place, as `scanner regions` does: never half a set, never two
        // runs mixed.
        ExportFormat::Set(_) | ExportFormat::Gltf => {
            let place = |e: std::io::Error| Failure(4, anyhow!("{}: {e}", output.display()));
            let staging = crate::fsutil::staging_dir(output).map_err(place)?;
            let what = if let ExportFormat::Set(maps) = format {
                set.write(staging.path(), maps).map_err(build_failure)?;
                let names = crate::build::export::MAPS.join(", ");
                format!("texture set ({}: {names})", maps.extension())
            } else {
                let files = gltf_files(&set).map_err(|e| Failure(4, anyhow!("{e}")))?;
                for (file, bytes) in &files {
                    crate::fsutil::write_atomic(&staging.path().join(file), bytes)
                        .map_err(|e| Failure(4, anyhow!("{file}: {e}")))?;
                }
                "glTF 2.0 asset (material.gltf; baseColor, metallicRoughness, normal, specularColor)".into()
            };
            check()?;
            crate::fsutil::replace_dir(staging, output).map_err(place)?;
            what
        }
    };
    println!(
        "{}: {what} of {1}² texels over {2} mm → {3}",
        name,
        set.side,
        set.size_mm,
        output.display()
    );
    if components > 0 {
        println!(
            "  the detail layer's {components} light components vary with the light: left out"
        );
    }
    Ok(())
}

/// A material file for a command, or exit 3 (its errors name the file).
fn open_material(path: &Path) -> Result<scanner_shading::Material, Failure> {
    scanner_shading::Material::open(path).map_err(|e| Failure(3, anyhow!(e)))
}

/// `img` as a PNG file at `path`, written atomically (exit 4 if not).
fn write_png(path: &Path, img: &image::RgbImage) -> Result<(), Failure> {
    let failed = |e: &dyn std::fmt::Display| Failure(4, anyhow!("{}: {e}", path.display()));
    let mut bytes = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)
        .map_err(|e| failed(&e))?;
    crate::fsutil::write_atomic(path, &bytes).map_err(|e| failed(&e))
}

#[cfg(test)]
mod tests {
    use super::is_region_file;

    #[test]
    fn region_files_are_told_from_others() {
        for ok in [
            "l00-v39.exr",
            "l123-v07.exr",
            "detail.exr",
            "detail-l05.exr",
            "detail-l112.exr",
            "regions.json",
        ] {
            assert!(is_region_file(ok), "{ok}");
        }
        for not in
            ["l0-v39.exr", "l00-v39.png", "detail-l5.exr", "detail-lab.exr", "notes.txt", "detail"]
        {
            assert!(!is_region_file(not), "{not}");
        }
    }
}
