//! Property and robustness tests of framing and the stream decoder.

mod common;

use std::collections::HashSet;

use arbitrary::{Arbitrary, Unstructured};
use proptest::prelude::*;
use protocol::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn encode<M: Message>(seq: u8, msg: &M) -> Vec<u8> {
    let mut buf = [0u8; MAX_FRAME_LEN];
    let n = encode_frame(seq, msg, &mut buf).expect("every message fits MAX_FRAME_LEN");
    buf[..n].to_vec()
}

/// Arbitrary message from raw entropy (the `arbitrary` derive covers every variant).
fn message<'a, M: Arbitrary<'a>>(entropy: &'a [u8]) -> Option<M> {
    M::arbitrary(&mut Unstructured::new(entropy)).ok()
}

/// Decode a whole stream, delivered in chunks cut at `cuts`.
fn decode_chunked<M: Message>(stream: &[u8], cuts: &[usize]) -> Vec<Result<Frame<M>, FrameError>> {
    let mut decoder = FrameDecoder::<M>::new();
    let mut out = Vec::new();
    let mut cuts: Vec<usize> = cuts.iter().map(|c| c % (stream.len() + 1)).collect();
    cuts.sort_unstable();
    let mut start = 0;
    for end in cuts.into_iter().chain([stream.len()]) {
        out.extend(decoder.feed(&stream[start..end]));
        start = end;
    }
    out
}

fn round_trip<M: Message + std::fmt::Debug>(seq: u8, msg: &M) {
    let mut bytes = encode(seq, msg);
    assert!(bytes.len() <= M::MAX_FRAME_LEN);
    assert_eq!(bytes.pop(), Some(0));
    assert!(!bytes.contains(&0));
    let frame: Frame<M> = decode_frame(&mut bytes).expect("own frame decodes");
    assert_eq!(frame.seq, seq);
    // Compare by re-encoding and by Debug: both are exact even for NaN floats.
    assert_eq!(encode(seq, &frame.msg), encode(seq, msg));
    assert_eq!(format!("{:?}", frame.msg), format!("{msg:?}"));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    #[test]
    fn arbitrary_requests_round_trip(seq: u8, entropy in prop::collection::vec(any::<u8>(), 0..160)) {
        if let Some(msg) = message::<Request>(&entropy) {
            round_trip(seq, &msg);
        }
    }

    #[test]
    fn arbitrary_device_messages_round_trip(seq: u8, entropy in prop::collection::vec(any::<u8>(), 0..200)) {
        if let Some(msg) = message::<ToHost>(&entropy) {
            round_trip(seq, &msg);
        }
    }

    #[test]
    fn any_chunking_yields_the_frames_sent(
        entropies in prop::collection::vec(prop::collection::vec(any::<u8>(), 0..120), 1..12),
        cuts in prop::collection::vec(any::<usize>(), 0..40),
    ) {
        let sent: Vec<(u8, ToHost)> = entropies
            .iter()
            .enumerate()
            .filter_map(|(i, e)| message::<ToHost>(e).map(|m| (i as u8, m)))
            .collect();
        let stream: Vec<u8> = sent.iter().flat_map(|(s, m)| encode(*s, m)).collect();
        let got: Vec<(u8, String)> = decode_chunked::<ToHost>(&stream, &cuts)
            .into_iter()
            .map(|r| r.map(|f| (f.seq, format!("{:?}", f.msg))).expect("clean stream"))
            .collect();
        let want: Vec<(u8, String)> = sent.iter().map(|(s, m)| (*s, format!("{m:?}"))).collect();
        prop_assert_eq!(got, want);
    }

    #[test]
    fn decoder_never_panics_on_arbitrary_bytes(
        bytes in prop::collection::vec(any::<u8>(), 0..600),
        cuts in prop::collection::vec(any::<usize>(), 0..20),
    ) {
        let _ = decode_chunked::<Request>(&bytes, &cuts);
        let _ = decode_chunked::<ToHost>(&bytes, &cuts);
    }
}

/// Corrupt a frame the way a bad line does.
fn corrupt(rng: &mut ChaCha8Rng, frame: &mut Vec<u8>) {
    match rng.random_range(0..5) {
        0 => {
            let i = rng.random_range(0..frame.len());
            frame[i] ^= 1 << rng.random_range(0..8);
        }
        1 => {
            let i = rng.random_range(0..frame.len());
            frame[i] = rng.random();
        }
        2 => {
            frame.remove(rng.random_range(0..frame.len()));
        }
        3 => {
            let i = rng.random_range(0..=frame.len());
            frame.insert(i, rng.random());
        }
        _ => {
            let keep = rng.random_range(0..frame.len());
            frame.truncate(keep);
        }
    }
}

/// ≥ 1,000,000 bytes of valid frames, corrupted frames and noise, in random
/// chunks: the decoder never panics, never accepts a frame that was not sent,
/// and recovers every intact frame.
#[test]
fn million_noisy_bytes_accept_only_sent_frames() {
    let mut rng = ChaCha8Rng::seed_from_u64(0x5CA7_0001);
    let mut stream = Vec::with_capacity(1_100_000);
    let mut sent: HashSet<Vec<u8>> = HashSet::new();
    let mut intact = 0usize;
    let mut entropy = vec![0u8; 200];
    while stream.len() < 1_000_000 {
        match rng.random_range(0..10) {
            // An intact frame, preceded by a delimiter as senders may do.
            0..=4 => {
                rng.fill(&mut entropy[..]);
                let Some(msg) = message::<ToHost>(&entropy) else { continue };
                let frame = encode(rng.random(), &msg);
                stream.push(0);
                stream.extend_from_slice(&frame);
                sent.insert(frame);
                intact += 1;
            }
            // A corrupted frame (its original counts as "sent").
            5..=7 => {
                rng.fill(&mut entropy[..]);
                let Some(msg) = message::<ToHost>(&entropy) else { continue };
                let frame = encode(rng.random(), &msg);
                let mut bad = frame.clone();
                corrupt(&mut rng, &mut bad);
                stream.extend_from_slice(&bad);
                sent.insert(frame);
            }
            // Line noise, sometimes long enough to overflow the buffer.
            _ => {
                let n = if rng.random_bool(0.1) {
                    rng.random_range(100..400)
                } else {
                    rng.random_range(1..40)
                };
                stream.extend((0..n).map(|_| rng.random::<u8>()));
            }
        }
    }
    // One trailing delimiter so the last frame completes.
    stream.push(0);

    let mut decoder = FrameDecoder::<ToHost>::new();
    let (mut accepted, mut rejected) = (0usize, 0usize);
    let mut pos = 0;
    while pos < stream.len() {
        let end = (pos + rng.random_range(1..300)).min(stream.len());
        for result in decoder.feed(&stream[pos..end]) {
            match result {
                Ok(frame) => {
                    let bytes = encode(frame.seq, &frame.msg);
                    assert!(
                        sent.contains(&bytes),
                        "accepted a frame that was never sent: {frame:?}"
                    );
                    accepted += 1;
                }
                Err(_) => rejected += 1,
            }
        }
        pos = end;
    }
    eprintln!("bytes {} intact {intact} accepted {accepted} rejected {rejected}", stream.len());
    assert!(stream.len() >= 1_000_000);
    // Every intact frame is recovered; a corrupted frame may also be accepted
    // when the damage only cut it short of its delimiter (it is then still a
    // sent frame, as checked above) — but never more than that.
    assert!(accepted >= intact, "recovered {accepted} of {intact} intact frames");
    assert!(rejected > 0);
}

#[test]
fn overlong_input_is_dropped_and_decoder_resyncs() {
    let mut decoder = FrameDecoder::<Request>::new();
    let noise = vec![0x55u8; 3 * MAX_FRAME_LEN];
    assert_eq!(decoder.feed(&noise).count(), 0);
    let good = encode(9, &Request::GetStatus);
    let mut stream = vec![0u8];
    stream.extend_from_slice(&good);
    let results: Vec<_> = decoder.feed(&stream).collect();
    assert_eq!(results.len(), 2);
    assert_eq!(results[0], Err(FrameError::TooLong));
    assert_eq!(results[1], Ok(Frame { seq: 9, msg: Request::GetStatus }));
}

#[test]
fn a_flushed_frame_survives_the_loss_of_the_delimiter_before_it() {
    let status = || Request::GetStatus;
    let mut flushed = [0u8; MAX_FLUSHED_FRAME_LEN];
    let n = encode_flushed_frame(5, &status(), &mut flushed).unwrap();
    assert_eq!(flushed[0], 0);
    assert_eq!(&flushed[1..n], encode(5, &status()).as_slice());
    let mut scratch = [0u8; MAX_FLUSHED_FRAME_LEN];
    let short = encode_flushed_frame(5, &status(), &mut scratch[..n - 1]);
    assert_eq!(short, Err(FrameError::BufferTooSmall));
    assert_eq!(encode_flushed_frame(5, &status(), &mut []), Err(FrameError::BufferTooSmall));
    // The longest request fits.
    let worst = Request::Move { mode: MoveMode::Absolute, targets: [Some(i32::MIN); 3] };
    assert!(encode_flushed_frame(1, &worst, &mut scratch).unwrap() <= MAX_FLUSHED_FRAME_LEN);
    // Noise turns the delimiter of the frame before into a data byte: that
    // frame is lost, the flushed one after it is not; without its leading
    // `0x00` it would be lost too.
    let mut before = encode(4, &Request::Ping { token: 1 });
    *before.last_mut().unwrap() = 0x42;
    let mut stream = before.clone();
    stream.extend_from_slice(&flushed[..n]);
    let frames: Vec<_> = FrameDecoder::<Request>::new().feed(&stream).collect();
    assert_eq!(frames.len(), 2);
    assert!(frames[0].is_err());
    assert_eq!(frames[1], Ok(Frame { seq: 5, msg: status() }));
    let mut bare = before;
    bare.extend_from_slice(&flushed[1..n]);
    let frames: Vec<_> = FrameDecoder::<Request>::new().feed(&bare).collect();
    assert_eq!(frames.len(), 1);
    assert!(frames[0].is_err());
}

#[test]
fn each_rejection_is_typed() {
    let good = encode(3, &Request::Ping { token: 7 });
    let body = &good[..good.len() - 1];

    let mut crc_bad = body.to_vec();
    let last = crc_bad.len() - 1;
    crc_bad[last] ^= 0x01;
    if crc_bad[last] == 0 {
        crc_bad[last] = 0x02;
    }
    assert_eq!(decode_frame::<Request>(&mut crc_bad), Err(FrameError::Crc));

    assert_eq!(decode_frame::<Request>(&mut [0x03, 0x01, 0x02]), Err(FrameError::TooShort));
    assert_eq!(decode_frame::<Request>(&mut [0x09, 0x01]), Err(FrameError::Cobs));

    // A valid CRC around an unknown request index: a newer peer's message.
    let mut raw = vec![0x05, 0x7F];
    raw.extend_from_slice(&CRC.checksum(&raw).to_le_bytes());
    let mut cobs_buf = vec![0u8; 16];
    let n = cobs::encode(&raw, &mut cobs_buf);
    assert_eq!(decode_frame::<Request>(&mut cobs_buf[..n]), Err(FrameError::Payload));

    // Trailing bytes after a complete message are refused too.
    let mut raw = vec![0x05, 0x02, 0x00];
    raw.extend_from_slice(&CRC.checksum(&raw).to_le_bytes());
    let n = cobs::encode(&raw, &mut cobs_buf);
    assert_eq!(decode_frame::<Request>(&mut cobs_buf[..n]), Err(FrameError::Payload));

    let mut tiny = [0u8; 4];
    assert_eq!(encode_frame(0, &Request::GetStatus, &mut tiny), Err(FrameError::BufferTooSmall));
}

#[test]
fn log_text_truncates_at_char_boundary() {
    let long = "é".repeat(40); // 80 bytes
    let t = LogText::truncated(&long);
    assert_eq!(t.as_str().len(), 48);
    assert!(t.as_str().chars().all(|c| c == 'é'));
    round_trip(1, &ToHost::Event(Event::Log { level: LogLevel::Info, text: t }));
}

#[test]
fn axis_set_operations() {
    let s = AxisSet::single(Axis::Track).with(Axis::Tilt);
    assert!(s.contains(Axis::Tilt) && !s.contains(Axis::Disk));
    assert_eq!(s.iter().collect::<Vec<_>>(), vec![Axis::Track, Axis::Tilt]);
    assert!(s.is_valid() && !AxisSet(0x08).is_valid());
    assert_eq!(
        FaultFlags(0b101).names().collect::<Vec<_>>(),
        ["emergency stop", "home switch hit far from home"]
    );
    // Every defined capability has a name; an unknown bit is left out.
    let caps = Capabilities::EXPOSURE_STROBE.union(Capabilities::SYSTEM_BOOTLOADER);
    assert_eq!(
        Capabilities(caps.0 | 1 << 15).names().collect::<Vec<_>>(),
        ["exposure strobe input", "ROM bootloader on command"]
    );
    assert_eq!(Capabilities(0x7f).names().count(), 7);
    assert_eq!(
        MotionOutcome::HomingFailed(Axis::Track, HomingFailure::SwitchStuck).to_string(),
        "failed on the track axis: its switch stayed pressed after backing off"
    );
}
