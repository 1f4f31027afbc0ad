//! The memory-mapped reader: clips by id, feature-only decoding, and the seeded window sampler.

mod common;

use common::*;
use ingest::corpus::schema::FEATURE_DIM;
use ingest::corpus::Corpus;

/// The six demo clips and their mirrors, ingested into `tmp/corpus`.
fn demo_corpus(tmp: &std::path::Path) -> std::path::PathBuf {
    let inputs = tmp.join("inputs");
    demo_inputs(&inputs);
    let dir = tmp.join("corpus");
    let out = motionscale(&[
        "ingest",
        "--source",
        &format!("bvh:{}", inputs.display()),
        "--out",
        dir.to_str().unwrap(),
        "--mirror",
    ]);
    assert_eq!(code(&out), 0, "{}", text(&out));
    dir
}

#[test]
fn reader_gives_clips_by_id_and_reproducible_normalised_windows() {
    let tmp = tempfile::tempdir().unwrap();
    let corpus = Corpus::open(&demo_corpus(tmp.path())).unwrap();
    assert_eq!(corpus.clips().len(), 12);
    let i = corpus.find("Mdemo_wave").expect("mirrored copy present");
    let clip = corpus.clip(i).unwrap();
    assert!(clip.mirrored);
    assert_eq!(clip.source_clip, "demo_wave");
    assert!(
        clip.captions.iter().any(|c| c.contains("left hand")),
        "{:?}",
        clip.captions
    );
    assert_eq!(clip.features, corpus.features(i).unwrap());
    assert_eq!(clip.num_frames as usize * FEATURE_DIM, clip.features.len());
    let original = corpus.clip(corpus.find("demo_wave").unwrap()).unwrap();
    assert_eq!(
        original.split, clip.split,
        "mirrored copies share the split"
    );
    assert_eq!(
        original.num_frames, 79,
        "4 s at 30 fps → 80 frames at 20 fps → 79 feature rows"
    );

    let split = clip.split.clone();
    let mut a = corpus.window_sampler(&split, 64, 7);
    let mut b = corpus.window_sampler(&split, 64, 7);
    assert!(a.eligible_clips() > 0);
    let (wa, oa) = a.sample(16).unwrap();
    let (wb, ob) = b.sample(16).unwrap();
    assert_eq!(oa, ob);
    assert_eq!(wa, wb);
    assert_eq!(wa.len(), 16 * 64 * FEATURE_DIM);
    // A window equals the clip's features normalised with the corpus mean/std.
    let o = oa[3];
    let feats = corpus.features(o.clip).unwrap();
    let (mean, std) = (corpus.mean(), corpus.std());
    for t in [0, 63] {
        for d in [0, 5, 100, 262] {
            let raw = feats[(o.start + t) * FEATURE_DIM + d];
            let got = wa[(3 * 64 + t) * FEATURE_DIM + d];
            assert!((got - (raw - mean[d]) / std[d]).abs() < 1e-6);
        }
    }
    let mut c = corpus.window_sampler(&split, 64, 8);
    assert_ne!(
        c.sample(16).unwrap().1,
        oa,
        "another seed draws other windows"
    );
    assert!(corpus.window_sampler(&split, 10_000, 1).sample(1).is_err());
}

#[test]
fn window_sampler_covers_every_window_uniformly_and_preloads_identically() {
    let tmp = tempfile::tempdir().unwrap();
    let corpus = Corpus::open(&demo_corpus(tmp.path())).unwrap();
    let window = 32;
    let split = ["train", "val", "test"]
        .into_iter()
        .max_by_key(|s| corpus.window_sampler(s, window, 0).eligible_clips())
        .unwrap();
    // Preloading changes where features come from, not what is drawn.
    let mut decoding = corpus.window_sampler(split, window, 3);
    let mut preloaded = corpus.window_sampler(split, window, 3).preload().unwrap();
    for _ in 0..3 {
        assert_eq!(decoding.sample(8).unwrap(), preloaded.sample(8).unwrap());
    }
    preloaded.reseed(9);
    let first = preloaded.sample(8).unwrap();
    preloaded.reseed(9);
    assert_eq!(
        first,
        preloaded.sample(8).unwrap(),
        "reseeding replays the draws"
    );

    // Every (clip, start) window is equally likely: a chi-square test over all windows.
    let windows: Vec<(usize, usize)> = corpus
        .clips()
        .iter()
        .enumerate()
        .filter(|(_, c)| c.split == split && c.num_frames as usize >= window)
        .flat_map(|(i, c)| (0..=c.num_frames as usize - window).map(move |s| (i, s)))
        .collect();
    assert!(windows.len() > 100, "{} windows", windows.len());
    let draws = 100 * windows.len();
    let mut counts = std::collections::HashMap::new();
    let (_, origins) = preloaded.sample(draws).unwrap();
    for o in origins {
        *counts.entry((o.clip, o.start)).or_insert(0u64) += 1;
    }
    assert_eq!(counts.len(), windows.len(), "every window is drawn");
    let expected = draws as f64 / windows.len() as f64;
    let chi2: f64 = windows
        .iter()
        .map(|w| (counts[w] as f64 - expected).powi(2) / expected)
        .sum();
    // Wilson–Hilferty 0.999 quantile of chi-square with k - 1 degrees of freedom.
    let k = (windows.len() - 1) as f64;
    let critical = k * (1.0 - 2.0 / (9.0 * k) + 3.09 * (2.0 / (9.0 * k)).sqrt()).powi(3);
    assert!(
        chi2 < critical,
        "chi2 {chi2:.1} ≥ {critical:.1} over {k} dof"
    );
}
