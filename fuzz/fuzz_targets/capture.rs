//! Fuzz the capture (`host::scan`: the mirror table, homing and its
//! repeatability, a three-mirror scan into a temporary directory) against a
//! device that answers as a board would, except as the fuzzer's bytes say
//! (`host::hostile::exercise_capture`). No panic, bounded simulated time.
#![no_main]

use std::time::Duration;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let dir = tempfile::tempdir().expect("a temporary directory");
    let (took, drain) = host::hostile::exercise_capture(data.to_vec(), dir.path());
    assert!(took < Duration::from_secs(3_600), "{took:?} of simulated time");
    // The longest exposure and the frame timeout (200 ms).
    assert!(drain <= Duration::from_millis(2_200), "a stray frame waited for {drain:?}");
});
