//! The NPF model (spec/npf-brdf.md §2), its JSON file (docs/npf-format.md),
//! and the naive D·F·H comparison model.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::coords::{from_directions, g_interp, phi_d_bin, theta_d_bin, theta_h_bin};
use super::{BINS, Brdf, MAX_VALUE, Vec3};

/// Smallest factor value (spec §2).
pub const EPSILON: f64 = 1e-6;

/// One colour channel of an NPF model.
#[derive(Debug, Clone, PartialEq)]
pub struct Channel {
    /// Diffuse constant (π folded in).
    pub rho_d: f64,
    /// Specular scale (1/4 folded in).
    pub rho_s: f64,
    /// Normal distribution over θh′ bins.
    pub d: [f64; BINS],
    /// Fresnel-like factor over θd bins.
    pub f: [f64; BINS],
    /// Shadowing/masking over θ, interpolated between bin centres.
    pub g: [f64; BINS],
}

impl Channel {
    /// ρd = 0, ρs = 1, every factor 1.
    pub fn flat() -> Channel {
        Channel { rho_d: 0.0, rho_s: 1.0, d: [1.0; BINS], f: [1.0; BINS], g: [1.0; BINS] }
    }

    /// G at θ (linear between bin centres).
    pub fn g_at(&self, theta: f64) -> f64 {
        self.g_lerp(g_interp(theta))
    }

    fn g_lerp(&self, (a, w): (usize, f64)) -> f64 {
        self.g[a] * (1.0 - w) + self.g[a + 1] * w
    }

    /// ρ at a direction pair (cos θi, cos θo > 0 assumed).
    pub fn eval_hd(&self, th_bin: usize, td_bin: usize, cos_i: f64, cos_o: f64) -> f64 {
        let gi = g_interp(cos_i.clamp(-1.0, 1.0).acos());
        let go = g_interp(cos_o.clamp(-1.0, 1.0).acos());
        self.eval_at(th_bin, td_bin, gi, go, cos_i * cos_o)
    }

    fn eval_at(&self, th: usize, td: usize, gi: (usize, f64), go: (usize, f64), cc: f64) -> f64 {
        self.rho_d + self.rho_s * self.d[th] * self.f[td] * self.g_lerp(gi) * self.g_lerp(go) / cc
    }
}

/// An RGB NPF model.
#[derive(Debug, Clone, PartialEq)]
pub struct NpfModel {
    /// R, G, B.
    pub channels: [Channel; 3],
    /// Free-form description of how it was made (stored in the file).
    pub metadata: serde_json::Value,
}

impl Brdf for NpfModel {
    fn eval(&self, wi: Vec3, wo: Vec3) -> [f64; 3] {
        if wi[2] <= 0.0 || wo[2] <= 0.0 {
            return [0.0; 3];
        }
        // Only θh and θd are needed: both come straight from the half vector.
        let h = [wi[0] + wo[0], wi[1] + wo[1], wi[2] + wo[2]];
        let len = (h[0] * h[0] + h[1] * h[1] + h[2] * h[2]).sqrt();
        let cos_h = (h[2] / len).clamp(-1.0, 1.0);
        let cos_d = ((wi[0] * h[0] + wi[1] * h[1] + wi[2] * h[2]) / len).clamp(-1.0, 1.0);
        let (th, td) = (theta_h_bin(cos_h.acos()), theta_d_bin(cos_d.acos()));
        let (gi, go) = (g_interp(wi[2].min(1.0).acos()), g_interp(wo[2].min(1.0).acos()));
        [0, 1, 2].map(|c| self.channels[c].eval_at(th, td, gi, go, wi[2] * wo[2]))
    }
}

/// Why a model file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    /// I/O failed.
    #[error("cannot read {path}: {source}")]
    Io {
        /// File.
        path: String,
        /// Cause.
        source: std::io::Error,
    },
    /// Not JSON of the documented shape.
    #[error("{path} is not an NPF model file: {source}")]
    Json {
        /// File.
        path: String,
        /// Cause.
        source: serde_json::Error,
    },
    /// Shape or values wrong.
    #[error("{path}: {why}")]
    Invalid {
        /// File.
        path: String,
        /// What is wrong.
        why: String,
    },
}

/// The JSON file (docs/npf-format.md).
#[derive(Debug, Serialize, Deserialize)]
struct ModelFile {
    format: String,
    version: u32,
    rho_d: Vec<f64>,
    rho_s: Vec<f64>,
    d: Vec<f64>,
    f: Vec<f64>,
    g: Vec<f64>,
    #[serde(default)]
    metadata: serde_json::Value,
}

/// `format` field of a model file.
pub const FORMAT: &str = "npf-brdf";

impl NpfModel {
    /// Write the model file (atomically); a model out of range
    /// ([`NpfModel::check`]) is refused (`InvalidData`), as its reader would.
    pub fn save(&self, path: &Path) -> std::io::Result<()> {
        self.check().map_err(|why| std::io::Error::new(std::io::ErrorKind::InvalidData, why))?;
        crate::fsutil::write_atomic(path, &self.to_json())
    }

    /// The bytes of the model file (docs/npf-format.md §2).
    pub fn to_json(&self) -> Vec<u8> {
        serde_json::to_vec_pretty(&self.file()).expect("a model file serialises")
    }

    fn file(&self) -> ModelFile {
        let flat = |pick: fn(&Channel) -> &[f64; BINS]| {
            self.channels.iter().flat_map(|c| pick(c).iter().copied()).collect::<Vec<_>>()
        };
        ModelFile {
            format: FORMAT.into(),
            version: 1,
            rho_d: self.channels.iter().map(|c| c.rho_d).collect(),
            rho_s: self.channels.iter().map(|c| c.rho_s).collect(),
            d: flat(|c| &c.d),
            f: flat(|c| &c.f),
            g: flat(|c| &c.g),
            metadata: self.metadata.clone(),
        }
    }

    /// Every number within its range (docs/npf-format.md §2): ρd and ρs
    /// within [0, [`MAX_VALUE`]], every table within [0, 1]. Else which
    /// field holds what.
    pub fn check(&self) -> Result<(), String> {
        self.file().check()
    }

    /// Read a model file.
    pub fn load(path: &Path) -> Result<NpfModel, ModelError> {
        let name = path.display().to_string();
        let bytes = scanner_formats::input::read(path)
            .map_err(|source| ModelError::Io { path: name.clone(), source })?;
        NpfModel::from_json(&bytes, &name)
    }

    /// A model from the bytes of a model file (docs/npf-format.md §2);
    /// `name` names it in errors. Its numbers must pass [`NpfModel::check`],
    /// as the fit's do.
    pub fn from_json(bytes: &[u8], name: &str) -> Result<NpfModel, ModelError> {
        let file: ModelFile = serde_json::from_slice(bytes)
            .map_err(|source| ModelError::Json { path: name.to_owned(), source })?;
        file.check().map_err(|why| ModelError::Invalid { path: name.to_owned(), why })?;
        let table = |v: &[f64], c: usize| -> [f64; BINS] {
            v[c * BINS..(c + 1) * BINS].try_into().unwrap()
        };
        let channels = [0, 1, 2].map(|c| Channel {
            rho_d: file.rho_d[c],
            rho_s: file.rho_s[c],
            d: table(&file.d, c),
            f: table(&file.f, c),
            g: table(&file.g, c),
        });
        Ok(NpfModel { channels, metadata: file.metadata })
    }
}

impl ModelFile {
    /// Format, version, the arrays' lengths and every number's range.
    fn check(&self) -> Result<(), String> {
        if self.format != FORMAT || self.version != 1 {
            return Err(format!(
                "format {:?} version {}, expected {FORMAT:?} 1",
                self.format, self.version
            ));
        }
        for (field, v, n, max) in [
            ("rho_d", &self.rho_d, 3, MAX_VALUE),
            ("rho_s", &self.rho_s, 3, MAX_VALUE),
            ("d", &self.d, 3 * BINS, 1.0),
            ("f", &self.f, 3 * BINS, 1.0),
            ("g", &self.g, 3 * BINS, 1.0),
        ] {
            if v.len() != n {
                return Err(format!("`{field}` has {} numbers, expected {n}", v.len()));
            }
            if let Some(bad) = v.iter().find(|x| !(0.0..=max).contains(*x)) {
                return Err(format!(
                    "`{field}` holds {bad:e}; its values must lie within [0, {max:e}]"
                ));
            }
        }
        Ok(())
    }
}

/// One channel of the naive model: (ρd, ρs, D over θh′, F over θd, H over φd).
pub type NaiveChannel = (f64, f64, [f64; BINS], [f64; BINS], [f64; BINS]);

/// The naive comparison model ρ = ρd + ρs D(θh) F(θd) H(φd), factors
/// tabulated directly in the parameter variables (H over 90 φd bins).
#[derive(Debug, Clone, PartialEq)]
pub struct NaiveModel {
    /// Per channel: (ρd, ρs, D, F, H).
    pub channels: [NaiveChannel; 3],
}

/// H bin of φd ∈ [0, π): 90 bins.
pub fn h_bin(phi_d: f64) -> usize {
    phi_d_bin(phi_d) / 2
}

impl Brdf for NaiveModel {
    fn eval(&self, wi: Vec3, wo: Vec3) -> [f64; 3] {
        if wi[2] <= 0.0 || wo[2] <= 0.0 {
            return [0.0; 3];
        }
        let hd = from_directions(wi, wo);
        let (th, td, ph) = (theta_h_bin(hd.theta_h), theta_d_bin(hd.theta_d), h_bin(hd.phi_d));
        [0, 1, 2].map(|c| {
            let (rd, rs, d, f, h) = &self.channels[c];
            rd + rs * d[th] * f[td] * h[ph]
        })
    }
}
