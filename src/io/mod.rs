//! File plumbing shared by every stage: atomic writes, named-tensor files
//! (safetensors with string metadata), the one PNG codec ([`png`]), render
//! images ([`image`]), and reading PyTorch `.pth` files.

pub mod image;
pub mod png;
pub mod pth;
pub mod tensor_file;

pub use tensor_file::{Tensor, TensorFile};

use crate::error::{Error, Result};
use std::io::Write;
use std::path::Path;

/// Write `bytes` to `path` atomically: write a temporary file in the same
/// folder, flush it to disk, then rename it over `path`. A crash leaves either
/// the old file or the new one, never half of one.
///
/// A symbolic link is followed: the file it points to is replaced, the link
/// stays. An existing path that is not a regular file (a device such as
/// `/dev/stdout`, a named pipe) is written through, not replaced.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    if path.is_symlink() {
        let target = std::fs::canonicalize(path).map_err(|e| Error::io(path, e))?;
        return write_atomic(&target, bytes);
    }
    if let Ok(m) = std::fs::metadata(path) {
        if !m.is_file() && !m.is_dir() {
            let write = || -> std::io::Result<()> {
                let mut f = std::fs::OpenOptions::new().write(true).open(path)?;
                f.write_all(bytes)?;
                f.flush()
            };
            return write().map_err(|e| Error::io(path, e));
        }
    }
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => std::path::PathBuf::from("."),
    };
    let name = path.file_name().ok_or_else(|| {
        Error::invalid(
            "output path",
            format!("{} has no file name", path.display()),
        )
    })?;
    let tmp = dir.join(format!(
        ".{}.tmp{}",
        name.to_string_lossy(),
        std::process::id()
    ));
    let write = || -> std::io::Result<()> {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)
    };
    write().map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        Error::io(path, e)
    })
}

/// Refuses a device, a named pipe or a socket given as an input (`/dev/zero`
/// has no end to read to; opening a pipe waits for a writer that may never
/// come).
fn refuse_device(path: &Path) -> Result<()> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if let Ok(m) = std::fs::metadata(path) {
            let t = m.file_type();
            let what = if t.is_char_device() || t.is_block_device() {
                Some("a device")
            } else if t.is_fifo() {
                Some("a named pipe (FIFO)")
            } else if t.is_socket() {
                Some("a socket")
            } else {
                None
            };
            if let Some(what) = what {
                return Err(Error::invalid(
                    "input file",
                    format!("{} is {what}, not a file", path.display()),
                ));
            }
        }
    }
    Ok(())
}

/// `std::fs::create_dir_all`, with the path in the error; where a file
/// stands in the way (the folder itself or one above it), the error says
/// which (the system's own message is only "File exists" or "Not a
/// directory").
pub fn create_dir_all(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| {
        let mut parts: Vec<&Path> = dir.ancestors().collect();
        parts.reverse();
        match parts
            .into_iter()
            .find(|p| !p.as_os_str().is_empty() && p.exists() && !p.is_dir())
        {
            Some(file) => Error::invalid(
                "output folder",
                format!(
                    "cannot create {}: {} is a file, not a folder",
                    dir.display(),
                    file.display()
                ),
            ),
            None => Error::io(dir, e),
        }
    })
}

/// Read a whole file, with the path in the error (a device is refused).
pub fn read(path: &Path) -> Result<Vec<u8>> {
    refuse_device(path)?;
    std::fs::read(path).map_err(|e| Error::io(path, e))
}

/// Open a file for reading, with the path in the error (a device is
/// refused).
pub fn open(path: &Path) -> Result<std::fs::File> {
    refuse_device(path)?;
    std::fs::File::open(path).map_err(|e| Error::io(path, e))
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    use super::*;
    use std::os::unix::fs::FileTypeExt;

    #[test]
    fn links_are_followed_and_devices_written_through() {
        let dir = std::env::temp_dir().join(format!("ls-io-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (target, link) = (dir.join("target"), dir.join("link"));
        std::fs::write(&target, b"old").unwrap();
        let _ = std::fs::remove_file(&link);
        std::os::unix::fs::symlink(&target, &link).unwrap();
        write_atomic(&link, b"new").unwrap();
        assert!(link.is_symlink());
        assert_eq!(std::fs::read(&target).unwrap(), b"new");
        // A device stays a device; one that refuses the bytes is an error
        // naming it.
        write_atomic(Path::new("/dev/null"), b"x").unwrap();
        let err = write_atomic(Path::new("/dev/full"), b"x")
            .unwrap_err()
            .to_string();
        assert!(err.contains("/dev/full"), "{err}");
        for dev in ["/dev/null", "/dev/full"] {
            let t = std::fs::metadata(dev).unwrap().file_type();
            assert!(t.is_char_device(), "{dev}");
        }
        // A device is not read (/dev/zero has no end).
        let err = read(Path::new("/dev/zero")).unwrap_err().to_string();
        assert!(err.contains("/dev/zero") && err.contains("device"), "{err}");
        // Nor a named pipe, whose opening waited for a writer for ever; a
        // link to one neither.
        let fifo = dir.join("fifo");
        let _ = std::fs::remove_file(&fifo);
        let c = std::ffi::CString::new(fifo.as_os_str().as_encoded_bytes()).unwrap();
        // SAFETY: a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        let to_fifo = dir.join("to_fifo");
        let _ = std::fs::remove_file(&to_fifo);
        std::os::unix::fs::symlink(&fifo, &to_fifo).unwrap();
        for p in [&fifo, &to_fifo] {
            let err = open(p).unwrap_err().to_string();
            assert!(err.contains("named pipe (FIFO)"), "{err}");
            let err = read(p).unwrap_err().to_string();
            assert!(err.contains(&*p.to_string_lossy()), "{err}");
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
