//! Step "search": the centre of the coarse poses found in a wide region around the prior
//! ([`crate::core::pose_search`], issue #12), before "plan". The model is rendered at the prior's
//! centre at a few headings; every candidate rotation of the grid is scored on the photo's
//! oriented edges without a rendering of its own; the best distinct candidates (beams) and the
//! prior itself are refined by edge alignment ([`super::refine_pose`]) and compared by their edge
//! support. A beam replaces the prior only when its support clearly beats the prior's, and even
//! then the prior stays a centre of its own coarse poses (`keep_prior_centre`: a wrong beam can
//! beat a weak prior's support); when another distinct beam is about as good, the search does
//! not toss a coin: the
//! best beam, the prior and the rivals each become the centre of their own coarse poses, and
//! verification with the calibrated confidence decides among them ([`super::decide`]). When the
//! photo's edges show the model nowhere in the region (the search is blind, `is_blind`), the
//! prior's flipped heading becomes a second centre: the edges could not rule it out.

use std::time::Instant;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::{
    process_cpu_ms, refine_pose, render_coarse_view, CoarseView, RefineWorkspace,
    RegistrationConfig,
};
use crate::core::camera::Camera;
use crate::core::edge_align::{
    align_level, blurred_query, edge_evidence, model_edge_samples, AlignedKinds, AlignedParameters,
    EdgeAlignConfig, EdgeSample, UNBOUNDED_IMAGE_UNCERTAINTY_PX,
};
use crate::core::image::{Image, ImageView};
use crate::core::mesh::Mesh;
use crate::core::pose_search::{
    first_distinct, position_candidate, score_rotation, score_rotations, screening_capture_deg,
    search_samples, select_beams, turned_pose, wrap_deg, Candidate, OrientedEdgeMap,
    PoseSearchConfig, SearchSample,
};
use crate::core::raster::Rasterizer;
use crate::core::rigid::Rigid3;

/// One beam after its refinement.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Beam {
    /// Heading, pitch and roll of the grid candidate relative to the prior, degrees (zeros for
    /// the prior itself).
    pub yaw_deg: f64,
    pub pitch_deg: f64,
    pub roll_deg: f64,
    /// The grid score (mean oriented edge-map value, 0..1; the prior's is not computed: NaN).
    pub grid_score: f64,
    /// Its edge support after the render-free screening alignment (0..1; NaN for the prior).
    pub screened_support: f64,
    /// Where its edge alignment ended (or the candidate when the alignment was not better).
    pub cam_from_world: Rigid3,
    /// Its edge support (share of model edges supported by photo ridges, 0..1).
    pub support: f64,
    /// How far the frame's image may move per px of edge noise given its supported edges
    /// ([`crate::core::edge_align::image_uncertainty_px`]); a beam above the confidence's
    /// `max_image_uncertainty_px` cannot replace the prior nor be its rival.
    #[serde(default)]
    pub image_uncertainty_px: f64,
    /// The support the photo's edges give this pose's model edges by chance: the mean share
    /// where the image is moved by the far ring's shift
    /// ([`crate::core::edge_align::SupportPeak::far`]; 0 when its refinement failed, and in
    /// files written before it existed).
    #[serde(default)]
    pub chance: f64,
}

/// What the search found.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseSearchOutcome {
    /// The centres of the coarse poses, best first: the prior or the beam that replaced it; when
    /// the search is ambiguous also the prior and the rivals; when it is blind the prior's
    /// flipped heading (at most
    /// [`crate::core::pose_search::PoseSearchConfig::max_centres`]). Each gets its own
    /// `coarse_pose_count` coarse poses and verification decides among them.
    pub centres: Vec<Rigid3>,
    /// Whether a beam replaced the prior.
    pub moved: bool,
    /// The prior's own edge support (0..1).
    pub prior_support: f64,
    /// The refined prior first, then the grid's beams, best grid score first.
    pub beams: Vec<Beam>,
    /// Why the search could not choose on the photo's edges alone, when it could not.
    pub ambiguous: Option<String>,
    /// Whether the photo's edges showed the model nowhere in the region (`is_blind`): the prior
    /// stayed, and where the flip was searched and the model is in view from it (and
    /// `max_centres` ≥ 2) its flipped heading became a centre too. Reported by the diagnosis
    /// (`search_diagnosis.json`).
    #[serde(default)]
    pub blind: bool,
    /// The search's own wall time, ms.
    pub search_ms: f64,
    /// The process's CPU time during the search, ms (the search's own where nothing else runs in
    /// the process, as in `register`; its renderings run on several threads).
    #[serde(default)]
    pub search_cpu_ms: f64,
}

/// Searches the region of `config.pose_search` around `prior` for the pose that best explains
/// `query`'s edges. `None` when the search is disabled.
pub fn search_pose(
    mesh: &Mesh,
    camera: &Camera,
    prior: &Rigid3,
    query: ImageView<'_, f32>,
    config: &RegistrationConfig,
    rasterizer: &mut Rasterizer,
    view: &mut CoarseView,
) -> Option<PoseSearchOutcome> {
    let search = &config.pose_search;
    if !search.enabled {
        return None;
    }
    let started = Instant::now();
    let started_cpu_ms = process_cpu_ms();
    let map = OrientedEdgeMap::build(query, search);
    let ScreenedGrid { grid, screened } =
        screen_grid(mesh, camera, prior, query, &map, config, rasterizer, view);
    // The model shows edges from the prior's flipped heading (its grid rendering had enough
    // samples; an oblique camera turned around may look away from it).
    let flip_in_view = group_of(&grid.groups, 180.0, search.render_heading_step_deg).is_some();
    let grid_beams = beams_of(screened, search);

    // Each beam, and the prior, refined by edge alignment from a wide first search.
    let refine_config = RegistrationConfig {
        edge_align: EdgeAlignConfig {
            initial_search_radius_px: search
                .refine_initial_radius_px
                .max(config.edge_align.final_search_radius_px),
            ..search_alignment(&config.edge_align)
        },
        ..config.clone()
    };
    // A start refined: where it ended as a beam (grid fields as for the prior) and the start's
    // own support.
    let refine = |workspace: &mut RefineWorkspace, start: &Rigid3| -> (Beam, f64) {
        let beam =
            |cam_from_world: Rigid3, support: f64, image_uncertainty_px: f64, chance: f64| Beam {
                yaw_deg: 0.0,
                pitch_deg: 0.0,
                roll_deg: 0.0,
                grid_score: f64::NAN,
                screened_support: f64::NAN,
                cam_from_world,
                support,
                image_uncertainty_px,
                chance,
            };
        match refine_pose(
            mesh,
            camera,
            query,
            start,
            AlignedParameters::Pose,
            &refine_config,
            workspace,
        ) {
            Ok(r) => {
                let before = r.verified.support_fraction();
                // The peak is measured at the output: the aligned pose when kept.
                let (pose, support) = if r.kept {
                    (r.aligned_cam_from_world, r.aligned.support_fraction())
                } else {
                    (*start, before)
                };
                (
                    beam(pose, support, r.peak.image_uncertainty_px, r.peak.far),
                    before,
                )
            }
            Err(_) => (beam(*start, 0.0, UNBOUNDED_IMAGE_UNCERTAINTY_PX, 0.0), 0.0),
        }
    };
    // The prior and each beam, refined side by side (independent runs), in that order.
    let starts: Vec<&Rigid3> = std::iter::once(prior)
        .chain(grid_beams.iter().map(|(_, screened_pose, _)| screened_pose))
        .collect();
    let mut refined: Vec<(Beam, f64)> = starts
        .par_iter()
        .map_init(RefineWorkspace::default, |workspace, start| {
            refine(workspace, start)
        })
        .collect();
    let prior_support = refined[0].1;
    let prior_refined_support = refined[0].0.support;
    let mut beams: Vec<Beam> = Vec::with_capacity(refined.len());
    beams.push(refined.remove(0).0);
    for ((candidate, _, screened_support), (refined_beam, _)) in grid_beams.iter().zip(refined) {
        beams.push(Beam {
            yaw_deg: candidate.yaw_deg,
            pitch_deg: candidate.pitch_deg,
            roll_deg: candidate.roll_deg,
            grid_score: candidate.score,
            screened_support: *screened_support,
            ..refined_beam
        });
    }

    // The decision, among the prior and the beams whose supporting edges fix them (a beam whose
    // support comes from a sliver of the model or from parallel lines is no evidence).
    let fixed = |index: usize| {
        index == 0
            || beams[index].image_uncertainty_px <= config.confidence.max_image_uncertainty_px
    };
    let best_index = beams
        .iter()
        .enumerate()
        .filter(|(index, _)| fixed(*index))
        .max_by(|a, b| a.1.support.total_cmp(&b.1.support))
        .map_or(0, |(index, _)| index);
    let best = &beams[best_index];
    // The beams are refined, so the prior is measured refined too (and as it is, if better).
    let reference = prior_support.max(prior_refined_support);
    let moved = best_index != 0
        && best.support >= reference + search.min_support_gain
        && best.support >= search.min_support;
    let separation_rad = search.beam_separation_deg.to_radians();
    // Only a move is a choice among beams: when the prior stays, the coarse poses start from it
    // as without the search, and verification decides.
    let mut rivals: Vec<usize> = (0..beams.len())
        .filter(|&index| {
            moved
                && index != best_index
                && fixed(index)
                && beams[index].support >= search.min_support
                && beams[index].support >= search.ambiguity_ratio * best.support
                && beams[index]
                    .cam_from_world
                    .rotation_angle_to_rad(&best.cam_from_world)
                    > separation_rad
        })
        .collect();
    rivals.sort_by(|&a, &b| beams[b].support.total_cmp(&beams[a].support));
    let ambiguous = rivals.first().map(|&rival| {
        let rival = &beams[rival];
        format!(
            "edge support {:.2} at heading {:+.0}° pitch {:+.1}° roll {:+.1}° against {:.2} at heading {:+.0}° pitch {:+.1}° roll {:+.1}° ({:.1}° apart)",
            best.support,
            best.yaw_deg,
            best.pitch_deg,
            best.roll_deg,
            rival.support,
            rival.yaw_deg,
            rival.pitch_deg,
            rival.roll_deg,
            rival
                .cam_from_world
                .rotation_angle_to_rad(&best.cam_from_world)
                .to_degrees()
        )
    });
    // The centres: the best beam; when a rival is about as good, also the prior (the photo's
    // edges cannot choose, so the prior's own information counts) and the rivals, each distinct
    // from those already chosen.
    // With `keep_prior_centre`, a move never drops the prior: it is the second centre whether
    // or not a rival makes the search ambiguous.
    let mut centres = vec![if moved { best.cam_from_world } else { *prior }];
    if moved && search.keep_prior_centre && search.max_centres > 1 {
        centres.push(*prior);
    }
    if ambiguous.is_some() {
        for candidate in
            std::iter::once(*prior).chain(rivals.iter().map(|&i| beams[i].cam_from_world))
        {
            if centres.len() >= search.max_centres {
                break;
            }
            if centres
                .iter()
                .all(|c| c.rotation_angle_to_rad(&candidate) > separation_rad)
            {
                centres.push(candidate);
            }
        }
    }
    // A photo that shows the model's edges nowhere in the region cannot tell the prior's
    // heading from its flip (a compass or gimbal yaw recorded 180° off, issue #12): the flip
    // becomes a centre of its own and the flow's agreement, verified, decides between them —
    // when the model is in view from it (the grid rendered it with edges: with
    // `include_flipped_heading`).
    let blind = is_blind(moved, &beams, config.confidence.min_support_above_chance);
    if blind && flip_in_view && centres.len() < search.max_centres {
        centres.push(turned_pose(prior, 180.0, 0.0, 0.0));
    }
    Some(PoseSearchOutcome {
        centres,
        moved,
        prior_support,
        beams,
        ambiguous,
        blind,
        search_ms: started.elapsed().as_secs_f64() * 1e3,
        search_cpu_ms: process_cpu_ms() - started_cpu_ms,
    })
}

/// Whether the photo's edges showed the model nowhere in the search's region: the search did not
/// move, and neither the refined prior nor any refined beam has an edge support at its pose
/// `min_above_chance` above the support its own edges get by chance (the confidence's
/// `min_support_above_chance`, the margin of verification's "at chance near",
/// [`crate::core::edge_align::SupportPeak::at_chance_near`], read here at the pose only). A
/// pose whose refinement failed (too few model edge samples) counts as at chance. On such a
/// photo the search's ranking is noise (Brighton's mesh creases are not edges of its photos:
/// beams 250–360 px off score above the truth), so it cannot have ruled out a hypothesis the
/// prior holds, such as its flip.
pub(crate) fn is_blind(moved: bool, beams: &[Beam], min_above_chance: f64) -> bool {
    !moved
        && beams
            .iter()
            .all(|beam| beam.support - beam.chance < min_above_chance)
}

/// The grid of a search and what its screening made of it.
pub(crate) struct ScreenedGrid {
    pub grid: SearchGrid,
    /// Every start the search screened (the grid's best distinct candidates and, with the
    /// position search, the best of them moved), each with the pose its screening alignment
    /// ended at and its edge support there, best support first; without the screening
    /// (`screened_candidates` 0) the grid's best `beams` as they are, support NaN. The beams are
    /// the first of them ([`beams_of`]); the diagnosis measures all of them against the truth.
    pub screened: Vec<(Candidate, Rigid3, f64)>,
}

/// The grid of `config.pose_search` around `prior` scored on the query's edge map `map`, and its
/// best candidates screened (step "search" up to its beams).
#[allow(clippy::too_many_arguments)]
pub(crate) fn screen_grid(
    mesh: &Mesh,
    camera: &Camera,
    prior: &Rigid3,
    query: ImageView<'_, f32>,
    map: &OrientedEdgeMap,
    config: &RegistrationConfig,
    rasterizer: &mut Rasterizer,
    view: &mut CoarseView,
) -> ScreenedGrid {
    let search = &config.pose_search;
    let grid = score_grid(mesh, camera, prior, map, config, rasterizer, view);
    let screened = if search.screened_candidates == 0 {
        select_beams(&grid.candidates, search.beams, search.beam_separation_deg)
            .into_iter()
            .map(|c| (c, c.cam_from_world, f64::NAN))
            .collect()
    } else {
        // The grid's best, and the best of them moved by the position search (both: a moved
        // candidate is another start for the screening, not a replacement).
        let mut starts = select_beams(
            &grid.candidates,
            search.screened_candidates,
            search.beam_separation_deg,
        );
        // Within the basins, the candidates the screening from their best could not reach.
        if search.capture_candidates > 0 {
            for candidate in select_beams(
                &grid.candidates,
                search.capture_candidates,
                screening_capture_deg(camera, search),
            ) {
                if !starts.contains(&candidate) {
                    starts.push(candidate);
                }
            }
        }
        if search.position_half_range_m > 0.0 {
            let moved = position_candidates(
                &select_beams(
                    &grid.candidates,
                    search.positioned_candidates,
                    search.beam_separation_deg,
                ),
                &grid.groups,
                map,
                camera,
                search,
            );
            starts.extend(select_beams(
                &moved,
                search.screened_candidates,
                search.beam_separation_deg,
            ));
        }
        screen_candidates(&starts, &grid.groups, camera, query, config)
    };
    ScreenedGrid { grid, screened }
}

/// The beams among the screened starts of [`screen_grid`] (its order): the best screened. With
/// the position search or the capture's candidates, each distinct from the better ones: several
/// starts that the screening took into one basin are one beam (a moved start and its unmoved
/// candidate, docs/measurements.md, twenty-second session; neighbours within a basin, branch
/// `reach25`).
pub(crate) fn beams_of(
    screened: Vec<(Candidate, Rigid3, f64)>,
    search: &PoseSearchConfig,
) -> Vec<(Candidate, Rigid3, f64)> {
    if search.screened_candidates != 0
        && (search.position_half_range_m > 0.0 || search.capture_candidates > 0)
    {
        first_distinct(screened, search.beams, search.beam_separation_deg, |s| &s.1)
    } else {
        screened.into_iter().take(search.beams).collect()
    }
}

/// One rendering of the grid: its heading relative to the prior's, its pose, and the model's
/// edge samples it gave, as the screening aligns on them (world points) and as the grid scores
/// them (in the rendering's camera).
pub(crate) struct HeadingGroup {
    pub rendered_yaw_deg: f64,
    pub rendered: Rigid3,
    pub edge_samples: Vec<EdgeSample>,
    pub search_samples: Vec<SearchSample>,
}

/// The group whose rendering scores the candidates of heading `yaw_deg` (relative to the
/// prior's, degrees): the nearest rendered heading ([`rendered_heading_deg`]); `None` when that
/// rendering had too few samples.
fn group_of(
    groups: &[HeadingGroup],
    yaw_deg: f64,
    render_heading_step_deg: f64,
) -> Option<&HeadingGroup> {
    let rendered = rendered_heading_deg(yaw_deg, render_heading_step_deg);
    groups
        .iter()
        .find(|g| wrap_deg(g.rendered_yaw_deg - rendered).abs() < 1e-9)
}

/// The rotation grid of a search around `prior`: every candidate scored on `map`, and the
/// renderings that scored them (the screening and the position search work on their samples).
pub(crate) struct SearchGrid {
    pub candidates: Vec<Candidate>,
    pub groups: Vec<HeadingGroup>,
}

/// Scores the grid of `config.pose_search` around `prior` on the query's edge map `map`, a
/// rendering per heading group.
pub(crate) fn score_grid(
    mesh: &Mesh,
    camera: &Camera,
    prior: &Rigid3,
    map: &OrientedEdgeMap,
    config: &RegistrationConfig,
    rasterizer: &mut Rasterizer,
    view: &mut CoarseView,
) -> SearchGrid {
    let search = &config.pose_search;

    // The grid, a rendering per heading group.
    let mut groups: Vec<(f64, Vec<f64>)> = Vec::new();
    for yaw_deg in search.candidate_yaws_deg() {
        let rendered = rendered_heading_deg(yaw_deg, search.render_heading_step_deg);
        match groups
            .iter_mut()
            .find(|(r, _)| wrap_deg(r - rendered).abs() < 1e-9)
        {
            Some((_, yaws)) => yaws.push(yaw_deg),
            None => groups.push((rendered, vec![yaw_deg])),
        }
    }
    let mut candidates: Vec<Candidate> = Vec::new();
    let mut rendered_groups: Vec<HeadingGroup> = Vec::with_capacity(groups.len());
    for (rendered_yaw_deg, yaws) in &groups {
        let rendered = turned_pose(prior, *rendered_yaw_deg, 0.0, 0.0);
        let edge_samples = rendered_edge_samples(mesh, camera, &rendered, config, rasterizer, view);
        let samples = search_samples(&edge_samples, camera, &rendered);
        if samples.len() < config.edge_align.min_samples {
            continue;
        }
        candidates.extend(score_rotations(
            &samples,
            map,
            camera,
            prior,
            (*rendered_yaw_deg, yaws),
            search,
        ));
        rendered_groups.push(HeadingGroup {
            rendered_yaw_deg: *rendered_yaw_deg,
            rendered,
            edge_samples,
            search_samples: samples,
        });
    }
    SearchGrid {
        candidates,
        groups: rendered_groups,
    }
}

/// The position search ([`crate::core::pose_search::position_candidate`]) of each of
/// `candidates` on the samples of the rendering nearest its heading: the candidates it moved.
pub(crate) fn position_candidates(
    candidates: &[Candidate],
    groups: &[HeadingGroup],
    map: &OrientedEdgeMap,
    camera: &Camera,
    search: &PoseSearchConfig,
) -> Vec<Candidate> {
    candidates
        .iter()
        .filter_map(|candidate| {
            let group = group_of(groups, candidate.yaw_deg, search.render_heading_step_deg)?;
            position_candidate(
                &group.search_samples,
                map,
                camera,
                &group.rendered,
                candidate,
                search,
            )
        })
        .collect()
}

/// The heading (relative to the prior's, degrees) of the rendering whose edge samples score the
/// candidates of heading `yaw_deg`: the nearest multiple of the render step.
fn rendered_heading_deg(yaw_deg: f64, render_heading_step_deg: f64) -> f64 {
    wrap_deg((yaw_deg / render_heading_step_deg).round() * render_heading_step_deg)
}

/// The screening of the grid's best candidates: each aligned with the query's edges (6 DoF,
/// coarse to fine over the search's refinement radii down to the final radius) on the edge
/// samples of the rendering nearest its heading, without a rendering of its own; returned with
/// its aligned pose and edge support, best support first. The samples' visibility is their
/// rendering's, a few degrees of heading away: good enough to rank, not to output.
pub(crate) fn screen_candidates(
    candidates: &[Candidate],
    groups: &[HeadingGroup],
    camera: &Camera,
    query: ImageView<'_, f32>,
    config: &RegistrationConfig,
) -> Vec<(Candidate, Rigid3, f64)> {
    let align = EdgeAlignConfig {
        initial_search_radius_px: config
            .pose_search
            .refine_initial_radius_px
            .max(config.edge_align.final_search_radius_px),
        ..search_alignment(&config.edge_align)
    };
    let radii = align.level_radii_px();
    let blurred: Vec<Image<f32>> = radii
        .iter()
        .map(|&radius_px| {
            let mut out = Image::default();
            blurred_query(query, radius_px, &mut out);
            out
        })
        .collect();
    let mut screened: Vec<(Candidate, Rigid3, f64)> = candidates
        .iter()
        .filter_map(|candidate| {
            let samples = &group_of(
                groups,
                candidate.yaw_deg,
                config.pose_search.render_heading_step_deg,
            )?
            .edge_samples;
            let mut pose = candidate.cam_from_world;
            for (radius_px, query_level) in radii.iter().zip(&blurred) {
                let (_, next, _) = align_level(
                    samples,
                    &query_level.view(),
                    camera,
                    &pose,
                    AlignedParameters::Pose,
                    *radius_px,
                    &align,
                    &mut 0.0,
                );
                pose = next;
            }
            let support = edge_evidence(samples, &query, camera, &pose, &align).support_fraction();
            Some((*candidate, pose, support))
        })
        .collect();
    screened.sort_by(|a, b| b.2.total_cmp(&a.2));
    screened
}

/// The grid score (as [`search_pose`] scores its candidates) of `pose` from a rendering at
/// `pose` itself: what a candidate exactly there would score. For the diagnosis, which compares
/// the truth's score with the beams'. `map` is the query's edge map
/// (`OrientedEdgeMap::build(query, &config.pose_search)`).
pub fn grid_score_at(
    mesh: &Mesh,
    camera: &Camera,
    pose: &Rigid3,
    map: &OrientedEdgeMap,
    config: &RegistrationConfig,
    rasterizer: &mut Rasterizer,
    view: &mut CoarseView,
) -> f64 {
    let edge_samples = rendered_edge_samples(mesh, camera, pose, config, rasterizer, view);
    let samples = search_samples(&edge_samples, camera, pose);
    score_rotation(&samples, map, camera, &nalgebra::Matrix3::identity())
}

/// The model's edge samples of a rendering at `pose`, at the search's sample spacing: what the
/// grid scores its candidates with.
fn rendered_edge_samples(
    mesh: &Mesh,
    camera: &Camera,
    pose: &Rigid3,
    config: &RegistrationConfig,
    rasterizer: &mut Rasterizer,
    view: &mut CoarseView,
) -> Vec<EdgeSample> {
    let sampling = EdgeAlignConfig {
        sample_spacing_px: config.pose_search.sample_spacing_px,
        ..config.edge_align
    };
    render_coarse_view(mesh, camera, 0, pose, config, rasterizer, view);
    let mut edge_samples = Vec::new();
    model_edge_samples(
        view.asg.view(),
        &view.render,
        camera,
        pose,
        &sampling,
        &mut edge_samples,
    );
    edge_samples
}

/// The final refinement's edge alignment as the search uses it: the pose alone, on every edge
/// sample (the search picks a basin; the refinement's precision options are the final step's:
/// the level check too, since a beam degrees off starts at chance support, where a level that
/// lowers it is noise, and only the coarse levels reach the basin).
fn search_alignment(align: &EdgeAlignConfig) -> EdgeAlignConfig {
    EdgeAlignConfig {
        estimate_rounding: false,
        check_levels: false,
        rounding_kinds: AlignedKinds::All,
        aligned_kinds: AlignedKinds::All,
        coarse_rotation_only: false,
        ..*align
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector3;

    use super::*;
    use crate::core::frame::tests::{house_and_poses, ideal_query, photo_without_the_model};
    use crate::core::pose_search::PoseSearchConfig;
    use crate::core::reprojection::{mutual_reprojection_error_px, ReprojectionWorkspace};

    /// The search from `prior` on `query`, and its first centre's rotation angle (degrees) and δ
    /// (px) from `truth`.
    #[allow(clippy::too_many_arguments)]
    fn first_centre_from(
        mesh: &Mesh,
        camera: &Camera,
        truth: &Rigid3,
        prior: &Rigid3,
        query: &Image<f32>,
        config: &RegistrationConfig,
        rasterizer: &mut Rasterizer,
        reprojection: &mut ReprojectionWorkspace,
    ) -> (PoseSearchOutcome, f64, f64) {
        let outcome = search_pose(
            mesh,
            camera,
            prior,
            query.view(),
            config,
            rasterizer,
            &mut CoarseView::default(),
        )
        .expect("the search is enabled by default");
        let centre = outcome.centres[0];
        let angle_deg = centre.rotation_angle_to_rad(truth).to_degrees();
        let delta_px =
            mutual_reprojection_error_px(mesh, camera, &centre, camera, truth, reprojection)
                .unwrap_or(f64::INFINITY);
        (outcome, angle_deg, delta_px)
    }

    /// Known pose, ideal query (the model's own ASG at the truth): from a prior whose heading is
    /// 30° or 180° off and whose centre is 0.8 m off, the search must move the centre of the coarse
    /// poses to within a couple of degrees and a few pixels of the truth.
    #[test]
    fn the_search_recovers_a_wrong_heading_and_a_shifted_centre() {
        let (mesh, camera, truth, _) = house_and_poses();
        let default = RegistrationConfig::default();
        // Without the screening (on by default) the search must find the same poses.
        let screened = RegistrationConfig {
            pose_search: PoseSearchConfig {
                screened_candidates: 0,
                ..default.pose_search
            },
            ..default.clone()
        };
        let mut rasterizer = Rasterizer::new();
        let query = ideal_query(&mesh, &camera, &truth, &default);
        let mut reprojection = ReprojectionWorkspace::new();
        for (config, heading_error_deg) in [&default, &screened]
            .into_iter()
            .flat_map(|c| [30.0, -25.0, 180.0].map(|h| (c, h)))
        {
            let turned = turned_pose(&truth, heading_error_deg, 0.5, -0.5);
            let centre = turned.camera_center() + Vector3::new(0.5, -0.5, 0.3);
            let prior = Rigid3::new(turned.rotation, -(turned.rotation * centre));
            let (outcome, angle_deg, delta_px) = first_centre_from(
                &mesh,
                &camera,
                &truth,
                &prior,
                &query,
                config,
                &mut rasterizer,
                &mut reprojection,
            );
            println!(
                "heading {heading_error_deg:+}°: moved {}, centre {angle_deg:.2}° / δ {delta_px:.2} px from the truth, prior support {:.2}, beams {:?}, {:.0} ms",
                outcome.moved,
                outcome.prior_support,
                outcome
                    .beams
                    .iter()
                    .map(|b| (b.yaw_deg, b.pitch_deg, b.roll_deg, (b.grid_score * 100.0).round() / 100.0, (b.support * 100.0).round() / 100.0))
                    .collect::<Vec<_>>(),
                outcome.search_ms
            );
            assert!(outcome.moved, "heading {heading_error_deg}");
            assert!(outcome.ambiguous.is_none(), "{:?}", outcome.ambiguous);
            // The prior stays the second centre (`keep_prior_centre`, on by default).
            assert_eq!(outcome.centres.len(), 2);
            assert_eq!(outcome.centres[1], prior);
            assert!(angle_deg < 2.0, "heading {heading_error_deg}: {angle_deg}°");
            assert!(delta_px < 5.0, "heading {heading_error_deg}: {delta_px} px");
        }
    }

    /// Known pose, ideal query: a prior rolled 25° about its optical axis (and turned 10° in
    /// heading, 6° in pitch, > 50 px off) is recovered by a region of roll ±30°
    /// (`--search-roll-deg 30`): first centre within 2° and 5 px. (On this house view even ±3°
    /// recovers it, 0.06 px: the grid's heading and the screening's 6-DoF alignment take up the
    /// roll of a steep view; on the block's oblique photos ±15° did not, see docs/measurements.md.)
    #[test]
    fn the_search_reaches_a_prior_rolled_beyond_fifteen_degrees() {
        let (mesh, camera, truth, _) = house_and_poses();
        let wide = |roll_half_range_deg: f64| {
            let default = RegistrationConfig::default();
            RegistrationConfig {
                pose_search: PoseSearchConfig {
                    roll_half_range_deg,
                    ..default.pose_search
                },
                ..default
            }
        };
        let default = wide(30.0);
        let query = ideal_query(&mesh, &camera, &truth, &default);
        let mut rasterizer = Rasterizer::new();
        let mut reprojection = ReprojectionWorkspace::new();
        // The prior: the truth turned back by (yaw, pitch, roll), so that the grid candidate
        // (−yaw, ·, ·) of the prior is about the truth.
        let prior = turned_pose(&truth, 10.0, 0.0, 0.0);
        let tilt = turned_pose(&prior, 0.0, 6.0, 25.0);
        let prior = Rigid3::new(tilt.rotation, -(tilt.rotation * prior.camera_center()));
        let prior_delta_px = mutual_reprojection_error_px(
            &mesh,
            &camera,
            &prior,
            &camera,
            &truth,
            &mut reprojection,
        )
        .unwrap_or(f64::INFINITY);
        assert!(prior_delta_px > 50.0, "{prior_delta_px} px");
        let mut first_centre = |config: &RegistrationConfig| {
            let (outcome, angle_deg, delta_px) = first_centre_from(
                &mesh,
                &camera,
                &truth,
                &prior,
                &query,
                config,
                &mut rasterizer,
                &mut reprojection,
            );
            println!(
                "roll ±{}°: moved {}, first centre {angle_deg:.2}° / δ {delta_px:.2} px from the truth",
                config.pose_search.roll_half_range_deg, outcome.moved
            );
            (angle_deg, delta_px)
        };
        let (angle_deg, delta_px) = first_centre(&default);
        assert!(angle_deg < 2.0, "{angle_deg}°");
        assert!(delta_px < 5.0, "{delta_px} px");
    }

    /// On a photo that shows none of the model's edges the search cannot rank headings: it does
    /// not move, says it was blind, and the prior's flipped heading becomes the second centre
    /// (with `include_flipped_heading`, the default; without, the prior stays alone), unless the
    /// model is out of view from the flip. On the ideal query from the truth the search is not
    /// blind and the prior is the only centre.
    #[test]
    fn a_photo_without_the_models_edges_makes_the_priors_flip_a_centre() {
        let (mesh, camera, truth, _) = house_and_poses();
        let default = RegistrationConfig::default();
        let no_flip = RegistrationConfig {
            pose_search: PoseSearchConfig {
                include_flipped_heading: false,
                ..default.pose_search
            },
            ..default.clone()
        };
        let mut rasterizer = Rasterizer::new();
        let search =
            |query: &Image<f32>, config: &RegistrationConfig, rasterizer: &mut Rasterizer| {
                search_pose(
                    &mesh,
                    &camera,
                    &truth,
                    query.view(),
                    config,
                    rasterizer,
                    &mut CoarseView::default(),
                )
                .expect("the search is enabled by default")
            };
        let blank = photo_without_the_model(&camera);
        let outcome = search(&blank, &default, &mut rasterizer);
        let supports: Vec<(f64, f64)> = outcome
            .beams
            .iter()
            .map(|b| (b.support, b.chance))
            .collect();
        assert!(!outcome.moved, "{supports:?}");
        assert!(outcome.blind, "{supports:?}");
        assert_eq!(
            outcome.centres,
            vec![truth, turned_pose(&truth, 180.0, 0.0, 0.0)]
        );
        let outcome = search(&blank, &no_flip, &mut rasterizer);
        assert!(outcome.blind);
        assert_eq!(outcome.centres, vec![truth]);

        let query = ideal_query(&mesh, &camera, &truth, &default);
        let outcome = search(&query, &default, &mut rasterizer);
        assert!(!outcome.blind, "{:?}", outcome.beams[0]);
        assert_eq!(outcome.centres, vec![truth]);

        // A camera looking up at the house: turned around it sees only sky, and a flip the
        // model is not in view from is no centre.
        let upward = Rigid3::look_at(
            &Vector3::new(12.0, 0.0, 1.5),
            &Vector3::new(0.0, 0.0, 9.0),
            &Vector3::z(),
        )
        .unwrap();
        let outcome = search_pose(
            &mesh,
            &camera,
            &upward,
            blank.view(),
            &default,
            &mut rasterizer,
            &mut CoarseView::default(),
        )
        .expect("the search is enabled by default");
        assert!(outcome.blind);
        assert_eq!(outcome.centres, vec![upward], "{:?}", outcome.beams);
    }

    /// With `keep_prior_centre` (the default), a search that moves keeps the prior as its second
    /// centre (its own coarse poses are tried beside the beam's); without, the beam is the only
    /// centre.
    #[test]
    fn a_move_keeps_the_prior_as_a_centre_when_asked() {
        let (mesh, camera, truth, _) = house_and_poses();
        let kept = RegistrationConfig::default();
        let default = RegistrationConfig {
            pose_search: PoseSearchConfig {
                keep_prior_centre: false,
                ..kept.pose_search
            },
            ..kept.clone()
        };
        let query = ideal_query(&mesh, &camera, &truth, &default);
        let prior = turned_pose(&truth, 30.0, 0.0, 0.0);
        let mut rasterizer = Rasterizer::new();
        let mut centres = |config: &RegistrationConfig| {
            let outcome = search_pose(
                &mesh,
                &camera,
                &prior,
                query.view(),
                config,
                &mut rasterizer,
                &mut CoarseView::default(),
            )
            .expect("the search is enabled by default");
            assert!(outcome.moved);
            outcome.centres
        };
        let alone = centres(&default);
        let beside = centres(&kept);
        assert_eq!(alone.len(), 1);
        assert_eq!(beside, vec![alone[0], prior]);
    }
}
