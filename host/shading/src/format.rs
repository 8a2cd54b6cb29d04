//! The material file (docs/material-format.md): one safetensors container
//! whose header metadata holds a JSON document under the key `material`
//! ([`Metadata`]) and whose tensors hold the palettes, the index images and
//! the direction tables. [`MaterialData`] is the file's content, written by
//! the builder with [`MaterialData::to_bytes`] and read, with every shape,
//! index and value checked, by [`MaterialData::from_bytes`].

use std::borrow::Cow;
use std::collections::HashMap;

use safetensors::tensor::{Dtype, SafeTensors, View};
use serde::{Deserialize, Serialize};

use crate::error::MaterialError;
use crate::texel::{STORED, TexelParams};

/// `Metadata::format`.
pub const FORMAT: &str = "material-scanner/material";
/// The format version this crate writes for a material without a texel
/// model; such files are also version-1 files.
pub const VERSION: u32 = 1;
/// The format version of a material with a texel model
/// (`Metadata::texel_model`). This crate reads both.
pub const VERSION_TEXEL_MODEL: u32 = 2;
/// The format version of a material with a detail layer
/// (`Metadata::detail`), with or without a texel model.
pub const VERSION_DETAIL: u32 = 3;
/// The format version of a material whose detail layer has light
/// components (`Metadata::detail_components` ≥ 1).
pub const VERSION_LIGHT_DETAIL: u32 = 4;
/// The format version of an enlarged material (`Metadata::enlargement`,
/// Fig. 9): uv spans a large piece, each of whose texels names the texel of
/// the scanned sample that looks most like it. Its other parts (texel
/// model, detail layer, light components) are as their own keys say. This
/// crate reads versions 1 to 5.
pub const VERSION_ENLARGED: u32 = 5;
/// An enlargement map's unit: the scanned sample's side over it. A map
/// value m is the sample's u (or v) (m + ½) / 65 536.
pub const ENLARGEMENT_UNITS: u32 = 65536;
/// Most columns or rows of an enlargement map.
pub const MAX_ENLARGEMENT: u32 = 16384;
/// The detail layer's range: every factor lies in [1 / it, it].
pub const DETAIL_RANGE: f32 = 4.0;
/// Most light components of a detail layer.
pub const MAX_DETAIL_COMPONENTS: u32 = 8;
/// The light components' coefficients lie in [−it, it].
pub const DETAIL_COEFFICIENT_RANGE: f32 = 64.0;
/// The safetensors metadata key holding the JSON [`Metadata`].
pub const METADATA_KEY: &str = "material";
/// The safetensors metadata key holding the file's content digest
/// ([`content_digest`]): 64 lowercase hexadecimal digits. Files written
/// before session 103 have none and are read without the check.
pub const DIGEST_KEY: &str = "content_sha256";
/// Most (mirror, weight) pairs one patent-table cell may hold.
pub const MAX_CELL_PAIRS: usize = 64;
/// The largest palette colour a file holds: float16's largest finite
/// value. A brighter colour (a near-mirror's highlight, 2.6·10⁵ times a
/// white target's radiance) is stored at it.
pub const PALETTE_MAX: f32 = 65504.0;
/// Tolerance on the length of a unit direction.
const UNIT_TOLERANCE: f64 = 1e-4;

/// One mirror of the scan and its calibrated direction.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Mirror {
    /// The mirror's number in the scanner (0-based, docs/scanner-geometry.md).
    pub mirror: u32,
    /// Unit direction from the sample towards it (light: towards where the
    /// beam comes from; view: towards the camera through it), sample-local.
    pub direction: [f64; 3],
}

/// How directions between the captured ones are shaded.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum Interpolation {
    /// Spherical barycentric weights over a triangulation of the directions.
    Default,
    /// The patent's Voronoi cell table (Fig. 11A).
    Patent {
        /// Cells along the azimuth φ ∈ [0, 360°).
        columns: u32,
        /// Cells along the polar angle θ ∈ [0, 90°].
        rows: u32,
        /// Random points thrown per cell (the weights are counts / points).
        points: u32,
    },
}

impl Interpolation {
    /// The patent table's size in range: 1…8192 columns and rows, 1…65 535
    /// points (counts are 16-bit).
    pub fn check(&self) -> Result<(), String> {
        match *self {
            Interpolation::Patent { columns, rows, points }
                if !((1..=8192).contains(&columns)
                    && (1..=8192).contains(&rows)
                    && (1..=u16::MAX as u32).contains(&points)) =>
            {
                Err(format!(
                    "patent table of {columns} × {rows} cells with {points} points: columns and \
                     rows must be in 1…8192, points in 1…65535"
                ))
            }
            _ => Ok(()),
        }
    }
}

/// Where a material came from: hashes of everything it was built from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Provenance {
    /// SHA-256 of the sample scan's `manifest.json`.
    pub scan_manifest_sha256: String,
    /// The scanner geometry's hash (docs/scanner-geometry.md).
    pub geometry_sha256: String,
    /// SHA-256 of the calibration file.
    pub calibration_sha256: String,
    /// The program that built it, e.g. `scanner 0.1.0`.
    pub builder: String,
    /// Where the region images took the sample's face to lie (since
    /// session 80; absent before, and for materials not built from a
    /// scan). The material's directions are in this face's frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub face: Option<FaceRecord>,
}

/// [`Provenance::face`]: the sample's face the material was read on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FaceRecord {
    /// Its centre's height above the holder's plane, mm.
    pub height_mm: f64,
    /// Its rise along u and along v, mm per mm.
    pub slope: [f64; 2],
    /// What it was measured on (`"chroma"`, `"outline"`, `"chroma and
    /// outline"`, `"none"`, `"disagreeing"`), or `"given"`.
    pub measured_on: String,
    /// Read as a thick sample's whose sides show beyond the edges facing
    /// each view (since session 81; absent: false).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub sides_shown: bool,
}

/// The signatures an enlargement's texels may have been matched by.
pub const SIGNATURES: [&str; 2] = ["colour", "height"];

/// Fig. 9's enlargement: the map from a large piece's texels to the scanned
/// sample's (tensor `enlargement`, docs/material-format.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Enlargement {
    /// Texels of the map along u.
    pub columns: u32,
    /// Texels of the map along v.
    pub rows: u32,
    /// How each texel was matched ([`SIGNATURES`]): `"colour"`, the
    /// patent's colour signature (the 3 × 3 neighbourhood's RGB in every
    /// direct image), or `"height"`, its height signature (the 3 × 3
    /// neighbourhood's heights from photometric stereo).
    pub signature: String,
    /// The directions (sample-local, unit, towards the camera and the
    /// light) of the direct images the signatures were taken from.
    pub directions: Vec<[f64; 3]>,
    /// SHA-256 of the direct images' manifest (docs/direct-images.md).
    #[serde(default)]
    pub direct_sha256: String,
}

/// The JSON document stored under [`METADATA_KEY`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Metadata {
    /// Always [`FORMAT`].
    pub format: String,
    /// [`VERSION`], [`VERSION_TEXEL_MODEL`], [`VERSION_DETAIL`],
    /// [`VERSION_LIGHT_DETAIL`] or [`VERSION_ENLARGED`].
    pub version: u32,
    /// The sample's name.
    pub name: String,
    /// Side of the scanned sample, mm.
    pub sample_size_mm: f64,
    /// Size (width along u, height along v) of what uv ∈ [0, 1]² spans, mm.
    pub extent_mm: [f64; 2],
    /// Side S of every index image, px.
    pub resolution: u32,
    /// Colours per palette, K ≤ 256.
    pub colours: u32,
    /// Most lights sharing one index image, g (their palettes differ).
    pub lights_per_index: u32,
    /// How directions between the captured ones are shaded.
    pub interpolation: Interpolation,
    /// Default interpolation: how far (0…1) each light's view moves from
    /// wo towards the view that keeps the query's half vector (chosen by
    /// the builder by leave-one-light-out prediction; ignored by the
    /// patent's).
    pub half_vector_shift: f64,
    /// The lit mirrors in tensor order.
    pub lights: Vec<Mirror>,
    /// The seen mirrors in tensor order.
    pub views: Vec<Mirror>,
    /// Where the material came from.
    pub provenance: Provenance,
    /// Default interpolation only (version 2): the file holds a fitted
    /// texel model (tensor `texel_model`), and the shading interpolates the
    /// captured images' residuals from it rather than the images
    /// themselves. Absent in version 1.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub texel_model: bool,
    /// Version 3: the file holds a detail layer (tensor `detail`), a
    /// 2S × 2S factor that multiplies every answer. Absent before.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub detail: bool,
    /// Version 4: the detail layer's light components R (tensors
    /// `detail_bases` and `detail_coefficients`). Absent (0) before.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub detail_components: u32,
    /// Version 5: uv spans a large piece (`extent_mm`) through an
    /// enlargement map (tensor `enlargement`). Absent before.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub enlargement: Option<Enlargement>,
}

fn is_zero(x: &u32) -> bool {
    *x == 0
}

/// A patent direction table in compressed rows: the pairs of cell `c` are
/// `mirrors[offsets[c]..offsets[c + 1]]` with `counts` alongside; cell
/// `c = row · columns + column`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct CellTable {
    /// `rows · columns + 1` ascending offsets, starting at 0.
    pub offsets: Vec<u32>,
    /// Direction indices (into `lights` or `views`).
    pub mirrors: Vec<u16>,
    /// How many of the cell's random points fell nearest to that mirror.
    pub counts: Vec<u16>,
}

/// The direction tables of either interpolation.
#[derive(Debug, Clone, PartialEq)]
pub enum DirectionTables {
    /// Triangles over the view and over the light directions, by index.
    Triangles {
        /// Triangles of view directions.
        views: Vec<[u16; 3]>,
        /// Triangles of light directions.
        lights: Vec<[u16; 3]>,
    },
    /// The patent's cell tables.
    Patent {
        /// Over the view directions.
        views: CellTable,
        /// Over the light directions.
        lights: CellTable,
    },
}

/// The content of a material file.
#[derive(Debug, Clone, PartialEq)]
pub struct MaterialData {
    /// The JSON metadata.
    pub meta: Metadata,
    /// `[L][V][K]` RGB: f · cos θi at the captured light direction, linear,
    /// stored as float16; with a texel model, at the pair's central
    /// directions (docs/material-format.md, "Texel model").
    pub palettes: Vec<[f32; 3]>,
    /// `[V][S][S][G]` palette indices: view, row t (along v), column s
    /// (along u), light group.
    pub indices: Vec<u8>,
    /// `[L]`: the light group (index-image slot) of each light.
    pub light_groups: Vec<u8>,
    /// The direction tables.
    pub tables: DirectionTables,
    /// `[S][S]` (row t along v, column s along u): the fitted texel model,
    /// when `meta.texel_model`; empty otherwise.
    pub texels: Vec<TexelParams>,
    /// `[2S][2S]` RGB (row along v, column along u): the detail layer's
    /// shared factors, when `meta.detail`; empty otherwise.
    pub detail: Vec<[f32; 3]>,
    /// `[R][2S][2S]` RGB, each in [−1, 1]: the detail layer's light
    /// components (log factors), R = `meta.detail_components`.
    pub detail_bases: Vec<[f32; 3]>,
    /// `[L][R]`: each light's coefficients on the light components.
    pub detail_coefficients: Vec<f32>,
    /// `[rows][columns]` (row along v, column along u) of the enlargement
    /// map, when `meta.enlargement`: where on the scanned sample the large
    /// piece's texel centre looks alike, (u, v) each as (m + ½) / 65 536
    /// ([`ENLARGEMENT_UNITS`]); empty otherwise.
    pub enlargement: Vec<[u16; 2]>,
}

/// A tensor to serialise.
struct Tensor {
    dtype: Dtype,
    shape: Vec<usize>,
    data: Vec<u8>,
}

impl View for &Tensor {
    fn dtype(&self) -> Dtype {
        self.dtype
    }
    fn shape(&self) -> &[usize] {
        &self.shape
    }
    fn data(&self) -> Cow<'_, [u8]> {
        Cow::Borrowed(&self.data)
    }
    fn data_len(&self) -> usize {
        self.data.len()
    }
}

fn u16_bytes(v: impl IntoIterator<Item = u16>) -> Vec<u8> {
    v.into_iter().flat_map(u16::to_le_bytes).collect()
}

fn cell_tensors(prefix: &str, t: &CellTable, out: &mut Vec<(String, Tensor)>) {
    out.push((
        format!("{prefix}_cell_offsets"),
        Tensor {
            dtype: Dtype::U32,
            shape: vec![t.offsets.len()],
            data: t.offsets.iter().flat_map(|o| o.to_le_bytes()).collect(),
        },
    ));
    out.push((
        format!("{prefix}_cell_mirrors"),
        Tensor {
            dtype: Dtype::U16,
            shape: vec![t.mirrors.len()],
            data: u16_bytes(t.mirrors.iter().copied()),
        },
    ));
    out.push((
        format!("{prefix}_cell_counts"),
        Tensor {
            dtype: Dtype::U16,
            shape: vec![t.counts.len()],
            data: u16_bytes(t.counts.iter().copied()),
        },
    ));
}

/// The content digest of a material file's bytes (docs/material-format.md,
/// "The content digest"): SHA-256, in lowercase hexadecimal, of the
/// `material` metadata's UTF-8 text, a 0 byte, one line
/// `name:dtype:shape:begin-end\n` per tensor in the order of their names
/// (shape's sizes joined by `,`; begin and end the data offsets), a 0 byte,
/// and the data section (every byte after the header). It covers every
/// byte a reader uses; the header's own layout (key order, padding) does
/// not change it.
pub fn content_digest(bytes: &[u8]) -> Result<String, MaterialError> {
    let (n, header) = SafeTensors::read_metadata(bytes).map_err(not_safetensors)?;
    digest_of(bytes, n, &header)
}

/// [`content_digest`] of `bytes` whose header (`n` bytes) is parsed.
fn digest_of(
    bytes: &[u8],
    n: usize,
    header: &safetensors::tensor::Metadata,
) -> Result<String, MaterialError> {
    use sha2::{Digest, Sha256};
    let json = header.metadata().as_ref().and_then(|m| m.get(METADATA_KEY)).ok_or_else(|| {
        MaterialError::Metadata(format!("no `{METADATA_KEY}` entry: not a material file"))
    })?;
    let mut h = Sha256::new();
    h.update(json.as_bytes());
    h.update([0u8]);
    let mut tensors: Vec<_> = header.tensors().into_iter().collect();
    tensors.sort_by(|a, b| a.0.cmp(&b.0));
    for (name, info) in tensors {
        let shape: Vec<String> = info.shape.iter().map(usize::to_string).collect();
        let (begin, end) = info.data_offsets;
        h.update(format!("{name}:{}:{}:{begin}-{end}\n", info.dtype, shape.join(",")).as_bytes());
    }
    h.update([0u8]);
    // `read_metadata` checked that the header lies within the bytes.
    h.update(&bytes[(8 + n).min(bytes.len())..]);
    Ok(h.finalize().iter().map(|b| format!("{b:02x}")).collect())
}

/// A container the safetensors reader or writer refuses.
fn not_safetensors(e: safetensors::SafeTensorError) -> MaterialError {
    MaterialError::Container(format!("not a safetensors file ({e})"))
}

/// `bytes`, a safetensors file, with its header's keys in sorted order
/// (and the header padded with spaces to 8 bytes, as safetensors pads it):
/// the metadata's keys are a hash map's, whose order changes from one
/// process to the next, and the same material is written as the same
/// bytes.
fn canonical_header(bytes: Vec<u8>) -> Result<Vec<u8>, MaterialError> {
    let (n, _) = SafeTensors::read_metadata(&bytes).map_err(not_safetensors)?;
    // serde_json's maps are sorted by key (its `preserve_order` is off).
    let header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n])
        .map_err(|e| MaterialError::Container(e.to_string()))?;
    let mut text =
        serde_json::to_vec(&header).map_err(|e| MaterialError::Container(e.to_string()))?;
    text.resize(text.len().next_multiple_of(8), b' ');
    let mut out = Vec::with_capacity(8 + text.len() + bytes.len() - 8 - n);
    out.extend_from_slice(&(text.len() as u64).to_le_bytes());
    out.extend_from_slice(&text);
    out.extend_from_slice(&bytes[8 + n..]);
    Ok(out)
}

/// A material file's bytes written again without their content digest (a
/// file as written before session 103): what a fuzzer's seeds are, so that
/// a mutation reaches the checks behind the digest's.
pub fn without_digest(bytes: &[u8]) -> Result<Vec<u8>, MaterialError> {
    let st = SafeTensors::deserialize(bytes).map_err(not_safetensors)?;
    let (_, header) = SafeTensors::read_metadata(bytes).map_err(not_safetensors)?;
    let mut info = header.metadata().clone().unwrap_or_default();
    info.remove(DIGEST_KEY);
    safetensors::serialize(st.tensors(), Some(info)).map_err(not_safetensors)
}

impl MaterialData {
    /// The number of light groups G: one more than the largest in
    /// `light_groups` (⌈L / g⌉ when every group but the last holds g
    /// lights).
    pub fn groups(&self) -> usize {
        self.light_groups.iter().map(|&x| x as usize + 1).max().unwrap_or(0)
    }

    /// How many palette values lie above [`PALETTE_MAX`] (stored at it).
    pub fn palettes_beyond_float16(&self) -> usize {
        self.palettes.iter().flatten().filter(|&&x| x > PALETTE_MAX).count()
    }

    /// The file's bytes: palette values above [`PALETTE_MAX`] at it. Fails
    /// only if the content is inconsistent (it is checked exactly as the
    /// reader checks it).
    pub fn to_bytes(&self) -> Result<Vec<u8>, MaterialError> {
        let (l, v) = (self.meta.lights.len(), self.meta.views.len());
        let (s, k, g) = (self.meta.resolution as usize, self.meta.colours as usize, self.groups());
        if self.indices.len() != v * s * s * g {
            return Err(MaterialError::Tensor(format!(
                "indices: {} bytes, not {v} × {s} × {s} × {g} (light groups 0…{})",
                self.indices.len(),
                g.saturating_sub(1)
            )));
        }
        let mut tensors = vec![
            (
                "palettes".to_string(),
                Tensor {
                    dtype: Dtype::F16,
                    shape: vec![l, v, k, 3],
                    data: u16_bytes(
                        self.palettes
                            .iter()
                            .flatten()
                            .map(|&x| half::f16::from_f32(x.min(PALETTE_MAX)).to_bits()),
                    ),
                },
            ),
            (
                "indices".to_string(),
                Tensor { dtype: Dtype::U8, shape: vec![v, s, s, g], data: self.indices.clone() },
            ),
            (
                "light_groups".to_string(),
                Tensor { dtype: Dtype::U8, shape: vec![l], data: self.light_groups.clone() },
            ),
        ];
        if self.meta.texel_model {
            if self.texels.len() != s * s {
                return Err(MaterialError::Tensor(format!(
                    "texel_model: {} texels for {s} × {s}",
                    self.texels.len()
                )));
            }
            tensors.push((
                "texel_model".to_string(),
                Tensor {
                    dtype: Dtype::F16,
                    shape: vec![s, s, STORED],
                    data: u16_bytes(
                        self.texels
                            .iter()
                            .flat_map(|p| p.to_stored())
                            .map(|x| half::f16::from_f32(x).to_bits()),
                    ),
                },
            ));
        }
        if self.meta.detail {
            if self.detail.len() != 4 * s * s {
                return Err(MaterialError::Tensor(format!(
                    "detail: {} factors for {f} × {f}",
                    self.detail.len(),
                    f = 2 * s
                )));
            }
            tensors.push((
                "detail".to_string(),
                Tensor {
                    dtype: Dtype::F16,
                    shape: vec![2 * s, 2 * s, 3],
                    data: u16_bytes(
                        self.detail.iter().flatten().map(|&x| half::f16::from_f32(x).to_bits()),
                    ),
                },
            ));
        }
        let r = self.meta.detail_components as usize;
        if r > 0 {
            let f = 2 * s;
            if self.detail_bases.len() != r * f * f || self.detail_coefficients.len() != l * r {
                return Err(MaterialError::Tensor(format!(
                    "detail components: {} basis values and {} coefficients for {r} × {f} × {f} \
                     and {l} × {r}",
                    self.detail_bases.len(),
                    self.detail_coefficients.len()
                )));
            }
            tensors.push((
                "detail_bases".to_string(),
                Tensor {
                    dtype: Dtype::F16,
                    shape: vec![r, f, f, 3],
                    data: u16_bytes(
                        self.detail_bases
                            .iter()
                            .flatten()
                            .map(|&x| half::f16::from_f32(x).to_bits()),
                    ),
                },
            ));
            tensors.push((
                "detail_coefficients".to_string(),
                Tensor {
                    dtype: Dtype::F32,
                    shape: vec![l, r],
                    data: self.detail_coefficients.iter().flat_map(|x| x.to_le_bytes()).collect(),
                },
            ));
        }
        if let Some(e) = &self.meta.enlargement {
            let (c, r) = (e.columns as usize, e.rows as usize);
            if self.enlargement.len() != c * r {
                return Err(MaterialError::Tensor(format!(
                    "enlargement: {} texels for {c} × {r}",
                    self.enlargement.len()
                )));
            }
            tensors.push((
                "enlargement".to_string(),
                Tensor {
                    dtype: Dtype::U16,
                    shape: vec![r, c, 2],
                    data: u16_bytes(self.enlargement.iter().flatten().copied()),
                },
            ));
        }
        match &self.tables {
            DirectionTables::Triangles { views, lights } => {
                for (name, t) in [("view_triangles", views), ("light_triangles", lights)] {
                    tensors.push((
                        name.to_string(),
                        Tensor {
                            dtype: Dtype::U16,
                            shape: vec![t.len(), 3],
                            data: u16_bytes(t.iter().flatten().copied()),
                        },
                    ));
                }
            }
            DirectionTables::Patent { views, lights } => {
                cell_tensors("view", views, &mut tensors);
                cell_tensors("light", lights, &mut tensors);
            }
        }
        let json = serde_json::to_string(&self.meta)
            .map_err(|e| MaterialError::Metadata(e.to_string()))?;
        let mut info = HashMap::from([(METADATA_KEY.to_string(), json)]);
        let serialize = |info: &HashMap<String, String>| {
            safetensors::serialize(tensors.iter().map(|(n, t)| (n.as_str(), t)), Some(info.clone()))
                .map_err(|e| MaterialError::Container(e.to_string()))
        };
        // The tensors' layout does not depend on the metadata: the digest
        // of a first serialisation is that of the second's.
        let digest = content_digest(&serialize(&info)?)?;
        info.insert(DIGEST_KEY.to_string(), digest);
        let bytes = canonical_header(serialize(&info)?)?;
        // What cannot be read back is not written.
        MaterialData::from_bytes(&bytes)?;
        Ok(bytes)
    }

    /// Parse and check a material file's bytes.
    pub fn from_bytes(bytes: &[u8]) -> Result<MaterialData, MaterialError> {
        let st = SafeTensors::deserialize(bytes).map_err(not_safetensors)?;
        let (n, header) = SafeTensors::read_metadata(bytes).map_err(not_safetensors)?;
        // Like an unexpected tensor, an unexpected metadata key is refused:
        // a flip in the digest's key would otherwise skip the check.
        if let Some(key) = header
            .metadata()
            .iter()
            .flatten()
            .map(|(k, _)| k)
            .find(|k| k.as_str() != METADATA_KEY && k.as_str() != DIGEST_KEY)
        {
            return Err(MaterialError::Metadata(format!(
                "unexpected key `{key}` beside `{METADATA_KEY}` and `{DIGEST_KEY}`"
            )));
        }
        if let Some(want) = header.metadata().as_ref().and_then(|m| m.get(DIGEST_KEY)) {
            let have = digest_of(bytes, n, &header)?;
            if *want != have {
                return Err(MaterialError::Container(format!(
                    "the content's SHA-256 is {have}, not the {want} the file was written with: \
                     the file was altered or damaged after it was written"
                )));
            }
        }
        let json =
            header.metadata().as_ref().and_then(|m| m.get(METADATA_KEY)).ok_or_else(|| {
                MaterialError::Metadata(format!("no `{METADATA_KEY}` entry: not a material file"))
            })?;
        let meta: Metadata =
            serde_json::from_str(json).map_err(|e| MaterialError::Metadata(e.to_string()))?;
        check_metadata(&meta)?;
        let (l, v) = (meta.lights.len(), meta.views.len());
        let (s, k) = (meta.resolution as usize, meta.colours as usize);
        // G, the light groups: the index images' last axis, between
        // ⌈L / g⌉ (every group full) and L (one light each).
        let g = match st.tensor("indices") {
            Ok(t) if t.shape().len() == 4 => t.shape()[3],
            _ => l.div_ceil(meta.lights_per_index as usize),
        };
        if !(l.div_ceil(meta.lights_per_index as usize)..=l.min(256)).contains(&g) {
            return Err(MaterialError::Tensor(format!(
                "indices: {g} light groups for {l} lights of up to {} per group",
                meta.lights_per_index
            )));
        }

        let mut expected: Vec<String> =
            ["palettes", "indices", "light_groups"].map(String::from).to_vec();
        let palettes: Vec<[f32; 3]> = {
            let raw = tensor(&st, "palettes", Dtype::F16, &[l, v, k, 3])?;
            let vals: Vec<f32> = raw
                .chunks_exact(2)
                .map(|c| half::f16::from_bits(u16::from_le_bytes([c[0], c[1]])).to_f32())
                .collect();
            if let Some(bad) = vals.iter().find(|x| !(x.is_finite() && **x >= 0.0)) {
                return Err(MaterialError::Value(format!(
                    "palettes: {bad} is not a finite radiance ≥ 0"
                )));
            }
            vals.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
        };
        let indices = tensor(&st, "indices", Dtype::U8, &[v, s, s, g])?.to_vec();
        if let Some(bad) = indices.iter().find(|&&i| i as usize >= k) {
            return Err(MaterialError::Value(format!(
                "indices: {bad} is outside the {k}-colour palettes"
            )));
        }
        let light_groups = tensor(&st, "light_groups", Dtype::U8, &[l])?.to_vec();
        let mut per_group = vec![0usize; g];
        for &grp in &light_groups {
            let slot = per_group.get_mut(grp as usize).ok_or_else(|| {
                MaterialError::Value(format!("light_groups: group {grp} of {g} does not exist"))
            })?;
            *slot += 1;
        }
        if per_group.iter().any(|&n| n > meta.lights_per_index as usize) {
            return Err(MaterialError::Value(format!(
                "light_groups: a group holds more than {} lights",
                meta.lights_per_index
            )));
        }
        if let Some(empty) = per_group.iter().position(|&n| n == 0) {
            return Err(MaterialError::Value(format!(
                "light_groups: group {empty} of {g} holds no light"
            )));
        }
        let tables = match meta.interpolation {
            Interpolation::Default => {
                expected.extend(["view_triangles", "light_triangles"].map(String::from));
                let tri = |name: &str, n: usize| -> Result<Vec<[u16; 3]>, MaterialError> {
                    let info = st.tensor(name).map_err(|_| missing(name))?;
                    let t = info.shape().first().copied().unwrap_or(0);
                    let raw = tensor(&st, name, Dtype::U16, &[t, 3])?;
                    let tris: Vec<[u16; 3]> = raw
                        .chunks_exact(6)
                        .map(|c| {
                            std::array::from_fn(|i| u16::from_le_bytes([c[2 * i], c[2 * i + 1]]))
                        })
                        .collect();
                    if n >= 3 && tris.is_empty() {
                        return Err(MaterialError::Value(format!("{name}: no triangles")));
                    }
                    for t in &tris {
                        if t.iter().any(|&i| i as usize >= n) {
                            return Err(MaterialError::Value(format!(
                                "{name}: {t:?} names a direction outside 0…{}",
                                n.saturating_sub(1)
                            )));
                        }
                    }
                    Ok(tris)
                };
                DirectionTables::Triangles {
                    views: tri("view_triangles", v)?,
                    lights: tri("light_triangles", l)?,
                }
            }
            Interpolation::Patent { columns, rows, points } => {
                let cells = (columns as usize) * (rows as usize);
                let table = |prefix: &str, n: usize| -> Result<CellTable, MaterialError> {
                    let on = format!("{prefix}_cell_offsets");
                    let offsets: Vec<u32> = tensor(&st, &on, Dtype::U32, &[cells + 1])?
                        .chunks_exact(4)
                        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                        .collect();
                    let p = *offsets.last().unwrap_or(&0) as usize;
                    if offsets[0] != 0
                        || offsets
                            .windows(2)
                            .any(|w| w[1] <= w[0] || (w[1] - w[0]) as usize > MAX_CELL_PAIRS)
                    {
                        return Err(MaterialError::Value(format!(
                            "{on}: not ascending from 0 with 1…{MAX_CELL_PAIRS} pairs per cell"
                        )));
                    }
                    let read16 = |name: &str| -> Result<Vec<u16>, MaterialError> {
                        Ok(tensor(&st, name, Dtype::U16, &[p])?
                            .chunks_exact(2)
                            .map(|c| u16::from_le_bytes([c[0], c[1]]))
                            .collect())
                    };
                    let mn = format!("{prefix}_cell_mirrors");
                    let cn = format!("{prefix}_cell_counts");
                    let mirrors = read16(&mn)?;
                    let counts = read16(&cn)?;
                    if let Some(bad) = mirrors.iter().find(|&&m| m as usize >= n) {
                        return Err(MaterialError::Value(format!(
                            "{mn}: direction {bad} outside 0…{}",
                            n.saturating_sub(1)
                        )));
                    }
                    for w in offsets.windows(2) {
                        let sum: u64 =
                            counts[w[0] as usize..w[1] as usize].iter().map(|&c| c as u64).sum();
                        if sum == 0 || sum > points as u64 {
                            return Err(MaterialError::Value(format!(
                                "{cn}: a cell's counts sum to {sum}, not 1…{points}"
                            )));
                        }
                    }
                    Ok(CellTable { offsets, mirrors, counts })
                };
                for p in ["view", "light"] {
                    for t in ["offsets", "mirrors", "counts"] {
                        expected.push(format!("{p}_cell_{t}"));
                    }
                }
                DirectionTables::Patent { views: table("view", v)?, lights: table("light", l)? }
            }
        };
        let texels = if meta.texel_model {
            expected.push("texel_model".into());
            let raw = tensor(&st, "texel_model", Dtype::F16, &[s, s, STORED])?;
            let vals: Vec<f32> = raw
                .chunks_exact(2)
                .map(|c| half::f16::from_bits(u16::from_le_bytes([c[0], c[1]])).to_f32())
                .collect();
            vals.chunks_exact(STORED)
                .enumerate()
                .map(|(i, v)| {
                    TexelParams::check_stored(v).map_err(|e| {
                        MaterialError::Value(format!(
                            "texel_model: texel ({}, {}): {e}",
                            i % s,
                            i / s
                        ))
                    })?;
                    Ok(TexelParams::from_stored(v))
                })
                .collect::<Result<Vec<_>, MaterialError>>()?
        } else {
            Vec::new()
        };
        let detail = if meta.detail {
            expected.push("detail".into());
            let raw = tensor(&st, "detail", Dtype::F16, &[2 * s, 2 * s, 3])?;
            let vals: Vec<f32> = raw
                .chunks_exact(2)
                .map(|c| half::f16::from_bits(u16::from_le_bytes([c[0], c[1]])).to_f32())
                .collect();
            if let Some(i) =
                vals.iter().position(|x| !(1.0 / DETAIL_RANGE..=DETAIL_RANGE).contains(x))
            {
                let t = i / 3;
                return Err(MaterialError::Value(format!(
                    "detail: factor {} at ({}, {}) outside 1/{DETAIL_RANGE}…{DETAIL_RANGE}",
                    vals[i],
                    t % (2 * s),
                    t / (2 * s)
                )));
            }
            vals.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
        } else {
            Vec::new()
        };
        let r = meta.detail_components as usize;
        let (detail_bases, detail_coefficients) = if r > 0 {
            expected.extend(["detail_bases", "detail_coefficients"].map(String::from));
            let f = 2 * s;
            let raw = tensor(&st, "detail_bases", Dtype::F16, &[r, f, f, 3])?;
            let vals: Vec<f32> = raw
                .chunks_exact(2)
                .map(|c| half::f16::from_bits(u16::from_le_bytes([c[0], c[1]])).to_f32())
                .collect();
            if let Some(i) = vals.iter().position(|x| !(-1.0..=1.0).contains(x)) {
                let t = i / 3;
                return Err(MaterialError::Value(format!(
                    "detail_bases: {} at component {}, ({}, {}) outside −1…1",
                    vals[i],
                    t / (f * f),
                    t % f,
                    t / f % f
                )));
            }
            let bases = vals.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
            let coefficients: Vec<f32> = tensor(&st, "detail_coefficients", Dtype::F32, &[l, r])?
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect();
            let range = DETAIL_COEFFICIENT_RANGE;
            if let Some(i) = coefficients.iter().position(|x| !(-range..=range).contains(x)) {
                return Err(MaterialError::Value(format!(
                    "detail_coefficients: {} of light {} outside −{range}…{range}",
                    coefficients[i],
                    i / r
                )));
            }
            (bases, coefficients)
        } else {
            (Vec::new(), Vec::new())
        };
        let enlargement = if let Some(e) = &meta.enlargement {
            expected.push("enlargement".into());
            let (c, r) = (e.columns as usize, e.rows as usize);
            let map: Vec<[u16; 2]> = tensor(&st, "enlargement", Dtype::U16, &[r, c, 2])?
                .chunks_exact(4)
                .map(|b| [u16::from_le_bytes([b[0], b[1]]), u16::from_le_bytes([b[2], b[3]])])
                .collect();
            map
        } else {
            Vec::new()
        };
        if let Some(extra) = st.names().into_iter().find(|n| !expected.iter().any(|e| e == n)) {
            return Err(MaterialError::Tensor(format!(
                "unexpected tensor `{extra}` for {:?} interpolation",
                meta.interpolation
            )));
        }
        Ok(MaterialData {
            meta,
            palettes,
            indices,
            light_groups,
            tables,
            texels,
            detail,
            detail_bases,
            detail_coefficients,
            enlargement,
        })
    }
}

fn missing(name: &str) -> MaterialError {
    MaterialError::Tensor(format!("tensor `{name}` is missing"))
}

/// A tensor's bytes, checked for its dtype and shape.
fn tensor<'a>(
    st: &SafeTensors<'a>,
    name: &str,
    dtype: Dtype,
    shape: &[usize],
) -> Result<&'a [u8], MaterialError> {
    let t = st.tensor(name).map_err(|_| missing(name))?;
    if t.dtype() != dtype || t.shape() != shape {
        return Err(MaterialError::Tensor(format!(
            "tensor `{name}` is {:?} {:?}, expected {dtype:?} {shape:?}",
            t.dtype(),
            t.shape()
        )));
    }
    Ok(t.data())
}

fn check_metadata(m: &Metadata) -> Result<(), MaterialError> {
    let bad = |s: String| Err(MaterialError::Metadata(s));
    if m.format != FORMAT {
        return bad(format!("format is {:?}, not {FORMAT:?}", m.format));
    }
    if !(VERSION..=VERSION_ENLARGED).contains(&m.version) {
        return bad(format!(
            "version {} (this reader reads versions {VERSION}…{VERSION_ENLARGED})",
            m.version
        ));
    }
    if m.enlargement.is_some() != (m.version == VERSION_ENLARGED) {
        return bad(format!(
            "version {} with{} an enlargement: an enlargement is version {VERSION_ENLARGED}'s, \
             and only its",
            m.version,
            if m.enlargement.is_some() { "" } else { "out" }
        ));
    }
    if let Some(f) = &m.provenance.face {
        let sane = f.height_mm.is_finite()
            && f.height_mm.abs() <= 1000.0
            && f.slope.iter().all(|s| s.is_finite() && s.abs() <= 1.0);
        if !sane {
            return bad(format!(
                "provenance.face: height {} mm, slopes {:?} (a face within 1 m of the holder's \
                 plane, tilted at most 45°)",
                f.height_mm, f.slope
            ));
        }
    }
    // Versions 1–4 say by their number what they hold; version 5 by its keys.
    let laddered = m.version < VERSION_ENLARGED;
    if laddered && m.detail != (m.version >= VERSION_DETAIL) {
        return bad(format!(
            "version {} with{} a detail layer: a detail layer is versions {VERSION_DETAIL} and \
             {VERSION_LIGHT_DETAIL}'s, and only theirs",
            m.version,
            if m.detail { "" } else { "out" }
        ));
    }
    if laddered && (m.detail_components > 0) != (m.version == VERSION_LIGHT_DETAIL) {
        return bad(format!(
            "version {} with {} light components: light components are version \
             {VERSION_LIGHT_DETAIL}'s, and only its (at least one)",
            m.version, m.detail_components
        ));
    }
    if m.detail_components > 0 && !m.detail {
        return bad(format!("{} light components without a detail layer", m.detail_components));
    }
    if m.detail_components > MAX_DETAIL_COMPONENTS {
        return bad(format!(
            "detail_components {} outside 0…{MAX_DETAIL_COMPONENTS}",
            m.detail_components
        ));
    }
    if let Some(e) = &m.enlargement {
        let span = 1..=MAX_ENLARGEMENT;
        if !(span.contains(&e.columns) && span.contains(&e.rows)) {
            return bad(format!(
                "enlargement of {} × {} texels: columns and rows must be in 1…{MAX_ENLARGEMENT}",
                e.columns, e.rows
            ));
        }
        if !SIGNATURES.contains(&e.signature.as_str()) {
            return bad(format!(
                "enlargement signature {:?}: this reader knows \"colour\" and \"height\"",
                e.signature
            ));
        }
        if e.directions.is_empty()
            || e.directions.iter().any(|d| {
                let len = d.iter().map(|x| x * x).sum::<f64>().sqrt();
                !((len - 1.0).abs() < UNIT_TOLERANCE && d[2] > 0.0)
            })
        {
            return bad("enlargement directions: need unit vectors above the sample".into());
        }
    }
    if m.version < VERSION_DETAIL && m.texel_model != (m.version == VERSION_TEXEL_MODEL) {
        return bad(format!(
            "version {} with{} a texel model: a texel model is version {VERSION_TEXEL_MODEL}'s, \
             and only its",
            m.version,
            if m.texel_model { "" } else { "out" }
        ));
    }
    if m.texel_model && m.interpolation != Interpolation::Default {
        return bad("a texel model is only for the default interpolation".into());
    }
    if !(m.sample_size_mm.is_finite() && m.sample_size_mm > 0.0) {
        return bad(format!("sample_size_mm {} is not a positive size", m.sample_size_mm));
    }
    if !m.extent_mm.iter().all(|x| x.is_finite() && *x > 0.0) {
        return bad(format!("extent_mm {:?} is not a positive size", m.extent_mm));
    }
    if !(1..=8192).contains(&m.resolution) {
        return bad(format!("resolution {} outside 1…8192", m.resolution));
    }
    if !(1..=256).contains(&m.colours) {
        return bad(format!("colours {} outside 1…256", m.colours));
    }
    for (what, list) in [("lights", &m.lights), ("views", &m.views)] {
        if list.is_empty() || list.len() > 1024 {
            return bad(format!("{} {what}: need 1…1024", list.len()));
        }
        for d in list {
            let len = d.direction.iter().map(|x| x * x).sum::<f64>().sqrt();
            if !((len - 1.0).abs() < UNIT_TOLERANCE && d.direction[2] > 0.0) {
                return bad(format!(
                    "{what}: mirror {}'s direction {:?} is not a unit vector above the sample",
                    d.mirror, d.direction
                ));
            }
        }
    }
    if !(0.0..=1.0).contains(&m.half_vector_shift) {
        return bad(format!("half_vector_shift {} outside 0…1", m.half_vector_shift));
    }
    if !(1..=m.lights.len() as u32).contains(&m.lights_per_index) || m.lights_per_index > 256 {
        return bad(format!(
            "lights_per_index {} outside 1…{}",
            m.lights_per_index,
            m.lights.len()
        ));
    }
    if m.lights.len().div_ceil(m.lights_per_index as usize) > 256 {
        return bad("more than 256 light groups".into());
    }
    m.interpolation.check().map_err(MaterialError::Metadata)
}
