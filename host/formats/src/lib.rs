//! # scanner-formats
//!
//! Files the scanner's programs share, so that each format has one reader
//! and one writer:
//! - [`atomic`]: outputs written atomically (temporary file, fsync, rename,
//!   directory fsync) that never replace a device node, a symlink's target,
//!   a directory or one of the command's inputs;
//! - [`input`]: inputs read only from regular files (never endlessly from a
//!   device or waiting on a FIFO);
//! - [`direct`]: direct images of a large piece and their manifest
//!   (`hil-sim direct` writes them, `scanner enlarge` reads them;
//!   docs/direct-images.md);
//! - [`queries`]: shading query files (`u, v, wi, wo` rows) and their answer
//!   files (`r, g, b` rows), as `.npy` or `.csv` — `hil-sim truth` and
//!   `scanner shade` read and write the same files (docs/query-format.md).

pub mod atomic;
pub mod direct;
pub mod input;
pub mod queries;

pub use atomic::{OutputError, check_output, write_atomic, write_atomic_with};
