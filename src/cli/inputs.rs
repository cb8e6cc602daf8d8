//! Loading the inputs several commands share (mesh, COLMAP cameras and poses, one image's pose),
//! with errors that name the file and say what to do.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{bail, Context};
use asgreg::core::camera::Camera;
use asgreg::core::mesh::Mesh;
use asgreg::io::colmap::ImagePose;
use asgreg::io::colmap_model::{read_cameras_at, read_images_at};
use asgreg::io::mesh_file::read_mesh;

/// A mesh, the cameras and the poses of a COLMAP model (text or binary).
pub struct PosedInputs {
    pub mesh: Mesh,
    pub cameras: BTreeMap<u32, Camera>,
    pub images: Vec<ImagePose>,
}

pub fn load_posed_inputs(
    mesh_path: &Path,
    cameras_path: &Path,
    poses_path: &Path,
) -> anyhow::Result<PosedInputs> {
    let started = std::time::Instant::now();
    let mesh = read_mesh(mesh_path)?;
    tracing::info!(
        "read {} ({} vertices, {} faces) in {:.0} ms",
        mesh_path.display(),
        mesh.vertex_count(),
        mesh.face_count(),
        started.elapsed().as_secs_f64() * 1e3
    );
    // Each path is a cameras/images file (.bin binary, else text) or a model folder.
    let (cameras, cameras_file) = read_cameras_at(cameras_path)?;
    let (images, images_file) = read_images_at(poses_path)?;
    tracing::info!(
        "read {} cameras from {} and {} poses from {}",
        cameras.len(),
        cameras_file.display(),
        images.len(),
        images_file.display()
    );
    Ok(PosedInputs {
        mesh,
        cameras,
        images,
    })
}

impl PosedInputs {
    /// The pose and camera of the image called `name` (the NAME column of images.txt; a path's
    /// file name also matches).
    pub fn find_image(
        &self,
        name: &str,
        poses_path: &Path,
        cameras_path: &Path,
    ) -> anyhow::Result<(&ImagePose, &Camera)> {
        let file_name = Path::new(name)
            .file_name()
            .map(|f| f.to_string_lossy().into_owned())
            .unwrap_or_else(|| name.to_string());
        let image = self
            .images
            .iter()
            .find(|image| image.name == name)
            .or_else(|| {
                self.images.iter().find(|image| {
                    Path::new(&image.name)
                        .file_name()
                        .is_some_and(|f| f.to_string_lossy() == file_name)
                })
            });
        let Some(image) = image else {
            let known: Vec<&str> = self
                .images
                .iter()
                .take(5)
                .map(|i| i.name.as_str())
                .collect();
            bail!(
                "image '{name}' is not listed in {} ({} images, e.g. {}); pass a name from its NAME column",
                poses_path.display(),
                self.images.len(),
                known.join(", ")
            );
        };
        let camera = self.cameras.get(&image.camera_id).with_context(|| {
            format!(
                "image '{}' in {} uses camera {}, which {} does not define",
                image.name,
                poses_path.display(),
                image.camera_id,
                cameras_path.display()
            )
        })?;
        if !matches!(camera.distortion, asgreg::core::camera::Distortion::None) {
            tracing::warn!(
                "camera {} is {} with lens distortion; renderings are ideal pinhole images, so undistort the photo for an exact match",
                image.camera_id,
                camera.model.colmap_name()
            );
        }
        Ok((image, camera))
    }
}
