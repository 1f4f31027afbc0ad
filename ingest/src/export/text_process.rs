//! HumanML3D's caption processing (`text_process.py` of the HumanML3D repository): hyphens
//! dropped, spaCy `en_core_web_sm` over the caption, alphabetic tokens kept, each written as
//! `word/POS` with spaCy's universal POS tag, the word being the lemma for nouns and verbs
//! (except the word "left") and the token as written otherwise.

pub use super::spacy::SPACY_PACKAGES;
pub use super::token::Token;
use super::{builtin_tagger, spacy};
use crate::error::IngestError;
use std::collections::HashMap;

/// Which tagger writes the `word/POS` tokens of HumanML3D texts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum PosTagger {
    /// The built-in tagger (no Python): an averaged perceptron trained on spaCy's tags of the
    /// project's own motion captions.
    #[default]
    BuiltIn,
    /// spaCy's `en_core_web_sm` through python3, as HumanML3D ran it: byte-exact texts.
    Spacy,
}

impl std::str::FromStr for PosTagger {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "builtin" => Ok(Self::BuiltIn),
            "spacy" => Ok(Self::Spacy),
            other => Err(format!(
                "unknown POS tagger {other:?}: expected builtin or spacy"
            )),
        }
    }
}

impl PosTagger {
    /// The alphabetic tokens of each caption, analysed by this tagger.
    pub fn analyse(self, captions: &[&str]) -> Result<Vec<Vec<Token>>, IngestError> {
        match self {
            Self::BuiltIn => Ok(captions
                .iter()
                .map(|c| builtin_tagger::analyse(c))
                .collect()),
            Self::Spacy => spacy::analyse(captions),
        }
    }
}

/// The `word/POS …` field HumanML3D writes for a caption's tokens.
pub fn hml3d_tokens(tokens: &[Token]) -> String {
    tokens
        .iter()
        .map(|t| {
            let lemmatised = (t.pos == "NOUN" || t.pos == "VERB") && t.text != "left";
            let word = if lemmatised { &t.lemma } else { &t.text };
            format!("{word}/{}", t.pos)
        })
        .collect::<Vec<_>>()
        .join(" ")
}

/// Captions with their `word/POS` fields, tagged in one batch.
#[derive(Debug)]
pub struct TaggedCaptions {
    tokens: HashMap<String, String>,
}

impl TaggedCaptions {
    /// Tag the distinct captions among `captions` with `tagger`.
    pub fn new<'a>(
        tagger: PosTagger,
        captions: impl IntoIterator<Item = &'a str>,
    ) -> Result<Self, IngestError> {
        let mut distinct: Vec<&str> = captions.into_iter().collect();
        distinct.sort_unstable();
        distinct.dedup();
        let analysed = tagger.analyse(&distinct)?;
        let tokens = distinct
            .iter()
            .zip(&analysed)
            .map(|(c, t)| (c.to_string(), hml3d_tokens(t)))
            .collect();
        Ok(Self { tokens })
    }

    /// The `texts/<id>.txt` line `caption#word/POS …#start#end` (seconds as Python prints a
    /// float, `0.0#0.0` for the whole clip) of a caption given to [`TaggedCaptions::new`].
    pub fn line(&self, caption: &str, start: f64, end: f64) -> String {
        let tokens = self.tokens.get(caption).map_or("", String::as_str);
        format!("{caption}#{tokens}#{start:?}#{end:?}\n")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn token(text: &str, pos: &str, lemma: &str) -> Token {
        Token {
            text: text.into(),
            pos: pos.into(),
            lemma: lemma.into(),
        }
    }

    #[test]
    fn nouns_and_verbs_are_lemmatised_except_left() {
        let tokens = [
            token("He", "PRON", "he"),
            token("left", "VERB", "leave"),
            token("Left", "VERB", "leave"),
            token("feet", "NOUN", "foot"),
            token("softly", "ADV", "softly"),
        ];
        assert_eq!(
            hml3d_tokens(&tokens),
            "He/PRON left/VERB leave/VERB foot/NOUN softly/ADV"
        );
    }

    #[test]
    fn lines_print_seconds_as_python_does() {
        let tagged = TaggedCaptions::new(PosTagger::BuiltIn, ["a man walks."]).unwrap();
        assert_eq!(
            tagged.line("a man walks.", 1.5, 10.0),
            "a man walks.#a/DET man/NOUN walk/VERB#1.5#10.0\n"
        );
        assert_eq!("spacy".parse::<PosTagger>(), Ok(PosTagger::Spacy));
        assert!("nltk"
            .parse::<PosTagger>()
            .unwrap_err()
            .contains("builtin or spacy"));
    }
}
