//! Stage "ingest": turns a folder of photos with COLMAP poses into Frame messages, one per image
//! listed in images.txt, in that order. A frame whose inputs are unusable becomes a FrameFailed
//! naming the file, so that it still gets its one result. A restarted ingest passes over the
//! frames that already have theirs (`next_frame_except`).

use std::borrow::Cow;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::batch::BatchFrame;
use crate::core::camera::Camera;
use crate::core::frame::IntrinsicsMode;
use crate::core::image::Image;
use crate::frame_files::{depth_path_for, frame_seed, FrameLoader};
use crate::io::colmap::ImagePose;
use crate::io::colmap_model::{read_cameras_at, read_images_at, ModelError};
use crate::msg::{Frame, FrameFailed, FrameInfo};

/// Where the frames come from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SourceConfig {
    /// Folder of the photos (names as in images.txt).
    pub images: PathBuf,
    /// The photos' cameras: a COLMAP `cameras.txt` or `cameras.bin`, or a model folder.
    pub cameras: PathBuf,
    /// The initial (GPS/IMU) poses: a COLMAP `images.txt` or `images.bin`, or a model folder.
    pub poses: PathBuf,
    /// Folder of depth maps (`<image stem>.pfm`): the change stage's photo depth, and the
    /// depth-ASG query when `registration.query_mode` asks for it.
    pub depth: Option<PathBuf>,
    /// True (the default, as `register --intrinsics known`): the cameras file is the
    /// calibration, trusted (EPnP). False: the intrinsics are estimated (DLT) per frame. A
    /// config that left it out estimated them while `register` trusted the same file (block
    /// seed 1, 48 frames: 30 accepted against `register`'s 46).
    pub intrinsics_known: bool,
    /// Frames per second to emit; 0 = as fast as the pipeline takes them.
    pub rate_hz: f64,
    /// Stop after this many frames (0 = all).
    pub max_frames: usize,
    /// Seed of every frame's random choices (combined with the image id); 1 by default, as
    /// `register` and `eval` (a config that left it out ran with 0, so `run` and `register`
    /// registered the same photos with other draws: house s1, 5 of 48 frames decided otherwise).
    pub seed: u64,
}

impl Default for SourceConfig {
    fn default() -> Self {
        Self {
            images: PathBuf::new(),
            cameras: PathBuf::new(),
            poses: PathBuf::new(),
            depth: None,
            intrinsics_known: true,
            rate_hz: 0.0,
            max_frames: 0,
            seed: 1,
        }
    }
}

impl SourceConfig {
    /// A scene folder as `asgreg synth` writes it, with the initial poses of `level_px`.
    pub fn scene(scene: &Path, level_px: u32) -> Self {
        Self {
            images: scene.join("images"),
            cameras: scene.join("gt").join("cameras.txt"),
            poses: scene
                .join("initial")
                .join(level_px.to_string())
                .join("images.txt"),
            intrinsics_known: true,
            ..Self::default()
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    #[error(transparent)]
    Model(Box<ModelError>),
    #[error("{poses}: image '{name}' uses camera {camera_id}, which {cameras} does not define")]
    UnknownCamera {
        poses: PathBuf,
        cameras: PathBuf,
        name: String,
        camera_id: u32,
    },
    #[error("{poses}: lists no images; nothing to register")]
    NoImages { poses: PathBuf },
}

impl From<ModelError> for SourceError {
    fn from(error: ModelError) -> Self {
        // Boxed: a model error is large and a source error travels up through every stage's
        // `Result`.
        Self::Model(Box::new(error))
    }
}

/// A folder source: the list is read up front, each photo when its frame is emitted.
pub struct FolderSource {
    config: SourceConfig,
    cameras: BTreeMap<u32, Camera>,
    images: Vec<ImagePose>,
    next: usize,
    /// Brings photos to the working camera (default working width), each camera's plan once.
    loader: FrameLoader,
}

impl FolderSource {
    pub fn open(config: &SourceConfig) -> Result<Self, SourceError> {
        let (cameras, _) = read_cameras_at(&config.cameras)?;
        let (mut images, _) = read_images_at(&config.poses)?;
        if config.max_frames > 0 {
            images.truncate(config.max_frames);
        }
        if images.is_empty() {
            return Err(SourceError::NoImages {
                poses: config.poses.clone(),
            });
        }
        for image in &images {
            if !cameras.contains_key(&image.camera_id) {
                return Err(SourceError::UnknownCamera {
                    poses: config.poses.clone(),
                    cameras: config.cameras.clone(),
                    name: image.name.clone(),
                    camera_id: image.camera_id,
                });
            }
        }
        Ok(Self {
            config: config.clone(),
            cameras,
            images,
            next: 0,
            loader: FrameLoader::default(),
        })
    }

    /// Frames this source will emit.
    pub fn len(&self) -> usize {
        self.images.len()
    }

    pub fn is_empty(&self) -> bool {
        self.images.is_empty()
    }

    /// The frames this source emits, with their ids, as `register` reads them (the same photos,
    /// depth maps, cameras and initial poses): what a pipeline's results are checked against
    /// ([`crate::runtime::reference`]).
    pub fn batch_frames(&self) -> Vec<(u64, BatchFrame)> {
        self.images
            .iter()
            .enumerate()
            .filter_map(|(index, image)| {
                let camera = *self.cameras.get(&image.camera_id)?;
                Some((
                    index as u64,
                    BatchFrame {
                        image_id: image.image_id,
                        camera_id: image.camera_id,
                        name: image.name.clone(),
                        image_path: self.config.images.join(&image.name),
                        depth_path: self.depth_path(image),
                        camera,
                        intrinsics: IntrinsicsMode::from_known(self.config.intrinsics_known),
                        initial_cam_from_world: image.cam_from_world,
                    },
                ))
            })
            .collect()
    }

    /// The next frame (its id is its position in images.txt), or its failure; `None` at the end.
    pub fn next_frame(&mut self) -> Option<(u64, Result<Frame<'static>, FrameFailed>)> {
        let image = self.images.get(self.next)?.clone();
        let frame_id = self.next as u64;
        self.next += 1;
        Some((frame_id, self.load(&image)))
    }

    /// The next frame whose id is not in `done` (frames that already have their result: a
    /// restarted ingest resumes instead of replaying); the frames passed over are not read.
    pub fn next_frame_except(
        &mut self,
        done: &std::collections::BTreeSet<u64>,
    ) -> Option<(u64, Result<Frame<'static>, FrameFailed>)> {
        while self.next < self.images.len() && done.contains(&(self.next as u64)) {
            self.next += 1;
        }
        self.next_frame()
    }

    /// The image's depth map, when the source has a depth folder.
    fn depth_path(&self, image: &ImagePose) -> Option<PathBuf> {
        self.config
            .depth
            .as_ref()
            .map(|dir| depth_path_for(dir, &image.name))
    }

    fn load(&self, image: &ImagePose) -> Result<Frame<'static>, FrameFailed> {
        let failed = |reason: String| FrameFailed {
            name: image.name.clone(),
            stage: "ingest".to_string(),
            reason,
        };
        // Checked in `open`.
        let camera = *self
            .cameras
            .get(&image.camera_id)
            .ok_or_else(|| failed(format!("camera {} is not defined", image.camera_id)))?;
        if !image.cam_from_world.is_finite() {
            return Err(failed(format!(
                "{}: the initial pose of '{}' is not finite (NaN or infinity); fix its QW..TZ",
                self.config.poses.display(),
                image.name
            )));
        }
        let depth_path = self.depth_path(image);
        let files = self
            .loader
            .load(
                &self.config.images.join(&image.name),
                image.camera_id,
                &camera,
                depth_path.as_deref(),
            )
            .map_err(|e| failed(e.to_string()))?;
        Ok(Frame {
            info: FrameInfo {
                name: image.name.clone(),
                camera_id: image.camera_id,
                // The working camera (undistorted, at the working width): the photo's.
                camera: files.camera,
                intrinsics_known: self.config.intrinsics_known,
                initial_cam_from_world: image.cam_from_world,
                seed: frame_seed(self.config.seed, image.image_id),
            },
            image: Cow::Owned(files.photo.into_data()),
            depth_m: Cow::Owned(files.depth_m.map(Image::into_data).unwrap_or_default()),
        })
    }
}
