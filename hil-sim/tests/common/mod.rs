//! A minimal protocol client over the deterministic link, for the simulator's
//! own tests (the host crate has the real one).
#![allow(dead_code)]

use std::time::Duration;

use hil_sim::{LinkError, SimConfig, SimDevice, SimLink};
use protocol::*;

pub struct Client {
    pub link: SimLink,
    seq: u8,
    decoder: FrameDecoder<ToHost>,
    /// Every event received, in order.
    pub events: Vec<Event>,
    /// Every byte received (for determinism checks).
    pub received: Vec<u8>,
    replies: Vec<(u8, Reply)>,
    pub retransmissions: u32,
    /// Events before this index came before the last command.
    mark: usize,
}

impl Client {
    pub fn new(config: SimConfig) -> Client {
        Client {
            link: SimLink::new(SimDevice::new(config)),
            seq: 0,
            decoder: FrameDecoder::new(),
            events: Vec::new(),
            received: Vec::new(),
            replies: Vec::new(),
            retransmissions: 0,
            mark: 0,
        }
    }

    /// Read for up to `timeout`, dispatching frames; true if anything came.
    fn pump(&mut self, timeout: Duration) -> bool {
        let mut buf = Vec::new();
        match self.link.read(&mut buf, timeout) {
            Ok(0) | Err(LinkError::Disconnected) => false,
            Ok(_) => {
                self.received.extend_from_slice(&buf);
                for frame in self.decoder.feed(&buf).flatten() {
                    match frame.msg {
                        ToHost::Reply(r) => self.replies.push((frame.seq, r)),
                        ToHost::Event(e) => self.events.push(e),
                    }
                }
                true
            }
        }
    }

    /// Send a request and wait for its reply, retransmitting the same frame
    /// every 30 ms of device time (up to 100 times, across disconnects).
    pub fn request(&mut self, request: Request) -> Reply {
        if !matches!(request, Request::Ping { .. } | Request::GetStatus) {
            // Later waits look for what this command causes.
            self.mark = self.events.len();
        }
        self.seq = self.seq.wrapping_add(1);
        let seq = self.seq;
        let mut frame = [0u8; MAX_FRAME_LEN];
        let n = encode_frame(seq, &request, &mut frame).unwrap();
        for attempt in 0..100 {
            if attempt > 0 {
                self.retransmissions += 1;
            }
            if self.link.write(&frame[..n]).is_err() {
                self.link.sleep(Duration::from_millis(30));
                continue;
            }
            let deadline = self.link.now() + 30 * firmware::hal::TICKS_PER_MS;
            while self.link.now() < deadline {
                self.pump(Duration::from_millis(5));
                if let Some(i) = self.replies.iter().position(|(s, _)| *s == seq) {
                    let (_, reply) = self.replies.remove(i);
                    self.replies.clear();
                    return reply;
                }
            }
        }
        panic!("no reply to {request:?}");
    }

    pub fn hello(&mut self) -> DeviceInfo {
        match self.request(Request::Hello { host_protocol: PROTOCOL_VERSION }) {
            Reply::Info(info) => info,
            other => panic!("handshake: {other:?}"),
        }
    }

    pub fn status(&mut self) -> Status {
        match self.request(Request::GetStatus) {
            Reply::Status(s) => s,
            other => panic!("status: {other:?}"),
        }
    }

    /// Wait (pinging every 100 ms) until an event since the last command
    /// matches, at most `max`.
    pub fn wait_event(&mut self, max: Duration, pred: impl Fn(&Event) -> bool) -> Option<Event> {
        let end = self.link.now() + (max.as_millis() as u64) * firmware::hal::TICKS_PER_MS;
        let mut seen = self.mark;
        while self.link.now() < end {
            while seen < self.events.len() {
                if pred(&self.events[seen]) {
                    return Some(self.events[seen].clone());
                }
                seen += 1;
            }
            self.pump(Duration::from_millis(100));
            let _ = self.request(Request::Ping { token: 0 });
        }
        None
    }

    /// Wait until the device is idle (status polled every 50 ms).
    pub fn wait_idle(&mut self, max: Duration) -> Status {
        let end = self.link.now() + (max.as_millis() as u64) * firmware::hal::TICKS_PER_MS;
        loop {
            let s = self.status();
            if s.state == DeviceState::Idle
                || s.state == DeviceState::Faulted
                || self.link.now() >= end
            {
                return s;
            }
            self.link.sleep(Duration::from_millis(50));
        }
    }

    pub fn home_all(&mut self) {
        assert_eq!(self.request(Request::Home { axes: AxisSet::ALL }), Reply::Ack);
        let done = self
            .wait_event(Duration::from_secs(60), |e| matches!(e, Event::MotionDone { .. }))
            .expect("homing ends");
        assert!(
            matches!(done, Event::MotionDone { outcome: MotionOutcome::Completed, .. }),
            "homing: {done:?}"
        );
    }
}

/// The default scanner's mirror table from its inverse kinematics.
pub fn mirror_table() -> Vec<MirrorPosition> {
    let g = hil_sim::geometry::ScannerGeometry::default_scanner();
    g.mirror_table(&hil_sim::camera::default_axes()).unwrap()
}

pub fn load_mirror_table(client: &mut Client) -> Vec<MirrorPosition> {
    let table = mirror_table();
    for (l, position) in table.iter().enumerate() {
        assert_eq!(
            client.request(Request::SetMirror { mirror: l as u8, position: *position }),
            Reply::Ack
        );
    }
    assert_eq!(client.request(Request::SetMirrorCount { count: 40 }), Reply::Ack);
    table
}

/// One capture step per mirror; returns the TriggerFired events.
pub fn capture_all(client: &mut Client, mirrors: usize) -> Vec<TriggerFired> {
    let mut fired = Vec::new();
    for l in 0..mirrors as u8 {
        let step = CaptureStep {
            mirror: l,
            settle_ms: DEFAULT_SETTLE_MS,
            exposure_us: DEFAULT_EXPOSURE_US,
            light_duty_permille: FULL_DUTY_PERMILLE,
        };
        assert_eq!(client.request(Request::CaptureStep(step)), Reply::Ack, "capture {l}");
        // Events are not retransmitted: one lost on a noisy link is asked
        // for (as the host does).
        let event = client.wait_event(
            Duration::from_secs(10),
            |e| matches!(e, Event::TriggerFired(t) if t.mirror == Some(l)),
        );
        let t = match event {
            Some(Event::TriggerFired(t)) => t,
            _ => match client.request(Request::GetLastTrigger) {
                Reply::Trigger(Some(t)) if t.mirror == Some(l) => t,
                other => panic!("trigger for mirror {l}: {other:?}, {:?}", client.events),
            },
        };
        fired.push(t);
        let s = client.wait_idle(Duration::from_secs(2));
        assert_eq!(s.state, DeviceState::Idle, "after mirror {l}");
    }
    fired
}

/// Send `Hello` with sequence number `seq` over a serial port (a pty) and
/// wait up to 5 s of wall time for the `Info` reply.
pub fn handshake_over_serial(port: &mut dyn serialport::SerialPort, seq: u8) -> Option<DeviceInfo> {
    let mut frame = [0u8; MAX_FRAME_LEN];
    let n =
        encode_frame(seq, &Request::Hello { host_protocol: PROTOCOL_VERSION }, &mut frame).unwrap();
    port.write_all(&frame[..n]).unwrap();
    let mut decoder = FrameDecoder::<ToHost>::new();
    let mut buf = [0u8; 256];
    let started = std::time::Instant::now();
    while started.elapsed() < Duration::from_secs(5) {
        let got = match port.read(&mut buf) {
            Ok(n) => n,
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => 0,
            Err(e) => panic!("{e}"),
        };
        for f in decoder.feed(&buf[..got]).flatten() {
            if let (true, ToHost::Reply(Reply::Info(info))) = (f.seq == seq, f.msg) {
                return Some(info);
            }
        }
    }
    None
}
