//! Step "query": the image that stands for the photo in the flow, the photo's gradient magnitude
//! or the ASG of its depth map's normals (docs/design.md §2 step 3), on the same 0..1 scale as the ASG
//! renderings.

use rayon::prelude::*;

use super::GRADIENT_SCALE_PERCENTILE;
use super::{FrameInput, QueryMode, RegistrationConfig, RegistrationError};
use crate::core::image::{Image, ImageView};
use crate::core::shading::{
    asg_from_normals, gradient_magnitude_with_filter, normals_from_depth, scale_to_percentile,
};

/// Step "query": the photo's gradient image (either mode), scaled to 0..1, the photo's size.
pub fn query_gradient(
    input: &FrameInput,
    config: &RegistrationConfig,
) -> Result<Image<f32>, RegistrationError> {
    let photo = input.photo;
    let (width_px, height_px) = photo.size();
    if width_px != input.camera.width_px as usize || height_px != input.camera.height_px as usize {
        return Err(RegistrationError::PhotoSize {
            photo_width_px: width_px,
            photo_height_px: height_px,
            camera_width_px: input.camera.width_px,
            camera_height_px: input.camera.height_px,
        });
    }
    let mut query = Image::default();
    match config.query_mode {
        QueryMode::ImageGradient => {
            gradient_magnitude_with_filter(photo, config.asg.derivative_filter, &mut query)
        }
        QueryMode::DepthAsg => {
            let depth = input.depth_m.ok_or(RegistrationError::MissingDepth)?;
            if depth.size() != photo.size() {
                return Err(RegistrationError::DepthSize {
                    depth_width_px: depth.width_px(),
                    depth_height_px: depth.height_px(),
                    photo_width_px: width_px,
                    photo_height_px: height_px,
                });
            }
            let mut smoothed = Image::default();
            smooth_depth(
                depth,
                config.query_depth_smoothing_radius_px,
                config.query_depth_max_relative_step,
                &mut smoothed,
            );
            let mut normals = Image::default();
            normals_from_depth(smoothed.view(), &input.camera.intrinsics, &mut normals);
            asg_from_normals(normals.view(), &config.asg, &mut query);
        }
    }
    scale_to_percentile(query.data_mut(), GRADIENT_SCALE_PERCENTILE);
    Ok(query)
}

/// Discontinuity-aware box smoothing of a depth map (holes are 0 and stay 0) into `out` (made
/// the depth map's size): each valid pixel becomes the mean of the valid pixels within
/// `radius_px` whose depth is within `max_relative_step` of its own. Rows in parallel.
pub fn smooth_depth(
    depth_m: ImageView<'_, f32>,
    radius_px: usize,
    max_relative_step: f32,
    out: &mut Image<f32>,
) {
    let (width_px, height_px) = depth_m.size();
    out.resize(width_px, height_px, 0.0);
    let depth_m = depth_m.data();
    out.data_mut()
        .par_chunks_mut(width_px.max(1))
        .enumerate()
        .for_each(|(row, out_row)| {
            for (col, out_value) in out_row.iter_mut().enumerate() {
                let centre = depth_m[row * width_px + col];
                if !(centre.is_finite() && centre > 0.0) {
                    *out_value = 0.0;
                    continue;
                }
                let (mut sum, mut count) = (0.0f32, 0u32);
                for r in row.saturating_sub(radius_px)..(row + radius_px + 1).min(height_px) {
                    for c in col.saturating_sub(radius_px)..(col + radius_px + 1).min(width_px) {
                        let d = depth_m[r * width_px + c];
                        if d.is_finite()
                            && d > 0.0
                            && (d - centre).abs() <= max_relative_step * centre
                        {
                            sum += d;
                            count += 1;
                        }
                    }
                }
                *out_value = sum / count.max(1) as f32;
            }
        });
}
