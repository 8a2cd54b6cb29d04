//! The board's queue of frames for the host (`firmware::usb::queue_whole`)
//! on the `embassy_sync::Pipe` the board uses, drained in USB packets.

use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::pipe::Pipe;
use firmware::usb::{MAX_PACKET, queue_whole};
use protocol::{
    Event, FrameDecoder, LogLevel, LogText, MAX_FLUSHED_FRAME_LEN, ToHost, encode_flushed_frame,
};

fn log_frame(seq: u8, text: &str) -> Vec<u8> {
    let msg = ToHost::Event(Event::Log { level: LogLevel::Info, text: LogText::truncated(text) });
    let mut buf = [0u8; MAX_FLUSHED_FRAME_LEN];
    let n = encode_flushed_frame(seq, &msg, &mut buf).unwrap();
    buf[..n].to_vec()
}

fn drain<const N: usize>(pipe: &Pipe<CriticalSectionRawMutex, N>, out: &mut Vec<u8>) {
    let mut packet = [0u8; MAX_PACKET as usize];
    while let Ok(n) = pipe.try_read(&mut packet) {
        out.extend_from_slice(&packet[..n]);
    }
}

#[test]
fn a_frame_across_the_end_of_the_ring_is_queued_whole() {
    let pipe = Pipe::<CriticalSectionRawMutex, 64>::new();
    // Move the ring's positions to 40 of 64, empty.
    assert!(queue_whole(&pipe, &[7; 40]));
    let mut out = Vec::new();
    drain(&pipe, &mut out);
    assert_eq!(out.len(), 40);
    let frame = log_frame(3, "a frame longer than the 24 bytes left");
    assert!(frame.len() > 24 && frame.len() <= 64);
    // One `try_write` takes only the 24 bytes up to the ring's end.
    let probe = Pipe::<CriticalSectionRawMutex, 64>::new();
    probe.try_write(&[7; 40]).unwrap();
    drain(&probe, &mut Vec::new());
    assert_eq!(probe.try_write(&frame), Ok(24));
    assert!(queue_whole(&pipe, &frame));
    out.clear();
    drain(&pipe, &mut out);
    assert_eq!(out, frame);
}

#[test]
fn a_frame_that_does_not_fit_is_dropped_whole() {
    let pipe = Pipe::<CriticalSectionRawMutex, 64>::new();
    let frame = log_frame(1, "twenty-odd characters of text");
    assert!(queue_whole(&pipe, &frame));
    assert!(!queue_whole(&pipe, &frame), "{} + {} bytes > 64", frame.len(), frame.len());
    assert_eq!(pipe.len(), frame.len());
}

/// Frames of every length through the board's 1 KiB queue, drained a
/// packet at a time at an uneven pace: each arrives, in order.
#[test]
fn every_frame_arrives_through_many_turns_of_the_ring() {
    let pipe = Pipe::<CriticalSectionRawMutex, { firmware::hal::USB_TX_QUEUE }>::new();
    let text = "0123456789abcdefghijklmnopqrstuvwxyz0123456789ABCDEFGHIJKLMNOP";
    let mut sent = Vec::new();
    let mut wire = Vec::new();
    let mut packet = [0u8; MAX_PACKET as usize];
    for i in 0..2000usize {
        let frame = log_frame(i as u8, &text[..i % text.len()]);
        if queue_whole(&pipe, &frame) {
            sent.push(i);
        }
        for _ in 0..i % 3 {
            if let Ok(n) = pipe.try_read(&mut packet) {
                wire.extend_from_slice(&packet[..n]);
            }
        }
    }
    drain(&pipe, &mut wire);
    assert!(sent.len() > 1500, "{} of 2000 queued", sent.len());
    assert!(wire.len() > 20 * 1024, "{} bytes: the ring turned many times", wire.len());
    let mut decoder = FrameDecoder::<ToHost>::new();
    let received: Vec<_> = decoder.feed(&wire).collect::<Result<_, _>>().expect("no frame cut");
    assert_eq!(received.len(), sent.len());
    for (frame, &i) in received.iter().zip(&sent) {
        assert_eq!(frame.seq, i as u8);
        let ToHost::Event(Event::Log { text: t, .. }) = &frame.msg else { panic!("a log") };
        assert_eq!(t.as_str(), LogText::truncated(&text[..i % text.len()]).as_str());
    }
}
