//! Axis defaults (spec/hardware.md, "Axes"), configuration validation and the
//! persisted configuration blob.

use heapless::Vec;
use protocol::{
    AXIS_COUNT, AxisConfig, BoardConfig, DEFAULT_STROBE_DELAY_US, HomeSensors, MAX_MIRRORS,
    MAX_STROBE_DELAY_US, MirrorPosition, StrobeConfig,
};
use serde::{Deserialize, Serialize};

// The speed range and the validity rule live in `protocol`, which the
// host checks an axis configuration file with before sending it.
pub use protocol::{MAX_AXIS_SPEED as MAX_SPEED, MIN_AXIS_SPEED as MIN_SPEED};

// The spec's default axes live in `protocol`, which the host's design
// check (`scanner geometry`) reads too: one copy of the travel limits.
pub use protocol::{default_axes, disk_default, tilt_default, track_default};

/// Whether `c` is a configuration the controller can execute
/// ([`AxisConfig::problem`]).
pub fn is_valid(c: &AxisConfig) -> bool {
    c.problem().is_none()
}

/// Format version of [`PersistedConfig`] (2 added the board options, 3
/// the home sensors' polarity, 4 the exposure strobe; blobs of formats 1
/// to 3 still load, with the defaults for what they lack).
pub const CONFIG_FORMAT: u16 = 4;

/// The strobe's settings after boot without any saved: not watched,
/// active low (an open-collector output against the board's pull-up),
/// [`DEFAULT_STROBE_DELAY_US`].
pub const fn strobe_default() -> StrobeConfig {
    StrobeConfig { enabled: false, active_high: false, max_delay_us: DEFAULT_STROBE_DELAY_US }
}

/// Whether the controller can watch a strobe configured as `c`.
pub const fn strobe_is_valid(c: &StrobeConfig) -> bool {
    c.max_delay_us >= 1 && c.max_delay_us <= MAX_STROBE_DELAY_US
}

/// What [`protocol::Request::SaveConfig`] writes to flash (postcard-encoded).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PersistedConfig {
    /// [`CONFIG_FORMAT`].
    pub format: u16,
    /// Axis configurations.
    pub axes: [AxisConfig; AXIS_COUNT],
    /// Mirror table; its length is the mirror count.
    pub mirrors: Vec<Option<MirrorPosition>, MAX_MIRRORS>,
    /// The board's wiring options.
    pub board: BoardConfig,
    /// The home / index sensors' polarity.
    pub home: HomeSensors,
    /// The camera's exposure strobe.
    pub strobe: StrobeConfig,
}

/// Format 3: the same without the exposure strobe.
#[derive(Deserialize)]
struct PersistedConfigV3 {
    _format: u16,
    axes: [AxisConfig; AXIS_COUNT],
    mirrors: Vec<Option<MirrorPosition>, MAX_MIRRORS>,
    board: BoardConfig,
    home: HomeSensors,
}

/// Format 2: the same without the home sensors' polarity.
#[derive(Deserialize)]
struct PersistedConfigV2 {
    _format: u16,
    axes: [AxisConfig; AXIS_COUNT],
    mirrors: Vec<Option<MirrorPosition>, MAX_MIRRORS>,
    board: BoardConfig,
}

/// Format 1: the same without the board options.
#[derive(Deserialize)]
struct PersistedConfigV1 {
    _format: u16,
    axes: [AxisConfig; AXIS_COUNT],
    mirrors: Vec<Option<MirrorPosition>, MAX_MIRRORS>,
}

/// Largest encoded [`PersistedConfig`], bytes.
pub const PERSISTED_MAX_LEN: usize =
    2 + AXIS_COUNT * 64 + 1 + MAX_MIRRORS * 16 + 1 + AXIS_COUNT + 2 + 5;

impl Default for PersistedConfig {
    fn default() -> Self {
        PersistedConfig {
            format: CONFIG_FORMAT,
            axes: default_axes(),
            mirrors: Vec::new(),
            board: BoardConfig::default(),
            home: HomeSensors::default(),
            strobe: strobe_default(),
        }
    }
}

impl PersistedConfig {
    /// Decode a blob; `None` if it is not a valid configuration of this format.
    pub fn decode(blob: &[u8]) -> Option<PersistedConfig> {
        let format = postcard::from_bytes::<u16>(blob).ok()?;
        let cfg = match format {
            CONFIG_FORMAT => postcard::from_bytes::<PersistedConfig>(blob).ok()?,
            3 => {
                let v3: PersistedConfigV3 = postcard::from_bytes(blob).ok()?;
                PersistedConfig {
                    format: CONFIG_FORMAT,
                    axes: v3.axes,
                    mirrors: v3.mirrors,
                    board: v3.board,
                    home: v3.home,
                    strobe: strobe_default(),
                }
            }
            2 => {
                let v2: PersistedConfigV2 = postcard::from_bytes(blob).ok()?;
                PersistedConfig {
                    format: CONFIG_FORMAT,
                    axes: v2.axes,
                    mirrors: v2.mirrors,
                    board: v2.board,
                    home: HomeSensors::default(),
                    strobe: strobe_default(),
                }
            }
            1 => {
                let v1: PersistedConfigV1 = postcard::from_bytes(blob).ok()?;
                PersistedConfig {
                    format: CONFIG_FORMAT,
                    axes: v1.axes,
                    mirrors: v1.mirrors,
                    board: BoardConfig::default(),
                    home: HomeSensors::default(),
                    strobe: strobe_default(),
                }
            }
            _ => return None,
        };
        (cfg.axes.iter().all(is_valid) && strobe_is_valid(&cfg.strobe)).then_some(cfg)
    }

    /// Encode into `buf`; returns the used part.
    pub fn encode<'a>(&self, buf: &'a mut [u8]) -> Option<&'a mut [u8]> {
        postcard::to_slice(self, buf).ok()
    }
}
