//! End-to-end tests across firmware, simulator and host live in `tests/tests/`.
