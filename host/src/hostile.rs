//! A device that answers whatever its bytes say: the host's link under input
//! it did not create — a foreign or buggy firmware, a stream corrupted in a
//! way the CRC let through, a board that resets or unplugs at any moment.
//!
//! [`HostileDevice`] is a [`Transport`] on a simulated clock. It decodes the
//! host's frames like a board and, for each, lets its bytes choose: the
//! right reply (with any field values), any message at all with the right
//! or a wrong sequence number, silence, line noise, a flood of events, a
//! reset (a `Boot` event, then `NoHandshake` until greeted again) or an
//! unplug (reconnecting may fail a while); replies come after any delay up
//! to 100 ms. Its bytes spent, it falls silent. [`exercise`] drives a
//! [`Device`] through what the capture does with one — handshake, status,
//! homing and waiting for its end, capture steps and their trigger and
//! exposure reports, keep-alive, a check for a reset — and returns the
//! simulated time it took: whatever the device says, the host must answer
//! with a value or an error, never a panic, and within bounded time.
//!
//! Used by a seeded test here and by `fuzz/fuzz_targets/device_link.rs`
//! (feature `hostile-device`).

use std::collections::VecDeque;
use std::time::Duration;

use arbitrary::{Arbitrary, Unstructured};
use protocol::{
    AxisSet, CaptureStep, DeviceError, Event, FrameDecoder, MAX_FLUSHED_FRAME_LEN,
    PROTOCOL_VERSION, Reply, Request, StrobeConfig, ToHost, TriggerFired, encode_flushed_frame,
};

use crate::link::{Device, LinkTimings, Transport, TransportError};

/// The longest a hostile device delays a reply.
const MAX_DELAY_MS: u64 = 100;

/// A device whose answers are drawn from bytes. See the module docs.
#[derive(Debug)]
pub struct HostileDevice {
    bytes: Vec<u8>,
    at: usize,
    now: Duration,
    decoder: FrameDecoder<Request>,
    /// (readable at, bytes), in order of time.
    outbox: VecDeque<(Duration, Vec<u8>)>,
    connected: bool,
    handshake: bool,
}

impl HostileDevice {
    /// A device that answers as `bytes` say.
    pub fn new(bytes: Vec<u8>) -> HostileDevice {
        HostileDevice {
            bytes,
            at: 0,
            now: Duration::ZERO,
            decoder: FrameDecoder::new(),
            outbox: VecDeque::new(),
            connected: true,
            handshake: false,
        }
    }

    fn spent(&self) -> bool {
        self.at >= self.bytes.len()
    }

    fn byte(&mut self) -> u8 {
        let b = self.bytes.get(self.at).copied().unwrap_or(0);
        self.at += 1;
        b
    }

    /// A value drawn from the bytes (`None` once they are spent).
    fn draw<T: for<'a> Arbitrary<'a>>(&mut self) -> Option<T> {
        let rest = self.bytes.get(self.at..).unwrap_or(&[]);
        let mut u = Unstructured::new(rest);
        let value = T::arbitrary(&mut u).ok();
        self.at = self.bytes.len() - u.len();
        value
    }

    /// Queue `msg` framed as the board frames it, `delay` from now.
    fn send(&mut self, seq: u8, msg: &ToHost, delay: Duration) {
        let mut buf = [0u8; MAX_FLUSHED_FRAME_LEN];
        if let Ok(n) = encode_flushed_frame(seq, msg, &mut buf) {
            self.queue(buf[..n].to_vec(), delay);
        }
    }

    fn queue(&mut self, bytes: Vec<u8>, delay: Duration) {
        // Readable in order: never before what is queued already.
        let at = (self.now + delay).max(self.outbox.back().map_or(Duration::ZERO, |b| b.0));
        self.outbox.push_back((at, bytes));
    }

    /// The reply a board would give `request`, any field values.
    fn natural_reply(&mut self, request: &Request) -> Reply {
        if !self.handshake && !matches!(request, Request::Hello { .. }) {
            return Reply::Error(DeviceError::NoHandshake);
        }
        let drawn = |d: &mut Self, fallback: Reply| d.draw::<Reply>().unwrap_or(fallback);
        match request {
            Request::Hello { .. } => {
                self.handshake = true;
                match self.draw::<protocol::DeviceInfo>() {
                    // Mostly a version the host speaks, so that the rest is
                    // reached.
                    Some(mut info) => {
                        if !self.byte().is_multiple_of(8) {
                            info.protocol = PROTOCOL_VERSION;
                        }
                        Reply::Info(info)
                    }
                    None => Reply::Error(DeviceError::Busy),
                }
            }
            Request::Ping { token } => Reply::Pong { token: *token },
            Request::GetStatus => match self.draw() {
                Some(s) => Reply::Status(s),
                None => Reply::Ack,
            },
            Request::GetLastTrigger => Reply::Trigger(self.draw().flatten()),
            Request::GetStrobe => match self.draw() {
                Some(s) => Reply::Strobe(s),
                None => Reply::Ack,
            },
            _ if self.byte().is_multiple_of(4) => drawn(self, Reply::Ack),
            _ => Reply::Ack,
        }
    }

    /// What the device does about one request from the host.
    fn answer(&mut self, seq: u8, request: Request) {
        if self.spent() {
            return;
        }
        let choice = self.byte() % 16;
        let delay = Duration::from_millis(self.byte() as u64 * MAX_DELAY_MS / 255);
        match choice {
            0..=6 => {
                let reply = self.natural_reply(&request);
                self.send(seq, &ToHost::Reply(reply), delay);
            }
            7 | 8 => {
                if let Some(msg) = self.draw::<ToHost>() {
                    self.send(seq, &msg, delay);
                }
            }
            9 => {
                if let Some((s, msg)) = self.draw::<(u8, ToHost)>() {
                    self.send(s, &msg, delay);
                }
            }
            10 => {} // lost
            11 => {
                let n = self.byte() as usize;
                let start = self.at.min(self.bytes.len());
                let end = (start + n).min(self.bytes.len());
                let noise = self.bytes[start..end].to_vec();
                self.at = end;
                self.queue(noise, delay);
            }
            12 => {
                // A reset: the board greets with its new boot, and wants a
                // handshake again.
                self.handshake = false;
                let boot_id = self.draw::<u32>().unwrap_or(0);
                let reason = self.draw().unwrap_or(protocol::ResetReason::Software);
                self.send(0, &ToHost::Event(Event::Boot { boot_id, reason }), delay);
            }
            13 => self.connected = false,
            _ => {
                for _ in 0..self.byte() % 8 {
                    if let Some(e) = self.draw::<Event>() {
                        let s = self.byte();
                        self.send(s, &ToHost::Event(e), delay);
                    }
                }
                let reply = self.natural_reply(&request);
                self.send(seq, &ToHost::Reply(reply), delay);
            }
        }
    }
}

impl Transport for HostileDevice {
    fn write_all(&mut self, bytes: &[u8]) -> Result<(), TransportError> {
        if !self.connected {
            return Err(TransportError::Disconnected("the hostile device unplugged".into()));
        }
        let frames: Vec<_> = self.decoder.feed(bytes).flatten().collect();
        for frame in frames {
            self.answer(frame.seq, frame.msg);
        }
        Ok(())
    }

    fn read(&mut self, out: &mut Vec<u8>, timeout: Duration) -> Result<usize, TransportError> {
        if !self.connected {
            return Err(TransportError::Disconnected("the hostile device unplugged".into()));
        }
        let until = self.now + timeout;
        match self.outbox.front() {
            Some(&(at, _)) if at <= until => self.now = self.now.max(at),
            _ => {
                self.now = until;
                return Ok(0);
            }
        }
        let mut n = 0;
        while self.outbox.front().is_some_and(|(at, _)| *at <= self.now) {
            let (_, bytes) = self.outbox.pop_front().expect("a front");
            n += bytes.len();
            out.extend_from_slice(&bytes);
        }
        Ok(n)
    }

    fn sleep(&mut self, d: Duration) {
        self.now += d;
    }

    fn now(&self) -> Duration {
        self.now
    }

    fn reconnect(&mut self) -> Result<(), TransportError> {
        if self.spent() || self.byte().is_multiple_of(4) {
            return Err(TransportError::Open("the hostile device is not back".into()));
        }
        self.connected = true;
        self.outbox.clear();
        self.decoder = FrameDecoder::new();
        Ok(())
    }

    fn describe(&self) -> String {
        "a hostile device".into()
    }
}

/// Drive a [`Device`] on a [`HostileDevice`] of `bytes` through what a
/// capture does with one; the simulated time it took. Every call may fail
/// (that is the device's right); none may panic or hang.
pub fn exercise(bytes: Vec<u8>) -> Duration {
    let device = HostileDevice::new(bytes);
    // The default timings, but a lost device is given up sooner.
    let timings = LinkTimings { reconnect_for: Duration::from_secs(2), ..LinkTimings::default() };
    let mut dev = match Device::connect_with(Box::new(device), timings) {
        Ok(dev) => dev,
        Err(e) => {
            let _ = e.to_string();
            return Duration::ZERO;
        }
    };
    let _ = format!("{:?} {}", dev.info(), dev.describe());
    let motion_done = |e: &Event| matches!(e, Event::MotionDone { .. });
    for round in 0..4 {
        let _ = dev.status().map(|s| format!("{s:?}"));
        let _ = dev.command(Request::Home { axes: AxisSet::ALL });
        let _ = dev.wait_event(Duration::from_secs(2), motion_done);
        let step = CaptureStep {
            mirror: round,
            settle_ms: 10,
            exposure_us: 20_000,
            light_duty_permille: 1000,
        };
        dev.clear_events();
        if dev.command(Request::CaptureStep(step)).is_ok() {
            let fired =
                dev.wait_event(Duration::from_secs(2), |e| matches!(e, Event::TriggerFired(_)));
            if let Ok(Some(Event::TriggerFired(fired))) = fired {
                report_exposure(&mut dev, &fired);
            }
        }
        if let Ok(Reply::Trigger(Some(t))) = dev.request(Request::GetLastTrigger) {
            report_exposure(&mut dev, &t);
        }
        let _ = dev.sleep(Duration::from_millis(120));
        let _ = dev.check_boot().map_err(|e| e.to_string());
        let _ = dev.take_events();
    }
    dev.now()
}

/// The strobe's report on a pulse, as the capture asks for it.
fn report_exposure(dev: &mut Device, fired: &TriggerFired) {
    if let Ok(Some(strobe)) = crate::strobe::watched(dev) {
        let _ = crate::strobe::report(dev, fired, &strobe);
    } else {
        let strobe = StrobeConfig { enabled: true, active_high: true, max_delay_us: 10_000 };
        let _ = crate::strobe::report(dev, fired, &strobe);
    }
}

#[cfg(test)]
mod tests {
    use rand::{RngCore, SeedableRng};

    use super::*;

    /// Whatever a device says, the host's link answers with a value or an
    /// error in bounded time: 3 000 devices of random bytes (and their
    /// first bytes a sensible start, so that most get past the handshake).
    #[test]
    fn the_link_survives_any_device() {
        let mut longest = Duration::ZERO;
        let mut connected = 0;
        for seed in 0..3_000u64 {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
            let mut bytes = vec![0u8; 64 + (rng.next_u32() % 4096) as usize];
            rng.fill_bytes(&mut bytes);
            let took = exercise(bytes);
            connected += usize::from(took > Duration::ZERO);
            longest = longest.max(took);
        }
        assert!(connected > 1_000, "{connected} of 3 000 got past the handshake");
        assert!(longest < Duration::from_secs(600), "{longest:?}");
    }
}
