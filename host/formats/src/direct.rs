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
/// The farthest camera distance, mm.
pub const MAX_DISTANCE_MM: f64 = 1e6;
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
    /// A direct image of a diffuse white target of known albedo, taken
    /// with the same light: it puts the images on an absolute scale.
    /// Without it the scale is estimated from the images themselves.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub white: Option<WhiteImage>,
}

/// The white reference of a set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WhiteImage {
    /// Its file in the directory: a linear RGB EXR of the target (its
    /// central half, along each side, is used).
    pub file: String,
    /// The direction it was taken from (as [`DirectImage::direction`]).
    pub direction: [f64; 3],
    /// Its exposure, s.
    pub exposure_s: f64,
    /// The target's albedo (its certificate's), in (0, 1].
    pub albedo: f64,
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
    /// For a photograph taken in perspective and rectified: the camera's
    /// distance from the piece's centre along `direction`, mm. Each point
    /// of the piece was then seen from its own direction, towards the
    /// camera. Absent: a camera infinitely far away.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera_distance_mm: Option<f64>,
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
        Ok(DirectManifest::read_with_bytes(dir)?.0)
    }

    /// [`DirectManifest::read`], with the bytes it was read from (to hash
    /// what was parsed, not a second read).
    pub fn read_with_bytes(dir: &Path) -> Result<(DirectManifest, Vec<u8>), DirectError> {
        let path = dir.join(MANIFEST);
        let bytes = crate::input::read(&path)
            .map_err(|source| DirectError::Io { path: path.clone(), source })?;
        let m = DirectManifest::parse(&bytes)
            .map_err(|message| DirectError::Invalid { path: path.clone(), message })?;
        Ok((m, bytes))
    }

    /// Parse and check a manifest's bytes.
    pub fn parse(bytes: &[u8]) -> Result<DirectManifest, String> {
        let text = std::str::from_utf8(bytes).map_err(|_| "not UTF-8 text".to_string())?;
        let m: DirectManifest = toml::from_str(text).map_err(|e| e.to_string())?;
        m.check()?;
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
        let white = self.white.as_ref().map(|w| (w.file.as_str(), w.direction, w.exposure_s));
        let all = self.image.iter().map(|im| (im.file.as_str(), im.direction, im.exposure_s));
        let mut seen: Vec<&str> = Vec::new();
        for (i, (file, d, exposure_s)) in all.chain(white).enumerate() {
            let what = if i < self.image.len() { format!("image {i}") } else { "white".into() };
            let name = Path::new(file);
            let plain = name.components().count() == 1
                && matches!(name.components().next(), Some(std::path::Component::Normal(_)));
            if !plain {
                return Err(format!("{what}: file {file:?} is not a name in the directory"));
            }
            if seen.contains(&file) {
                return Err(format!("{what}: file {file:?} is listed twice"));
            }
            seen.push(file);
            let len = d.iter().map(|x| x * x).sum::<f64>().sqrt();
            if !((len - 1.0).abs() <= UNIT_TOLERANCE && d[2] > 0.0) {
                return Err(format!(
                    "{what} ({file}): direction {d:?} is not a unit vector above the piece"
                ));
            }
            if !(exposure_s.is_finite() && exposure_s > 0.0) {
                return Err(format!(
                    "{what} ({file}): exposure_s {exposure_s} is not a positive time"
                ));
            }
        }
        for (i, im) in self.image.iter().enumerate() {
            if let Some(d) = im.camera_distance_mm {
                let half = 0.5 * self.size_mm[0].hypot(self.size_mm[1]);
                if !(d.is_finite() && d > half && d <= MAX_DISTANCE_MM) {
                    return Err(format!(
                        "image {i} ({}): camera_distance_mm {d} outside ({half:.1}, \
                         {MAX_DISTANCE_MM}] (beyond the piece's corners)",
                        im.file
                    ));
                }
            }
        }
        if let Some(w) = &self.white
            && !(w.albedo > 0.0 && w.albedo <= 1.0)
        {
            return Err(format!("white ({}): albedo {} outside (0, 1]", w.file, w.albedo));
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
                    camera_distance_mm: Some(400.0),
                },
                DirectImage {
                    file: "b.exr".into(),
                    direction: [0.6, 0.0, 0.8],
                    exposure_s: 0.02,
                    mirror: None,
                    camera_distance_mm: None,
                },
            ],
            white: Some(WhiteImage {
                file: "w.exr".into(),
                direction: [0.0, 0.0, 1.0],
                exposure_s: 0.01,
                albedo: 0.98,
            }),
        }
    }

    #[test]
    fn a_manifest_round_trips_and_every_rule_is_checked() {
        let m = good();
        let back: DirectManifest = toml::from_str(&m.to_toml()).unwrap();
        assert_eq!(back, m);
        assert_eq!(m.check(), Ok(()));
        type Edit = Box<dyn Fn(&mut DirectManifest)>;
        let cases: Vec<(Edit, &str)> = vec![
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
            (Box::new(|m| m.image[0].camera_distance_mm = Some(50.0)), "camera_distance_mm 50"),
            (Box::new(|m| m.image[1].camera_distance_mm = Some(f64::NAN)), "image 1 (b.exr)"),
            (Box::new(|m| m.image[1].camera_distance_mm = Some(2e6)), "(50.0, 1000000]"),
            (Box::new(|m| m.white.as_mut().unwrap().file = "a.exr".into()), "white: file"),
            (Box::new(|m| m.white.as_mut().unwrap().albedo = 1.5), "albedo 1.5 outside (0, 1]"),
            (Box::new(|m| m.white.as_mut().unwrap().albedo = f64::NAN), "albedo NaN"),
            (Box::new(|m| m.white.as_mut().unwrap().exposure_s = -1.0), "white (w.exr): exposure"),
            (
                Box::new(|m| m.white.as_mut().unwrap().direction[2] = 0.0),
                "white (w.exr): direction",
            ),
        ];
        for (edit, want) in cases {
            let mut m = good();
            edit(&mut m);
            let e = m.check().expect_err(want);
            assert!(e.contains(want), "{e} (wanted {want})");
        }
        let unknown = format!("{}\ncolour = 1\n", good().to_toml());
        assert!(toml::from_str::<DirectManifest>(&unknown).is_err());
    }
}
