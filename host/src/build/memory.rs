//! Refusing work whose memory the machine cannot give, before anything is
//! allocated (region images of a large `--size`, the map of a large piece),
//! rather than being killed when it runs out.

use super::BuildError;

/// The memory the system can give this process without swapping, where it
/// says (Linux: `MemAvailable` in /proc/meminfo); `None` elsewhere.
pub fn available_memory() -> Option<u64> {
    let info = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = info.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    kib.checked_mul(1024)
}

/// A bad input when `need` bytes exceed `available` (unknown: allowed):
/// "`what` ≈ N GB; M GB of memory is available: `advice`", where `what`
/// says what needs it, its verb included.
pub fn check_memory(
    need: u128,
    available: Option<u64>,
    what: &str,
    advice: &str,
) -> Result<(), BuildError> {
    match available {
        Some(a) if need > a as u128 => Err(BuildError::Input(format!(
            "{what} ≈ {:.1} GB; {:.1} GB of memory is available: {advice}",
            need as f64 / 1e9,
            a as f64 / 1e9
        ))),
        _ => Ok(()),
    }
}
