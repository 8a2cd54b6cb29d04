//! Shading query files and their answers (docs/query-format.md).
//!
//! A **query** is one shading request: a sample position `uv` and two unit
//! directions in the sample-local frame of docs/scanner-geometry.md (z =
//! the sample's normal): `wi` towards the light, `wo` towards the viewer.
//! Its **answer** is the radiance reflected towards `wo` per unit irradiance
//! from `wi` (f · cos θi), linear RGB.
//!
//! - Queries: `.npy`, shape (N, 8), float32 or float64, columns
//!   `u, v, wi_x, wi_y, wi_z, wo_x, wo_y, wo_z`; or `.csv` with a header
//!   naming exactly those eight columns (any order).
//! - Answers: `.npy`, shape (N, 3), float32; or `.csv` with header `r,g,b`.
//!
//! Directions need not be unit vectors: any finite direction longer than
//! 1e-6 is **normalised**; NaN, infinite or zero directions and non-finite
//! uv are refused with the row they are on.

use std::path::{Path, PathBuf};

use crate::atomic::write_atomic_with;

/// Column names of a query file, in `.npy` column order.
pub const QUERY_COLUMNS: [&str; 8] = ["u", "v", "wi_x", "wi_y", "wi_z", "wo_x", "wo_y", "wo_z"];
/// Column names of an answer file.
pub const ANSWER_COLUMNS: [&str; 3] = ["r", "g", "b"];

/// One shading request.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Query {
    /// Position on the sample, [0, 1]² across it.
    pub uv: [f64; 2],
    /// Unit direction towards the light, sample-local.
    pub wi: [f64; 3],
    /// Unit direction towards the viewer, sample-local.
    pub wo: [f64; 3],
}

impl Query {
    /// A query from a file row (the eight columns in order), validated and
    /// with its directions normalised. `row` counts from 0, for messages.
    pub fn from_row(r: [f64; 8], row: usize) -> Result<Query, RowError> {
        for (k, v) in r.iter().enumerate() {
            if !v.is_finite() {
                return Err(RowError { row, reason: format!("{} is {v}", QUERY_COLUMNS[k]) });
            }
        }
        let unit = |v: [f64; 3], name: &str| {
            // Scaled by the largest component first, so that no square
            // overflows (1e200 would give a zero "unit" vector).
            let big = v.iter().fold(0.0f64, |m, c| m.max(c.abs()));
            let s = v.map(|c| c / big);
            let len = big * (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt();
            if len > 1e-6 {
                Ok(v.map(|c| c / len))
            } else {
                Err(RowError { row, reason: format!("{name} is a zero vector") })
            }
        };
        Ok(Query {
            uv: [r[0], r[1]],
            wi: unit([r[2], r[3], r[4]], "wi")?,
            wo: unit([r[5], r[6], r[7]], "wo")?,
        })
    }

    /// The eight columns in order.
    pub fn to_row(&self) -> [f64; 8] {
        [
            self.uv[0], self.uv[1], self.wi[0], self.wi[1], self.wi[2], self.wo[0], self.wo[1],
            self.wo[2],
        ]
    }
}

/// A bad row.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("row {row}: {reason}")]
pub struct RowError {
    /// Row, from 0 (data rows; a CSV header is not counted).
    pub row: usize,
    /// What is wrong.
    pub reason: String,
}

/// Why a query or answer file was refused.
#[derive(Debug, thiserror::Error)]
pub enum QueryError {
    /// Not `.npy` or `.csv`.
    #[error("{}: unknown file type (use .npy or .csv)", .0.display())]
    Extension(PathBuf),
    /// Cannot read or write the file.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The file is not what the format says.
    #[error("{}: {reason}", path.display())]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong (shape, dtype, columns, header).
        reason: String,
    },
    /// A row is refused.
    #[error("{}: {error}", path.display())]
    Row {
        /// The file.
        path: PathBuf,
        /// The row and why.
        error: RowError,
    },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Npy,
    Csv,
}

fn kind(path: &Path) -> Result<Kind, QueryError> {
    match path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase).as_deref() {
        Some("npy") => Ok(Kind::Npy),
        Some("csv") => Ok(Kind::Csv),
        _ => Err(QueryError::Extension(path.to_path_buf())),
    }
}

fn format_err(path: &Path, reason: impl Into<String>) -> QueryError {
    QueryError::Format { path: path.to_path_buf(), reason: reason.into() }
}

/// Check that `path` names a query or answer file type (before any work).
pub fn check_extension(path: &Path) -> Result<(), QueryError> {
    kind(path).map(|_| ())
}

fn read_bytes(path: &Path) -> Result<Vec<u8>, QueryError> {
    kind(path)?;
    crate::input::read(path).map_err(|source| QueryError::Io { path: path.to_path_buf(), source })
}

/// Read a query file.
pub fn read_queries(path: &Path) -> Result<Vec<Query>, QueryError> {
    parse_queries(path, &read_bytes(path)?)
}

/// A query file's content: `bytes` as read from `path` (whose extension
/// says `.npy` or `.csv`; the path is only named in errors).
pub fn parse_queries(path: &Path, bytes: &[u8]) -> Result<Vec<Query>, QueryError> {
    let rows = match kind(path)? {
        Kind::Npy => parse_npy::<8>(path, bytes)?,
        Kind::Csv => parse_csv::<8>(path, bytes, &QUERY_COLUMNS)?,
    };
    rows.into_iter()
        .enumerate()
        .map(|(i, r)| {
            Query::from_row(r, i)
                .map_err(|error| QueryError::Row { path: path.to_path_buf(), error })
        })
        .collect()
}

/// Write a query file (float64 `.npy`, or `.csv` with exact round trip).
pub fn write_queries(path: &Path, queries: &[Query]) -> Result<(), QueryError> {
    let rows: Vec<[f64; 8]> = queries.iter().map(Query::to_row).collect();
    match kind(path)? {
        Kind::Npy => write_npy(path, &rows),
        Kind::Csv => write_csv(path, &QUERY_COLUMNS, &rows),
    }
}

/// Read an answer file.
pub fn read_answers(path: &Path) -> Result<Vec<[f32; 3]>, QueryError> {
    parse_answers(path, &read_bytes(path)?)
}

/// An answer file's content (`path` as for [`parse_queries`]).
pub fn parse_answers(path: &Path, bytes: &[u8]) -> Result<Vec<[f32; 3]>, QueryError> {
    let rows = match kind(path)? {
        Kind::Npy => parse_npy::<3>(path, bytes)?,
        Kind::Csv => parse_csv::<3>(path, bytes, &ANSWER_COLUMNS)?,
    };
    Ok(rows.into_iter().map(|r| r.map(|v| v as f32)).collect())
}

/// Write an answer file (float32 `.npy`, or `.csv`).
pub fn write_answers(path: &Path, answers: &[[f32; 3]]) -> Result<(), QueryError> {
    match kind(path)? {
        Kind::Npy => write_npy(path, answers),
        Kind::Csv => write_csv(path, &ANSWER_COLUMNS, answers),
    }
}

fn parse_npy<const C: usize>(path: &Path, bytes: &[u8]) -> Result<Vec<[f64; C]>, QueryError> {
    check_npy_header(bytes).map_err(|reason| format_err(path, reason))?;
    let npy =
        npyz::NpyFile::new(bytes).map_err(|e| format_err(path, format!("not a .npy file: {e}")))?;
    let shape = npy.shape().to_vec();
    if shape.len() != 2 || shape[1] != C as u64 {
        return Err(format_err(path, format!("shape {shape:?}, expected (N, {C})")));
    }
    let n = usize::try_from(shape[0]).map_err(|_| format_err(path, "too many rows"))?;
    let fortran = npy.order() == npyz::Order::Fortran;
    let dtype = npy.dtype().descr();
    let item = match dtype.trim_matches('\'').trim_start_matches(['<', '=', '|']) {
        "f8" => 8,
        "f4" => 4,
        _ => return Err(format_err(path, format!("dtype {dtype}, expected float32 or float64"))),
    };
    // The header's shape must fit in the file before anything is allocated
    // for it: a forged row count would otherwise ask for exabytes.
    if n.checked_mul(C * item).is_none_or(|data| data > bytes.len()) {
        return Err(format_err(
            path,
            format!("shape ({n}, {C}) needs more data than the file's {} bytes", bytes.len()),
        ));
    }
    let flat: Vec<f64> = if item == 8 {
        npy.into_vec::<f64>()
    } else {
        npy.into_vec::<f32>().map(|v| v.into_iter().map(f64::from).collect())
    }
    .map_err(|e| format_err(path, format!("truncated or unreadable data: {e}")))?;
    if flat.len() != n * C {
        return Err(format_err(path, format!("{} values for shape ({n}, {C})", flat.len())));
    }
    Ok((0..n)
        .map(|i| std::array::from_fn(|k| if fortran { flat[k * n + i] } else { flat[i * C + k] }))
        .collect())
}

/// Checks of a `.npy` header that npyz 0.9 does not make safely, before
/// it parses it: its Python-literal parser backtracks exponentially on
/// nested brackets (a few hundred bytes of `{'a':{'a':…` never finish), and
/// it multiplies the shape unchecked (a panic in debug builds, a wrapped
/// count in release ones). A query or answer file's header is one flat
/// dictionary — `descr` a string, `shape` a tuple of integers — so more
/// than one `{` or `(`, or any `[`, is refused here. A file that is not
/// `.npy` at all is left to npyz's own error.
fn check_npy_header(bytes: &[u8]) -> Result<(), String> {
    if !bytes.starts_with(b"\x93NUMPY") || bytes.len() < 12 {
        return Ok(());
    }
    let (len, start): (usize, usize) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => (u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize, 12),
        _ => return Ok(()),
    };
    let header = &bytes[start..bytes.len().min(start.saturating_add(len))];
    let count = |c: u8| header.iter().filter(|&&b| b == c).count();
    if count(b'{') > 1 || count(b'(') > 1 || count(b'[') > 0 {
        return Err("the header is not one flat dictionary with a shape tuple (nested or \
                    structured dtypes are not query or answer files)"
            .into());
    }
    let Some(at) = header.windows(8).position(|w| w == b"'shape':") else {
        return Ok(());
    };
    let rest = &header[at + 8..];
    let (Some(open), Some(close)) =
        (rest.iter().position(|&b| b == b'('), rest.iter().position(|&b| b == b')'))
    else {
        return Ok(());
    };
    let Some(Ok(tuple)) = (open < close).then(|| std::str::from_utf8(&rest[open + 1..close]))
    else {
        return Ok(());
    };
    let mut product: Option<u64> = Some(1);
    for dim in tuple.split(',').map(str::trim).filter(|d| !d.is_empty()) {
        let Ok(d) = dim.parse::<u64>() else {
            return Ok(());
        };
        product = product.and_then(|p| p.checked_mul(d));
    }
    match product {
        Some(_) => Ok(()),
        None => Err("shape has more elements than any file can hold".into()),
    }
}

trait NpyValue: Copy + npyz::AutoSerialize + npyz::Serialize {}
impl NpyValue for f32 {}
impl NpyValue for f64 {}

fn write_npy<T: NpyValue, const C: usize>(path: &Path, rows: &[[T; C]]) -> Result<(), QueryError> {
    use npyz::WriterBuilder;
    write_atomic_with(path, |w| {
        let mut writer = npyz::WriteOptions::new()
            .default_dtype()
            .shape(&[rows.len() as u64, C as u64])
            .writer(w)
            .begin_nd()?;
        writer.extend(rows.iter().flat_map(|r| r.iter().copied()))?;
        writer.finish()
    })
    .map_err(|source| QueryError::Io { path: path.to_path_buf(), source })
}

fn parse_csv<const C: usize>(
    path: &Path,
    bytes: &[u8],
    names: &[&str; C],
) -> Result<Vec<[f64; C]>, QueryError> {
    let mut reader = csv::ReaderBuilder::new().trim(csv::Trim::All).from_reader(bytes);
    let header = reader.headers().map_err(|e| csv_err(path, e))?.clone();
    let mut index = [usize::MAX; C];
    for (col, name) in header.iter().enumerate() {
        match names.iter().position(|n| *n == name) {
            Some(k) if index[k] == usize::MAX => index[k] = col,
            Some(_) => return Err(format_err(path, format!("column {name:?} appears twice"))),
            None => {
                return Err(format_err(
                    path,
                    format!("unknown column {name:?} (expected {})", names.join(",")),
                ));
            }
        }
    }
    if let Some(k) = index.iter().position(|&i| i == usize::MAX) {
        return Err(format_err(path, format!("missing column {:?}", names[k])));
    }
    let mut rows = Vec::new();
    for (i, record) in reader.records().enumerate() {
        let record = record.map_err(|e| csv_err(path, e))?;
        let mut row = [0.0; C];
        for k in 0..C {
            let text = record.get(index[k]).unwrap_or("");
            row[k] = text.parse().map_err(|_| QueryError::Row {
                path: path.to_path_buf(),
                error: RowError {
                    row: i,
                    reason: format!("{}: {text:?} is not a number", names[k]),
                },
            })?;
        }
        rows.push(row);
    }
    Ok(rows)
}

fn csv_err(path: &Path, e: csv::Error) -> QueryError {
    if e.is_io_error() {
        if let csv::ErrorKind::Io(source) = e.into_kind() {
            return QueryError::Io { path: path.to_path_buf(), source };
        }
        unreachable!("is_io_error");
    }
    format_err(path, e.to_string())
}

fn write_csv<T: std::fmt::Display, const C: usize>(
    path: &Path,
    names: &[&str; C],
    rows: &[[T; C]],
) -> Result<(), QueryError> {
    write_atomic_with(path, |w| {
        writeln!(w, "{}", names.join(","))?;
        for r in rows {
            let cells: Vec<String> = r.iter().map(|v| v.to_string()).collect();
            writeln!(w, "{}", cells.join(","))?;
        }
        Ok(())
    })
    .map_err(|source| QueryError::Io { path: path.to_path_buf(), source })
}
