//! The device link: byte transports (serial / CDC-ACM, USB bulk, the
//! in-process simulator) behind one trait, and the protocol client on top —
//! sequence numbers, timeouts, retransmission of the same frame (the device
//! executes each sequence number at most once), keep-alive, reconnection
//! after a disconnect, and detection of a device reset by its boot id.

use std::collections::VecDeque;
use std::io::{Read, Write};
use std::time::{Duration, Instant};

use protocol::{
    DeviceError, DeviceInfo, Event, FrameDecoder, MAX_FLUSHED_FRAME_LEN, PROTOCOL_VERSION, Reply,
    Request, Status, ToHost, encode_flushed_frame,
};

/// Why a transport operation failed.
#[derive(Debug, thiserror::Error)]
pub enum TransportError {
    /// The device went away (unplugged, pty closed, link down).
    #[error("disconnected: {0}")]
    Disconnected(String),
    /// Cannot open the device.
    #[error("cannot open {0}")]
    Open(String),
}

/// A byte pipe to a scanner controller.
pub trait Transport: Send {
    /// Send all of `bytes`.
    fn write_all(&mut self, bytes: &[u8]) -> Result<(), TransportError>;
    /// Wait up to `timeout` for bytes; append them to `out`; `Ok(0)` on timeout.
    fn read(&mut self, out: &mut Vec<u8>, timeout: Duration) -> Result<usize, TransportError>;
    /// Let `d` pass (simulated time on a simulated link).
    fn sleep(&mut self, d: Duration);
    /// A monotonic clock (simulated time on a simulated link).
    fn now(&self) -> Duration;
    /// Try once to open the device again after a disconnect.
    fn reconnect(&mut self) -> Result<(), TransportError>;
    /// What this is connected to, for messages.
    fn describe(&self) -> String;
}

/// Wall-clock origin shared by the real transports.
fn wall_now() -> Duration {
    static START: std::sync::OnceLock<Instant> = std::sync::OnceLock::new();
    START.get_or_init(Instant::now).elapsed()
}

/// Where the scanners' locks live: one file per USB serial number, shared
/// by every user of the machine (the folder is sticky and world-writable).
fn lock_dir() -> std::path::PathBuf {
    std::env::temp_dir().join("scanner-locks")
}

/// One program at a time on a scanner. Its CDC-ACM tty and its USB bulk
/// interface reach the same controller: two programs on the two would each
/// command the machine and read each other's replies (the board answers on
/// the interface it last heard). A tty is opened exclusively already (its
/// `flock`, by serialport) and a USB interface is claimed exclusively; this
/// lock, on a file named by the USB serial number, spans both. Held while
/// the returned file is open (the process's end releases it, whatever way it
/// ends). A lock that cannot be taken for want of a place to keep it is
/// skipped with a warning: that must not stop a scanner from being used.
fn lock_scanner(serial: &str) -> Result<Option<std::fs::File>, TransportError> {
    let dir = lock_dir();
    let path = lock_path(serial);
    if std::fs::create_dir(&dir).is_ok() {
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let _ = std::fs::set_permissions(&dir, std::fs::Permissions::from_mode(0o1777));
        }
    }
    let file = match scanner_formats::input::open_lock_file(&path) {
        Ok(f) => f,
        Err(e) => {
            tracing::warn!("{}: {e}; scanner {serial} used without a lock", path.display());
            return Ok(None);
        }
    };
    // A listing's brief shared lock (`scanner_in_use`) is waited out.
    let mut attempt = file.try_lock();
    for _ in 0..5 {
        if !matches!(attempt, Err(std::fs::TryLockError::WouldBlock)) {
            break;
        }
        std::thread::sleep(Duration::from_millis(10));
        attempt = file.try_lock();
    }
    match attempt {
        Ok(()) => {
            // Who holds it, for the message of the next one that asks.
            let _ = file.set_len(0);
            let args: Vec<String> = std::env::args().collect();
            let _ = (&file)
                .write_all(format!("{} {}\n", std::process::id(), args.join(" ")).as_bytes());
            Ok(Some(file))
        }
        Err(std::fs::TryLockError::WouldBlock) => {
            let holder = lock_holder(&path).map(|h| format!(" ({h})")).unwrap_or_default();
            Err(TransportError::Open(format!(
                "scanner {serial}: in use by another program{holder}; one program at a \
                 time talks to a scanner, on either of its interfaces"
            )))
        }
        Err(std::fs::TryLockError::Error(e)) => {
            tracing::warn!("{}: {e}; scanner {serial} used without a lock", path.display());
            Ok(None)
        }
    }
}

/// The lock file of the scanner with USB serial number `serial`.
fn lock_path(serial: &str) -> std::path::PathBuf {
    let name: String = serial
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '_' })
        .collect();
    lock_dir().join(format!("usb-{name}.lock"))
}

/// "process PID: COMMAND" of the lock's holder, as it wrote it.
fn lock_holder(path: &std::path::Path) -> Option<String> {
    let text = scanner_formats::input::read_to_string(path).ok()?;
    let (pid, command) = text.trim().split_once(' ')?;
    Some(format!("process {pid}: {command}"))
}

/// Who has the scanner with USB serial number `serial` ("process PID:
/// COMMAND"), if another `scanner` has it; `None` if it is free (or its
/// lock cannot be read). For listings: it takes no lock.
pub fn scanner_in_use(serial: &str) -> Option<String> {
    let path = lock_path(serial);
    // A listing makes no file.
    if !std::fs::symlink_metadata(&path).is_ok_and(|m| m.is_file()) {
        return None;
    }
    let file = scanner_formats::input::open_lock_file(&path).ok()?;
    match file.try_lock_shared() {
        Ok(()) => None,
        Err(std::fs::TryLockError::WouldBlock) => {
            Some(lock_holder(&path).unwrap_or_else(|| "another program".into()))
        }
        Err(std::fs::TryLockError::Error(_)) => None,
    }
}

/// A serial port's open error, in words where it is the port being in use.
fn serial_open_error(path: &str, e: serialport::Error) -> TransportError {
    let busy = match e.kind {
        // serialport's exclusive `flock` on the tty.
        serialport::ErrorKind::NoDevice => e.description.contains("lock"),
        // TIOCEXCL's EBUSY, "Device or resource busy".
        serialport::ErrorKind::Io(_) => e.description.contains("busy"),
        _ => false,
    };
    if busy {
        TransportError::Open(format!("{path}: in use by another program ({e})"))
    } else {
        TransportError::Open(format!("{path}: {e}"))
    }
}

/// A serial port: the CDC-ACM interface of the board, a UART, or the
/// simulator's pty. A USB port is remembered by its serial number too: when
/// the board re-enumerates under another name (`ttyACM0` → `ttyACM1`) after
/// a reset or a replug, reconnecting follows it.
pub struct SerialTransport {
    path: String,
    serial: Option<String>,
    port: Option<Box<dyn serialport::SerialPort>>,
    /// The scanner's lock when the port is a scanner's USB tty
    /// ([`lock_scanner`]).
    _lock: Option<std::fs::File>,
}

impl std::fmt::Debug for SerialTransport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SerialTransport").field("path", &self.path).finish()
    }
}

impl SerialTransport {
    /// Open `path` (e.g. `/dev/ttyACM0`).
    pub fn open(path: &str) -> Result<SerialTransport, TransportError> {
        // A regular file, a directory or /dev/null is no serial port: say
        // so rather than the terminal ioctl's "Not a typewriter".
        #[cfg(unix)]
        if let Ok(meta) = std::fs::metadata(path) {
            use std::os::unix::fs::FileTypeExt;
            let ft = meta.file_type();
            if !ft.is_char_device() {
                let what = if ft.is_dir() { "a directory" } else { "a regular file" };
                return Err(TransportError::Open(format!("{path}: not a serial port ({what})")));
            }
        }
        // By its serial number the port is locked against a second process
        // (on this interface or the bulk one) and followed when it comes
        // back under another name; a by-id link is the port it names.
        let listed = crate::discovery::serial_scanners().unwrap_or_default();
        let serial = crate::discovery::scanner_at(path, &listed).and_then(|p| p.serial.clone());
        let lock = match &serial {
            Some(serial) => lock_scanner(serial)?,
            None => None,
        };
        let mut t = SerialTransport { path: path.to_string(), serial, port: None, _lock: lock };
        t.reconnect().map_err(|e| {
            // A device node that is no terminal (/dev/null, /dev/zero).
            use std::io::IsTerminal;
            match std::fs::File::open(path) {
                Ok(f) if !f.is_terminal() => TransportError::Open(format!(
                    "{path}: not a serial port (a device that is no terminal)"
                )),
                _ => e,
            }
        })?;
        Ok(t)
    }
}

impl Transport for SerialTransport {
    fn write_all(&mut self, bytes: &[u8]) -> Result<(), TransportError> {
        let port =
            self.port.as_mut().ok_or_else(|| TransportError::Disconnected(self.path.clone()))?;
        match port.write_all(bytes).and_then(|_| port.flush()) {
            Ok(()) => Ok(()),
            Err(e) => {
                self.port = None;
                Err(TransportError::Disconnected(format!("{}: {e}", self.path)))
            }
        }
    }

    fn read(&mut self, out: &mut Vec<u8>, timeout: Duration) -> Result<usize, TransportError> {
        let port =
            self.port.as_mut().ok_or_else(|| TransportError::Disconnected(self.path.clone()))?;
        let _ = port.set_timeout(timeout.max(Duration::from_millis(1)));
        let mut buf = [0u8; 1024];
        match port.read(&mut buf) {
            Ok(0) => {
                // End of file: the other side closed (a pty master, a USB unplug).
                std::thread::sleep(timeout.min(Duration::from_millis(5)));
                Ok(0)
            }
            Ok(n) => {
                out.extend_from_slice(&buf[..n]);
                Ok(n)
            }
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::TimedOut | std::io::ErrorKind::Interrupted
                ) =>
            {
                Ok(0)
            }
            Err(e) => {
                self.port = None;
                Err(TransportError::Disconnected(format!("{}: {e}", self.path)))
            }
        }
    }

    fn sleep(&mut self, d: Duration) {
        std::thread::sleep(d);
    }

    fn now(&self) -> Duration {
        wall_now()
    }

    fn reconnect(&mut self) -> Result<(), TransportError> {
        self.port = None;
        if let Some(serial) = &self.serial
            && let listed = crate::discovery::serial_scanners().unwrap_or_default()
            && let Some(p) = listed.iter().find(|p| p.serial.as_ref() == Some(serial))
            && crate::discovery::scanner_at(&self.path, &listed).map(|q| &q.path) != Some(&p.path)
        {
            tracing::info!("scanner {serial} is now {}", p.path);
            self.path = p.path.clone();
        }
        let port = serialport::new(&self.path, 115_200)
            .timeout(Duration::from_millis(10))
            .open()
            .map_err(|e| serial_open_error(&self.path, e))?;
        self.port = Some(port);
        Ok(())
    }

    fn describe(&self) -> String {
        self.path.clone()
    }
}

/// The board's vendor-class bulk interface over USB (nusb, no libusb).
pub struct UsbTransport {
    serial: String,
    /// The scanner's lock ([`lock_scanner`]).
    _lock: Option<std::fs::File>,
    io: Option<(
        nusb::io::EndpointWrite<nusb::transfer::Bulk>,
        nusb::io::EndpointRead<nusb::transfer::Bulk>,
    )>,
}

impl std::fmt::Debug for UsbTransport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("UsbTransport").field("serial", &self.serial).finish()
    }
}

impl UsbTransport {
    /// Open the scanner with USB serial number `serial`.
    pub fn open(serial: &str) -> Result<UsbTransport, TransportError> {
        let lock = lock_scanner(serial)?;
        let mut t = UsbTransport { serial: serial.to_string(), _lock: lock, io: None };
        t.reconnect()?;
        Ok(t)
    }
}

impl Transport for UsbTransport {
    fn write_all(&mut self, bytes: &[u8]) -> Result<(), TransportError> {
        let (tx, _) =
            self.io.as_mut().ok_or_else(|| TransportError::Disconnected(self.serial.clone()))?;
        match tx.write_all(bytes).and_then(|_| tx.flush_end()) {
            Ok(()) => Ok(()),
            Err(e) => {
                self.io = None;
                Err(TransportError::Disconnected(format!("usb {}: {e}", self.serial)))
            }
        }
    }

    fn read(&mut self, out: &mut Vec<u8>, timeout: Duration) -> Result<usize, TransportError> {
        let (_, rx) =
            self.io.as_mut().ok_or_else(|| TransportError::Disconnected(self.serial.clone()))?;
        rx.set_read_timeout(timeout.max(Duration::from_millis(1)));
        let mut buf = [0u8; 512];
        match rx.read(&mut buf) {
            Ok(n) => {
                out.extend_from_slice(&buf[..n]);
                Ok(n)
            }
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => Ok(0),
            Err(e) => {
                self.io = None;
                Err(TransportError::Disconnected(format!("usb {}: {e}", self.serial)))
            }
        }
    }

    fn sleep(&mut self, d: Duration) {
        std::thread::sleep(d);
    }

    fn now(&self) -> Duration {
        wall_now()
    }

    fn reconnect(&mut self) -> Result<(), TransportError> {
        use nusb::MaybeFuture;
        self.io = None;
        let fail = |what: &str| TransportError::Open(format!("usb {}: {what}", self.serial));
        let info = crate::discovery::usb_devices()
            .map_err(|e| fail(&e))?
            .into_iter()
            .find(|d| d.serial == self.serial)
            .ok_or_else(|| fail("not connected"))?;
        let iface = info.vendor_interface.ok_or_else(|| fail("no vendor-class bulk interface"))?;
        let device = info.info.open().wait().map_err(|e| fail(&e.to_string()))?;
        let config = device.active_configuration().map_err(|e| fail(&e.to_string()))?;
        let alt = config
            .interface_alt_settings()
            .find(|a| a.interface_number() == iface && a.alternate_setting() == 0)
            .ok_or_else(|| fail("vendor interface has no descriptor"))?;
        let bulk = |dir: nusb::transfer::Direction| {
            alt.endpoints()
                .find(|e| {
                    e.transfer_type() == nusb::descriptors::TransferType::Bulk
                        && e.direction() == dir
                })
                .map(|e| e.address())
        };
        let ep_out =
            bulk(nusb::transfer::Direction::Out).ok_or_else(|| fail("no bulk OUT endpoint"))?;
        let ep_in =
            bulk(nusb::transfer::Direction::In).ok_or_else(|| fail("no bulk IN endpoint"))?;
        let interface = device.claim_interface(iface).wait().map_err(|e| fail(&e.to_string()))?;
        let tx = interface
            .endpoint::<nusb::transfer::Bulk, nusb::transfer::Out>(ep_out)
            .map_err(|e| fail(&e.to_string()))?
            .writer(64);
        let rx = interface
            .endpoint::<nusb::transfer::Bulk, nusb::transfer::In>(ep_in)
            .map_err(|e| fail(&e.to_string()))?
            .reader(64);
        self.io = Some((tx, rx));
        Ok(())
    }

    fn describe(&self) -> String {
        format!("usb:{}", self.serial)
    }
}

/// The in-process deterministic simulator's link.
#[cfg(feature = "sim")]
#[derive(Debug, Clone)]
pub struct SimTransport(pub hil_sim::SimRig);

#[cfg(feature = "sim")]
impl Transport for SimTransport {
    fn write_all(&mut self, bytes: &[u8]) -> Result<(), TransportError> {
        self.0.write(bytes).map_err(|e| TransportError::Disconnected(e.to_string()))
    }
    fn read(&mut self, out: &mut Vec<u8>, timeout: Duration) -> Result<usize, TransportError> {
        self.0.read(out, timeout).map_err(|e| TransportError::Disconnected(e.to_string()))
    }
    fn sleep(&mut self, d: Duration) {
        self.0.sleep(d)
    }
    fn now(&self) -> Duration {
        self.0.now()
    }
    fn reconnect(&mut self) -> Result<(), TransportError> {
        // The simulated cable comes back by itself; waiting is all it takes.
        self.0.sleep(Duration::from_millis(10));
        if self.0.is_connected() {
            Ok(())
        } else {
            Err(TransportError::Open("simulator: link down".into()))
        }
    }
    fn describe(&self) -> String {
        "simulator (in-process)".into()
    }
}

/// Why a device operation failed.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    /// The device was not there or did not come back in time.
    #[error("device not reachable: {0}")]
    NoDevice(String),
    /// The device speaks another protocol major version.
    #[error("incompatible firmware: device speaks protocol {device}, this host {host}")]
    Incompatible {
        /// The device's protocol version.
        device: protocol::ProtocolVersion,
        /// Ours.
        host: protocol::ProtocolVersion,
    },
    /// No reply despite retransmissions.
    #[error("no reply from {device} to {request} after {attempts} attempts")]
    Timeout {
        /// The device.
        device: String,
        /// The request's name.
        request: &'static str,
        /// Frames sent.
        attempts: u32,
    },
    /// The device refused the request.
    #[error("device refused {request}: {error}")]
    Refused {
        /// The request's name.
        request: &'static str,
        /// Its error.
        error: DeviceError,
    },
    /// The device reset (new boot id): homing and any motion are lost.
    #[error("device reset (boot id {old:08x} → {new:08x})")]
    Reset {
        /// Boot id before.
        old: u32,
        /// Boot id now.
        new: u32,
    },
    /// The device replied with something the request cannot produce.
    #[error("unexpected reply to {request}: {reply:?}")]
    Unexpected {
        /// The request's name.
        request: &'static str,
        /// What came.
        reply: Reply,
    },
}

/// Timing of the protocol client.
#[derive(Debug, Clone, Copy)]
pub struct LinkTimings {
    /// Wait this long for a reply before sending the frame again.
    pub retransmit_after: Duration,
    /// The same for the keep-alive `Ping`, which the firmware answers at
    /// once: sooner, so that a few lost pings in a row do not add up to the
    /// device's link timeout while it moves.
    pub ping_retransmit_after: Duration,
    /// Attempts per request.
    pub attempts: u32,
    /// Keep trying to reopen a lost device for this long.
    pub reconnect_for: Duration,
    /// While waiting for events, ping this often after the last answer (the
    /// device stops moving after 500 ms of silence; the protocol asks for
    /// at least every 200 ms).
    pub keepalive: Duration,
}

impl Default for LinkTimings {
    fn default() -> LinkTimings {
        LinkTimings {
            retransmit_after: Duration::from_millis(60),
            ping_retransmit_after: Duration::from_millis(20),
            attempts: 50,
            reconnect_for: Duration::from_secs(15),
            // A tenth of the link timeout: a host not scheduled for a
            // while (a busy machine, a simulator at several times real
            // time) keeps the link for the other nine tenths.
            keepalive: Duration::from_millis(50),
        }
    }
}

impl LinkTimings {
    /// What a call may overrun its limit by: the transport's last read
    /// (up to 10 ms) and the pause between two tries to reopen (100 ms).
    pub const SLACK: Duration = Duration::from_millis(110);

    /// The longest one exchange — a request sent and sent again until its
    /// reply comes — takes whatever the device does (within
    /// [`LinkTimings::SLACK`]): every attempt's wait and, once, the time to
    /// reopen a lost device, shared by every loss during the exchange (a
    /// device that drops off at every write is given up then, not after
    /// `attempts` reconnections). `ping`: for the keep-alive's shorter
    /// retransmission.
    pub fn exchange_limit(&self, ping: bool) -> Duration {
        let each = if ping { self.ping_retransmit_after } else { self.retransmit_after };
        each.saturating_mul(self.attempts).saturating_add(self.reconnect_for)
    }

    /// The longest [`Device::request`] takes: its exchange, and for a
    /// device that lost the handshake the greeting and the request again.
    pub fn request_limit(&self, ping: bool) -> Duration {
        self.exchange_limit(ping).saturating_mul(2).saturating_add(self.exchange_limit(false))
    }

    /// The longest [`Device::wait_event`] or [`Device::sleep`] for
    /// `timeout` takes: the timeout, and what began before its end — a
    /// keep-alive request, the greeting that checks a `Boot` event, or
    /// reopening a device lost while listening.
    pub fn wait_limit(&self, timeout: Duration) -> Duration {
        timeout.saturating_add(self.request_limit(true).max(self.reconnect_for))
    }
}

/// Counters of link trouble survived.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LinkStats {
    /// Requests answered.
    pub requests: u64,
    /// Frames sent again.
    pub retransmissions: u64,
    /// Reconnections after a disconnect.
    pub reconnects: u64,
    /// Device resets detected.
    pub resets: u64,
    /// Frames dropped by the decoder (CRC, framing).
    pub bad_frames: u64,
}

/// The protocol client.
pub struct Device {
    transport: Box<dyn Transport>,
    seq: u8,
    decoder: FrameDecoder<ToHost>,
    replies: Vec<(u8, Reply)>,
    events: VecDeque<Event>,
    info: DeviceInfo,
    timings: LinkTimings,
    /// The end of the running exchange ([`LinkTimings::exchange_limit`]):
    /// reopening a lost device stops there.
    give_up: Option<Duration>,
    /// Trouble survived so far.
    pub stats: LinkStats,
}

impl std::fmt::Debug for Device {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Device")
            .field("link", &self.transport.describe())
            .field("info", &self.info)
            .finish()
    }
}

impl Device {
    /// Handshake over `transport` (version check) with default timings.
    pub fn connect(transport: Box<dyn Transport>) -> Result<Device, LinkError> {
        Self::connect_with(transport, LinkTimings::default())
    }

    /// Handshake over `transport` with `timings`.
    pub fn connect_with(
        transport: Box<dyn Transport>,
        timings: LinkTimings,
    ) -> Result<Device, LinkError> {
        let mut d = Device {
            transport,
            seq: 0,
            decoder: FrameDecoder::new(),
            replies: Vec::new(),
            events: VecDeque::new(),
            info: placeholder_info(),
            timings,
            give_up: None,
            stats: LinkStats::default(),
        };
        d.info = d.hello()?;
        Ok(d)
    }

    /// The handshake's answer (refreshed on every reconnect).
    pub fn info(&self) -> &DeviceInfo {
        &self.info
    }

    /// The link's timings.
    pub fn timings(&self) -> &LinkTimings {
        &self.timings
    }

    /// The link's timings, to change from here on (e.g. not to wait for a
    /// device that is expected to go away).
    pub fn timings_mut(&mut self) -> &mut LinkTimings {
        &mut self.timings
    }

    /// What the link is connected to.
    pub fn describe(&self) -> String {
        self.transport.describe()
    }

    /// The transport's clock.
    pub fn now(&self) -> Duration {
        self.transport.now()
    }

    /// Let time pass on the transport's clock (reading and queueing events).
    pub fn sleep(&mut self, d: Duration) -> Result<(), LinkError> {
        let end = self.transport.now() + d;
        loop {
            // One reading of the clock: it may pass `end` between two.
            let left = end.saturating_sub(self.transport.now());
            if left.is_zero() {
                return Ok(());
            }
            self.pump(left.min(Duration::from_millis(20)))?;
        }
    }

    fn hello(&mut self) -> Result<DeviceInfo, LinkError> {
        match self.exchange(Request::Hello { host_protocol: PROTOCOL_VERSION })? {
            Reply::Info(info) => {
                if !info.protocol.is_compatible_with(PROTOCOL_VERSION) {
                    return Err(LinkError::Incompatible {
                        device: info.protocol,
                        host: PROTOCOL_VERSION,
                    });
                }
                Ok(info)
            }
            Reply::Error(DeviceError::UnsupportedVersion(v)) => {
                Err(LinkError::Incompatible { device: v, host: PROTOCOL_VERSION })
            }
            reply => Err(LinkError::Unexpected { request: "Hello", reply }),
        }
    }

    /// Read what is there (up to `timeout`), decode, queue events.
    fn pump(&mut self, timeout: Duration) -> Result<(), LinkError> {
        let mut buf = Vec::new();
        match self.transport.read(&mut buf, timeout) {
            Ok(_) => {}
            Err(TransportError::Disconnected(why)) | Err(TransportError::Open(why)) => {
                self.reopen(&why)?;
            }
        }
        for frame in self.decoder.feed(&buf) {
            match frame {
                Ok(f) => match f.msg {
                    ToHost::Reply(r) => self.replies.push((f.seq, r)),
                    ToHost::Event(e) => self.events.push_back(e),
                },
                Err(_) => self.stats.bad_frames += 1,
            }
        }
        Ok(())
    }

    /// Reopen the transport after a disconnect, for up to `reconnect_for`.
    fn reopen(&mut self, why: &str) -> Result<(), LinkError> {
        tracing::warn!("link to {} lost ({why}); reconnecting", self.transport.describe());
        let end = self.transport.now() + self.timings.reconnect_for;
        let end = self.give_up.map_or(end, |g| g.min(end));
        loop {
            match self.transport.reconnect() {
                Ok(()) => {
                    self.stats.reconnects += 1;
                    self.decoder = FrameDecoder::new();
                    return Ok(());
                }
                Err(e) => {
                    if self.transport.now() >= end {
                        return Err(LinkError::NoDevice(e.to_string()));
                    }
                    self.transport.sleep(Duration::from_millis(100));
                }
            }
        }
    }

    /// Send one request and wait for its reply, retransmitting the same
    /// frame (same sequence number) until it comes.
    fn exchange(&mut self, request: Request) -> Result<Reply, LinkError> {
        let ping = matches!(request, Request::Ping { .. });
        self.give_up = self.transport.now().checked_add(self.timings.exchange_limit(ping));
        let result = self.exchange_until(request);
        self.give_up = None;
        result
    }

    /// [`Device::exchange`] until [`Device::give_up`].
    fn exchange_until(&mut self, request: Request) -> Result<Reply, LinkError> {
        let give_up = self.give_up.unwrap_or(Duration::MAX);
        self.seq = self.seq.wrapping_add(1);
        let seq = self.seq;
        let mut frame = [0u8; MAX_FLUSHED_FRAME_LEN];
        let n = encode_flushed_frame(seq, &request, &mut frame)
            .expect("every request fits MAX_FLUSHED_FRAME_LEN");
        let retransmit_after = match request {
            Request::Ping { .. } => self.timings.ping_retransmit_after,
            _ => self.timings.retransmit_after,
        };
        let mut sent = 0;
        for attempt in 0..self.timings.attempts {
            if self.transport.now() >= give_up {
                break;
            }
            if attempt > 0 {
                self.stats.retransmissions += 1;
            }
            if let Err(e) = self.transport.write_all(&frame[..n]) {
                self.reopen(&e.to_string())?;
                continue;
            }
            sent += 1;
            let deadline = (self.transport.now() + retransmit_after).min(give_up);
            loop {
                // One reading per turn: two could straddle the deadline.
                let left = deadline.saturating_sub(self.transport.now());
                if left.is_zero() {
                    break;
                }
                self.pump(left.min(Duration::from_millis(10)))?;
                if let Some(i) = self.replies.iter().position(|(s, _)| *s == seq) {
                    let (_, reply) = self.replies.swap_remove(i);
                    self.replies.clear();
                    self.stats.requests += 1;
                    return Ok(reply);
                }
            }
        }
        Err(LinkError::Timeout {
            device: self.transport.describe(),
            request: request.name(),
            attempts: sent,
        })
    }

    /// Send a request; a device error becomes [`LinkError::Refused`]. A
    /// device that lost the handshake (it reset) is greeted again and
    /// [`LinkError::Reset`] returned if its boot id changed.
    pub fn request(&mut self, request: Request) -> Result<Reply, LinkError> {
        let name = request.name();
        match self.exchange(request)? {
            Reply::Error(DeviceError::NoHandshake) => {
                self.check_boot()?;
                match self.exchange(request)? {
                    Reply::Error(error) => Err(LinkError::Refused { request: name, error }),
                    reply => Ok(reply),
                }
            }
            Reply::Error(error) => Err(LinkError::Refused { request: name, error }),
            reply => Ok(reply),
        }
    }

    /// A request whose only good answer is `Ack`.
    pub fn command(&mut self, request: Request) -> Result<(), LinkError> {
        let name = request.name();
        match self.request(request)? {
            Reply::Ack => Ok(()),
            reply => Err(LinkError::Unexpected { request: name, reply }),
        }
    }

    /// The device status.
    pub fn status(&mut self) -> Result<Status, LinkError> {
        match self.request(Request::GetStatus)? {
            Reply::Status(s) => Ok(s),
            reply => Err(LinkError::Unexpected { request: "GetStatus", reply }),
        }
    }

    /// Greet the device again (after a reconnect) and report a reset.
    pub fn check_boot(&mut self) -> Result<(), LinkError> {
        let old = self.info.boot_id;
        self.info = self.hello()?;
        if self.info.boot_id != old {
            self.stats.resets += 1;
            return Err(LinkError::Reset { old, new: self.info.boot_id });
        }
        Ok(())
    }

    /// Forget queued events (before a command whose events matter).
    pub fn clear_events(&mut self) {
        self.events.clear();
    }

    /// Wait up to `timeout` for an event matching `pred`, pinging as
    /// keep-alive; a `Boot` event with a new boot id is a reset. Other events
    /// stay queued for [`Device::take_events`].
    ///
    /// It returns within `timeout` and one request (a keep-alive or the
    /// greeting that checks a `Boot` event; [`LinkTimings::wait_limit`]),
    /// whatever the device sends: a
    /// `Boot` event still queued at the end is checked by the next wait or
    /// request (a device that did reset refuses that with `NoHandshake`).
    pub fn wait_event(
        &mut self,
        timeout: Duration,
        pred: impl Fn(&Event) -> bool,
    ) -> Result<Option<Event>, LinkError> {
        let end = self.transport.now() + timeout;
        let mut next_ping = self.transport.now() + self.timings.keepalive;
        loop {
            // Past the end, only what was waited for is taken: a device that
            // sends `Boot` events its greeting does not confirm would
            // otherwise be greeted for as long as it sends them.
            let late = self.transport.now() >= end;
            if let Some(i) = self.events.iter().position(|e| {
                matches!(e, Event::Boot { boot_id, .. } if *boot_id != self.info.boot_id && !late)
                    || pred(e)
            }) {
                let e = self.events.remove(i).expect("index from position");
                if let Event::Boot { boot_id, .. } = e
                    && boot_id != self.info.boot_id
                    && !late
                {
                    // Greeting it again reports the reset (an event from a
                    // boot the handshake does not confirm is dropped).
                    self.check_boot()?;
                    continue;
                }
                return Ok(Some(e));
            }
            let now = self.transport.now();
            if now >= end {
                return Ok(None);
            }
            if now >= next_ping {
                self.request(Request::Ping { token: 0 })?;
                next_ping = self.transport.now() + self.timings.keepalive;
                continue;
            }
            self.pump((next_ping.min(end) - now).min(Duration::from_millis(20)))?;
        }
    }

    /// Events queued so far.
    pub fn take_events(&mut self) -> Vec<Event> {
        self.events.drain(..).collect()
    }
}

fn placeholder_info() -> DeviceInfo {
    DeviceInfo {
        protocol: PROTOCOL_VERSION,
        firmware: protocol::FirmwareVersion { major: 0, minor: 0, patch: 0 },
        board: 0,
        device_id: [0; 12],
        capabilities: protocol::Capabilities::default(),
        mirror_count: 0,
        boot_id: 0,
    }
}

#[cfg(test)]
mod tests {
    use std::sync::{Arc, Mutex};

    use super::*;
    use protocol::ResetReason;

    #[test]
    fn one_program_at_a_time_on_a_scanner() {
        // A serial number of this test's own: other tests and programs
        // keep theirs.
        let serial = format!("TEST/{}:one-program", std::process::id());
        let first = lock_scanner(&serial).unwrap();
        assert!(first.is_some(), "the lock is taken");
        // Another open of the file, as another program's would be.
        let Err(TransportError::Open(why)) = lock_scanner(&serial) else {
            panic!("a second lock on the same scanner is refused")
        };
        let pid = std::process::id();
        assert!(why.contains("in use by another program (process"), "{why}");
        assert!(why.contains(&format!("process {pid}:")), "names the holder: {why}");
        let listed = scanner_in_use(&serial).expect("a listing sees it in use");
        assert!(listed.starts_with(&format!("process {pid}: ")), "{listed}");
        drop(first);
        assert_eq!(scanner_in_use(&serial), None, "free once released");
        assert!(lock_scanner(&serial).unwrap().is_some(), "taken again once released");
        let other = format!("TEST/{}:another", std::process::id());
        let _held = lock_scanner(&serial).unwrap();
        assert!(lock_scanner(&other).unwrap().is_some(), "another scanner is not locked");
        let name = lock_dir().join(format!("usb-TEST_{pid}_one-program.lock"));
        assert!(name.is_file(), "the file is named by the serial number, made safe");
        drop(_held);
        let _ = std::fs::remove_file(name);
        let _ = std::fs::remove_file(lock_dir().join(format!("usb-TEST_{pid}_another.lock")));
    }

    /// A device on a simulated clock that answers every request after a
    /// round trip of `round_trip` (`Hello` with its info, `Ping` with its
    /// `Pong`, anything else with `Ack`), noting when each request arrived.
    struct Answering {
        now: Duration,
        round_trip: Duration,
        decoder: FrameDecoder<Request>,
        /// (readable at, bytes) in order.
        replies: VecDeque<(Duration, Vec<u8>)>,
        arrivals: Arc<Mutex<Vec<Duration>>>,
        /// Line noise turns the last byte of these writes (counted from 0)
        /// into another: their frame's delimiter never arrives.
        hide_delimiter: Vec<usize>,
        /// Line noise loses these writes (counted from 0) altogether.
        lose: Vec<usize>,
        writes: usize,
        /// Follow every reply with a `Boot` event of a new boot id (which
        /// the greeting never confirms), as an inconsistent device might.
        boot_flood: Option<u32>,
        /// From this write on (counted from 0), every write finds the
        /// device gone, and it comes back `flap` after (a cable with a bad
        /// contact): (first write, flap).
        flapping: Option<(usize, Duration)>,
        back_at: Option<Duration>,
    }

    impl Answering {
        fn new(round_trip: Duration, arrivals: Arc<Mutex<Vec<Duration>>>) -> Answering {
            Answering {
                now: Duration::ZERO,
                round_trip,
                decoder: FrameDecoder::new(),
                replies: VecDeque::new(),
                arrivals,
                hide_delimiter: Vec::new(),
                lose: Vec::new(),
                writes: 0,
                boot_flood: None,
                flapping: None,
                back_at: None,
            }
        }
    }

    impl Transport for Answering {
        fn write_all(&mut self, bytes: &[u8]) -> Result<(), TransportError> {
            let arrived = self.now + self.round_trip / 2;
            let mut bytes = bytes.to_vec();
            if self.hide_delimiter.contains(&self.writes) {
                *bytes.last_mut().unwrap() = 0x55;
            }
            let lost = self.lose.contains(&self.writes);
            if let Some((from, flap)) = self.flapping
                && self.writes >= from
            {
                self.writes += 1;
                self.back_at = Some(self.now + flap);
                return Err(TransportError::Disconnected("a bad contact".into()));
            }
            self.writes += 1;
            if lost {
                return Ok(());
            }
            for frame in self.decoder.feed(&bytes) {
                // A damaged frame is dropped, as the device does.
                let Ok(frame) = frame else { continue };
                self.arrivals.lock().unwrap().push(arrived);
                let reply = match frame.msg {
                    Request::Hello { .. } => Reply::Info(placeholder_info()),
                    Request::Ping { token } => Reply::Pong { token },
                    _ => Reply::Ack,
                };
                let mut buf = [0u8; MAX_FLUSHED_FRAME_LEN];
                let n = encode_flushed_frame(frame.seq, &ToHost::Reply(reply), &mut buf).unwrap();
                let mut bytes = buf[..n].to_vec();
                if let Some(boot_id) = &mut self.boot_flood {
                    *boot_id += 1;
                    let boot = Event::Boot { boot_id: *boot_id, reason: ResetReason::Software };
                    let n = encode_flushed_frame(0, &ToHost::Event(boot), &mut buf).unwrap();
                    bytes.extend_from_slice(&buf[..n]);
                }
                self.replies.push_back((arrived + self.round_trip / 2, bytes));
            }
            Ok(())
        }
        fn read(&mut self, out: &mut Vec<u8>, timeout: Duration) -> Result<usize, TransportError> {
            let next = self.replies.front().map(|r| r.0);
            self.now = match next {
                Some(at) if at <= self.now + timeout => self.now.max(at),
                _ => self.now + timeout,
            };
            let start = out.len();
            while let Some((at, bytes)) = self.replies.front()
                && *at <= self.now
            {
                out.extend_from_slice(bytes);
                self.replies.pop_front();
            }
            Ok(out.len() - start)
        }
        fn sleep(&mut self, d: Duration) {
            self.now += d;
        }
        fn now(&self) -> Duration {
            self.now
        }
        fn reconnect(&mut self) -> Result<(), TransportError> {
            match self.back_at {
                Some(at) if self.now < at => Err(TransportError::Open("not there yet".into())),
                _ => Ok(()),
            }
        }
        fn describe(&self) -> String {
            "answering".into()
        }
    }

    /// The longest silence the device hears while a host waits 2 s for an
    /// event over `transport` (the handshake excluded).
    fn longest_silence_while_waiting(transport: Answering) -> Duration {
        let arrivals = transport.arrivals.clone();
        let mut dev = Device::connect(Box::new(transport)).unwrap();
        let start = dev.now();
        assert!(dev.wait_event(Duration::from_secs(2), |_| false).unwrap().is_none());
        let end = dev.now();
        let mut heard = arrivals.lock().unwrap().clone();
        assert!(heard.len() > 20, "{} requests in 2 s", heard.len());
        heard[0] = start;
        heard.push(end);
        heard.windows(2).map(|w| w[1] - w[0]).max().unwrap()
    }

    /// While a host waits for an event, the device hears from it often
    /// enough that the host may go unscheduled for most of the device's
    /// 500 ms link timeout: with a 10 ms round trip, never 70 ms of
    /// silence (a waiting host leaves the device ≥ 430 ms of margin).
    #[test]
    fn a_waiting_host_pings_well_inside_the_link_timeout() {
        let arrivals = Arc::new(Mutex::new(Vec::new()));
        let longest =
            longest_silence_while_waiting(Answering::new(Duration::from_millis(10), arrivals));
        assert!(longest < Duration::from_millis(70), "{longest:?} of silence");
    }

    /// Two lost pings in a row (a ping and its first retransmission) cost
    /// the device less than 100 ms of silence with a 2 ms round trip: a
    /// ping is retransmitted after 20 ms, not the 60 ms of other requests
    /// (which would make it 170 ms, past the link timeout of a simulator
    /// at three times real time).
    #[test]
    fn lost_pings_are_sent_again_soon() {
        let arrivals = Arc::new(Mutex::new(Vec::new()));
        let mut transport = Answering::new(Duration::from_millis(2), arrivals);
        // Write 0 is the handshake; 1–4 pings, 5 the fourth one sent again.
        transport.lose = vec![4, 5];
        let longest = longest_silence_while_waiting(transport);
        assert!(longest < Duration::from_millis(100), "{longest:?} of silence");
    }

    /// A device that follows every reply with a `Boot` event its greeting
    /// does not confirm keeps a waiting host no longer than the wait and
    /// one greeting (it held it for as long as the device sent them: each
    /// greeting's reply brought the next event).
    #[test]
    fn unconfirmed_boot_events_do_not_stretch_a_wait() {
        let arrivals = Arc::new(Mutex::new(Vec::new()));
        let mut transport = Answering::new(Duration::from_millis(2), arrivals.clone());
        transport.boot_flood = Some(1);
        let mut dev = Device::connect(Box::new(transport)).unwrap();
        let start = dev.now();
        let got = dev.wait_event(Duration::from_secs(1), |e| matches!(e, Event::MotionDone { .. }));
        let took = dev.now() - start;
        assert_eq!(got.unwrap(), None);
        assert!(took < Duration::from_millis(1_010), "{took:?}");
        assert!(
            arrivals.lock().unwrap().len() > 100,
            "the events were checked while there was time"
        );
        assert!(dev.info().boot_id == 0, "no reset was confirmed");
    }

    /// A device that drops off at every write and comes back just before
    /// the host would give it up (a cable with a bad contact) costs a
    /// request no more than its attempts' waits and one reconnection time,
    /// [`LinkTimings::exchange_limit`] (each reconnection had its own:
    /// 50 attempts × 14 s).
    #[test]
    fn a_flapping_device_is_given_up_within_the_exchange_limit() {
        let arrivals = Arc::new(Mutex::new(Vec::new()));
        let mut transport = Answering::new(Duration::from_millis(2), arrivals.clone());
        // Write 0 is the handshake.
        transport.flapping = Some((1, Duration::from_secs(14)));
        let mut dev = Device::connect(Box::new(transport)).unwrap();
        let start = dev.now();
        let got = dev.request(Request::GetStatus);
        let took = dev.now() - start;
        let limit = dev.timings().exchange_limit(false);
        assert!(took <= limit + LinkTimings::SLACK, "{took:?} against {limit:?}");
        assert!(matches!(got, Err(LinkError::NoDevice(_))), "{got:?}");
        assert!(dev.stats.reconnects >= 1, "it came back once at least");
    }

    /// Timings too long to add up (a library user's "wait forever") make
    /// limits that saturate, not a panic.
    #[test]
    fn endless_timings_saturate() {
        let endless = LinkTimings { reconnect_for: Duration::MAX, ..LinkTimings::default() };
        assert_eq!(endless.exchange_limit(false), Duration::MAX);
        assert_eq!(endless.wait_limit(Duration::from_secs(1)), Duration::MAX);
        let arrivals = Arc::new(Mutex::new(Vec::new()));
        let transport = Answering::new(Duration::from_millis(2), arrivals);
        let mut dev = Device::connect_with(Box::new(transport), endless).unwrap();
        assert_eq!(dev.request(Request::Ping { token: 3 }).unwrap(), Reply::Pong { token: 3 });
    }

    /// A frame whose delimiter line noise hid costs that frame alone: the
    /// host starts each frame with a delimiter, so the device ends the
    /// damaged one there and takes the retransmission whole (without it,
    /// the two would run together and both be lost — 120 ms of silence at
    /// the default timings instead of 60).
    #[test]
    fn a_lost_delimiter_costs_one_frame() {
        let arrivals = Arc::new(Mutex::new(Vec::new()));
        let mut transport = Answering::new(Duration::from_millis(2), arrivals.clone());
        // Write 0 is the handshake; write 1 the first ping.
        transport.hide_delimiter = vec![1];
        let mut dev = Device::connect(Box::new(transport)).unwrap();
        assert_eq!(dev.request(Request::Ping { token: 7 }).unwrap(), Reply::Pong { token: 7 });
        assert_eq!(dev.stats.retransmissions, 1);
        assert_eq!(arrivals.lock().unwrap().len(), 2, "the handshake and the retransmitted ping");
    }
}
