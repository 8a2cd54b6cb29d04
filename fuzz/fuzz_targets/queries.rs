//! Fuzz the shading query and answer file readers (docs/query-format.md):
//! arbitrary bytes read as `.npy` and as `.csv` must give a typed error or
//! rows, never a panic or an allocation the file cannot back; every query
//! read has finite uv and unit directions.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use scanner_formats::queries::{parse_answers, parse_queries};

fuzz_target!(|data: &[u8]| {
    for name in ["q.npy", "q.csv"] {
        if let Ok(qs) = parse_queries(Path::new(name), data) {
            for q in qs {
                assert!(q.uv.iter().all(|x| x.is_finite()), "{q:?}");
                for d in [q.wi, q.wo] {
                    let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                    assert!((len - 1.0).abs() < 1e-9, "{q:?}");
                }
            }
        }
        let _ = parse_answers(Path::new(name), data);
    }
});
