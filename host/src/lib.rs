//! Host library: device link, scan capture, material building, NPF fitting.

pub use protocol;
