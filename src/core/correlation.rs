//! A dense photo evidence for a pose that does not rest on the model's creases (issues #11 item 4,
//! #12): how sharply the rendered ASG correlates with the query at the pose against the same
//! rendering shifted by a few pixels. On the real Brighton photos the edge support of a correct
//! pose sits at its chance level (the MVS mesh's creases are noise, the photo's edges are roads
//! and paint), but this correlation still peaks at the truth (docs/measurements.md, "Brighton's
//! real photos stage by stage"). The frame's decision reads it from [`FrameEvidence`]
//! (`crate::core::confidence`); the diagnosis reports it at the truth and at the output.
//!
//! [`FrameEvidence`]: crate::core::confidence::FrameEvidence

use serde::{Deserialize, Serialize};

use super::edge_align::{blurred_query, SUPPORT_PEAK_SHIFTS_PX};
use super::image::{Image, ImageView};
use super::raster::NO_FACE;

/// Blur of both images before they are correlated, px (σ): the photo's ridges and the model's
/// need not coincide to the pixel for the correlation to see them.
pub const CORRELATION_BLUR_SIGMA_PX: f64 = 1.0;

/// How sharply the rendered ASG correlates with the query at a pose: the normalised
/// cross-correlation (NCC, −1..1) of both (blurred, σ = [`CORRELATION_BLUR_SIGMA_PX`]) over the
/// rendering's model pixels, at the pose and with the rendering shifted by
/// [`SUPPORT_PEAK_SHIFTS_PX`] in eight directions (means), as
/// [`crate::core::edge_align::support_peak`] does for edges.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CorrelationPeak {
    /// NCC at the pose.
    pub at_pose: f64,
    /// Mean NCC with the rendering shifted by the near shift (3 px).
    pub near: f64,
    /// Mean NCC with the rendering shifted by the far shift (12 px): the chance level.
    pub far: f64,
}

/// Buffers of [`correlation_peak`], reused across calls.
#[derive(Default)]
pub struct CorrelationWorkspace {
    rendering: Image<f32>,
    photo: Image<f32>,
    /// Model pixels of the rendering: (x, y, blurred ASG value).
    model_pixels: Vec<(usize, usize, f64)>,
}

/// [`CorrelationPeak`] of the rendering `asg` (model pixels: `face_index` not [`NO_FACE`])
/// against `query` (same size); `None` without model pixels, when the sizes differ or when either
/// image is constant over the model pixels at the pose.
pub fn correlation_peak(
    asg: ImageView<'_, f32>,
    face_index: ImageView<'_, u32>,
    query: ImageView<'_, f32>,
    workspace: &mut CorrelationWorkspace,
) -> Option<CorrelationPeak> {
    correlation_peak_blurred(asg, face_index, query, CORRELATION_BLUR_SIGMA_PX, workspace)
}

/// [`correlation_peak`] with both images blurred by `blur_sigma_px` (σ) instead of
/// [`CORRELATION_BLUR_SIGMA_PX`]: a coarser blur weighs the model's large-scale layout against
/// the photo's and not its fine texture (the diagnosis measures it at several).
pub fn correlation_peak_blurred(
    asg: ImageView<'_, f32>,
    face_index: ImageView<'_, u32>,
    query: ImageView<'_, f32>,
    blur_sigma_px: f64,
    workspace: &mut CorrelationWorkspace,
) -> Option<CorrelationPeak> {
    let (width_px, height_px) = asg.size();
    if query.size() != (width_px, height_px) || face_index.size() != (width_px, height_px) {
        return None;
    }
    let CorrelationWorkspace {
        rendering,
        photo,
        model_pixels,
    } = workspace;
    // `blurred_query` blurs with a quarter of its radius as σ.
    blurred_query(asg, 4.0 * blur_sigma_px, rendering);
    blurred_query(query, 4.0 * blur_sigma_px, photo);
    let (rendering, photo, faces) = (rendering.data(), photo.data(), face_index.data());
    model_pixels.clear();
    for y in 0..height_px {
        for x in 0..width_px {
            let pixel = y * width_px + x;
            if faces[pixel] != NO_FACE {
                model_pixels.push((x, y, f64::from(rendering[pixel])));
            }
        }
    }
    let ncc = |dx: isize, dy: isize| -> Option<f64> {
        let (mut n, mut sa, mut sb, mut saa, mut sbb, mut sab) = (0.0f64, 0.0, 0.0, 0.0, 0.0, 0.0);
        for &(x, y, a) in model_pixels.iter() {
            let (qx, qy) = (x as isize + dx, y as isize + dy);
            if qx < 0 || qy < 0 || qx >= width_px as isize || qy >= height_px as isize {
                continue;
            }
            let b = f64::from(photo[qy as usize * width_px + qx as usize]);
            n += 1.0;
            sa += a;
            sb += b;
            saa += a * a;
            sbb += b * b;
            sab += a * b;
        }
        let var_a = saa - sa * sa / n;
        let var_b = sbb - sb * sb / n;
        (n > 0.0 && var_a > 0.0 && var_b > 0.0)
            .then(|| (sab - sa * sb / n) / (var_a * var_b).sqrt())
    };
    // Mean NCC over the eight shifts that have one.
    let ring = |shift_px: f64| -> f64 {
        let (sum, count) = (0..8)
            .filter_map(|direction| {
                let angle = direction as f64 * std::f64::consts::FRAC_PI_4;
                ncc(
                    (shift_px * angle.cos()).round() as isize,
                    (shift_px * angle.sin()).round() as isize,
                )
            })
            .fold((0.0, 0usize), |(sum, count), value| {
                (sum + value, count + 1)
            });
        sum / count.max(1) as f64
    };
    let [near_shift_px, far_shift_px] = SUPPORT_PEAK_SHIFTS_PX;
    Some(CorrelationPeak {
        at_pose: ncc(0, 0)?,
        near: ring(near_shift_px),
        far: ring(far_shift_px),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::frame::tests::{house_and_poses, view_at};
    use crate::core::frame::RegistrationConfig;
    use crate::core::rigid::Rigid3;
    use nalgebra::{UnitQuaternion, Vector3};

    /// Known pose, ideal query (the rendering at the truth): the correlation peaks at the true
    /// pose, falls at the near ring and more at the far one; a rendering at a pose whose image is
    /// about 10 px off correlates less at its pose than the truth's and peaks away from it (its
    /// ring is not below its pose).
    #[test]
    fn correlation_peaks_at_the_true_pose_on_an_ideal_query() {
        let (mesh, camera, truth, _) = house_and_poses();
        let config = RegistrationConfig::default();
        let at_truth = view_at(&mesh, &camera, &truth, &config);
        let query = at_truth.asg.view();
        let mut workspace = CorrelationWorkspace::default();
        let peak = correlation_peak(
            at_truth.asg.view(),
            at_truth.render.face_index().view(),
            query,
            &mut workspace,
        )
        .expect("the model is seen");
        assert!(peak.at_pose > 0.99, "{peak:?}");
        assert!(
            peak.at_pose > peak.near + 0.05 && peak.near > peak.far + 0.05,
            "{peak:?}"
        );
        // Turned about the camera's y axis so that the image moves by about 10 px.
        let focal_px = camera.intrinsics.fx_px;
        let turn = UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 10.0 / focal_px, 0.0));
        let shifted = Rigid3::new(turn * truth.rotation, turn * truth.translation);
        let off = view_at(&mesh, &camera, &shifted, &config);
        let off_peak = correlation_peak(
            off.asg.view(),
            off.render.face_index().view(),
            query,
            &mut workspace,
        )
        .expect("the model is seen");
        assert!(off_peak.at_pose < peak.at_pose - 0.3, "{off_peak:?}");
        assert!(
            off_peak.at_pose - off_peak.far < 0.5 * (peak.at_pose - peak.far),
            "{off_peak:?} vs {peak:?}"
        );
        // Sizes that differ give nothing.
        let small = Image::<f32>::filled(3, 3, 0.0);
        assert_eq!(
            correlation_peak(
                at_truth.asg.view(),
                at_truth.render.face_index().view(),
                small.view(),
                &mut workspace
            ),
            None
        );
    }
}
