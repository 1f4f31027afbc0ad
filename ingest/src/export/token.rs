//! The token both caption taggers produce.

/// One alphabetic token of a caption as spaCy analyses it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Token {
    /// The token as written.
    pub text: String,
    /// Universal POS tag (`NOUN`, `VERB`, `ADP`, …).
    pub pos: String,
    /// Lemma (lower case).
    pub lemma: String,
}
