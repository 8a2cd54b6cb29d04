//! Atomic file writes that never replace a device node, a symlink's target,
//! a directory or an input: the shared implementation in
//! [`scanner_formats::atomic`].

pub use scanner_formats::atomic::*;
