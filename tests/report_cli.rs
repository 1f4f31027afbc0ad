//! `motionscale report` on the committed scaling sweep (`docs/results/scaling-sweep`: plan,
//! results table, fits.json, tokenizer evaluations) and a small synthetic corpus: the page
//! opens with the predictions, predict's verdict and the law they extrapolate, then holds
//! every other section, the fit's laws and charts inline and nothing external; headless
//! Chromium renders it at 1280 px with no console output, a non-blank screenshot, the first
//! prediction and its verdict on the first screen (900 px), no horizontal overflow, charts at
//! full width and no text below 12 px.

mod common;

use common::*;
use std::path::{Path, PathBuf};
use std::process::Command;

/// Measures the laid-out page and writes the figures as JSON into `<pre id="layout">`; the
/// test appends it to a copy of the report (the report itself has no scripts).
const MEASURE: &str = r#"<script>
const texts = [...document.querySelectorAll('body *')].filter(e =>
  !e.closest('svg') && [...e.childNodes].some(n => n.nodeType === 3 && n.textContent.trim()));
const svgs = [...document.querySelectorAll('svg')].map(s => s.getBoundingClientRect());
const pre = document.createElement('pre');
pre.id = 'layout';
pre.textContent = JSON.stringify({
  viewport: window.innerWidth,
  scroll_width: document.documentElement.scrollWidth,
  min_font_px: Math.min(...texts.map(e => parseFloat(getComputedStyle(e).fontSize))),
  svgs: svgs.length,
  min_svg_width: Math.min(...svgs.map(r => r.width)),
  max_svg_right: Math.max(...svgs.map(r => r.right)),
  prediction_bottom: document.querySelector('#predictions table').getBoundingClientRect().bottom,
  verdict_bottom: document.querySelector('#predictions .verdict').getBoundingClientRect().bottom,
});
document.body.appendChild(pre);
</script></body>"#;

/// The height of the first screen (a 1280 × 900 window), where the answer must be.
const FIRST_SCREEN_PX: f64 = 900.0;

/// The Chromium binary, or `None` (a recorded skip; a failure in strict runs).
fn chromium() -> Option<&'static str> {
    let found = ["chromium", "chromium-browser"].into_iter().find(|b| {
        Command::new(b)
            .arg("--version")
            .output()
            .is_ok_and(|o| o.status.success())
    });
    if found.is_none() {
        not_run(
            "headless Chromium is missing (scripts/test.sh installs it: apt-get install chromium)",
        );
    }
    found
}

/// Run headless Chromium at 1280 px on `page` with `args`; returns stdout, stderr.
fn headless(chromium: &str, profile: &Path, page: &Path, args: &[&str]) -> (String, String) {
    let out = Command::new(chromium)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--hide-scrollbars",
        ])
        .args([
            "--enable-logging=stderr",
            "--v=0",
            "--window-size=1280,2000",
        ])
        // Nothing may be fetched: every host name fails to resolve.
        .arg("--host-resolver-rules=MAP * ~NOTFOUND")
        .arg(format!("--user-data-dir={}", profile.display()))
        .args(args)
        .arg(format!("file://{}", page.display()))
        .output()
        .expect("chromium runs");
    assert!(out.status.success(), "chromium failed: {}", text(&out));
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    (stdout, String::from_utf8_lossy(&out.stderr).into_owned())
}

/// Width, height and the fraction of pixels that are not near-white, of an 8-bit PNG.
fn ink(png_path: &Path) -> (u32, u32, f64) {
    let file = std::fs::File::open(png_path).unwrap();
    let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
    decoder.set_transformations(png::Transformations::normalize_to_color8());
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    let channels = info.color_type.samples();
    let pixels = buf[..info.buffer_size()].chunks_exact(channels);
    let total = (info.width * info.height) as f64;
    let inked = pixels
        .filter(|p| p.iter().take(3).any(|&c| c < 200))
        .count();
    (info.width, info.height, inked as f64 / total)
}

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

#[test]
fn report_of_the_committed_sweep_renders_in_headless_chromium() {
    let tmp = tempfile::tempdir().unwrap();
    let corpus = tmp.path().join("corpus");
    motionscale_ok(&[
        "synth",
        "--clips",
        "12",
        "--seed",
        "3",
        "--out",
        arg(&corpus),
    ]);
    let sweep = repo().join("docs/results/scaling-sweep");
    let html_path = tmp.path().join("report.html");
    let stdout = motionscale_ok(&[
        "report",
        arg(&sweep),
        arg(&corpus),
        "--budgets",
        "1e13,1e18",
        "--out",
        arg(&html_path),
    ]);
    assert!(stdout.contains("Predictions"), "{stdout}");
    let html = std::fs::read_to_string(&html_path).unwrap();

    // Self-contained: no scripts, no links or sources outside the page.
    for external in ["<script", "src=", "url(", "@import", "<link", "href=\"http"] {
        assert!(!html.contains(external), "the page holds {external:?}");
    }
    // The answer first: the predictions before every other section, each budget's verdict
    // (the committed fit's intervals are too wide at 1e18) and the law chart in its section.
    let section = |id: &str| {
        html.find(&format!("<section id=\"{id}\">"))
            .unwrap_or_else(|| panic!("section {id}"))
    };
    let predictions = section("predictions");
    for id in ["corpus", "tokenizers", "sweep", "isoflop", "laws"] {
        assert!(predictions < section(id), "predictions after {id}");
    }
    let answer = &html[predictions..section("corpus")];
    assert_eq!(answer.matches("class=\"verdict\"").count(), 2, "{answer}");
    assert!(answer.contains("too wide to act on"), "{answer}");
    assert_eq!(answer.matches("<svg").count(), 1, "the law chart: {answer}");
    assert!(
        !html.contains("class=\"absent\""),
        "every section has content"
    );
    // Every law and chart of the committed fit, the tokenizer evaluations, both budgets.
    let fits: serde_json::Value = read_json(&sweep.join("fits.json"));
    for (key, law) in fits["power_laws"].as_object().unwrap() {
        assert!(html.contains(key.as_str()), "law {key}");
        let exponent = law["fit"]["slope"]["value"].as_f64().unwrap();
        assert!(html.contains(&format!("{exponent:.4}")), "{key} exponent");
    }
    let charts = fits["plots"].as_array().unwrap().len();
    assert_eq!(html.matches("<svg").count(), charts);
    for eval in ["fsq-256-eval-test.json", "fsq-1024-eval-test.json"] {
        assert!(html.contains(eval), "{eval}");
    }
    for budget in ["C = 1.000e13 FLOPs", "C = 1.000e18 FLOPs"] {
        assert!(html.contains(budget), "{budget}");
    }
    assert!(html.contains("Consistency checks"));
    assert!(
        html.contains("12 clips") || html.contains("24 clips"),
        "corpus totals"
    );

    let Some(chromium) = chromium() else { return };
    let profile = tmp.path().join("chromium-profile");
    let shot = tmp.path().join("shot.png");
    let (_, log) = headless(
        chromium,
        &profile,
        &html_path,
        &[&format!("--screenshot={}", shot.display())],
    );
    let console: Vec<&str> = log.lines().filter(|l| l.contains(":CONSOLE")).collect();
    assert!(console.is_empty(), "console output: {console:#?}");
    let (width, height, inked) = ink(&shot);
    assert_eq!((width, height), (1280, 2000));
    assert!(
        inked > 0.01,
        "screenshot nearly blank: {inked:.4} of pixels inked"
    );

    // Layout at 1280 px, measured by a script in a copy of the page.
    let measured = tmp.path().join("measured.html");
    std::fs::write(&measured, html.replace("</body>", MEASURE)).unwrap();
    let (dom, _) = headless(chromium, &profile, &measured, &["--dump-dom"]);
    let json = dom
        .split("<pre id=\"layout\">")
        .nth(1)
        .and_then(|s| s.split("</pre>").next())
        .unwrap_or_else(|| panic!("no layout figures in the DOM: {dom}"));
    let layout: serde_json::Value = serde_json::from_str(json).unwrap();
    let num = |k: &str| {
        layout[k]
            .as_f64()
            .unwrap_or_else(|| panic!("{k}: {layout}"))
    };
    assert_eq!(num("viewport"), 1280.0, "{layout}");
    assert!(
        num("scroll_width") <= 1280.0,
        "horizontal overflow: {layout}"
    );
    assert!(num("min_font_px") >= 12.0, "text below 12 px: {layout}");
    assert_eq!(num("svgs") as usize, charts, "{layout}");
    assert!(num("min_svg_width") >= 900.0, "charts shrunk: {layout}");
    assert!(
        num("max_svg_right") <= 1280.0,
        "a chart overflows: {layout}"
    );
    assert!(
        num("prediction_bottom") <= FIRST_SCREEN_PX && num("verdict_bottom") <= FIRST_SCREEN_PX,
        "the first prediction and its verdict below the first screen: {layout}"
    );
}
