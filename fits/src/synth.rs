//! Synthetic results tables with known laws and noise: for checking that the fitters recover
//! what they should, and for the `bench fit` timing.

use motionscale_core::rng::SplitMix64;
use std::io::Write;
use std::path::Path;

/// L(N, D) = E + A/N^α + B/D^β.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Law {
    /// Irreducible loss E.
    pub e: f64,
    /// A.
    pub a: f64,
    /// B.
    pub b: f64,
    /// α.
    pub alpha: f64,
    /// β.
    pub beta: f64,
}

/// Hoffmann et al.'s published Chinchilla fit.
pub const CHINCHILLA: Law = Law {
    e: 1.69,
    a: 406.4,
    b: 410.7,
    alpha: 0.34,
    beta: 0.28,
};

/// Chinchilla's nine IsoFLOP budgets (FLOPs).
pub const CHINCHILLA_BUDGETS: [f64; 9] = [6e18, 1e19, 3e19, 6e19, 1e20, 3e20, 6e20, 1e21, 3e21];

impl Law {
    /// The loss at (N, D).
    pub fn loss(&self, n: f64, d: f64) -> f64 {
        self.e + self.a / n.powf(self.alpha) + self.b / d.powf(self.beta)
    }

    /// Compute-optimal N at budget C under C = 6·N·D: G·(C/6)^(β/(α+β)).
    pub fn n_opt(&self, c: f64) -> f64 {
        let g = (self.alpha * self.a / (self.beta * self.b)).powf(1.0 / (self.alpha + self.beta));
        g * (c / 6.0).powf(self.n_exponent())
    }

    /// The exponent b of N_opt ∝ C^b: β/(α+β).
    pub fn n_exponent(&self) -> f64 {
        self.beta / (self.alpha + self.beta)
    }
}

/// One synthetic run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Run {
    /// Parameters N.
    pub n: f64,
    /// Tokens D.
    pub d: f64,
    /// FLOPs C = 6·N·D.
    pub c: f64,
    /// Noisy loss.
    pub loss: f64,
}

/// IsoFLOP runs: at each budget, `per_budget` sizes log-spaced over N_opt(C)·10^[−0.8, 0.8]
/// (each nudged by up to ±0.02 dex), the run's C jittered log-normally by `c_jitter`, D = C/(6N),
/// and loss = law·exp(noise·z) with z standard normal.
pub fn isoflop_runs(
    law: &Law,
    budgets: &[f64],
    per_budget: usize,
    noise: f64,
    c_jitter: f64,
    seed: u64,
) -> Vec<Run> {
    let mut rng = SplitMix64::stream(seed, 0);
    let mut out = Vec::with_capacity(budgets.len() * per_budget);
    for &budget in budgets {
        let centre = law.n_opt(budget).log10();
        for k in 0..per_budget {
            let frac = k as f64 / (per_budget.max(2) - 1) as f64;
            let ln = centre - 0.8 + 1.6 * frac + 0.02 * (2.0 * rng.unit() - 1.0);
            let n = 10f64.powf(ln);
            let c = budget * (c_jitter * rng.normal()).exp();
            let d = c / (6.0 * n);
            let loss = law.loss(n, d) * (noise * rng.normal()).exp();
            out.push(Run { n, d, c, loss });
        }
    }
    out
}

/// A stand-in for Epoch's extracted Chinchilla data: 9 budgets × 28 runs = 252 rows from
/// [`CHINCHILLA`] with 1% log-normal loss noise and 1% C jitter.
pub fn chinchilla_standin(seed: u64) -> Vec<Run> {
    isoflop_runs(&CHINCHILLA, &CHINCHILLA_BUDGETS, 28, 0.01, 0.01, seed)
}

/// Writes runs as CSV with Epoch's column names: `Model Size`, `Training Tokens`,
/// `Training FLOP`, `loss`.
pub fn write_epoch_csv(path: &Path, runs: &[Run]) -> std::io::Result<()> {
    let mut f = std::io::BufWriter::new(std::fs::File::create(path)?);
    writeln!(f, "Model Size,Training Tokens,Training FLOP,loss")?;
    for r in runs {
        writeln!(f, "{},{},{},{}", r.n, r.d, r.c, r.loss)?;
    }
    f.flush()
}

/// The vocabulary-aware truth of [`vocab_sweep`]: the Chinchilla form in N and D plus
/// κ·(log10 V − log10 V*(N))², with the optimal vocabulary parameters N_v*(N) = 10^k·N^γ and
/// V* = N_v*/d. D in the loss is C/(6N): the V-optimum at fixed N is exactly V*.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VocabLaw {
    /// The N, D part.
    pub base: Law,
    /// κ.
    pub kappa: f64,
    /// log10 k of N_v*.
    pub log10_k: f64,
    /// γ.
    pub gamma: f64,
}

/// The truth used by [`vocab_sweep`].
pub const VOCAB_LAW: VocabLaw = VocabLaw {
    base: Law {
        e: 1.0,
        a: 50.0,
        b: 400.0,
        alpha: 0.3,
        beta: 0.3,
    },
    kappa: 0.05,
    log10_k: -1.09,
    gamma: 1.07,
};

/// One row of a sweep's results table (the columns of scaling-laws.md, "IsoFLOP sweep").
#[derive(Debug, Clone, PartialEq)]
pub struct SweepRow {
    /// Run id.
    pub run_id: String,
    /// Budget C.
    pub budget: f64,
    /// Non-vocabulary parameters.
    pub n_nv: f64,
    /// Vocabulary parameters V·d.
    pub n_v: f64,
    /// Codebook size.
    pub vocab: f64,
    /// Width.
    pub d_model: f64,
    /// Layers.
    pub layers: u32,
    /// Heads.
    pub heads: u32,
    /// Tokens D = C / (6·(n_nv + n_v)).
    pub tokens: f64,
    /// Train loss.
    pub train_loss: f64,
    /// Test loss (> 0).
    pub test_loss: f64,
    /// Normalised test loss (test loss − 3: negative for good runs, as ScaMo's L_u).
    pub norm_test_loss: f64,
    /// Wall time.
    pub wall_s: f64,
    /// Actual FLOPs.
    pub flops: f64,
}

/// The column names of [`SweepRow`], in order.
pub const SWEEP_COLUMNS: [&str; 14] = [
    "run_id",
    "budget",
    "n_nv",
    "n_v",
    "vocab",
    "d_model",
    "layers",
    "heads",
    "tokens",
    "train_loss",
    "test_loss",
    "norm_test_loss",
    "wall_s",
    "flops",
];

/// A ScaMo-style sweep from [`VOCAB_LAW`]: 7 budgets (1e15–1e18) × 7 widths (64–512, layers =
/// d/32, N_nv = 12·layers·d²) × 6 codebooks (2^6–2^16, so that even the narrowest width's
/// optimum, near 2^8, is interior), with 1% log-normal loss noise.
pub fn vocab_sweep(seed: u64) -> Vec<SweepRow> {
    let law = VOCAB_LAW;
    let mut rng = SplitMix64::stream(seed, 1);
    let budgets = [1e15, 3e15, 1e16, 3e16, 1e17, 3e17, 1e18];
    let widths = [64u32, 96, 128, 192, 256, 384, 512];
    let vocabs = [64.0, 256.0, 1024.0, 4096.0, 16384.0, 65536.0];
    let mut rows = Vec::new();
    for &c in &budgets {
        for &d in &widths {
            let layers = d / 32;
            let n = 12.0 * layers as f64 * (d as f64).powi(2);
            let v_star = 10f64.powf(law.log10_k) * n.powf(law.gamma) / d as f64;
            for &v in &vocabs {
                let n_v = v * d as f64;
                let clean = law.base.loss(n, c / (6.0 * n))
                    + law.kappa * (v.log10() - v_star.log10()).powi(2);
                let test = clean * (0.01 * rng.normal()).exp();
                rows.push(SweepRow {
                    run_id: format!("c{c:.0e}-d{d}-v{v}"),
                    budget: c,
                    n_nv: n,
                    n_v,
                    vocab: v,
                    d_model: d as f64,
                    layers,
                    heads: (d / 64).max(1),
                    tokens: c / (6.0 * (n + n_v)),
                    train_loss: test * 0.97,
                    test_loss: test,
                    norm_test_loss: test - 3.0,
                    wall_s: 1.0 + c / 1e15,
                    flops: c * 1.02,
                });
            }
        }
    }
    rows
}

/// Writes sweep rows as CSV with [`SWEEP_COLUMNS`].
pub fn write_sweep_csv(path: &Path, rows: &[SweepRow]) -> std::io::Result<()> {
    let mut f = std::io::BufWriter::new(std::fs::File::create(path)?);
    writeln!(f, "{}", SWEEP_COLUMNS.join(","))?;
    for r in rows {
        writeln!(
            f,
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
            r.run_id,
            r.budget,
            r.n_nv,
            r.n_v,
            r.vocab,
            r.d_model,
            r.layers,
            r.heads,
            r.tokens,
            r.train_loss,
            r.test_loss,
            r.norm_test_loss,
            r.wall_s,
            r.flops
        )?;
    }
    f.flush()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn n_opt_minimises_the_law_on_the_isoflop_line() {
        let c = 1e20;
        let at = |n: f64| CHINCHILLA.loss(n, c / (6.0 * n));
        let n = CHINCHILLA.n_opt(c);
        assert!(at(n) < at(n * 1.01) && at(n) < at(n / 1.01));
        assert!((CHINCHILLA.n_exponent() - 0.28 / 0.62).abs() < 1e-15);
    }

    #[test]
    fn standin_has_epoch_shape() {
        let runs = chinchilla_standin(3);
        assert_eq!(runs.len(), 252);
        for r in &runs {
            assert!((6.0 * r.n * r.d / r.c - 1.0).abs() < 1e-9);
            let rel = r.loss / CHINCHILLA.loss(r.n, r.d);
            assert!(rel > 0.95 && rel < 1.05, "{r:?}");
        }
        assert_eq!(runs, chinchilla_standin(3), "seeded");
    }
}
