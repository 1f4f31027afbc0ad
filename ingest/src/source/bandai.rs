//! Labels and captions for Bandai Namco clips, from the `.json` sidecar (indices into
//! `cfg/content_label.txt` and `cfg/style_label.txt`) mapped per DESIGN.md.

use super::{Labels, Reject};
use std::path::{Path, PathBuf};

/// Emotion carried by a Bandai style; persona styles are neutral.
pub fn emotion_of_style(style: &str) -> &'static str {
    match style {
        "happy" => "happy",
        "sad" => "sad",
        "angry" => "angry",
        "proud" => "proud",
        "not-confident" => "anxious",
        "tired" | "exhausted" => "tired",
        "active" => "energetic",
        _ => "neutral",
    }
}

/// Scenario of a Bandai content label, or `None` for contents outside the five scenarios.
pub fn scenario_of_content(content: &str) -> Option<&'static str> {
    Some(match content {
        c if c.starts_with("walk") || c == "run" || c == "dash" => "locomotion",
        "bow" | "bye" | "byebye" | "guide" | "respond" | "call" => "greeting",
        c if c.starts_with("wave-") || c.starts_with("raise-up-") => "gesture",
        "punch" | "kick" | "slash" => "fighting",
        c if c.starts_with("dance-") => "dance",
        _ => return None,
    })
}

fn action_phrase(content: &str) -> String {
    match content {
        "walk" => "walks forward",
        "run" => "runs forward",
        "dash" => "dashes forward",
        "walk-back" => "walks backward",
        "walk-left" => "walks to the left",
        "walk-right" => "walks to the right",
        "walk-turn-left" => "walks and turns left",
        "walk-turn-right" => "walks and turns right",
        "bow" => "bows",
        "bye" => "waves goodbye",
        "byebye" => "waves goodbye with both hands",
        "guide" => "gestures to show someone the way",
        "respond" => "responds to someone with a gesture",
        "call" => "calls someone over",
        "punch" => "throws a punch",
        "kick" => "kicks",
        "slash" => "slashes with one arm",
        "dance-long" => "dances",
        "dance-short" => "does a short dance",
        "wave-both-hands" => "waves both hands",
        "wave-left-hand" => "waves the left hand",
        "wave-right-hand" => "waves the right hand",
        "raise-up-both-hands" => "raises both hands",
        "raise-up-left-hand" => "raises the left hand",
        "raise-up-right-hand" => "raises the right hand",
        other => return format!("performs a {} motion", other.replace('-', " ")),
    }
    .to_string()
}

fn style_phrases(style: &str) -> [&'static str; 2] {
    match style {
        "happy" => ["looking happy", "cheerfully"],
        "sad" => ["looking sad", "with a sad posture"],
        "angry" => ["looking angry", "angrily"],
        "proud" => ["proudly", "with a proud posture"],
        "not-confident" => ["without confidence", "looking unsure"],
        "tired" | "exhausted" => ["looking tired", "wearily"],
        "active" => ["energetically", "full of energy"],
        "masculinity" | "masculine" => ["in a masculine way", "with a masculine manner"],
        "feminine" => ["in a feminine way", "with a feminine manner"],
        "childish" => ["like a child", "in a childish way"],
        "old" | "elderly" => ["like an elderly person", "in an old person's manner"],
        "youthful" => ["in a youthful way", "like a young person"],
        "musical" => ["like in a musical", "theatrically"],
        "giant" => ["like a giant", "with huge heavy movements"],
        "chimpira" => ["like a street thug", "with a thuggish swagger"],
        _ => ["", "calmly"],
    }
}

/// Captions for a (content, style) pair from several templates.
pub fn captions(content: &str, style: &str) -> Vec<String> {
    let action = action_phrase(content);
    let [s1, s2] = style_phrases(style);
    let mut out = Vec::with_capacity(3);
    out.push(if s1.is_empty() {
        format!("a person {action}.")
    } else {
        format!("a person {action}, {s1}.")
    });
    out.push(format!("someone {action} {s2}."));
    out.push(if s1.is_empty() {
        format!("the person {action} in a normal way.")
    } else {
        format!("the person {action} {s1}.")
    });
    out
}

/// Find `cfg/` beside or above the clip's folder (Bandai layout: `<root>/data/*.bvh`, `<root>/cfg/`).
fn find_cfg(path: &Path) -> Option<PathBuf> {
    path.ancestors()
        .skip(1)
        .take(3)
        .map(|dir| dir.join("cfg"))
        .find(|cfg| cfg.join("content_label.txt").is_file())
}

fn label_list(path: &Path) -> Result<Vec<String>, Reject> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| Reject::new("labels", format!("{}: {e}", path.display())))?;
    // Entries look like `dataset-1_walk`; the part after the dataset prefix is the label.
    Ok(text
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .map(|l| match l.split_once('_') {
            Some((prefix, rest)) if prefix.starts_with("dataset") => rest.to_string(),
            _ => l.to_string(),
        })
        .collect())
}

/// Labels and captions of a Bandai clip from its `.json` sidecar, or `None` when there is none.
pub fn sidecar(clip_path: &Path) -> Result<Option<(Labels, Vec<String>)>, Reject> {
    let json_path = clip_path.with_extension("json");
    if !json_path.is_file() {
        return Ok(None);
    }
    let Some(cfg) = find_cfg(clip_path) else {
        return Ok(None);
    };
    let text = std::fs::read_to_string(&json_path)
        .map_err(|e| Reject::new("labels", format!("{}: {e}", json_path.display())))?;
    #[derive(serde::Deserialize)]
    struct Sidecar {
        content: usize,
        style: usize,
    }
    let ids: Sidecar = serde_json::from_str(&text)
        .map_err(|e| Reject::new("labels", format!("{}: {e}", json_path.display())))?;
    let contents = label_list(&cfg.join("content_label.txt"))?;
    let styles = label_list(&cfg.join("style_label.txt"))?;
    let lookup = |list: &[String], i: usize, what: &str| {
        list.get(i).cloned().ok_or_else(|| {
            Reject::new(
                "labels",
                format!(
                    "{}: {what} index {i} outside the {} labels in {}",
                    json_path.display(),
                    list.len(),
                    cfg.display()
                ),
            )
        })
    };
    let content = lookup(&contents, ids.content, "content")?;
    let style = lookup(&styles, ids.style, "style")?;
    let captions = captions(&content, &style);
    let labels = Labels {
        emotion: Some(emotion_of_style(&style).to_string()),
        scenario: scenario_of_content(&content).map(str::to_string),
        action: Some(content),
        style: Some(style),
    };
    Ok(Some((labels, captions)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn design_mappings() {
        assert_eq!(emotion_of_style("not-confident"), "anxious");
        assert_eq!(emotion_of_style("exhausted"), "tired");
        assert_eq!(emotion_of_style("chimpira"), "neutral");
        assert_eq!(scenario_of_content("walk-turn-left"), Some("locomotion"));
        assert_eq!(scenario_of_content("byebye"), Some("greeting"));
        assert_eq!(scenario_of_content("raise-up-left-hand"), Some("gesture"));
        assert_eq!(scenario_of_content("slash"), Some("fighting"));
        assert_eq!(scenario_of_content("dance-short"), Some("dance"));
        assert_eq!(scenario_of_content("swim"), None);
    }

    #[test]
    fn sidecar_reads_labels_and_makes_captions() {
        let root = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(root.path().join("cfg")).unwrap();
        std::fs::create_dir_all(root.path().join("data")).unwrap();
        std::fs::write(
            root.path().join("cfg/content_label.txt"),
            "dataset-1_walk\ndataset-1_bow\n",
        )
        .unwrap();
        std::fs::write(
            root.path().join("cfg/style_label.txt"),
            "dataset-1_normal\ndataset-1_sad\n",
        )
        .unwrap();
        let clip = root.path().join("data/dataset-1_walk_sad_001.bvh");
        std::fs::write(clip.with_extension("json"), r#"{"content": 0, "style": 1}"#).unwrap();
        let (labels, caps) = sidecar(&clip).unwrap().unwrap();
        assert_eq!(labels.action.as_deref(), Some("walk"));
        assert_eq!(labels.emotion.as_deref(), Some("sad"));
        assert_eq!(labels.scenario.as_deref(), Some("locomotion"));
        assert_eq!(caps[0], "a person walks forward, looking sad.");
        assert_eq!(caps.len(), 3);
        std::fs::write(clip.with_extension("json"), r#"{"content": 5, "style": 1}"#).unwrap();
        let err = sidecar(&clip).unwrap_err();
        assert!(err.reason.contains("content index 5"), "{err}");
    }
}
