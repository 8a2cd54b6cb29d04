//! Golden bytes: every message type encodes to exactly the frame documented in
//! `docs/protocol.md` §8, and that frame decodes back to the message.

mod common;

use common::{Example, capture_step, examples, hex, status};
use protocol::*;

const DOC: &str = include_str!("../../docs/protocol.md");

/// The golden table of the doc: message name → (seq, frame bytes).
fn documented() -> Vec<(String, u8, Vec<u8>)> {
    let table = DOC.split("## 8. Golden frames").nth(1).expect("doc has §8");
    table
        .lines()
        .filter(|l| l.starts_with("| `"))
        .map(|l| {
            let cells: Vec<&str> = l.split('|').map(|c| c.trim().trim_matches('`')).collect();
            let bytes = cells[3]
                .split_whitespace()
                .map(|b| u8::from_str_radix(b, 16).expect("hex byte"))
                .collect();
            (cells[1].to_string(), cells[2].parse().expect("seq"), bytes)
        })
        .collect()
}

#[test]
fn every_example_encodes_to_its_documented_frame() {
    let doc = documented();
    let examples = examples();
    assert_eq!(doc.len(), examples.len(), "doc table and examples list differ in length");
    for (name, seq, example) in &examples {
        let (_, doc_seq, doc_bytes) = doc
            .iter()
            .find(|(n, _, _)| n == name)
            .unwrap_or_else(|| panic!("{name} missing from docs/protocol.md §8"));
        assert_eq!(doc_seq, seq, "{name}: seq");
        assert_eq!(hex(&example.encode(*seq)), hex(doc_bytes), "{name}: encoding");
    }
}

#[test]
fn every_documented_frame_decodes_to_its_example() {
    for (name, seq, example) in examples() {
        let (_, _, mut bytes) = documented().into_iter().find(|(n, _, _)| *n == name).unwrap();
        assert_eq!(bytes.pop(), Some(0), "{name}: ends with the delimiter");
        assert!(!bytes.contains(&0), "{name}: no zero inside a frame");
        match example {
            Example::ToDevice(m) => {
                let f: Frame<Request> = decode_frame(&mut bytes).unwrap();
                assert_eq!((f.seq, f.msg), (seq, m), "{name}");
            }
            Example::ToHost(m) => {
                let f: Frame<ToHost> = decode_frame(&mut bytes).unwrap();
                assert_eq!((f.seq, f.msg), (seq, m), "{name}");
            }
        }
    }
}

#[test]
fn examples_cover_every_variant() {
    // Adding a variant without a golden example fails here: the match must be
    // extended, and then the example list.
    let names: Vec<&str> = examples().iter().map(|(n, _, _)| *n).collect();
    let variant = |r: &Request| r.name();
    let requests = names.iter().filter(|n| n.starts_with("Request::")).count();
    assert_eq!(requests, 29);
    for (name, _, ex) in examples() {
        if let Example::ToDevice(r) = ex {
            assert_eq!(name, format!("Request::{}", variant(&r)));
        }
    }
    for prefix in [
        "Reply::Ack",
        "Reply::Error",
        "Reply::Info",
        "Reply::Status",
        "Reply::Mirror",
        "Reply::AxisConfig",
        "Reply::Pong",
        "Reply::Trigger",
        "Reply::BoardConfig",
        "Reply::HomeSensors",
        "Reply::Inputs",
        "Reply::Strobe",
        "Event::Boot",
        "Event::MotionDone",
        "Event::TriggerFired",
        "Event::FaultRaised",
        "Event::Log",
        "Event::PositionChecked",
        "Event::Exposure",
    ] {
        assert!(names.contains(&prefix), "no golden example for {prefix}");
    }
}

#[test]
fn hello_frame_by_hand() {
    // docs/protocol.md §7, byte by byte.
    let mut buf = [0u8; MAX_FRAME_LEN];
    let n = encode_frame(1, &Request::Hello { host_protocol: PROTOCOL_VERSION }, &mut buf).unwrap();
    assert_eq!(CRC.checksum(&[0x01, 0x00, 0x01, 0x05]), 0xB371_6D14);
    assert_eq!(&buf[..n], &[0x02, 0x01, 0x07, 0x01, 0x05, 0x14, 0x6d, 0x71, 0xb3, 0x00]);
}

#[test]
fn crc_is_crc32c() {
    assert_eq!(CRC.checksum(b"123456789"), 0xE306_9283);
}

#[test]
fn documented_sizes() {
    // docs/protocol.md §2 and the foundation issue's budgets.
    assert_eq!(Request::MAX_FRAME_LEN, 71);
    assert_eq!(ToHost::MAX_FRAME_LEN, 72);
    assert_eq!(MAX_FRAME_LEN, 72);
    assert!(Example::ToDevice(capture_step()).encode(200).len() <= 16);
    assert!(Example::ToHost(status()).encode(200).len() <= 64);
    // Worst case of a capture step: every varint at its documented maximum.
    let worst = Request::CaptureStep(CaptureStep {
        mirror: 63,
        settle_ms: u16::MAX,
        exposure_us: MAX_EXPOSURE_US,
        light_duty_permille: FULL_DUTY_PERMILLE,
    });
    assert!(Example::ToDevice(worst).encode(255).len() <= 17);
}

#[test]
fn version_check() {
    assert!(check_version(ProtocolVersion { major: 1, minor: 9 }).is_ok());
    let err = check_version(ProtocolVersion { major: 2, minor: 0 }).unwrap_err();
    assert!(err.to_string().contains("incompatible protocol"), "{err}");
}
