//! A frame's input files (photo, optional depth map) read and checked one way for batch
//! registration and for the pipeline's ingest stage, with the file naming and seed derivation
//! both share, so that `asgreg register` and `asgreg run` see the same frame.

use std::path::{Path, PathBuf};

use crate::core::camera::Camera;
use crate::core::image::Image;
use crate::io::images::{check_image_matches_camera, load_gray, ImageIoError};
use crate::io::pfm::{read_pfm, PfmError};

/// Why a frame's files cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum FrameFilesError {
    #[error(transparent)]
    Image(#[from] ImageIoError),
    #[error(transparent)]
    Depth(#[from] PfmError),
    #[error("{path}: depth map is {depth_width_px}×{depth_height_px} px but the photo is {photo_width_px}×{photo_height_px} px")]
    DepthSize {
        path: PathBuf,
        depth_width_px: usize,
        depth_height_px: usize,
        photo_width_px: usize,
        photo_height_px: usize,
    },
}

/// A frame's photo and, when asked for, its depth map of the same size.
pub struct FrameFiles {
    /// Grey, 0..1.
    pub photo: Image<f32>,
    /// Metres along the optical axis, holes 0 (`io::pfm`).
    pub depth_m: Option<Image<f32>>,
}

/// Reads the photo at `image_path` (it must have `camera`'s size) and the depth map at
/// `depth_path`, when given (it must have the photo's size).
pub fn load_frame_files(
    image_path: &Path,
    camera_id: u32,
    camera: &Camera,
    depth_path: Option<&Path>,
) -> Result<FrameFiles, FrameFilesError> {
    let photo = load_gray(image_path)?;
    check_image_matches_camera(
        image_path,
        photo.width_px(),
        photo.height_px(),
        camera_id,
        camera,
    )?;
    let depth_m = match depth_path {
        Some(path) => {
            let depth = read_pfm(path)?;
            if depth.size() != photo.size() {
                return Err(FrameFilesError::DepthSize {
                    path: path.to_path_buf(),
                    depth_width_px: depth.width_px(),
                    depth_height_px: depth.height_px(),
                    photo_width_px: photo.width_px(),
                    photo_height_px: photo.height_px(),
                });
            }
            Some(depth)
        }
        None => None,
    };
    Ok(FrameFiles { photo, depth_m })
}

/// The frame's depth file in `depth_dir`: `<stem of the image name>.pfm`.
pub fn depth_path_for(depth_dir: &Path, image_name: &str) -> PathBuf {
    let stem = Path::new(image_name)
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| image_name.to_string());
    depth_dir.join(format!("{stem}.pfm"))
}

/// The seed of a frame: one derivation for batch registration and the pipeline, so `asgreg
/// register` and `asgreg run` give the same result for the same seed.
pub fn frame_seed(seed: u64, image_id: u32) -> u64 {
    seed ^ u64::from(image_id).wrapping_mul(0x9E37_79B9_7F4A_7C15)
}
