//! A training recipe per model size: the peak learning rate by a power law in the
//! non-vocabulary parameters, fitted on a rate sweep at several widths (as Porian et al. 2024,
//! "Resolving Discrepancies in Compute-Optimal Scaling of Language Models", tune it per size),
//! and the settings every size shares (warm-up, weight decay, dropout). `sweep plan --recipe`
//! records it in the plan; each point then trains with the rate of its size, and every
//! results row names the recipe and the settings it ran with.

use crate::error::SweepError;
use lm::train::Hyperparams;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The recipe: `lr(N_nv) = lr_at_reference · (N_nv / reference_params)^lr_exponent`, and the
/// shared settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Recipe {
    /// Name recorded in every results row (e.g. `data-bound-2026-11-29`).
    pub name: String,
    /// Peak learning rate at `reference_params`.
    pub lr_at_reference: f64,
    /// Non-vocabulary parameters where the rate is `lr_at_reference`.
    pub reference_params: f64,
    /// Exponent of the rate in N_nv (negative: larger models take smaller rates).
    pub lr_exponent: f64,
    /// Warm-up steps as a fraction of all steps.
    pub warmup: f64,
    /// AdamW decoupled weight decay.
    pub weight_decay: f64,
    /// Residual dropout probability.
    pub dropout: f64,
    /// Where the rule and the settings come from (sweep folders, commands, revision).
    #[serde(default)]
    pub source: String,
}

impl Recipe {
    /// Read a recipe TOML file, checking that its numbers are usable.
    pub fn read(path: &Path) -> Result<Self, SweepError> {
        let text = std::fs::read_to_string(path).map_err(|e| SweepError::io(path, e))?;
        let recipe: Self = toml::from_str(&text).map_err(|e| SweepError::invalid(path, e))?;
        recipe.check().map_err(|e| SweepError::invalid(path, e))?;
        Ok(recipe)
    }

    fn check(&self) -> Result<(), String> {
        let positive = [
            ("lr_at_reference", self.lr_at_reference),
            ("reference_params", self.reference_params),
        ];
        if let Some((name, v)) = positive.iter().find(|(_, v)| !(v.is_finite() && *v > 0.0)) {
            return Err(format!("{name} must be positive, not {v}"));
        }
        if !self.lr_exponent.is_finite() || self.lr_exponent.abs() > 2.0 {
            return Err(format!(
                "lr_exponent {} is not in [-2, 2]",
                self.lr_exponent
            ));
        }
        let fractions = [
            ("warmup", self.warmup),
            ("weight_decay", self.weight_decay),
            ("dropout", self.dropout),
        ];
        match fractions.iter().find(|(_, v)| !(0.0..1.0).contains(v)) {
            Some((name, v)) => Err(format!("{name} {v} is not in [0, 1)")),
            None => Ok(()),
        }
    }

    /// The peak learning rate of a model with `n_nv` non-vocabulary parameters.
    pub fn lr_for(&self, n_nv: u64) -> f64 {
        self.lr_at_reference * (n_nv as f64 / self.reference_params).powf(self.lr_exponent)
    }

    /// `base` with the recipe's settings for a model of `n_nv` non-vocabulary parameters.
    pub fn apply(&self, base: &Hyperparams, n_nv: u64) -> Hyperparams {
        Hyperparams {
            lr: self.lr_for(n_nv),
            warmup_fraction: self.warmup,
            weight_decay: self.weight_decay,
            dropout: self.dropout,
            ..base.clone()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use lm::train::HYPERPARAMS;

    fn recipe() -> Recipe {
        Recipe {
            name: "r".into(),
            lr_at_reference: 4e-3,
            reference_params: 1e6,
            lr_exponent: -0.5,
            warmup: 0.02,
            weight_decay: 0.3,
            dropout: 0.1,
            source: String::new(),
        }
    }

    #[test]
    fn the_rate_follows_the_power_law_and_the_rest_is_shared() {
        let r = recipe();
        assert!((r.lr_for(1_000_000) - 4e-3).abs() < 1e-15);
        assert!((r.lr_for(4_000_000) - 2e-3).abs() < 1e-15);
        let h = r.apply(&HYPERPARAMS, 250_000);
        assert!((h.lr - 8e-3).abs() < 1e-15);
        assert_eq!(
            (h.warmup_fraction, h.weight_decay, h.dropout),
            (0.02, 0.3, 0.1)
        );
        assert_eq!(
            (h.batch_size, h.seed),
            (HYPERPARAMS.batch_size, HYPERPARAMS.seed)
        );
    }

    #[test]
    fn a_file_is_read_and_bad_numbers_are_refused_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("recipe.toml");
        std::fs::write(&path, toml::to_string(&recipe()).unwrap()).unwrap();
        assert_eq!(Recipe::read(&path).unwrap(), recipe());
        let bad = Recipe {
            dropout: 1.0,
            ..recipe()
        };
        std::fs::write(&path, toml::to_string(&bad).unwrap()).unwrap();
        let err = Recipe::read(&path).unwrap_err().to_string();
        assert!(
            err.contains("recipe.toml") && err.contains("dropout"),
            "{err}"
        );
        std::fs::write(&path, "name = \"x\"\nlr = 1\n").unwrap();
        assert!(Recipe::read(&path).is_err());
    }
}
