//! The `scanner` program, built inside this package so its end-to-end tests
//! can run it as a process (`CARGO_BIN_EXE_scanner-e2e`), kill it and run it
//! again.

fn main() -> std::process::ExitCode {
    host::cli::main()
}
