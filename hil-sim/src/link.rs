//! Links between a host and the simulated device.
//!
//! - [`SimLink`]: in-process and deterministic. Simulated time advances only
//!   while the host waits for bytes ([`SimLink::read`]) or sleeps
//!   ([`SimLink::sleep`]), as fast as the CPU allows. Same seed, same run.
//! - [`PtyServer`]: a pseudo-terminal that the host opens like
//!   `/dev/ttyACM0`, with the device run in real time (or scaled).
//!
//! Both pass the bytes through [`LinkNoise`], the seeded byte-level fault
//! injector (bit flips, lost bytes, disconnects), in both directions.

use std::collections::VecDeque;
use std::io::{Read, Write};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use firmware::hal::{TICK_HZ, TICKS_PER_MS, USB_TX_PACKET, USB_TX_QUEUE, USB_TX_TIMEOUT_MS};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serialport::{SerialPort, TTYPort};

use std::path::{Path, PathBuf};

use crate::camera::{FrameFiles, SimCamera, drop_frame};
use crate::device::SimDevice;
use crate::faults::FaultEvent;
use crate::optics::Exposure;

/// The seeded byte-level fault injector of a link.
#[derive(Debug)]
pub struct LinkNoise {
    corrupt_rate: f64,
    drop_rate: f64,
    rng: ChaCha8Rng,
    disconnected_until: Option<u64>,
    /// Bytes corrupted and dropped so far (diagnostics).
    pub corrupted: u64,
    /// Bytes dropped so far.
    pub dropped: u64,
}

impl LinkNoise {
    /// Noise with the given per-byte rates.
    pub fn new(seed: u64, corrupt_rate: f64, drop_rate: f64) -> LinkNoise {
        LinkNoise {
            corrupt_rate,
            drop_rate,
            rng: ChaCha8Rng::seed_from_u64(seed ^ 0x4C49_4E4B),
            disconnected_until: None,
            corrupted: 0,
            dropped: 0,
        }
    }

    /// Pass `bytes` through the noise.
    pub fn mangle(&mut self, bytes: &[u8]) -> Vec<u8> {
        let mut out = Vec::with_capacity(bytes.len());
        for &b in bytes {
            if self.drop_rate > 0.0 && self.rng.random_bool(self.drop_rate) {
                self.dropped += 1;
                continue;
            }
            if self.corrupt_rate > 0.0 && self.rng.random_bool(self.corrupt_rate) {
                self.corrupted += 1;
                out.push(b ^ (1 << self.rng.random_range(0..8)));
            } else {
                out.push(b);
            }
        }
        out
    }

    fn apply(&mut self, events: Vec<(u64, FaultEvent)>) {
        for (at, event) in events {
            if let FaultEvent::Disconnect { duration_ms } = event {
                self.disconnected_until = Some(at + duration_ms * TICKS_PER_MS);
            }
        }
    }

    fn connected(&mut self, now: u64) -> bool {
        match self.disconnected_until {
            Some(until) if now < until => false,
            Some(_) => {
                self.disconnected_until = None;
                true
            }
            None => true,
        }
    }
}

/// The board's way out to the host (`firmware/board`): replies and events
/// queue as whole frames in [`USB_TX_QUEUE`] bytes (a frame that does not
/// fit is dropped whole), and leave in packets of [`USB_TX_PACKET`] bytes,
/// each of which waits at most [`USB_TX_TIMEOUT_MS`] for the host to take
/// it and is then dropped. The pty stands for the host's USB driver and its
/// tty buffer: while the host reads, nothing waits here; a host that stops
/// reading loses output as it would on the board, not at once.
#[derive(Debug, Default)]
pub struct UsbTx {
    queue: VecDeque<u8>,
    /// The rest of the packet being sent (bytes as the link delivers them).
    packet: Vec<u8>,
    /// Device time when that packet began to wait, ticks.
    waiting_since: u64,
    /// Frames dropped whole because the queue was full.
    pub frames_dropped: u64,
    /// Bytes of packets dropped after waiting too long (they cut frames: the
    /// host's decoder drops the cut frame at the next delimiter).
    pub packet_bytes_dropped: u64,
}

impl UsbTx {
    /// Queue the device's `output` (whole frames, each ending in the
    /// delimiter 0), each frame whole or not at all; `mangle` is what the
    /// wire does to its bytes.
    pub fn queue(&mut self, output: &[u8], mut mangle: impl FnMut(&[u8]) -> Vec<u8>) {
        for frame in output.split_inclusive(|&b| b == 0) {
            if USB_TX_QUEUE - self.queue.len() >= frame.len() {
                self.queue.extend(mangle(frame));
            } else {
                self.frames_dropped += 1;
            }
        }
    }

    /// Hand packets to `write` (which takes what the host side has room for:
    /// `Ok(n)`, or an error when it has none now) until it takes no more or
    /// nothing is queued; at device time `now` (ticks), drop a packet that
    /// has waited [`USB_TX_TIMEOUT_MS`]. With `connected` false nothing is
    /// written (a packet still times out). Returns the bytes dropped now.
    pub fn pump(
        &mut self,
        now: u64,
        connected: bool,
        mut write: impl FnMut(&[u8]) -> std::io::Result<usize>,
    ) -> usize {
        loop {
            if self.packet.is_empty() {
                let n = self.queue.len().min(USB_TX_PACKET);
                if n == 0 {
                    return 0;
                }
                self.packet.extend(self.queue.drain(..n));
                self.waiting_since = now;
            }
            if !connected {
                break;
            }
            match write(&self.packet) {
                Ok(n) if n > 0 => {
                    self.packet.drain(..n.min(self.packet.len()));
                }
                _ => break,
            }
        }
        if now.saturating_sub(self.waiting_since) >= USB_TX_TIMEOUT_MS * TICKS_PER_MS {
            let n = self.packet.len();
            self.packet_bytes_dropped += n as u64;
            self.packet.clear();
            // The next packet begins its wait at once, as on the board.
            let next = self.queue.len().min(USB_TX_PACKET);
            self.packet.extend(self.queue.drain(..next));
            self.waiting_since = now;
            return n;
        }
        0
    }

    /// Bytes waiting (queued and the packet's rest).
    pub fn pending(&self) -> usize {
        self.queue.len() + self.packet.len()
    }

    /// Forget what waits (the port is gone).
    pub fn discard(&mut self) {
        self.queue.clear();
        self.packet.clear();
    }
}

/// Why a link operation failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum LinkError {
    /// The device is disconnected (it may come back).
    #[error("the simulated device is disconnected")]
    Disconnected,
}

/// The deterministic in-process link.
#[derive(Debug)]
pub struct SimLink {
    device: SimDevice,
    noise: LinkNoise,
    inbox: VecDeque<u8>,
}

impl SimLink {
    /// A link to `device`, with the byte noise of the device's fault plan.
    pub fn new(device: SimDevice) -> SimLink {
        SimLink { noise: device.link_noise(), device, inbox: VecDeque::new() }
    }

    /// The device (tests read its physical truth here; hosts must not).
    pub fn device(&self) -> &SimDevice {
        &self.device
    }

    /// Mutable device access (tests).
    pub fn device_mut(&mut self) -> &mut SimDevice {
        &mut self.device
    }

    /// The link's noise counters.
    pub fn noise(&self) -> &LinkNoise {
        &self.noise
    }

    /// Device time, ticks.
    pub fn now(&self) -> u64 {
        self.device.now()
    }

    fn sync_faults(&mut self) {
        let events = self.device.take_link_faults();
        self.noise.apply(events);
    }

    /// Whether the link is up now.
    pub fn is_connected(&mut self) -> bool {
        self.sync_faults();
        let now = self.device.now();
        self.noise.connected(now)
    }

    /// Send bytes to the device (they arrive at the current device time).
    pub fn write(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        if !self.is_connected() {
            return Err(LinkError::Disconnected);
        }
        let bytes = self.noise.mangle(bytes);
        self.device.receive(&bytes);
        Ok(())
    }

    /// Wait up to `timeout` of device time for bytes from the device; appends
    /// them to `out` and returns how many (0 on timeout).
    pub fn read(&mut self, out: &mut Vec<u8>, timeout: Duration) -> Result<usize, LinkError> {
        let deadline = self.device.now() + duration_ticks(timeout);
        loop {
            if !self.is_connected() {
                // Time passes while the host waits for the device to return.
                let step = (self.device.now() + TICKS_PER_MS).min(deadline);
                self.device.advance_to(step);
                self.device.take_output(); // lost on the dead link
                return Err(LinkError::Disconnected);
            }
            let sent = self.device.take_output();
            self.inbox.extend(self.noise.mangle(&sent));
            if !self.inbox.is_empty() {
                let n = self.inbox.len();
                out.extend(self.inbox.drain(..));
                return Ok(n);
            }
            if self.device.now() >= deadline {
                return Ok(0);
            }
            let step = (self.device.now() + TICKS_PER_MS).min(deadline);
            self.device.advance_to(step);
        }
    }

    /// Let `duration` of device time pass without reading.
    pub fn sleep(&mut self, duration: Duration) {
        let end = self.device.now() + duration_ticks(duration);
        self.device.advance_to(end);
    }
}

/// Simulated time a board has run before its port appears: its inputs'
/// debounce and two input samples.
const BOOTED_TICKS: u64 =
    firmware::controller::DEBOUNCE_US * firmware::hal::TICKS_PER_US + 2 * crate::device::POLL_TICKS;

fn duration_ticks(d: Duration) -> u64 {
    (d.as_nanos() * TICK_HZ as u128 / 1_000_000_000) as u64
}

/// Simulated time of a [`PtyServer`]: `speed` × wall time, except that a
/// stretch of wall time the server's thread did not run (the machine busy
/// elsewhere) is not simulated in one step.
///
/// A real device's firmware runs all the time and sees each byte when it
/// arrives. The server's thread, descheduled for 200 ms, would find on waking
/// the host's keep-alive pings of that time in the pty and, had it caught up
/// with wall time first, hand them to a device that had already counted
/// 600 simulated ms of silence — a link timeout the hardware would not
/// have. So one step advances at most a tenth of the device's link timeout;
/// the rest of the stretch is dropped (the device seems to pause), and
/// simulated time runs on at `speed` from there.
#[derive(Debug, Clone, Copy)]
struct PtyClock {
    origin: u64,
    speed: f64,
    /// Simulated ticks dropped so far.
    dropped: u64,
}

impl PtyClock {
    /// The most simulated time one step advances.
    const MAX_STEP: u64 = firmware::controller::LINK_TIMEOUT_MS * TICKS_PER_MS / 10;

    fn new(origin: u64, speed: f64) -> PtyClock {
        PtyClock { origin, speed, dropped: 0 }
    }

    /// Where the device should be after `elapsed` wall time since the start,
    /// being at `now`.
    fn target(&mut self, now: u64, elapsed: Duration) -> u64 {
        let wall = (self.origin + duration_ticks(elapsed.mul_f64(self.speed)))
            .saturating_sub(self.dropped);
        let cap = now + Self::MAX_STEP;
        if wall > cap {
            self.dropped += wall - cap;
            cap
        } else {
            wall.max(now)
        }
    }
}

/// When the axes come to rest at a new place.
struct RestWatch {
    steps: [i64; 3],
    since: u64,
    reported: [i64; 3],
}

impl RestWatch {
    /// Simulated time the axes must keep still to be at rest.
    const STILL_TICKS: u64 = firmware::hal::TICK_HZ as u64 / 10;

    fn new(device: &SimDevice) -> RestWatch {
        let steps = protocol::Axis::ALL.map(|a| device.physical_position(a));
        RestWatch { steps, since: device.now(), reported: steps }
    }

    /// The axes' physical place, once, when they have come to rest
    /// somewhere other than where they were last reported.
    fn stopped(&mut self, device: &SimDevice) -> Option<scanner_geometry::AxisValues> {
        let steps = protocol::Axis::ALL.map(|a| device.physical_position(a));
        if steps != self.steps {
            (self.steps, self.since) = (steps, device.now());
            return None;
        }
        let still = device.now().saturating_sub(self.since) >= Self::STILL_TICKS;
        (still && steps != self.reported).then(|| {
            self.reported = steps;
            device.physical_axes()
        })
    }
}

/// What a [`PtyServer`] gives the host to open.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub enum Port {
    /// The pty itself (`/dev/pts/N`). It stays open through everything: a
    /// disconnect fault only silences the link, and a reset shows only as
    /// the board's `Boot` event.
    #[default]
    Pty,
    /// A USB board's port: a symbolic link to the current pty, as udev's
    /// `/dev/serial/by-id/…`, at the path given (`None`: in a temporary
    /// directory of the server's). The board unplugs as a USB device does:
    /// on a disconnect fault, for its duration; on a reset (watchdog or
    /// `Reset`), [`RESET_UNPLUG_MS`] after it (the bytes already sent are
    /// the host's to read) until [`REPLUG_MS`] after it, the boot and the
    /// enumeration; after `EnterBootloader`, for good (the chip's ROM
    /// enumerates as a DFU device, no serial port). Unplugged, the pty is
    /// closed — the host's reads and writes on it fail, as on a real
    /// unplug — and the link removed; plugged again, the link names a new
    /// pty. An existing path is replaced only if it is a symbolic link, and
    /// not while another server holds it.
    Usb(Option<PathBuf>),
}

/// After a reset, the board's USB port disappears this much later
/// ([`Port::Usb`]): what it sent before has been read by then, as the
/// board waits before it resets on request.
pub const RESET_UNPLUG_MS: u64 = firmware::hal::RESET_AFTER_REPLY_MS;

/// After a reset, the board's USB port is back this much later
/// ([`Port::Usb`]): its boot and the host's enumeration.
pub const REPLUG_MS: u64 = 800;

/// What passes through a [`ServedPort`] this turn.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Passing {
    /// Bytes both ways.
    Both,
    /// The board has just reset: what it had queued still goes out, then
    /// nothing until the port comes back.
    LastOut,
    /// Nothing (the link down, the board resetting or unplugged).
    Nothing,
}

/// The [`Port::Usb`] side of a [`ServedPort`].
#[derive(Debug)]
struct UsbPlug {
    link: PathBuf,
    /// The boots and ROM state last seen: a change is a reset.
    boots: u32,
    in_rom: bool,
    /// A reset: the port goes at this tick.
    unplug_at: Option<u64>,
    /// The port may come back from this tick on (`u64::MAX`: never).
    back_at: u64,
    /// A failure to plug, said once.
    plug_failed: bool,
    /// The link's path held against a second server ([`claim_link`]).
    _claim: Option<LinkClaim>,
}

/// A link path held by one server while it runs.
#[cfg(target_os = "linux")]
type LinkClaim = std::os::unix::net::UnixListener;
#[cfg(not(target_os = "linux"))]
type LinkClaim = ();

/// Hold `link` for this server: a second server given the same path (two
/// `scanner sim --link` at once) is refused rather than taking the link
/// over, and the first's unplug then removing the second's link. The hold
/// is a socket in Linux's abstract namespace named after the path, which
/// the kernel releases when the process ends, however it ends: a link left
/// by a killed server is taken over.
fn claim_link(link: &Path) -> std::io::Result<LinkClaim> {
    #[cfg(target_os = "linux")]
    {
        use std::os::linux::net::SocketAddrExt;
        let parent = match link.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.canonicalize()?,
            _ => std::env::current_dir()?,
        };
        let full = parent.join(link.file_name().unwrap_or_default());
        // FNV-1a over the path's bytes: an abstract name is at most 107 bytes.
        let hash =
            full.as_os_str().as_encoded_bytes().iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| {
                (h ^ b as u64).wrapping_mul(0x0100_0000_01b3)
            });
        let name = format!("hil-sim-port:{hash:016x}");
        let addr = std::os::unix::net::SocketAddr::from_abstract_name(name.as_bytes())?;
        std::os::unix::net::UnixListener::bind_addr(&addr).map_err(|e| {
            if e.kind() == std::io::ErrorKind::AddrInUse {
                std::io::Error::other(format!(
                    "{}: another simulator serves its board there",
                    link.display()
                ))
            } else {
                e
            }
        })
    }
    #[cfg(not(target_os = "linux"))]
    {
        let _ = link;
        Ok(())
    }
}

/// The server's end of the port: the pty pair (none while a
/// [`Port::Usb`] board is unplugged).
#[derive(Debug)]
struct ServedPort {
    master: Option<TTYPort>,
    /// Held so that the pty lives while no host has it open.
    slave: Option<std::fs::File>,
    usb: Option<UsbPlug>,
    /// Where a [`Port::Usb`] without a path keeps its link (removed after
    /// the link, as fields drop after [`Drop::drop`]).
    _dir: Option<tempfile::TempDir>,
}

impl ServedPort {
    /// The port for `device` and the path the host opens.
    fn open(port: &Port, device: &SimDevice) -> std::io::Result<(ServedPort, String)> {
        let mut served = ServedPort { master: None, slave: None, usb: None, _dir: None };
        let mut claim = None;
        let link = match port {
            Port::Pty => {
                let name = served.plug()?;
                return Ok((served, name));
            }
            Port::Usb(Some(path)) => {
                if let Ok(meta) = std::fs::symlink_metadata(path)
                    && !meta.file_type().is_symlink()
                {
                    return Err(std::io::Error::other(format!(
                        "{}: exists and is no symbolic link; not replaced",
                        path.display()
                    )));
                }
                claim = Some(claim_link(path)?);
                path.clone()
            }
            Port::Usb(None) => {
                let dir = tempfile::Builder::new().prefix("hil-sim-port-").tempdir()?;
                let link = dir.path().join("ttySIM");
                served._dir = Some(dir);
                link
            }
        };
        served.usb = Some(UsbPlug {
            link: link.clone(),
            boots: device.boot_count(),
            in_rom: device.in_bootloader(),
            unplug_at: None,
            back_at: 0,
            plug_failed: false,
            _claim: claim,
        });
        served.plug()?;
        Ok((served, link.to_string_lossy().into_owned()))
    }

    /// A new pty pair (and the link to it); its name.
    fn plug(&mut self) -> std::io::Result<String> {
        let (mut master, slave, name) = pty_pair()?;
        master.set_timeout(Duration::from_millis(1)).map_err(std::io::Error::other)?;
        if let Some(usb) = &self.usb {
            // Made beside the link and renamed over it: the link is never
            // half there, and never replaces anything but a link.
            let tmp = usb.link.with_extension(format!("tmp-{}", std::process::id()));
            let _ = std::fs::remove_file(&tmp);
            std::os::unix::fs::symlink(&name, &tmp)?;
            std::fs::rename(&tmp, &usb.link)?;
        }
        (self.master, self.slave) = (Some(master), Some(slave));
        Ok(name)
    }

    /// Close the pty (the host's side hangs up) and remove the link.
    fn unplug(&mut self) {
        if let Some(usb) = &self.usb {
            let _ = std::fs::remove_file(&usb.link);
        }
        (self.master, self.slave) = (None, None);
    }

    /// Follow the board and the wire after the device has run; what
    /// passes this turn. A [`Port::Pty`] passes whenever the wire is up.
    fn follow(&mut self, device: &SimDevice, wire_up: bool) -> Passing {
        let plugged = self.master.is_some();
        let Some(usb) = &mut self.usb else {
            return if wire_up { Passing::Both } else { Passing::Nothing };
        };
        let now = device.now();
        let mut reset_now = false;
        if device.boot_count() != usb.boots || device.in_bootloader() != usb.in_rom {
            (usb.boots, usb.in_rom) = (device.boot_count(), device.in_bootloader());
            usb.unplug_at = plugged.then_some(now + RESET_UNPLUG_MS * TICKS_PER_MS);
            usb.back_at =
                if usb.in_rom { u64::MAX } else { now.saturating_add(REPLUG_MS * TICKS_PER_MS) };
            reset_now = true;
        }
        if plugged {
            if !wire_up || usb.unplug_at.is_some_and(|t| now >= t) {
                usb.unplug_at = None;
                self.unplug();
                return Passing::Nothing;
            }
        } else {
            if wire_up && now >= usb.back_at {
                let failed = self.plug().err();
                if let Some(usb) = &mut self.usb
                    && std::mem::replace(&mut usb.plug_failed, failed.is_some()) != failed.is_some()
                    && let Some(e) = failed
                {
                    eprintln!("hil-sim: cannot plug the board in again: {e}");
                }
            }
            return Passing::Nothing;
        }
        match (reset_now, usb.unplug_at.is_some()) {
            (true, _) => Passing::LastOut,
            (false, true) => Passing::Nothing,
            (false, false) => Passing::Both,
        }
    }

    /// Bytes from the host (0: none within the port's 1 ms, or unplugged).
    fn read(&mut self, buf: &mut [u8]) -> usize {
        let Some(master) = &mut self.master else {
            std::thread::sleep(Duration::from_millis(1));
            return 0;
        };
        match master.read(buf) {
            Ok(n) => n,
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => 0,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => 0,
            // No peer has the pty open (yet / any more): wait.
            Err(_) => {
                std::thread::sleep(Duration::from_millis(1));
                0
            }
        }
    }

    fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
        match &mut self.master {
            Some(master) => master.write(bytes),
            None => Err(std::io::Error::from(std::io::ErrorKind::NotConnected)),
        }
    }
}

/// A pseudo-terminal pair: the board's side (the master), the host's side
/// (the slave, raw, held open here) and the slave's path. No child process
/// inherits either descriptor: serialport's `TTYPort::pair` opens them
/// without `O_CLOEXEC`, so a `scanner` a test spawned while the server ran
/// would hold the board's side open, and an unplug would not hang up the
/// host's port.
fn pty_pair() -> std::io::Result<(TTYPort, std::fs::File, String)> {
    use std::os::fd::{AsRawFd, FromRawFd, IntoRawFd, OwnedFd};
    use std::os::unix::fs::OpenOptionsExt;
    let os = std::io::Error::last_os_error;
    // SAFETY: libc calls on descriptors this function owns, and on buffers
    // of the sizes given.
    unsafe {
        let fd = libc::posix_openpt(libc::O_RDWR | libc::O_NOCTTY | libc::O_CLOEXEC);
        if fd < 0 {
            return Err(os());
        }
        let master = OwnedFd::from_raw_fd(fd);
        if libc::grantpt(fd) != 0 || libc::unlockpt(fd) != 0 {
            return Err(os());
        }
        let mut buf = [0 as libc::c_char; 128];
        let r = libc::ptsname_r(fd, buf.as_mut_ptr(), buf.len());
        if r != 0 {
            return Err(std::io::Error::from_raw_os_error(r));
        }
        let name = std::ffi::CStr::from_ptr(buf.as_ptr())
            .to_str()
            .map_err(|_| std::io::Error::other("the pty's name is not UTF-8"))?
            .to_owned();
        // std opens with O_CLOEXEC.
        let slave = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .custom_flags(libc::O_NOCTTY)
            .open(&name)?;
        // Raw: no echo of what the board writes before the host opens it.
        let mut t = std::mem::MaybeUninit::<libc::termios>::uninit();
        if libc::tcgetattr(slave.as_raw_fd(), t.as_mut_ptr()) != 0 {
            return Err(os());
        }
        let mut t = t.assume_init();
        libc::cfmakeraw(&mut t);
        if libc::tcsetattr(slave.as_raw_fd(), libc::TCSANOW, &t) != 0 {
            return Err(os());
        }
        Ok((TTYPort::from_raw_fd(master.into_raw_fd()), slave, name))
    }
}

impl Drop for ServedPort {
    fn drop(&mut self) {
        if self.master.is_some() {
            self.unplug();
        }
    }
}

/// The simulated device served on a pseudo-terminal, in real time.
#[derive(Debug)]
pub struct PtyServer {
    path: String,
    stop: Arc<AtomicBool>,
    ruler: Arc<AtomicBool>,
    thread: Option<JoinHandle<SimDevice>>,
    renderer: Option<JoinHandle<()>>,
}

impl PtyServer {
    /// Serve `device` on a new pty, simulated time running at `speed` × wall
    /// time (1.0 = real time; keep ≤ 4, `scanner sim`'s limit, so the host's
    /// keep-alive, 50 ms after each answer, stays well inside the device's
    /// 500 ms link timeout). A stretch the serving
    /// thread could not run is not simulated at once (see `PtyClock`).
    pub fn start(device: SimDevice, speed: f64) -> std::io::Result<PtyServer> {
        Self::start_with_camera(device, speed, None, Port::Pty)
    }

    /// [`PtyServer::start`] with a simulated camera on the trigger output
    /// that drops each frame into `camera.1` as `frame-NNNNNN.EXT` (NNNNNN:
    /// the trigger pulse's index since power-on; the files as `camera.2`
    /// says), written atomically — as a real camera's capture program
    /// would. Frames render on their own thread. The host opens `port`.
    pub fn start_with_camera(
        mut device: SimDevice,
        speed: f64,
        camera: Option<(SimCamera, PathBuf, FrameFiles)>,
        port: Port,
    ) -> std::io::Result<PtyServer> {
        let mut renderer = None;
        let mut camera = match camera {
            Some((cam, dir, files)) => {
                std::fs::create_dir_all(&dir)?;
                let (tx, rx) = std::sync::mpsc::channel::<(usize, Exposure)>();
                let optics = cam.optics().clone();
                renderer = Some(std::thread::spawn(move || {
                    let sensor = optics.geometry().sensor.clone();
                    for (index, exposure) in rx {
                        let frame = optics.render(&exposure);
                        let path = dir.join(format!("frame-{index:06}.{}", files.extension()));
                        if let Err(e) = drop_frame(&frame, &sensor, files, &path) {
                            eprintln!("hil-sim camera: cannot write {}: {e}", path.display());
                        }
                    }
                }));
                Some((cam, tx))
            }
            None => None,
        };
        // A board's port appears only once it has booted, by which time its
        // inputs have been read and debounced: a fault line asserted from
        // power-on is latched before the host can ask. Without this, a
        // server thread first scheduled after the host has written (a busy
        // machine) would answer at tick 0, before the first debounce ended.
        device.advance_to(device.now() + BOOTED_TICKS);
        let (mut served, path) = ServedPort::open(&port, &device)?;
        let stop = Arc::new(AtomicBool::new(false));
        let stop_flag = Arc::clone(&stop);
        let ruler = Arc::new(AtomicBool::new(false));
        let ruler_on = Arc::clone(&ruler);
        let thread = std::thread::spawn(move || {
            let mut noise = device.link_noise();
            let started = Instant::now();
            let mut clock = PtyClock::new(device.now(), speed);
            let mut buf = [0u8; 4096];
            let mut rest = RestWatch::new(&device);
            let mut tx = UsbTx::default();
            let mut stall_told = false;
            while !stop_flag.load(Ordering::Relaxed) {
                if ruler_on.load(Ordering::Relaxed)
                    && let Some(v) = rest.stopped(&device)
                {
                    eprintln!(
                        "hil-sim: the axes stopped at disk {:.3}°, track {:.3} mm, tilt {:.3}° \
                         (measured on the machine)",
                        v.disk_deg, v.track_mm, v.tilt_deg
                    );
                }
                let n = served.read(&mut buf);
                device.advance_to(clock.target(device.now(), started.elapsed()));
                if let Some((cam, tx)) = &mut camera {
                    for job in cam.take_exposures(device.truth()) {
                        let _ = tx.send(job);
                    }
                }
                noise.apply(device.take_link_faults());
                let passing = served.follow(&device, noise.connected(device.now()));
                if n > 0 && passing == Passing::Both {
                    let bytes = noise.mangle(&buf[..n]);
                    device.receive(&bytes);
                }
                let out = device.take_output();
                if passing != Passing::Nothing {
                    tx.queue(&out, |b| noise.mangle(b));
                }
                let up = passing != Passing::Nothing;
                let dropped = tx.pump(device.now(), up, |p| served.write(p));
                if served.master.is_none() {
                    // Unplugged: what the board had queued is gone.
                    tx.discard();
                }
                // Once a stall: a host that never reads would fill stderr.
                if dropped > 0 && !stall_told {
                    eprintln!(
                        "hil-sim: output not read by the host within {USB_TX_TIMEOUT_MS} ms is \
                         dropped, as on the board ({dropped} bytes so far)"
                    );
                    stall_told = true;
                }
                stall_told &= tx.pending() > 0;
            }
            drop(camera); // ends the renderer once it has written every frame
            device
        });
        Ok(PtyServer { path, stop, ruler, thread: Some(thread), renderer })
    }

    /// From now on, print (stderr) where the axes physically stop after
    /// each motion, in degrees and mm — the simulator's stand-in for
    /// measuring a move on the machine (`scanner axes --correct`).
    pub fn print_where_axes_stop(&self) {
        self.ruler.store(true, Ordering::Relaxed);
    }

    /// Path of the port to open, like `/dev/ttyACM0`: the pty, or the link
    /// to it ([`Port`]).
    pub fn path(&self) -> &str {
        &self.path
    }

    /// Stop serving; returns the device (with its physical truth).
    pub fn stop(mut self) -> Option<SimDevice> {
        self.stop.store(true, Ordering::Relaxed);
        let device = self.thread.take().and_then(|t| t.join().ok());
        if let Some(r) = self.renderer.take() {
            let _ = r.join();
        }
        device
    }
}

impl Drop for PtyServer {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        if let Some(r) = self.renderer.take() {
            let _ = r.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = TICKS_PER_MS;

    /// `n` frames of `len` bytes (the last one the delimiter), frame k's
    /// bytes all k + 1.
    fn frames(n: usize, len: usize) -> Vec<u8> {
        (0..n).flat_map(|k| std::iter::repeat_n(k as u8 + 1, len - 1).chain([0])).collect()
    }

    #[test]
    fn a_host_that_reads_late_or_a_little_at_a_time_gets_every_frame_whole() {
        let mut tx = UsbTx::default();
        let out = frames(40, 25); // 1000 bytes: within the queue
        tx.queue(&out, |b| b.to_vec());
        let mut got = Vec::new();
        // The host takes nothing for 150 ms (less than the packet's wait) …
        for ms in 0..150 {
            let busy = || Err(std::io::ErrorKind::TimedOut.into());
            assert_eq!(tx.pump(ms * MS, true, |_| busy()), 0);
        }
        // … then at most 10 bytes a call.
        let mut ms = 150;
        while tx.pending() > 0 {
            tx.pump(ms * MS, true, |p| {
                let n = p.len().min(10);
                got.extend_from_slice(&p[..n]);
                Ok(n)
            });
            ms += 1;
        }
        assert_eq!(got, out);
        assert_eq!((tx.frames_dropped, tx.packet_bytes_dropped), (0, 0));
    }

    #[test]
    fn a_host_that_stops_reading_loses_whole_frames_then_a_packet_each_wait() {
        let mut tx = UsbTx::default();
        // 100 frames of 20 bytes: 51 fit the 1024 bytes, 49 are dropped whole.
        tx.queue(&frames(100, 20), |b| b.to_vec());
        assert_eq!(tx.frames_dropped, 49);
        assert_eq!(tx.pending(), 51 * 20);
        let busy = |_: &[u8]| Err(std::io::ErrorKind::TimedOut.into());
        // The first packet waits 200 ms, then goes; the next one waits anew.
        assert_eq!(tx.pump(0, true, busy), 0);
        assert_eq!(tx.pump((USB_TX_TIMEOUT_MS - 1) * MS, true, busy), 0);
        assert_eq!(tx.pump(USB_TX_TIMEOUT_MS * MS, true, busy), USB_TX_PACKET);
        assert_eq!(tx.pump((2 * USB_TX_TIMEOUT_MS - 1) * MS, true, busy), 0);
        assert_eq!(tx.pump(2 * USB_TX_TIMEOUT_MS * MS, true, busy), USB_TX_PACKET);
        assert_eq!(tx.pending(), 51 * 20 - 2 * USB_TX_PACKET);
        // Disconnected: nothing is written, and packets still time out.
        let mut wrote = false;
        tx.pump(3 * USB_TX_TIMEOUT_MS * MS, false, |p| {
            wrote = true;
            Ok(p.len())
        });
        assert!(!wrote);
        assert_eq!(tx.packet_bytes_dropped, 3 * USB_TX_PACKET as u64);
        // Room again for a frame once the host reads.
        let mut got = Vec::new();
        tx.pump(3 * USB_TX_TIMEOUT_MS * MS, true, |p| {
            got.extend_from_slice(p);
            Ok(p.len())
        });
        assert_eq!(got.len(), 51 * 20 - 3 * USB_TX_PACKET);
        tx.queue(&frames(1, 30), |b| b.to_vec());
        assert_eq!(tx.pending(), 30);
    }

    #[test]
    fn the_pty_clock_runs_at_its_speed_while_the_server_keeps_up() {
        let mut clock = PtyClock::new(1_000, 3.0);
        let mut now = 1_000;
        for ms in 1..=2_000u64 {
            now = clock.target(now, Duration::from_millis(ms));
            assert_eq!(now, 1_000 + 3 * ms * MS);
        }
    }

    #[test]
    fn a_stretch_the_server_did_not_run_is_not_simulated_in_one_step() {
        let mut clock = PtyClock::new(0, 3.0);
        let mut now = clock.target(0, Duration::from_millis(10));
        assert_eq!(now, 30 * MS);
        // The thread sleeps 200 ms of wall time (600 simulated ms, more than
        // the device's 500 ms link timeout): one step advances 50 ms.
        now = clock.target(now, Duration::from_millis(210));
        assert_eq!(now, 80 * MS);
        assert!(now - 30 * MS < firmware::controller::LINK_TIMEOUT_MS * MS);
        // From there on, speed × wall time again; the rest is dropped.
        now = clock.target(now, Duration::from_millis(211));
        assert_eq!(now, 83 * MS);
        now = clock.target(now, Duration::from_millis(221));
        assert_eq!(now, 113 * MS);
        // Simulated time never runs backwards.
        assert_eq!(clock.target(now, Duration::from_millis(221)), 113 * MS);
    }
}
