//! The whole simulated scanner in one process, deterministic: the board
//! (behind its [`SimLink`]) and the camera wired to its trigger output share
//! one simulated clock. Time passes only while the host waits (reads,
//! sleeps, waits for a frame), so a run is reproducible bit for bit.
//!
//! The host drives it through two handles, as it would a real scanner and a
//! real camera: bytes in and out ([`SimRig::write`], [`SimRig::read`]) and
//! frames ([`SimRig::wait_frame`]).

use std::collections::VecDeque;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use firmware::hal::TICK_HZ;

use crate::camera::SimCamera;
use crate::device::{SimConfig, SimDevice};
use crate::link::{LinkError, SimLink};
use crate::optics::{Frame, OpticalSim};

#[derive(Debug)]
struct Inner {
    link: SimLink,
    camera: SimCamera,
    frames: VecDeque<Frame>,
}

/// A simulated scanner and camera; clones share it.
#[derive(Debug, Clone)]
pub struct SimRig {
    inner: Arc<Mutex<Inner>>,
}

impl SimRig {
    /// Power on a simulated scanner with `optics` behind its camera.
    pub fn new(config: SimConfig, optics: OpticalSim) -> SimRig {
        let inner = Inner {
            camera: SimCamera::new(optics)
                .with_trigger_latency(config.trigger_latency_us)
                .with_axes(config.axes),
            link: SimLink::new(SimDevice::new(config)),
            frames: VecDeque::new(),
        };
        SimRig { inner: Arc::new(Mutex::new(inner)) }
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        // A panic elsewhere cannot leave the simulation half-updated in a way
        // that matters to a reader: keep going.
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Send bytes to the board.
    pub fn write(&self, bytes: &[u8]) -> Result<(), LinkError> {
        self.lock().link.write(bytes)
    }

    /// Wait up to `timeout` (simulated) for bytes from the board.
    pub fn read(&self, out: &mut Vec<u8>, timeout: Duration) -> Result<usize, LinkError> {
        self.lock().link.read(out, timeout)
    }

    /// Whether the simulated cable is connected now.
    pub fn is_connected(&self) -> bool {
        self.lock().link.is_connected()
    }

    /// Let simulated time pass.
    pub fn sleep(&self, d: Duration) {
        self.lock().link.sleep(d)
    }

    /// Simulated time since power-on.
    pub fn now(&self) -> Duration {
        let ticks = self.lock().link.now();
        Duration::from_nanos((ticks as u128 * 1_000_000_000 / TICK_HZ as u128) as u64)
    }

    /// Forget frames not yet taken and exposures not yet rendered (the
    /// camera is re-armed: anything older is stale).
    pub fn arm_camera(&self) {
        let mut g = self.lock();
        let Inner { link, camera, frames } = &mut *g;
        camera.take_exposures(link.device().truth());
        frames.clear();
    }

    /// The next frame, rendered when its trigger pulse has ended; `None`
    /// after `timeout` of simulated time without one.
    pub fn wait_frame(&self, timeout: Duration) -> Option<Frame> {
        let end = self.now() + timeout;
        loop {
            {
                let mut g = self.lock();
                let Inner { link, camera, frames } = &mut *g;
                frames.extend(camera.collect(link.device().truth()).into_iter().map(|(_, f)| f));
                if let Some(f) = frames.pop_front() {
                    return Some(f);
                }
            }
            if self.now() >= end {
                return None;
            }
            self.sleep(Duration::from_millis(10));
        }
    }

    /// Run `f` on the simulated board (tests and benchmarks: physical truth).
    pub fn with_device<R>(&self, f: impl FnOnce(&mut SimDevice) -> R) -> R {
        f(self.lock().link.device_mut())
    }

    /// The optics (ground truth; tests and benchmarks only).
    pub fn optics(&self) -> OpticalSim {
        self.lock().camera.optics().clone()
    }
}
