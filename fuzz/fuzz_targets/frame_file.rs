//! Fuzz the frame files a camera's capture program drops into the folder
//! camera's folder (`host::frame_file::decode_frame_file`: 16- and 8-bit
//! PNG and TIFF, 32-bit float TIFF, through the image crate, then the
//! integer-code conventions): arbitrary bytes must give an error or a
//! frame of the size its header gives, never a panic.
//!
//! The first byte chooses how the rest is read: bit 0 the format (PNG or
//! TIFF), bits 1–2 the integer convention, bit 3 whether the camera's size
//! is given, bit 4 an 8-bit sensor instead of 12.
#![no_main]

use std::io::Cursor;

use host::frame_file::decode_frame_file;
use libfuzzer_sys::fuzz_target;
use scanner_geometry::{IntegerCodes, ScannerGeometry};

fuzz_target!(|data: &[u8]| {
    let Some((&how, bytes)) = data.split_first() else { return };
    let (name, format) = if how & 1 == 0 {
        ("f.png", image::ImageFormat::Png)
    } else {
        ("f.tiff", image::ImageFormat::Tiff)
    };
    // A header may claim an image up to the image crate's allocation limit
    // (512 MiB), which is legal; bounded here so that libFuzzer's malloc
    // limit does not call that a crash.
    if let Ok((w, h)) =
        image::ImageReader::with_format(Cursor::new(bytes), format).into_dimensions()
        && w as u64 * h as u64 > 1 << 22
    {
        return;
    }
    let codes = [IntegerCodes::Native, IntegerCodes::Shifted, IntegerCodes::Scaled]
        [((how as usize >> 1) & 3) % 3];
    let size = (how & 8 != 0).then_some([48, 40]);
    let mut sensor = ScannerGeometry::default_scanner().sensor;
    sensor.bits = if how & 16 != 0 { 8 } else { 12 };
    if let Ok(f) = decode_frame_file(name, bytes, &sensor, codes, size) {
        assert_eq!(f.rgb.len(), f.width as usize * f.height as usize * 3);
        if let Some([w, h]) = size {
            assert_eq!([f.width, f.height], [w, h]);
        }
        // Integers come out within full scale; floats are the file's own.
        if !matches!(image::ImageReader::with_format(Cursor::new(bytes), format)
            .into_decoder()
            .map(|d| image::ImageDecoder::color_type(&d)), Ok(image::ColorType::Rgb32F | image::ColorType::Rgba32F))
        {
            assert!(f.rgb.iter().all(|v| (0.0..=1.0).contains(v)), "integer codes beyond full scale");
        }
    }
});
