//! The built-in caption tagger: spaCy-style tokens, universal POS tags from an averaged
//! perceptron, and lemmas from a lexicon with suffix rules. It learns, on first use, from
//! `caption_tags.txt`: spaCy `en_core_web_sm`'s analysis of the project's own motion captions
//! (`ingest/tests/captions/tune.txt`), so it follows spaCy's habits — errors included — on the
//! narrow vocabulary of motion captions without Python or model files.

use super::token::Token;
use motionscale_core::rng::SplitMix64;
use std::collections::{HashMap, HashSet};
use std::sync::OnceLock;

/// spaCy's analysis of the tuning captions: `caption<TAB>text/POS/lemma …` per line.
const TRAINING: &str = include_str!("caption_tags.txt");

/// The universal POS tags spaCy writes.
const TAGS: [&str; 17] = [
    "ADJ", "ADP", "ADV", "AUX", "CCONJ", "DET", "INTJ", "NOUN", "NUM", "PART", "PRON", "PROPN",
    "PUNCT", "SCONJ", "SYM", "VERB", "X",
];
const N: usize = TAGS.len();
const EPOCHS: usize = 12;
const SEED: u64 = 0x7461_6767_6572;

/// A perceptron feature's weight per tag, with the running sums that average it.
#[derive(Default)]
struct Weights {
    w: [f64; N],
    total: [f64; N],
    stamp: [u64; N],
}

/// The trained tagger: averaged weights and the lemmas seen in training.
struct Model {
    weights: HashMap<String, [f64; N]>,
    /// (lower-case word, tag) → lemma, for nouns and verbs.
    lemmas: HashMap<(String, usize), String>,
    /// Every noun and verb lemma seen.
    known: HashSet<String>,
}

/// One training sentence: (token, tag index, lemma).
type Sentence = Vec<(String, usize, String)>;

/// Tokens, tags and lemmas of one caption.
pub fn analyse(caption: &str) -> Vec<Token> {
    static MODEL: OnceLock<Model> = OnceLock::new();
    let model = MODEL.get_or_init(|| Model::train(&parse_training(TRAINING)));
    let words = alpha_tokens(caption);
    let tags = model.tag(&words);
    words
        .into_iter()
        .zip(tags)
        .map(|(text, tag)| Token {
            lemma: model.lemma(&text, tag),
            pos: TAGS[tag].to_string(),
            text,
        })
        .collect()
}

/// One line of `caption_tags.txt` for a caption and spaCy's tokens of it.
pub fn training_line(caption: &str, tokens: &[Token]) -> String {
    let tokens: Vec<String> = tokens
        .iter()
        .map(|t| format!("{}/{}/{}", t.text, t.pos, t.lemma))
        .collect();
    format!("{caption}\t{}\n", tokens.join(" "))
}

fn parse_training(text: &str) -> Vec<Sentence> {
    text.lines()
        .filter_map(|line| line.split_once('\t'))
        .map(|(_, tokens)| {
            tokens
                .split(' ')
                .filter_map(|t| {
                    let mut parts = t.splitn(3, '/');
                    let (text, pos, lemma) = (parts.next()?, parts.next()?, parts.next()?);
                    let tag = TAGS.iter().position(|&p| p == pos)?;
                    Some((text.to_string(), tag, lemma.to_string()))
                })
                .collect()
        })
        .collect()
}

/// The alphabetic tokens spaCy's English tokenizer makes of a caption with hyphens dropped:
/// words split at punctuation, contractions split off (`don't` → `do` + `n't`), and only
/// all-letter tokens kept, as `text_process.py` keeps them.
pub fn alpha_tokens(caption: &str) -> Vec<String> {
    let caption = caption.replace('-', "");
    let mut out = Vec::new();
    let pieces = caption.split(|c: char| !(c.is_alphanumeric() || c == '\'' || c == '’'));
    for piece in pieces {
        let piece = piece.trim_matches(['\'', '’']);
        let lower = piece.to_lowercase();
        let split: Vec<&str> = match lower.as_str() {
            "cannot" => vec![&piece[..3], &piece[3..]],
            "gonna" | "wanna" | "gotta" => vec![&piece[..3], &piece[3..]],
            _ => vec![contraction_stem(piece)],
        };
        let alpha = |w: &&str| !w.is_empty() && w.chars().all(char::is_alphabetic);
        out.extend(split.into_iter().filter(alpha).map(str::to_string));
    }
    out
}

/// The part of a word before a contraction spaCy splits off (`n't`, `'s`, `'re`, …).
fn contraction_stem(word: &str) -> &str {
    let lower = word.to_lowercase().replace('’', "'");
    for (whole, stem_len) in [("can't", 2), ("won't", 2), ("ain't", 2), ("shan't", 3)] {
        if lower == whole {
            return &word[..stem_len];
        }
    }
    let suffixes = ["n't", "'s", "'re", "'ve", "'ll", "'d", "'m"];
    for suffix in suffixes {
        if lower.ends_with(suffix) && lower.len() > suffix.len() {
            let cut = word.char_indices().rev().nth(suffix.chars().count() - 1);
            return &word[..cut.map_or(0, |(i, _)| i)];
        }
    }
    word
}

/// The perceptron's features of token `i` given the tags already chosen for the ones before.
fn features(words: &[String], i: usize, prev: &str, prev2: &str) -> Vec<String> {
    let word = |k: isize| -> &str {
        let j = i as isize + k;
        if j < 0 {
            "<s>"
        } else {
            words.get(j as usize).map_or("</s>", String::as_str)
        }
    };
    let suffix = |w: &str, n: usize| w.chars().rev().take(n).collect::<String>();
    let w = word(0);
    vec![
        "bias".to_string(),
        format!("w={w}"),
        format!("s3={}", suffix(w, 3)),
        format!("s2={}", suffix(w, 2)),
        format!("p1={}", w.chars().next().unwrap_or(' ')),
        format!("t-1={prev}"),
        format!("t-2={prev2},{prev}"),
        format!("t-1w={prev},{w}"),
        format!("w-1={}", word(-1)),
        format!("s3-1={}", suffix(word(-1), 3)),
        format!("w-2={}", word(-2)),
        format!("w+1={}", word(1)),
        format!("s3+1={}", suffix(word(1), 3)),
        format!("w+2={}", word(2)),
        format!("w-1w={},{w}", word(-1)),
        format!("ww+1={w},{}", word(1)),
    ]
}

impl Model {
    /// Averaged-perceptron training over `EPOCHS` seeded shuffles of the sentences.
    fn train(sentences: &[Sentence]) -> Self {
        let mut table: HashMap<String, Weights> = HashMap::new();
        let mut step = 0u64;
        let mut order: Vec<usize> = (0..sentences.len()).collect();
        let mut rng = SplitMix64(SEED);
        for _ in 0..EPOCHS {
            for k in (1..order.len()).rev() {
                order.swap(k, rng.index(k + 1));
            }
            for &s in &order {
                let words: Vec<String> = sentences[s].iter().map(|t| t.0.to_lowercase()).collect();
                let (mut prev, mut prev2) = ("<s>", "<s>");
                for (i, &(_, truth, _)) in sentences[s].iter().enumerate() {
                    step += 1;
                    let feats = features(&words, i, prev, prev2);
                    let guess = argmax(&scores(&feats, |f| table.get(f).map(|w| &w.w)));
                    if guess != truth {
                        for f in feats {
                            let entry = table.entry(f).or_default();
                            for (c, delta) in [(truth, 1.0), (guess, -1.0)] {
                                entry.total[c] += (step - entry.stamp[c]) as f64 * entry.w[c];
                                entry.stamp[c] = step;
                                entry.w[c] += delta;
                            }
                        }
                    }
                    (prev2, prev) = (prev, TAGS[guess]);
                }
            }
        }
        let weights = table
            .into_iter()
            .map(|(f, e)| {
                let avg = std::array::from_fn(|c| {
                    (e.total[c] + (step - e.stamp[c]) as f64 * e.w[c]) / step as f64
                });
                (f, avg)
            })
            .collect();
        let mut lemmas = HashMap::new();
        for (text, tag, lemma) in sentences.iter().flatten() {
            if [tag_index("NOUN"), tag_index("VERB")].contains(tag) {
                lemmas
                    .entry((text.to_lowercase(), *tag))
                    .or_insert_with(|| lemma.clone());
            }
        }
        let known = lemmas.values().cloned().collect();
        Self {
            weights,
            lemmas,
            known,
        }
    }

    /// Greedy left-to-right tags of a caption's tokens.
    fn tag(&self, words: &[String]) -> Vec<usize> {
        let lower: Vec<String> = words.iter().map(|w| w.to_lowercase()).collect();
        let (mut prev, mut prev2) = ("<s>", "<s>");
        let mut tags = Vec::with_capacity(words.len());
        for i in 0..words.len() {
            let feats = features(&lower, i, prev, prev2);
            let tag = argmax(&scores(&feats, |f| self.weights.get(f)));
            tags.push(tag);
            (prev2, prev) = (prev, TAGS[tag]);
        }
        tags
    }

    /// The lemma spaCy would give a word under `tag`: as seen in training (as a noun or a
    /// verb), else by rule.
    fn lemma(&self, word: &str, tag: usize) -> String {
        let lower = word.to_lowercase();
        let seen = |t: usize| self.lemmas.get(&(lower.clone(), t)).cloned();
        let (noun, verb) = (tag_index("NOUN"), tag_index("VERB"));
        if tag == noun {
            seen(noun)
                .or_else(|| seen(verb))
                .unwrap_or_else(|| noun_lemma(&lower))
        } else if tag == verb {
            let known = |w: &str| self.known.contains(w);
            seen(verb)
                .or_else(|| seen(noun))
                .unwrap_or_else(|| verb_lemma(&lower, &known))
        } else {
            lower
        }
    }
}

fn tag_index(tag: &str) -> usize {
    TAGS.iter()
        .position(|&t| t == tag)
        .expect("a universal POS tag")
}

fn scores<'a>(feats: &[String], get: impl Fn(&str) -> Option<&'a [f64; N]>) -> [f64; N] {
    let mut s = [0.0; N];
    for w in feats.iter().filter_map(|f| get(f)) {
        s.iter_mut().zip(w).for_each(|(a, b)| *a += b);
    }
    s
}

/// The best tag; ties go to the earlier tag, so tagging is deterministic.
fn argmax(scores: &[f64; N]) -> usize {
    (0..N).fold(0, |best, c| if scores[c] > scores[best] { c } else { best })
}

/// Singular of a plural noun by spaCy's English suffix rules.
fn noun_lemma(word: &str) -> String {
    let irregular = [
        ("feet", "foot"),
        ("teeth", "tooth"),
        ("men", "man"),
        ("women", "woman"),
        ("children", "child"),
        ("mice", "mouse"),
    ];
    if let Some((_, l)) = irregular.iter().find(|(w, _)| *w == word) {
        return l.to_string();
    }
    let rules = [
        ("ies", "y"),
        ("ves", "f"),
        ("sses", "ss"),
        ("shes", "sh"),
        ("ches", "ch"),
        ("xes", "x"),
        ("zes", "z"),
    ];
    for (suffix, replacement) in rules {
        if let Some(stem) = word.strip_suffix(suffix).filter(|s| s.len() > 1) {
            return format!("{stem}{replacement}");
        }
    }
    match word.strip_suffix('s') {
        Some(stem) if !["s", "u", "i"].iter().any(|e| stem.ends_with(e)) && stem.len() > 1 => {
            stem.to_string()
        }
        _ => word.to_string(),
    }
}

/// Base form of a verb by suffix rules, preferring a lemma seen in training.
fn verb_lemma(word: &str, known: &dyn Fn(&str) -> bool) -> String {
    if let Some(stem) = word
        .strip_suffix("ies")
        .or_else(|| word.strip_suffix("ied"))
    {
        return format!("{stem}y");
    }
    for suffix in ["ing", "ed"] {
        let Some(stem) = word.strip_suffix(suffix).filter(|s| s.len() > 1) else {
            continue;
        };
        return restore_stem(stem, known);
    }
    if let Some(stem) = word.strip_suffix("es") {
        if ["s", "sh", "ch", "x", "z", "o"]
            .iter()
            .any(|e| stem.ends_with(e))
        {
            return stem.to_string();
        }
    }
    match word.strip_suffix('s') {
        Some(stem) if !stem.ends_with('s') && stem.len() > 1 => stem.to_string(),
        _ => word.to_string(),
    }
}

/// The base form behind an `-ing`/`-ed` stem: known forms first, then an undoubled final
/// consonant (`stepp` → `step`) or a restored silent e (`wav` → `wave`).
fn restore_stem(stem: &str, known: &dyn Fn(&str) -> bool) -> String {
    let with_e = format!("{stem}e");
    if known(stem) {
        return stem.to_string();
    }
    if known(&with_e) {
        return with_e;
    }
    let chars: Vec<char> = stem.chars().collect();
    let n = chars.len();
    let vowel = |c: char| "aeiou".contains(c);
    if n >= 3 && chars[n - 1] == chars[n - 2] && !"lsz".contains(chars[n - 1]) {
        return chars[..n - 1].iter().collect();
    }
    let last = chars[n - 1];
    let before = chars[n - 2];
    let silent_e = "vcz".contains(last)
        || (last == 'l' && !vowel(before) && before != 'l')
        || (last == 's' && vowel(before))
        || (n >= 3 && !vowel(chars[n - 3]) && vowel(before) && "kdt".contains(last));
    if silent_e {
        with_e
    } else {
        stem.to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_follow_spacy() {
        assert_eq!(
            alpha_tokens("A person's arm can't stop; he doesn't t-pose 3 times (left/right)."),
            ["A", "person", "arm", "ca", "stop", "he", "does", "tpose", "times", "left", "right"]
        );
        assert_eq!(alpha_tokens("cannot x2 3rd"), ["can", "not"]);
    }

    #[test]
    fn lemma_rules_cover_unseen_words() {
        let none = |_: &str| false;
        assert_eq!(noun_lemma("boxes"), "box");
        assert_eq!(noun_lemma("ladies"), "lady");
        assert_eq!(noun_lemma("feet"), "foot");
        assert_eq!(noun_lemma("bus"), "bus");
        assert_eq!(verb_lemma("skipping", &none), "skip");
        assert_eq!(verb_lemma("juggling", &none), "juggle");
        assert_eq!(verb_lemma("rotated", &none), "rotate");
        assert_eq!(verb_lemma("kicked", &none), "kick");
        assert_eq!(verb_lemma("tosses", &none), "toss");
        assert_eq!(verb_lemma("carries", &none), "carry");
    }

    #[test]
    fn captions_are_tagged_as_spacy_tags_them() {
        let tagged = |c: &str| super::super::text_process::hml3d_tokens(&analyse(c));
        assert_eq!(
            tagged("A person walks forward, then waves his left hand!"),
            "A/DET person/NOUN walk/VERB forward/ADV then/ADV wave/VERB his/PRON left/ADJ hand/NOUN"
        );
        assert_eq!(
            tagged("the man softly lands on both feet and turns left."),
            "the/DET man/NOUN softly/ADV land/VERB on/ADP both/DET foot/NOUN and/CCONJ turn/VERB left/ADJ"
        );
    }
}
