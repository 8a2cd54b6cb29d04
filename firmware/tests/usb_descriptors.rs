//! The controller's USB device (`firmware::usb`, the board's own) answers
//! a host's enumeration on a model of the bus: the device, configuration,
//! BOS and string descriptors, and the MS OS 2.0 descriptor set that makes
//! Windows bind WinUSB to the vendor interface — read the way Windows and
//! Linux read them, and checked field by field against the USB 2.0 and
//! Microsoft OS 2.0 specifications.

use std::cell::RefCell;
use std::collections::VecDeque;
use std::future::{Future, poll_fn};
use std::pin::pin;
use std::rc::Rc;
use std::task::{Context, Poll, Waker};

use embassy_usb::driver::{
    Bus, ControlPipe, Direction, Driver, Endpoint, EndpointAddress, EndpointAllocError,
    EndpointError, EndpointIn, EndpointInfo, EndpointOut, EndpointType, Event, Unsupported,
};
use firmware::usb::{MAX_PACKET, MSOS_VENDOR_CODE, UsbBuffers, VENDOR_INTERFACE, build};
use protocol::{USB_PID, USB_VID, USB_WINUSB_GUID};

/// What the host sends and what the device answered.
#[derive(Default)]
struct Wire {
    setups: VecDeque<[u8; 8]>,
    events: VecDeque<Event>,
    data_in: Vec<u8>,
    /// One per control transfer: the data stage (empty for a status-only
    /// transfer), or `Err` for a STALL.
    answers: Vec<Result<Vec<u8>, ()>>,
    endpoints: Vec<EndpointInfo>,
    address: Option<u8>,
}

type Shared = Rc<RefCell<Wire>>;

struct ModelDriver {
    wire: Shared,
    next: [u8; 2],
}

struct ModelEndpoint(EndpointInfo);

impl Endpoint for ModelEndpoint {
    fn info(&self) -> &EndpointInfo {
        &self.0
    }
    async fn wait_enabled(&mut self) {
        std::future::pending().await
    }
}

impl EndpointOut for ModelEndpoint {
    async fn read(&mut self, _buf: &mut [u8]) -> Result<usize, EndpointError> {
        std::future::pending().await
    }
}

impl EndpointIn for ModelEndpoint {
    async fn write(&mut self, _buf: &[u8]) -> Result<(), EndpointError> {
        std::future::pending().await
    }
}

impl ModelDriver {
    fn alloc(
        &mut self,
        dir: Direction,
        ep_type: EndpointType,
        max_packet_size: u16,
        interval_ms: u8,
    ) -> Result<ModelEndpoint, EndpointAllocError> {
        let slot = &mut self.next[matches!(dir, Direction::In) as usize];
        // The F411's OTG_FS: endpoints 1…3 in each direction beside EP0.
        if *slot > 3 {
            return Err(EndpointAllocError);
        }
        let info = EndpointInfo {
            addr: EndpointAddress::from_parts(*slot as usize, dir),
            ep_type,
            max_packet_size,
            interval_ms,
        };
        *slot += 1;
        self.wire.borrow_mut().endpoints.push(info);
        Ok(ModelEndpoint(info))
    }
}

impl<'a> Driver<'a> for ModelDriver {
    type EndpointOut = ModelEndpoint;
    type EndpointIn = ModelEndpoint;
    type ControlPipe = ModelControl;
    type Bus = ModelBus;

    fn alloc_endpoint_out(
        &mut self,
        ep_type: EndpointType,
        _addr: Option<EndpointAddress>,
        max_packet_size: u16,
        interval_ms: u8,
    ) -> Result<ModelEndpoint, EndpointAllocError> {
        self.alloc(Direction::Out, ep_type, max_packet_size, interval_ms)
    }

    fn alloc_endpoint_in(
        &mut self,
        ep_type: EndpointType,
        _addr: Option<EndpointAddress>,
        max_packet_size: u16,
        interval_ms: u8,
    ) -> Result<ModelEndpoint, EndpointAllocError> {
        self.alloc(Direction::In, ep_type, max_packet_size, interval_ms)
    }

    fn start(self, control_max_packet_size: u16) -> (ModelBus, ModelControl) {
        assert_eq!(control_max_packet_size, MAX_PACKET);
        (ModelBus(self.wire.clone()), ModelControl(self.wire))
    }
}

struct ModelBus(Shared);

impl Bus for ModelBus {
    async fn enable(&mut self) {}
    async fn disable(&mut self) {}
    async fn poll(&mut self) -> Event {
        poll_fn(|_| self.0.borrow_mut().events.pop_front().map_or(Poll::Pending, Poll::Ready)).await
    }
    fn endpoint_set_enabled(&mut self, _ep: EndpointAddress, _enabled: bool) {}
    fn endpoint_set_stalled(&mut self, _ep: EndpointAddress, _stalled: bool) {}
    fn endpoint_is_stalled(&mut self, _ep: EndpointAddress) -> bool {
        false
    }
    async fn remote_wakeup(&mut self) -> Result<(), Unsupported> {
        Err(Unsupported)
    }
}

struct ModelControl(Shared);

impl ControlPipe for ModelControl {
    fn max_packet_size(&self) -> usize {
        MAX_PACKET as usize
    }
    async fn setup(&mut self) -> [u8; 8] {
        poll_fn(|_| self.0.borrow_mut().setups.pop_front().map_or(Poll::Pending, Poll::Ready)).await
    }
    async fn data_out(
        &mut self,
        _buf: &mut [u8],
        _first: bool,
        _last: bool,
    ) -> Result<usize, EndpointError> {
        Ok(0)
    }
    async fn data_in(
        &mut self,
        data: &[u8],
        _first: bool,
        last: bool,
    ) -> Result<(), EndpointError> {
        assert!(data.len() <= MAX_PACKET as usize, "a control packet of {} bytes", data.len());
        let mut w = self.0.borrow_mut();
        w.data_in.extend_from_slice(data);
        if last {
            let d = std::mem::take(&mut w.data_in);
            w.answers.push(Ok(d));
        }
        Ok(())
    }
    async fn accept(&mut self) {
        self.0.borrow_mut().answers.push(Ok(Vec::new()));
    }
    async fn reject(&mut self) {
        self.0.borrow_mut().answers.push(Err(()));
    }
    async fn accept_set_address(&mut self, addr: u8) {
        let mut w = self.0.borrow_mut();
        w.address = Some(addr);
        w.answers.push(Ok(Vec::new()));
    }
}

/// A SETUP packet.
fn setup(request_type: u8, request: u8, value: u16, index: u16, length: u16) -> [u8; 8] {
    let [v0, v1] = value.to_le_bytes();
    let [i0, i1] = index.to_le_bytes();
    let [l0, l1] = length.to_le_bytes();
    [request_type, request, v0, v1, i0, i1, l0, l1]
}

const GET_DESCRIPTOR: u8 = 6;
const SET_ADDRESS: u8 = 5;

/// The descriptors of a buffer: (type, bytes including the header).
fn descriptors(mut b: &[u8]) -> Vec<(u8, &[u8])> {
    let mut out = Vec::new();
    while !b.is_empty() {
        let len = b[0] as usize;
        assert!(len >= 2 && len <= b.len(), "a descriptor of length {len} in {} bytes", b.len());
        out.push((b[1], &b[..len]));
        b = &b[len..];
    }
    out
}

fn le16(b: &[u8]) -> u16 {
    u16::from_le_bytes([b[0], b[1]])
}

fn utf16(s: &str) -> Vec<u8> {
    s.encode_utf16().flat_map(u16::to_le_bytes).collect()
}

#[test]
fn the_host_enumerates_cdc_and_a_winusb_vendor_interface() {
    let wire: Shared = Rc::default();
    let driver = ModelDriver { wire: wire.clone(), next: [1, 1] };
    let mut buffers = UsbBuffers::default();
    let parts = build(driver, "0123456789ABCDEF01234567", &mut buffers);
    wire.borrow_mut().events.extend([Event::PowerDetected, Event::Reset]);
    let mut device = parts.device;
    let mut run = pin!(device.run());
    let mut cx = Context::from_waker(Waker::noop());
    let mut transfer = |s: [u8; 8]| -> Result<Vec<u8>, ()> {
        let before = wire.borrow().answers.len();
        wire.borrow_mut().setups.push_back(s);
        for _ in 0..64 {
            assert!(run.as_mut().poll(&mut cx).is_pending());
            if wire.borrow().answers.len() > before {
                return wire.borrow_mut().answers.pop().expect("an answer");
            }
        }
        panic!("no answer to {s:02x?}");
    };

    // Device descriptor (USB 2.0 §9.6.1), before and after SET_ADDRESS.
    let dev = transfer(setup(0x80, GET_DESCRIPTOR, 0x0100, 0, 64)).expect("device descriptor");
    assert_eq!(transfer(setup(0x00, SET_ADDRESS, 7, 0, 0)), Ok(Vec::new()));
    assert_eq!(wire.borrow().address, Some(7));
    assert_eq!(dev.len(), 18);
    assert_eq!((dev[0], dev[1]), (18, 1));
    // bcdUSB 2.1: a BOS descriptor exists (Windows reads MS OS 2.0 from it).
    assert_eq!(le16(&dev[2..]), 0x0210);
    // Composite with interface association: EF/02/01.
    assert_eq!((dev[4], dev[5], dev[6]), (0xEF, 0x02, 0x01));
    assert_eq!(dev[7] as u16, MAX_PACKET);
    assert_eq!((le16(&dev[8..]), le16(&dev[10..])), (USB_VID, USB_PID));
    assert_eq!(dev[17], 1, "one configuration");
    let serial_index = dev[16];
    assert_ne!(serial_index, 0, "a serial number string");

    // Strings: language ids, then the serial number in US English.
    let langs = transfer(setup(0x80, GET_DESCRIPTOR, 0x0300, 0, 255)).expect("languages");
    assert_eq!(langs, [4, 3, 0x09, 0x04]);
    let serial = transfer(setup(0x80, GET_DESCRIPTOR, 0x0300 | serial_index as u16, 0x0409, 255))
        .expect("the serial number");
    assert_eq!(&serial[2..], utf16("0123456789ABCDEF01234567").as_slice());
    for index in [dev[14], dev[15]] {
        let s = transfer(setup(0x80, GET_DESCRIPTOR, 0x0300 | index as u16, 0x0409, 255))
            .expect("manufacturer and product");
        assert!(s.len() > 2 && s[1] == 3);
    }

    // Configuration: first its header, then all of it (as Windows does).
    let head = transfer(setup(0x80, GET_DESCRIPTOR, 0x0200, 0, 9)).expect("configuration");
    let total = le16(&head[2..]);
    let config = transfer(setup(0x80, GET_DESCRIPTOR, 0x0200, 0, total)).expect("configuration");
    assert_eq!(config.len(), total as usize);
    let descs = descriptors(&config);
    let (_, c) = descs[0];
    assert_eq!(c[1], 2);
    assert_eq!(c[4], 3, "three interfaces");
    assert_eq!(c[8], 50, "100 mA in 2 mA units");
    // (number, class, endpoints as (address, attributes, max packet)).
    type Endpoints = Vec<(u8, u8, u16)>;
    let mut interfaces: Vec<(u8, u8, Endpoints)> = Vec::new();
    for &(ty, d) in &descs[1..] {
        match ty {
            4 => interfaces.push((d[2], d[5], Vec::new())),
            5 => interfaces.last_mut().expect("an interface").2.push((d[2], d[3], le16(&d[4..]))),
            _ => {}
        }
    }
    let classes: Vec<(u8, u8)> = interfaces.iter().map(|i| (i.0, i.1)).collect();
    assert_eq!(classes, [(0, 0x02), (1, 0x0A), (VENDOR_INTERFACE, 0xFF)]);
    // The vendor interface: one bulk OUT and one bulk IN of 64 bytes.
    let vendor = &interfaces[2].2;
    assert_eq!(vendor.len(), 2);
    assert!(vendor.iter().all(|&(_, attr, size)| attr == 2 && size == MAX_PACKET));
    assert_eq!(vendor.iter().filter(|e| e.0 & 0x80 != 0).count(), 1);
    // Within the F411's OTG_FS: 3 IN and 3 OUT beside EP0, all allocated.
    let all: Vec<u8> = interfaces.iter().flat_map(|i| i.2.iter().map(|e| e.0)).collect();
    assert_eq!(all.len(), wire.borrow().endpoints.len());
    assert!(all.iter().all(|&a| (1..=3).contains(&(a & 0x0F))), "endpoints {all:02x?}");
    assert_eq!(all.iter().filter(|&&a| a & 0x80 != 0).count(), 3);

    // BOS (USB 3.2 §9.6.2) with the MS OS 2.0 platform capability.
    let head = transfer(setup(0x80, GET_DESCRIPTOR, 0x0F00, 0, 5)).expect("BOS");
    let bos =
        transfer(setup(0x80, GET_DESCRIPTOR, 0x0F00, 0, le16(&head[2..]))).expect("the whole BOS");
    const MS_OS_20: [u8; 16] = [
        0xDF, 0x60, 0xDD, 0xD8, 0x89, 0x45, 0xC7, 0x4C, 0x9C, 0xD2, 0x65, 0x9D, 0x9E, 0x64, 0x8A,
        0x9F,
    ];
    let platform = descriptors(&bos)
        .into_iter()
        .find(|&(ty, d)| ty == 0x10 && d[2] == 0x05 && d[4..20] == MS_OS_20)
        .expect("an MS OS 2.0 platform capability")
        .1;
    // dwWindowsVersion ≥ Windows 8.1, the set's length, the vendor code.
    assert!(u32::from_le_bytes(platform[20..24].try_into().unwrap()) >= 0x0603_0000);
    let set_len = le16(&platform[24..]);
    assert_eq!(platform[26], MSOS_VENDOR_CODE);

    // The descriptor set (Microsoft OS 2.0 Descriptors Specification, table 9).
    let set = transfer(setup(0xC0, MSOS_VENDOR_CODE, 0, 7, set_len)).expect("the MS OS 2.0 set");
    assert_eq!(set.len(), set_len as usize);
    let mut at = 0;
    let mut items = Vec::new();
    while at < set.len() {
        let (len, ty) = (le16(&set[at..]) as usize, le16(&set[at + 2..]));
        assert!(len >= 4 && at + len <= set.len());
        items.push((ty, &set[at..at + len]));
        at += len;
    }
    assert_eq!(items[0].0, 0, "set header first");
    assert_eq!(le16(&items[0].1[8..]) as usize, set.len(), "the header's total length");
    let function = items.iter().position(|i| i.0 == 2).expect("a function subset");
    assert_eq!(items[function].1[4], VENDOR_INTERFACE, "the subset is the vendor interface's");
    let features = &items[function + 1..];
    let compat = features.iter().find(|i| i.0 == 3).expect("a compatible id").1;
    assert_eq!(&compat[4..12], b"WINUSB\0\0");
    let reg = features.iter().find(|i| i.0 == 4).expect("a registry property").1;
    assert_eq!(le16(&reg[4..]), 7, "REG_MULTI_SZ");
    let name_len = le16(&reg[6..]) as usize;
    assert_eq!(&reg[8..8 + name_len], utf16("DeviceInterfaceGUIDs\0").as_slice());
    let data = &reg[10 + name_len..];
    assert_eq!(le16(&reg[8 + name_len..]) as usize, data.len());
    assert_eq!(data, utf16(&format!("{USB_WINUSB_GUID}\0\0")).as_slice());

    // A vendor request with another code is refused (STALL), not answered.
    assert_eq!(transfer(setup(0xC0, MSOS_VENDOR_CODE + 1, 0, 7, set_len)), Err(()));
}
