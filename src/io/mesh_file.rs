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
    #[error("{}: could not parse the OBJ file at line {line}: {source}", .path.display())]
    Obj {
        path: PathBuf,
        /// The line the parser stopped at.
        line: usize,
        #[source]
        source: tobj::LoadError,
    },
    /// Loading the mesh would take more memory than the limit the user gave.
    #[error(
        "{}: the mesh needs about {needed_mib} MiB to load ({what}), more than the limit of {limit_mib} MiB; simplify or tile the mesh, or raise the limit (--max-mesh-mib, or max_mesh_mib in a pipeline config)",
        .path.display()
    )]
    TooLarge {
        path: PathBuf,
        needed_mib: u64,
        limit_mib: u64,
        what: String,
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
            | Self::TooLarge { path, .. }
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

/// Bytes loading a PLY takes per declared vertex: f64 positions while reading (24), the mesh's
/// f32 local positions (12), normals while reading and in the mesh (2 × 12).
const PLY_BYTES_PER_VERTEX: u64 = 60;
/// Bytes per declared face: one triangle's indices (12); polygons take more.
const PLY_BYTES_PER_FACE: u64 = 12;
/// Bytes loading an OBJ takes per byte of the file (it has no header to count from): tobj's
/// arrays and ours, for the usual ~40-byte vertex and ~30-byte face lines, come to about twice
/// the file; three leaves room.
const OBJ_BYTES_PER_FILE_BYTE: u64 = 3;

/// Estimates, before loading, the memory a mesh file will take (the file's bytes, which the PLY
/// reader holds, plus its vertices and faces as the header declares them; for OBJ, from the file
/// size) and refuses a file above `limit_mib`. Cheap: reads the PLY header only.
pub fn check_mesh_fits(path: &Path, limit_mib: u64) -> Result<(), MeshIoError> {
    let file_bytes = std::fs::metadata(path)
        .map_err(|source| MeshIoError::Read {
            path: path.to_path_buf(),
            source,
        })?
        .len();
    let extension = path
        .extension()
        .map(|extension| extension.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    let (needed_bytes, what) = match extension.as_str() {
        "ply" => {
            let (vertices, faces) = crate::io::ply::read_ply_counts(path)?;
            let needed = file_bytes
                .saturating_add(vertices.saturating_mul(PLY_BYTES_PER_VERTEX))
                .saturating_add(faces.saturating_mul(PLY_BYTES_PER_FACE));
            (
                needed,
                format!(
                    "{vertices} vertices and {faces} faces in its header, a {file_bytes}-byte file"
                ),
            )
        }
        "obj" => (
            file_bytes.saturating_mul(OBJ_BYTES_PER_FILE_BYTE),
            format!("estimated from the {file_bytes}-byte OBJ file"),
        ),
        _ => {
            return Err(MeshIoError::UnsupportedFormat {
                path: path.to_path_buf(),
                extension,
            })
        }
    };
    let needed_mib = needed_bytes.div_ceil(1 << 20);
    if needed_mib > limit_mib {
        return Err(MeshIoError::TooLarge {
            path: path.to_path_buf(),
            needed_mib,
            limit_mib,
            what,
        });
    }
    Ok(())
}

/// [`read_mesh`], after [`check_mesh_fits`] when a limit is given.
pub fn read_mesh_within(path: &Path, limit_mib: Option<u64>) -> Result<Mesh, MeshIoError> {
    if let Some(limit_mib) = limit_mib {
        check_mesh_fits(path, limit_mib)?;
    }
    read_mesh(path)
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

    /// A header claiming 10^8 vertices is refused against a 100 MiB limit from its first lines,
    /// without reading the (absent) data; a real small mesh fits.
    #[test]
    fn a_mesh_above_the_memory_limit_is_refused_from_its_header() {
        let dir = tempfile::tempdir().unwrap();
        let big = dir.path().join("big.ply");
        std::fs::write(
            &big,
            "ply\nformat binary_little_endian 1.0\nelement vertex 100000000\nproperty float x\n\
             property float y\nproperty float z\nelement face 200000000\n\
             property list uchar int vertex_indices\nend_header\n",
        )
        .unwrap();
        let error = read_mesh_within(&big, Some(100)).unwrap_err();
        let message = error.to_string();
        assert!(
            matches!(
                error,
                MeshIoError::TooLarge {
                    needed_mib: 8011,
                    limit_mib: 100,
                    ..
                }
            ),
            "{message}"
        );
        assert!(
            message.starts_with(&format!("{}: the mesh needs about 8011 MiB", big.display())),
            "{message}"
        );
        assert!(
            message.contains("100000000 vertices and 200000000 faces"),
            "{message}"
        );
        assert!(!message.contains('\n'), "one line: {message}");

        let small = dir.path().join("small.ply");
        write_ply(&small, &triangle(), PlyEncoding::BinaryLittleEndian).unwrap();
        assert_eq!(read_mesh_within(&small, Some(1)).unwrap().face_count(), 1);
        let obj = dir.path().join("big.obj");
        std::fs::write(&obj, vec![b'#'; 3 << 20]).unwrap();
        assert!(matches!(
            check_mesh_fits(&obj, 8),
            Err(MeshIoError::TooLarge { needed_mib: 9, .. })
        ));
    }
}
