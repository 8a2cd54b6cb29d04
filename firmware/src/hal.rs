//! What the controller needs from the hardware, as small traits and plain
//! data. The board binary implements them with embassy-stm32; `hil-sim` with
//! simulated motors, switches and a simulated clock.

use protocol::{AXIS_COUNT, Axis, ResetReason};

use crate::step::StepGenerator;

/// The step timer's tick rate: the F411's 96 MHz timer clock (96 MHz so that
/// USB gets its exact 48 MHz) prescaled by 8.
pub const TICK_HZ: u32 = 12_000_000;

/// Ticks per millisecond.
pub const TICKS_PER_MS: u64 = TICK_HZ as u64 / 1000;
/// Ticks per microsecond.
pub const TICKS_PER_US: u64 = TICK_HZ as u64 / 1_000_000;

/// A snapshot of the digital inputs, taken by the caller of
/// [`Controller::poll`](crate::Controller::poll).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Inputs {
    /// The home / index sensor's line per axis is high (its electrical
    /// level: whether that is actuated depends on
    /// `HomeSensors::active_high`).
    pub home_line: [bool; AXIS_COUNT],
    /// Emergency-stop input asserted.
    pub estop: bool,
    /// The drivers' fault line is high (its electrical level: whether that
    /// is a fault depends on `BoardConfig::driver_fault_active_high`).
    pub driver_fault_line: bool,
    /// The camera's "exposure active" strobe line is high (its electrical
    /// level: whether that means exposing depends on
    /// `StrobeConfig::active_high`; a board without the input reads it
    /// low).
    pub strobe_line: bool,
}

/// Outputs and services the controller drives.
pub trait Hardware {
    /// Run `f` on the step generator of `axis`. The step interrupt shares the
    /// generators, so on hardware this takes a critical section: keep `f`
    /// short (the controller plans segments outside it and only pushes here).
    fn with_stepper<R>(&mut self, axis: Axis, f: impl FnOnce(&mut StepGenerator) -> R) -> R;
    /// Set the DIR line of `axis` before its first step.
    fn set_direction(&mut self, axis: Axis, positive: bool);
    /// Schedule the first step of a move of `axis` at `tick`; the step
    /// interrupt then keeps itself armed from [`StepGenerator::step`].
    fn arm_step_timer(&mut self, axis: Axis, tick: u64);
    /// Cancel any scheduled step of `axis`.
    fn disarm_step_timer(&mut self, axis: Axis);
    /// Enable or disable the stepper drivers (EN lines).
    fn set_drivers_enabled(&mut self, enabled: bool);
    /// Light output: 0 = off, else PWM duty in per mille.
    fn set_light(&mut self, duty_permille: u16);
    /// Camera trigger output level. `false` lowers it at once: the end of
    /// an exposure, or an abort in the middle of one.
    fn set_trigger(&mut self, high: bool);
    /// Raise the camera trigger for `ticks` ticks: the camera's exposure.
    ///
    /// A board whose timer ends the pulse by itself ([`crate::trigger`])
    /// does so and returns the tick by which the pulse has certainly ended;
    /// the controller then keeps the light on until that tick and only
    /// then calls `set_trigger(false)`. The default raises the line and
    /// returns `None`: the controller lowers it `ticks` later, and the
    /// pulse is as exact as its wake-up at that tick (the simulator's is).
    fn start_trigger_pulse(&mut self, ticks: u64) -> Option<u64> {
        let _ = ticks;
        self.set_trigger(true);
        None
    }
    /// Persist the configuration blob (axis configs and mirror table).
    fn save_config(&mut self, blob: &[u8]) -> Result<(), StorageError>;
}

/// Persistent storage failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct StorageError;

/// Who the device is and why it booted; fixed for one boot.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BootInfo {
    /// An id that differs from boot to boot (the board: a CRC of the chip
    /// id, the flash boot counter and a RAM boot counter).
    pub boot_id: u32,
    /// Why it booted.
    pub reason: ResetReason,
    /// Unique device id (chip UID).
    pub device_id: [u8; 12],
    /// Board id (`protocol::BOARD_*`).
    pub board: u16,
    /// Capabilities.
    pub capabilities: protocol::Capabilities,
    /// Persistent storage failed at boot (latched as `STORAGE_FAILED`).
    pub storage_failed: bool,
}

/// The board's boot id: the protocol's CRC-32C over the chip id, the flash
/// boot counter and the RAM boot counter (little-endian). Two boots of one
/// chip where only one counter differs always get different ids (the
/// inputs differ within one 32-bit field: a burst a CRC of degree 32
/// always detects), so a failed flash store (the flash counter repeats)
/// still changes the id through the RAM counter; where both differ, ids
/// collide with probability 2⁻³².
pub fn boot_id(device_id: &[u8; 12], flash_boots: u32, ram_boots: u32) -> u32 {
    let mut bytes = [0u8; 20];
    bytes[..12].copy_from_slice(device_id);
    bytes[12..16].copy_from_slice(&flash_boots.to_le_bytes());
    bytes[16..].copy_from_slice(&ram_boots.to_le_bytes());
    protocol::CRC.checksum(&bytes)
}

/// Bytes of replies and events the board holds for the host: frames are
/// queued whole or dropped whole when they do not fit (the host recovers
/// replies by retransmitting, events from the status).
pub const USB_TX_QUEUE: usize = 1024;
/// Largest USB packet the board sends (full-speed bulk).
pub const USB_TX_PACKET: usize = 64;
/// How long a packet may wait for the host to read it before it is dropped
/// (ms): a host that stopped reading, or switched interfaces, must not stall
/// the board's output.
pub const USB_TX_TIMEOUT_MS: u64 = 200;
/// After a `Reset` or `EnterBootloader` request, once its reply has left
/// the queue, the board waits this long (ms) for the host to take it before
/// it resets, and its USB port goes away.
pub const RESET_AFTER_REPLY_MS: u64 = 20;

/// Where the board sends a packet for the host: `(vendor bulk, CDC-ACM)`.
/// Until the host has spoken on either interface (the `Boot` event, events
/// after a reset) everything goes to both, so a host on either sees it;
/// then only to the interface it last spoke on.
pub const fn usb_destinations(host_spoke: bool, vendor_active: bool) -> (bool, bool) {
    if host_spoke { (vendor_active, !vendor_active) } else { (true, true) }
}

#[cfg(test)]
mod tests {
    use super::{boot_id, usb_destinations};

    #[test]
    fn the_boot_id_changes_with_either_counter() {
        let chip = *b"\x27\x00\x41\x00\x0e\x51\x38\x33\x30\x32\x36\x39";
        // A stuck flash counter (storage failed) with the RAM counter
        // counting, and the other way round, from values that wrap.
        for start in [0u32, 1, 0x7FFF_FFF0, u32::MAX - 20] {
            let distinct = |mut ids: [u32; 40]| {
                ids.sort_unstable();
                ids.windows(2).all(|w| w[0] != w[1])
            };
            let ram = core::array::from_fn(|k| boot_id(&chip, 7, start.wrapping_add(k as u32)));
            assert!(distinct(ram), "RAM counter from {start:#x}");
            let flash = core::array::from_fn(|k| boot_id(&chip, start.wrapping_add(k as u32), 3));
            assert!(distinct(flash), "flash counter from {start:#x}");
        }
        // Another chip with the same counters: another id.
        let mut other = chip;
        other[11] ^= 1;
        assert_ne!(boot_id(&chip, 5, 9), boot_id(&other, 5, 9));
    }

    #[test]
    fn boot_goes_to_both_interfaces_then_to_the_one_the_host_uses() {
        assert_eq!(usb_destinations(false, false), (true, true));
        assert_eq!(usb_destinations(false, true), (true, true));
        assert_eq!(usb_destinations(true, true), (true, false));
        assert_eq!(usb_destinations(true, false), (false, true));
    }
}
