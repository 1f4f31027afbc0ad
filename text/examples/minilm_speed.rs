//! Sentences per second of the MiniLM encoder at a given batch size (default 64) on the
//! fetched encoder: `cargo run --release -p model --example minilm_speed [BATCH] [SENTENCES]`.
//! Threads follow `RAYON_NUM_THREADS`.

use std::time::Instant;
use text::{BertEncoder, TextEncoder};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let batch: usize = args.next().map_or(Ok(64), |a| a.parse())?;
    let total: usize = args.next().map_or(Ok(1024), |a| a.parse())?;
    let dir = std::env::var_os("MOTIONSCALE_TEXT_ENCODER")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(text::default_encoder_dir);
    let encoder = BertEncoder::load(&dir)?;
    let subjects = ["a person", "someone", "a man", "the figure"];
    let verbs = [
        "walks forward",
        "waves the left hand",
        "jumps twice",
        "turns around slowly",
    ];
    let endings = [
        "",
        ", looking sad",
        " and then stops",
        " while holding a cup in the right hand",
    ];
    let captions: Vec<String> = (0..total)
        .map(|i| {
            format!(
                "{} {}{} ({i}).",
                subjects[i % 4],
                verbs[(i / 4) % 4],
                endings[(i / 16) % 4]
            )
        })
        .collect();
    // Length-sorted, as `embed_corpus` batches them (less padding).
    let mut texts: Vec<&str> = captions.iter().map(String::as_str).collect();
    texts.sort_by_key(|t| t.len());
    encoder.encode(&texts[..batch.min(total)])?;
    let start = Instant::now();
    let mut tokens = 0;
    for chunk in texts.chunks(batch) {
        tokens += encoder
            .encode(chunk)?
            .iter()
            .map(|e| e.len())
            .sum::<usize>();
    }
    let secs = start.elapsed().as_secs_f64();
    println!(
        "{} sentences ({tokens} tokens) in batches of {batch}: {:.1} s, {:.0} sentences/s",
        total,
        secs,
        total as f64 / secs
    );
    Ok(())
}
