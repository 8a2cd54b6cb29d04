//! Fuzz the direct images' manifest (docs/direct-images.md), which
//! `scanner enlarge` reads: arbitrary bytes must give a typed error or a
//! manifest that passes its own check and writes back to the same
//! manifest. Mutated as TOML (`fuzz_support::structured`) as well as bytes.
#![no_main]

use libfuzzer_sys::fuzz_target;
use scanner_formats::direct::DirectManifest;

fuzz_target!(|data: &[u8]| {
    let Ok(m) = DirectManifest::parse(data) else { return };
    assert_eq!(m.check(), Ok(()));
    let text = m.to_toml();
    assert_eq!(DirectManifest::parse(text.as_bytes()).as_ref(), Ok(&m), "{text}");
});

fuzz_support::structured_mutator!(fuzz_support::structured::toml_file);
