//! The chip's ROM bootloader, reached by [`protocol::Request::EnterBootloader`]
//! (protocol 1.5, capability `SYSTEM_BOOTLOADER`): the firmware can be
//! flashed over USB (DFU) without a probe.
//!
//! The controller stops everything and answers; the board, once the answer
//! is sent, writes [`REQUEST_MARK`] into a RAM word the reset does not clear
//! and resets. The first thing its next boot does — before any clock or
//! peripheral is set up, as the ROM expects the chip — is
//! [`take_request`]: on the mark it clears it (so the boot after the ROM's
//! is the firmware's), maps the system memory at address 0
//! ([`map_system_memory`]) and jumps through the ROM's vector table at
//! [`SYSTEM_MEMORY`].
//!
//! The register sequence is written against [`Registers`] so that a model
//! checks it on the host; the addresses are the STM32F4's (RM0383).

/// The RAM word's value that asks the next boot for the ROM bootloader.
pub const REQUEST_MARK: u32 = 0xB007_10AD;

/// STM32F4: the system memory, where the ROM bootloader's vector table is.
pub const SYSTEM_MEMORY: u32 = 0x1FFF_0000;

/// RCC_APB2ENR (RM0383 §6.3.12) and its SYSCFG clock enable bit.
pub const RCC_APB2ENR: u32 = 0x4002_3844;
/// SYSCFGEN in [`RCC_APB2ENR`].
pub const SYSCFGEN: u32 = 1 << 14;
/// SYSCFG_MEMRMP (RM0383 §7.2.1): MEM_MODE in bits 1:0.
pub const SYSCFG_MEMRMP: u32 = 0x4001_3800;
/// MEM_MODE's bits.
pub const MEM_MODE: u32 = 0b11;
/// MEM_MODE = 01: the system flash mapped at 0.
pub const MEM_MODE_SYSTEM_FLASH: u32 = 0b01;

/// SCB_VTOR (ARMv7-M): where the core finds its vector table.
pub const SCB_VTOR: u32 = 0xE000_ED08;

/// Whether the RAM word `mark` asks for the ROM bootloader; it is cleared
/// either way (after power-up it holds anything), so that only the boot
/// right after an [`protocol::Request::EnterBootloader`] goes there.
pub fn take_request(mark: &mut u32) -> bool {
    let asked = *mark == REQUEST_MARK;
    *mark = 0;
    asked
}

/// 32-bit memory-mapped registers, read-modify-written.
pub trait Registers {
    /// Clear the bits of `clear`, then set those of `set`, in the register
    /// at `address`.
    fn modify(&mut self, address: u32, clear: u32, set: u32);
}

/// Map the system memory (the ROM bootloader) at address 0: the SYSCFG's
/// clock on, then its memory remap, and the core's vector table at 0.
/// The ROM then finds its own vector table where the core looks for
/// interrupts, whatever the firmware had set.
pub fn map_system_memory(r: &mut impl Registers) {
    r.modify(RCC_APB2ENR, 0, SYSCFGEN);
    r.modify(SYSCFG_MEMRMP, MEM_MODE, MEM_MODE_SYSTEM_FLASH);
    r.modify(SCB_VTOR, u32::MAX, 0);
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Registers as a map of address to value, every access recorded.
    struct Model {
        values: [(u32, u32); 3],
        writes: [(u32, u32); 4],
        n: usize,
    }

    impl Registers for Model {
        fn modify(&mut self, address: u32, clear: u32, set: u32) {
            let slot =
                self.values.iter_mut().find(|(a, _)| *a == address).expect("a known register");
            slot.1 = (slot.1 & !clear) | set;
            self.writes[self.n] = (address, slot.1);
            self.n += 1;
        }
    }

    #[test]
    fn the_mark_is_taken_once_and_anything_else_boots_the_firmware() {
        let mut mark = REQUEST_MARK;
        assert!(take_request(&mut mark));
        assert_eq!(mark, 0);
        assert!(!take_request(&mut mark), "the boot after the ROM's is the firmware's");
        for garbage in [0, u32::MAX, REQUEST_MARK ^ 1, REQUEST_MARK.rotate_left(8)] {
            let mut m = garbage;
            assert!(!take_request(&mut m), "{garbage:#x}");
            assert_eq!(m, 0);
        }
    }

    #[test]
    fn the_system_memory_is_mapped_with_the_syscfg_clock_on_first() {
        // Reset values (RM0383): APB2ENR 0x0000_0000, MEMRMP as BOOT pins
        // left it (main flash: 00) — here other bits set to see them kept.
        let mut m = Model {
            values: [
                (RCC_APB2ENR, 0x0000_0011),
                (SYSCFG_MEMRMP, 0x0000_0000),
                (SCB_VTOR, 0x0800_0000),
            ],
            writes: [(0, 0); 4],
            n: 0,
        };
        map_system_memory(&mut m);
        assert_eq!(m.n, 3);
        assert_eq!(m.writes[0], (RCC_APB2ENR, 0x0000_4011), "SYSCFG clocked first, others kept");
        assert_eq!(m.writes[1], (SYSCFG_MEMRMP, 0b01), "system flash at 0");
        assert_eq!(m.writes[2], (SCB_VTOR, 0), "vectors from 0: the ROM's");
        // From a remap to SRAM (11), the same: 01.
        m.values[1].1 = 0b11;
        m.n = 0;
        map_system_memory(&mut m);
        assert_eq!(m.writes[1], (SYSCFG_MEMRMP, 0b01));
    }
}
