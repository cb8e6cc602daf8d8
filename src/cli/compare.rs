//! `asgreg compare`: two `asgreg eval` runs of the same scene, frame by frame. Every change to
//! the method is judged on the same frames before and after; a cell's mean moves with each frame
//! that flips between accepted and rejected, so this prints the paired figures and each frame
//! that changed (what the team's ad hoc scripts did, kept as a command).

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use asgreg::eval::{compare_frames, Comparison, EvalCell, EvalResults};
use clap::Args;

#[derive(Args, Debug)]
pub struct CompareArgs {
    /// The baseline: an `asgreg eval` output folder or its results.json.
    pub base: PathBuf,
    /// The run to compare with it (the same scene and frames).
    pub new: PathBuf,
    /// A frame whose δ moved by more than this (px) is listed as changed, as is every frame whose
    /// acceptance flipped.
    #[arg(long, default_value_t = 0.5)]
    pub changed_px: f64,
}

/// `path`'s results.json (the path itself when it is a file).
fn read_results(path: &Path) -> anyhow::Result<EvalResults> {
    let file = if path.is_dir() {
        path.join("results.json")
    } else {
        path.to_path_buf()
    };
    let text = std::fs::read_to_string(&file).with_context(|| {
        format!(
            "reading {} (give an `asgreg eval --out` folder or its results.json)",
            file.display()
        )
    })?;
    serde_json::from_str(&text).with_context(|| {
        format!(
            "{}: not a results.json of `asgreg eval` (rerun eval to write one)",
            file.display()
        )
    })
}

pub fn run(args: &CompareArgs) -> anyhow::Result<()> {
    let base = read_results(&args.base)?;
    let new = read_results(&args.new)?;
    print!("{}", comparison_markdown(&base, &new, args.changed_px)?);
    Ok(())
}

/// The comparison of every cell both runs hold, as Markdown: one summary row per cell, then
/// the frames that changed.
fn comparison_markdown(
    base: &EvalResults,
    new: &EvalResults,
    changed_px: f64,
) -> anyhow::Result<String> {
    let key = |cell: &EvalCell| (cell.level_text(), cell.method.clone());
    let new_cells: BTreeMap<_, _> = new.cells.iter().map(|c| (key(c), c)).collect();
    let compared: Vec<((String, String), Comparison)> = base
        .cells
        .iter()
        .filter_map(|cell| {
            new_cells.get(&key(cell)).map(|other| {
                (
                    key(cell),
                    compare_frames(
                        &cell.frames,
                        &other.frames,
                        base.false_accept_threshold_px,
                        changed_px,
                    ),
                )
            })
        })
        .collect();
    if compared.is_empty() {
        bail!(
            "the two results share no (level, method) cell: compare runs of the same levels and \
             intrinsics"
        );
    }
    let px = |value: Option<f64>| value.map_or("–".to_string(), |v| format!("{v:.2}"));
    let false_accepts = |values: &[f64]| {
        if values.is_empty() {
            "0".to_string()
        } else {
            let list: Vec<String> = values.iter().map(|v| format!("{v:.1}")).collect();
            format!("{} ({} px)", values.len(), list.join(", "))
        }
    };
    let mut out = String::new();
    writeln!(
        out,
        "false accept: δ > {:.2} px; mean δ of the correct accepts; paired: the frames both \
         accepted\n",
        base.false_accept_threshold_px
    )?;
    writeln!(
        out,
        "| level | method | frames | accepted | mean δ (px) | false accepts | paired: frames, δ (px) |"
    )?;
    writeln!(out, "|---|---|---|---|---|---|---|")?;
    for ((level, method), c) in &compared {
        writeln!(
            out,
            "| {level} | {method} | {} | {} → {} | {} → {} | {} → {} | {}, {} |",
            c.frames,
            c.base.accepted,
            c.new.accepted,
            px(c.base.correct_mean_px),
            px(c.new.correct_mean_px),
            false_accepts(&c.base.false_accepts_px),
            false_accepts(&c.new.false_accepts_px),
            c.both_accepted,
            c.both_accepted_mean_px
                .map_or("–".to_string(), |(b, n)| format!("{b:.2} → {n:.2}")),
        )?;
    }
    let verdict = |(accepted, delta): (bool, Option<f64>)| {
        format!(
            "{} {}",
            if accepted { "accepted" } else { "rejected" },
            px(delta)
        )
    };
    for ((level, method), c) in &compared {
        if c.changed.is_empty() {
            continue;
        }
        writeln!(
            out,
            "\n{level} {method}: {} frames changed (acceptance, or δ by more than {changed_px} px)\n",
            c.changed.len()
        )?;
        for change in &c.changed {
            writeln!(
                out,
                "- {}: {} → {}{}",
                change.name,
                verdict(change.base),
                verdict(change.new),
                change
                    .new_reason
                    .as_deref()
                    .filter(|_| !change.new.0)
                    .map_or(String::new(), |r| format!(" ({r})")),
            )?;
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn results(frames: &str) -> EvalResults {
        serde_json::from_str(&format!(
            r#"{{"false_accept_threshold_px": 25.25, "cells": [
                {{"level_px": 30, "method": "known K", "frames": [{frames}]}},
                {{"level_px": "heading", "method": "known K", "frames": []}}]}}"#
        ))
        .unwrap()
    }

    fn frame(name: &str, accepted: bool, delta_px: f64, reason: &str) -> String {
        format!(
            r#"{{"name": "{name}", "initial_delta_px": 30.0, "accepted": {accepted},
                "final_delta_px": {delta_px}, "confidence": 0.9, "evidence": null,
                "reason": {reason}, "total_ms": 1.0}}"#
        )
    }

    #[test]
    fn two_runs_print_their_cells_and_the_frames_that_changed() {
        let base = results(
            &[
                frame("v0.jpg", true, 1.0, "null"),
                frame("v1.jpg", true, 4.0, "null"),
            ]
            .join(","),
        );
        let new = results(
            &[
                frame("v0.jpg", true, 1.1, "null"),
                frame("v1.jpg", false, 9.0, r#""the refined poses disagree""#),
            ]
            .join(","),
        );
        let text = comparison_markdown(&base, &new, 0.5).unwrap();
        assert!(
            text.contains("| 30 | known K | 2 | 2 → 1 | 2.50 → 1.10 | 0 → 0 | 1, 1.00 → 1.10 |"),
            "{text}"
        );
        assert!(text.contains("| heading | known K | 0 |"), "{text}");
        assert!(
            text.contains("- v1.jpg: accepted 4.00 → rejected 9.00 (the refined poses disagree)"),
            "{text}"
        );
        assert!(!text.contains("- v0.jpg"), "{text}");
    }

    #[test]
    fn runs_without_a_common_cell_are_an_error() {
        let base = results("");
        let mut new = results("");
        for cell in &mut new.cells {
            cell.method = "unknown K".into();
        }
        let error = comparison_markdown(&base, &new, 0.5).unwrap_err();
        assert!(error.to_string().contains("share no (level, method) cell"));
    }
}
