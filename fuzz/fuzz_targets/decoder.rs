//! Fuzz the stream decoder: arbitrary bytes in arbitrary chunks must never
//! panic, and every frame it accepts must re-encode to bytes that decode to
//! the same frame.
#![no_main]

use libfuzzer_sys::fuzz_target;
use protocol::{FrameDecoder, MAX_FRAME_LEN, Message, Request, ToHost, decode_frame, encode_frame};

fn check<M: Message + PartialEq + core::fmt::Debug>(data: &[u8]) {
    let Some((&chunk, bytes)) = data.split_first() else { return };
    let chunk = usize::from(chunk).max(1);
    let mut decoder = FrameDecoder::<M>::new();
    for piece in bytes.chunks(chunk) {
        for frame in decoder.feed(piece).flatten() {
            let mut buf = [0u8; MAX_FRAME_LEN];
            let n =
                encode_frame(frame.seq, &frame.msg, &mut buf).expect("accepted frame re-encodes");
            let again = decode_frame::<M>(&mut buf[..n - 1]).expect("re-encoded frame decodes");
            // Debug comparison: exact even for NaN payload floats.
            assert_eq!(format!("{:?}", again), format!("{:?}", frame));
        }
    }
}

fuzz_target!(|data: &[u8]| {
    check::<Request>(data);
    check::<ToHost>(data);
});
