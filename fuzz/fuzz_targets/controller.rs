//! Fuzz the controller's safety (`firmware::chaos`): the fuzzer's bytes are
//! the randomness of a random operation — requests (plausible, decoded
//! from raw bytes, framed through the decoder), line noise, an emergency
//! stop or driver fault at any moment, switches that break, axes pushed or
//! skipping, a silent host, reboots — and every rule is checked at every
//! step and poll. A broken rule or a panic of the controller is a crash.
#![no_main]

use firmware::chaos::{Bytes, run};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Err(v) = run(&mut Bytes(data), 2_000) {
        panic!("{v}");
    }
});
