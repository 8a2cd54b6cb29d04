//! What the fuzz targets share: the structure-aware mutator of the text
//! files and the scanner they check a file against.

pub mod structured;

use std::sync::OnceLock;

use host::geometry::ScannerGeometry;

/// The default scanner, its sensor binned `bin`× (1 or 64: the scanners the
/// seeds of `fuzz_seeds` were made for), made once per process.
pub fn default_scanner(bin: u32) -> &'static ScannerGeometry {
    static FULL: OnceLock<ScannerGeometry> = OnceLock::new();
    static BINNED: OnceLock<ScannerGeometry> = OnceLock::new();
    match bin {
        1 => FULL.get_or_init(ScannerGeometry::default_scanner),
        64 => BINNED.get_or_init(|| ScannerGeometry::default_scanner().with_sensor_scaled(64)),
        _ => panic!("no seeds for a sensor binned {bin}×"),
    }
}

/// Direction pairs above the horizon (local frame, normal +z) that a BRDF
/// target evaluates a model at: normal, oblique and grazing (cos θ = 0.001)
/// light and view directions, in and out of the plane of incidence.
pub fn direction_pairs() -> Vec<([f64; 3], [f64; 3])> {
    let dirs: Vec<[f64; 3]> = [1.0, 0.9, 0.5, 0.1, 0.001]
        .iter()
        .flat_map(|&z: &f64| {
            let s = (1.0 - z * z).sqrt();
            [0.0, 1.3, 3.1].map(|p: f64| [s * p.cos(), s * p.sin(), z])
        })
        .collect();
    dirs.iter().flat_map(|&wi| dirs.iter().map(move |&wo| (wi, wo))).collect()
}

/// Whether the environment asks for libFuzzer's byte mutations alone
/// (`FUZZ_BYTES_ONLY=1`), to compare the structure-aware mutator with them.
pub fn bytes_only() -> bool {
    static B: OnceLock<bool> = OnceLock::new();
    *B.get_or_init(|| std::env::var_os("FUZZ_BYTES_ONLY").is_some_and(|v| v == "1"))
}

/// libFuzzer's custom mutator for a target whose input is a document:
/// `$mutate` (one of [`structured::json_file`], [`structured::toml_file`],
/// [`structured::material_file`]) three times in four, of the input or, if
/// it does not parse, of a document seen before ([`structured::with_pool`]);
/// libFuzzer's own byte mutations otherwise, and always under
/// `FUZZ_BYTES_ONLY=1`.
#[macro_export]
macro_rules! structured_mutator {
    ($mutate:path) => {
        libfuzzer_sys::fuzz_mutator!(|data: &mut [u8], size: usize, max_size: usize, seed: u32| {
            if !$crate::bytes_only() && seed % 4 != 0 {
                if let Some(n) =
                    $crate::structured::with_pool($mutate, data, size, max_size, seed / 4)
                {
                    return n;
                }
            }
            libfuzzer_sys::fuzzer_mutate(data, size, max_size)
        });
    };
}
