//! Arguments of `motionscale sweep plan`, and the plan request they make: `sweep plan` plans
//! it ([`crate::sweep_cmd`]), `sweep plan --next` extends a plan by the planner's proposals
//! from it ([`crate::planner_cmd`]).

use crate::tokenizer_cmd::TrainFlags;
use anyhow::{bail, Context, Result};
use clap::Parser;
use experiments::data_ladder::{self, DataSource};
use experiments::plan::{self, PlanRequest, TrainSettings, VocabSource};
use experiments::recipe::Recipe;
use experiments::IsoFlopPlan;
use lm::train::Hyperparams;
use std::path::PathBuf;

/// Arguments of `motionscale sweep plan`.
#[derive(clap::Args, Debug)]
pub struct PlanArgs {
    /// Corpus with caption embeddings (`embed-text`); tokenizers the plan trains learn on it.
    #[arg(long)]
    pub corpus: PathBuf,
    /// Compute budgets C in FLOPs (6·N·D convention), comma-separated.
    #[arg(long, value_delimiter = ',', required_unless_present = "extend")]
    pub budgets: Vec<f64>,
    /// Models, comma-separated: presets, `cpu` (the CPU ladder), `scamo` (ScaMo's six sizes)
    /// or WIDTHxLAYERS[xHEADS] shapes (heads of width 64 by default).
    #[arg(long, value_delimiter = ',', required_unless_present = "extend")]
    pub models: Vec<String>,
    /// Nominal codebook sizes, comma-separated.
    #[arg(long, value_delimiter = ',', required_unless_present = "extend")]
    pub vocabs: Vec<usize>,
    /// Trained tokenizers to use: `V=DIR,…` (tokenized into RUNS/tokens/V).
    #[arg(long, value_delimiter = ',')]
    pub tokenizers: Vec<String>,
    /// Token sets to use as they are: `V=DIR,…`.
    #[arg(long, value_delimiter = ',')]
    pub token_sets: Vec<String>,
    /// Quantizer of the tokenizers the plan trains (vocabularies given neither way).
    #[arg(long, default_value = "fsq", value_parser = ["fsq", "vq"])]
    pub quantizer: String,
    /// `tokenizer train` flags of the tokenizers the plan trains, e.g.
    /// "--width 64 --batch 64 --steps 1200 --lr 5e-4 --grad-clip 1".
    #[arg(long, default_value = "", allow_hyphen_values = true)]
    pub tokenizer_flags: String,
    /// Text encoder id of the caption embeddings (default: the corpus's only one).
    #[arg(long)]
    pub text_emb: Option<String>,
    /// Optimisation settings of every point.
    #[command(flatten)]
    pub hyper: Hyperparams,
    /// A recipe per model size (TOML: name, lr_at_reference, reference_params, lr_exponent,
    /// warmup, weight_decay, dropout, source): each point's peak rate is the recipe's at its
    /// N_nv, and the recipe's warm-up, weight decay and dropout replace --warmup,
    /// --weight-decay and --dropout; every results row names it.
    #[arg(long, value_name = "RECIPE_TOML")]
    pub recipe: Option<PathBuf>,
    /// Checkpoint and evaluate the test split every N steps (and at the end).
    #[arg(long, default_value_t = TrainSettings::default().checkpoint_every)]
    pub checkpoint_every: u64,
    /// Arithmetic of every point: f32, or bf16 products from f32 masters (on a GPU).
    #[arg(long, default_value = "f32", value_name = "f32|bf16")]
    pub precision: nn::device::Precision,
    /// An earlier fit (`fit`'s fits.json, e.g. of a pilot sweep): each budget then gets the
    /// --sizes-per-budget models of --models nearest its predicted N_opt (the fit's parabola at
    /// that budget, else its N_opt ∝ C^b law, else its parametric L(N, D)), with a warning where
    /// they do not bracket it.
    #[arg(long, value_name = "FITS_JSON")]
    pub fits: Option<PathBuf>,
    /// Models per budget when centring on --fits.
    #[arg(long, default_value_t = 6, requires = "fits")]
    pub sizes_per_budget: usize,
    /// Flag points that take more than E epochs of the train split (`above-max-epochs`).
    #[arg(long, value_name = "E")]
    pub max_epochs: Option<f64>,
    /// Drop the points above --max-epochs instead of flagging them (listed as warnings).
    #[arg(long, requires = "max_epochs")]
    pub drop_above_max_epochs: bool,
    /// An earlier plan to extend: its points come first, unchanged, and a sweep folder that
    /// ran it adopts the new plan (give the same corpus, settings and vocabulary folders).
    #[arg(long, value_name = "PLAN")]
    pub extend: Option<PathBuf>,
    /// Run ids to repeat with each of --seeds (new points `<run_id>-s<seed>`), e.g. each
    /// budget's best point, for the run-to-run noise.
    #[arg(long, value_delimiter = ',', requires = "seeds")]
    pub repeat: Vec<String>,
    /// Training seeds of the --repeat points, comma-separated.
    #[arg(long, value_delimiter = ',', requires = "repeat")]
    pub seeds: Vec<u64>,
    /// The unique-data axis: every point at each fraction of the train hours, e.g.
    /// `1/8,1/4,1/2,1` (nested subsets drawn by source clip, mirrors and segments together;
    /// val and test stay whole; run ids end in `-d<source>-<fraction>`).
    #[arg(long, value_delimiter = ',', value_parser = data_ladder::parse_fraction)]
    pub data_fractions: Vec<f64>,
    /// The clips the --data-fractions draw from: real (captured), synth or all.
    #[arg(long, default_value = "all", requires = "data_fractions")]
    pub data_source: DataSource,
    /// Seed of the clip order of the --data-fractions (recorded in the plan).
    #[arg(long, default_value_t = 0, requires = "data_fractions")]
    pub data_seed: u64,
    /// Propose the K runs (from --budgets × --models × --vocabs) that most narrow the
    /// --target's interval at --target-budget per FLOP, given the runs of the --extend plan
    /// trained so far (`sweep replay` judges the policy); the output extends that plan.
    #[arg(long, value_name = "K", requires_all = ["target_budget", "fits", "extend"])]
    pub next: Option<usize>,
    /// With --next: the budget C* whose target is narrowed (above every trained budget).
    #[arg(long, requires = "next")]
    pub target_budget: Option<f64>,
    /// With --next: n_opt (log10 N_opt), loss (at N_opt), or hour_value (the loss change of
    /// +1 h of captured motion at --target-budget; needs a `fit --repeated-data` fit).
    #[arg(long, default_value = "n_opt", value_parser = fits::planner::Goal::parse)]
    pub target: fits::planner::Goal,
    /// With --next --target hour_value: the corpus's hours per source (default: the plan's
    /// full-data subset).
    #[arg(long, value_name = "real=H,synth=H", value_parser = crate::fit::parse_hours, requires = "next")]
    pub hours: Option<fits::data_value::Hours>,
    /// With --next: the most FLOPs the proposed runs may cost together.
    #[arg(long, requires = "next")]
    pub max_compute: Option<f64>,
    /// With --next: the results table of the trained runs (default: the table --fits read).
    #[arg(long, requires = "next")]
    pub results: Option<PathBuf>,
    /// Output plan file (.toml).
    #[arg(long)]
    pub out: PathBuf,
}

/// `tokenizer train` flags given as one string.
#[derive(Parser, Debug)]
#[command(no_binary_name = true)]
struct TokenizerFlagsLine {
    #[command(flatten)]
    flags: TrainFlags,
}

/// `V=DIR` pairs.
fn vocab_dirs(pairs: &[String], flag: &str) -> Result<Vec<(usize, PathBuf)>> {
    pairs
        .iter()
        .map(|p| {
            let (v, dir) = p
                .split_once('=')
                .with_context(|| format!("--{flag} {p:?}: want V=DIR"))?;
            let v = v
                .parse()
                .with_context(|| format!("--{flag} {p:?}: {v:?} is not a codebook size"))?;
            Ok((v, PathBuf::from(dir)))
        })
        .collect()
}

impl PlanArgs {
    /// The shared training settings; with a recipe, its settings at its reference size.
    fn settings(&self) -> Result<TrainSettings> {
        let recipe = self.recipe.as_deref().map(Recipe::read).transpose()?;
        let hyper = match &recipe {
            Some(r) => r.apply(&self.hyper, r.reference_params as u64),
            None => self.hyper.clone(),
        };
        Ok(TrainSettings {
            hyper,
            checkpoint_every: self.checkpoint_every,
            precision: self.precision,
            recipe,
        })
    }

    pub(crate) fn request(&self) -> Result<PlanRequest> {
        let flags = TokenizerFlagsLine::try_parse_from(self.tokenizer_flags.split_whitespace())
            .with_context(|| format!("--tokenizer-flags {:?}", self.tokenizer_flags))?
            .flags;
        let tokenizers = vocab_dirs(&self.tokenizers, "tokenizers")?;
        let token_sets = vocab_dirs(&self.token_sets, "token-sets")?;
        for (v, _) in tokenizers.iter().chain(&token_sets) {
            if !self.vocabs.contains(v) {
                bail!("vocabulary {v} is given a folder but is not in --vocabs");
            }
        }
        let mut vocabularies = Vec::new();
        for &v in &self.vocabs {
            let given = |list: &[(usize, PathBuf)]| {
                list.iter().find(|(k, _)| *k == v).map(|(_, d)| d.clone())
            };
            let source = match (given(&token_sets), given(&tokenizers)) {
                (Some(_), Some(_)) => {
                    bail!("vocabulary {v}: give a token set or a tokenizer, not both")
                }
                (Some(dir), None) => VocabSource::TokenSet { dir },
                (None, Some(dir)) => VocabSource::Tokenizer { dir },
                (None, None) => VocabSource::Train {
                    tokenizer: Box::new(flags.tokenizer_config(&self.quantizer, v)?),
                    train: Box::new(flags.train_config()),
                },
            };
            vocabularies.push((v, source));
        }
        Ok(PlanRequest {
            corpus: self.corpus.clone(),
            text_encoder: self.text_emb.clone(),
            budgets: self.budgets.clone(),
            models: self.models.clone(),
            vocabularies,
            train: self.settings()?,
            // With --next, --fits is the planner's fit, not the grid's centre.
            centring: match (&self.fits, self.next) {
                (None, _) | (_, Some(_)) => None,
                (Some(path), None) => Some(plan::Centring {
                    fits: fits::Fits::read(path)?,
                    sizes: self.sizes_per_budget,
                }),
            },
            max_epochs: self.max_epochs.map(|epochs| plan::EpochLimit {
                epochs,
                drop: self.drop_above_max_epochs,
            }),
            extend: self.extend.as_deref().map(IsoFlopPlan::read).transpose()?,
            repeat: self.repeat.clone(),
            repeat_seeds: self.seeds.clone(),
            data_fractions: self.data_fractions.clone(),
            data_source: self.data_source,
            data_seed: self.data_seed,
            only: Vec::new(),
        })
    }
}
