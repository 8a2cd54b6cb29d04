//! Configuration persistence: the controller's config blob and a boot counter
//! in flash sectors 6–7 (0x08040000..0x08080000), wear-levelled by
//! `sequential-storage`'s key-value map.
//!
//! Saving is only allowed while the machine is idle (the controller refuses
//! `SaveConfig` while an axis moves: an erase stalls instruction fetch on the
//! single-bank F411, and with it the step interrupt). Erase times (STM32F411
//! datasheet, "Flash memory programming", 128 KB sector): 2 s typical, 4 s
//! maximum at x8 parallelism (PSIZE = 00, which embassy's erase leaves:
//! it clears PSIZE after every write), 1 s / 2 s at x32. The watchdog
//! (`main.rs`) is started after the boot-time flash work and is long enough
//! for a 4 s erase at the fastest LSI (47 kHz).

use embassy_embedded_hal::adapter::BlockingAsync;
use embassy_futures::block_on;
use embassy_stm32::flash::{Blocking, Flash};
use firmware::config::PERSISTED_MAX_LEN;
use firmware::hal::StorageError;
use sequential_storage::cache::{Cache, Uncached};
use sequential_storage::map::{MapConfig, MapStorage};

const RANGE: core::ops::Range<u32> = 0x4_0000..0x8_0000;
const KEY_CONFIG: u8 = 0;
const KEY_BOOT_COUNT: u8 = 1;

type ConfigMap = MapStorage<
    u8,
    BlockingAsync<Flash<'static, Blocking>>,
    Cache<Uncached, Uncached, Uncached, u8>,
>;

/// The configuration store.
pub struct Store {
    map: ConfigMap,
    buf: [u8; PERSISTED_MAX_LEN + 64],
}

impl Store {
    /// Open the store on the flash.
    pub fn new(flash: Flash<'static, Blocking>) -> Store {
        Store {
            map: MapStorage::new(
                BlockingAsync::new(flash),
                MapConfig::new(RANGE),
                Cache::new_uncached(),
            ),
            buf: [0; PERSISTED_MAX_LEN + 64],
        }
    }

    /// Read the saved configuration blob into `out`; its length.
    pub fn load_config(&mut self, out: &mut [u8]) -> Option<usize> {
        let blob: Option<&[u8]> = block_on(self.map.fetch_item(&mut self.buf, &KEY_CONFIG)).ok()?;
        let blob = blob?;
        let dest = out.get_mut(..blob.len())?;
        dest.copy_from_slice(blob);
        Some(blob.len())
    }

    /// Save a configuration blob.
    pub fn save_config(&mut self, blob: &[u8]) -> Result<(), StorageError> {
        block_on(self.map.store_item(&mut self.buf, &KEY_CONFIG, &blob)).map_err(|_| StorageError)
    }

    /// Increment and return the boot counter (0 on a blank flash); `Err`
    /// with the count it would have stored if the flash cannot store it.
    pub fn next_boot_count(&mut self) -> Result<u32, u32> {
        let n = block_on(self.map.fetch_item::<u32>(&mut self.buf, &KEY_BOOT_COUNT))
            .ok()
            .flatten()
            .map_or(0, |n| n.wrapping_add(1));
        match block_on(self.map.store_item(&mut self.buf, &KEY_BOOT_COUNT, &n)) {
            Ok(()) => Ok(n),
            Err(_) => Err(n),
        }
    }
}
