//! Scores an export of curated depth against the hand labels of its real images
//! (`dist4d_stages::eval::labels`), one line per image and the totals:
//!
//!   cargo run --release -p dist4d-stages --example label_scores -- OUT LABELS [SKY_DEPTH]
//!
//! OUT is the `--out` of `dist4d run pipelines/curation.ron`; LABELS a folder of label files
//! (e.g. tests/fixtures/real_labels/dgp-scene02). Used by scripts/real_checks.sh.

use dist4d_stages::eval::labels::{score_export, LabelScores};
use std::path::PathBuf;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(args.len() == 2 || args.len() == 3, "usage: label_scores OUT LABELS [SKY_DEPTH]");
    let sky_depth: f32 = args.get(2).map(|s| s.parse()).transpose()?.unwrap_or(100.0);
    let scored = score_export(&PathBuf::from(&args[0]), &PathBuf::from(&args[1]), sky_depth)?;
    anyhow::ensure!(!scored.is_empty(), "no labelled image of {} is in {}", args[1], args[0]);
    let mut total = LabelScores::default();
    let mut worst_streak: f64 = 0.0;
    println!("image | ego masked | others masked | sky at sky depth | bright structure not sky | streak ratio");
    for s in &scored {
        total.add(&s.scores);
        let streak = s.streak_ratio.unwrap_or(f64::NAN);
        if streak.is_finite() {
            worst_streak = worst_streak.max(streak);
        }
        println!(
            "{} | {} | {} | {} | {} | {:.2}",
            s.depth, s.scores.ego_masked, s.scores.other_masked, s.scores.sky_at_sky, s.scores.bright_not_sky, streak
        );
    }
    println!(
        "all {} images | {} | {} | {} | {} | worst {:.2}",
        scored.len(),
        total.ego_masked,
        total.other_masked,
        total.sky_at_sky,
        total.bright_not_sky,
        worst_streak
    );
    Ok(())
}
