//! Reading a mesh file whatever its format, and the one error type of all mesh readers and writers.
//!
//! Callers (the CLI, the stages) hold a path from a config file and want a [`Mesh`]; this module
//! picks the reader from the extension so that they do not need to know PLY from OBJ. Every error
//! names the file, because a registration run loads several files and "unexpected end of data" alone
//! does not say which one is broken.

use std::path::{Path, PathBuf};

use crate::core::mesh::{Mesh, MeshError};

/// Errors of reading and writing mesh files. Every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum MeshIoError {
    #[error("{}: could not read the file: {source}", .path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: could not write the file: {source}", .path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "{}: cannot tell the mesh format from the extension {extension:?}; supported formats are {}",
        .path.display(),
        SUPPORTED_EXTENSIONS
    )]
    UnsupportedFormat { path: PathBuf, extension: String },
    /// The PLY header is malformed or asks for something this reader does not support.
    /// `line_number` counts from 1 (line 1 is `ply`).
    #[error("{}: PLY header line {line_number}: {message}", .path.display())]
    PlyHeader {
        path: PathBuf,
        line_number: usize,
        message: String,
    },
    /// The PLY data does not match its header: it ends early, or a value is not what the header
    /// promised. `index` counts the element's records from 0.
    #[error("{}: PLY element '{element}' {index}: {message}", .path.display())]
    PlyData {
        path: PathBuf,
        element: String,
        index: usize,
        message: String,
    },
    /// The mesh cannot be written in the requested format.
    #[error("{}: cannot write the mesh: {message}", .path.display())]
    Unwritable { path: PathBuf, message: String },
    #[error("{}: could not parse the OBJ file: {source}", .path.display())]
    Obj {
        path: PathBuf,
        #[source]
        source: tobj::LoadError,
    },
    /// The file parsed, but its contents are not a valid triangle mesh.
    #[error("{}: {source}", .path.display())]
    Mesh {
        path: PathBuf,
        #[source]
        source: MeshError,
    },
}

impl MeshIoError {
    /// The file the error is about.
    pub fn path(&self) -> &Path {
        match self {
            Self::Read { path, .. }
            | Self::Write { path, .. }
            | Self::UnsupportedFormat { path, .. }
            | Self::PlyHeader { path, .. }
            | Self::PlyData { path, .. }
            | Self::Unwritable { path, .. }
            | Self::Obj { path, .. }
            | Self::Mesh { path, .. } => path,
        }
    }
}

/// The extensions [`read_mesh`] understands (compared case-insensitively).
pub const SUPPORTED_EXTENSIONS: &str = ".ply, .obj";

/// Reads a triangle mesh, choosing the format from the extension (case-insensitive): `.ply`
/// (ASCII or binary, see [`crate::io::ply::read_ply`]) or `.obj` (see [`crate::io::obj::read_obj`]).
pub fn read_mesh(path: &Path) -> Result<Mesh, MeshIoError> {
    let extension = path
        .extension()
        .map(|extension| extension.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    match extension.as_str() {
        "ply" => crate::io::ply::read_ply(path),
        "obj" => crate::io::obj::read_obj(path),
        _ => Err(MeshIoError::UnsupportedFormat {
            path: path.to_path_buf(),
            extension,
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::ply::{write_ply, PlyEncoding};
    use nalgebra::Vector3;

    fn triangle() -> Mesh {
        let positions = [Vector3::zeros(), Vector3::x(), Vector3::y()];
        Mesh::from_world(&positions, vec![[0, 1, 2]], None).unwrap()
    }

    #[test]
    fn extension_is_matched_case_insensitively() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("TRIANGLE.PLY");
        write_ply(&path, &triangle(), PlyEncoding::Ascii).unwrap();
        let mesh = read_mesh(&path).unwrap();
        assert_eq!(mesh.face_count(), 1);

        let obj_path = dir.path().join("triangle.Obj");
        std::fs::write(&obj_path, "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n").unwrap();
        assert_eq!(read_mesh(&obj_path).unwrap().vertex_count(), 3);
    }

    #[test]
    fn unknown_extension_lists_supported_formats() {
        let error = read_mesh(Path::new("scene/model.stl")).unwrap_err();
        let message = error.to_string();
        assert!(matches!(error, MeshIoError::UnsupportedFormat { .. }));
        assert!(message.contains("scene/model.stl"), "{message}");
        assert!(message.contains("\"stl\""), "{message}");
        assert!(message.contains(".ply, .obj"), "{message}");

        let without_extension = read_mesh(Path::new("scene/mesh")).unwrap_err();
        assert!(
            matches!(&without_extension, MeshIoError::UnsupportedFormat { extension, .. } if extension.is_empty())
        );
    }

    #[test]
    fn missing_file_names_the_file() {
        let error = read_mesh(Path::new("/nonexistent/dir/mesh.ply")).unwrap_err();
        assert!(matches!(error, MeshIoError::Read { .. }));
        assert_eq!(error.path(), Path::new("/nonexistent/dir/mesh.ply"));
        assert!(error
            .to_string()
            .starts_with("/nonexistent/dir/mesh.ply: could not read"));
    }
}
