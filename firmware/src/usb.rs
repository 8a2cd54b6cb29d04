//! The controller's USB device, for any `embassy-usb` driver (feature
//! `usb`): the board builds it on the F411's OTG_FS, the tests on a model
//! of a bus that answers a host's control requests
//! (`firmware/tests/usb_descriptors.rs`), so the descriptors Windows and
//! Linux read are tested without a board.
//!
//! Two interfaces carry the same framed protocol (docs/protocol.md §1):
//! CDC-ACM (a tty for any serial tool: interfaces 0 and 1) and a vendor
//! class bulk pair (interface 2, for hosts that talk USB directly with no
//! kernel driver). MS OS 2.0 descriptors make Windows bind WinUSB to the
//! vendor interface by itself (no .inf, no Zadig), with the device
//! interface GUID [`protocol::USB_WINUSB_GUID`].
//!
//! Endpoints: IN — EP0, the CDC notification, CDC bulk, vendor bulk; OUT —
//! EP0, CDC bulk, vendor bulk: within the F411 OTG_FS's 4 IN and 4 OUT.

use embassy_sync::blocking_mutex::raw::RawMutex;
use embassy_sync::pipe::Pipe;
use embassy_usb::class::cdc_acm::{CdcAcmClass, State};
use embassy_usb::driver::Driver;
use embassy_usb::msos::{self, windows_version};
use embassy_usb::{Builder, UsbDevice};
use protocol::{USB_PID, USB_VID, USB_WINUSB_GUID};

/// The vendor request code of the MS OS 2.0 descriptor set (any value the
/// device does not use otherwise; the BOS descriptor tells it to Windows).
pub const MSOS_VENDOR_CODE: u8 = 0x01;
/// Largest packet of every bulk endpoint and of EP0 (full speed).
pub const MAX_PACKET: u16 = crate::hal::USB_TX_PACKET as u16;
/// The vendor interface's number (after CDC-ACM's two).
pub const VENDOR_INTERFACE: u8 = 2;

/// The memory a USB device borrows for its lifetime (a `static` on the
/// board).
pub struct UsbBuffers<'d> {
    config_descriptor: [u8; 256],
    bos_descriptor: [u8; 256],
    msos_descriptor: [u8; 256],
    control: [u8; 64],
    cdc: State<'d>,
}

impl core::fmt::Debug for UsbBuffers<'_> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str("UsbBuffers")
    }
}

impl Default for UsbBuffers<'_> {
    fn default() -> Self {
        UsbBuffers {
            config_descriptor: [0; 256],
            bos_descriptor: [0; 256],
            msos_descriptor: [0; 256],
            control: [0; 64],
            cdc: State::new(),
        }
    }
}

/// The built device: run `device`, and move bytes through the two
/// interfaces.
pub struct UsbParts<'d, D: Driver<'d>> {
    /// The device: run it for the bus's lifetime.
    pub device: UsbDevice<'d, D>,
    /// CDC-ACM, interfaces 0 and 1.
    pub cdc: CdcAcmClass<'d, D>,
    /// The vendor interface's bulk OUT endpoint.
    pub vendor_out: D::EndpointOut,
    /// The vendor interface's bulk IN endpoint.
    pub vendor_in: D::EndpointIn,
}

impl<'d, D: Driver<'d>> core::fmt::Debug for UsbParts<'d, D> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str("UsbParts")
    }
}

/// The controller's USB device on `driver`; `serial` is the board's
/// serial-number string (its unique id).
pub fn build<'d, D: Driver<'d>>(
    driver: D,
    serial: &'d str,
    buffers: &'d mut UsbBuffers<'d>,
) -> UsbParts<'d, D> {
    let mut config = embassy_usb::Config::new(USB_VID, USB_PID);
    config.manufacturer = Some("Material Scanner");
    config.product = Some("Scanner controller");
    config.serial_number = Some(serial);
    config.max_power = 100;
    config.max_packet_size_0 = MAX_PACKET as u8;
    let mut builder = Builder::new(
        driver,
        config,
        &mut buffers.config_descriptor,
        &mut buffers.bos_descriptor,
        &mut buffers.msos_descriptor,
        &mut buffers.control,
    );
    builder.msos_descriptor(windows_version::WIN8_1, MSOS_VENDOR_CODE);
    let cdc = CdcAcmClass::new(&mut builder, &mut buffers.cdc, MAX_PACKET);
    let (vendor_out, vendor_in) = {
        let mut function = builder.function(0xFF, 0x00, 0x00);
        function.msos_feature(msos::CompatibleIdFeatureDescriptor::new("WINUSB", ""));
        function.msos_feature(msos::RegistryPropertyFeatureDescriptor::new(
            "DeviceInterfaceGUIDs",
            msos::PropertyData::RegMultiSz(&[USB_WINUSB_GUID]),
        ));
        let mut interface = function.interface();
        let mut alt = interface.alt_setting(0xFF, 0x00, 0x00, None);
        (alt.endpoint_bulk_out(None, MAX_PACKET), alt.endpoint_bulk_in(None, MAX_PACKET))
    };
    UsbParts { device: builder.build(), cdc, vendor_out, vendor_in }
}

/// Queue `bytes` (one flushed frame) for the host whole, or not at all: the
/// board's replies and events wait in a `Pipe` that the USB task drains in
/// packets. `Pipe::try_write` copies only up to the end of its ring, so a
/// single call would cut a frame that crosses it — once every ring length of
/// output, the frame's tail and with it the next frame would be lost.
/// Returns whether the frame was queued; one that does not fit is dropped
/// (the host recovers replies by retransmitting, events from the status).
pub fn queue_whole<M: RawMutex, const N: usize>(pipe: &Pipe<M, N>, bytes: &[u8]) -> bool {
    if pipe.free_capacity() < bytes.len() {
        return false;
    }
    let mut rest = bytes;
    while !rest.is_empty() {
        match pipe.try_write(rest) {
            Ok(n) => rest = &rest[n..],
            // Only another writer filling it in between could do this: the
            // frame's head is out, and the next frame's delimiter ends it.
            Err(_) => return false,
        }
    }
    true
}
