//! Step "query": the image that stands for the photo in the flow, the photo's gradient magnitude,
//! the ASG of its depth map's normals (docs/design.md §2 step 3), or both mixed by where the depth
//! can be trusted (issue #11 item 5), on the same 0..1 scale as the ASG renderings.

use rayon::prelude::*;

use super::GRADIENT_SCALE_PERCENTILE;
use super::{FrameInput, QueryMode, RegistrationConfig, RegistrationError};
use crate::core::image::{Image, ImageView};
use crate::core::shading::{
    asg_from_normals, gradient_magnitude_with_filter, normals_from_depth, scale_to_percentile,
};

/// Step "query": the image standing for the photo in the flow (any [`QueryMode`]), scaled to
/// 0..1, the photo's size.
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
            gradient_magnitude_with_filter(photo, config.asg.derivative_filter, &mut query);
            scale_to_percentile(query.data_mut(), GRADIENT_SCALE_PERCENTILE);
        }
        QueryMode::DepthAsg => {
            depth_asg(input, config, &mut query)?;
            scale_to_percentile(query.data_mut(), GRADIENT_SCALE_PERCENTILE);
        }
        QueryMode::Mixed => {
            let depth = checked_depth(input, config.query_mode)?;
            let mut asg = Image::default();
            depth_asg(input, config, &mut asg)?;
            gradient_magnitude_with_filter(photo, config.asg.derivative_filter, &mut query);
            scale_to_percentile(query.data_mut(), GRADIENT_SCALE_PERCENTILE);
            let trust = depth_trust(
                depth,
                config.query_depth_smoothing_radius_px + 1,
                config.query_mixed_min_valid_share,
            );
            // The depth-ASG's scale from the trusted pixels only: hole borders are not surfaces.
            let mut trusted: Vec<f32> = asg
                .data()
                .iter()
                .zip(&trust)
                .filter(|(v, w)| **w >= 0.5 && v.is_finite() && **v > 0.0)
                .map(|(v, _)| *v)
                .collect();
            let scale = if trusted.is_empty() {
                0.0
            } else {
                let rank = ((trusted.len() - 1) as f64 * GRADIENT_SCALE_PERCENTILE) as usize;
                let (_, high, _) = trusted.select_nth_unstable_by(rank, f32::total_cmp);
                1.0 / high.max(f32::MIN_POSITIVE)
            };
            for ((out, a), w) in query.data_mut().iter_mut().zip(asg.data()).zip(&trust) {
                let a = if a.is_finite() {
                    (a * scale).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                *out = w * a + (1.0 - w) * *out;
            }
        }
    }
    Ok(query)
}

/// The frame's depth map, checked against the photo's size.
fn checked_depth<'a>(
    input: &FrameInput<'a>,
    mode: QueryMode,
) -> Result<ImageView<'a, f32>, RegistrationError> {
    let depth = input
        .depth_m
        .ok_or(RegistrationError::MissingDepth { mode })?;
    if depth.size() != input.photo.size() {
        return Err(RegistrationError::DepthSize {
            depth_width_px: depth.width_px(),
            depth_height_px: depth.height_px(),
            photo_width_px: input.photo.width_px(),
            photo_height_px: input.photo.height_px(),
        });
    }
    Ok(depth)
}

/// ASG of the normals of the frame's depth map after discontinuity-aware smoothing, unscaled.
fn depth_asg(
    input: &FrameInput,
    config: &RegistrationConfig,
    out: &mut Image<f32>,
) -> Result<(), RegistrationError> {
    let depth = checked_depth(input, config.query_mode)?;
    let mut smoothed = Image::default();
    smooth_depth(
        depth,
        config.query_depth_smoothing_radius_px,
        config.query_depth_max_relative_step,
        &mut smoothed,
    );
    let mut normals = Image::default();
    normals_from_depth(smoothed.view(), &input.camera.intrinsics, &mut normals);
    asg_from_normals(normals.view(), &config.asg, out);
    Ok(())
}

/// Per pixel, how far the depth-ASG can be trusted, 0..1: 0 unless the pixel and its 3×3
/// neighbours have depth (the ASG's derivative filter reads them); otherwise a ramp from
/// `min_valid_share` to 1 of the share of pixels with depth within `radius_px` (the normals come
/// from a full neighbourhood, not from a sliver between holes).
pub fn depth_trust(
    depth_m: ImageView<'_, f32>,
    radius_px: usize,
    min_valid_share: f32,
) -> Vec<f32> {
    let (width_px, height_px) = depth_m.size();
    let valid: Vec<u32> = depth_m
        .data()
        .iter()
        .map(|d| u32::from(d.is_finite() && *d > 0.0))
        .collect();
    // Summed-area table of validity, (w+1)×(h+1).
    let stride = width_px + 1;
    let mut table = vec![0u32; stride * (height_px + 1)];
    for row in 0..height_px {
        let mut line = 0u32;
        for col in 0..width_px {
            line += valid[row * width_px + col];
            table[(row + 1) * stride + col + 1] = table[row * stride + col + 1] + line;
        }
    }
    let window = |row: usize, col: usize, r: usize| {
        let (r0, c0) = (row.saturating_sub(r), col.saturating_sub(r));
        let (r1, c1) = ((row + r + 1).min(height_px), (col + r + 1).min(width_px));
        let sum = table[r1 * stride + c1] + table[r0 * stride + c0]
            - table[r0 * stride + c1]
            - table[r1 * stride + c0];
        (sum, ((r1 - r0) * (c1 - c0)) as u32)
    };
    (0..width_px * height_px)
        .into_par_iter()
        .map(|index| {
            let (row, col) = (index / width_px, index % width_px);
            let (near, near_count) = window(row, col, 1);
            if near < near_count {
                return 0.0;
            }
            let (sum, count) = window(row, col, radius_px);
            let share = sum as f32 / count.max(1) as f32;
            ((share - min_valid_share) / (1.0 - min_valid_share).max(1e-6)).clamp(0.0, 1.0)
        })
        .collect()
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::camera::{Camera, PinholeIntrinsics};
    use crate::core::frame::IntrinsicsMode;
    use crate::core::rigid::Rigid3;

    const W: usize = 80;
    const H: usize = 60;

    fn camera() -> Camera {
        Camera::pinhole(
            W as u32,
            H as u32,
            PinholeIntrinsics::centered(70.0, W as u32, H as u32),
        )
    }

    /// A photo with texture and a roof-like depth map (two planes meeting at a crease).
    fn photo_and_depth() -> (Image<f32>, Image<f32>) {
        let photo = Image::from_fn(W, H, |col, row| {
            0.5 + 0.3 * ((col as f32 * 0.7).sin() * (row as f32 * 0.4).cos())
        });
        let depth = Image::from_fn(W, H, |col, _| 20.0 + 0.05 * (col as f32 - 40.0).abs());
        (photo, depth)
    }

    fn query(
        mode: QueryMode,
        photo: &Image<f32>,
        depth: Option<&Image<f32>>,
    ) -> Result<Image<f32>, RegistrationError> {
        let camera = camera();
        let input = FrameInput {
            photo: photo.view(),
            depth_m: depth.map(Image::view),
            camera: &camera,
            intrinsics: IntrinsicsMode::Known,
            initial_cam_from_world: Rigid3::identity(),
            seed: 1,
        };
        let config = RegistrationConfig {
            query_mode: mode,
            ..RegistrationConfig::default()
        };
        query_gradient(&input, &config)
    }

    #[test]
    fn trust_is_zero_at_and_next_to_holes_and_ramps_with_the_valid_share() {
        let mut depth = Image::filled(40, 30, 10.0f32);
        depth.data_mut()[15 * 40 + 20] = 0.0;
        let trust = depth_trust(depth.view(), 4, 0.8);
        let at = |col: usize, row: usize| trust[row * 40 + col];
        assert_eq!(at(20, 15), 0.0);
        assert_eq!(at(21, 16), 0.0, "3×3 neighbour of the hole");
        // Two px away: 80 of 81 pixels valid, share 0.988 → (0.988 − 0.8) / 0.2.
        assert!(
            (at(22, 15) - (80.0 / 81.0 - 0.8) / 0.2).abs() < 1e-4,
            "{}",
            at(22, 15)
        );
        assert_eq!(at(5, 5), 1.0);
        let all_holes = Image::filled(40, 30, 0.0f32);
        assert!(depth_trust(all_holes.view(), 4, 0.8)
            .iter()
            .all(|t| *t == 0.0));
    }

    #[test]
    fn mixed_is_depth_asg_where_depth_is_full_and_gradient_where_it_is_missing() {
        let (photo, depth) = photo_and_depth();
        let gradient = query(QueryMode::ImageGradient, &photo, None).unwrap();
        let depth_asg = query(QueryMode::DepthAsg, &photo, Some(&depth)).unwrap();
        let mixed_full = query(QueryMode::Mixed, &photo, Some(&depth)).unwrap();
        assert_eq!(mixed_full.data(), depth_asg.data());
        let holes = Image::filled(W, H, 0.0f32);
        let mixed_empty = query(QueryMode::Mixed, &photo, Some(&holes)).unwrap();
        assert_eq!(mixed_empty.data(), gradient.data());
        // Left half with depth, right half without: each side from its source.
        let half = Image::from_fn(W, H, |col, row| {
            if col < W / 2 {
                depth.data()[row * W + col]
            } else {
                0.0
            }
        });
        let mixed_half = query(QueryMode::Mixed, &photo, Some(&half)).unwrap();
        let at = |image: &Image<f32>, col: usize| image.data()[30 * W + col];
        assert_eq!(at(&mixed_half, 60), at(&gradient, 60));
        assert!(at(&mixed_half, 10) <= 1.0);
        assert_ne!(at(&mixed_half, 10), at(&gradient, 10));
        assert!(matches!(
            query(QueryMode::Mixed, &photo, None),
            Err(RegistrationError::MissingDepth {
                mode: QueryMode::Mixed
            })
        ));
    }
}
