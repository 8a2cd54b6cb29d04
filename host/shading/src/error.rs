//! Why a material file cannot be used.

/// A material file that cannot be opened or is not a valid material.
#[derive(Debug, thiserror::Error)]
pub enum MaterialError {
    /// The file cannot be read.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// Why.
        source: std::io::Error,
    },
    /// Not a safetensors container, or a damaged one (truncated, offsets
    /// outside the file).
    #[error("{0}")]
    Container(String),
    /// The JSON metadata is missing, malformed or out of range.
    #[error("metadata: {0}")]
    Metadata(String),
    /// A tensor is missing, unexpected, or of the wrong dtype or shape.
    #[error("{0}")]
    Tensor(String),
    /// A value is out of range: an index beyond its palette, a negative or
    /// non-finite radiance, a table naming a direction that does not exist,
    /// a degenerate triangle.
    #[error("{0}")]
    Value(String),
    /// A file whose content is refused for the reason in `source` (what
    /// [`Material::open`](crate::Material::open) returns for a damaged
    /// file, so that every message names it).
    #[error("{path}: {source}")]
    File {
        /// The file.
        path: String,
        /// What is wrong with its content.
        source: Box<MaterialError>,
    },
}
