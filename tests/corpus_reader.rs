//! The memory-mapped reader: clips by id, feature-only decoding, and the seeded window sampler.

mod common;

use common::*;
use ingest::corpus::schema::FEATURE_DIM;
use ingest::corpus::Corpus;

#[test]
fn reader_gives_clips_by_id_and_reproducible_normalised_windows() {
    let tmp = tempfile::tempdir().unwrap();
    let inputs = tmp.path().join("inputs");
    demo_inputs(&inputs);
    let dir = tmp.path().join("corpus");
    let out = motionscale(&[
        "ingest",
        "--source",
        &format!("bvh:{}", inputs.display()),
        "--out",
        dir.to_str().unwrap(),
        "--mirror",
    ]);
    assert_eq!(code(&out), 0, "{}", text(&out));

    let corpus = Corpus::open(&dir).unwrap();
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
