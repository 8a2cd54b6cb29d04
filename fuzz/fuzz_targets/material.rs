//! Fuzz the material reader: arbitrary bytes must give a typed error or a
//! material, never a panic; a material that opens answers every query
//! with finite, non-negative values. Mutated as a safetensors file whose
//! header and material metadata are JSON (`fuzz_support::structured`) as
//! well as bytes.
#![no_main]

use libfuzzer_sys::fuzz_target;
use scanner_shading::Material;

fuzz_target!(|data: &[u8]| {
    if let Ok(m) = Material::from_bytes(data) {
        for (uv, wi, wo) in [
            ([0.5, 0.5], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]),
            ([-3.2, 7.9], [0.6, -0.3, 0.2], [-0.5, 0.5, 0.4]),
            ([0.0, 1.0], [1.0, 0.0, 1e-4], [0.0, 1.0, 1e-4]),
        ] {
            let c = m.eval(uv, wi, wo);
            assert!(c.iter().all(|x| x.is_finite() && *x >= 0.0), "{c:?}");
        }
    }
});

fuzz_support::structured_mutator!(fuzz_support::structured::material_file);
