//! Step "query": the image that stands for the photo in the flow, the photo's gradient magnitude
//! or the ASG of its depth map's normals (docs/design.md §2 step 3), on the same 0..1 scale as the ASG
//! renderings.

use rayon::prelude::*;

use super::GRADIENT_SCALE_PERCENTILE;
use super::{FrameInput, QueryGradient, QueryMode, RegistrationConfig, RegistrationError};
use crate::core::shading::{
    asg_from_normals, gradient_magnitude_with_filter, normals_from_depth, scale_to_percentile,
};

/// Step "query": the photo's gradient image (either mode), scaled to 0..1.
pub fn query_gradient(
    input: &FrameInput,
    config: &RegistrationConfig,
) -> Result<QueryGradient, RegistrationError> {
    let photo = input.photo;
    if photo.width_px != input.camera.width_px as usize
        || photo.height_px != input.camera.height_px as usize
    {
        return Err(RegistrationError::PhotoSize {
            photo_width_px: photo.width_px,
            photo_height_px: photo.height_px,
            camera_width_px: input.camera.width_px,
            camera_height_px: input.camera.height_px,
        });
    }
    let (width_px, height_px) = (photo.width_px, photo.height_px);
    let mut pixels = vec![0.0f32; width_px * height_px];
    match config.query_mode {
        QueryMode::ImageGradient => gradient_magnitude_with_filter(
            photo.pixels,
            width_px,
            height_px,
            config.asg.derivative_filter,
            &mut pixels,
        ),
        QueryMode::DepthAsg => {
            let depth = input.depth_m.ok_or(RegistrationError::MissingDepth)?;
            if depth.width_px != width_px || depth.height_px != height_px {
                return Err(RegistrationError::DepthSize {
                    depth_width_px: depth.width_px,
                    depth_height_px: depth.height_px,
                    photo_width_px: width_px,
                    photo_height_px: height_px,
                });
            }
            let mut smoothed = vec![0.0f32; width_px * height_px];
            smooth_depth(
                depth.pixels,
                width_px,
                height_px,
                config.query_depth_smoothing_radius_px,
                config.query_depth_max_relative_step,
                &mut smoothed,
            );
            let mut normals = vec![glam::Vec3::ZERO; width_px * height_px];
            normals_from_depth(
                &smoothed,
                width_px,
                height_px,
                &input.camera.intrinsics,
                &mut normals,
            );
            asg_from_normals(&normals, width_px, height_px, &config.asg, &mut pixels);
        }
    }
    scale_to_percentile(&mut pixels, GRADIENT_SCALE_PERCENTILE);
    Ok(QueryGradient {
        width_px,
        height_px,
        pixels,
    })
}

/// Discontinuity-aware box smoothing of a depth map (holes are 0 and stay 0): each valid pixel
/// becomes the mean of the valid pixels within `radius_px` whose depth is within
/// `max_relative_step` of its own. Rows in parallel.
pub fn smooth_depth(
    depth_m: &[f32],
    width_px: usize,
    height_px: usize,
    radius_px: usize,
    max_relative_step: f32,
    out: &mut [f32],
) {
    out.par_chunks_mut(width_px.max(1))
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
