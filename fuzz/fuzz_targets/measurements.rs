//! Fuzz the scattered-measurement CSV (docs/npf-format.md §7) that
//! `scanner fit` reads from a gonioreflectometer or another program:
//! arbitrary bytes must give an error naming the line or measurements, and
//! measurements the fit accepts must fit without a panic to a model of
//! finite numbers. A model within range (`NpfModel::check`: ρd and ρs
//! within [0, 1e8], tables within [0, 1]; out of it, `scanner fit` says the
//! measurements do not determine the model) must read back as itself and
//! evaluate to finite, non-negative values. Two iterations, with Smith or
//! independent G by the input's length.
#![no_main]

use host::brdf::Brdf;
use host::brdf::fit::{FitOptions, GVariant, Samples, fit};
use host::brdf::measurements::parse_csv;
use host::brdf::npf::NpfModel;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(measurements) = parse_csv(data, "fuzz.csv") else { return };
    for m in &measurements {
        for d in [m.wi, m.wo] {
            let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            assert!((len - 1.0).abs() < 1e-9, "{m:?}");
        }
    }
    let Ok(samples) = Samples::from_measurements(&measurements) else { return };
    let g = if data.len().is_multiple_of(2) { GVariant::Smith } else { GVariant::Independent };
    let opts = FitOptions { g, max_iterations: 2, ..FitOptions::default() };
    let (model, _) = fit(&samples, &opts, &|_, _, _| {});
    for c in &model.channels {
        let numbers = [c.rho_d, c.rho_s].into_iter().chain(c.d).chain(c.f).chain(c.g);
        assert!(numbers.into_iter().all(f64::is_finite), "{c:?}");
    }
    if model.check().is_err() {
        return;
    }
    let back = NpfModel::from_json(&model.to_json(), "fitted.json").expect("reads back");
    assert!(back.channels == model.channels, "the file round-trips");
    for (wi, wo) in fuzz_support::direction_pairs() {
        let rho = model.eval(wi, wo);
        assert!(rho.iter().all(|x| x.is_finite() && *x >= 0.0), "{wi:?} {wo:?}: {rho:?}");
    }
});
