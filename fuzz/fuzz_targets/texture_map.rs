//! Fuzz the OpenEXR reading of a texture set's maps (docs/texture-set.md):
//! `hil-sim` reads them with the exr crate's flat-layer reader, every
//! channel of the first valid layer. Arbitrary bytes must give an error or
//! an image, never a panic.
#![no_main]

use std::io::Cursor;

use exr::prelude::*;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    // As in the `frame` target: headers that claim more than 2²² px are
    // left out, so that libFuzzer's malloc limit does not call a large
    // (legal) image a crash.
    if let Ok(meta) = exr::meta::MetaData::read_from_buffered(Cursor::new(data), false)
        && meta.headers.iter().any(|h| h.layer_size.area() > 1 << 22)
    {
        return;
    }
    let _ = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_buffered(Cursor::new(data));
});
