//! Inputs read whole: only from a regular file. A path that names a device
//! (`/dev/zero`, `/dev/urandom`: endless), a FIFO (blocks until a writer
//! comes), a socket or a directory — directly or through a symbolic link —
//! is refused with a clear error before anything is read, instead of
//! reading until memory runs out or waiting forever.

use std::io::{Error, ErrorKind, Read};
use std::path::Path;

/// Open `path` for reading if it is a regular file (a symbolic link to one
/// is followed).
pub fn open(path: &Path) -> std::io::Result<std::fs::File> {
    let meta = std::fs::metadata(path)?;
    if !meta.is_file() {
        return Err(Error::new(ErrorKind::InvalidInput, not_regular(&meta.file_type())));
    }
    // Opened non-blocking, so that a FIFO put there since the check above
    // is refused below instead of waiting for a writer (no effect on a
    // regular file's reads).
    let mut options = std::fs::OpenOptions::new();
    options.read(true);
    #[cfg(target_os = "linux")]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(rustix::fs::OFlags::NONBLOCK.bits() as i32);
    }
    let file = options.open(path)?;
    let meta = file.metadata()?;
    if !meta.is_file() {
        return Err(Error::new(ErrorKind::InvalidInput, not_regular(&meta.file_type())));
    }
    Ok(file)
}

/// Open (creating it if need be) the lock file at `path`, to hold a lock
/// on: read and write where it may be written, else read only (another
/// user's lock in a shared folder; a lock needs no writing). A symbolic
/// link there is not followed (no file is made or truncated where it
/// points) and anything but a regular file is refused: lock files live in
/// folders others may write to.
pub fn open_lock_file(path: &Path) -> std::io::Result<std::fs::File> {
    let options = |write: bool| {
        let mut options = std::fs::OpenOptions::new();
        options.read(true);
        if write {
            options.write(true).create(true).truncate(false);
        }
        #[cfg(target_os = "linux")]
        {
            use std::os::unix::fs::OpenOptionsExt;
            let flags = rustix::fs::OFlags::NOFOLLOW | rustix::fs::OFlags::NONBLOCK;
            options.custom_flags(flags.bits() as i32);
        }
        options
    };
    // Said in words here; refused by the open's O_NOFOLLOW on Linux should
    // a link be put there in between.
    if std::fs::symlink_metadata(path).is_ok_and(|m| m.file_type().is_symlink()) {
        return Err(Error::new(ErrorKind::InvalidInput, "a symbolic link, not a regular file"));
    }
    let file = options(true).open(path).or_else(|e| match e.kind() {
        ErrorKind::PermissionDenied | ErrorKind::ReadOnlyFilesystem => options(false).open(path),
        _ => Err(e),
    })?;
    let meta = file.metadata()?;
    if !meta.is_file() {
        return Err(Error::new(ErrorKind::InvalidInput, not_regular(&meta.file_type())));
    }
    Ok(file)
}

/// The bytes of the regular file at `path` (see [`open`]).
pub fn read(path: &Path) -> std::io::Result<Vec<u8>> {
    let mut file = open(path)?;
    let mut bytes = Vec::new();
    file.read_to_end(&mut bytes)?;
    Ok(bytes)
}

/// The text of the regular file at `path` (see [`open`]): UTF-8, else an
/// error of kind [`ErrorKind::InvalidData`].
pub fn read_to_string(path: &Path) -> std::io::Result<String> {
    String::from_utf8(read(path)?)
        .map_err(|_| Error::new(ErrorKind::InvalidData, "stream did not contain valid UTF-8"))
}

/// What a non-regular file is, said for an error.
fn not_regular(ft: &std::fs::FileType) -> &'static str {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if ft.is_fifo() {
            return "a FIFO, not a regular file";
        }
        if ft.is_socket() {
            return "a socket, not a regular file";
        }
        if ft.is_char_device() || ft.is_block_device() {
            return "a device, not a regular file";
        }
    }
    if ft.is_dir() { "a directory, not a regular file" } else { "not a regular file" }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_lock_file_is_made_opened_again_and_never_followed_through_a_link() {
        let dir = tempfile::tempdir().unwrap();
        let lock = dir.path().join("x.lock");
        let file = open_lock_file(&lock).unwrap();
        assert!(lock.is_file());
        drop(file);
        std::fs::write(&lock, "12 scanner scan").unwrap();
        let _again = open_lock_file(&lock).unwrap();
        assert_eq!(std::fs::read_to_string(&lock).unwrap(), "12 scanner scan", "not truncated");
        #[cfg(unix)]
        {
            let precious = dir.path().join("precious.txt");
            std::fs::write(&precious, "keep").unwrap();
            let link = dir.path().join("link.lock");
            std::os::unix::fs::symlink(&precious, &link).unwrap();
            let e = open_lock_file(&link).unwrap_err();
            assert!(e.to_string().contains("symbolic link"), "{e}");
            let dangling = dir.path().join("dangling.lock");
            let target = dir.path().join("made-by-the-link");
            std::os::unix::fs::symlink(&target, &dangling).unwrap();
            assert!(open_lock_file(&dangling).is_err());
            assert!(!target.exists(), "no file made where a link points");
            assert_eq!(std::fs::read_to_string(&precious).unwrap(), "keep");
            let e = open_lock_file(dir.path()).unwrap_err();
            assert!(e.to_string().contains("directory"), "{e}");
        }
    }

    #[test]
    fn a_regular_file_and_a_link_to_one_are_read() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("a.txt");
        std::fs::write(&file, "text").unwrap();
        assert_eq!(read_to_string(&file).unwrap(), "text");
        #[cfg(unix)]
        {
            let link = dir.path().join("link.txt");
            std::os::unix::fs::symlink(&file, &link).unwrap();
            assert_eq!(read(&link).unwrap(), b"text");
        }
    }

    #[test]
    fn devices_directories_and_fifos_are_refused_before_reading() {
        let dir = tempfile::tempdir().unwrap();
        let e = read(dir.path()).unwrap_err();
        assert_eq!(e.to_string(), "a directory, not a regular file");
        #[cfg(unix)]
        {
            // Endless: read_to_end would never return.
            let link = dir.path().join("zero.npy");
            std::os::unix::fs::symlink("/dev/zero", &link).unwrap();
            let e = read(&link).unwrap_err();
            assert_eq!(e.kind(), ErrorKind::InvalidInput);
            assert_eq!(e.to_string(), "a device, not a regular file");
        }
        #[cfg(target_os = "linux")]
        {
            // Opening a FIFO for reading would wait for a writer.
            let fifo = dir.path().join("fifo.csv");
            rustix::fs::mknodat(
                rustix::fs::CWD,
                &fifo,
                rustix::fs::FileType::Fifo,
                rustix::fs::Mode::RUSR | rustix::fs::Mode::WUSR,
                0,
            )
            .unwrap();
            let e = read(&fifo).unwrap_err();
            assert_eq!(e.to_string(), "a FIFO, not a regular file");
        }
    }
}
