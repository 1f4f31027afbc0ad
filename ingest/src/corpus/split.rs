//! Deterministic train/val/test assignment by hash of the source clip id (80/5/15), so a
//! clip, its segments and its mirrored copy always share a split.

use sha2::{Digest, Sha256};

/// The three splits, in manifest order.
pub const SPLITS: [&str; 3] = ["train", "val", "test"];

/// Split of a source clip id: sha256 of the id, first 8 bytes as u64, mod 100.
pub fn split_of(source_clip: &str) -> &'static str {
    let digest = Sha256::digest(source_clip.as_bytes());
    let bucket = u64::from_le_bytes(digest[..8].try_into().expect("8 bytes")) % 100;
    match bucket {
        0..80 => "train",
        80..85 => "val",
        _ => "test",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn proportions_are_close_to_80_5_15() {
        let mut counts = [0usize; 3];
        for i in 0..20_000 {
            let s = split_of(&format!("clip_{i:05}"));
            counts[SPLITS.iter().position(|x| *x == s).unwrap()] += 1;
        }
        let pct = |c: usize| c as f64 / 200.0;
        assert!((pct(counts[0]) - 80.0).abs() < 1.5, "{counts:?}");
        assert!((pct(counts[1]) - 5.0).abs() < 1.0, "{counts:?}");
        assert!((pct(counts[2]) - 15.0).abs() < 1.5, "{counts:?}");
        assert_eq!(split_of("clip_00001"), split_of("clip_00001"));
    }
}
