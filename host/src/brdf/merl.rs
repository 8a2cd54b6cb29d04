//! MERL binary BRDF tables (spec/npf-brdf.md §5): a header of three
//! little-endian i32 (90, 90, 180), then 3 × 1 458 000 little-endian f64,
//! channel-major, scaled by 1/1500, 1.15/1500, 1.66/1500 for R, G, B; a
//! negative value marks a missing sample. Values must be finite and, once
//! scaled, at most [`MAX_VALUE`] sr⁻¹.

use std::io::Read;
use std::path::Path;

use super::coords::{
    MERL_CELLS, N_PHI_D, N_THETA_D, N_THETA_H, from_directions, merl_index, phi_d_bin, theta_d_bin,
    theta_h_bin,
};
use super::{Brdf, MAX_VALUE, Vec3};

/// Stored value × scale = BRDF value (sr⁻¹), per channel.
pub const SCALE: [f64; 3] = [1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0];

/// Size of a MERL file, bytes.
pub const FILE_SIZE: u64 = 12 + 3 * MERL_CELLS as u64 * 8;

/// Why a MERL file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum MerlError {
    /// I/O failed.
    #[error("cannot read {path}: {source}")]
    Io {
        /// File.
        path: String,
        /// Cause.
        source: std::io::Error,
    },
    /// The file has the wrong length.
    #[error("{path} is {size} bytes; a MERL table is exactly {FILE_SIZE} bytes")]
    WrongSize {
        /// File.
        path: String,
        /// Its size.
        size: u64,
    },
    /// The header does not say 90 × 90 × 180.
    #[error("{path}: header dimensions {dims:?}, expected [90, 90, 180] (product 1458000)")]
    WrongDims {
        /// File.
        path: String,
        /// What the header says.
        dims: [i32; 3],
    },
    /// A value is NaN or infinite.
    #[error("{path}: value {index} of channel {channel} is not finite ({value})")]
    NotFinite {
        /// File.
        path: String,
        /// Channel 0..3.
        channel: usize,
        /// Cell index.
        index: usize,
        /// The value.
        value: f64,
    },
    /// A value lies beyond [`MAX_VALUE`] once scaled.
    #[error(
        "{path}: value {index} of channel {channel} is {value:.3e} sr⁻¹, beyond any BRDF (at most {MAX_VALUE:.0e} sr⁻¹): are the units right?"
    )]
    TooLarge {
        /// File.
        path: String,
        /// Channel 0..3.
        channel: usize,
        /// Cell index.
        index: usize,
        /// The value, scaled (sr⁻¹).
        value: f64,
    },
}

/// A MERL table in BRDF units (already scaled); negative = missing.
#[derive(Debug, Clone, PartialEq)]
pub struct MerlTable {
    /// Channel-major values, `3 × MERL_CELLS`.
    values: Vec<f64>,
}

impl MerlTable {
    /// A table with every cell missing.
    pub fn empty() -> MerlTable {
        MerlTable { values: vec![-1.0; 3 * MERL_CELLS] }
    }

    /// Fill every cell from `f(θh, θd, φd)` at its centre; cells whose
    /// directions are below the horizon are marked missing.
    pub fn from_fn(f: impl Fn(Vec3, Vec3) -> [f64; 3] + Sync) -> MerlTable {
        use rayon::prelude::*;
        let mut t = MerlTable::empty();
        let cells: Vec<(usize, [f64; 3])> = (0..N_THETA_H)
            .into_par_iter()
            .flat_map_iter(|th| {
                let f = &f;
                (0..N_THETA_D).flat_map(move |td| {
                    (0..N_PHI_D).map(move |pd| {
                        let hd = super::coords::cell_centre(th, td, pd);
                        let (wi, wo) = super::coords::to_directions(hd);
                        let v = if wi[2] > 0.0 && wo[2] > 0.0 { f(wi, wo) } else { [-1.0; 3] };
                        (merl_index(th, td, pd), v)
                    })
                })
            })
            .collect();
        for (i, v) in cells {
            for (c, v) in v.iter().enumerate() {
                t.values[c * MERL_CELLS + i] = *v;
            }
        }
        t
    }

    /// Value of cell `index` in `channel` (negative: missing).
    pub fn get(&self, channel: usize, index: usize) -> f64 {
        self.values[channel * MERL_CELLS + index]
    }

    /// Set a cell.
    pub fn set(&mut self, channel: usize, index: usize, value: f64) {
        self.values[channel * MERL_CELLS + index] = value;
    }

    /// Read a MERL file.
    pub fn read(path: &Path) -> Result<MerlTable, MerlError> {
        let name = path.display().to_string();
        let io = |source| MerlError::Io { path: name.clone(), source };
        let mut file = scanner_formats::input::open(path).map_err(io)?;
        let size = file.metadata().map_err(io)?.len();
        let mut header = [0u8; 12];
        if size < 12 {
            return Err(MerlError::WrongSize { path: name, size });
        }
        file.read_exact(&mut header).map_err(io)?;
        let dims = [0, 4, 8].map(|o| i32::from_le_bytes(header[o..o + 4].try_into().unwrap()));
        let product = dims.iter().map(|&d| d as i64).product::<i64>();
        if dims != [90, 90, 180] || product != MERL_CELLS as i64 {
            return Err(MerlError::WrongDims { path: name, dims });
        }
        if size != FILE_SIZE {
            return Err(MerlError::WrongSize { path: name, size });
        }
        let mut raw = vec![0u8; 3 * MERL_CELLS * 8];
        file.read_exact(&mut raw).map_err(io)?;
        let mut values = Vec::with_capacity(3 * MERL_CELLS);
        for (n, chunk) in raw.chunks_exact(8).enumerate() {
            let v = f64::from_le_bytes(chunk.try_into().unwrap());
            let channel = n / MERL_CELLS;
            if !v.is_finite() {
                return Err(MerlError::NotFinite {
                    path: name,
                    channel,
                    index: n % MERL_CELLS,
                    value: v,
                });
            }
            let value = if v < 0.0 { v } else { v * SCALE[channel] };
            if value > MAX_VALUE {
                return Err(MerlError::TooLarge {
                    path: name,
                    channel,
                    index: n % MERL_CELLS,
                    value,
                });
            }
            values.push(value);
        }
        Ok(MerlTable { values })
    }

    /// Write a MERL file (atomically).
    pub fn write(&self, path: &Path) -> std::io::Result<()> {
        let mut bytes = Vec::with_capacity(FILE_SIZE as usize);
        for d in [90i32, 90, 180] {
            bytes.extend_from_slice(&d.to_le_bytes());
        }
        for (n, &v) in self.values.iter().enumerate() {
            let stored = if v < 0.0 { v } else { v / SCALE[n / MERL_CELLS] };
            bytes.extend_from_slice(&stored.to_le_bytes());
        }
        crate::fsutil::write_atomic(path, &bytes)
    }

    /// Nearest-cell lookup of a direction pair (missing cells read as 0).
    pub fn lookup(&self, wi: Vec3, wo: Vec3) -> [f64; 3] {
        if wi[2] <= 0.0 || wo[2] <= 0.0 {
            return [0.0; 3];
        }
        let hd = from_directions(wi, wo);
        let i = merl_index(theta_h_bin(hd.theta_h), theta_d_bin(hd.theta_d), phi_d_bin(hd.phi_d));
        [0, 1, 2].map(|c| self.get(c, i).max(0.0))
    }
}

/// Cosine-weighted relative RMSE of `model` against `table` over the valid
/// cells at their centres (docs/npf-format.md §5):
/// sqrt(Σ (cos θi cos θo (ρ − ρ̂))² / Σ (cos θi cos θo ρ̂)²), all channels.
pub fn cosine_weighted_relative_rmse(table: &MerlTable, model: &dyn Brdf) -> f64 {
    let (mut num, mut den) = (0.0, 0.0);
    for th in 0..N_THETA_H {
        for td in 0..N_THETA_D {
            for pd in 0..N_PHI_D {
                let (wi, wo) = super::coords::to_directions(super::coords::cell_centre(th, td, pd));
                if wi[2] <= 0.0 || wo[2] <= 0.0 {
                    continue;
                }
                let i = merl_index(th, td, pd);
                let w = (wi[2] * wo[2]).powi(2);
                for (c, f) in model.eval(wi, wo).iter().enumerate() {
                    let t = table.get(c, i);
                    if t >= 0.0 {
                        num += w * (f - t) * (f - t);
                        den += w * t * t;
                    }
                }
            }
        }
    }
    (num / den).sqrt()
}

impl Brdf for MerlTable {
    fn eval(&self, wi: Vec3, wo: Vec3) -> [f64; 3] {
        self.lookup(wi, wo)
    }
}
