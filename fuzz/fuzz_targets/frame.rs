//! Fuzz the OpenEXR frame decoder (`host::exrio::decode_rgb_within`, which
//! reads scan frames and the folder camera's frames, with the vendored exr
//! crate's PIZ decoder): arbitrary bytes must give an error or a frame of
//! the size its header gives, never a panic, whether every block is wanted
//! or only some.
#![no_main]

use std::io::Cursor;

use host::exrio::decode_rgb_within;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    // A header may claim up to 2²⁸ px (`MAX_PIXELS`), which the decoder
    // accepts and only maps (the pixels of blocks not decoded are never
    // touched); bounded here so that libFuzzer's malloc limit does not call
    // that a crash.
    if let Ok(meta) = exr::meta::MetaData::read_from_buffered(Cursor::new(data), false)
        && meta.headers.iter().any(|h| h.layer_size.area() > 1 << 22)
    {
        return;
    }
    for (wanted, unit) in [
        (&(|_| true) as &(dyn Fn([usize; 4]) -> bool + Sync), 1.0),
        (&|b: [usize; 4]| b[0] < 40 && b[1] < 40, 0.5),
    ] {
        if let Ok(f) = decode_rgb_within(Cursor::new(data), wanted, unit, None) {
            assert_eq!(f.rgb.len(), f.width as usize * f.height as usize * 3);
            // Asked for its own size it reads the same; for another, not at all.
            let size = [f.width as usize, f.height as usize];
            let again = decode_rgb_within(Cursor::new(data), wanted, unit, Some(size));
            assert!(again.is_ok_and(|g| g.rgb.len() == f.rgb.len()));
            let other = Some([size[0] + 1, size[1]]);
            assert!(decode_rgb_within(Cursor::new(data), wanted, unit, other).is_err());
        }
    }
});
