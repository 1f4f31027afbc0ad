//! What every stage of motionscale shares below its own concern: one seeded generator, files
//! written atomically (bytes and JSON), the check that a run folder holds the run asked for,
//! advisory file locks, and the hex spelling of content ids. Errors name the file.

pub mod files;
pub mod lock;
pub mod rng;

pub use files::{read_json, write_atomic, write_json, FileError};

/// Lower-case hex of `bytes` (content ids and checksums).
pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}
