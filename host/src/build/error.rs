//! Why building failed, with the `scanner` exit code of each kind.

/// A builder failure.
#[derive(Debug, thiserror::Error)]
pub enum BuildError {
    /// A bad input: a scan with missing frames or of another geometry, a
    /// frame of the wrong size, a region that cannot be found, a white
    /// target at the noise floor, a damaged calibration file.
    #[error("{0}")]
    Input(String),
    /// An output could not be written.
    #[error("{0}")]
    Output(String),
}

impl BuildError {
    /// Process exit code: 3 bad input, 4 output not written.
    pub fn exit_code(&self) -> u8 {
        match self {
            BuildError::Input(_) => 3,
            BuildError::Output(_) => 4,
        }
    }
}
