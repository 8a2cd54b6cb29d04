//! The `hil-sim` binary: prints the pty path, serves the protocol on it, and
//! refuses bad options with a clear message.

use std::io::{BufRead, BufReader, Read, Write};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use protocol::*;

#[test]
fn serves_on_the_printed_pty_until_killed() {
    let mut child = Command::new(env!("CARGO_BIN_EXE_hil-sim"))
        .args(["--seed", "3"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let path = line.trim().to_string();
    assert!(path.starts_with("/dev/"), "prints the pty path first: {path:?}");

    let mut port =
        serialport::new(&path, 115_200).timeout(Duration::from_millis(50)).open().unwrap();
    let mut frame = [0u8; MAX_FRAME_LEN];
    let n =
        encode_frame(7, &Request::Hello { host_protocol: PROTOCOL_VERSION }, &mut frame).unwrap();
    port.write_all(&frame[..n]).unwrap();
    let mut decoder = FrameDecoder::<ToHost>::new();
    let mut buf = [0u8; 256];
    let started = Instant::now();
    let mut answered = false;
    while !answered && started.elapsed() < Duration::from_secs(5) {
        let got = match port.read(&mut buf) {
            Ok(n) => n,
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => 0,
            Err(e) => panic!("{e}"),
        };
        answered = decoder
            .feed(&buf[..got])
            .flatten()
            .any(|f| f.seq == 7 && matches!(f.msg, ToHost::Reply(Reply::Info(_))));
    }
    child.kill().unwrap();
    let _ = child.wait();
    assert!(answered, "the simulated controller answered the handshake");
}

#[test]
fn bad_options_are_refused() {
    let out = Command::new(env!("CARGO_BIN_EXE_hil-sim"))
        .args(["--fault", "explode@ms=1"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("unknown kind"));
    let out =
        Command::new(env!("CARGO_BIN_EXE_hil-sim")).args(["--corrupt", "1.5"]).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
}
