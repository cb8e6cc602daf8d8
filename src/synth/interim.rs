//! Stand-ins for library pieces being written in parallel (δ of eq. 5, PLY / COLMAP / PFM writers,
//! image gradients and ASG). They keep `synth` compiling and testable until those land on main;
//! then this file goes away and the callers use `crate::core` / `crate::io`.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::Path;

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
    workspace
        .rasterizer
        .render(mesh, &camera_a.intrinsics, pose_a, &RenderOptions::default(), &mut workspace.buffers);
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

fn create(path: &Path) -> std::io::Result<std::io::BufWriter<std::fs::File>> {
    Ok(std::io::BufWriter::new(std::fs::File::create(path)?))
}

/// Binary little-endian PLY with positions (float) and triangles.
pub fn write_ply(path: &Path, mesh: &Mesh) -> std::io::Result<()> {
    let mut out = create(path)?;
    write!(
        out,
        "ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
        mesh.vertex_count(),
        mesh.face_count()
    )?;
    for v in 0..mesh.vertex_count() {
        let p = mesh.world_position(v);
        for c in [p.x, p.y, p.z] {
            out.write_all(&(c as f32).to_le_bytes())?;
        }
    }
    for f in mesh.faces() {
        out.write_all(&[3u8])?;
        for &v in f {
            out.write_all(&(v as i32).to_le_bytes())?;
        }
    }
    out.flush()
}

pub fn write_cameras_txt(path: &Path, cameras: &BTreeMap<u32, Camera>) -> std::io::Result<()> {
    let mut out = create(path)?;
    writeln!(out, "# Camera list with one line of data per camera:")?;
    writeln!(out, "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]")?;
    for (id, camera) in cameras {
        let params: Vec<String> = camera.colmap_params().iter().map(|p| format!("{p}")).collect();
        writeln!(
            out,
            "{id} {} {} {} {}",
            camera.model.colmap_name(),
            camera.width_px,
            camera.height_px,
            params.join(" ")
        )?;
    }
    out.flush()
}

/// One image entry of `images.txt`.
pub struct ImagePose {
    pub image_id: u32,
    pub camera_id: u32,
    pub name: String,
    pub cam_from_world: Rigid3,
}

pub fn write_images_txt(path: &Path, images: &[ImagePose]) -> std::io::Result<()> {
    let mut out = create(path)?;
    writeln!(out, "# Image list with two lines of data per image:")?;
    writeln!(out, "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME")?;
    writeln!(out, "#   POINTS2D[] as (X, Y, POINT3D_ID)")?;
    for image in images {
        let q = image.cam_from_world.colmap_qvec();
        let t = image.cam_from_world.translation;
        writeln!(
            out,
            "{} {} {} {} {} {} {} {} {} {}\n",
            image.image_id, q[0], q[1], q[2], q[3], t.x, t.y, t.z, image.camera_id, image.name
        )?;
    }
    out.flush()
}

pub fn write_empty_points3d_txt(path: &Path) -> std::io::Result<()> {
    let mut out = create(path)?;
    writeln!(out, "# 3D point list with one line of data per point:")?;
    out.flush()
}

/// Float32 PFM, little-endian, rows bottom to top.
pub fn write_pfm(path: &Path, width_px: usize, height_px: usize, depth_m: &[f32]) -> std::io::Result<()> {
    let mut out = create(path)?;
    write!(out, "Pf\n{width_px} {height_px}\n-1.0\n")?;
    for row in (0..height_px).rev() {
        for v in &depth_m[row * width_px..(row + 1) * width_px] {
            out.write_all(&v.to_le_bytes())?;
        }
    }
    out.flush()
}

/// Central-difference gradient magnitude.
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
