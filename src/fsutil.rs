//! Safe file output: refuse to clobber, write to a temporary sibling, then rename into place;
//! one writer per output folder; and appending lines to logs.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// Fails with [`Error::WouldClobber`] when `path` exists and `force` is false.
pub fn check_writable(path: &Path, force: bool) -> Result<()> {
    if path.exists() && !force {
        return Err(Error::WouldClobber(path.to_path_buf()));
    }
    Ok(())
}

/// The temporary sibling a file is written to before it is renamed over `path`.
fn temp_sibling(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    path.with_file_name(format!(".{name}.tmp-{}", std::process::id()))
}

/// Writes `path` atomically: `write` fills a temporary file in the same folder, which is
/// renamed over `path` only once it is complete, so a crash never leaves a half-written file
/// and an existing file survives any failure. Refuses to replace an existing file unless `force`.
pub fn write_atomically<T>(
    path: &Path,
    force: bool,
    write: impl FnOnce(&mut BufWriter<File>) -> Result<T>,
) -> Result<T> {
    check_writable(path, force)?;
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|e| Error::io(parent, e))?;
    }
    let temp = temp_sibling(path);
    let result = (|| {
        let file = File::create(&temp).map_err(|e| Error::io(path, e))?;
        let mut writer = BufWriter::new(file);
        let value = write(&mut writer)?;
        writer.flush().map_err(|e| Error::io(path, e))?;
        let file = writer
            .into_inner()
            .map_err(|e| Error::io(path, e.into_error()))?;
        file.sync_all().map_err(|e| Error::io(path, e))?;
        if force {
            std::fs::rename(&temp, path).map_err(|e| Error::io(path, e))?;
        } else {
            // A hard link is created only where nothing exists, atomically: of two writers
            // racing for a new file, the second is refused instead of replacing the first.
            match std::fs::hard_link(&temp, path) {
                Ok(()) => {
                    let _ = std::fs::remove_file(&temp);
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    return Err(Error::WouldClobber(path.to_path_buf()));
                }
                // File systems without hard links: check, then rename.
                Err(_) => {
                    check_writable(path, false)?;
                    std::fs::rename(&temp, path).map_err(|e| Error::io(path, e))?;
                }
            }
        }
        Ok(value)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&temp);
    }
    result
}

/// Writes `value` as pretty-printed JSON to `path` atomically, replacing any existing file
/// (used for the outputs procl owns: config.json, eval.json, diagnostics, summaries).
pub fn write_json<T: serde::Serialize + ?Sized>(path: &Path, value: &T) -> Result<()> {
    let json = serde_json::to_string_pretty(value)
        .map_err(|e| Error::config(path.display().to_string(), e.to_string()))?;
    write_atomically(path, true, |w| {
        w.write_all(json.as_bytes()).map_err(|e| Error::io(path, e))
    })
}

/// Appends `line` and a newline to the log `path` (created if missing), writing `header` first
/// when the file is new and `header` is not empty.
pub fn append_line(path: &Path, header: &str, line: &str) -> Result<()> {
    let mut text = String::new();
    if !path.exists() && !header.is_empty() {
        text.push_str(header);
        text.push('\n');
    }
    text.push_str(line);
    text.push('\n');
    std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .and_then(|mut f| f.write_all(text.as_bytes()))
        .map_err(|e| Error::io(path, e))
}

/// The name of the lock file in an output folder.
const LOCK_FILE: &str = ".procl.lock";

/// An exclusive advisory lock on an output folder, held while it lives: one writer per folder.
/// The operating system releases it when the process exits, however it exits, so a killed
/// writer never leaves the folder locked.
#[derive(Debug)]
pub struct FolderLock {
    _file: File,
}

impl FolderLock {
    /// Creates `dir` if needed and locks it, or fails with [`Error::Busy`] naming the holder's
    /// pid when another process holds it.
    pub fn acquire(dir: &Path) -> Result<Self> {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        let path = dir.join(LOCK_FILE);
        let mut file = std::fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .read(true)
            .write(true)
            .open(&path)
            .map_err(|e| Error::io(&path, e))?;
        match file.try_lock() {
            Ok(()) => {}
            Err(std::fs::TryLockError::WouldBlock) => {
                let pid = std::fs::read_to_string(&path)
                    .ok()
                    .map(|s| s.trim().to_string())
                    .filter(|s| !s.is_empty())
                    .unwrap_or_else(|| "unknown".into());
                return Err(Error::Busy {
                    path: dir.to_path_buf(),
                    pid,
                });
            }
            Err(std::fs::TryLockError::Error(e)) => return Err(Error::io(&path, e)),
        }
        use std::io::Seek;
        file.set_len(0)
            .and_then(|()| file.seek(std::io::SeekFrom::Start(0)))
            .and_then(|_| writeln!(file, "{}", std::process::id()))
            .map_err(|e| Error::io(&path, e))?;
        Ok(Self { _file: file })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_created_while_writing_is_not_replaced_without_force() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("data.npz");
        // Another writer finishes the same file while this one is still writing.
        let err = write_atomically(&path, false, |w| {
            std::fs::write(&path, b"theirs").expect("other writer");
            w.write_all(b"mine").map_err(|e| Error::io(&path, e))
        })
        .unwrap_err();
        assert!(matches!(err, Error::WouldClobber(_)), "{err}");
        assert_eq!(std::fs::read(&path).expect("read"), b"theirs");
        assert_eq!(std::fs::read_dir(dir.path()).expect("dir").count(), 1);
        // With force, the last writer wins.
        write_atomically(&path, true, |w| {
            w.write_all(b"mine").map_err(|e| Error::io(&path, e))
        })
        .expect("forced");
        assert_eq!(std::fs::read(&path).expect("read"), b"mine");
    }

    #[test]
    fn a_locked_folder_refuses_a_second_writer_until_the_first_lets_go() {
        let dir = tempfile::tempdir().expect("tempdir");
        let out = dir.path().join("run");
        let first = FolderLock::acquire(&out).expect("first writer");
        let err = FolderLock::acquire(&out).unwrap_err().to_string();
        let pid = std::process::id().to_string();
        assert!(err.contains("run") && err.contains(&pid), "{err}");
        drop(first);
        FolderLock::acquire(&out).expect("free again");
    }
}
