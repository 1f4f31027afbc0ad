//! Checkpoint files: safetensors written atomically, and the resumable files of a training run.

use candle_core::Tensor;
use motionscale_core::{write_json, FileError};
use serde::Serialize;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Write `tensors` as safetensors to `path` atomically (temporary file in the same folder,
/// then rename), so a crash never leaves a half-written checkpoint.
pub fn save_safetensors(tensors: &HashMap<String, Tensor>, path: &Path) -> Result<(), FileError> {
    let file_error = |e: &dyn std::fmt::Display| FileError::invalid(path, e);
    let dir = path.parent().unwrap_or_else(|| Path::new("."));
    std::fs::create_dir_all(dir).map_err(|e| file_error(&e))?;
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("out");
    let tmp = dir.join(format!(".{name}.tmp{}", std::process::id()));
    candle_core::safetensors::save(tensors, &tmp).map_err(|e| file_error(&e))?;
    std::fs::rename(&tmp, path).map_err(|e| file_error(&e))
}

fn file_error(path: &Path, e: std::io::Error) -> FileError {
    FileError::io(path, e)
}

/// The current value of every variable, by name (what a checkpoint saves).
pub fn var_tensors(
    vars: &std::collections::HashMap<String, candle_core::Var>,
) -> std::collections::HashMap<String, candle_core::Tensor> {
    vars.iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
        .collect()
}

/// The resumable state of a training run: the files of step `s` live in `RUN/resume/<s>/`,
/// and `RUN/state.json`, written last and atomically, names the step. That one write is the
/// commit point, so a run killed at any moment (even between two files) resumes from a
/// complete, consistent set.
pub struct ResumeFiles {
    dir: PathBuf,
    state: PathBuf,
}

impl ResumeFiles {
    /// The resume files of the run folder `run`.
    pub fn new(run: &Path) -> Self {
        Self {
            dir: run.join("resume"),
            state: run.join("state.json"),
        }
    }

    /// `RUN/state.json`, the commit record.
    pub fn state_path(&self) -> &Path {
        &self.state
    }

    /// An empty staging folder to write the next checkpoint's files into.
    pub fn stage(&self) -> Result<PathBuf, FileError> {
        let staging = self.dir.join(".staging");
        if staging.exists() {
            std::fs::remove_dir_all(&staging).map_err(|e| file_error(&staging, e))?;
        }
        std::fs::create_dir_all(&staging).map_err(|e| file_error(&staging, e))?;
        Ok(staging)
    }

    /// Publish the staged files as step `step`, commit `state` to `state.json`, then remove
    /// every other step's files.
    pub fn commit<T: Serialize>(&self, step: u64, state: &T) -> Result<(), FileError> {
        let target = self.files(step);
        // A killed run can leave this step published but never committed.
        if target.exists() {
            std::fs::remove_dir_all(&target).map_err(|e| file_error(&target, e))?;
        }
        let staging = self.dir.join(".staging");
        std::fs::rename(&staging, &target).map_err(|e| file_error(&staging, e))?;
        write_json(&self.state, state)?;
        let entries = std::fs::read_dir(&self.dir).map_err(|e| file_error(&self.dir, e))?;
        for entry in entries {
            let path = entry.map_err(|e| file_error(&self.dir, e))?.path();
            if path != target {
                std::fs::remove_dir_all(&path).map_err(|e| file_error(&path, e))?;
            }
        }
        Ok(())
    }

    /// The folder holding step `step`'s files.
    pub fn files(&self, step: u64) -> PathBuf {
        self.dir.join(step.to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use motionscale_core::read_json;

    #[test]
    fn only_the_committed_step_survives_and_an_uncommitted_one_is_replaced() {
        let run = tempfile::tempdir().unwrap();
        let resume = ResumeFiles::new(run.path());
        let write = |step: u64, text: &str| {
            let stage = resume.stage().unwrap();
            std::fs::write(stage.join("weights"), text).unwrap();
            resume.commit(step, &step).unwrap();
        };
        write(2, "two");
        write(4, "four");
        assert!(!resume.files(2).exists());
        assert_eq!(read_json::<u64>(resume.state_path()).unwrap(), 4);
        // Killed after publishing step 6 but before committing it: state still says 4, and
        // the run repeats steps 5–6 and publishes step 6 again over the stale folder.
        let stage = resume.stage().unwrap();
        std::fs::write(stage.join("weights"), "stale").unwrap();
        std::fs::rename(stage, resume.files(6)).unwrap();
        assert_eq!(read_json::<u64>(resume.state_path()).unwrap(), 4);
        let leftover = resume.stage().unwrap();
        std::fs::write(leftover.join("half"), "x").unwrap();
        write(6, "six");
        let got = std::fs::read_to_string(resume.files(6).join("weights")).unwrap();
        assert_eq!(got, "six");
        assert!(!resume.files(6).join("half").exists());
        let left: Vec<_> = std::fs::read_dir(run.path().join("resume"))
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(left, vec![std::ffi::OsString::from("6")]);
    }
}
