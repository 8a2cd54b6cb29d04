//! Direct images of a large piece (Fig. 9, docs/direct-images.md): a
//! directory of linear EXR images, each the piece seen and lit from one
//! direction and rectified onto it, and the manifest `direct.toml` that
//! says which direction each was taken from. The simulator writes such
//! sets (`hil-sim direct`); `scanner enlarge` reads them.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

/// The manifest's name in a direct-image directory.
pub const MANIFEST: &str = "direct.toml";
/// The manifest format this crate reads and writes.
pub const FORMAT: u32 = 1;
/// Most images in one set.
pub const MAX_IMAGES: usize = 16;
/// The largest side of a piece, mm.
pub const MAX_SIZE_MM: f64 = 10_000.0;
/// Tolerance on the length of a unit direction.
const UNIT_TOLERANCE: f64 = 1e-3;

/// `direct.toml`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DirectManifest {
    /// Always [`FORMAT`].
    pub format: u32,
    /// The piece's width (along u, image columns) and height (along v,
    /// image rows), mm: what every image covers.
    pub size_mm: [f64; 2],
    /// The images, one per direction.
    pub image: Vec<DirectImage>,
}

/// One direct image.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DirectImage {
    /// Its file in the directory: a linear RGB EXR.
    pub file: String,
    /// The direction (sample-local frame of docs/scanner-geometry.md,
    /// towards the camera, which the light shares) it was taken from.
    pub direction: [f64; 3],
    /// Its exposure, s: values divided by it are on one scale across the set.
    pub exposure_s: f64,
    /// The scanner mirror whose view of the sample it copies, if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mirror: Option<u32>,
}

/// A manifest that cannot be read or is not valid.
#[derive(Debug, thiserror::Error)]
pub enum DirectError {
    /// The manifest could not be read.
    #[error("{path}: {source}")]
    Io {
        /// The manifest's path.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The manifest is not what docs/direct-images.md describes.
    #[error("{path}: {message}")]
    Invalid {
        /// The manifest's path.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}

impl DirectManifest {
    /// Read and check `DIR/direct.toml`.
    pub fn read(dir: &Path) -> Result<DirectManifest, DirectError> {
        let path = dir.join(MANIFEST);
        let text = crate::input::read_to_string(&path)
            .map_err(|source| DirectError::Io { path: path.clone(), source })?;
        let invalid = |message: String| DirectError::Invalid { path: path.clone(), message };
        let m: DirectManifest = toml::from_str(&text).map_err(|e| invalid(e.to_string()))?;
        m.check().map_err(invalid)?;
        Ok(m)
    }

    /// The manifest's text.
    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("a manifest is plain data")
    }

    /// Every rule of docs/direct-images.md.
    pub fn check(&self) -> Result<(), String> {
        if self.format != FORMAT {
            return Err(format!("format {} (this reader reads format {FORMAT})", self.format));
        }
        if !self.size_mm.iter().all(|s| s.is_finite() && *s > 0.0 && *s <= MAX_SIZE_MM) {
            return Err(format!("size_mm {:?} outside (0, {MAX_SIZE_MM}]", self.size_mm));
        }
        if self.image.is_empty() || self.image.len() > MAX_IMAGES {
            return Err(format!("{} images: need 1…{MAX_IMAGES}", self.image.len()));
        }
        for (i, im) in self.image.iter().enumerate() {
            let name = Path::new(&im.file);
            let plain = name.components().count() == 1
                && matches!(name.components().next(), Some(std::path::Component::Normal(_)));
            if !plain {
                return Err(format!(
                    "image {i}: file {:?} is not a name in the directory",
                    im.file
                ));
            }
            if self.image[..i].iter().any(|o| o.file == im.file) {
                return Err(format!("image {i}: file {:?} is listed twice", im.file));
            }
            let d = im.direction;
            let len = d.iter().map(|x| x * x).sum::<f64>().sqrt();
            if !((len - 1.0).abs() <= UNIT_TOLERANCE && d[2] > 0.0) {
                return Err(format!(
                    "image {i} ({}): direction {d:?} is not a unit vector above the piece",
                    im.file
                ));
            }
            if !(im.exposure_s.is_finite() && im.exposure_s > 0.0) {
                return Err(format!(
                    "image {i} ({}): exposure_s {} is not a positive time",
                    im.file, im.exposure_s
                ));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn good() -> DirectManifest {
        DirectManifest {
            format: 1,
            size_mm: [80.0, 60.0],
            image: vec![
                DirectImage {
                    file: "a.exr".into(),
                    direction: [0.0, 0.0, 1.0],
                    exposure_s: 0.05,
                    mirror: Some(3),
                },
                DirectImage {
                    file: "b.exr".into(),
                    direction: [0.6, 0.0, 0.8],
                    exposure_s: 0.02,
                    mirror: None,
                },
            ],
        }
    }

    #[test]
    fn a_manifest_round_trips_and_every_rule_is_checked() {
        let m = good();
        let back: DirectManifest = toml::from_str(&m.to_toml()).unwrap();
        assert_eq!(back, m);
        assert_eq!(m.check(), Ok(()));
        let cases: Vec<(Box<dyn Fn(&mut DirectManifest)>, &str)> = vec![
            (Box::new(|m| m.format = 2), "format 2"),
            (Box::new(|m| m.size_mm[1] = f64::NAN), "size_mm [80.0, NaN]"),
            (Box::new(|m| m.size_mm[0] = 0.0), "outside (0, 10000]"),
            (Box::new(|m| m.image.clear()), "0 images: need 1…16"),
            (Box::new(|m| m.image = vec![m.image[0].clone(); 17]), "17 images"),
            (Box::new(|m| m.image[1].file = "../x.exr".into()), "not a name in the directory"),
            (Box::new(|m| m.image[1].file = "/etc/x.exr".into()), "not a name in the directory"),
            (Box::new(|m| m.image[1].file = "a.exr".into()), "listed twice"),
            (Box::new(|m| m.image[0].direction = [0.0, 0.0, 2.0]), "not a unit vector"),
            (Box::new(|m| m.image[0].direction = [0.6, 0.0, -0.8]), "not a unit vector"),
            (Box::new(|m| m.image[1].exposure_s = 0.0), "exposure_s 0 is not"),
            (Box::new(|m| m.image[1].exposure_s = f64::INFINITY), "exposure_s inf"),
        ];
        for (edit, want) in cases {
            let mut m = good();
            edit(&mut m);
            let e = m.check().unwrap_err();
            assert!(e.contains(want), "{e} (wanted {want})");
        }
        let unknown = format!("{}\ncolour = 1\n", good().to_toml());
        assert!(toml::from_str::<DirectManifest>(&unknown).is_err());
    }
}
