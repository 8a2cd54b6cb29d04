//! Scattered BRDF measurements as CSV — what a gonioreflectometer or a scan
//! provides instead of a dense MERL table (docs/npf-format.md §7).
//!
//! One measurement per row, with a header naming the columns:
//!
//! ```text
//! wi_x,wi_y,wi_z,wo_x,wo_y,wo_z,r,g,b
//! 0.2588,0,0.9659,-0.5,0,0.8660,0.182,0.041,0.029
//! ```
//!
//! Directions are unit vectors in the local frame (normal +z), `wi` towards
//! the light; r, g, b are BRDF values in sr⁻¹ without the cosine, negative
//! for a channel that was not measured. Columns may come in any order (they
//! are matched by name); extra columns are ignored.

use std::io::Read;
use std::path::Path;

use super::MAX_VALUE;
use super::fit::Measurement;

/// Why a measurement file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum MeasurementError {
    /// The file could not be opened or read.
    #[error("cannot read {path}")]
    Io {
        /// The file.
        path: String,
        /// The cause.
        source: std::io::Error,
    },
    /// A row (or the header) is malformed.
    #[error("{path}, line {line}: {why}")]
    Malformed {
        /// The file.
        path: String,
        /// 1-based line number.
        line: u64,
        /// What is wrong.
        why: String,
    },
    /// No row.
    #[error("{path}: no measurement")]
    Empty {
        /// The file.
        path: String,
    },
}

/// The columns, in the order [`write_csv`] writes them.
pub const COLUMNS: [&str; 9] = ["wi_x", "wi_y", "wi_z", "wo_x", "wo_y", "wo_z", "r", "g", "b"];

/// Read a measurement CSV. Every value must be a finite number, r, g and b
/// at most [`MAX_VALUE`], and both directions unit vectors (±1e-4, to allow
/// for printed precision; such vectors are renormalised); below-horizon rows
/// are kept (the fit skips them).
pub fn read_csv(path: &Path) -> Result<Vec<Measurement>, MeasurementError> {
    let name = path.display().to_string();
    let file = scanner_formats::input::open(path)
        .map_err(|source| MeasurementError::Io { path: name.clone(), source })?;
    parse_csv(file, &name)
}

/// [`read_csv`] of a reader; `name` names the file in errors.
pub fn parse_csv(file: impl Read, name: &str) -> Result<Vec<Measurement>, MeasurementError> {
    let malformed =
        |line: u64, why: String| MeasurementError::Malformed { path: name.to_owned(), line, why };
    let mut reader =
        csv::ReaderBuilder::new().trim(csv::Trim::All).comment(Some(b'#')).from_reader(file);
    let header = reader.headers().map_err(|e| malformed(1, e.to_string()))?.clone();
    let mut index = [0usize; 9];
    for (slot, column) in index.iter_mut().zip(COLUMNS) {
        *slot = header.iter().position(|h| h == column).ok_or_else(|| {
            malformed(1, format!("no column {column:?} (need {})", COLUMNS.join(",")))
        })?;
    }
    let mut out = Vec::new();
    for record in reader.records() {
        let record = record.map_err(|e| {
            let line = e.position().map_or(0, |p| p.line());
            malformed(line, e.to_string())
        })?;
        let line = record.position().map_or(0, |p| p.line());
        let mut v = [0.0f64; 9];
        for (k, (x, column)) in v.iter_mut().zip(COLUMNS).enumerate() {
            let text = record.get(index[k]).unwrap_or_default();
            *x = text
                .parse::<f64>()
                .map_err(|_| malformed(line, format!("{column} = {text:?} is not a number")))?;
            if !x.is_finite() {
                return Err(malformed(line, format!("{column} = {text} is not finite")));
            }
            if k >= 6 && *x > MAX_VALUE {
                return Err(malformed(
                    line,
                    format!(
                        "{column} = {x:e} is beyond any BRDF (at most {MAX_VALUE:.0e} sr⁻¹): are the units right?"
                    ),
                ));
            }
        }
        let unit = |d: [f64; 3], what: &str| {
            let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            if (n - 1.0).abs() > 1e-4 {
                Err(malformed(line, format!("{what} has length {n:.6}, not 1")))
            } else if (n - 1.0).abs() > 1e-12 {
                // Printed with few digits: renormalise (exact vectors are kept bit for bit).
                Ok(d.map(|x| x / n))
            } else {
                Ok(d)
            }
        };
        out.push(Measurement {
            wi: unit([v[0], v[1], v[2]], "wi")?,
            wo: unit([v[3], v[4], v[5]], "wo")?,
            rgb: [v[6], v[7], v[8]],
        });
    }
    if out.is_empty() {
        return Err(MeasurementError::Empty { path: name.to_owned() });
    }
    Ok(out)
}

/// Write measurements as CSV (atomically: temporary file + rename), with the
/// header of [`COLUMNS`] and full f64 precision.
pub fn write_csv(path: &Path, measurements: &[Measurement]) -> std::io::Result<()> {
    let mut w = csv::Writer::from_writer(Vec::new());
    let io = |e: csv::Error| std::io::Error::other(e.to_string());
    w.write_record(COLUMNS).map_err(io)?;
    for m in measurements {
        let row: Vec<String> =
            m.wi.iter().chain(&m.wo).chain(&m.rgb).map(|x| format!("{x:?}")).collect();
        w.write_record(&row).map_err(io)?;
    }
    let bytes = w.into_inner().map_err(|e| std::io::Error::other(e.to_string()))?;
    crate::fsutil::write_atomic(path, &bytes)
}
