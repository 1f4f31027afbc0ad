//! Ingest: heterogeneous motion capture → SMPL-22 joints → HumanML3D-263 features →
//! a Parquet corpus with manifest, statistics, splits and a rejects list.

pub mod budget;
#[doc(hidden)]
pub mod bvh_fuzzing;
pub mod corpus;
pub mod demo;
pub mod error;
pub mod export;
pub mod hml263;
pub mod npy;
pub mod pipeline;
pub mod quat;
pub mod resample;
pub mod scenarios;
pub mod skeleton;
pub mod source;

pub use error::IngestError;
