//! Atomic outputs: write a temporary file in the destination's directory,
//! flush it to disk, rename it over the destination and flush the directory,
//! so a reader sees the old file or the new one, never a partial one, and a
//! power loss cannot lose the rename.
//!
//! What is at the output path is checked first: an existing output must be
//! a regular file (not a device node such as `/dev/null` or `/dev/full`, a
//! FIFO, a socket, a directory or a symbolic link — writing through a link
//! would replace its target, renaming over it would replace the link), and
//! never one of the command's inputs.

use std::io::Write;
use std::path::{Path, PathBuf};

/// Why an output path is refused.
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    /// Something other than a regular file is there.
    #[error("{}: {what}; refusing to replace it (choose a regular file)", path.display())]
    NotRegular {
        /// The output path.
        path: PathBuf,
        /// What is there.
        what: &'static str,
    },
    /// The output is one of the inputs.
    #[error("{}: the output would replace the input {}", path.display(), input.display())]
    IsInput {
        /// The output path.
        path: PathBuf,
        /// The input it is.
        input: PathBuf,
    },
}

impl From<OutputError> for std::io::Error {
    fn from(e: OutputError) -> std::io::Error {
        std::io::Error::new(std::io::ErrorKind::InvalidInput, e.to_string())
    }
}

/// Check that `path` may be written: nothing there, or a regular file that
/// is none of `inputs` (compared by device and inode, so another name of
/// the same file is caught too).
pub fn check_output(path: &Path, inputs: &[&Path]) -> Result<(), OutputError> {
    let meta = match std::fs::symlink_metadata(path) {
        Ok(m) => m,
        Err(_) => return Ok(()), // nothing there (or unreachable: the write will say)
    };
    let ft = meta.file_type();
    let what = if ft.is_symlink() {
        Some("a symbolic link")
    } else if ft.is_dir() {
        Some("a directory")
    } else if ft.is_file() {
        None
    } else {
        Some(special_kind(&ft))
    };
    if let Some(what) = what {
        return Err(OutputError::NotRegular { path: path.to_path_buf(), what });
    }
    for input in inputs {
        if same_file(path, input) {
            return Err(OutputError::IsInput {
                path: path.to_path_buf(),
                input: input.to_path_buf(),
            });
        }
    }
    Ok(())
}

#[cfg(unix)]
fn special_kind(ft: &std::fs::FileType) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    if ft.is_block_device() || ft.is_char_device() {
        "a device node"
    } else if ft.is_fifo() {
        "a FIFO"
    } else if ft.is_socket() {
        "a socket"
    } else {
        "not a regular file"
    }
}

#[cfg(not(unix))]
fn special_kind(_: &std::fs::FileType) -> &'static str {
    "not a regular file"
}

#[cfg(unix)]
fn same_file(a: &Path, b: &Path) -> bool {
    use std::os::unix::fs::MetadataExt;
    match (std::fs::metadata(a), std::fs::metadata(b)) {
        (Ok(x), Ok(y)) => x.dev() == y.dev() && x.ino() == y.ino(),
        _ => false,
    }
}

#[cfg(not(unix))]
fn same_file(a: &Path, b: &Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(x), Ok(y)) => x == y,
        _ => false,
    }
}

/// Write `bytes` to `path` atomically.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    write_atomic_with(path, |w| w.write_all(bytes))
}

/// Write `path` atomically with `fill` producing the contents.
pub fn write_atomic_with(
    path: &Path,
    fill: impl FnOnce(&mut dyn Write) -> std::io::Result<()>,
) -> std::io::Result<()> {
    check_output(path, &[])?;
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let mut tmp = tempfile::Builder::new().prefix(".tmp-").tempfile_in(dir)?;
    // Temporary files are created private (0600); a finished file should
    // have the permissions of the one it replaces, or ordinary ones.
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(path).map(|m| m.permissions().mode()).unwrap_or(0o644);
        tmp.as_file().set_permissions(std::fs::Permissions::from_mode(mode))?;
    }
    {
        let mut w = std::io::BufWriter::new(tmp.as_file_mut());
        fill(&mut w)?;
        w.flush()?;
    }
    tmp.as_file().sync_all()?;
    tmp.persist(path).map_err(|e| e.error)?;
    sync_dir(dir)
}

/// Flush a directory's entries (after a rename into it).
pub fn sync_dir(dir: &Path) -> std::io::Result<()> {
    #[cfg(unix)]
    {
        std::fs::File::open(dir)?.sync_all()?;
    }
    #[cfg(not(unix))]
    let _ = dir;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refuses_what_it_must_not_replace() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("a.txt");
        write_atomic(&file, b"one").unwrap();
        write_atomic(&file, b"two").unwrap();
        assert_eq!(std::fs::read(&file).unwrap(), b"two");
        // A device node.
        let e = check_output(Path::new("/dev/null"), &[]).unwrap_err();
        assert!(e.to_string().contains("a device node"), "{e}");
        assert!(write_atomic(Path::new("/dev/null"), b"x").is_err());
        // A symbolic link: neither it nor its target is touched.
        #[cfg(unix)]
        {
            let link = dir.path().join("link");
            std::os::unix::fs::symlink(&file, &link).unwrap();
            let e = write_atomic(&link, b"three").unwrap_err();
            assert!(e.to_string().contains("symbolic link"), "{e}");
            assert_eq!(std::fs::read(&file).unwrap(), b"two");
            assert!(std::fs::symlink_metadata(&link).unwrap().file_type().is_symlink());
        }
        // A directory.
        assert!(matches!(
            check_output(dir.path(), &[]),
            Err(OutputError::NotRegular { what: "a directory", .. })
        ));
        // The input, also under another name.
        let other = dir.path().join("b.txt");
        std::fs::hard_link(&file, &other).unwrap();
        assert!(matches!(check_output(&other, &[&file]), Err(OutputError::IsInput { .. })));
        assert!(check_output(&dir.path().join("new"), &[&file]).is_ok());
    }
}
