//! Pictures a person can look at: the model drawn over a photo under a pose (the paper's
//! qualitative figure) and gradient images scaled for display. This is how users and reviewers see
//! whether a pose is right, so it is plain and exact: a pixel of the overlay is a pixel of the photo.

use glam::Vec3;

use crate::core::image::{Image, ImageError, ImageView};
use crate::core::raster::{RenderBuffers, NO_FACE};
use crate::core::shading::scale_to_percentile;

/// How the model is drawn over the photo.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
pub enum OverlayStyle {
    /// Normal colours blended over the photo, with the model's edges on top.
    #[default]
    NormalsAndEdges,
    /// Only the model's silhouette and crease edges, the photo untouched elsewhere.
    Edges,
}

/// Colour of the model's edges in overlays.
const EDGE_RGB: [u8; 3] = [255, 40, 40];

/// Normals that differ by more than this angle (about 35°) make a crease edge.
const CREASE_COS: f32 = 0.82;

/// Pixels where the rendered model has an edge: a silhouette (surface next to background or a depth
/// jump of more than 5 %) or a crease (the normal turns by more than about 35°).
pub fn model_edges(render: &RenderBuffers) -> Image<bool> {
    let width = render.width_px();
    let height = render.height_px();
    let (face_index, depth_m, normal_cam) = (
        render.face_index().data(),
        render.depth_m().data(),
        render.normal_cam().data(),
    );
    let mut edges = Image::filled(width, height, false);
    let edges_data = edges.data_mut();
    for row in 0..height {
        for col in 0..width {
            let index = row * width + col;
            let here_valid = face_index[index] != NO_FACE;
            let neighbours = [
                (col + 1 < width).then(|| index + 1),
                (row + 1 < height).then(|| index + width),
            ];
            for other in neighbours.into_iter().flatten() {
                let other_valid = face_index[other] != NO_FACE;
                let edge = match (here_valid, other_valid) {
                    (false, false) => false,
                    (true, false) | (false, true) => true,
                    (true, true) => {
                        let (d0, d1) = (depth_m[index], depth_m[other]);
                        let jump = (d0 - d1).abs() > 0.05 * d0.min(d1);
                        let crease = normal_cam[index].dot(normal_cam[other]) < CREASE_COS;
                        jump || crease
                    }
                };
                if edge {
                    edges_data[index] = true;
                    edges_data[other] = true;
                }
            }
        }
    }
    edges
}

/// Colour of a camera-frame normal: x → red, -y (up) → green, -z (towards the camera) → blue.
fn normal_rgb(normal: Vec3) -> [f32; 3] {
    [
        (normal.x * 0.5 + 0.5) * 255.0,
        (-normal.y * 0.5 + 0.5) * 255.0,
        (-normal.z * 0.5 + 0.5) * 255.0,
    ]
}

/// Draws the rendered model over `photo_rgb`, which must have the rendering's size. `alpha` is
/// the opacity of the normal colours (0..1).
pub fn overlay_model(
    photo_rgb: ImageView<'_, [u8; 3]>,
    render: &RenderBuffers,
    style: OverlayStyle,
    alpha: f32,
) -> Result<Image<[u8; 3]>, ImageError> {
    photo_rgb.check_size("the photo", render.width_px(), render.height_px())?;
    let alpha = alpha.clamp(0.0, 1.0);
    let edges = model_edges(render);
    let (face_index, normal_cam) = (render.face_index().data(), render.normal_cam().data());
    let pixels = photo_rgb
        .data()
        .iter()
        .enumerate()
        .map(|(index, photo)| {
            if edges.data()[index] {
                return EDGE_RGB;
            }
            if style == OverlayStyle::Edges || face_index[index] == NO_FACE {
                return *photo;
            }
            let model = normal_rgb(normal_cam[index]);
            std::array::from_fn(|c| {
                (f32::from(photo[c]) * (1.0 - alpha) + model[c] * alpha).round() as u8
            })
        })
        .collect();
    Image::new(photo_rgb.width_px(), photo_rgb.height_px(), pixels)
}

/// Scales a non-negative image (a gradient image, a depth map) to 0..1 for display: values are
/// divided by their 99th percentile (so a few strong edges do not make everything black) and clamped.
pub fn normalize_for_display(values: ImageView<'_, f32>) -> Image<f32> {
    let mut scaled = values.to_image();
    scale_to_percentile(scaled.data_mut(), 0.99);
    if !scaled.data().iter().any(|v| *v > 0.0) {
        scaled.fill(0.0);
    }
    scaled
}

/// Colour of added pixels in change overlays.
pub const ADDED_RGB: [u8; 3] = [235, 40, 40];
/// Colour of removed pixels in change overlays.
pub const REMOVED_RGB: [u8; 3] = [40, 120, 255];

/// Change classes coloured over a grey photo (0..1, the classes' size): added red, removed blue,
/// unknown slightly darkened, unchanged as it is. `alpha` is the colours' opacity (0..1).
pub fn overlay_changes(
    photo_grey: ImageView<'_, f32>,
    classes: ImageView<'_, crate::core::change::ChangeClass>,
    alpha: f32,
) -> Result<Image<[u8; 3]>, ImageError> {
    use crate::core::change::ChangeClass;
    photo_grey.check_size("the photo", classes.width_px(), classes.height_px())?;
    let alpha = alpha.clamp(0.0, 1.0);
    let pixels = photo_grey
        .data()
        .iter()
        .zip(classes.data())
        .map(|(grey, class)| {
            let g = (grey.clamp(0.0, 1.0) * 255.0).round();
            let blend = |colour: [u8; 3]| -> [u8; 3] {
                std::array::from_fn(|c| (g * (1.0 - alpha) + f32::from(colour[c]) * alpha) as u8)
            };
            match class {
                ChangeClass::Added => blend(ADDED_RGB),
                ChangeClass::Removed => blend(REMOVED_RGB),
                ChangeClass::Unknown => [(g * 0.7) as u8; 3],
                ChangeClass::Unchanged => [g as u8; 3],
            }
        })
        .collect();
    Image::new(photo_grey.width_px(), photo_grey.height_px(), pixels)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::camera::PinholeIntrinsics;
    use crate::core::mesh::Mesh;
    use crate::core::raster::{Rasterizer, RenderOptions};
    use crate::core::rigid::Rigid3;
    use nalgebra::Vector3;

    fn square_render() -> RenderBuffers {
        let positions = [
            Vector3::new(-1.0, -1.0, 5.0),
            Vector3::new(1.0, -1.0, 5.0),
            Vector3::new(1.0, 1.0, 5.0),
            Vector3::new(-1.0, 1.0, 5.0),
        ];
        let mesh = Mesh::from_world(&positions, vec![[0, 2, 1], [0, 3, 2]], None).unwrap();
        let mut out = RenderBuffers::new(100, 80);
        Rasterizer::new().render(
            &mesh,
            &PinholeIntrinsics::centered(100.0, 100, 80),
            &Rigid3::identity(),
            &RenderOptions::default(),
            &mut out,
        );
        out
    }

    #[test]
    fn edges_trace_the_silhouette_only() {
        let render = square_render();
        let edges = model_edges(&render);
        let edges = edges.data();
        // The square covers columns 30..=69, rows 20..=59: its border and the background pixel
        // next to it are edges, its inside (one flat plane split into two triangles) is not.
        assert!(edges[40 * 100 + 30] && edges[40 * 100 + 29] && edges[20 * 100 + 50]);
        assert!(!edges[40 * 100 + 50] && !edges[40 * 100 + 10]);
        assert!(
            !edges[45 * 100 + 45],
            "the diagonal between the two triangles is no edge"
        );
    }

    #[test]
    fn overlay_blends_inside_and_keeps_the_photo_outside() {
        let render = square_render();
        let photo = Image::filled(100, 80, [10u8, 20, 30]);
        let out = overlay_model(photo.view(), &render, OverlayStyle::NormalsAndEdges, 0.5).unwrap();
        assert_eq!(out.get(5, 5), Some(&[10, 20, 30]));
        assert_eq!(out.get(30, 40), Some(&EDGE_RGB));
        // Normal (0, 0, -1): colour (127.5, 127.5, 255) blended half with the photo.
        assert_eq!(out.get(50, 40), Some(&[69, 74, 143]));
        let edges_only = overlay_model(photo.view(), &render, OverlayStyle::Edges, 0.5).unwrap();
        assert_eq!(edges_only.get(50, 40), Some(&[10, 20, 30]));
        let small = Image::filled(80, 100, [0u8; 3]);
        let error = overlay_model(small.view(), &render, OverlayStyle::Edges, 0.5).unwrap_err();
        assert!(matches!(error, ImageError::SizeMismatch { .. }), "{error}");
    }

    #[test]
    fn display_scaling_ignores_a_few_outliers() {
        let mut values = vec![1.0f32; 1000];
        values[0] = 1000.0;
        let scaled = normalize_for_display(ImageView::new(1000, 1, &values).unwrap());
        assert_eq!(scaled.data()[1], 1.0);
        assert_eq!(scaled.data()[0], 1.0);
        let flat = ImageView::new(2, 1, &[0.0, f32::NAN]).unwrap();
        assert_eq!(normalize_for_display(flat).data(), &[0.0, 0.0]);
    }
}
