//! What `motionscale fit` wrote, read once for every command that takes `--fits`: the IsoFLOP
//! fit (`fits.json`) or the law families' fit (`laws.json` of `fit --law`).

use crate::family::run::LawReport;
use crate::fitted::Fits;
use crate::FitError;
use std::path::Path;

/// What `motionscale fit` wrote: the IsoFLOP fit (`fits.json`) or the law families' fit
/// (`laws.json` of `fit --law`). Every command that takes `--fits` reads it here.
#[derive(Debug, Clone)]
pub enum FitFile {
    /// `fits.json`.
    IsoFlop(Box<Fits>),
    /// `laws.json`.
    Families(Box<LawReport>),
}

impl FitFile {
    /// Reads either file, told apart by its keys.
    pub fn read(path: &Path) -> Result<Self, FitError> {
        let text = std::fs::read_to_string(path).map_err(|source| FitError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let format = |message: String| FitError::Format {
            path: path.to_path_buf(),
            message,
        };
        let value: serde_json::Value =
            serde_json::from_str(&text).map_err(|e| format(format!("not JSON: {e}")))?;
        if value.get("power_laws").is_some() {
            let fits = serde_json::from_value(value)
                .map_err(|e| format(format!("not a fits.json of `motionscale fit`: {e}")))?;
            return Ok(Self::IsoFlop(Box::new(fits)));
        }
        if value.get("adopted").is_some() {
            let laws = serde_json::from_value(value)
                .map_err(|e| format(format!("not a laws.json of `motionscale fit --law`: {e}")))?;
            return Ok(Self::Families(Box::new(laws)));
        }
        Err(format(
            "neither a fits.json (`motionscale fit`) nor a laws.json (`fit --law`)".into(),
        ))
    }
}

impl Fits {
    /// Reads a `fits.json`; a `laws.json` is refused, saying what is needed instead.
    pub fn read(path: &Path) -> Result<Self, FitError> {
        match FitFile::read(path)? {
            FitFile::IsoFlop(fits) => Ok(*fits),
            FitFile::Families(_) => Err(FitError::Format {
                path: path.to_path_buf(),
                message: "a laws.json of `fit --law`; this needs the IsoFLOP fit (fits.json of `motionscale fit` without --law)".into(),
            }),
        }
    }
}
