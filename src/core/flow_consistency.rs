//! Query ↔ rendering pixel matches from SIFT flow in both directions, kept only where the two
//! flows agree (forward–backward consistency). The paper (§3.2) computes SIFT flow (Liu, Yuen,
//! Torralba, TPAMI 2011) between the photo's gradient image and each ASG rendering and lets only
//! textured pixels take part; this module is that step, as one library call per pair that also
//! reports per-step timings.
//!
//! Definitions:
//! - a pixel is *textured* when the mean gradient magnitude over its dense-SIFT support (4×4 cells,
//!   about 12×12 px) is at least `min_support_gradient` (intensity units per px of a `0..=1` image);
//! - in the forward flow (query → rendering) untextured query pixels carry no data term, and
//!   rendering candidates that are invalid (no geometry) cost as much as candidates outside the
//!   image; in the backward flow (rendering → query) invalid or untextured rendering pixels carry
//!   no data term;
//! - a query pixel `p` is kept when it is textured, `q = p + w_f(p)` falls on a valid, textured
//!   rendering pixel (rounded to the nearest), and the round trip `‖w_f(p) + w_b(q)‖` is at most
//!   `max_round_trip_error_px`.
//!
//! Names: a *match* ([`PixelMatch`]) is a pair of pixels, query and rendering, as this module
//! makes them; a *correspondence* is a query pixel and a 3D model point, made from a match by
//! lifting it onto the mesh (`core::frame::correspond`, `core::pose::Correspondences`).
//!
//! Preconditions: grey images with values in `0..=1` (see dense SIFT); the validity mask, when
//! given, has the rendering's size.

use std::time::{Duration, Instant};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::core::dense_sift::{
    compute_dense_sift, DenseSiftConfig, DenseSiftImage, DenseSiftWorkspace,
};
use crate::core::image::{Image, ImageView};
use crate::core::sift_flow::{
    compute_sift_flow_on_pyramids, FlowError, FlowField, SiftFlowConfig, SiftFlowWorkspace,
    SiftPyramid,
};

/// Parameters of the two-way matching and of the consistency check.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MatchConfig {
    pub dense_sift: DenseSiftConfig,
    pub sift_flow: SiftFlowConfig,
    /// Minimum mean gradient magnitude over a descriptor's support for a pixel to count as
    /// textured, intensity units per px (`0..=1` images). 0 lets every pixel take part.
    pub min_support_gradient: f32,
    /// A rendering pixel takes part only where its descriptor's support (half-width
    /// 2 × `dense_sift.cell_size_px`) holds a model edge: an ASG value at least this (ASG on the
    /// rendering's 0..1 scale; the edge alignment's `EdgeAlignConfig::min_model_ridge`).
    /// A noisy mesh gives its smooth surfaces a speckle of weak ASG that dense SIFT's
    /// normalisation turns into random descriptors, matched to the photo's texture by chance.
    /// `None`: every textured rendering pixel takes part (the paper).
    pub min_rendering_edge: Option<f32>,
    /// Largest accepted `‖w_forward(p) + w_backward(p + w_forward(p))‖`, px.
    pub max_round_trip_error_px: f32,
}

impl Default for MatchConfig {
    fn default() -> Self {
        Self {
            dense_sift: DenseSiftConfig::default(),
            sift_flow: SiftFlowConfig::default(),
            min_support_gradient: 0.002,
            min_rendering_edge: None,
            max_round_trip_error_px: 1.0,
        }
    }
}

impl MatchConfig {
    /// Checks every field once.
    pub fn validate(&self) -> Result<(), FlowError> {
        self.dense_sift.validate()?;
        self.sift_flow.validate()?;
        if !(self.min_support_gradient.is_finite() && self.min_support_gradient >= 0.0) {
            return Err(FlowError::InvalidConfig {
                field: "min_support_gradient",
                reason: format!("{} is not >= 0", self.min_support_gradient),
            });
        }
        if let Some(edge) = self.min_rendering_edge {
            if !(edge.is_finite() && edge >= 0.0) {
                return Err(FlowError::InvalidConfig {
                    field: "min_rendering_edge",
                    reason: format!("{edge} is not >= 0"),
                });
            }
        }
        if !(self.max_round_trip_error_px.is_finite() && self.max_round_trip_error_px >= 0.0) {
            return Err(FlowError::InvalidConfig {
                field: "max_round_trip_error_px",
                reason: format!("{} is not >= 0", self.max_round_trip_error_px),
            });
        }
        Ok(())
    }
}

/// One consistent pixel pair: a query pixel centre and where it lands in the rendering (sub-pixel).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PixelMatch {
    pub query_x_px: f32,
    pub query_y_px: f32,
    pub rendering_x_px: f32,
    pub rendering_y_px: f32,
    /// Descriptor L1 distance of the forward match (sum of absolute byte differences, 0..32640).
    pub matching_cost: f32,
    /// `‖w_forward + w_backward‖` at this pixel, px.
    pub round_trip_error_px: f32,
}

/// Time spent in each step of one pair.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MatchTimings {
    pub dense_sift: Duration,
    /// Descriptor pyramid of the rendering.
    pub pyramid: Duration,
    pub forward_flow: Duration,
    pub backward_flow: Duration,
    pub consistency: Duration,
    pub total: Duration,
}

/// The result of matching one query against one rendering.
#[derive(Clone, Debug, Default)]
pub struct PixelMatches {
    /// Query → rendering flow (query size).
    pub forward: FlowField,
    /// Rendering → query flow (rendering size).
    pub backward: FlowField,
    /// The forward–backward consistent pixel pairs.
    pub matches: Vec<PixelMatch>,
    pub timings: MatchTimings,
}

/// Buffers reused between pairs.
#[derive(Debug, Default)]
pub struct MatchWorkspace {
    sift_workspace: DenseSiftWorkspace,
    flow_workspace: SiftFlowWorkspace,
    backward_flow_workspace: SiftFlowWorkspace,
    rendering_sift: DenseSiftImage,
    rendering_pyramid: SiftPyramid,
    query_textured: Image<bool>,
    rendering_participates: Image<bool>,
    rendering_near_edge: Image<bool>,
    near_edge_row_counts: Vec<u32>,
    forward_cost: Image<f32>,
    backward_cost: Image<f32>,
}

/// Dense SIFT of both images, SIFT flow both ways, consistency check: the per-pair entry point
/// for a query matched once. A query matched against many renderings computes its
/// [`QueryFeatures`] once and calls [`match_rendering`] for each.
pub fn match_query_to_rendering(
    query: ImageView<'_, f32>,
    rendering: ImageView<'_, f32>,
    rendering_valid: Option<ImageView<'_, bool>>,
    config: &MatchConfig,
    workspace: &mut MatchWorkspace,
    out: &mut PixelMatches,
) -> Result<(), FlowError> {
    let started = Instant::now();
    let query = QueryFeatures::compute(query, config, &mut workspace.sift_workspace)?;
    // The query's dense SIFT and pyramid count as dense SIFT here.
    let query_time = started.elapsed();
    match_rendering(&query, rendering, rendering_valid, config, workspace, out)?;
    out.timings.dense_sift += query_time;
    out.timings.total = started.elapsed();
    Ok(())
}

/// As [`match_query_to_rendering`] from the query's dense SIFT image and pyramid computed by the
/// caller (so that they serve all its renderings) and the rendering's dense SIFT image.
/// `timings.dense_sift` is left at zero.
pub fn match_sift_images(
    query_sift: &DenseSiftImage,
    query_pyramid: &SiftPyramid,
    rendering_sift: &DenseSiftImage,
    rendering_valid: Option<ImageView<'_, bool>>,
    config: &MatchConfig,
    workspace: &mut MatchWorkspace,
    out: &mut PixelMatches,
) -> Result<(), FlowError> {
    match_sift_images_near_edges(
        query_sift,
        query_pyramid,
        rendering_sift,
        rendering_valid,
        false,
        config,
        workspace,
        out,
    )
}

/// As [`match_sift_images`]; with `near_edges_only` the rendering pixels also have to be marked
/// in `workspace.rendering_near_edge` (filled by the caller from the rendering's ASG).
#[allow(clippy::too_many_arguments)]
fn match_sift_images_near_edges(
    query_sift: &DenseSiftImage,
    query_pyramid: &SiftPyramid,
    rendering_sift: &DenseSiftImage,
    rendering_valid: Option<ImageView<'_, bool>>,
    near_edges_only: bool,
    config: &MatchConfig,
    workspace: &mut MatchWorkspace,
    out: &mut PixelMatches,
) -> Result<(), FlowError> {
    let started = Instant::now();
    config.validate()?;
    let ws = workspace;
    if let Some(valid) = rendering_valid {
        valid.check_size(
            "rendering validity mask",
            rendering_sift.width_px,
            rendering_sift.height_px,
        )?;
    }
    for (image, what) in [
        (query_sift, "query support gradient"),
        (rendering_sift, "rendering support gradient"),
    ] {
        image
            .support_gradient
            .check_size(what, image.width_px, image.height_px)?;
    }
    query_sift.textured_mask(config.min_support_gradient, &mut ws.query_textured);
    rendering_sift.textured_mask(config.min_support_gradient, &mut ws.rendering_participates);
    if let Some(valid) = rendering_valid {
        for (participates, &is_valid) in ws
            .rendering_participates
            .data_mut()
            .iter_mut()
            .zip(valid.data())
        {
            *participates &= is_valid;
        }
    }
    if near_edges_only {
        ws.rendering_near_edge.view().check_size(
            "rendering edge mask",
            rendering_sift.width_px,
            rendering_sift.height_px,
        )?;
        for (participates, &near_edge) in ws
            .rendering_participates
            .data_mut()
            .iter_mut()
            .zip(ws.rendering_near_edge.data())
        {
            *participates &= near_edge;
        }
    }

    let pyramid_started = Instant::now();
    ws.rendering_pyramid
        .build(rendering_sift, &config.sift_flow)?;
    let pyramid = pyramid_started.elapsed();
    // The two directions are independent: run them side by side (rayon decides whether that
    // uses a second thread).
    let rendering_pyramid = &ws.rendering_pyramid;
    let (query_textured, rendering_participates) = (&ws.query_textured, &ws.rendering_participates);
    let (forward_workspace, backward_workspace) =
        (&mut ws.flow_workspace, &mut ws.backward_flow_workspace);
    let (forward_cost, backward_cost) = (&mut ws.forward_cost, &mut ws.backward_cost);
    let (forward_out, backward_out) = (&mut out.forward, &mut out.backward);
    let (forward_result, backward_result) = rayon::join(
        || {
            let started = Instant::now();
            compute_sift_flow_on_pyramids(
                (query_sift, query_pyramid, Some(query_textured.view())),
                (rendering_sift, rendering_pyramid, rendering_valid),
                &config.sift_flow,
                forward_workspace,
                forward_out,
                forward_cost,
            )
            .map(|_| started.elapsed())
        },
        || {
            let started = Instant::now();
            compute_sift_flow_on_pyramids(
                (
                    rendering_sift,
                    rendering_pyramid,
                    Some(rendering_participates.view()),
                ),
                (query_sift, query_pyramid, None),
                &config.sift_flow,
                backward_workspace,
                backward_out,
                backward_cost,
            )
            .map(|_| started.elapsed())
        },
    );
    let forward_flow = forward_result?;
    let backward_flow = backward_result?;

    let consistency_started = Instant::now();
    collect_consistent_pairs(
        &out.forward,
        &out.backward,
        ws.query_textured.view(),
        ws.rendering_participates.view(),
        ws.forward_cost.view(),
        config.max_round_trip_error_px,
        &mut out.matches,
    )?;
    out.timings = MatchTimings {
        dense_sift: Duration::ZERO,
        pyramid,
        forward_flow,
        backward_flow,
        consistency: consistency_started.elapsed(),
        total: started.elapsed(),
    };
    Ok(())
}

/// What a query contributes to every pair it is matched in: its dense SIFT image and descriptor
/// pyramid, computed once per frame (not once per rendering).
#[derive(Debug, Default)]
pub struct QueryFeatures {
    pub sift: DenseSiftImage,
    pub pyramid: SiftPyramid,
}

impl QueryFeatures {
    /// Dense SIFT and pyramid of `query`.
    pub fn compute(
        query: ImageView<'_, f32>,
        config: &MatchConfig,
        workspace: &mut DenseSiftWorkspace,
    ) -> Result<Self, FlowError> {
        config.validate()?;
        let mut features = Self::default();
        compute_dense_sift(query, &config.dense_sift, workspace, &mut features.sift)?;
        features.pyramid.build(&features.sift, &config.sift_flow)?;
        Ok(features)
    }
}

/// Matches a query (its features) against one rendering: the rendering's dense SIFT, SIFT flow
/// both ways, consistency check. The step every path runs per coarse view.
pub fn match_rendering(
    query: &QueryFeatures,
    rendering: ImageView<'_, f32>,
    rendering_valid: Option<ImageView<'_, bool>>,
    config: &MatchConfig,
    workspace: &mut MatchWorkspace,
    out: &mut PixelMatches,
) -> Result<(), FlowError> {
    let started = Instant::now();
    let mut rendering_sift = std::mem::take(&mut workspace.rendering_sift);
    let sift_result = compute_dense_sift(
        rendering,
        &config.dense_sift,
        &mut workspace.sift_workspace,
        &mut rendering_sift,
    );
    if let Some(min_edge) = config.min_rendering_edge {
        near_model_edge_mask(
            rendering,
            min_edge,
            2 * config.dense_sift.cell_size_px,
            &mut workspace.near_edge_row_counts,
            &mut workspace.rendering_near_edge,
        );
    }
    let dense_sift = started.elapsed();
    let result = sift_result.and_then(|()| {
        match_sift_images_near_edges(
            &query.sift,
            &query.pyramid,
            &rendering_sift,
            rendering_valid,
            config.min_rendering_edge.is_some(),
            config,
            workspace,
            out,
        )
    });
    workspace.rendering_sift = rendering_sift;
    result?;
    out.timings.dense_sift = dense_sift;
    out.timings.total = started.elapsed();
    Ok(())
}

/// `out[p]`: some pixel within `radius_px` (Chebyshev) of `p` has a value of at least
/// `min_value` in `image`: a box dilation of the thresholded image, two separable passes of
/// running counts (linear in the pixels whatever the radius); `row_counts` is the caller's
/// scratch buffer (resized here).
pub fn near_model_edge_mask(
    image: ImageView<'_, f32>,
    min_value: f32,
    radius_px: usize,
    row_counts: &mut Vec<u32>,
    out: &mut Image<bool>,
) {
    let (width, height) = image.size();
    out.reset(width, height, false);
    if width == 0 || height == 0 {
        return;
    }
    // Horizontal pass: how many edge pixels within the radius along the row.
    row_counts.clear();
    row_counts.resize(width * height, 0);
    for row in 0..height {
        let values = image.row(row);
        let counts = &mut row_counts[row * width..(row + 1) * width];
        let mut running = 0u32;
        let is_edge = |col: usize| u32::from(values[col] >= min_value);
        for col in 0..radius_px.min(width) {
            running += is_edge(col);
        }
        for (col, count) in counts.iter_mut().enumerate() {
            if col + radius_px < width {
                running += is_edge(col + radius_px);
            }
            *count = running;
            if col >= radius_px {
                running -= is_edge(col - radius_px);
            }
        }
    }
    // Vertical pass over the row counts.
    let mask = out.data_mut();
    for col in 0..width {
        let mut running = 0u32;
        for row in 0..radius_px.min(height) {
            running += row_counts[row * width + col];
        }
        for row in 0..height {
            if row + radius_px < height {
                running += row_counts[(row + radius_px) * width + col];
            }
            mask[row * width + col] = running > 0;
            if row >= radius_px {
                running -= row_counts[(row - radius_px) * width + col];
            }
        }
    }
}

/// Matches one query against many renderings, in parallel over renderings (rayon), reusing one
/// workspace per worker thread and the query's features for every pair.
pub fn match_query_to_renderings(
    query: ImageView<'_, f32>,
    renderings: &[(ImageView<'_, f32>, Option<ImageView<'_, bool>>)],
    config: &MatchConfig,
) -> Result<Vec<PixelMatches>, FlowError> {
    let features = QueryFeatures::compute(query, config, &mut DenseSiftWorkspace::default())?;
    renderings
        .par_iter()
        .map_init(MatchWorkspace::default, |workspace, (rendering, valid)| {
            let mut out = PixelMatches::default();
            match_rendering(&features, *rendering, *valid, config, workspace, &mut out)?;
            Ok(out)
        })
        .collect()
}

/// Keeps the query pixels whose forward and backward flows agree (see the module comment) and
/// writes them into `matches`. `query_textured` and `forward_cost` have the query's size
/// (the forward flow's), `rendering_participates` the rendering's (the backward flow's).
pub fn collect_consistent_pairs(
    forward: &FlowField,
    backward: &FlowField,
    query_textured: ImageView<'_, bool>,
    rendering_participates: ImageView<'_, bool>,
    forward_cost: ImageView<'_, f32>,
    max_round_trip_error_px: f32,
    matches: &mut Vec<PixelMatch>,
) -> Result<(), FlowError> {
    matches.clear();
    let (width, height) = forward.size();
    let (rendering_width_px, rendering_height_px) = backward.size();
    query_textured.check_size("query texture mask", width, height)?;
    forward_cost.check_size("forward matching costs", width, height)?;
    rendering_participates.check_size("rendering mask", rendering_width_px, rendering_height_px)?;
    let (query_textured, rendering_participates, forward_cost) = (
        query_textured.data(),
        rendering_participates.data(),
        forward_cost.data(),
    );
    let (forward_u, forward_v) = (forward.u_px().data(), forward.v_px().data());
    let (backward_u, backward_v) = (backward.u_px().data(), backward.v_px().data());
    let (rendering_width, rendering_height) =
        (rendering_width_px as i64, rendering_height_px as i64);
    for y in 0..height {
        for x in 0..width {
            let pixel = y * width + x;
            if !query_textured[pixel] {
                continue;
            }
            let target_x = x as f32 + forward_u[pixel];
            let target_y = y as f32 + forward_v[pixel];
            let (nearest_x, nearest_y) = (target_x.round() as i64, target_y.round() as i64);
            if nearest_x < 0
                || nearest_y < 0
                || nearest_x >= rendering_width
                || nearest_y >= rendering_height
            {
                continue;
            }
            let target = (nearest_y * rendering_width + nearest_x) as usize;
            if !rendering_participates[target] {
                continue;
            }
            let error_u = forward_u[pixel] + backward_u[target];
            let error_v = forward_v[pixel] + backward_v[target];
            let round_trip_error_px = error_u.hypot(error_v);
            if round_trip_error_px <= max_round_trip_error_px {
                matches.push(PixelMatch {
                    query_x_px: x as f32,
                    query_y_px: y as f32,
                    rendering_x_px: target_x,
                    rendering_y_px: target_y,
                    matching_cost: forward_cost[pixel],
                    round_trip_error_px,
                });
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::dense_sift::DenseSiftConfig;
    use crate::core::image::ImageError;
    use crate::core::sift_flow::test_support::*;

    #[test]
    fn the_near_edge_mask_is_the_box_dilation_of_the_edges() {
        let (width, height) = (23usize, 17usize);
        let texture = textured_image(width, height);
        // Few pixels above 0.8: isolated edges; check against a brute-force dilation.
        let image = ImageView::new(width, height, &texture).unwrap();
        for radius in [0usize, 1, 2, 6, 30] {
            let mut mask = Image::default();
            near_model_edge_mask(image, 0.8, radius, &mut Vec::new(), &mut mask);
            assert_eq!(mask.size(), (width, height));
            let mut marked = 0;
            for row in 0..height {
                for col in 0..width {
                    let expected = (row.saturating_sub(radius)..(row + radius + 1).min(height))
                        .any(|r| {
                            (col.saturating_sub(radius)..(col + radius + 1).min(width))
                                .any(|c| texture[r * width + c] >= 0.8)
                        });
                    assert_eq!(
                        mask.data()[row * width + col],
                        expected,
                        "({col}, {row}) r {radius}"
                    );
                    marked += usize::from(expected);
                }
            }
            assert!(
                marked > 0 && (radius >= 30 || marked < width * height),
                "r {radius}: {marked}"
            );
        }
    }

    /// A deterministic textured image: hashed white noise smoothed by two 3×3 box passes (texture at
    /// the scale of a SIFT cell) plus a gentle ramp, values in 0..1.
    pub(crate) fn textured_image(width: usize, height: usize) -> Vec<f32> {
        let hash = |x: usize, y: usize| {
            let mut state = (x as u64) << 32 | y as u64;
            state = (state ^ (state >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            state = (state ^ (state >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            ((state ^ (state >> 31)) >> 40) as f32 / (1u64 << 24) as f32
        };
        let mut image: Vec<f32> = (0..width * height)
            .map(|pixel| hash(pixel % width, pixel / width))
            .collect();
        for _ in 0..2 {
            let previous = image.clone();
            for y in 0..height {
                for x in 0..width {
                    let mut sum = 0.0;
                    for dy in -1i32..=1 {
                        for dx in -1i32..=1 {
                            let xx = (x as i32 + dx).clamp(0, width as i32 - 1) as usize;
                            let yy = (y as i32 + dy).clamp(0, height as i32 - 1) as usize;
                            sum += previous[yy * width + xx];
                        }
                    }
                    image[y * width + x] = sum / 9.0;
                }
            }
        }
        image
            .iter()
            .enumerate()
            .map(|(pixel, value)| {
                (value - 0.5) * 2.0 + 0.4 + 0.2 * (pixel % width) as f32 / width as f32
            })
            .collect()
    }

    /// Bilinear sample with clamped borders.
    fn sample(image: &[f32], width: usize, height: usize, x: f32, y: f32) -> f32 {
        let x = x.clamp(0.0, (width - 1) as f32);
        let y = y.clamp(0.0, (height - 1) as f32);
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(width - 1), (y0 + 1).min(height - 1));
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let at = |xx: usize, yy: usize| image[yy * width + xx];
        (at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx) * (1.0 - fy)
            + (at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx) * fy
    }

    fn run_pair(
        query: &[f32],
        rendering: &[f32],
        width: usize,
        height: usize,
        valid: Option<&[bool]>,
        config: &MatchConfig,
    ) -> PixelMatches {
        let mut out = PixelMatches::default();
        match_query_to_rendering(
            ImageView::new(width, height, query).unwrap(),
            ImageView::new(width, height, rendering).unwrap(),
            valid.map(|valid| ImageView::new(width, height, valid).unwrap()),
            config,
            &mut MatchWorkspace::default(),
            &mut out,
        )
        .unwrap();
        out
    }

    #[test]
    fn identity_pair_gives_zero_flow_and_full_consistency() {
        let (width, height) = (96, 64);
        let image = textured_image(width, height);
        let mut config = MatchConfig::default();
        config.sift_flow.subpixel = crate::core::sift_flow::SubpixelRefinement::None;
        let out = run_pair(&image, &image, width, height, None, &config);
        for field in [&out.forward, &out.backward] {
            assert!(field
                .u_px()
                .data()
                .iter()
                .chain(field.v_px().data())
                .all(|&value| value == 0.0));
        }
        assert_eq!(out.matches.len(), width * height);
        assert!(out.matches.iter().all(|pair| pair.matching_cost == 0.0));
    }

    #[test]
    fn integer_translation_is_recovered_exactly_inside_the_border() {
        let (width, height) = (120, 80);
        let (shift_x, shift_y) = (5i32, -3i32);
        let query = textured_image(width + 20, height + 20);
        // rendering(x + shift) = query(x): the flow query → rendering is (shift_x, shift_y).
        let crop = |dx: i32, dy: i32| -> Vec<f32> {
            (0..width * height)
                .map(|pixel| {
                    let x = (pixel % width) as i32 + 10 + dx;
                    let y = (pixel / width) as i32 + 10 + dy;
                    query[y as usize * (width + 20) + x as usize]
                })
                .collect()
        };
        let query_crop = crop(0, 0);
        let rendering_crop = crop(-shift_x, -shift_y);
        let mut integer_config = MatchConfig::default();
        integer_config.sift_flow.subpixel = crate::core::sift_flow::SubpixelRefinement::None;
        let integer = run_pair(
            &query_crop,
            &rendering_crop,
            width,
            height,
            None,
            &integer_config,
        );
        let refined = run_pair(
            &query_crop,
            &rendering_crop,
            width,
            height,
            None,
            &MatchConfig::default(),
        );
        let (integer_u, integer_v) = (integer.forward.u_px(), integer.forward.v_px());
        let (refined_u, refined_v) = (refined.forward.u_px(), refined.forward.v_px());
        for y in 12..height - 12 {
            for x in 12..width - 12 {
                assert_eq!(
                    integer_u.get(x, y),
                    Some(&(shift_x as f32)),
                    "u at ({x}, {y})"
                );
                assert_eq!(
                    integer_v.get(x, y),
                    Some(&(shift_y as f32)),
                    "v at ({x}, {y})"
                );
                // The parabola fit may move a little off the exact integer, never far.
                assert!(
                    (refined_u.get(x, y).unwrap() - shift_x as f32).abs() < 0.25,
                    "refined u at ({x}, {y})"
                );
                assert!(
                    (refined_v.get(x, y).unwrap() - shift_y as f32).abs() < 0.25,
                    "refined v at ({x}, {y})"
                );
            }
        }
    }

    #[test]
    fn occluded_and_out_of_view_pixels_are_rejected() {
        let (width, height) = (120, 80);
        let shift_x = 6i32;
        let wide = textured_image(width + 20, height);
        // query(x) = wide(x + 10) and rendering(x) = wide(x + 4), so rendering(x + 6) = query(x):
        // the flow is +6 px and the query's last 6 columns leave the view.
        let crop = |start: usize| -> Vec<f32> {
            (0..width * height)
                .map(|pixel| wide[(pixel / width) * (width + 20) + pixel % width + start])
                .collect()
        };
        let query = crop(10);
        let rendering = crop(10 - shift_x as usize);
        // An occluder: a block of the rendering without geometry.
        let mut valid = vec![true; width * height];
        for y in 30..50 {
            for x in 50..70 {
                valid[y * width + x] = false;
            }
        }
        let out = run_pair(
            &query,
            &rendering,
            width,
            height,
            Some(&valid),
            &MatchConfig::default(),
        );
        assert!(
            out.matches.len() > width * height / 2,
            "{} pairs",
            out.matches.len()
        );
        for pair in &out.matches {
            let (x, y) = (
                pair.rendering_x_px.round() as usize,
                pair.rendering_y_px.round() as usize,
            );
            assert!(x < width && y < height, "out of view: {pair:?}");
            assert!(valid[y * width + x], "lands on the occluder: {pair:?}");
            assert!(
                pair.query_x_px < (width as i32 - shift_x) as f32,
                "query pixel leaves the view: {pair:?}"
            );
        }
        // Away from the occluder and the borders the pairs are right.
        let good = out
            .matches
            .iter()
            .filter(|pair| (pair.rendering_x_px - pair.query_x_px - shift_x as f32).abs() < 0.5)
            .count();
        assert!(
            good as f64 > 0.95 * out.matches.len() as f64,
            "{good} of {}",
            out.matches.len()
        );
    }

    #[test]
    fn smooth_synthetic_warp_meets_the_error_thresholds() {
        let (width, height) = (160, 120);
        let image = textured_image(width, height);
        // query(x, y) = rendering(x + u, y + v) with a smooth known flow.
        let flow_at = |x: f32, y: f32| {
            (
                2.0 + 1.5 * (x / 40.0).sin() * (y / 50.0).cos(),
                -1.0 + 1.5 * (x / 45.0 + 0.3).cos() * (y / 35.0).sin(),
            )
        };
        let query: Vec<f32> = (0..width * height)
            .map(|pixel| {
                let (x, y) = ((pixel % width) as f32, (pixel / width) as f32);
                let (u, v) = flow_at(x, y);
                sample(&image, width, height, x + u, y + v)
            })
            .collect();
        let out = run_pair(&query, &image, width, height, None, &MatchConfig::default());
        let truth = FlowField::new(
            Image::from_fn(width, height, |x, y| flow_at(x as f32, y as f32).0),
            Image::from_fn(width, height, |x, y| flow_at(x as f32, y as f32).1),
        )
        .unwrap();
        let (epe, under_one) = score_flow(&out.forward, &truth, 12);
        println!("synthetic warp: EPE {epe:.3} px, < 1 px {under_one:.3}");
        // Measured: EPE 0.13 px, all pixels under 1 px.
        assert!(epe < 0.3, "EPE {epe}");
        assert!(under_one > 0.98, "< 1 px {under_one}");
    }

    /// The 505×275 real pair of `tests/data/flow-pairs` (part of the repository).
    fn repo_pair() -> SharedPair {
        load_pair(
            &crate::test_data::repo_data("flow-pairs"),
            "dji0024_505x275",
        )
    }

    /// SIFT flow on a real pair against its true flow (pixels ≥ 20 px from the border).
    fn pair_scores(pair: &SharedPair, name: &str, sift_flow: SiftFlowConfig) -> (f64, f64) {
        let sift_config = DenseSiftConfig::default();
        let first = sift_of(pair.first.view(), &sift_config);
        let second = sift_of(pair.second.view(), &sift_config);
        let mut forward = FlowField::default();
        let mut cost = Image::default();
        crate::core::sift_flow::compute_sift_flow(
            &first,
            None,
            &second,
            None,
            &sift_flow,
            &mut SiftFlowWorkspace::default(),
            &mut forward,
            &mut cost,
        )
        .unwrap();
        let scores = score_flow(&forward, &pair.truth, 20);
        println!("{name}: EPE {:.3} px, < 1 px {:.3}", scores.0, scores.1);
        scores
    }

    // Reference (Ce Liu's C++, integer flow): EPE 0.440 px, 98.9 % under 1 px at 505×275;
    // 0.434 px, 99.2 % at 1010×550. Measured here: 0.277 / 99.8 % and 0.271 / 99.8 %.
    /// EPE ≤ 0.35 px and ≥ 99 % of pixels under 1 px on a real pair.
    fn assert_beats_the_reference(pair: &SharedPair, name: &str, config: SiftFlowConfig) {
        let (epe, under_one) = pair_scores(pair, name, config);
        assert!(epe <= 0.35, "EPE {epe}");
        assert!(under_one >= 0.99, "< 1 px {under_one}");
    }

    #[test]
    fn real_pair_505x275_beats_the_reference() {
        assert_beats_the_reference(&repo_pair(), "505x275", SiftFlowConfig::default());
    }

    #[test]
    fn real_pair_505x275_fast_preset_beats_the_reference() {
        assert_beats_the_reference(&repo_pair(), "505x275", SiftFlowConfig::fast());
    }

    #[test]
    #[ignore = "needs ../shared/data/flow-pairs (the shared data set beside the repo)"]
    fn shared_data_pair_1010x550_fast_preset_beats_the_reference() {
        // Fails, naming the path, when the shared data is absent.
        let pair = load_pair(
            &crate::test_data::shared_data("flow-pairs"),
            "dji0024_1010x550",
        );
        assert_beats_the_reference(&pair, "1010x550", SiftFlowConfig::fast());
    }

    #[test]
    fn integer_flow_without_multigrid_stays_near_the_reference() {
        // The reference's schedule without its multigrid start and without sub-pixel refinement:
        // measured 0.566 px; the reference reports 0.440 px with its multigrid.
        let config = SiftFlowConfig {
            multigrid: false,
            subpixel: crate::core::sift_flow::SubpixelRefinement::None,
            ..Default::default()
        };
        let (epe, _) = pair_scores(&repo_pair(), "505x275", config);
        assert!(epe <= 0.65, "EPE {epe}");
    }

    #[test]
    fn untextured_query_pixels_give_no_matches() {
        let (width, height) = (96, 64);
        let mut query = textured_image(width, height);
        // A flat block, far wider than a descriptor's support.
        for y in 10..54 {
            for x in 20..76 {
                query[y * width + x] = 0.5;
            }
        }
        let rendering = query.clone();
        let out = run_pair(
            &query,
            &rendering,
            width,
            height,
            None,
            &MatchConfig::default(),
        );
        assert!(!out.matches.is_empty());
        for pair in &out.matches {
            let inside_flat_core =
                (30.0..66.0).contains(&pair.query_x_px) && (20.0..44.0).contains(&pair.query_y_px);
            assert!(!inside_flat_core, "{pair:?}");
        }
    }

    #[test]
    fn frame_matching_equals_pair_matching() {
        let (width, height) = (80, 60);
        let image = textured_image(width + 8, height);
        let crop = |start: usize| -> Vec<f32> {
            (0..width * height)
                .map(|pixel| image[(pixel / width) * (width + 8) + pixel % width + start])
                .collect()
        };
        let query = crop(4);
        let renderings: Vec<Vec<f32>> = (0..3).map(|shift| crop(2 * shift)).collect();
        let config = MatchConfig {
            sift_flow: SiftFlowConfig::fast(),
            ..Default::default()
        };
        fn grey(pixels: &[f32], width_px: usize, height_px: usize) -> ImageView<'_, f32> {
            ImageView::new(width_px, height_px, pixels).unwrap()
        }
        let inputs: Vec<(ImageView<f32>, Option<ImageView<bool>>)> = renderings
            .iter()
            .map(|rendering| (grey(rendering, width, height), None))
            .collect();
        let frame =
            match_query_to_renderings(grey(&query, width, height), &inputs, &config).unwrap();
        assert_eq!(frame.len(), 3);
        for (rendering, from_frame) in renderings.iter().zip(&frame) {
            let single = run_pair(&query, rendering, width, height, None, &config);
            assert_eq!(single.forward, from_frame.forward);
            assert_eq!(single.backward, from_frame.backward);
            assert_eq!(single.matches, from_frame.matches);
            assert!(!single.matches.is_empty());
        }
    }

    #[test]
    fn reused_workspace_gives_the_same_results_as_a_fresh_one() {
        let config = MatchConfig::default();
        let mut shared_workspace = MatchWorkspace::default();
        for (width, height, shift) in [(120, 90, 3usize), (64, 48, 1), (120, 90, 2)] {
            let image = textured_image(width + 4, height);
            let crop = |start: usize| -> Vec<f32> {
                (0..width * height)
                    .map(|pixel| image[(pixel / width) * (width + 4) + pixel % width + start])
                    .collect()
            };
            let (query, rendering) = (crop(shift), crop(0));
            let grey = |pixels| ImageView::new(width, height, pixels).unwrap();
            let mut reused = PixelMatches::default();
            match_query_to_rendering(
                grey(&query),
                grey(&rendering),
                None,
                &config,
                &mut shared_workspace,
                &mut reused,
            )
            .unwrap();
            let fresh = run_pair(&query, &rendering, width, height, None, &config);
            assert_eq!(reused.forward, fresh.forward, "{width}x{height}");
            assert_eq!(reused.backward, fresh.backward, "{width}x{height}");
            assert_eq!(reused.matches, fresh.matches, "{width}x{height}");
        }
    }

    #[test]
    fn flows_do_not_depend_on_the_thread_count() {
        let pair = repo_pair();
        let sift_config = DenseSiftConfig::default();
        let first = sift_of(pair.first.view(), &sift_config);
        let second = sift_of(pair.second.view(), &sift_config);
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let mut field = FlowField::default();
                let mut cost = Image::default();
                crate::core::sift_flow::compute_sift_flow(
                    &first,
                    None,
                    &second,
                    None,
                    &SiftFlowConfig::fast(),
                    &mut SiftFlowWorkspace::default(),
                    &mut field,
                    &mut cost,
                )
                .unwrap();
                (field, cost)
            })
        };
        let one_thread = run(1);
        let two_threads = run(2);
        assert!(one_thread == two_threads);
        let (epe, under_one) = score_flow(&two_threads.0, &pair.truth, 20);
        println!("fast preset, 1 and 2 threads: EPE {epe:.3}, < 1 px {under_one:.3}");
        assert!(under_one >= 0.99, "{under_one}");
    }

    #[test]
    fn round_trip_check_keeps_only_agreeing_in_view_pairs() {
        let row = |values: Vec<f32>| Image::new(4, 1, values).unwrap();
        let forward = FlowField::new(row(vec![1.0; 4]), row(vec![0.0; 4])).unwrap();
        // Query 0 → rendering 1 and back: agrees. Query 1 → rendering 2, whose backward flow
        // points elsewhere (an occlusion): rejected. Query 2 → rendering 3: agrees but rendering 3
        // takes no part. Query 3 → x = 4: out of view.
        let backward = FlowField::new(row(vec![-1.0, -1.0, 2.0, -1.0]), row(vec![0.0; 4])).unwrap();
        let participates = Image::new(4, 1, vec![true, true, true, false]).unwrap();
        let all_textured = Image::filled(4, 1, true);
        let costs = Image::filled(4, 1, 7.0);
        let mut pairs = Vec::new();
        collect_consistent_pairs(
            &forward,
            &backward,
            all_textured.view(),
            participates.view(),
            costs.view(),
            0.5,
            &mut pairs,
        )
        .unwrap();
        assert_eq!(pairs.len(), 1);
        assert_eq!((pairs[0].query_x_px, pairs[0].rendering_x_px), (0.0, 1.0));
        assert_eq!(pairs[0].matching_cost, 7.0);
        let error = collect_consistent_pairs(
            &forward,
            &backward,
            Image::filled(3, 1, true).view(),
            participates.view(),
            costs.view(),
            0.5,
            &mut pairs,
        );
        assert!(matches!(
            error,
            Err(FlowError::Image(ImageError::SizeMismatch {
                what: "query texture mask",
                ..
            }))
        ));
    }

    #[test]
    fn bad_masks_and_configs_are_rejected() {
        let (width, height) = (16, 16);
        let image = textured_image(width, height);
        let grey = ImageView::new(width, height, &image).unwrap();
        let mut out = PixelMatches::default();
        let mut workspace = MatchWorkspace::default();
        let small_mask = Image::filled(3, 1, true);
        let error = match_query_to_rendering(
            grey,
            grey,
            Some(small_mask.view()),
            &MatchConfig::default(),
            &mut workspace,
            &mut out,
        );
        assert!(matches!(
            error,
            Err(FlowError::Image(ImageError::SizeMismatch {
                what: "rendering validity mask",
                ..
            }))
        ));
        let config = MatchConfig {
            max_round_trip_error_px: -1.0,
            ..Default::default()
        };
        let error = match_query_to_rendering(grey, grey, None, &config, &mut workspace, &mut out);
        assert!(matches!(
            error,
            Err(FlowError::InvalidConfig {
                field: "max_round_trip_error_px",
                ..
            })
        ));
    }
}
