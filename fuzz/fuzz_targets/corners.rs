//! Fuzz finding a piece's corners in a photograph
//! (`host::build::corners::find_corners`, `scanner rectify --corners
//! auto`, and `refine_corners` for `--refine`): any picture gives a typed
//! error or corners that `rectify` accepts, never a panic. The input:
//! width and height (1–96 px), then one byte per pixel, on a log scale
//! over 2⁻⁸…2⁸ (0: black), repeated to fill the picture; the origin and
//! whether the lens is estimated (`--lens auto`) from the third byte.
#![no_main]

use host::build::corners::{Origin, find_corners, refine_corners};
use host::build::lens::{Lens, LensChoice};
use host::build::rectify::{RectifyOptions, rectify};
use host::camera::Frame;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let [w, h, o, pixels @ ..] = data else { return };
    if pixels.is_empty() {
        return;
    }
    let (w, h) = (*w as u32 % 96 + 1, *h as u32 % 96 + 1);
    let value = |b: u8| if b == 0 { 0.0 } else { (2.0f32).powf(b as f32 / 16.0 - 8.0) };
    let rgb = (0..(w * h) as usize).flat_map(|i| [value(pixels[i % pixels.len()]); 3]).collect();
    let photo = Frame { width: w, height: h, rgb };
    let origin = Origin::ALL[*o as usize % 4].1;
    let lens = if o & 4 != 0 { LensChoice::Estimate } else { LensChoice::Known(Lens::PINHOLE) };
    // Found, and refined from marks around the picture's middle half.
    let (x0, y0, x1, y1) =
        (w as f64 / 4.0, h as f64 / 4.0, 3.0 * w as f64 / 4.0, 3.0 * h as f64 / 4.0);
    let marked = [[x0, y1], [x1, y1], [x1, y0], [x0, y0]];
    for found in [find_corners(&photo, origin, lens), refine_corners(&photo, marked, lens)] {
        let Ok(found) = found else { continue };
        assert!(found.contrast >= 2.0 && found.edge_rms_px <= 0.75, "{found:?}");
        let opts = RectifyOptions {
            corners: found.corners,
            size_mm: [10.0, 10.0],
            px_per_mm: None,
            lens: found.lens,
        };
        assert!(opts.check(w, h).is_ok(), "{found:?}: {:?}", opts.check(w, h));
        assert!(rectify(&photo, &opts).is_ok());
    }
});
