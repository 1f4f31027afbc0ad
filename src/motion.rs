//! Motion output of `motionscale generate`: tokens → tokenizer decoder → HumanML3D features
//! → joints → BVH or `.npy`.

use anyhow::{bail, Result};
use model::train::RunConfig;
use std::path::Path;

/// Decode `tokens` with the run's tokenizer and write them to `out` (.npy or .bvh).
pub fn write_motion(
    _tokens: &[u32],
    _run: &RunConfig,
    _tokenizer: Option<&Path>,
    _out: &Path,
) -> Result<()> {
    bail!(
        "decoding tokens to motion needs the tokenizer checkpoint loader (issue 3/8), which this \
         build does not have yet; write the tokens with --out FILE.json"
    )
}
