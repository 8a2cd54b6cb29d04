//! Frame files a camera's capture program drops into the folder camera's
//! folder (docs/scan-format.md, "Frames from a folder"):
//! - OpenEXR and 32-bit float TIFF hold values in the frames' unit (ADC
//!   code / top code);
//! - 16-bit PNG and TIFF (8-bit for a sensor of at most 8 bits) hold
//!   integers: the sensor's ADC codes as the capture program stores them
//!   ([`IntegerCodes`]: as they are, shifted left, or stretched over the
//!   integer's range).
//!
//! Grey images are read as three equal channels; an alpha channel is
//! dropped. An integer image whose values contradict the convention it is
//! read with (values above the top code, or low bits where a shift leaves
//! zeros) is refused with the option that reads it, not scaled wrongly.

use std::io::Cursor;
use std::path::Path;

use image::{DynamicImage, ExtendedColorType, ImageDecoder, ImageFormat, ImageReader};
use scanner_geometry::{IntegerCodes, SensorSpec};

use crate::camera::Frame;

/// Why a frame file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum FrameFileError {
    /// Not (yet) a whole image: perhaps still being written, or damaged.
    #[error("{0}")]
    Decode(String),
    /// An image, but not a frame of this sensor as read (its bit depth,
    /// its colours, its codes): reading it again will not help.
    #[error("{0}")]
    Unusable(String),
}

/// Whether a file named `name` is a frame file by its extension (`.exr`,
/// `.png`, `.tif`, `.tiff`, any case).
pub fn is_frame_file(name: &str) -> bool {
    format_of(name).is_some()
}

fn format_of(name: &str) -> Option<ImageFormat> {
    let ext = Path::new(name).extension()?.to_str()?.to_ascii_lowercase();
    match ext.as_str() {
        "exr" => Some(ImageFormat::OpenExr),
        "png" => Some(ImageFormat::Png),
        "tif" | "tiff" => Some(ImageFormat::Tiff),
        _ => None,
    }
}

/// The frame in the file at `path`, in the frames' unit: integer images are
/// read as `codes` says for `sensor`. An image of another size than `size`
/// (`[width, height]`, the camera's), when given, is refused from its
/// header, before its pixels are decoded.
pub fn read_frame_file(
    path: &Path,
    sensor: &SensorSpec,
    codes: IntegerCodes,
    size: Option<[u32; 2]>,
) -> Result<Frame, FrameFileError> {
    let name = path.display().to_string();
    let file = path.file_name().and_then(|n| n.to_str()).unwrap_or_default();
    if format_of(file).is_none() {
        return Err(FrameFileError::Unusable(format!("{name}: not an .exr, .png or .tiff")));
    }
    let bytes = scanner_formats::input::read(path)
        .map_err(|e| FrameFileError::Decode(format!("{name}: {e}")))?;
    decode_frame_file(&name, &bytes, sensor, codes, size)
}

/// [`read_frame_file`] on the bytes of a file named `name` (its format
/// from the name's extension; `name` also heads the messages).
pub fn decode_frame_file(
    name: &str,
    bytes: &[u8],
    sensor: &SensorSpec,
    codes: IntegerCodes,
    size: Option<[u32; 2]>,
) -> Result<Frame, FrameFileError> {
    let format = format_of(name)
        .ok_or_else(|| FrameFileError::Unusable(format!("{name}: not an .exr, .png or .tiff")))?;
    let of_size = |[w, h]: [usize; 2]| match size {
        Some(want) if [w, h] != want.map(|n| n as usize) => Err(FrameFileError::Unusable(format!(
            "{name}: {}",
            crate::camera::wrong_size(w, h, want)
        ))),
        _ => Ok(()),
    };
    if format == ImageFormat::OpenExr {
        // Its size from the header first: a mismatch is final, where a
        // file that does not decode may still be being written.
        let meta = exr::meta::MetaData::read_from_buffered(Cursor::new(bytes), false)
            .map_err(|e| FrameFileError::Decode(format!("{name}: {e}")))?;
        if let Some(layer) = crate::exrio::rgb_layer(&meta.headers) {
            let header = &meta.headers[layer];
            of_size([header.layer_size.width(), header.layer_size.height()])?;
        }
        return crate::exrio::decode_rgb_within(Cursor::new(bytes), &|_| true, 1.0, None)
            .map_err(|e| FrameFileError::Decode(format!("{name}: {e}")));
    }
    let decoder = ImageReader::with_format(Cursor::new(bytes), format)
        .into_decoder()
        .map_err(|e| FrameFileError::Decode(format!("{name}: {e}")))?;
    let (w, h) = decoder.dimensions();
    of_size([w as usize, h as usize])?;
    let original = decoder.original_color_type();
    if matches!(original, ExtendedColorType::Cmyk8 | ExtendedColorType::Cmyk16) {
        return Err(FrameFileError::Unusable(format!(
            "{name}: a CMYK image is not a camera frame (grey or RGB)"
        )));
    }
    let image = DynamicImage::from_decoder(decoder)
        .map_err(|e| FrameFileError::Decode(format!("{name}: {e}")))?;
    let (width, height) = (image.width(), image.height());
    let unusable = |what: String| FrameFileError::Unusable(format!("{name}: {what}"));
    // Grey is replicated and alpha dropped by the crate's conversion to RGB
    // of the same depth (values unchanged).
    use image::ColorType::*;
    let rgb = match image.color() {
        Rgb32F | Rgba32F => image.into_rgb32f().into_raw(),
        L8 | La8 | Rgb8 | Rgba8 => {
            integers(image.into_rgb8().as_raw(), 8, sensor, codes).map_err(unusable)?
        }
        L16 | La16 | Rgb16 | Rgba16 => {
            integers(image.into_rgb16().as_raw(), 16, sensor, codes).map_err(unusable)?
        }
        other => return Err(unusable(format!("{other:?} pixels are not a camera frame"))),
    };
    Ok(Frame { width, height, rgb })
}

/// RGB integers of `file_bits` bits holding `sensor`'s codes as `codes`
/// says, in the frames' unit; refused when the values contradict the convention.
fn integers<T: Copy + Into<u32>>(
    values: &[T],
    file_bits: u32,
    sensor: &SensorSpec,
    codes: IntegerCodes,
) -> Result<Vec<f32>, String> {
    let bits = sensor.bits;
    let full = sensor.integer_full_scale(codes, file_bits).ok_or_else(|| {
        format!(
            "its {file_bits}-bit integers cannot hold the sensor's {bits}-bit codes (a \
             preview export?): have the capture program write 16-bit PNG or TIFF, or OpenEXR"
        )
    })?;
    // Every value's low bits are 0 when a capture program shifts the codes.
    let step = 1u32 << (file_bits - bits);
    let (mut max, mut nonzero, mut off_step, mut example) = (0u32, 0usize, 0usize, 0u32);
    for &v in values {
        let v: u32 = v.into();
        max = max.max(v);
        nonzero += (v != 0) as usize;
        if !v.is_multiple_of(step) {
            off_step += 1;
            example = v;
        }
    }
    let shifted_hint = format!(
        "the capture program shifts its codes left (× {step}): scan with --camera-codes shifted"
    );
    let top = (1u64 << file_bits) - 1;
    match codes {
        IntegerCodes::Native if max as u64 > full => {
            let hint = if off_step == 0 {
                shifted_hint
            } else {
                format!(
                    "if the capture program stretches its codes over 0…{top}, scan with \
                     --camera-codes scaled"
                )
            };
            return Err(format!("values up to {max}, above the sensor's top code {full}: {hint}"));
        }
        // A few non-zero values could all be multiples by chance (a dark
        // frame); a thousand cannot.
        IntegerCodes::Native if step > 1 && off_step == 0 && nonzero >= 1000 => {
            return Err(format!(
                "each of its {nonzero} non-zero values is a multiple of {step}: {shifted_hint}"
            ));
        }
        IntegerCodes::Shifted if off_step > 0 => {
            return Err(format!(
                "{off_step} values are not multiples of {step} (one is {example}), so the capture \
                 program does not shift its codes left: scan with --camera-codes native (the \
                 codes as they are), or scaled if it stretches them over 0…{top}"
            ));
        }
        _ => {}
    }
    // One division per possible value, not per value.
    let unit: Vec<f32> = (0..=top).map(|v| (v as f64 / full as f64) as f32).collect();
    Ok(values.iter().map(|&v| unit[Into::<u32>::into(v) as usize]).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sensor(bits: u32) -> SensorSpec {
        let mut s = scanner_geometry::ScannerGeometry::default_scanner().sensor;
        s.bits = bits;
        s
    }

    /// Codes 0 … 4095 spread over a 40 × 30 image, noise-like.
    fn codes(n: usize) -> Vec<u16> {
        (0..n).map(|i| ((i * 2_654_435_761usize) % 4096) as u16).collect()
    }

    fn write(dir: &Path, name: &str, image: DynamicImage) -> std::path::PathBuf {
        let path = dir.join(name);
        image.save(&path).unwrap();
        path
    }

    fn rgb16(values: Vec<u16>) -> DynamicImage {
        DynamicImage::ImageRgb16(image::ImageBuffer::from_raw(40, 30, values).unwrap())
    }

    /// A file of another size than the camera's is unusable (final, not
    /// retried as a file still being written), from its header.
    #[test]
    fn a_frame_of_another_size_than_the_cameras_is_unusable() {
        let dir = tempfile::tempdir().unwrap();
        let s = sensor(12);
        let png = write(dir.path(), "f.png", rgb16(codes(40 * 30 * 3)));
        let floats = Frame { width: 40, height: 30, rgb: vec![0.25; 40 * 30 * 3] };
        let exr = dir.path().join("f.exr");
        std::fs::write(&exr, crate::exrio::encode_half(&floats).unwrap()).unwrap();
        for path in [&png, &exr] {
            let read = |size| read_frame_file(path, &s, IntegerCodes::Native, size);
            assert_eq!(read(Some([40, 30])).unwrap().rgb.len(), 40 * 30 * 3);
            match read(Some([30, 40])) {
                Err(FrameFileError::Unusable(m)) => assert!(
                    m.ends_with(&format!(
                        "f.{}: a frame of 40×30 px; the geometry's camera has 30×40 px (set the \
                         camera's resolution and binning, or scan with its geometry)",
                        path.extension().unwrap().to_str().unwrap()
                    )),
                    "{m}"
                ),
                other => panic!("{other:?}"),
            }
        }
    }

    #[test]
    fn sixteen_bit_png_and_tiff_read_as_codes_over_the_top_code() {
        let dir = tempfile::tempdir().unwrap();
        let s = sensor(12);
        let c = codes(40 * 30 * 3);
        let expect: Vec<f32> = c.iter().map(|&v| (v as f64 / 4095.0) as f32).collect();
        for (name, values, convention) in [
            ("native.png", c.clone(), IntegerCodes::Native),
            ("native.tiff", c.clone(), IntegerCodes::Native),
            ("shifted.png", c.iter().map(|v| v << 4).collect(), IntegerCodes::Shifted),
            ("shifted.TIF", c.iter().map(|v| v << 4).collect(), IntegerCodes::Shifted),
        ] {
            let path = write(dir.path(), name, rgb16(values));
            let f = read_frame_file(&path, &s, convention, None).unwrap();
            assert_eq!((f.width, f.height), (40, 30));
            assert!(f.rgb == expect, "{name}: the same floats as code / 4095");
        }
        // Stretched: within half a step of 65 535.
        let scaled: Vec<u16> =
            c.iter().map(|&v| (v as f64 * 65535.0 / 4095.0).round() as u16).collect();
        let path = write(dir.path(), "scaled.png", rgb16(scaled));
        let f = read_frame_file(&path, &s, IntegerCodes::Scaled, None).unwrap();
        let worst = f.rgb.iter().zip(&expect).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
        assert!(worst <= 0.5 / 65535.0 + 1e-7, "{worst}");
    }

    #[test]
    fn grey_and_alpha_images_read_as_rgb() {
        let dir = tempfile::tempdir().unwrap();
        let s = sensor(12);
        let grey: Vec<u16> = codes(40 * 30);
        let path = write(
            dir.path(),
            "grey.tiff",
            DynamicImage::ImageLuma16(image::ImageBuffer::from_raw(40, 30, grey.clone()).unwrap()),
        );
        let f = read_frame_file(&path, &s, IntegerCodes::Native, None).unwrap();
        for (i, &g) in grey.iter().enumerate() {
            let v = (g as f64 / 4095.0) as f32;
            assert_eq!(&f.rgb[3 * i..3 * i + 3], &[v, v, v]);
        }
        let rgba: Vec<u16> = codes(40 * 30 * 4);
        let path = write(
            dir.path(),
            "alpha.png",
            DynamicImage::ImageRgba16(image::ImageBuffer::from_raw(40, 30, rgba.clone()).unwrap()),
        );
        let f = read_frame_file(&path, &s, IntegerCodes::Native, None).unwrap();
        assert_eq!(f.rgb.len(), 40 * 30 * 3);
        assert_eq!(f.rgb[3 * 7 + 2], (rgba[4 * 7 + 2] as f64 / 4095.0) as f32);
        // Float TIFF: the values themselves.
        let floats: Vec<f32> = (0..40 * 30 * 3).map(|i| i as f32 / 3600.0).collect();
        let path = write(
            dir.path(),
            "float.tiff",
            DynamicImage::ImageRgb32F(
                image::ImageBuffer::from_raw(40, 30, floats.clone()).unwrap(),
            ),
        );
        assert!(read_frame_file(&path, &s, IntegerCodes::Shifted, None).unwrap().rgb == floats);
    }

    #[test]
    fn values_that_contradict_the_convention_are_refused_with_the_option_that_reads_them() {
        let dir = tempfile::tempdir().unwrap();
        let s = sensor(12);
        let c = codes(40 * 30 * 3);
        let unusable = |path: &Path, codes| match read_frame_file(path, &s, codes, None) {
            Err(FrameFileError::Unusable(m)) => m,
            other => panic!("{other:?}"),
        };
        // Shifted codes read as native: above the top code.
        let shifted = write(dir.path(), "shifted.png", rgb16(c.iter().map(|v| v << 4).collect()));
        let m = unusable(&shifted, IntegerCodes::Native);
        assert!(m.contains("values up to 65520, above the sensor's top code 4095"), "{m}");
        assert!(m.contains("--camera-codes shifted"), "{m}");
        // … and a dark one, whose values all stay below it.
        let dark = write(dir.path(), "dark.png", rgb16(c.iter().map(|v| (v % 4) << 4).collect()));
        let m = unusable(&dark, IntegerCodes::Native);
        assert!(m.contains("is a multiple of 16: the capture program shifts"), "{m}");
        // A few non-zero multiples of 16 are no evidence.
        let sparse: Vec<u16> = (0..3600).map(|i| if i % 8 == 0 { 16 } else { 0 }).collect();
        let sparse = write(dir.path(), "sparse.png", rgb16(sparse));
        assert!(read_frame_file(&sparse, &s, IntegerCodes::Native, None).is_ok());
        // Native codes read as shifted.
        let native = write(dir.path(), "native.tiff", rgb16(c.clone()));
        let m = unusable(&native, IntegerCodes::Shifted);
        assert!(m.contains("are not multiples of 16"), "{m}");
        assert!(m.contains("--camera-codes native"), "{m}");
        // Stretched codes read as native.
        let scaled = write(
            dir.path(),
            "scaled.png",
            rgb16(c.iter().map(|&v| (v as f64 * 65535.0 / 4095.0).round() as u16).collect()),
        );
        let m = unusable(&scaled, IntegerCodes::Native);
        assert!(m.contains("--camera-codes scaled"), "{m}");
        // An 8-bit image of a 12-bit sensor; of an 8-bit sensor it is fine.
        let eight = write(
            dir.path(),
            "eight.png",
            DynamicImage::ImageRgb8(image::ImageBuffer::from_raw(40, 30, vec![7u8; 3600]).unwrap()),
        );
        let m = unusable(&eight, IntegerCodes::Native);
        assert!(m.contains("its 8-bit integers cannot hold the sensor's 12-bit codes"), "{m}");
        let f = read_frame_file(&eight, &sensor(8), IntegerCodes::Native, None).unwrap();
        assert_eq!(f.rgb[0], (7.0f64 / 255.0) as f32);
    }

    #[test]
    fn a_partial_file_is_a_decode_error_and_other_names_are_not_frames() {
        let dir = tempfile::tempdir().unwrap();
        let s = sensor(12);
        for name in ["partial.png", "partial.tiff"] {
            let whole = write(dir.path(), &format!("whole-{name}"), rgb16(codes(3600)));
            let bytes = std::fs::read(&whole).unwrap();
            let p = dir.path().join(name);
            std::fs::write(&p, &bytes[..bytes.len() / 2]).unwrap();
            assert!(
                matches!(
                    read_frame_file(&p, &s, IntegerCodes::Native, None),
                    Err(FrameFileError::Decode(_))
                ),
                "{name}"
            );
        }
        assert!(is_frame_file("a.EXR") && is_frame_file("b.tif") && is_frame_file("c.Png"));
        assert!(!is_frame_file("d.jpg") && !is_frame_file("tiff") && !is_frame_file("e.raw"));
    }
}
