//! Fuzz the material reader: arbitrary bytes must give a typed error or a
//! material, never a panic; a material that opens answers every query
//! with finite, non-negative values and draws directions with a positive
//! density, and its export as a texture set
//! (`scanner export`) is a set the format accepts, or a typed refusal; the
//! set converts to a consistent `.glb`.
//! Mutated as a safetensors file whose
//! header and material metadata are JSON (`fuzz_support::structured`) as
//! well as bytes.
#![no_main]

use libfuzzer_sys::fuzz_target;
use scanner_shading::Material;

fuzz_target!(|data: &[u8]| {
    if let Ok(d) = scanner_shading::MaterialData::from_bytes(data) {
        if let Ok(set) = host::build::export::texture_set(&d) {
            let n = set.side * set.side;
            assert!(set.diffuse.len() == n && set.specular.len() == n && set.normal.len() == n);
            let unit = |x: f32| (0.0..=1.0).contains(&x);
            for i in 0..n {
                assert!(set.diffuse[i].iter().chain(&set.specular[i]).all(|&x| unit(x)));
                assert!(set.specular[i].iter().any(|&x| x > 0.0), "a lobe lost");
                assert!((0.03..=1.0).contains(&set.roughness[i]), "{}", set.roughness[i]);
                let v = set.normal[i];
                let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                assert!((len - 1.0).abs() < 1e-5 && v[2] >= 0.09, "{v:?}");
            }
            // … and as a glTF asset (`--format glb`): one file whose header
            // and chunks agree with its length.
            let glb = host::build::gltf::glb(&set).expect("any set converts");
            let word = |at: usize| u32::from_le_bytes(glb[at..at + 4].try_into().unwrap()) as usize;
            assert!(&glb[..4] == b"glTF" && word(8) == glb.len());
            let json = word(12);
            assert_eq!(20 + json + 8 + word(20 + json), glb.len());
        }
    }
    if let Ok(m) = Material::from_bytes(data) {
        for (uv, wi, wo) in [
            ([0.5, 0.5], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]),
            ([-3.2, 7.9], [0.6, -0.3, 0.2], [-0.5, 0.5, 0.4]),
            ([0.0, 1.0], [1.0, 0.0, 1e-4], [0.0, 1.0, 1e-4]),
        ] {
            let c = m.eval(uv, wi, wo);
            assert!(c.iter().all(|x| x.is_finite() && *x >= 0.0), "{c:?}");
        }
        // Importance sampling (one view's table): a draw is above the
        // horizon with a positive finite density, which `pdf` repeats.
        let wo = [0.3, -0.2, 0.9];
        for (uc, u) in [(0.05, [0.3, 0.7]), (0.6, [0.5, 0.5]), (0.999, [0.99, 0.01])] {
            if let Some(s) = m.sample([0.3, 0.8], wo, uc, u) {
                assert!(s.wi[2] > 0.0 && s.pdf.is_finite() && s.pdf > 0.0, "{s:?}");
                assert!(s.f_cos.iter().all(|x| x.is_finite() && *x >= 0.0), "{s:?}");
                assert_eq!(s.pdf, m.pdf([0.3, 0.8], s.wi, wo));
            }
        }
    }
});

fuzz_support::structured_mutator!(fuzz_support::structured::material_file);
