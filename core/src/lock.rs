//! Advisory file locks (`flock`): one process at a time per run folder, per vocabulary
//! preparation and per results rebuild. The kernel drops a lock when its holder dies, even
//! by SIGKILL, so a lock never outlives the process that took it.

use crate::FileError;
use std::fs::File;
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};

/// An exclusive lock on a file, released on drop.
#[derive(Debug)]
pub struct FileLock {
    _file: File,
    path: PathBuf,
}

impl FileLock {
    fn open(path: &Path) -> Result<File, FileError> {
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(|e| FileError::io(dir, e))?;
        }
        std::fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(path)
            .map_err(|e| FileError::io(path, e))
    }

    fn flock(file: &File, path: &Path, flags: libc::c_int) -> Result<bool, FileError> {
        loop {
            // SAFETY: flock on a file descriptor this function borrows; no memory is shared.
            if unsafe { libc::flock(file.as_raw_fd(), flags) } == 0 {
                return Ok(true);
            }
            let err = std::io::Error::last_os_error();
            match err.raw_os_error() {
                Some(libc::EWOULDBLOCK) => return Ok(false),
                Some(libc::EINTR) => continue,
                _ => return Err(FileError::io(path, err)),
            }
        }
    }

    /// Take the lock on `path` (created if needed), waiting while another process holds it.
    pub fn acquire(path: &Path) -> Result<Self, FileError> {
        let file = Self::open(path)?;
        Self::flock(&file, path, libc::LOCK_EX)?;
        Ok(Self {
            _file: file,
            path: path.to_path_buf(),
        })
    }

    /// Take the lock on `path`; when another process holds it, call `on_wait` first, then wait.
    pub fn acquire_or_wait(path: &Path, on_wait: impl FnOnce()) -> Result<Self, FileError> {
        match Self::try_acquire(path)? {
            Some(lock) => Ok(lock),
            None => {
                on_wait();
                Self::acquire(path)
            }
        }
    }

    /// Take the lock on `path` if no other process holds it.
    pub fn try_acquire(path: &Path) -> Result<Option<Self>, FileError> {
        let file = Self::open(path)?;
        Ok(
            Self::flock(&file, path, libc::LOCK_EX | libc::LOCK_NB)?.then(|| Self {
                _file: file,
                path: path.to_path_buf(),
            }),
        )
    }

    /// Whether another process holds the lock on `path` now (false when the file is absent).
    pub fn is_held(path: &Path) -> Result<bool, FileError> {
        if !path.exists() {
            return Ok(false);
        }
        Ok(Self::try_acquire(path)?.is_none())
    }

    /// The locked file.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_held_lock_excludes_others_until_dropped() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x/.lock");
        assert!(!FileLock::is_held(&path).unwrap());
        let held = FileLock::acquire(&path).unwrap();
        assert_eq!(held.path(), path);
        // flock locks belong to the open file description: a second open conflicts even
        // within one process.
        assert!(FileLock::try_acquire(&path).unwrap().is_none());
        assert!(FileLock::is_held(&path).unwrap());
        drop(held);
        let mut waited = false;
        assert!(FileLock::acquire_or_wait(&path, || waited = true).is_ok());
        assert!(!waited, "a free lock is taken at once");
    }
}
