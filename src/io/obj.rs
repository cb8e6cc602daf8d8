//! Wavefront OBJ meshes, read with `tobj`, for the meshes that come out of modelling tools and
//! textured photogrammetry exports rather than as PLY.
//!
//! All objects and groups of the file are merged into one mesh, polygons are triangulated, points
//! and lines are ignored, and materials are not loaded (registration renders shading only). tobj's
//! `use_f64` feature is on, so georeferenced OBJ coordinates keep millimetres.
//!
//! Normals: OBJ gives normals per face corner (`f v//vn`), not per vertex. This reader keeps the
//! file's vertices shared (it does not use tobj's `single_index`, which would split every vertex
//! whose corners differ in normal or texture coordinate and cut the mesh apart at texture seams)
//! and keeps the normals only when they are truly per vertex: every corner that uses a vertex names
//! the same normal (to 1e-6). Otherwise — flat-shaded files, hard edges — the mesh has no vertex
//! normals and the renderer shades with face normals, which is what such a file means.

use std::path::Path;

use glam::Vec3;
use nalgebra::Vector3;

use crate::core::mesh::Mesh;
use crate::io::mesh_file::MeshIoError;

/// Two corner normals of one vertex closer than this count as the same normal.
const SAME_NORMAL_TOLERANCE: f32 = 1e-6;

/// Reads a triangle mesh from a Wavefront OBJ file (all objects merged; see the module comment for
/// how normals are treated). A file without faces is an error
/// ([`crate::core::mesh::MeshError::NoFaces`]).
pub fn read_obj(path: &Path) -> Result<Mesh, MeshIoError> {
    let file = std::fs::File::open(path).map_err(|source| MeshIoError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    // These are all of tobj's options without its `merging` and `reordering` features.
    let options = tobj::LoadOptions {
        triangulate: true,
        single_index: false,
        ignore_points: true,
        ignore_lines: true,
    };
    // Materials are not needed: the loader declines every .mtl file without touching the disk.
    // tobj reads the file line by line and stops at the line it cannot parse: counting the lines
    // it consumed names that line in the error (tobj's own errors do not).
    let mut reader = LineCounter::new(std::io::BufReader::new(file));
    let (models, _materials) = tobj::load_obj_buf(&mut reader, &options, |_material_path| {
        Err(tobj::LoadError::OpenFileFailed)
    })
    .map_err(|source| MeshIoError::Obj {
        path: path.to_path_buf(),
        line: reader.line(),
        source,
    })?;

    let mut positions_m: Vec<Vector3<f64>> = Vec::new();
    let mut faces: Vec<[u32; 3]> = Vec::new();
    let mut corner_normals = CornerNormals::default();
    for model in &models {
        let mesh = &model.mesh;
        // tobj indexes with u32 as we do; a file with more vertices could not be held in memory.
        let first_vertex = positions_m.len() as u32;
        positions_m.extend(
            mesh.positions
                .chunks_exact(3)
                .map(|xyz| Vector3::new(xyz[0], xyz[1], xyz[2])),
        );
        faces.extend(
            mesh.indices
                .chunks_exact(3)
                .map(|corners| [corners[0], corners[1], corners[2]].map(|v| v + first_vertex)),
        );
        corner_normals.add_model(mesh, first_vertex as usize, positions_m.len());
    }
    let vertex_normals = corner_normals.into_vertex_normals(path);
    Mesh::from_world_owned(positions_m, faces, vertex_normals).map_err(|source| MeshIoError::Mesh {
        path: path.to_path_buf(),
        source,
    })
}

/// A reader that counts the lines its consumer has consumed, so that a parser that stops at a
/// line can be told which one.
struct LineCounter<R> {
    inner: R,
    newlines: usize,
    last_byte: Option<u8>,
}

impl<R> LineCounter<R> {
    fn new(inner: R) -> Self {
        Self {
            inner,
            newlines: 0,
            last_byte: None,
        }
    }

    /// The (1-based) line of the last byte consumed: the line a line-by-line parser stopped at.
    fn line(&self) -> usize {
        self.newlines + 1 - usize::from(self.last_byte == Some(b'\n'))
    }
}

impl<R: std::io::BufRead> std::io::Read for LineCounter<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let available = std::io::BufRead::fill_buf(self)?;
        let count = available.len().min(buf.len());
        buf[..count].copy_from_slice(&available[..count]);
        std::io::BufRead::consume(self, count);
        Ok(count)
    }
}

impl<R: std::io::BufRead> std::io::BufRead for LineCounter<R> {
    fn fill_buf(&mut self) -> std::io::Result<&[u8]> {
        self.inner.fill_buf()
    }

    fn consume(&mut self, amount: usize) {
        if let Ok(available) = self.inner.fill_buf() {
            let consumed = &available[..amount.min(available.len())];
            self.newlines += consumed.iter().filter(|&&byte| byte == b'\n').count();
            if let Some(&last) = consumed.last() {
                self.last_byte = Some(last);
            }
        }
        self.inner.consume(amount);
    }
}

/// Collects the normal of every vertex from the face corners that use it, and notices when the
/// normals are not per vertex.
#[derive(Default)]
struct CornerNormals {
    per_vertex: Vec<Option<Vec3>>,
    /// Why the normals cannot be used, once that is known.
    unusable_because: Option<&'static str>,
}

impl CornerNormals {
    fn add_model(&mut self, mesh: &tobj::Mesh, first_vertex: usize, vertex_count: usize) {
        if self.unusable_because.is_some() {
            return;
        }
        if mesh.normals.is_empty() || mesh.normal_indices.len() != mesh.indices.len() {
            self.unusable_because = Some("some faces have no normals");
            return;
        }
        self.per_vertex.resize(vertex_count, None);
        for (&vertex_index, &normal_index) in mesh.indices.iter().zip(&mesh.normal_indices) {
            let normal_start = normal_index as usize * 3;
            let Some(xyz) = mesh.normals.get(normal_start..normal_start + 3) else {
                self.unusable_because = Some("a face refers to a missing normal");
                return;
            };
            let normal = Vec3::new(xyz[0] as f32, xyz[1] as f32, xyz[2] as f32);
            match &mut self.per_vertex[first_vertex + vertex_index as usize] {
                slot @ None => *slot = Some(normal),
                Some(known) if (*known - normal).length() <= SAME_NORMAL_TOLERANCE => {}
                Some(_) => {
                    self.unusable_because =
                        Some("the normals are per face corner (a vertex has several)");
                    return;
                }
            }
        }
    }

    fn into_vertex_normals(self, path: &Path) -> Option<Vec<Vec3>> {
        if let Some(reason) = self.unusable_because {
            tracing::debug!(
                "{}: vertex normals not used ({reason}); faces will be shaded flat",
                path.display()
            );
            return None;
        }
        // Every vertex tobj keeps is used by a face, so every vertex has a normal.
        self.per_vertex.into_iter().collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::mesh::MeshError;

    fn write_obj(dir: &tempfile::TempDir, name: &str, contents: &str) -> std::path::PathBuf {
        let path = dir.path().join(name);
        std::fs::write(&path, contents).unwrap();
        path
    }

    const CUBE_VERTICES: &str = "v -1 -1 -1\nv 1 -1 -1\nv -1 1 -1\nv 1 1 -1\n\
                                 v -1 -1 1\nv 1 -1 1\nv -1 1 1\nv 1 1 1\n";

    /// The corner at vertex `v` (0-based) of the cube above.
    fn corner(v: usize) -> Vector3<f64> {
        Vector3::new(
            if v & 1 == 0 { -1.0 } else { 1.0 },
            if v & 2 == 0 { -1.0 } else { 1.0 },
            if v & 4 == 0 { -1.0 } else { 1.0 },
        )
    }

    fn assert_cube_is_closed_and_outward(mesh: &Mesh) {
        assert_eq!(mesh.vertex_count(), 8);
        assert_eq!(mesh.face_count(), 12);
        let mut positions: Vec<[i64; 3]> = (0..8)
            .map(|v| mesh.world_position(v).map(|c| c.round() as i64).into())
            .collect();
        positions.sort_unstable();
        let mut expected: Vec<[i64; 3]> =
            (0..8).map(|v| corner(v).map(|c| c as i64).into()).collect();
        expected.sort_unstable();
        assert_eq!(positions, expected);
        for face_index in 0..mesh.face_count() {
            let centroid: Vec3 = mesh.faces()[face_index]
                .iter()
                .map(|&v| mesh.positions_local_m()[v as usize])
                .sum::<Vec3>()
                / 3.0;
            assert!(
                mesh.face_normal(face_index).dot(centroid) > 0.0,
                "face {face_index} points inward"
            );
        }
    }

    #[test]
    fn smooth_cube_with_quads_keeps_vertex_normals() {
        // Normals per vertex: `vn` k belongs to `v` k.
        let mut contents = format!("# smooth cube\nmtllib cube.mtl\no Cube\n{CUBE_VERTICES}");
        for v in 0..8 {
            let n = corner(v).normalize();
            contents += &format!("vn {} {} {}\n", n.x, n.y, n.z);
        }
        contents += "usemtl none\ns 1\n";
        for q in [
            [1, 3, 4, 2],
            [5, 6, 8, 7],
            [1, 2, 6, 5],
            [3, 7, 8, 4],
            [1, 5, 7, 3],
            [2, 4, 8, 6],
        ] {
            contents += &format!(
                "f {a}//{a} {b}//{b} {c}//{c} {d}//{d}\n",
                a = q[0],
                b = q[1],
                c = q[2],
                d = q[3]
            );
        }
        let dir = tempfile::tempdir().unwrap();
        let mesh = read_obj(&write_obj(&dir, "smooth_cube.obj", &contents)).unwrap();
        assert_cube_is_closed_and_outward(&mesh);
        let normals = mesh.vertex_normals().expect("per-vertex normals are kept");
        for (vertex_index, normal) in normals.iter().enumerate() {
            let position = mesh.world_position(vertex_index);
            let expected =
                Vec3::new(position.x as f32, position.y as f32, position.z as f32).normalize();
            assert!(
                (*normal - expected).length() < 1e-6,
                "vertex {vertex_index}: {normal}"
            );
        }
    }

    #[test]
    fn flat_cube_in_two_groups_is_merged_without_normals() {
        let contents = format!(
            "{CUBE_VERTICES}vn 0 0 -1\nvn 0 0 1\nvn 0 -1 0\nvn 0 1 0\nvn -1 0 0\nvn 1 0 0\n\
             g bottom_and_top\nf 1//1 3//1 4//1 2//1\nf 5//2 6//2 8//2 7//2\n\
             g sides\nf 1//3 2//3 6//3 5//3\nf 3//4 7//4 8//4 4//4\n\
             f 1//5 5//5 7//5 3//5\nf 2//6 4//6 8//6 6//6\n"
        );
        let dir = tempfile::tempdir().unwrap();
        let mesh = read_obj(&write_obj(&dir, "flat_cube.obj", &contents)).unwrap();
        // Vertices shared by both groups appear once per group.
        assert_eq!(mesh.face_count(), 12);
        assert_eq!(mesh.vertex_count(), 8 + 8);
        assert!(mesh.vertex_normals().is_none());
    }

    #[test]
    fn cube_without_normals_keeps_its_eight_vertices() {
        let contents = format!(
            "{CUBE_VERTICES}f 1 3 4 2\nf 5 6 8 7\nf 1 2 6 5\nf 3 7 8 4\nf 1 5 7 3\nf 2 4 8 6\n"
        );
        let dir = tempfile::tempdir().unwrap();
        let mesh = read_obj(&write_obj(&dir, "cube.obj", &contents)).unwrap();
        assert_cube_is_closed_and_outward(&mesh);
        assert!(mesh.vertex_normals().is_none());
    }

    #[test]
    fn georeferenced_obj_keeps_millimetres() {
        let contents = "v 512345.001 5401234.002 250.003\nv 512346.004 5401234.005 250.006\n\
                        v 512345.007 5401235.008 250.009\nf 1 2 3\n";
        let dir = tempfile::tempdir().unwrap();
        let mesh = read_obj(&write_obj(&dir, "utm.obj", contents)).unwrap();
        let expected = Vector3::new(512_346.004, 5_401_234.005, 250.006);
        assert!((mesh.world_position(1) - expected).norm() < 1e-3);
    }

    #[test]
    fn missing_file_names_the_file() {
        let error = read_obj(Path::new("/nonexistent/model.obj")).unwrap_err();
        assert!(matches!(error, MeshIoError::Read { .. }), "{error:?}");
        assert!(error
            .to_string()
            .starts_with("/nonexistent/model.obj: could not read the file"));
    }

    #[test]
    fn obj_without_faces_is_no_mesh() {
        let dir = tempfile::tempdir().unwrap();
        let path = write_obj(
            &dir,
            "points.obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\np 1 2 3\nl 1 2\n",
        );
        let error = read_obj(&path).unwrap_err();
        assert!(
            matches!(
                error,
                MeshIoError::Mesh {
                    source: MeshError::NoFaces,
                    ..
                }
            ),
            "{error:?}"
        );
        assert!(error.to_string().ends_with("points.obj: the mesh has no faces (a point cloud cannot be rendered); give a triangle mesh"));
    }

    #[test]
    fn malformed_obj_names_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = write_obj(&dir, "broken.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n");
        let error = read_obj(&path).unwrap_err();
        assert!(matches!(error, MeshIoError::Obj { .. }), "{error:?}");
        let message = error.to_string();
        assert!(
            message.contains("broken.obj: could not parse the OBJ file at line 4: "),
            "{message}"
        );
        assert!(message.contains("out of bounds"), "{message}");
        // A bad line in the middle is named, not the last line read ahead.
        let path = write_obj(
            &dir,
            "middle.obj",
            "v 0 0 0\nv 1 zero 0\nv 0 1 0\nf 1 2 3\nf 1 3 2\n",
        );
        let message = read_obj(&path).unwrap_err().to_string();
        assert!(
            message.contains("middle.obj: could not parse the OBJ file at line 2: "),
            "{message}"
        );
    }
}
