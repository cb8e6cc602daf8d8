//! A frame's input files (photo, optional depth map) read, checked and brought to the working
//! camera one way for batch registration and for the pipeline's ingest stage, with the file
//! naming and seed derivation both share, so that `asgreg register` and `asgreg run` see the
//! same frame.
//!
//! The working camera (`core::undistort`): a photo wider than the working width is averaged down
//! to it, and a photo whose camera has lens distortion is resampled to an ideal pinhole camera,
//! because renderings are ideal pinhole images. Poses are the same for both cameras.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use crate::core::camera::Camera;
use crate::core::image::Image;
use crate::core::undistort::{UndistortError, WorkingCamera};
use crate::io::images::{check_image_matches_camera, load_gray, ImageIoError};
use crate::io::pfm::{read_pfm, PfmError};

/// The working width by default: the paper's image width (505×275), at which the flow's
/// parameters were chosen; wider photos are averaged down to it.
pub const DEFAULT_WORKING_WIDTH_PX: u32 = 505;

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
    #[error("{path}: camera {camera_id} ({model}) has no working camera: {source}")]
    WorkingCamera {
        path: PathBuf,
        camera_id: u32,
        model: &'static str,
        source: UndistortError,
    },
}

/// A frame's photo and, when asked for, its depth map, both as the working camera sees them.
pub struct FrameFiles {
    /// Grey, 0..1, of `camera`'s size.
    pub photo: Image<f32>,
    /// Metres along the optical axis, holes 0 (`io::pfm`), of `camera`'s size.
    pub depth_m: Option<Image<f32>>,
    /// The camera registration uses: pinhole, at the working size.
    pub camera: Camera,
    /// How the photo's own camera became `camera` (to map estimated intrinsics back).
    pub working: Arc<WorkingCamera>,
}

/// Loads frames for one working width, building each camera's plan (resize, undistortion map)
/// once and sharing it among threads.
#[derive(Debug)]
pub struct FrameLoader {
    working_width_px: Option<u32>,
    plans: Mutex<Vec<Arc<WorkingCamera>>>,
}

impl Default for FrameLoader {
    /// The default working width ([`DEFAULT_WORKING_WIDTH_PX`]).
    fn default() -> Self {
        Self::new(Some(DEFAULT_WORKING_WIDTH_PX))
    }
}

impl FrameLoader {
    /// `working_width_px`: photos wider are averaged down to it; None keeps every photo's size.
    pub fn new(working_width_px: Option<u32>) -> Self {
        Self {
            working_width_px,
            plans: Mutex::new(Vec::new()),
        }
    }

    pub fn working_width_px(&self) -> Option<u32> {
        self.working_width_px
    }

    /// The plan for `camera` (built on first use, then shared). `image_path` and `camera_id`
    /// only name the culprit in the error.
    pub fn working_camera(
        &self,
        image_path: &Path,
        camera_id: u32,
        camera: &Camera,
    ) -> Result<Arc<WorkingCamera>, FrameFilesError> {
        // A poisoned lock only means another thread panicked while pushing a plan: the list is
        // still a valid list of plans.
        let mut plans = self
            .plans
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        if let Some(plan) = plans.iter().find(|plan| plan.source == *camera) {
            return Ok(Arc::clone(plan));
        }
        let plan = WorkingCamera::new(camera, self.working_width_px).map_err(|source| {
            FrameFilesError::WorkingCamera {
                path: image_path.to_path_buf(),
                camera_id,
                model: camera.model.colmap_name(),
                source,
            }
        })?;
        if !plan.is_identity() {
            let steps: Vec<&str> = [
                (plan.undistorted != plan.source, "undistorted"),
                (plan.working != plan.undistorted, "resized"),
            ]
            .into_iter()
            .filter_map(|(done, step)| done.then_some(step))
            .collect();
            tracing::info!(
                "camera {camera_id} ({} {}x{} px) is registered as {} {}x{} px ({})",
                camera.model.colmap_name(),
                camera.width_px,
                camera.height_px,
                plan.working.model.colmap_name(),
                plan.working.width_px,
                plan.working.height_px,
                steps.join(", "),
            );
        }
        let plan = Arc::new(plan);
        plans.push(Arc::clone(&plan));
        Ok(plan)
    }

    /// Reads the photo at `image_path` (it must have `camera`'s size) and the depth map at
    /// `depth_path`, when given (it must have the photo's size), and brings both to the working
    /// camera.
    pub fn load(
        &self,
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
        let working = self.working_camera(image_path, camera_id, camera)?;
        if working.is_identity() {
            return Ok(FrameFiles {
                photo,
                depth_m,
                camera: working.working,
                working,
            });
        }
        // Sizes were checked above; an error here would name the photo.
        let on_error = |source| FrameFilesError::WorkingCamera {
            path: image_path.to_path_buf(),
            camera_id,
            model: camera.model.colmap_name(),
            source,
        };
        let photo = working.photo(photo.view()).map_err(on_error)?;
        let depth_m = match depth_m {
            Some(depth) => Some(working.depth(depth.view()).map_err(on_error)?),
            None => None,
        };
        Ok(FrameFiles {
            photo,
            depth_m,
            camera: working.working,
            working,
        })
    }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::colmap::read_cameras_txt;

    fn brighton_camera(data: &Path, folder: &str) -> Camera {
        *read_cameras_txt(&data.join(folder).join("cameras.txt"))
            .unwrap()
            .get(&1)
            .unwrap()
    }

    /// Mean absolute difference of two images over their interior, `a` shifted by `shift_px`
    /// columns.
    fn mean_abs_difference(a: &Image<f32>, b: &Image<f32>, shift_px: usize) -> f64 {
        const MARGIN_PX: usize = 8;
        let (mut sum, mut count) = (0.0, 0usize);
        for row in MARGIN_PX..a.height_px() - MARGIN_PX {
            for col in MARGIN_PX..a.width_px() - MARGIN_PX {
                let (x, y) = (
                    a.get(col + shift_px, row).unwrap(),
                    b.get(col, row).unwrap(),
                );
                sum += f64::from((x - y).abs());
                count += 1;
            }
        }
        sum / count as f64
    }

    /// The shared Brighton Beach photos: a SIMPLE_RADIAL photo brought to its working camera at
    /// its own size is COLMAP's undistorted photo (same camera, same pixels up to JPEG and
    /// interpolation): closer to it than to itself moved by one pixel.
    #[test]
    #[ignore = "needs ../shared/data/brighton_beach (the shared data set beside the repo)"]
    fn shared_data_brighton_distorted_photo_becomes_the_undistorted_photo() {
        let data = crate::test_data::shared_data("brighton_beach");
        let distorted_camera = brighton_camera(&data, "gt_simple_radial");
        let undistorted_camera = brighton_camera(&data, "gt_undistorted");
        let loader = FrameLoader::new(None);
        let name = "DJI_0031.JPG";
        let files = loader
            .load(
                &data.join("images_distorted").join(name),
                1,
                &distorted_camera,
                None,
            )
            .unwrap();
        assert_eq!(files.camera.model, undistorted_camera.model);
        assert_eq!(
            (files.camera.width_px, files.camera.height_px),
            (undistorted_camera.width_px, undistorted_camera.height_px)
        );
        let k_difference =
            (files.camera.intrinsics.k_matrix() - undistorted_camera.intrinsics.k_matrix()).norm();
        assert!(k_difference < 1e-9, "K differs by {k_difference}");
        let reference = load_gray(&data.join("images_undistorted").join(name)).unwrap();
        assert_eq!(reference.size(), files.photo.size());
        let ours = mean_abs_difference(&files.photo, &reference, 0);
        let shifted = mean_abs_difference(&files.photo, &reference, 1);
        // The photo as it was (distortion ignored), averaged to the same size.
        let mut unremapped = Image::default();
        crate::core::undistort::resize_area(
            load_gray(&data.join("images_distorted").join(name))
                .unwrap()
                .view(),
            reference.width_px(),
            reference.height_px(),
            &mut unremapped,
        );
        let ignored = mean_abs_difference(&unremapped, &reference, 0);
        eprintln!(
            "{name}: mean |ours - COLMAP's| {ours:.4}, moved by 1 px {shifted:.4}, distortion ignored {ignored:.4}"
        );
        assert!(ours < 0.5 * shifted, "{ours} vs {shifted} for 1 px");
        assert!(
            ours < 0.5 * ignored,
            "{ours} vs {ignored} with distortion ignored"
        );
    }
}
