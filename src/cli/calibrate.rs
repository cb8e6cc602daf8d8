//! `asgreg calibrate`: fits the confidence model ([`asgreg::core::confidence`]) on `asgreg eval`
//! results with ground truth and chooses the accept threshold so that the measured false-accept
//! rate among accepted frames stays below a bound (issue #11 item 4). Prints the calibration
//! table of the fit and of held-out results, and what the paper's check alone would accept in
//! its strictest form (`confidence.max_convergence_at_chance`); writes the model as JSON.

use std::path::PathBuf;

use anyhow::{bail, Context};
use asgreg::core::confidence::{
    features, fit_logistic, ConfidenceConfig, LogisticModel, FEATURE_COUNT, FEATURE_NAMES,
};
use asgreg::eval::{calibration_bins, EvalFrame, EvalResults};
use clap::Args;

#[derive(Args, Debug)]
pub struct CalibrateArgs {
    /// results.json files of `asgreg eval` to fit on (ICP cells are skipped).
    #[arg(long, required = true, num_args = 1..)]
    pub results: Vec<PathBuf>,
    /// Held-out results.json files: the fitted model's table on them.
    #[arg(long, num_args = 0..)]
    pub validate: Vec<PathBuf>,
    /// L2 penalty of the fit on the standardised weights.
    #[arg(long, default_value_t = 1.0)]
    pub ridge: f64,
    /// Highest false-accept rate allowed among accepted frames when choosing the threshold.
    #[arg(long, default_value_t = 0.005)]
    pub max_false_accept_rate: f64,
    /// Write the fitted model and threshold here (JSON).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Leave these features out of the fit (their weight is 0), e.g. to measure on the same
    /// frames whether a feature helps held out. Names as printed (`FEATURE_NAMES`).
    #[arg(long, num_args = 1..)]
    pub drop_feature: Vec<String>,
}

/// A frame with evidence and a pose (`frame.evidence` is always `Some`), labelled.
struct Labelled {
    frame: EvalFrame,
    correct: bool,
}

impl Labelled {
    fn check_passed(&self) -> bool {
        self.frame.evidence.is_some_and(|e| e.check_passed)
    }
}

fn load(paths: &[PathBuf]) -> anyhow::Result<Vec<Labelled>> {
    let mut out = Vec::new();
    for path in paths {
        let text =
            std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let file: EvalResults = serde_json::from_str(&text).with_context(|| {
            format!(
                "{}: not a results.json of `asgreg eval` (rerun eval to write one)",
                path.display()
            )
        })?;
        // Results written before the check's outcome was recorded read it as false everywhere;
        // their `accepted` was the check's outcome.
        let check_recorded = file
            .cells
            .iter()
            .flat_map(|c| c.frames.iter())
            .any(|f| f.evidence.is_some_and(|e| e.check_passed));
        for cell in file
            .cells
            .into_iter()
            .filter(|c| !c.method.starts_with("ICP"))
        {
            for mut frame in cell.frames {
                let (Some(mut evidence), Some(delta_px)) = (frame.evidence, frame.final_delta_px)
                else {
                    continue;
                };
                if !check_recorded {
                    evidence.check_passed = frame.accepted;
                    frame.evidence = Some(evidence);
                }
                out.push(Labelled {
                    correct: delta_px <= file.false_accept_threshold_px,
                    frame,
                });
            }
        }
    }
    Ok(out)
}

pub fn run(args: &CalibrateArgs) -> anyhow::Result<()> {
    let mut kept = [true; FEATURE_COUNT];
    for name in &args.drop_feature {
        let Some(index) = FEATURE_NAMES.iter().position(|n| n == name) else {
            bail!(
                "--drop-feature {name}: no such feature (the features: {})",
                FEATURE_NAMES.join(", ")
            );
        };
        kept[index] = false;
    }
    let per_file: Vec<Vec<Labelled>> = args
        .results
        .iter()
        .map(|path| load(std::slice::from_ref(path)))
        .collect::<anyhow::Result<_>>()?;
    let train: Vec<&Labelled> = per_file.iter().flatten().collect();
    if train.is_empty() {
        bail!("the results files hold no frame with evidence and a pose; run `asgreg eval` (known or unknown K) to make some");
    }
    let model = fit(&train, args.ridge, &kept)?;
    println!(
        "fitted on {} frames ({} correct); bias {:.3}",
        train.len(),
        train.iter().filter(|l| l.correct).count(),
        model.bias
    );
    for (name, weight) in FEATURE_NAMES.iter().zip(model.weights.iter()) {
        println!("  {name:<28} {weight:+.3}");
    }
    let mut threshold = report(
        &train,
        &model,
        args.max_false_accept_rate,
        "fit (in sample)",
    );
    // Each file held out in turn: fitted on the others, measured on it. The threshold must hold
    // on every held-out file, not only in sample.
    if per_file.len() > 1 {
        for (held_out_index, held_out) in per_file.iter().enumerate() {
            let others: Vec<&Labelled> = per_file
                .iter()
                .enumerate()
                .filter(|(i, _)| *i != held_out_index)
                .flat_map(|(_, frames)| frames.iter())
                .collect();
            let Ok(partial) = fit(&others, args.ridge, &kept) else {
                println!(
                    "\n{}: not held out (the other files have one class only)",
                    args.results[held_out_index].display()
                );
                continue;
            };
            let title = format!(
                "held out {} (fitted on the others)",
                args.results[held_out_index].display()
            );
            let held_out: Vec<&Labelled> = held_out.iter().collect();
            threshold = threshold.max(report(
                &held_out,
                &partial,
                args.max_false_accept_rate,
                &title,
            ));
        }
    }
    for path in &args.validate {
        let frames = load(std::slice::from_ref(path))?;
        let frames: Vec<&Labelled> = frames.iter().collect();
        report(
            &frames,
            &model,
            args.max_false_accept_rate,
            &format!("validate {}", path.display()),
        );
        report(
            &frames,
            &ConfidenceConfig::default().model,
            args.max_false_accept_rate,
            &format!("the default model on {}", path.display()),
        );
    }
    report_agreement_alone(&train);
    println!("\nthreshold (the highest of the in-sample and held-out ones): {threshold:.2}");
    if let Some(out) = &args.out {
        let json = serde_json::json!({
            "model": model,
            "accept_above": threshold,
            "features": FEATURE_NAMES,
            "fitted_on": args.results,
            "ridge": args.ridge,
            "dropped_features": args.drop_feature,
            "max_false_accept_rate": args.max_false_accept_rate,
        });
        std::fs::write(out, serde_json::to_string_pretty(&json)?)
            .with_context(|| format!("writing {}", out.display()))?;
        println!("wrote {}", out.display());
    }
    Ok(())
}

/// The paper's check alone, in the strictest form `confidence.max_convergence_at_chance` accepts
/// on where the photo shows none of the model's edges (`FrameEvidence::agreed_by_every_coarse_pose`),
/// measured on `frames` with their edge evidence withheld: per bound on the convergence, the
/// frames it would accept on the agreement alone and how far off they are.
fn report_agreement_alone(frames: &[&Labelled]) {
    let default_bound = ConfidenceConfig::default().max_convergence_at_chance;
    println!(
        "\n## The paper's check alone, strictest form (edge evidence withheld)\n\nEvery coarse pose refined, all in one agreeing group converged to at most the bound (the default bound: {default_bound}).\n"
    );
    println!("| convergence at most | frames | within 2 px | beyond 5 px | false accepts | their δ (px) |\n|---|---|---|---|---|---|");
    for bound in [0.25, 0.5, 0.75, 0.9] {
        let agreed: Vec<&&Labelled> = frames
            .iter()
            .filter(|l| {
                l.frame
                    .evidence
                    .is_some_and(|e| e.agreed_by_every_coarse_pose(bound))
            })
            .collect();
        let delta = |l: &&&Labelled| l.frame.final_delta_px.unwrap_or(f64::INFINITY);
        let within = agreed.iter().filter(|l| delta(l) <= 2.0).count();
        let beyond = agreed.iter().filter(|l| delta(l) > 5.0).count();
        let wrong: Vec<String> = agreed
            .iter()
            .filter(|l| !l.correct)
            .map(|l| format!("{:.1}", delta(l)))
            .collect();
        println!(
            "| {bound:.2} | {} | {within} | {beyond} | {} | {} |",
            agreed.len(),
            wrong.len(),
            wrong.join(", ")
        );
    }
}

/// The model fitted on `frames` with the features not `kept` held at 0 (so their weight is 0).
fn fit(
    frames: &[&Labelled],
    ridge: f64,
    kept: &[bool; FEATURE_COUNT],
) -> anyhow::Result<LogisticModel> {
    let samples: Vec<_> = frames
        .iter()
        .filter_map(|l| {
            l.frame.evidence.map(|e| {
                let mut x = features(&e);
                for (value, keep) in x.iter_mut().zip(kept) {
                    if !keep {
                        *value = 0.0;
                    }
                }
                (x, l.correct)
            })
        })
        .collect();
    fit_logistic(&samples, ridge).context("fitting the confidence model")
}

/// Prints the calibration table of `frames` under `model` and, per threshold, the frames a
/// decision "accept when the confidence is at least the threshold" accepts, its false accepts and
/// their mean δ; returns the lowest threshold at which (and above which) the false-accept rate
/// among accepted frames is within `max_rate`.
fn report(frames: &[&Labelled], model: &LogisticModel, max_rate: f64, title: &str) -> f64 {
    // Rescored by the model, with δ replaced by its label so that the bins count correct frames
    // whatever each file's false-accept threshold was.
    let rescored: Vec<EvalFrame> = frames
        .iter()
        .map(|l| {
            let mut frame = l.frame.clone();
            frame.confidence = l.frame.evidence.map_or(0.0, |e| model.probability(&e));
            frame.final_delta_px = Some(if l.correct { 0.0 } else { 1.0 });
            frame
        })
        .collect();
    println!(
        "\n{title}: {} frames, {} correct",
        frames.len(),
        frames.iter().filter(|l| l.correct).count()
    );
    println!("| confidence | frames | correct | share correct |\n|---|---|---|---|");
    for bin in calibration_bins(&rescored, 0.5, 10)
        .iter()
        .filter(|b| b.frames > 0)
    {
        println!(
            "| {:.1}–{:.1} | {} | {} | {:.0} % |",
            bin.lower,
            bin.upper,
            bin.frames,
            bin.correct,
            100.0 * bin.correct as f64 / bin.frames as f64
        );
    }
    println!("| threshold | accepted | of them check passed | false accepts | mean δ of correct accepted (px) |\n|---|---|---|---|---|");
    let mut chosen = 1.0;
    let mut still_within = true;
    for step in (0..20).rev() {
        let threshold = step as f64 / 20.0;
        let accepted: Vec<&&Labelled> = frames
            .iter()
            .zip(&rescored)
            .filter(|(_, f)| f.confidence >= threshold)
            .map(|(l, _)| l)
            .collect();
        let wrong = accepted.iter().filter(|l| !l.correct).count();
        let checked = accepted.iter().filter(|l| l.check_passed()).count();
        let correct_deltas: Vec<f64> = accepted
            .iter()
            .filter(|l| l.correct)
            .filter_map(|l| l.frame.final_delta_px)
            .collect();
        let mean_px = if correct_deltas.is_empty() {
            f64::NAN
        } else {
            correct_deltas.iter().sum::<f64>() / correct_deltas.len() as f64
        };
        println!(
            "| {threshold:.2} | {} | {checked} | {wrong} | {mean_px:.2} |",
            accepted.len()
        );
        let rate = wrong as f64 / accepted.len().max(1) as f64;
        still_within &= rate <= max_rate;
        if still_within {
            chosen = threshold;
        }
    }
    println!("{title}: lowest threshold with a false-accept rate ≤ {max_rate}: {chosen:.2}");
    chosen
}
