//! A COLMAP model folder, binary or text, chosen by what is in it; and the paths the command line
//! takes for cameras and poses (a file of either format, or a model folder).
//!
//! A folder is read as a binary model when it holds `cameras.bin` and `images.bin`, otherwise as a
//! text model when it holds `cameras.txt` and `images.txt` (`points3D` is not needed for poses, so
//! it may be missing). Binary comes first, as in COLMAP (`Reconstruction::Read`). A folder with
//! only one of the two files of a format (an interrupted copy, a stray file) is refused, naming the
//! file that is missing, rather than read in the other format: which one was meant is a guess.
//! A single file is read by its extension: `.bin` binary, anything else text.
//!
//! Writing puts both formats into the folder ([`write_model_dir`]): text for people, diffs and
//! scripts, binary for COLMAP, pycolmap and the tools that read only that; with the poses only
//! they are small, and both hold the same numbers.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use nalgebra::{Quaternion, UnitQuaternion};

use crate::core::camera::Camera;
use crate::core::rigid::Rigid3;
use crate::io::colmap::{
    read_cameras_txt, read_images_txt, read_model, ColmapError, ColmapModel, ImagePose,
    CAMERAS_FILE, IMAGES_FILE,
};
use crate::io::colmap_bin::{
    read_cameras_bin, read_images_bin, read_model_bin, write_model_bin, ColmapBinError,
    CAMERAS_BIN, IMAGES_BIN,
};

/// The two encodings of a COLMAP model.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ModelFormat {
    Binary,
    Text,
}

impl ModelFormat {
    pub fn cameras_file(self) -> &'static str {
        match self {
            ModelFormat::Binary => CAMERAS_BIN,
            ModelFormat::Text => CAMERAS_FILE,
        }
    }

    pub fn images_file(self) -> &'static str {
        match self {
            ModelFormat::Binary => IMAGES_BIN,
            ModelFormat::Text => IMAGES_FILE,
        }
    }

    /// The format of a single model file, by its extension.
    pub fn of_file(path: &Path) -> Self {
        if path.extension().is_some_and(|extension| extension == "bin") {
            ModelFormat::Binary
        } else {
            ModelFormat::Text
        }
    }
}

impl std::fmt::Display for ModelFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            ModelFormat::Binary => "binary",
            ModelFormat::Text => "text",
        })
    }
}

/// Errors of finding, reading and writing a model folder.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    #[error(transparent)]
    Text(#[from] ColmapError),
    #[error(transparent)]
    Binary(#[from] ColmapBinError),
    #[error(
        "{}: no COLMAP model here (a model folder holds {CAMERAS_BIN} and {IMAGES_BIN}, or {CAMERAS_FILE} and {IMAGES_FILE}){found}; give the folder of a COLMAP model, or the files themselves",
        dir.display()
    )]
    NoModel { dir: PathBuf, found: String },
    #[error(
        "{}: incomplete {format} COLMAP model: {present} is here but {missing} is not; add {missing}, or remove {present} (the folder is then read as a {other} model if it is one)",
        dir.display()
    )]
    Incomplete {
        dir: PathBuf,
        format: ModelFormat,
        present: &'static str,
        missing: &'static str,
        other: ModelFormat,
    },
}

/// Which format the model in `dir` is in (see the module docs for the rules).
pub fn detect_model_format(dir: &Path) -> Result<ModelFormat, ModelError> {
    let has = |name: &str| dir.join(name).is_file();
    for (format, other) in [
        (ModelFormat::Binary, ModelFormat::Text),
        (ModelFormat::Text, ModelFormat::Binary),
    ] {
        let (cameras, images) = (format.cameras_file(), format.images_file());
        match (has(cameras), has(images)) {
            (true, true) => return Ok(format),
            (true, false) | (false, true) => {
                let (present, missing) = if has(cameras) {
                    (cameras, images)
                } else {
                    (images, cameras)
                };
                return Err(ModelError::Incomplete {
                    dir: dir.to_path_buf(),
                    format,
                    present,
                    missing,
                    other,
                });
            }
            (false, false) => {}
        }
    }
    let found = match std::fs::read_dir(dir) {
        Err(error) => format!(" ({error})"),
        Ok(entries) => {
            let mut names: Vec<String> = entries
                .filter_map(|entry| entry.ok())
                .map(|entry| entry.file_name().to_string_lossy().into_owned())
                .collect();
            names.sort();
            let shown = names.len().min(8);
            let more = if names.len() > shown { ", …" } else { "" };
            if names.is_empty() {
                "; the folder is empty".to_string()
            } else {
                format!("; it holds {}{more}", names[..shown].join(", "))
            }
        }
    };
    Err(ModelError::NoModel {
        dir: dir.to_path_buf(),
        found,
    })
}

/// Reads the cameras and poses of the model in `dir`, binary or text, and says which it was.
pub fn read_model_dir(dir: &Path) -> Result<(ColmapModel, ModelFormat), ModelError> {
    let format = detect_model_format(dir)?;
    let model = match format {
        ModelFormat::Binary => read_model_bin(dir)?,
        ModelFormat::Text => read_model(dir)?,
    };
    Ok((model, format))
}

/// The cameras file `path` names: the path itself when it is no folder, else the folder's
/// `cameras.bin` or `cameras.txt` by [`detect_model_format`].
pub fn cameras_file_at(path: &Path) -> Result<PathBuf, ModelError> {
    if path.is_dir() {
        Ok(path.join(detect_model_format(path)?.cameras_file()))
    } else {
        Ok(path.to_path_buf())
    }
}

/// The images file `path` names, like [`cameras_file_at`].
pub fn images_file_at(path: &Path) -> Result<PathBuf, ModelError> {
    if path.is_dir() {
        Ok(path.join(detect_model_format(path)?.images_file()))
    } else {
        Ok(path.to_path_buf())
    }
}

/// Reads cameras from a `cameras.bin`/`cameras.txt` file or a model folder; returns them with the
/// file they came from.
pub fn read_cameras_at(path: &Path) -> Result<(BTreeMap<u32, Camera>, PathBuf), ModelError> {
    let file = cameras_file_at(path)?;
    let cameras = match ModelFormat::of_file(&file) {
        ModelFormat::Binary => read_cameras_bin(&file)?,
        ModelFormat::Text => read_cameras_txt(&file)?,
    };
    Ok((cameras, file))
}

/// Reads image poses from an `images.bin`/`images.txt` file or a model folder; returns them with
/// the file they came from.
pub fn read_images_at(path: &Path) -> Result<(Vec<ImagePose>, PathBuf), ModelError> {
    let file = images_file_at(path)?;
    let images = match ModelFormat::of_file(&file) {
        ModelFormat::Binary => read_images_bin(&file)?,
        ModelFormat::Text => read_images_txt(&file)?,
    };
    Ok((images, file))
}

/// Writes the model into `dir` (which must exist) in both formats: `cameras.txt`, `images.txt`,
/// `points3D.txt` and `cameras.bin`, `images.bin`, `points3D.bin` (no observations, no points).
/// Quaternions are written with `QW >= 0` in both, so the two hold the same numbers.
pub fn write_model_dir(dir: &Path, model: &ColmapModel) -> Result<(), ModelError> {
    let mut canonical = model.clone();
    for image in &mut canonical.images {
        // A sign flip of a unit quaternion is one.
        let [w, x, y, z] = image.cam_from_world.colmap_qvec();
        image.cam_from_world = Rigid3::new(
            UnitQuaternion::new_unchecked(Quaternion::new(w, x, y, z)),
            image.cam_from_world.translation,
        );
    }
    canonical.write_model(dir)?;
    write_model_bin(dir, &canonical)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::colmap::POINTS3D_FILE;
    use crate::io::colmap_bin::POINTS3D_BIN;

    fn brighton_model() -> ColmapModel {
        read_model(&crate::test_data::repo_data(
            "brighton_beach/gt_simple_radial",
        ))
        .unwrap()
    }

    #[test]
    fn both_formats_are_written_and_binary_is_read_first() {
        let model = brighton_model();
        let dir = tempfile::tempdir().unwrap();
        write_model_dir(dir.path(), &model).unwrap();
        for name in [
            CAMERAS_FILE,
            IMAGES_FILE,
            POINTS3D_FILE,
            CAMERAS_BIN,
            IMAGES_BIN,
            POINTS3D_BIN,
        ] {
            assert!(dir.path().join(name).is_file(), "{name}");
        }
        let (binary, format) = read_model_dir(dir.path()).unwrap();
        assert_eq!(format, ModelFormat::Binary);
        // The Brighton Beach quaternions have QW < 0: written with QW >= 0 in both formats, the
        // same rotations, and the two files hold identical numbers.
        assert!(model
            .images
            .iter()
            .any(|i| i.cam_from_world.rotation.w < 0.0));
        let text = read_model(dir.path()).unwrap();
        assert_eq!(binary, text);
        for (read, original) in binary.images.iter().zip(&model.images) {
            assert!(read.cam_from_world.rotation.w >= 0.0);
            assert_eq!(
                read.cam_from_world.translation,
                original.cam_from_world.translation
            );
            assert!(
                read.cam_from_world
                    .rotation_angle_to_rad(&original.cam_from_world)
                    < 1e-15
            );
        }
        assert_eq!(binary.cameras, model.cameras);

        // Without the binary files the text model is read.
        std::fs::remove_file(dir.path().join(CAMERAS_BIN)).unwrap();
        std::fs::remove_file(dir.path().join(IMAGES_BIN)).unwrap();
        let (again, format) = read_model_dir(dir.path()).unwrap();
        assert_eq!(format, ModelFormat::Text);
        assert_eq!(again, text);
    }

    #[test]
    fn files_and_folders_are_both_accepted() {
        let model = brighton_model();
        let dir = tempfile::tempdir().unwrap();
        write_model_dir(dir.path(), &model).unwrap();
        let (cameras, file) = read_cameras_at(dir.path()).unwrap();
        assert_eq!(file, dir.path().join(CAMERAS_BIN));
        assert_eq!(cameras, model.cameras);
        let (images, file) = read_images_at(dir.path()).unwrap();
        assert_eq!(file, dir.path().join(IMAGES_BIN));
        for path in [dir.path().join(IMAGES_FILE), dir.path().join(IMAGES_BIN)] {
            let (from_file, file) = read_images_at(&path).unwrap();
            assert_eq!(file, path);
            assert_eq!(from_file, images);
        }
        let (from_text, _) = read_cameras_at(&dir.path().join(CAMERAS_FILE)).unwrap();
        assert_eq!(from_text, cameras);
        // A missing file names itself.
        let missing = dir.path().join("nothing.bin");
        let message = read_images_at(&missing).unwrap_err().to_string();
        assert!(message.contains("nothing.bin"), "{message}");
    }

    #[test]
    fn incomplete_or_missing_models_are_refused_saying_what_to_do() {
        let model = brighton_model();
        let dir = tempfile::tempdir().unwrap();
        let message = read_model_dir(dir.path()).unwrap_err().to_string();
        println!("{message}");
        assert!(message.contains("no COLMAP model here"), "{message}");
        assert!(message.contains("the folder is empty"), "{message}");

        std::fs::write(dir.path().join("notes.md"), "x").unwrap();
        let message = read_cameras_at(dir.path()).unwrap_err().to_string();
        assert!(message.contains("it holds notes.md"), "{message}");

        write_model_dir(dir.path(), &model).unwrap();
        // A stray images.bin beside a complete text model: refused, not guessed.
        std::fs::remove_file(dir.path().join(CAMERAS_BIN)).unwrap();
        let message = read_model_dir(dir.path()).unwrap_err().to_string();
        println!("{message}");
        assert!(
            message.contains(
                "incomplete binary COLMAP model: images.bin is here but cameras.bin is not"
            ),
            "{message}"
        );
        assert!(message.contains("read as a text model"), "{message}");
        std::fs::remove_file(dir.path().join(IMAGES_BIN)).unwrap();
        std::fs::remove_file(dir.path().join(IMAGES_FILE)).unwrap();
        let error = read_images_at(dir.path()).unwrap_err();
        assert!(matches!(error, ModelError::Incomplete { .. }), "{error}");
        assert!(error.to_string().contains("images.txt is not"), "{error}");
    }
}
