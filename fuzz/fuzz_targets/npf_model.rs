//! Fuzz the NPF model file (docs/npf-format.md §2), which `scanner fit`
//! writes and `scanner render-brdf` and `plot-npf` read, as may another
//! program: arbitrary text must give an error or a model, never a panic; a
//! model the reader accepts evaluates to finite, non-negative values at any
//! pair of directions above the horizon (down to 0.06° from it), and writes
//! back to a file that reads as the same model. Mutated as JSON
//! (`fuzz_support::structured`) as well as bytes.
#![no_main]

use host::brdf::Brdf;
use host::brdf::npf::NpfModel;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(model) = NpfModel::from_json(data, "fuzz.json") else { return };
    for (wi, wo) in fuzz_support::direction_pairs() {
        let rho = model.eval(wi, wo);
        assert!(rho.iter().all(|x| x.is_finite() && *x >= 0.0), "{wi:?} {wo:?}: {rho:?}");
    }
    let back = NpfModel::from_json(&model.to_json(), "written.json").expect("reads back");
    assert!(back.channels == model.channels, "the file round-trips");
});

fuzz_support::structured_mutator!(fuzz_support::structured::json_file);
