//! `asgreg eval --changes`: change detection measured on a `synth --changes` scene. Runs
//! `asgreg changes` (the same function) with the scene's depth maps (or, `--depth-source stereo`,
//! plane-sweep stereo depth, also measured against the scene's depth maps) under the ground-truth
//! poses (or `--changes-poses`), then compares its masks with `changes_gt/` (pixel precision, recall,
//! IoU per kind) and its fused objects with `changes.json` (object recall over the true objects
//! of at least 3 × 3 m seen by at least 2 frames, precision over the confirmed detections; every
//! unmatched detection is listed: clutter that is not in the model shows there, not hidden).
//! The truth is every listed difference: the placed changes and the building parts the degraded
//! model omits by design (`model_omissions`), each shown in its own rows; a detection is true
//! when it matches one of them (kind, footprint within 1 m, centroid within 1 m of its footprint,
//! footprint at most 3 × its area + 10 m²: a whole roof is not a find of the small structure on it).

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use anyhow::Context;
use asgreg::core::change::fusion::FusedChange;
use asgreg::core::change::polygon::{convex_distance, width_and_length};
use asgreg::core::change::{ChangeClass, ChangeKind};
use asgreg::synth::changes::{ChangesFile, TrueChange, MASK_DIR, OBJECTS_FILE};
use serde::Serialize;

use super::changes::{detect_all, mask_path, stereo_depth_path, ChangesArgs};
use super::eval::{DepthSourceArg, EvalArgs};
use super::inputs::PosedInputs;
use asgreg::core::change::stereo::{depth_errors, DepthErrors};
use asgreg::core::reprojection::{mutual_reprojection_error_px, ReprojectionWorkspace};
use asgreg::io::colmap_model::read_images_at;
use asgreg::io::pfm::read_pfm;

/// A detection matches a true object of its kind when their footprints are this close, m.
const MATCH_DISTANCE_M: f64 = 1.0;
/// A true object counts as seen by a frame with at least this many true-mask pixels.
const SEEN_MIN_PIXELS: usize = 25;
/// Frames that must see a true object for it to count in the recall.
const SEEN_MIN_FRAMES: usize = 2;
/// Least footprint side of a counted true object, m (3 × 3 m).
const MIN_SIDE_M: f64 = 3.0;
/// A matching detection's footprint is at most this many times the true footprint's area…
const MATCH_AREA_RATIO: f64 = 3.0;
/// …plus this, m² (footprints of small objects widen by a metre of depth noise on each side).
const MATCH_AREA_MARGIN_M2: f64 = 10.0;

#[derive(Clone, Copy, Debug, Default, Serialize)]
struct PixelScores {
    true_positive: u64,
    false_positive: u64,
    false_negative: u64,
}

impl PixelScores {
    fn precision(&self) -> f64 {
        self.true_positive as f64 / (self.true_positive + self.false_positive).max(1) as f64
    }
    fn recall(&self) -> f64 {
        self.true_positive as f64 / (self.true_positive + self.false_negative).max(1) as f64
    }
    fn iou(&self) -> f64 {
        self.true_positive as f64
            / (self.true_positive + self.false_positive + self.false_negative).max(1) as f64
    }
}

/// The footprint's least width (a rectangle's shorter side).
fn min_side_m(object: &TrueChange) -> f64 {
    width_and_length(&object.footprint_m).0
}

fn matches(detection: &FusedChange, truth: &TrueChange) -> bool {
    let centroid = [[detection.centroid_m[0], detection.centroid_m[1]]];
    detection.kind == truth.kind
        && convex_distance(&detection.footprint_m, &truth.footprint_m) <= MATCH_DISTANCE_M
        && convex_distance(&centroid, &truth.footprint_m) <= MATCH_DISTANCE_M
        && detection.footprint_area_m2
            <= MATCH_AREA_RATIO * truth.footprint_area_m2 + MATCH_AREA_MARGIN_M2
}

/// One frame's pose term against the truth: the error its change map allowed for (u, px,
/// `ChangeConfig::pose_sigma_px` as the frame used it) and the true error of the pose it was
/// detected under (δ to the ground-truth pose, paper eq. 5, on the detection's model).
#[derive(Clone, Debug, Serialize)]
struct PoseTermRow {
    name: String,
    u_px: f32,
    true_delta_px: f64,
}

/// The pose term of every frame with a change map under `inputs`' poses (read from
/// `poses_path`) against the scene's truth (`gt/images.txt`): what the threshold allowed for a
/// pose error, and what the error was.
fn pose_term_against_truth(
    inputs: &PosedInputs,
    cameras_path: &Path,
    poses_path: &Path,
    truth_path: &Path,
    frames: &[(String, f32)],
) -> anyhow::Result<Vec<PoseTermRow>> {
    let (truth, _) = read_images_at(truth_path)
        .with_context(|| format!("cannot read the true poses {}", truth_path.display()))?;
    let mut workspace = ReprojectionWorkspace::default();
    let mut rows = Vec::new();
    for (name, u_px) in frames {
        let (posed, camera) = inputs.find_image(name, poses_path, cameras_path)?;
        let true_pose = truth
            .iter()
            .find(|t| &t.name == name)
            .with_context(|| format!("{name} is not in the true poses {}", truth_path.display()))?;
        let true_delta_px = mutual_reprojection_error_px(
            &inputs.mesh,
            camera,
            &posed.cam_from_world,
            camera,
            &true_pose.cam_from_world,
            &mut workspace,
        )
        .unwrap_or(f64::NAN);
        rows.push(PoseTermRow {
            name: name.clone(),
            u_px: *u_px,
            true_delta_px,
        });
    }
    Ok(rows)
}

/// The median of `values` (NaN left out); NaN when none.
fn median(mut values: Vec<f64>) -> f64 {
    values.retain(|v| !v.is_nan());
    if values.is_empty() {
        return f64::NAN;
    }
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

pub fn run(args: &EvalArgs) -> anyhow::Result<()> {
    let scene = &args.scene;
    let objects_path = scene.join(OBJECTS_FILE);
    let truth: ChangesFile =
        serde_json::from_str(&std::fs::read_to_string(&objects_path).with_context(|| {
            format!(
                "cannot read {}: make the scene with `asgreg synth --changes`",
                objects_path.display()
            )
        })?)
        .with_context(|| format!("{} is not a changes file", objects_path.display()))?;
    let poses = args
        .changes_poses
        .clone()
        .unwrap_or_else(|| scene.join("gt/images.txt"));
    let stereo = args.depth_source == DepthSourceArg::Stereo;
    let mut detect_args = ChangesArgs::with_defaults(
        args.model.path(scene)?,
        scene.join("images"),
        scene.join("gt/cameras.txt"),
        poses.clone(),
        (!stereo).then(|| scene.join("depth")),
        args.out
            .join(if stereo { "changes_stereo" } else { "changes" }),
    );
    detect_args.limit = args.limit;
    detect_args.edge_tolerance_px = args.change_edge_tolerance_px;
    detect_args.stereo = args.stereo.clone();
    detect_args.pose_sigma_px = args.change_pose_sigma_px;
    detect_args.no_pose_sigma_from_depth = args.change_no_pose_sigma_from_depth;
    // Registered poses: each frame's pose error from its registration (as the pipeline's change
    // stage has it), from the report beside the poses unless one is named.
    detect_args.registration_report = args.change_registration_report.clone().or_else(|| {
        let beside = args.changes_poses.as_ref()?.parent()?.join("report.json");
        beside.is_file().then_some(beside)
    });
    if let Some(report) = &detect_args.registration_report {
        println!(
            "pose error per frame from the registration report {}",
            report.display()
        );
    }
    let (report, inputs) = detect_all(&detect_args)?;

    // Pixels.
    let mut pixels: BTreeMap<ChangeKind, PixelScores> = BTreeMap::new();
    let mut frames_with_result = Vec::new();
    for frame in report.frames.iter().filter(|f| f.failure.is_none()) {
        let truth_path = scene
            .join(MASK_DIR)
            .join(Path::new(&frame.name).with_extension("png"));
        let truth_mask = image::open(&truth_path)
            .with_context(|| format!("cannot read the true mask {}", truth_path.display()))?
            .to_luma8();
        let detected_path = mask_path(&detect_args.out, &frame.name);
        let detected = image::open(&detected_path)
            .with_context(|| format!("cannot read {}", detected_path.display()))?
            .to_luma8();
        anyhow::ensure!(
            truth_mask.dimensions() == detected.dimensions(),
            "{}: true mask {:?} and detection {:?} differ in size",
            frame.name,
            truth_mask.dimensions(),
            detected.dimensions()
        );
        for (t, d) in truth_mask.as_raw().iter().zip(detected.as_raw()) {
            let (t, d) = (
                ChangeClass::from_mask_value(*t),
                ChangeClass::from_mask_value(*d),
            );
            for kind in [ChangeKind::Added, ChangeKind::Removed] {
                let scores = pixels.entry(kind).or_default();
                match (t == kind.class(), d == kind.class()) {
                    (true, true) => scores.true_positive += 1,
                    (false, true) => scores.false_positive += 1,
                    (true, false) => scores.false_negative += 1,
                    (false, false) => {}
                }
            }
        }
        frames_with_result.push(frame.name.clone());
    }

    // Under poses other than the truth: the pose term each change map allowed for, against the
    // pose's true error (how far u is from what it stands for).
    let pose_term = match &args.changes_poses {
        Some(poses) => Some(pose_term_against_truth(
            &inputs,
            &detect_args.cameras,
            poses,
            &scene.join("gt/images.txt"),
            &report
                .frames
                .iter()
                .filter(|f| f.failure.is_none())
                .map(|f| (f.name.clone(), f.pose_sigma_px))
                .collect::<Vec<_>>(),
        )?),
        None => None,
    };

    // Stereo depth against the scene's given (MVS-like) depth, over the frames with a result.
    let mut stereo_errors: Option<DepthErrors> = None;
    if stereo {
        let (mut estimate, mut reference) = (Vec::new(), Vec::new());
        for name in &frames_with_result {
            let ours = stereo_depth_path(&detect_args.out, name);
            let given = asgreg::frame_files::depth_path_for(&scene.join("depth"), name);
            let ours =
                read_pfm(&ours).with_context(|| format!("cannot read {}", ours.display()))?;
            let given = read_pfm(&given).with_context(|| {
                format!(
                    "cannot read {} (the scene's depth, to measure stereo against)",
                    given.display()
                )
            })?;
            anyhow::ensure!(
                ours.size() == given.size(),
                "{name}: stereo depth {:?} and given depth {:?} differ in size",
                ours.size(),
                given.size()
            );
            estimate.extend_from_slice(ours.data());
            reference.extend_from_slice(given.data());
        }
        let n = estimate.len();
        stereo_errors = Some(depth_errors(
            asgreg::core::image::ImageView::new(n, 1, &estimate)?,
            asgreg::core::image::ImageView::new(n, 1, &reference)?,
        ));
    }

    // Objects: the placed changes, then the parts the model omits (each true object takes the
    // nearest unused confirmed detection that matches it; a detection that merged two objects
    // finds one of them).
    let seen_frames = |object: &TrueChange| {
        object
            .pixels_per_image
            .iter()
            .filter(|(name, &count)| count >= SEEN_MIN_PIXELS && frames_with_result.contains(name))
            .count()
    };
    let is_counted =
        |o: &TrueChange| min_side_m(o) >= MIN_SIDE_M - 1e-6 && seen_frames(o) >= SEEN_MIN_FRAMES;
    let confirmed: Vec<&FusedChange> = report.objects.iter().filter(|o| o.confirmed).collect();
    let mut used: Vec<Option<u32>> = vec![None; confirmed.len()];
    let mut found_by: BTreeMap<u32, usize> = BTreeMap::new();
    for object in truth.objects.iter().chain(&truth.model_omissions) {
        let best = confirmed
            .iter()
            .enumerate()
            .filter(|(k, d)| used[*k].is_none() && matches(d, object))
            .min_by(|a, b| {
                convex_distance(&a.1.footprint_m, &object.footprint_m)
                    .total_cmp(&convex_distance(&b.1.footprint_m, &object.footprint_m))
            })
            .map(|(k, _)| k);
        if let Some(k) = best {
            used[k] = Some(object.id);
            found_by.insert(object.id, k);
        }
    }
    let score = |list: &[TrueChange]| -> (usize, usize, usize) {
        let counted = list.iter().filter(|o| is_counted(o)).count();
        let found = list
            .iter()
            .filter(|o| is_counted(o) && found_by.contains_key(&o.id))
            .count();
        let detections = list.iter().filter(|o| found_by.contains_key(&o.id)).count();
        (counted, found, detections)
    };
    let (counted_changes, found_changes, on_changes) = score(&truth.objects);
    let (counted_omissions, found_omissions, on_omissions) = score(&truth.model_omissions);
    let (counted, found) = (
        counted_changes + counted_omissions,
        found_changes + found_omissions,
    );
    let true_detections = on_changes + on_omissions;
    let recall = found as f64 / counted.max(1) as f64;
    let precision = true_detections as f64 / confirmed.len().max(1) as f64;

    let mut text = String::new();
    writeln!(
        text,
        "# asgreg eval --changes\n\nscene {}, poses {}, depth {}, {} frames with a change map ({} without), {:.1} ms per frame\n",
        scene.display(),
        poses.display(),
        report.depth_source,
        frames_with_result.len(),
        report.frames.len() - frames_with_result.len(),
        report.mean_detect_ms
    )?;
    if let (Some(e), Some(ms)) = (&stereo_errors, report.mean_stereo_ms) {
        writeln!(
            text,
            "stereo depth ({ms:.0} ms per frame) against the scene's given MVS-like depth (0.7 % noise): median |rel| {:.2} %, within 1/2/5 %: {:.1} / {:.1} / {:.1} %, {:.1} % of the given depth's pixels have a stereo depth\n",
            100.0 * e.median_relative,
            100.0 * e.within_1_percent,
            100.0 * e.within_2_percent,
            100.0 * e.within_5_percent,
            100.0 * e.valid_share
        )?;
    }
    if let Some(rows) = pose_term.as_ref().filter(|rows| !rows.is_empty()) {
        let covered = rows
            .iter()
            .filter(|r| f64::from(r.u_px) >= r.true_delta_px)
            .count();
        writeln!(
            text,
            "pose term (the pose error u each change map allowed for, against the pose's true δ), {} frames: u median {:.2} px, true δ median {:.2} px, u ≥ δ in {covered}, u / δ median {:.2}\n",
            rows.len(),
            median(rows.iter().map(|r| f64::from(r.u_px)).collect()),
            median(rows.iter().map(|r| r.true_delta_px).collect()),
            median(
                rows.iter()
                    .filter(|r| r.true_delta_px > 0.0)
                    .map(|r| f64::from(r.u_px) / r.true_delta_px)
                    .collect()
            ),
        )?;
    }
    writeln!(text, "| pixels | precision | recall | IoU | TP | FP | FN |")?;
    writeln!(text, "|---|---|---|---|---|---|---|")?;
    for (kind, s) in &pixels {
        writeln!(
            text,
            "| {} | {:.3} | {:.3} | {:.3} | {} | {} | {} |",
            kind.name(),
            s.precision(),
            s.recall(),
            s.iou(),
            s.true_positive,
            s.false_positive,
            s.false_negative
        )?;
    }
    writeln!(
        text,
        "\nobjects (truth: the placed changes and the parts the model omits by design): recall {found}/{counted} = {:.1} % (true objects ≥ 3 × 3 m seen by ≥ {SEEN_MIN_FRAMES} frames; changes {found_changes}/{counted_changes}, model omissions {found_omissions}/{counted_omissions}), precision {true_detections}/{} = {:.1} % (confirmed detections; {on_changes} on changes, {on_omissions} on model omissions), {} unconfirmed detections\n",
        100.0 * recall,
        confirmed.len(),
        100.0 * precision,
        report.objects.len() - confirmed.len()
    )?;
    for (title, list) in [
        ("true object (placed change)", &truth.objects),
        (
            "model omission (a part the degraded model leaves out)",
            &truth.model_omissions,
        ),
    ] {
        writeln!(
            text,
            "| {title} | kind | footprint m | area m² | height m | frames seen | counted | found (detection m²) |"
        )?;
        writeln!(text, "|---|---|---|---|---|---|---|---|")?;
        for object in list {
            let (width, length) = width_and_length(&object.footprint_m);
            writeln!(
                text,
                "| {} {:?} | {} | {:.1} × {:.1} | {:.1} | {:.1} | {} | {} | {} |",
                object.id,
                object.what,
                object.kind.name(),
                width,
                length,
                object.footprint_area_m2,
                object.height_m,
                seen_frames(object),
                if is_counted(object) { "yes" } else { "no" },
                match found_by.get(&object.id) {
                    Some(&k) => format!("yes ({:.1})", confirmed[k].footprint_area_m2),
                    None => "no".to_owned(),
                }
            )?;
        }
        writeln!(text)?;
    }
    writeln!(
        text,
        "confirmed detections matched to no true object (clutter not in the model, model errors, or a second object merged into one detection):\n"
    )?;
    for (_, detection) in confirmed
        .iter()
        .enumerate()
        .filter(|(k, _)| used[*k].is_none())
    {
        writeln!(
            text,
            "- {} {:.1} m² footprint, {:.1} m high at ({:.1}, {:.1}, {:.1}), {} frames",
            detection.kind.name(),
            detection.footprint_area_m2,
            detection.height_m,
            detection.centroid_m[0],
            detection.centroid_m[1],
            detection.centroid_m[2],
            detection.frames.len(),
        )?;
    }
    let omission_pixels: usize = truth
        .model_omissions
        .iter()
        .flat_map(|o| o.pixels_per_image.iter())
        .filter(|(name, _)| frames_with_result.contains(name))
        .map(|(_, count)| count)
        .sum();
    writeln!(
        text,
        "\nof the true added pixels, {omission_pixels} are on model omissions"
    )?;
    print!("{text}");
    std::fs::write(args.out.join("changes_eval.md"), &text)
        .with_context(|| format!("cannot write {}", args.out.display()))?;
    let json = serde_json::json!({
        "scene": scene,
        "poses": poses,
        "frames": frames_with_result.len(),
        "mean_detect_ms": report.mean_detect_ms,
        "depth_source": report.depth_source,
        "mean_stereo_ms": report.mean_stereo_ms,
        "stereo_depth_errors": stereo_errors,
        "pose_term": pose_term,
        "pixels": pixels.iter().map(|(k, s)| (k.name(), serde_json::json!({
            "precision": s.precision(), "recall": s.recall(), "iou": s.iou(), "counts": s,
        }))).collect::<BTreeMap<_, _>>(),
        "objects": {
            "counted_true": counted, "found": found, "recall": recall,
            "confirmed": confirmed.len(), "true_detections": true_detections, "precision": precision,
            "unconfirmed": report.objects.len() - confirmed.len(),
            "changes": {"counted": counted_changes, "found": found_changes, "detections": on_changes},
            "model_omissions": {"counted": counted_omissions, "found": found_omissions, "detections": on_omissions},
            "true_pixels_on_model_omissions": omission_pixels,
        },
    });
    std::fs::write(
        args.out.join("changes_eval.json"),
        serde_json::to_string_pretty(&json)?,
    )
    .with_context(|| format!("cannot write {}", args.out.display()))?;
    Ok(())
}
