//! Stand-ins for library pieces being written in parallel (δ of eq. 5, image gradients and ASG). They keep `synth` compiling and testable until those land on main;
//! then this file goes away and the callers use `crate::core` / `crate::io`.

#[cfg(test)]
use glam::Vec3;
use nalgebra::Vector2;

use crate::core::camera::Camera;
use crate::core::mesh::Mesh;
use crate::core::raster::{Rasterizer, RenderBuffers, RenderOptions};
use crate::core::rigid::Rigid3;

/// Scratch buffers of [`mutual_reprojection_error_px`].
#[derive(Default)]
pub struct ReprojectionWorkspace {
    rasterizer: Rasterizer,
    buffers: RenderBuffers,
}

impl ReprojectionWorkspace {
    pub fn new() -> Self {
        Self::default()
    }
}

fn one_way(
    mesh: &Mesh,
    camera_a: &Camera,
    pose_a: &Rigid3,
    camera_b: &Camera,
    pose_b: &Rigid3,
    workspace: &mut ReprojectionWorkspace,
) -> Option<f64> {
    let (w, h) = (camera_a.width_px as usize, camera_a.height_px as usize);
    workspace.buffers.resize(w, h);
    workspace.rasterizer.render(
        mesh,
        &camera_a.intrinsics,
        pose_a,
        &RenderOptions::default(),
        &mut workspace.buffers,
    );
    let world_from_a = pose_a.inverse();
    let mut sum = 0.0;
    let mut count = 0usize;
    for row in 0..h {
        for col in 0..w {
            let depth = workspace.buffers.depth_m[row * w + col];
            if depth <= 0.0 {
                continue;
            }
            let pixel = Vector2::new(col as f64 + 0.5, row as f64 + 0.5);
            let n = camera_a.intrinsics.pixel_to_normalized(pixel);
            let p_cam = nalgebra::Vector3::new(n.x, n.y, 1.0) * f64::from(depth);
            let world = world_from_a.transform_point(&p_cam);
            let in_b = pose_b.transform_point(&world);
            if let Some(q) = camera_b.intrinsics.project(&in_b) {
                sum += (q - pixel).norm();
                count += 1;
            }
        }
    }
    (count > 0).then(|| sum / count as f64)
}

/// δ(P_a, P_b) of paper eq. 5.
pub fn mutual_reprojection_error_px(
    mesh: &Mesh,
    camera_a: &Camera,
    pose_a: &Rigid3,
    camera_b: &Camera,
    pose_b: &Rigid3,
    workspace: &mut ReprojectionWorkspace,
) -> Option<f64> {
    let ab = one_way(mesh, camera_a, pose_a, camera_b, pose_b, workspace);
    let ba = one_way(mesh, camera_b, pose_b, camera_a, pose_a, workspace);
    match (ab, ba) {
        (Some(a), Some(b)) => Some(0.5 * (a + b)),
        (Some(a), None) | (None, Some(a)) => Some(a),
        _ => None,
    }
}

/// Central-difference gradient magnitude.
#[cfg(test)]
pub fn gradient_magnitude(pixels: &[f32], w: usize, h: usize, out: &mut [f32]) {
    for row in 0..h {
        for col in 0..w {
            let at = |r: usize, c: usize| pixels[r * w + c];
            let gx = (at(row, (col + 1).min(w - 1)) - at(row, col.saturating_sub(1))) * 0.5;
            let gy = (at((row + 1).min(h - 1), col) - at(row.saturating_sub(1), col)) * 0.5;
            out[row * w + col] = (gx * gx + gy * gy).sqrt();
        }
    }
}

/// ASG of paper eq. 4 on a normal map (zero normals = background).
#[cfg(test)]
pub fn asg_from_normals(normals: &[Vec3], w: usize, h: usize, out: &mut [f32]) {
    let scale = (std::f32::consts::PI / 3.0).sqrt();
    for row in 0..h {
        for col in 0..w {
            let at = |r: usize, c: usize| normals[r * w + c];
            let hx = (at(row, (col + 1).min(w - 1)) - at(row, col.saturating_sub(1))) * 0.5;
            let hy = (at((row + 1).min(h - 1), col) - at(row.saturating_sub(1), col)) * 0.5;
            out[row * w + col] = scale * (hx.length_squared() + hy.length_squared()).sqrt();
        }
    }
}
