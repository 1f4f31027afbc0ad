//! Safe replacement of a corpus folder. An ingest holds an exclusive lock on its output
//! folder (a second one refuses at once, naming the holder), builds the new corpus in a
//! staging folder beside it, and swaps it in only when complete; the old corpus stays
//! readable until then, and a killed run leaves nothing that reads as a corpus. The next
//! run removes what a killed one left behind.
//!
//! For output `DIR/name`: the lock is `DIR/.name.lock`, the staging folder
//! `DIR/.name.ingest-new` and the previous corpus, during the swap, `DIR/.name.ingest-old`.

use crate::error::IngestError;
use std::fs::File;
use std::io::{Read, Seek, Write};
use std::os::unix::fs::MetadataExt;
use std::os::unix::io::AsRawFd;
use std::path::{Path, PathBuf};

/// An output folder locked for one ingest; dropping it releases the lock.
pub struct Staging {
    out: PathBuf,
    staged: PathBuf,
    old: PathBuf,
    lock_path: PathBuf,
    _lock: File,
}

fn io(p: &Path) -> impl Fn(std::io::Error) -> IngestError + '_ {
    move |e| IngestError::io(p, e)
}

/// `DIR/.name<suffix>` beside the output folder `DIR/name`.
fn sibling(out: &Path, suffix: &str) -> Result<PathBuf, IngestError> {
    let name = out
        .file_name()
        .ok_or_else(|| IngestError::file(out, "the output must name a folder"))?;
    let parent = out
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    Ok(parent.join(format!(".{}{suffix}", name.to_string_lossy())))
}

/// Take the lock file's exclusive lock without waiting; on failure, say who holds it.
fn lock(path: &Path, out: &Path) -> Result<File, IngestError> {
    loop {
        let mut file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(path)
            .map_err(io(path))?;
        // SAFETY: flock on a descriptor this function owns; no memory is shared.
        if unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } != 0 {
            let mut holder = String::new();
            let _ = file.read_to_string(&mut holder);
            return Err(IngestError::file(out, format!("another ingest is writing this corpus: {} (lock file {}); wait for it to finish", holder.trim(), path.display())));
        }
        // The holder removes the lock file when it finishes: a lock taken on a file that is
        // no longer at `path` guards nothing, so open the current one again.
        let same = std::fs::metadata(path).is_ok_and(|m| {
            file.metadata()
                .is_ok_and(|f| (f.dev(), f.ino()) == (m.dev(), m.ino()))
        });
        if !same {
            continue;
        }
        let args: Vec<String> = std::env::args().collect();
        let holder = format!("pid {} running `{}`", std::process::id(), args.join(" "));
        file.set_len(0).map_err(io(path))?;
        file.rewind().map_err(io(path))?;
        file.write_all(holder.as_bytes()).map_err(io(path))?;
        return Ok(file);
    }
}

/// Move every entry of `from` that `to` lacks into `to` (files a user or `embed-text` kept
/// in the corpus folder survive a re-ingest), then remove `from`.
fn carry_over(from: &Path, to: &Path) -> Result<(), IngestError> {
    for entry in std::fs::read_dir(from).map_err(io(from))? {
        let entry = entry.map_err(io(from))?;
        let target = to.join(entry.file_name());
        if !target.exists() {
            std::fs::rename(entry.path(), &target).map_err(io(&target))?;
        }
    }
    std::fs::remove_dir_all(from).map_err(io(from))
}

impl Staging {
    /// Lock the output folder `out` and prepare an empty staging folder, first finishing or
    /// removing whatever a killed earlier run left. Refuses an existing `out` that is not a
    /// corpus (no `manifest.json`) and not empty, rather than replace someone's folder.
    pub fn begin(out: &Path) -> Result<Self, IngestError> {
        let lock_path = sibling(out, ".lock")?;
        if let Some(parent) = lock_path.parent() {
            std::fs::create_dir_all(parent).map_err(io(parent))?;
        }
        let lock = lock(&lock_path, out)?;
        let staging = Self {
            out: out.to_path_buf(),
            staged: sibling(out, ".ingest-new")?,
            old: sibling(out, ".ingest-old")?,
            lock_path,
            _lock: lock,
        };
        staging.recover()?;
        let foreign = out.is_dir()
            && !out.join("manifest.json").is_file()
            && std::fs::read_dir(out).map_err(io(out))?.next().is_some();
        if foreign {
            return Err(IngestError::file(
                out,
                "exists and is not a corpus (no manifest.json); choose an empty or new folder",
            ));
        }
        std::fs::create_dir_all(&staging.staged).map_err(io(&staging.staged))?;
        Ok(staging)
    }

    /// Undo a swap a kill interrupted (put the old corpus back, or finish carrying its extra
    /// files over) and remove an unfinished staging folder.
    fn recover(&self) -> Result<(), IngestError> {
        if self.old.is_dir() {
            if self.out.exists() {
                carry_over(&self.old, &self.out)?;
            } else {
                std::fs::rename(&self.old, &self.out).map_err(io(&self.out))?;
            }
        }
        if self.staged.exists() {
            std::fs::remove_dir_all(&self.staged).map_err(io(&self.staged))?;
        }
        Ok(())
    }

    /// The folder to build the new corpus in.
    pub fn dir(&self) -> &Path {
        &self.staged
    }

    /// Swap the complete staged corpus in for the old one (two renames), carry over the old
    /// folder's other files and remove it; dropping `self` then releases the lock.
    pub fn commit(self) -> Result<(), IngestError> {
        if self.out.exists() {
            std::fs::rename(&self.out, &self.old).map_err(io(&self.out))?;
        }
        std::fs::rename(&self.staged, &self.out).map_err(io(&self.out))?;
        if self.old.is_dir() {
            carry_over(&self.old, &self.out)?;
        }
        Ok(())
    }
}

impl Drop for Staging {
    /// Remove an unfinished staging folder (a failed run) and the lock file, still holding
    /// the lock, so nothing of this run is left beside the corpus.
    fn drop(&mut self) {
        if self.staged.exists() {
            let _ = std::fs::remove_dir_all(&self.staged);
        }
        let _ = std::fs::remove_file(&self.lock_path);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn a_second_writer_is_refused_naming_the_first() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("corpus");
        let first = Staging::begin(&out).unwrap();
        let e = Staging::begin(&out).err().unwrap().to_string();
        let pid = format!("pid {}", std::process::id());
        assert!(
            e.contains("another ingest is writing this corpus") && e.contains(&pid),
            "{e}"
        );
        drop(first);
        // Released (and its staging folder and lock file removed) when the first one ends.
        assert!(names(tmp.path()).is_empty(), "{:?}", names(tmp.path()));
        assert!(Staging::begin(&out).is_ok());
    }

    #[test]
    fn commit_swaps_carries_extra_files_over_and_leaves_nothing_beside() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("corpus");
        std::fs::create_dir_all(out.join("text")).unwrap();
        std::fs::write(out.join("manifest.json"), "old").unwrap();
        std::fs::write(out.join("text/index.json"), "kept").unwrap();
        let staging = Staging::begin(&out).unwrap();
        std::fs::write(staging.dir().join("manifest.json"), "new").unwrap();
        // Until the commit, the old corpus is what the folder holds.
        assert_eq!(
            std::fs::read_to_string(out.join("manifest.json")).unwrap(),
            "old"
        );
        staging.commit().unwrap();
        assert_eq!(
            std::fs::read_to_string(out.join("manifest.json")).unwrap(),
            "new"
        );
        assert_eq!(
            std::fs::read_to_string(out.join("text/index.json")).unwrap(),
            "kept"
        );
        assert_eq!(names(tmp.path()), ["corpus"]);
    }

    #[test]
    fn leftovers_of_a_killed_run_are_recovered_or_removed() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("corpus");
        // Killed between the two renames: the old corpus waits beside, the output is gone.
        let old = tmp.path().join(".corpus.ingest-old");
        std::fs::create_dir_all(&old).unwrap();
        std::fs::write(old.join("manifest.json"), "old").unwrap();
        let new = tmp.path().join(".corpus.ingest-new");
        std::fs::create_dir_all(new.join("shards")).unwrap();
        std::fs::write(new.join("shards/.shard-00000.parquet.tmp9"), "partial").unwrap();
        let staging = Staging::begin(&out).unwrap();
        assert_eq!(
            std::fs::read_to_string(out.join("manifest.json")).unwrap(),
            "old"
        );
        assert!(names(staging.dir()).is_empty());
        drop(staging);
        assert_eq!(names(tmp.path()), ["corpus"]);
    }

    #[test]
    fn a_folder_that_is_not_a_corpus_is_not_replaced() {
        let tmp = tempfile::tempdir().unwrap();
        std::fs::write(tmp.path().join("notes.txt"), "mine").unwrap();
        let e = Staging::begin(tmp.path()).err().unwrap().to_string();
        assert!(e.contains("is not a corpus"), "{e}");
        assert_eq!(names(tmp.path()), ["notes.txt"]);
    }
}
