//! Finding scanners: serial ports (CDC-ACM, found through sysfs — no
//! libudev) and USB devices with the project's VID/PID, with their serial
//! numbers; choosing one by serial number or path.

use protocol::{USB_PID, USB_VID};

/// A scanner reachable over a serial port.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SerialScanner {
    /// Port path.
    pub path: String,
    /// USB serial number (the board's unique id), if it is a USB port.
    pub serial: Option<String>,
}

/// A scanner on USB with a vendor-class (bulk) interface.
#[derive(Debug, Clone)]
pub struct UsbScanner {
    /// nusb's handle for opening it.
    pub info: nusb::DeviceInfo,
    /// USB serial number.
    pub serial: String,
    /// Bus and address, for messages.
    pub location: String,
    /// The vendor-class interface number, if it has one.
    pub vendor_interface: Option<u8>,
}

/// Serial ports whose USB VID/PID are ours.
pub fn serial_scanners() -> Result<Vec<SerialScanner>, String> {
    let ports = serialport::available_ports().map_err(|e| format!("listing serial ports: {e}"))?;
    Ok(ports
        .into_iter()
        .filter_map(|p| match p.port_type {
            serialport::SerialPortType::UsbPort(u) if u.vid == USB_VID && u.pid == USB_PID => {
                Some(SerialScanner { path: p.port_name, serial: u.serial_number })
            }
            _ => None,
        })
        .collect())
}

/// The scanner among `list` at `path`: the same port by name, or by what
/// both names resolve to — a `/dev/serial/by-id/…` link names the
/// `/dev/ttyACMn` the listing has.
pub fn scanner_at<'a>(path: &str, list: &'a [SerialScanner]) -> Option<&'a SerialScanner> {
    list.iter().find(|p| p.path == path).or_else(|| {
        let real = std::fs::canonicalize(path).ok()?;
        list.iter().find(|p| std::fs::canonicalize(&p.path).is_ok_and(|r| r == real))
    })
}

/// The links in `dir` (udev's `/dev/serial/by-id`) that resolve to `path`:
/// names that stay when the board comes back as another `ttyACMn`.
pub fn links_to(path: &str, dir: &std::path::Path) -> Vec<String> {
    let Ok(real) = std::fs::canonicalize(path) else { return Vec::new() };
    let mut links: Vec<String> = std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.path())
        .filter(|l| std::fs::symlink_metadata(l).is_ok_and(|m| m.file_type().is_symlink()))
        .filter(|l| std::fs::canonicalize(l).is_ok_and(|r| r == real))
        .filter_map(|l| l.to_str().map(str::to_string))
        .collect();
    links.sort();
    links
}

/// USB devices with our VID/PID.
pub fn usb_devices() -> Result<Vec<UsbScanner>, String> {
    use nusb::MaybeFuture;
    let list = nusb::list_devices().wait().map_err(|e| format!("listing USB devices: {e}"))?;
    Ok(list
        .filter(|d| d.vendor_id() == USB_VID && d.product_id() == USB_PID)
        .map(|d| {
            let vendor_interface =
                d.interfaces().find(|i| i.class() == 0xFF).map(|i| i.interface_number());
            UsbScanner {
                serial: d.serial_number().unwrap_or("").to_string(),
                location: format!("bus {} address {}", d.busnum(), d.device_address()),
                vendor_interface,
                info: d,
            }
        })
        .collect())
}

/// The STM32 ROM bootloader's USB DFU identity (ST's VID, its DFU PID).
pub const STM32_DFU: (u16, u16) = (0x0483, 0xdf11);

/// USB devices in the STM32 ROM bootloader (USB DFU): where they are.
pub fn dfu_bootloaders() -> Result<Vec<String>, String> {
    use nusb::MaybeFuture;
    let list = nusb::list_devices().wait().map_err(|e| format!("listing USB devices: {e}"))?;
    Ok(list
        .filter(|d| (d.vendor_id(), d.product_id()) == STM32_DFU)
        .map(|d| format!("bus {} address {}", d.busnum(), d.device_address()))
        .collect())
}

/// How to reach the device the user named.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum DeviceChoice {
    /// The in-process simulator.
    Simulator,
    /// A serial port path.
    Serial(String),
    /// USB bulk, by serial number.
    Usb(String),
}

/// Resolve `--device`: `sim`, a path (contains `/`, or `COM…`), `usb:SERIAL`,
/// or a bare serial number looked up among serial ports then USB devices.
pub fn choose(device: &str) -> Result<DeviceChoice, String> {
    if device == "sim" {
        return Ok(DeviceChoice::Simulator);
    }
    if let Some(serial) = device.strip_prefix("usb:") {
        return Ok(DeviceChoice::Usb(serial.to_string()));
    }
    if device.contains('/') || device.starts_with("COM") {
        return Ok(DeviceChoice::Serial(device.to_string()));
    }
    let serial_ports = serial_scanners().unwrap_or_default();
    if let Some(p) = serial_ports.iter().find(|p| p.serial.as_deref() == Some(device)) {
        return Ok(DeviceChoice::Serial(p.path.clone()));
    }
    match usb_devices() {
        Ok(list) if list.iter().any(|d| d.serial == device) => {
            Ok(DeviceChoice::Usb(device.to_string()))
        }
        Ok(_) => Err(format!("no scanner with serial number {device:?} (try `scanner devices`)")),
        Err(e) => Err(format!("no serial port with serial number {device:?}, and {e}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A by-id link finds the port the listing names by its device node;
    /// another node, or a link to it, does not.
    #[test]
    fn a_by_id_link_names_the_listed_port() {
        let dir = tempfile::tempdir().unwrap();
        let node = dir.path().join("ttyACM0");
        let other = dir.path().join("ttyACM1");
        std::fs::write(&node, b"").unwrap();
        std::fs::write(&other, b"").unwrap();
        let by_id = dir.path().join("usb-Scanner_0042-if00");
        std::os::unix::fs::symlink(&node, &by_id).unwrap();
        let to_other = dir.path().join("usb-Other-if00");
        std::os::unix::fs::symlink(&other, &to_other).unwrap();
        let s = |p: &std::path::Path| p.to_str().unwrap().to_string();
        let list = [SerialScanner { path: s(&node), serial: Some("0042".into()) }];
        let found = |p: &std::path::Path| scanner_at(&s(p), &list).and_then(|x| x.serial.clone());
        assert_eq!(found(&node).as_deref(), Some("0042"));
        assert_eq!(found(&by_id).as_deref(), Some("0042"));
        assert_eq!(found(&other), None);
        assert_eq!(found(&to_other), None);
        assert_eq!(found(&dir.path().join("gone")), None);
        assert_eq!(links_to(&s(&node), dir.path()), [s(&by_id)]);
        assert_eq!(links_to(&s(&other), dir.path()), [s(&to_other)]);
        assert_eq!(links_to(&s(&by_id), dir.path()), [s(&by_id)]);
        assert!(links_to(&s(&node), &dir.path().join("none")).is_empty());
    }
}
