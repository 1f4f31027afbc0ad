//! Codebook usage over a split: utilisation, entropy and perplexity of the code counts.

use crate::error::TokenizerError;

/// How often each code of a codebook was used.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CodeUsage {
    counts: Vec<u64>,
}

impl CodeUsage {
    /// Zero counts for a codebook of `codebook_size` codes.
    pub fn new(codebook_size: usize) -> Self {
        Self {
            counts: vec![0; codebook_size],
        }
    }

    /// Usage from explicit per-code counts.
    pub fn from_counts(counts: Vec<u64>) -> Self {
        Self { counts }
    }

    /// Count `indices`; an index outside the codebook is an error naming it (the indices
    /// before it stay counted).
    pub fn add(&mut self, indices: impl IntoIterator<Item = u32>) -> Result<(), TokenizerError> {
        let size = self.counts.len();
        for index in indices {
            let slot = self.counts.get_mut(index as usize).ok_or_else(|| {
                TokenizerError::Argument(format!(
                    "code index {index} outside a codebook of {size} codes"
                ))
            })?;
            *slot += 1;
        }
        Ok(())
    }

    /// Per-code counts.
    pub fn counts(&self) -> &[u64] {
        &self.counts
    }

    /// Number of indices counted.
    pub fn total(&self) -> u64 {
        self.counts.iter().sum()
    }

    /// Fraction of codes used at least once (0 for an empty codebook).
    pub fn utilisation(&self) -> f64 {
        if self.counts.is_empty() {
            return 0.0;
        }
        self.counts.iter().filter(|&&c| c > 0).count() as f64 / self.counts.len() as f64
    }

    /// Entropy in nats of the empirical code distribution (0 when nothing was counted).
    pub fn entropy(&self) -> f64 {
        let total = self.total();
        if total == 0 {
            return 0.0;
        }
        self.counts
            .iter()
            .filter(|&&c| c > 0)
            .map(|&c| {
                let p = c as f64 / total as f64;
                -p * p.ln()
            })
            .sum()
    }

    /// Perplexity `exp(entropy)`: the number of equally used codes with the same entropy.
    pub fn perplexity(&self) -> f64 {
        self.entropy().exp()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-12
    }

    #[test]
    fn two_of_four_codes_used_equally() {
        let mut usage = CodeUsage::new(4);
        usage.add([0, 1, 1, 0]).unwrap();
        assert_eq!(usage.counts(), &[2, 2, 0, 0]);
        assert!(close(usage.utilisation(), 0.5));
        assert!(close(usage.entropy(), 2f64.ln()));
        assert!(close(usage.perplexity(), 2.0));
    }

    #[test]
    fn uneven_and_uniform_counts() {
        // -(3/4 ln 3/4 + 1/4 ln 1/4) = 0.5623351446188083.
        let usage = CodeUsage::from_counts(vec![3, 1]);
        assert!(close(usage.entropy(), 0.5623351446188083));
        assert!(close(usage.perplexity(), 0.5623351446188083f64.exp()));
        assert!(close(usage.utilisation(), 1.0));
        let uniform = CodeUsage::from_counts(vec![5; 8]);
        assert!(close(uniform.perplexity(), 8.0));
    }

    #[test]
    fn empty_usage_and_out_of_range_index() {
        let mut usage = CodeUsage::new(3);
        assert_eq!(usage.entropy(), 0.0);
        assert_eq!(usage.perplexity(), 1.0);
        assert_eq!(usage.utilisation(), 0.0);
        let err = usage.add([1, 3]).unwrap_err().to_string();
        assert!(
            err.contains("code index 3 outside a codebook of 3"),
            "{err}"
        );
    }
}
