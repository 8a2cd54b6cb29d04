//! The `hil-sim` binary: prints the pty path, serves the protocol on it, and
//! refuses bad options with a clear message.

mod common;

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::Duration;

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
    let answered = common::handshake_over_serial(port.as_mut(), 7).is_some();
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
