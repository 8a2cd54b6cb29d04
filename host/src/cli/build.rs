//! `scanner calibrate` and `scanner regions`: the material builder's first
//! half on scan directories.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::anyhow;
use indicatif::{ProgressBar, ProgressStyle};
use scanner_geometry::ScannerGeometry;

use super::Failure;
use crate::build::calibrate::{BuildProgress, CalibrateOptions, Calibration};
use crate::build::locate::Checkerboard;
use crate::build::scanread::ScanFrames;
use crate::build::{BuildError, calibrate, extract_regions};

/// A progress bar per builder stage.
pub struct StageBar(ProgressBar);

impl StageBar {
    pub fn new() -> StageBar {
        let bar = ProgressBar::new(0);
        bar.set_style(
            ProgressStyle::with_template("{msg:>20} [{bar:30}] {pos}/{len}, {elapsed}")
                .expect("valid template"),
        );
        StageBar(bar)
    }

    pub fn finish(&self) {
        self.0.finish_and_clear();
    }
}

impl BuildProgress for StageBar {
    fn stage(&self, name: &str, total: usize) {
        self.0.set_message(name.to_string());
        self.0.set_length(total as u64);
        self.0.set_position(0);
    }
    fn step(&self) {
        self.0.inc(1);
    }
}

fn build_failure(e: BuildError) -> Failure {
    Failure(e.exit_code(), anyhow!(e))
}

/// The nominal geometry a scan was taken with: `--geometry`, or the
/// shipped default scaled to the scan's frame size (a binned sensor).
pub fn geometry_for(path: Option<&Path>, scan: &Path) -> Result<ScannerGeometry, Failure> {
    if let Some(p) = path {
        return ScannerGeometry::load(p).map_err(|e| Failure(3, anyhow!(e)));
    }
    let m = crate::scan::Manifest::load(scan)
        .map_err(|e| Failure(3, anyhow!("no scan at {}: {e}", scan.display())))?;
    let base = ScannerGeometry::default_scanner();
    for bin in 1..=64 {
        let g = base.with_sensor_scaled(bin);
        if g.hash() == m.settings.geometry_sha256 {
            return Ok(g);
        }
    }
    Err(Failure(
        3,
        anyhow!(
            "{}: taken with a geometry other than the shipped default: pass it with --geometry",
            scan.display()
        ),
    ))
}

/// `scanner calibrate`
pub fn calibrate_cmd(
    checkerboard: &Path,
    white: &Path,
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
    crate::fsutil::check_output(output, &[checkerboard, white])
        .map_err(|e| Failure(4, anyhow!(e)))?;
    let started = Instant::now();
    let g = geometry_for(geometry, checkerboard)?;
    let checker = ScanFrames::open(checkerboard, &g).map_err(build_failure)?;
    let white_scan = ScanFrames::open(white, &g).map_err(build_failure)?;
    let opts = CalibrateOptions { target: Checkerboard { squares }, white_albedo };
    let bar = StageBar::new();
    let cal = calibrate(&g, &checker, &white_scan, &opts, &bar);
    bar.finish();
    let cal = cal.map_err(build_failure)?;
    cal.save(output).map_err(build_failure)?;
    let with_corners = cal.views.iter().filter(|v| v.corners_used > 0).count();
    let rms = cal
        .views
        .iter()
        .filter(|v| v.corners_used > 0)
        .map(|v| v.corner_rms_px)
        .fold(0.0, f64::max);
    println!(
        "calibrated {} views and {} lights in {:.1} s: {with_corners} views by their checker corners \
         (largest fit residual {rms:.3} px), the rest by Fourier phase → {}",
        cal.views.len(),
        cal.lights.len(),
        started.elapsed().as_secs_f64(),
        output.display()
    );
    Ok(())
}

/// `scanner regions`
pub fn regions_cmd(
    scan: &Path,
    calibration: &Path,
    output: &Path,
    geometry: Option<&Path>,
    size: Option<usize>,
) -> Result<crate::build::RegionSet, Failure> {
    if let Some(s) = size
        && !(4..=4096).contains(&s)
    {
        return Err(Failure(2, anyhow!("--size must be in 4…4096, got {s}")));
    }
    if output.exists() && !output.is_dir() {
        return Err(Failure(4, anyhow!("{}: exists and is not a directory", output.display())));
    }
    let started = Instant::now();
    let cal = Calibration::load(calibration).map_err(build_failure)?;
    let g = geometry_for(geometry, scan)?;
    let frames = ScanFrames::open(scan, &g).map_err(build_failure)?;
    let bar = StageBar::new();
    let regions = extract_regions(&g, &cal, &frames, size, &bar);
    bar.finish();
    let regions = regions.map_err(build_failure)?;
    let extracted = started.elapsed().as_secs_f64();
    // Written into a fresh sibling directory, then renamed into place: no
    // partial output on failure.
    let staging = staging_dir(output);
    let _ = std::fs::remove_dir_all(&staging);
    if let Err(e) = regions.write_exr(&staging) {
        let _ = std::fs::remove_dir_all(&staging);
        return Err(build_failure(e));
    }
    replace_dir(&staging, output).map_err(|e| Failure(4, anyhow!("{}: {e}", output.display())))?;
    println!(
        "{} region images of {}² px ({} lights × {} views) in {extracted:.1} s (+ {:.1} s writing) → {}",
        regions.images.len(),
        regions.size,
        regions.lights.len(),
        regions.views.len(),
        started.elapsed().as_secs_f64() - extracted,
        output.display()
    );
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
    let (w, h) = (cols.len() as u32 * (s + gap) + gap, rows.len() as u32 * (s + gap) + gap);
    let mut img = image::RgbImage::from_pixel(w, h, image::Rgb([40, 40, 40]));
    let encode = |v: f32| {
        let x = (v * std::f32::consts::PI).max(0.0);
        let t = x / (1.0 + x);
        let c = if t <= 0.003_130_8 { 12.92 * t } else { 1.055 * t.powf(1.0 / 2.4) - 0.055 };
        (c * 255.0).round().clamp(0.0, 255.0) as u8
    };
    for (r, &li) in rows.iter().enumerate() {
        for (c, &vi) in cols.iter().enumerate() {
            let src = regions.image(li, vi);
            let (x0, y0) = (gap + c as u32 * (s + gap), gap + r as u32 * (s + gap));
            for (i, px) in src.iter().enumerate() {
                let (x, y) = (i as u32 % s, i as u32 / s);
                img.put_pixel(x0 + x, y0 + y, image::Rgb(px.map(encode)));
            }
        }
    }
    let mut bytes = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)
        .map_err(|e| Failure(4, anyhow!("{}: {e}", path.display())))?;
    crate::fsutil::write_atomic(path, &bytes)
        .map_err(|e| Failure(4, anyhow!("{}: {e}", path.display())))
}

fn staging_dir(output: &Path) -> PathBuf {
    let name = output.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    output.with_file_name(format!(".{name}.partial"))
}

/// Put `staging` where `output` is (an existing output directory is
/// replaced only after the new one is complete).
fn replace_dir(staging: &Path, output: &Path) -> std::io::Result<()> {
    if output.exists() {
        let old = output.with_file_name(format!(
            ".{}.old",
            output.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()
        ));
        let _ = std::fs::remove_dir_all(&old);
        std::fs::rename(output, &old)?;
        std::fs::rename(staging, output)?;
        std::fs::remove_dir_all(&old)?;
    } else {
        std::fs::rename(staging, output)?;
    }
    if let Some(parent) = output.parent() {
        crate::fsutil::sync_dir(if parent.as_os_str().is_empty() {
            Path::new(".")
        } else {
            parent
        })?;
    }
    Ok(())
}
