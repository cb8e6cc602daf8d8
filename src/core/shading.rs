//! Gradient images that SIFT flow compares: Average Shading Gradients (ASG, paper eq. 4) of a
//! rendered normal map, and the two query representations of a photo (docs/design.md §2 step 3):
//! (a) plain image gradients of the photo, (b) ASG of normals derived from the photo's depth map.
//!
//! ASG averages the gradient magnitude of Lambertian shading `max(0, -n·l)` over all light
//! directions `l`; its closed-form upper bound (eq. 4) is
//! `sqrt(pi/3) * sqrt(sum_{i=x,y,z} (hx*n_i)^2 + (hy*n_i)^2)`, the Frobenius norm of the normal
//! map's filtered Jacobian. The constant is the paper's; it treats `∫_S` as an unnormalised
//! integral inside the square root only, so the closed form is a (loose) upper bound of the
//! *mean* over directions too — the tests measure by how much. The scale does not matter to SIFT
//! (descriptors are normalised); the shape of the response does.
//!
//! All functions write into caller-provided images (resized to the input's size, allocating only
//! when it grows) and run over rows with rayon: one rendering per coarse pose goes through here.

use glam::Vec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::camera::PinholeIntrinsics;
use super::image::{Image, ImageView};

/// `sqrt(pi / 3)`, the constant of the closed form (paper eq. 4).
pub const ASG_SCALE: f32 = 1.023_326_7;

/// The discrete derivative filters `hx`, `hy`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum DerivativeFilter {
    /// `[-1, 0, 1] / 2` along the axis, nothing across it: the sharpest response, but every
    /// per-pixel wiggle of interpolated normals (noisy meshes, MVS depth) shows up.
    CentralDifference,
    /// Sobel, normalised by 1/8 so that a unit ramp gives 1 (same gain as the central
    /// difference): the central difference smoothed by `[1, 2, 1] / 4` across the axis.
    /// Default: the model is a noisy Poisson mesh and query mode (b) differentiates MVS depth,
    /// so the cross smoothing damps noise that is not structure, and the same filter is used on
    /// the photo in query mode (a) so that both sides see edges alike.
    #[default]
    Sobel,
}

impl DerivativeFilter {
    /// Weights across the derivative axis: `hx = ½ Σ_k w_k (I[row+k-1][col+1] − I[row+k-1][col−1])`
    /// and `hy` likewise with rows and columns swapped. Written as differences, a constant image
    /// gives exactly 0.
    pub fn cross_weights(self) -> [f32; 3] {
        match self {
            DerivativeFilter::CentralDifference => [0.0, 1.0, 0.0],
            DerivativeFilter::Sobel => [0.25, 0.5, 0.25],
        }
    }
}

/// `(hx * v, hy * v)` at the centre of a 3×3 neighbourhood `[row][col]`.
fn filter_3x3<T>(neighbourhood: &[[T; 3]; 3], cross_weights: &[f32; 3]) -> (T, T)
where
    T: Copy
        + std::ops::Sub<Output = T>
        + std::ops::Mul<f32, Output = T>
        + std::ops::Add<Output = T>,
{
    let n = neighbourhood;
    let mut derivative_x = (n[0][2] - n[0][0]) * (0.5 * cross_weights[0]);
    let mut derivative_y = (n[2][0] - n[0][0]) * (0.5 * cross_weights[0]);
    for k in 1..3 {
        derivative_x = derivative_x + (n[k][2] - n[k][0]) * (0.5 * cross_weights[k]);
        derivative_y = derivative_y + (n[2][k] - n[0][k]) * (0.5 * cross_weights[k]);
    }
    (derivative_x, derivative_y)
}

/// How pixels without a surface (zero normal: background, holes) enter the derivative filters.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum SilhouetteMode {
    /// Only gradients between pixels with a surface: a background neighbour inside the filter
    /// stencil takes the centre pixel's normal (a one-sided derivative at the border), and
    /// background pixels get 0. Default: in an aerial scene the model usually fills the frame,
    /// so the places where a rendering meets background are the model's outer boundary and the
    /// holes of a Poisson/MVS surface — edges the photo does not have (the terrain goes on).
    /// Real occlusion edges (a roof in front of the ground) are between two surfaces and keep
    /// their gradients in this mode. The same holds for holes of the MVS depth in query mode (b).
    #[default]
    ValidOnly,
    /// Background is a surface facing the camera (normal `(0, 0, -1)` in the camera frame):
    /// every silhouette is a strong edge, two pixels wide (one on each side). Right for an
    /// isolated object against sky or an unmodelled background that contrasts with it.
    BackgroundFacesCamera,
}

/// Options of the ASG rendering (and of the photo's gradient image in query mode (a)).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AsgOptions {
    /// The derivative filters `hx`, `hy` of eq. 4 (unit-gain kernels: results are in change of
    /// the normal's components per pixel).
    pub derivative_filter: DerivativeFilter,
    /// How silhouettes (a surface pixel next to background) are treated.
    pub silhouette_mode: SilhouetteMode,
    /// Occlusion contours from the rendering's depth ([`add_occlusion_contours`]): two surface
    /// pixels whose depths differ by more than this share of the nearer one lie on two sides of
    /// a contour, which then counts like a right-angled crease even where both surfaces have the
    /// same normal (a flat roof in front of the ground). `None`: normals only (the paper's ASG).
    #[serde(default)]
    pub occlusion_depth_ratio: Option<f32>,
}

/// The normal a background pixel stands for in [`SilhouetteMode::BackgroundFacesCamera`].
const BACKGROUND_NORMAL_CAM: Vec3 = Vec3::new(0.0, 0.0, -1.0);

/// Closed-form ASG (paper eq. 4) of a normal map into `out` (made the normal map's size); a zero
/// normal means "no surface". Image borders replicate the edge pixels.
pub fn asg_from_normals(normals: ImageView<'_, Vec3>, options: &AsgOptions, out: &mut Image<f32>) {
    let (width_px, height_px) = normals.size();
    out.resize(width_px, height_px, 0.0);
    if normals.is_empty() {
        return;
    }
    let normals = normals.data();
    let cross_weights = options.derivative_filter.cross_weights();
    let silhouette_mode = options.silhouette_mode;
    out.data_mut()
        .par_chunks_mut(width_px)
        .enumerate()
        .for_each(|(row, out_row)| {
            let rows = neighbour_rows(row, height_px);
            for (col, out_pixel) in out_row.iter_mut().enumerate() {
                let centre = normals[row * width_px + col];
                let centre_valid = centre != Vec3::ZERO;
                if !centre_valid && silhouette_mode == SilhouetteMode::ValidOnly {
                    *out_pixel = 0.0;
                    continue;
                }
                let centre_value = if centre_valid {
                    centre
                } else {
                    BACKGROUND_NORMAL_CAM
                };
                let cols = neighbour_cols(col, width_px);
                let neighbourhood = neighbourhood_3x3(normals, width_px, &rows, &cols, |sample| {
                    if sample != Vec3::ZERO {
                        sample
                    } else {
                        match silhouette_mode {
                            SilhouetteMode::ValidOnly => centre_value,
                            SilhouetteMode::BackgroundFacesCamera => BACKGROUND_NORMAL_CAM,
                        }
                    }
                });
                let (derivative_x, derivative_y) = filter_3x3(&neighbourhood, &cross_weights);
                *out_pixel = ASG_SCALE
                    * (derivative_x.length_squared() + derivative_y.length_squared()).sqrt();
            }
        });
}

/// The ASG of a rendering as registration sees it: [`asg_from_normals`] of its normals, and its
/// occlusion contours from its depth when `options.occlusion_depth_ratio` asks for them
/// ([`add_occlusion_contours`]). Into `out` (made the rendering's size).
pub fn asg_of_rendering(
    normals: ImageView<'_, Vec3>,
    depth_m: ImageView<'_, f32>,
    options: &AsgOptions,
    out: &mut Image<f32>,
) {
    asg_from_normals(normals, options, out);
    if let Some(depth_ratio) = options.occlusion_depth_ratio {
        add_occlusion_contours(depth_m, depth_ratio, options.derivative_filter, out);
    }
}

/// Adds occlusion contours to an ASG image made by [`asg_from_normals`] from a rendering whose
/// depth is `depth_m` (metres along the optical axis, 0 = no surface), in place. Why: ASG sees
/// only normals, so where a surface occludes another with the same normal (a flat roof against
/// the ground behind it, a wall in front of a parallel wall) it has no edge, though the photo
/// has one (two surfaces, two materials and lights); a smoothed Poisson mesh hides this by
/// rounding such edges into ridges, a clean city model (LoD2) does not.
///
/// Each stencil neighbour gets an indicator `c` (1 when its depth and the centre's differ by
/// more than `depth_ratio` times the nearer one, 0 otherwise or without a surface); the
/// indicator's derivative, weighted by √2 (the normal step of a right-angled crease), is added
/// to the normals' derivative in quadrature: a contour alone gives the ASG of a right-angled
/// crease on its two sides, and away from contours nothing changes. Background keeps its
/// [`SilhouetteMode`] treatment.
pub fn add_occlusion_contours(
    depth_m: ImageView<'_, f32>,
    depth_ratio: f32,
    filter: DerivativeFilter,
    asg: &mut Image<f32>,
) {
    let (width_px, height_px) = depth_m.size();
    debug_assert_eq!(
        asg.size(),
        depth_m.size(),
        "an ASG and its rendering's depth"
    );
    if depth_m.is_empty() || asg.size() != depth_m.size() {
        return;
    }
    let depth = depth_m.data();
    let cross_weights = filter.cross_weights();
    let crease_weight_sq = 2.0 * ASG_SCALE * ASG_SCALE;
    asg.data_mut()
        .par_chunks_mut(width_px)
        .enumerate()
        .for_each(|(row, out_row)| {
            let rows = neighbour_rows(row, height_px);
            for (col, out_pixel) in out_row.iter_mut().enumerate() {
                let centre = depth[row * width_px + col];
                if !(centre.is_finite() && centre > 0.0) {
                    continue;
                }
                let cols = neighbour_cols(col, width_px);
                let across = neighbourhood_3x3(depth, width_px, &rows, &cols, |sample| {
                    let contour = sample.is_finite()
                        && sample > 0.0
                        && (sample - centre).abs() > depth_ratio * sample.min(centre);
                    if contour {
                        1.0f32
                    } else {
                        0.0
                    }
                });
                if across.iter().flatten().all(|&c| c == 0.0) {
                    continue;
                }
                let (derivative_x, derivative_y) = filter_3x3(&across, &cross_weights);
                let contour_sq =
                    crease_weight_sq * (derivative_x * derivative_x + derivative_y * derivative_y);
                *out_pixel = (*out_pixel * *out_pixel + contour_sq).sqrt();
            }
        });
}

/// Gradient magnitude `sqrt((hx*I)^2 + (hy*I)^2)` of a grey image into `out` (made the image's
/// size) with the default derivative filter of [`AsgOptions`] (query mode (a)). Borders
/// replicate the edge pixels.
pub fn gradient_magnitude(image: ImageView<'_, f32>, out: &mut Image<f32>) {
    gradient_magnitude_with_filter(image, AsgOptions::default().derivative_filter, out);
}

/// [`gradient_magnitude`] with an explicit filter (use the one of the ASG renderings).
pub fn gradient_magnitude_with_filter(
    image: ImageView<'_, f32>,
    filter: DerivativeFilter,
    out: &mut Image<f32>,
) {
    let (width_px, height_px) = image.size();
    out.resize(width_px, height_px, 0.0);
    if image.is_empty() {
        return;
    }
    let pixels = image.data();
    let cross_weights = filter.cross_weights();
    out.data_mut()
        .par_chunks_mut(width_px)
        .enumerate()
        .for_each(|(row, out_row)| {
            let rows = neighbour_rows(row, height_px);
            for (col, out_pixel) in out_row.iter_mut().enumerate() {
                let cols = neighbour_cols(col, width_px);
                let neighbourhood = neighbourhood_3x3(pixels, width_px, &rows, &cols, |v| v);
                let (derivative_x, derivative_y) = filter_3x3(&neighbourhood, &cross_weights);
                *out_pixel = derivative_x.hypot(derivative_y);
            }
        });
}

/// Unit surface normals (camera frame, facing the camera) from a depth map, into `out` (made the
/// depth map's size): pixel centres are back-projected with the depth (metres along the optical
/// axis; holes are 0 or non-finite), tangents are central differences of the 3D points,
/// one-sided where a neighbour is a hole; the normal is their cross product oriented toward the
/// camera. Zero where it cannot be computed (a hole, or no neighbour along one axis). Query mode
/// (b) is `asg_from_normals(normals_from_depth(..))`.
pub fn normals_from_depth(
    depth_m: ImageView<'_, f32>,
    intrinsics: &PinholeIntrinsics,
    out: &mut Image<Vec3>,
) {
    let (width_px, height_px) = depth_m.size();
    out.resize(width_px, height_px, Vec3::ZERO);
    if depth_m.is_empty() {
        return;
    }
    let depth_m = depth_m.data();
    let back_project = |col: usize, row: usize| -> Option<Vec3> {
        let depth = depth_m[row * width_px + col];
        if !(depth.is_finite() && depth > 0.0) {
            return None;
        }
        let normalized = intrinsics
            .pixel_to_normalized(nalgebra::Vector2::new(col as f64 + 0.5, row as f64 + 0.5));
        Some(Vec3::new(
            normalized.x as f32 * depth,
            normalized.y as f32 * depth,
            depth,
        ))
    };
    // Central difference when both neighbours exist, else one-sided, else none.
    let tangent = |centre: Vec3, before: Option<Vec3>, after: Option<Vec3>| match (before, after) {
        (Some(before), Some(after)) => Some(after - before),
        (None, Some(after)) => Some(after - centre),
        (Some(before), None) => Some(centre - before),
        (None, None) => None,
    };
    out.data_mut()
        .par_chunks_mut(width_px)
        .enumerate()
        .for_each(|(row, out_row)| {
            for (col, out_normal) in out_row.iter_mut().enumerate() {
                *out_normal = Vec3::ZERO;
                let Some(centre) = back_project(col, row) else {
                    continue;
                };
                let left = col.checked_sub(1).and_then(|c| back_project(c, row));
                let right = (col + 1 < width_px)
                    .then(|| back_project(col + 1, row))
                    .flatten();
                let up = row.checked_sub(1).and_then(|r| back_project(col, r));
                let down = (row + 1 < height_px)
                    .then(|| back_project(col, row + 1))
                    .flatten();
                let (Some(tangent_x), Some(tangent_y)) =
                    (tangent(centre, left, right), tangent(centre, up, down))
                else {
                    continue;
                };
                let normal = tangent_x.cross(tangent_y).normalize_or_zero();
                // Toward the camera: the normal and the ray to the point point in opposite ways.
                *out_normal = if normal.dot(centre) > 0.0 {
                    -normal
                } else {
                    normal
                };
            }
        });
}

/// The 3×3 neighbourhood `[row][col]` at `rows × cols` of a row-major image `width_px` wide,
/// each sample mapped by `value` (the stencil the derivative filters read).
fn neighbourhood_3x3<T: Copy, U: Copy + Default>(
    data: &[T],
    width_px: usize,
    rows: &[usize; 3],
    cols: &[usize; 3],
    mut value: impl FnMut(T) -> U,
) -> [[U; 3]; 3] {
    let mut out = [[U::default(); 3]; 3];
    for (kernel_row, &sample_row) in rows.iter().enumerate() {
        for (kernel_col, &sample_col) in cols.iter().enumerate() {
            out[kernel_row][kernel_col] = value(data[sample_row * width_px + sample_col]);
        }
    }
    out
}

/// Rows `[row - 1, row, row + 1]`, clamped to the image.
fn neighbour_rows(row: usize, height_px: usize) -> [usize; 3] {
    [row.saturating_sub(1), row, (row + 1).min(height_px - 1)]
}

/// Columns `[col - 1, col, col + 1]`, clamped to the image.
fn neighbour_cols(col: usize, width_px: usize) -> [usize; 3] {
    [col.saturating_sub(1), col, (col + 1).min(width_px - 1)]
}

/// Scales a non-negative image in place so that the `percentile` (0..1) of its positive finite
/// values becomes 1; values above are clamped to 1, non-finite values become 0. A few very strong
/// edges then do not flatten everything else. An image without positive values is left as it is.
pub fn scale_to_percentile(values: &mut [f32], percentile: f64) {
    let mut positive: Vec<f32> = values
        .iter()
        .copied()
        .filter(|v| v.is_finite() && *v > 0.0)
        .collect();
    if positive.is_empty() {
        return;
    }
    let rank = ((positive.len() - 1) as f64 * percentile.clamp(0.0, 1.0)) as usize;
    let (_, high, _) = positive.select_nth_unstable_by(rank, f32::total_cmp);
    let scale = 1.0 / high.max(f32::MIN_POSITIVE);
    for value in values.iter_mut() {
        *value = if value.is_finite() {
            (*value * scale).clamp(0.0, 1.0)
        } else {
            0.0
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::mesh::Mesh;
    use crate::core::raster::{Rasterizer, RenderBuffers, RenderOptions};
    use crate::core::rigid::Rigid3;
    use nalgebra::Vector3;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    const FILTERS: [DerivativeFilter; 2] =
        [DerivativeFilter::CentralDifference, DerivativeFilter::Sobel];
    const MODES: [SilhouetteMode; 2] = [
        SilhouetteMode::ValidOnly,
        SilhouetteMode::BackgroundFacesCamera,
    ];

    #[test]
    fn options_round_trip_and_reject_unknown_fields() {
        let options = AsgOptions {
            derivative_filter: DerivativeFilter::CentralDifference,
            silhouette_mode: SilhouetteMode::BackgroundFacesCamera,
            occlusion_depth_ratio: Some(0.1),
        };
        let json = serde_json::to_string(&options).unwrap();
        assert_eq!(serde_json::from_str::<AsgOptions>(&json).unwrap(), options);
        let defaults: AsgOptions =
            serde_json::from_str(r#"{"derivative_filter":"Sobel","silhouette_mode":"ValidOnly"}"#)
                .unwrap();
        assert_eq!(defaults, AsgOptions::default());
        assert!(serde_json::from_str::<AsgOptions>(r#"{"filter":"Sobel"}"#).is_err());
    }

    #[test]
    fn the_scale_is_sqrt_pi_over_3() {
        assert!((f64::from(ASG_SCALE) - (std::f64::consts::PI / 3.0).sqrt()).abs() < 1e-7);
    }

    #[test]
    fn a_constant_normal_map_has_no_gradient() {
        let (width, height) = (13, 9);
        let normal = Vec3::new(0.3, -0.4, -0.8).normalize();
        let normals = Image::filled(width, height, normal);
        let mut out = Image::filled(width, height, f32::NAN);
        for derivative_filter in FILTERS {
            for silhouette_mode in MODES {
                let options = AsgOptions {
                    derivative_filter,
                    silhouette_mode,
                    ..AsgOptions::default()
                };
                asg_from_normals(normals.view(), &options, &mut out);
                assert!(out.data().iter().all(|&v| v == 0.0), "{options:?}: {out:?}");
            }
        }
    }

    #[test]
    fn a_crease_between_two_planes_gives_the_hand_computed_magnitude() {
        // Columns < 6 see a plane with normal n1, columns >= 6 one with n2 (a roof ridge).
        let (width, height) = (12, 7);
        let n1 = Vec3::new(-0.6, 0.0, -0.8);
        let n2 = Vec3::new(0.6, 0.0, -0.8);
        let normals = Image::from_fn(width, height, |col, _| if col < 6 { n1 } else { n2 });
        // Both filters: hx = (n2 - n1) / 2 at columns 5 and 6 (the only ones whose stencil
        // straddles the crease), hy = 0 (constant along columns, borders replicated).
        // |n2 - n1| = 1.2 → ASG = sqrt(pi/3) * 0.6.
        let expected = (std::f32::consts::PI / 3.0).sqrt() * 0.6;
        let mut out = Image::filled(width, height, f32::NAN);
        for derivative_filter in FILTERS {
            let options = AsgOptions {
                derivative_filter,
                ..AsgOptions::default()
            };
            asg_from_normals(normals.view(), &options, &mut out);
            for row in 0..height {
                for col in 0..width {
                    let value = out.data()[row * width + col];
                    let want = if col == 5 || col == 6 { expected } else { 0.0 };
                    assert!(
                        (value - want).abs() < 1e-6,
                        "{derivative_filter:?} ({col}, {row}): {value} vs {want}"
                    );
                }
            }
        }
    }

    /// A flat roof in front of the ground: both face up (the same normal), so the normals alone
    /// give no edge; with the depths, the contour gets a right-angled crease's ASG on its two
    /// sides and nothing else changes (a gently receding surface is not a contour).
    #[test]
    fn an_occlusion_contour_between_parallel_surfaces_is_an_edge_with_the_depth() {
        let (width, height) = (12, 7);
        let up = Vec3::new(0.0, -0.6, -0.8);
        let normals = Image::filled(width, height, up);
        // Roof at 20 m on columns < 6, ground at 30 m behind it; both recede by 1 % a row.
        let depth = Image::from_fn(width, height, |col, row| {
            (if col < 6 { 20.0 } else { 30.0 }) * (1.0 + 0.01 * row as f32)
        });
        for derivative_filter in FILTERS {
            let options = AsgOptions {
                derivative_filter,
                occlusion_depth_ratio: Some(0.1),
                ..AsgOptions::default()
            };
            let mut out = Image::filled(width, height, f32::NAN);
            asg_from_normals(normals.view(), &options, &mut out);
            assert!(out.data().iter().all(|&v| v == 0.0), "{out:?}");
            add_occlusion_contours(depth.view(), 0.1, derivative_filter, &mut out);
            // hx of the indicator = 1/2 on columns 5 and 6 → √2 · s · 1/2, as a crease whose
            // normals differ by √2 (a right angle).
            let expected = (std::f32::consts::PI / 3.0).sqrt() * 2f32.sqrt() * 0.5;
            for row in 0..height {
                for col in 0..width {
                    let value = out.data()[row * width + col];
                    let want = if col == 5 || col == 6 { expected } else { 0.0 };
                    assert!(
                        (value - want).abs() < 1e-6,
                        "{derivative_filter:?} ({col}, {row}): {value} vs {want}"
                    );
                }
            }
        }
    }

    #[test]
    fn silhouette_modes_differ_only_at_the_boundary_of_the_surface() {
        // A 4×4 patch of tilted surface in the middle of 10×10 background.
        let (width, height) = (10, 10);
        let tilted = Vec3::new(0.0, 0.6, -0.8);
        let inside = |col: usize, row: usize| (3..7).contains(&col) && (3..7).contains(&row);
        let normals = Image::from_fn(width, height, |col, row| {
            if inside(col, row) {
                tilted
            } else {
                Vec3::ZERO
            }
        });
        let mut valid_only = Image::filled(width, height, f32::NAN);
        let mut facing = Image::filled(width, height, f32::NAN);
        let options = |silhouette_mode| AsgOptions {
            derivative_filter: DerivativeFilter::CentralDifference,
            silhouette_mode,
            ..AsgOptions::default()
        };
        asg_from_normals(
            normals.view(),
            &options(SilhouetteMode::ValidOnly),
            &mut valid_only,
        );
        asg_from_normals(
            normals.view(),
            &options(SilhouetteMode::BackgroundFacesCamera),
            &mut facing,
        );
        let facing = facing.data();
        // ValidOnly: a constant surface has no gradient anywhere, background is 0.
        assert!(
            valid_only.data().iter().all(|&v| v == 0.0),
            "{valid_only:?}"
        );
        // BackgroundFacesCamera: the left border pixel (3, 4) sees background (0,0,-1) on its
        // left: hx = (tilted - bg) / 2, |tilted - bg| = sqrt(0.36 + 0.04) → ASG = s * sqrt(0.4)/2.
        let s = (std::f32::consts::PI / 3.0).sqrt();
        let edge = s * 0.4f32.sqrt() / 2.0;
        assert!((facing[4 * width + 3] - edge).abs() < 1e-6);
        // ... and so does the background pixel just outside, (2, 4).
        assert!((facing[4 * width + 2] - edge).abs() < 1e-6);
        // Interior pixels and far background: 0.
        assert_eq!(facing[4 * width + 4], 0.0);
        assert_eq!(facing[0], 0.0);
    }

    /// A smooth random unit normal field facing the camera.
    fn smooth_random_normals(width: usize, height: usize, seed: u64) -> Image<Vec3> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let waves: Vec<(f32, f32, f32, f32)> = (0..6)
            .map(|_| {
                (
                    rng.random_range(0.1..0.5),
                    rng.random_range(0.1..0.5),
                    rng.random_range(0.0..std::f32::consts::TAU),
                    rng.random_range(0.2..0.6),
                )
            })
            .collect();
        Image::from_fn(width, height, |col, row| {
            let (x, y) = (col as f32, row as f32);
            let mut n = Vec3::new(0.0, 0.0, -1.0);
            for (k, &(fx, fy, phase, amplitude)) in waves.iter().enumerate() {
                let v = amplitude * (fx * x + fy * y + phase).sin();
                if k % 2 == 0 {
                    n.x += v;
                } else {
                    n.y += v;
                }
            }
            n.normalize()
        })
    }

    /// `count` directions spread evenly over the unit sphere (Fibonacci lattice).
    fn fibonacci_sphere(count: usize) -> Vec<Vec3> {
        let golden_angle = std::f32::consts::PI * (3.0 - 5f32.sqrt());
        (0..count)
            .map(|i| {
                let z = 1.0 - 2.0 * (i as f32 + 0.5) / count as f32;
                let radius = (1.0 - z * z).sqrt();
                let azimuth = golden_angle * i as f32;
                Vec3::new(radius * azimuth.cos(), radius * azimuth.sin(), z)
            })
            .collect()
    }

    #[test]
    fn the_closed_form_bounds_the_brute_force_average_over_light_directions() {
        let (width, height) = (16, 16);
        let normals = smooth_random_normals(width, height, 7);
        let directions = fibonacci_sphere(4096);
        for derivative_filter in FILTERS {
            let options = AsgOptions {
                derivative_filter,
                ..AsgOptions::default()
            };
            let mut closed_form = Image::default();
            asg_from_normals(normals.view(), &options, &mut closed_form);

            let mut average = vec![0.0f64; width * height];
            let mut shading = Image::filled(width, height, 0.0f32);
            let mut gradient = Image::default();
            for light in &directions {
                for (s, n) in shading.data_mut().iter_mut().zip(normals.data()) {
                    *s = (-n.dot(*light)).max(0.0);
                }
                gradient_magnitude_with_filter(shading.view(), derivative_filter, &mut gradient);
                for (a, g) in average.iter_mut().zip(gradient.data()) {
                    *a += f64::from(*g);
                }
            }
            let mut ratio_sum = 0.0;
            let mut ratio_count = 0;
            for (pixel, (&avg_sum, &closed)) in average.iter().zip(closed_form.data()).enumerate() {
                let mean = avg_sum / directions.len() as f64;
                assert!(
                    mean <= f64::from(closed) + 1e-6,
                    "{derivative_filter:?} pixel {pixel}: brute-force mean {mean} > closed form {closed}"
                );
                if closed > 1e-4 {
                    ratio_sum += mean / f64::from(closed);
                    ratio_count += 1;
                }
            }
            assert!(ratio_count > width * height / 2);
            let mean_ratio = ratio_sum / ratio_count as f64;
            println!(
                "{derivative_filter:?}: mean over {ratio_count} pixels of brute-force average / closed form = {mean_ratio:.4}"
            );
            // Away from the terminator the mean is half the mean of |J^T l| over the sphere:
            // |a|/4 for a rank-1 Jacobian (ratio 1/(4 sqrt(pi/3)) = 0.244) up to (pi/8)|J|_F for an
            // isotropic one (ratio 0.271). Far outside means the closed form computes something else.
            assert!((0.22..0.3).contains(&mean_ratio), "{mean_ratio}");
        }
    }

    #[test]
    fn gradient_magnitude_of_a_step_edge() {
        // Intensity 0 left of column 5, 10 from column 5 on.
        let (width, height) = (10, 6);
        let pixels = Image::from_fn(width, height, |col, _| if col < 5 { 0.0 } else { 10.0 });
        let mut out = Image::filled(width, height, f32::NAN);
        for filter in FILTERS {
            gradient_magnitude_with_filter(pixels.view(), filter, &mut out);
            for row in 0..height {
                for col in 0..width {
                    let want = if col == 4 || col == 5 { 5.0 } else { 0.0 };
                    assert!(
                        (out.data()[row * width + col] - want).abs() < 1e-6,
                        "{filter:?} ({col}, {row})"
                    );
                }
            }
        }
        // The default entry point uses the default filter.
        let mut default_out = Image::filled(width, height, f32::NAN);
        gradient_magnitude(pixels.view(), &mut default_out);
        gradient_magnitude_with_filter(
            pixels.view(),
            AsgOptions::default().derivative_filter,
            &mut out,
        );
        assert_eq!(default_out, out);
    }

    #[test]
    fn normals_from_the_depth_of_a_rendered_tilted_plane_are_the_planes_normal() {
        // A large plane through (0, 0, 10) tilted about the y and x axes.
        let plane_normal = Vector3::new(0.3, -0.2, -1.0).normalize();
        let u = plane_normal.cross(&Vector3::new(0.0, 1.0, 0.0)).normalize();
        let v = plane_normal.cross(&u);
        let centre = Vector3::new(0.0, 0.0, 10.0);
        let corners = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
            .map(|(a, b)| centre + u * (a * 20.0) + v * (b * 20.0));
        let mesh = Mesh::from_world(&corners, vec![[0, 1, 2], [0, 2, 3]], None).unwrap();
        let (width, height) = (64, 48);
        let intrinsics = PinholeIntrinsics::centered(60.0, width as u32, height as u32);
        let mut buffers = RenderBuffers::new(width, height);
        Rasterizer::new().render(
            &mesh,
            &intrinsics,
            &Rigid3::identity(),
            &RenderOptions::default(),
            &mut buffers,
        );
        assert_eq!(buffers.valid_count(), width * height);
        // Punch a hole so the one-sided fallback is exercised.
        let mut depth = buffers.depth_m().clone();
        *depth.get_mut(30, 20).unwrap() = 0.0;
        *depth.get_mut(30, 21).unwrap() = f32::NAN;
        let mut normals = Image::filled(width, height, Vec3::splat(f32::NAN));
        normals_from_depth(depth.view(), &intrinsics, &mut normals);
        // The normal facing the camera (the camera looks along +z, so n_z < 0).
        let expected = Vec3::new(
            plane_normal.x as f32,
            plane_normal.y as f32,
            plane_normal.z as f32,
        );
        for (pixel, normal) in normals.data().iter().enumerate() {
            if pixel == 20 * width + 30 || pixel == 21 * width + 30 {
                assert_eq!(*normal, Vec3::ZERO);
            } else {
                assert!(
                    (*normal - expected).length() < 2e-3,
                    "pixel {pixel}: {normal} vs {expected}"
                );
            }
        }
        // A plane has no ASG (away from the hole, whose border sees only valid pixels).
        let mut asg = Image::filled(width, height, f32::NAN);
        asg_from_normals(normals.view(), &AsgOptions::default(), &mut asg);
        assert!(
            asg.data().iter().all(|&a| a < 5e-3),
            "max {:?}",
            asg.data().iter().cloned().fold(0.0, f32::max)
        );
    }

    #[test]
    fn normals_from_depth_are_zero_where_a_whole_axis_is_missing() {
        // A single valid column: no horizontal neighbour anywhere → all zero.
        let (width, height) = (5, 5);
        let depth = Image::from_fn(width, height, |col, _| if col == 2 { 3.0 } else { 0.0 });
        let mut normals = Image::filled(width, height, Vec3::ONE);
        let intrinsics = PinholeIntrinsics::centered(10.0, 5, 5);
        normals_from_depth(depth.view(), &intrinsics, &mut normals);
        assert!(normals.data().iter().all(|n| *n == Vec3::ZERO));
        // A fronto-parallel plane: normal (0, 0, -1) everywhere, borders included.
        let depth = Image::filled(width, height, 3.0);
        normals_from_depth(depth.view(), &intrinsics, &mut normals);
        for n in normals.data() {
            assert!((*n - Vec3::new(0.0, 0.0, -1.0)).length() < 1e-6, "{n}");
        }
    }

    #[test]
    fn percentile_scaling_clamps_outliers_and_clears_non_finite_values() {
        let mut values: Vec<f32> = (1..=100).map(|v| v as f32).collect();
        values.push(f32::NAN);
        scale_to_percentile(&mut values, 0.5);
        // The median of 1..=100 (rank 49 of 0..99) is 50.
        assert!((values[49] - 1.0).abs() < 1e-6);
        assert!((values[24] - 0.5).abs() < 1e-6);
        assert_eq!(values[99], 1.0);
        assert_eq!(values[100], 0.0);
        let mut flat = vec![0.0f32; 4];
        scale_to_percentile(&mut flat, 0.99);
        assert_eq!(flat, vec![0.0; 4]);
    }
}
