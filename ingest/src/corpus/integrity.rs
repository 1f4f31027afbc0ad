//! Does a corpus folder hold exactly the files its manifest describes? Every command that
//! reads a corpus runs [`check`] when it opens one (through [`super::Corpus::open`] or
//! [`read_checked`]), so a flipped byte, a swapped or extra shard, a changed
//! statistics file or a manifest whose totals do not add up is refused with the file named
//! instead of being read as if it were fine. Hashing every shard costs one sequential read
//! of the corpus (docs/stages.md, "Corpus format", gives the measured cost).

use super::manifest::Manifest;
use crate::error::IngestError;
use motionscale_core::hex;
use rayon::prelude::*;
use sha2::{Digest, Sha256};
use std::collections::HashSet;
use std::io::Read;
use std::path::Path;

/// sha256 of a file, hex, read in 1 MiB blocks (shards are never loaded whole for this).
pub fn file_sha256(path: &Path) -> Result<String, IngestError> {
    let mut file = std::fs::File::open(path).map_err(|e| IngestError::io(path, e))?;
    let mut hasher = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = file.read(&mut buf).map_err(|e| IngestError::io(path, e))?;
        if n == 0 {
            return Ok(hex(&hasher.finalize()));
        }
        hasher.update(&buf[..n]);
    }
}

/// Files in `shards/` that the manifest does not list (a stray shard would otherwise be
/// invisible to readers and silently missing from exports, or shadow a listed one).
pub fn unlisted_files(dir: &Path, manifest: &Manifest) -> Vec<String> {
    let listed: HashSet<&str> = manifest.shards.iter().map(|s| s.file.as_str()).collect();
    let shard_dir = dir.join("shards");
    let Ok(entries) = std::fs::read_dir(&shard_dir) else {
        return Vec::new();
    };
    let mut out: Vec<String> = entries
        .filter_map(|e| e.ok())
        .map(|e| format!("shards/{}", e.file_name().to_string_lossy()))
        .filter(|rel| !listed.contains(rel.as_str()))
        .map(|rel| {
            format!(
                "{}: not listed in manifest.json (a stray or leftover file; remove it or re-ingest)",
                dir.join(rel).display()
            )
        })
        .collect();
    out.sort();
    out
}

/// Manifest totals that disagree with its own shard list.
pub fn total_mismatches(dir: &Path, manifest: &Manifest) -> Vec<String> {
    let path = dir.join("manifest.json");
    let shard_clips: u64 = manifest.shards.iter().map(|s| s.rows).sum();
    let shard_frames: u64 = manifest.shards.iter().map(|s| s.frames).sum();
    let split_clips: u64 = manifest.clips_by_split.values().sum();
    let split_frames: u64 = manifest.frames_by_split.values().sum();
    let mut out = Vec::new();
    if shard_clips != split_clips {
        out.push(format!(
            "{}: clips_by_split adds up to {split_clips} clips, the shards list {shard_clips}",
            path.display()
        ));
    }
    if shard_frames != split_frames {
        out.push(format!(
            "{}: frames_by_split adds up to {split_frames} frames, the shards list {shard_frames}",
            path.display()
        ));
    }
    out
}

/// Listed files (shards in parallel, then statistics and rejects) whose sha256 differs
/// from the manifest's, or that cannot be read.
pub fn checksum_mismatches(dir: &Path, manifest: &Manifest) -> Vec<String> {
    let shards = manifest
        .shards
        .iter()
        .map(|s| (s.file.as_str(), s.sha256.as_str()));
    let others = manifest
        .file_sha256
        .iter()
        .map(|(f, s)| (f.as_str(), s.as_str()));
    let files: Vec<(&str, &str)> = shards.chain(others).collect();
    files
        .par_iter()
        .filter_map(|&(file, want)| {
            let path = dir.join(file);
            match file_sha256(&path) {
                Ok(got) if got == want => None,
                Ok(got) => Some(format!(
                    "{}: sha256 {got} differs from the manifest's {want} (the file was changed \
                     or replaced after ingest)",
                    path.display()
                )),
                Err(e) => Some(e.to_string()),
            }
        })
        .collect()
}

/// Every integrity problem of a corpus folder against its manifest (empty: it matches).
pub fn problems(dir: &Path, manifest: &Manifest) -> Vec<String> {
    let mut out = unlisted_files(dir, manifest);
    out.extend(total_mismatches(dir, manifest));
    out.extend(checksum_mismatches(dir, manifest));
    out
}

/// Refuse a corpus folder whose files do not match its manifest, naming the first problem
/// (and how many more there are).
pub fn check(dir: &Path, manifest: &Manifest) -> Result<(), IngestError> {
    let problems = problems(dir, manifest);
    match problems.as_slice() {
        [] => Ok(()),
        [only] => Err(format!("corpus refused: {only}").into()),
        [first, rest @ ..] => Err(format!(
            "corpus refused: {first} (and {} more; `corpus verify` lists them)",
            rest.len()
        )
        .into()),
    }
}
/// Read `manifest.json` and refuse the corpus unless its files match it ([`check`]): what
/// every reader of a corpus opens it with.
pub fn read_checked(dir: &Path) -> Result<Manifest, IngestError> {
    let manifest = Manifest::read(dir)?;
    check(dir, &manifest)?;
    Ok(manifest)
}
