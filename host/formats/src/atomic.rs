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
    /// Something other than a directory is where an output directory goes.
    #[error(
        "{}: {what}; refusing to replace it (choose a new or empty directory)",
        path.display()
    )]
    NotADirectory {
        /// The output path.
        path: PathBuf,
        /// What is there.
        what: &'static str,
    },
    /// The output would replace one of an input directory's own records.
    #[error(
        "{}: would replace a file of the input {} (its manifest, lock or frames); choose \
         another file",
        path.display(),
        input.display()
    )]
    InsideInput {
        /// The output path.
        path: PathBuf,
        /// The input directory it lies in.
        input: PathBuf,
    },
    /// An output directory holds a file the command did not write.
    #[error(
        "{}: holds {}, which this command did not write; refusing to replace it (choose a new or \
         empty directory)",
        path.display(),
        file.display()
    )]
    Foreign {
        /// The output directory.
        path: PathBuf,
        /// The first file found that is not the command's.
        file: PathBuf,
    },
    /// The output directory has no name of its own (`.`, `..`, `/`).
    #[error("{}: name a directory of its own for the output", path.display())]
    Unnamed {
        /// The output path.
        path: PathBuf,
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
    if let Some(what) = refusal(&meta.file_type(), false) {
        return Err(OutputError::NotRegular { path: path.to_path_buf(), what });
    }
    for input in inputs {
        if same_file(path, input) {
            return Err(OutputError::IsInput {
                path: path.to_path_buf(),
                input: input.to_path_buf(),
            });
        }
        if within(path, input) {
            return Err(OutputError::InsideInput {
                path: path.to_path_buf(),
                input: input.to_path_buf(),
            });
        }
    }
    Ok(())
}

/// Whether the existing file `path` is one of the input directory `dir`'s
/// own records: anything in its subdirectories (a scan's frames), or at
/// its top level a `manifest*` file or a dotfile (a scan's manifest, its
/// previous copy, its lock). An output of the command's own beside them
/// (`scan/sample.material`) may be replaced.
fn within(path: &Path, dir: &Path) -> bool {
    let (Ok(d), Ok(p)) = (dir.canonicalize(), parent_of(path).canonicalize()) else {
        return false;
    };
    if !d.is_dir() || !p.starts_with(&d) {
        return false;
    }
    let name = path.file_name().map(|n| n.to_string_lossy()).unwrap_or_default();
    p != d || name.starts_with("manifest") || name.starts_with('.')
}

/// What is at an output path if it is not what the output may replace —
/// a regular file, or with `want_dir` a real directory — else `None`.
fn refusal(ft: &std::fs::FileType, want_dir: bool) -> Option<&'static str> {
    if ft.is_symlink() {
        Some("a symbolic link")
    } else if ft.is_dir() {
        (!want_dir).then_some("a directory")
    } else if ft.is_file() {
        want_dir.then_some("a file, not a directory")
    } else {
        Some(special_kind(ft))
    }
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

/// Check that the directory `path` may be replaced by a command's output
/// directory: nothing there, or a directory (not a link) holding only
/// files whose names `ours` accepts — so never a user's other files, a
/// scan, or a directory holding an input.
pub fn check_output_dir(path: &Path, ours: impl Fn(&str) -> bool) -> Result<(), OutputError> {
    if path.file_name().is_none() {
        return Err(OutputError::Unnamed { path: path.to_path_buf() });
    }
    let meta = match std::fs::symlink_metadata(path) {
        Ok(m) => m,
        Err(_) => return Ok(()), // nothing there (or unreachable: the write will say)
    };
    if let Some(what) = refusal(&meta.file_type(), true) {
        return Err(OutputError::NotADirectory { path: path.to_path_buf(), what });
    }
    let foreign = |file: PathBuf| OutputError::Foreign { path: path.to_path_buf(), file };
    let entries = std::fs::read_dir(path).map_err(|_| foreign(path.to_path_buf()))?;
    for entry in entries {
        let entry = entry.map_err(|_| foreign(path.to_path_buf()))?;
        let name = entry.file_name();
        let is_file = entry.file_type().is_ok_and(|t| t.is_file());
        if !is_file || !name.to_str().is_some_and(&ours) {
            return Err(foreign(entry.path()));
        }
    }
    Ok(())
}

/// A new, uniquely named, empty directory beside `output` to fill before
/// [`replace_dir`] puts it in place; removed if dropped first.
pub fn staging_dir(output: &Path) -> std::io::Result<tempfile::TempDir> {
    let name = output.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    tempfile::Builder::new().prefix(&format!(".{name}.partial-")).tempdir_in(parent_of(output))
}

fn parent_of(path: &Path) -> &Path {
    match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    }
}

/// Put the finished directory `staging` (from [`staging_dir`]) at
/// `output`, whose old content (checked with [`check_output_dir`]) is
/// swapped out in one step where the system can (Linux), then removed. A
/// reader, or another process writing the same output, sees the old
/// directory or the new one, never a mixture.
pub fn replace_dir(staging: tempfile::TempDir, output: &Path) -> std::io::Result<()> {
    sync_dir(staging.path())?;
    let exists = std::fs::symlink_metadata(output).is_ok();
    if !exists {
        std::fs::rename(staging.path(), output)?;
        // Renamed away: nothing left for the guard to remove.
        let _ = staging.keep();
    } else if !exchange(staging.path(), output)? {
        // No atomic exchange here: move the old one aside under a unique name first.
        let old = staging_dir(output)?;
        std::fs::rename(output, old.path())?;
        if let Err(e) = std::fs::rename(staging.path(), output) {
            let _ = std::fs::rename(old.path(), output);
            return Err(e);
        }
        let _ = staging.keep();
        drop(old); // removes the old output
    }
    // After an exchange `staging` holds the old output; dropping it removes it.
    sync_dir(parent_of(output))
}

/// Swap two directories atomically; `Ok(false)` where the file system
/// cannot.
#[cfg(target_os = "linux")]
fn exchange(a: &Path, b: &Path) -> std::io::Result<bool> {
    use rustix::fs::{CWD, RenameFlags, renameat_with};
    match renameat_with(CWD, a, CWD, b, RenameFlags::EXCHANGE) {
        Ok(()) => Ok(true),
        Err(e) if e == rustix::io::Errno::INVAL || e == rustix::io::Errno::NOSYS => Ok(false),
        Err(e) => Err(e.into()),
    }
}

#[cfg(not(target_os = "linux"))]
fn exchange(_: &Path, _: &Path) -> std::io::Result<bool> {
    Ok(false)
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
    let dir = parent_of(path);
    // tempfile's own error names its random temporary path; name the directory.
    let mut tmp = tempfile::Builder::new().prefix(".tmp-").tempfile_in(dir).map_err(|e| {
        let why = match std::fs::metadata(dir) {
            Err(d) => d.to_string(),
            Ok(_) => e.get_ref().map_or_else(|| e.to_string(), |p| p.to_string()),
        };
        std::io::Error::new(e.kind(), format!("cannot create a file in {}: {why}", dir.display()))
    })?;
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

/// Bytes an unprivileged writer may still store on the file system that
/// holds `dir` (`None` where that cannot be asked).
pub fn free_bytes(dir: &Path) -> Option<u64> {
    #[cfg(target_os = "linux")]
    {
        let s = rustix::fs::statvfs(dir).ok()?;
        Some(s.f_bavail.saturating_mul(s.f_frsize))
    }
    #[cfg(not(target_os = "linux"))]
    {
        let _ = dir;
        None
    }
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
        // A file inside an input directory (a scan's manifest): refused; a
        // new file beside it is allowed.
        let scan = dir.path().join("scan");
        std::fs::create_dir_all(scan.join("frames")).unwrap();
        std::fs::write(scan.join("manifest.json"), "{}").unwrap();
        std::fs::write(scan.join("frames/mirror-00.exr"), "x").unwrap();
        for inside in ["manifest.json", "frames/mirror-00.exr"] {
            let e = check_output(&scan.join(inside), &[&scan]).unwrap_err();
            assert!(matches!(e, OutputError::InsideInput { .. }), "{e}");
        }
        std::fs::write(scan.join("sample.material"), "x").unwrap();
        assert!(check_output(&scan.join("sample.material"), &[&scan]).is_ok());
    }

    fn exr(name: &str) -> bool {
        name.ends_with(".exr")
    }

    #[test]
    fn an_output_directory_replaces_only_what_the_command_wrote() {
        let root = tempfile::tempdir().unwrap();
        let out = root.path().join("regions");
        // Nothing there, then its own files: replaced whole.
        for (round, names) in [["a.exr", "b.exr"], ["c.exr", "d.exr"]].iter().enumerate() {
            check_output_dir(&out, exr).unwrap();
            let staging = staging_dir(&out).unwrap();
            for n in names {
                std::fs::write(staging.path().join(n), format!("{round}")).unwrap();
            }
            replace_dir(staging, &out).unwrap();
            let mut got: Vec<String> = std::fs::read_dir(&out)
                .unwrap()
                .map(|e| e.unwrap().file_name().into_string().unwrap())
                .collect();
            got.sort();
            assert_eq!(got, names.to_vec());
        }
        // Nothing left beside it: no staging, no old copy.
        assert_eq!(std::fs::read_dir(root.path()).unwrap().count(), 1);
        // A user's file, a subdirectory, a link, a file, no name: refused, untouched.
        std::fs::write(out.join("thesis.txt"), "mine").unwrap();
        let e = check_output_dir(&out, exr).unwrap_err();
        assert!(e.to_string().contains("thesis.txt"), "{e}");
        std::fs::remove_file(out.join("thesis.txt")).unwrap();
        std::fs::create_dir(out.join("sub")).unwrap();
        assert!(matches!(check_output_dir(&out, exr), Err(OutputError::Foreign { .. })));
        #[cfg(unix)]
        {
            let link = root.path().join("link");
            std::os::unix::fs::symlink(&out, &link).unwrap();
            assert!(matches!(check_output_dir(&link, exr), Err(OutputError::NotADirectory { .. })));
        }
        let file = root.path().join("f");
        std::fs::write(&file, "x").unwrap();
        assert!(matches!(check_output_dir(&file, exr), Err(OutputError::NotADirectory { .. })));
        assert!(matches!(check_output_dir(Path::new("."), exr), Err(OutputError::Unnamed { .. })));
        assert!(matches!(check_output_dir(Path::new("/"), exr), Err(OutputError::Unnamed { .. })));
        // A dropped staging directory leaves nothing.
        let staging = staging_dir(&out).unwrap();
        let p = staging.path().to_path_buf();
        drop(staging);
        assert!(!p.exists());
    }
}
