//! Fuzz the host's device link (`host::link::Device`) against a device
//! that answers whatever the fuzzer's bytes say (`host::hostile`): wrong
//! replies, foreign sequence numbers, noise, event floods, resets, unplugs.
//! The host must answer each call with a value or an error, never panic,
//! and finish in bounded simulated time.
#![no_main]

use std::time::Duration;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let seen = host::hostile::exercise(data.to_vec());
    assert!(seen.took < Duration::from_secs(600), "{seen:?}: the session's simulated time");
    // Every link call within the limit the link documents for it.
    assert!(seen.overrun <= host::link::LinkTimings::SLACK, "{seen:?}: a call past its limit");
});
