//! The host's own protocol client (`host::link::Device`: sequence numbers,
//! retransmission, keep-alive, reconnection, reset detection) driving the
//! simulated scanner, plus what the simulator's tests look at besides: every
//! byte received (determinism), every event in order, and the simulated
//! board's physical truth.
#![allow(dead_code)]

use std::sync::{Arc, Mutex};
use std::time::Duration;

use hil_sim::materials::Sample;
use hil_sim::optics::OpticalSim;
use hil_sim::{SimConfig, SimDevice, SimRig, materials};
use host::link::{Device, LinkError, SimTransport, Transport, TransportError};
use host::scan::MotionEnd;
use protocol::*;

/// The in-process transport, keeping a copy of every byte received.
struct Recording {
    inner: SimTransport,
    received: Arc<Mutex<Vec<u8>>>,
}

impl Transport for Recording {
    fn write_all(&mut self, bytes: &[u8]) -> Result<(), TransportError> {
        self.inner.write_all(bytes)
    }
    fn read(&mut self, out: &mut Vec<u8>, timeout: Duration) -> Result<usize, TransportError> {
        let start = out.len();
        let n = self.inner.read(out, timeout)?;
        self.received.lock().unwrap().extend_from_slice(&out[start..]);
        Ok(n)
    }
    fn sleep(&mut self, d: Duration) {
        self.inner.sleep(d)
    }
    fn now(&self) -> Duration {
        self.inner.now()
    }
    fn reconnect(&mut self) -> Result<(), TransportError> {
        self.inner.reconnect()
    }
    fn describe(&self) -> String {
        self.inner.describe()
    }
}

pub struct Client {
    /// The host's client, connected (handshake done).
    pub dev: Device,
    /// The simulated scanner (tests read its physical truth).
    pub rig: SimRig,
    received: Arc<Mutex<Vec<u8>>>,
    /// Events taken from the client so far, in arrival order except that an
    /// event a wait matched comes before those it skipped.
    pub events: Vec<Event>,
    /// Events before this index came before the last command.
    mark: usize,
}

impl Client {
    /// Power on a simulated scanner (its camera on the 8× binned sensor,
    /// looking at the white target) and connect to it.
    pub fn new(config: SimConfig) -> Client {
        let seed = config.seed;
        let nominal = hil_sim::geometry::ScannerGeometry::default_scanner().with_sensor_scaled(8);
        let white = Sample::small(materials::by_name("diffuse-white").expect("library material"));
        let rig = SimRig::new(config, OpticalSim::as_built(&nominal, white, seed));
        let received = Arc::new(Mutex::new(Vec::new()));
        let transport = Recording { inner: SimTransport(rig.clone()), received: received.clone() };
        let dev = Device::connect(Box::new(transport)).expect("handshake with the simulator");
        Client { dev, rig, received, events: Vec::new(), mark: 0 }
    }

    /// The handshake's answer.
    pub fn info(&self) -> DeviceInfo {
        *self.dev.info()
    }

    /// Every byte received so far.
    pub fn received(&self) -> Vec<u8> {
        self.received.lock().unwrap().clone()
    }

    /// Run `f` on the simulated board.
    pub fn device<R>(&self, f: impl FnOnce(&mut SimDevice) -> R) -> R {
        self.rig.with_device(f)
    }

    /// Simulated time, ticks.
    pub fn now_ticks(&self) -> u64 {
        self.device(|d| d.now())
    }

    /// Let simulated time pass without reading the link.
    pub fn sleep(&self, d: Duration) {
        self.rig.sleep(d)
    }

    fn log_events(&mut self) {
        self.events.extend(self.dev.take_events());
    }

    /// Forget the events received so far.
    pub fn clear_events(&mut self) {
        self.log_events();
        self.events.clear();
        self.mark = 0;
    }

    /// Send a request; the device's refusal comes back as `Reply::Error`,
    /// link failures panic.
    pub fn request(&mut self, request: Request) -> Reply {
        if !matches!(request, Request::Ping { .. } | Request::GetStatus) {
            // Later waits look for what this command causes.
            self.log_events();
            self.mark = self.events.len();
        }
        match self.dev.request(request) {
            Ok(reply) => reply,
            Err(LinkError::Refused { error, .. }) => Reply::Error(error),
            Err(e) => panic!("{request:?}: {e}"),
        }
    }

    pub fn status(&mut self) -> Status {
        self.dev.status().expect("status")
    }

    /// Wait (pinging as keep-alive) until an event since the last command
    /// matches, at most `max` of simulated time.
    pub fn wait_event(&mut self, max: Duration, pred: impl Fn(&Event) -> bool) -> Option<Event> {
        self.log_events();
        if let Some(e) = self.events[self.mark..].iter().find(|e| pred(e)) {
            return Some(e.clone());
        }
        let found = self.dev.wait_event(max, pred).expect("link");
        self.events.extend(found.clone());
        self.log_events();
        found
    }

    /// Wait until the device is idle or faulted (the host's own wait).
    pub fn wait_idle(&mut self, max: Duration) -> Status {
        let s = host::scan::wait_idle(&mut self.dev, max).expect("idle within the time");
        self.log_events();
        s
    }

    /// Home every axis and wait for the end as the host does
    /// (`host::scan::wait_motion_end`: noise can lose the `MotionDone`).
    pub fn home_all(&mut self) {
        assert_eq!(self.request(Request::Home { axes: AxisSet::ALL }), Reply::Ack);
        self.log_events();
        let end = host::scan::wait_motion_end(&mut self.dev, Duration::from_secs(60))
            .expect("link")
            .expect("homing ends");
        // The event first, then those it skipped (as `wait_event` logs them).
        if let MotionEnd::Reported { axes, outcome, positions } = end {
            self.events.push(Event::MotionDone { axes, outcome, positions });
        }
        self.log_events();
        match end {
            MotionEnd::Reported { outcome, .. } => {
                assert_eq!(outcome, MotionOutcome::Completed, "homing: {end:?}")
            }
            MotionEnd::Unreported(s) => {
                assert!(s.faults.is_empty() && s.axes.iter().all(|a| a.homed), "homing: {end:?}")
            }
        }
    }
}

/// Load the default scanner's mirror table as `scanner setup` does; returns it.
pub fn load_mirror_table(client: &mut Client) -> Vec<MirrorPosition> {
    let geometry = hil_sim::geometry::ScannerGeometry::default_scanner();
    let setup = host::scan::setup(&mut client.dev, &geometry).expect("mirror table loaded");
    assert_eq!(client.dev.info().mirror_count, 40);
    setup.table
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
        // for (as the host's scan does).
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

/// Connect the host's client to a serial port (a pty); the handshake's answer.
pub fn connect_over_serial(path: &str) -> Result<DeviceInfo, LinkError> {
    let transport =
        host::link::SerialTransport::open(path).map_err(|e| LinkError::NoDevice(e.to_string()))?;
    Ok(*Device::connect(Box::new(transport))?.info())
}
