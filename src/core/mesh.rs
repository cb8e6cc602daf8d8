//! The triangle mesh every renderer draws, stored relative to a local origin.
//!
//! Georeferenced meshes have coordinates like (512345, 5401234, 250) m, where f32 keeps only about
//! half a metre. The mesh therefore keeps an f64 `origin_m` and f32 positions relative to it
//! (docs/design.md §6): world = origin + local. Renderers fold the origin into the pose in f64 before they
//! touch f32, so a georeferenced mesh renders exactly like the same mesh at the origin.

use glam::Vec3;
use nalgebra::Vector3;

/// Errors of mesh construction.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MeshError {
    #[error("the mesh has no faces (a point cloud cannot be rendered); give a triangle mesh")]
    NoFaces,
    #[error("face {face_index} refers to vertex {vertex_index}, but the mesh has {vertex_count} vertices")]
    IndexOutOfRange {
        face_index: usize,
        vertex_index: u32,
        vertex_count: usize,
    },
    #[error("vertex {vertex_index} has a non-finite coordinate ({value})")]
    NonFiniteVertex { vertex_index: usize, value: f64 },
    #[error("{normal_count} vertex normals for {vertex_count} vertices")]
    NormalCount {
        normal_count: usize,
        vertex_count: usize,
    },
}

/// A triangle mesh: positions relative to `origin_m`, counter-clockwise faces, optional normals,
/// and a grid of its faces ([`FaceGrid`]) so that a rendering visits only what its frustum holds.
#[derive(Clone, Debug, PartialEq)]
pub struct Mesh {
    origin_m: Vector3<f64>,
    positions_local_m: Vec<Vec3>,
    faces: Vec<[u32; 3]>,
    vertex_normals: Option<Vec<Vec3>>,
    grid: FaceGrid,
}

/// Faces per grid cell aimed at: frustum tests per cell stay negligible (10^7 faces: ~5000 cells)
/// while a city seen from one camera skips most of them.
const FACES_PER_CELL: usize = 2048;

/// Most distinct vertices in one cell, so that a cell's faces can name their corners by a `u16`
/// index into the cell's vertex list (a cell that would hold more is split into several).
const MAX_CELL_VERTICES: usize = 1 << 16;

/// The spatial index of a mesh: its faces grouped by the grid cell of their centroid (a grid over
/// the two longest extents, and the third when it is long enough), each cell with the tight box
/// of its faces' vertices in local coordinates, the list of the vertices its faces use, and its
/// faces' corners as indices into that list. The renderer tests the boxes against the frustum and
/// transforms and rasterises only the vertices and faces of cells it can see (`core::raster`), so
/// a rendering's work and scratch memory follow what the camera sees, not the mesh's size.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FaceGrid {
    cells: Vec<GridCell>,
    /// Face indices, cell after cell, ascending within a cell.
    faces: Vec<u32>,
    /// Parallel to `faces`: each face's corners as indices into its cell's vertex list.
    cell_corners: Vec<[u16; 3]>,
    /// Vertex indices, cell after cell: the distinct vertices of each cell's faces.
    vertices: Vec<u32>,
}

/// One non-empty cell of a [`FaceGrid`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GridCell {
    /// Tight box of the cell's faces' vertices, local coordinates (m).
    pub min_local_m: Vec3,
    pub max_local_m: Vec3,
    /// The cell's range in [`FaceGrid::faces`] and `cell_corners`.
    start: usize,
    end: usize,
    /// The cell's range in `FaceGrid::vertices`.
    vertex_start: usize,
    vertex_end: usize,
}

impl GridCell {
    /// Faces of the cell.
    pub fn face_count(&self) -> usize {
        self.end - self.start
    }

    /// Distinct vertices of the cell's faces.
    pub fn vertex_count(&self) -> usize {
        self.vertex_end - self.vertex_start
    }
}

impl FaceGrid {
    fn build(positions: &[Vec3], faces: &[[u32; 3]]) -> Self {
        let mut min = Vec3::splat(f32::INFINITY);
        let mut max = Vec3::splat(f32::NEG_INFINITY);
        for p in positions {
            min = min.min(*p);
            max = max.max(*p);
        }
        let extent = (max - min).max(Vec3::splat(0.0));
        let target_cells = (faces.len() / FACES_PER_CELL).clamp(1, 1 << 16) as f32;
        // Cell side from the two longest extents (a city is flat); the third axis is split too
        // when it is long enough.
        let mut sorted = extent.to_array();
        sorted.sort_by(f32::total_cmp);
        let area = (sorted[2] * sorted[1])
            .max(sorted[2] * sorted[2] * 1e-6)
            .max(f32::MIN_POSITIVE);
        let side = (area / target_cells).sqrt().max(f32::MIN_POSITIVE);
        let dims = extent
            .to_array()
            .map(|e| ((e / side).floor() as usize).clamp(1, 1 << 12));
        let cell_of = |p: Vec3| -> usize {
            let mut index = 0;
            for axis in (0..3).rev() {
                let t = if extent[axis] > 0.0 {
                    (p[axis] - min[axis]) / extent[axis]
                } else {
                    0.0
                };
                let i = ((t * dims[axis] as f32) as usize).min(dims[axis] - 1);
                index = index * dims[axis] + i;
            }
            index
        };
        let cell_count = dims[0] * dims[1] * dims[2];
        let face_cells: Vec<u32> = faces
            .iter()
            .map(|f| {
                let centroid = f
                    .iter()
                    .map(|&v| positions.get(v as usize).copied().unwrap_or(Vec3::ZERO))
                    .sum::<Vec3>()
                    / 3.0;
                cell_of(centroid) as u32
            })
            .collect();
        // Counting sort by cell, stable (face order within a cell).
        let mut starts = vec![0u32; cell_count + 1];
        for &c in &face_cells {
            starts[c as usize + 1] += 1;
        }
        for i in 0..cell_count {
            starts[i + 1] += starts[i];
        }
        let mut next = starts.clone();
        let mut sorted_faces = vec![0u32; faces.len()];
        for (face_index, &c) in face_cells.iter().enumerate() {
            sorted_faces[next[c as usize] as usize] = face_index as u32;
            next[c as usize] += 1;
        }
        drop(face_cells);
        drop(next);
        let groups = (0..cell_count)
            .filter(|&c| starts[c + 1] > starts[c])
            .map(|c| starts[c] as usize..starts[c + 1] as usize);
        Self::from_groups(positions, faces, sorted_faces, groups, None)
    }

    /// The grid of `sorted_faces` split into `groups` (consecutive ranges of it); a group whose
    /// faces use more than [`MAX_CELL_VERTICES`] vertices becomes several cells. Each cell's box
    /// is the tight box of its vertices, or `fixed_box` when given.
    fn from_groups(
        positions: &[Vec3],
        faces: &[[u32; 3]],
        sorted_faces: Vec<u32>,
        groups: impl Iterator<Item = std::ops::Range<usize>>,
        fixed_box: Option<(Vec3, Vec3)>,
    ) -> Self {
        // For each vertex, the cell that last listed it and its index in that cell's list
        // (build-time scratch, one pass over the faces).
        let mut listed_in = vec![u32::MAX; positions.len()];
        let mut listed_as = vec![0u16; positions.len()];
        let mut cells = Vec::new();
        let mut cell_corners = Vec::with_capacity(sorted_faces.len());
        let mut vertices = Vec::new();
        for group in groups {
            let mut face_position = group.start;
            while face_position < group.end {
                let cell_index = cells.len() as u32;
                let (start, vertex_start) = (face_position, vertices.len());
                let mut cell_min = Vec3::splat(f32::INFINITY);
                let mut cell_max = Vec3::splat(f32::NEG_INFINITY);
                while face_position < group.end {
                    let face = faces[sorted_faces[face_position] as usize];
                    let new_vertices = face
                        .iter()
                        .filter(|&&v| listed_in.get(v as usize) != Some(&cell_index))
                        .count();
                    if vertices.len() - vertex_start + new_vertices > MAX_CELL_VERTICES {
                        break;
                    }
                    let corners = face.map(|v| {
                        let v = v as usize;
                        if listed_in.get(v) != Some(&cell_index) {
                            if let (Some(cell), Some(local)) =
                                (listed_in.get_mut(v), listed_as.get_mut(v))
                            {
                                *cell = cell_index;
                                *local = (vertices.len() - vertex_start) as u16;
                            }
                            vertices.push(v as u32);
                            let p = positions.get(v).copied().unwrap_or(Vec3::ZERO);
                            cell_min = cell_min.min(p);
                            cell_max = cell_max.max(p);
                        }
                        listed_as.get(v).copied().unwrap_or(0)
                    });
                    cell_corners.push(corners);
                    face_position += 1;
                }
                let (min_local_m, max_local_m) = fixed_box.unwrap_or((cell_min, cell_max));
                cells.push(GridCell {
                    min_local_m,
                    max_local_m,
                    start,
                    end: face_position,
                    vertex_start,
                    vertex_end: vertices.len(),
                });
            }
        }
        Self {
            cells,
            faces: sorted_faces,
            cell_corners,
            vertices,
        }
    }

    /// The non-empty cells.
    pub fn cells(&self) -> &[GridCell] {
        &self.cells
    }

    /// The faces of `cell` (ascending face indices).
    pub fn cell_faces(&self, cell: &GridCell) -> &[u32] {
        &self.faces[cell.start..cell.end]
    }

    /// The corners of `cell`'s faces (parallel to [`Self::cell_faces`]) as indices into
    /// [`Self::cell_vertices`].
    pub fn cell_corners(&self, cell: &GridCell) -> &[[u16; 3]] {
        &self.cell_corners[cell.start..cell.end]
    }

    /// The distinct vertices of `cell`'s faces (mesh vertex indices).
    pub fn cell_vertices(&self, cell: &GridCell) -> &[u32] {
        &self.vertices[cell.vertex_start..cell.vertex_end]
    }
}

impl Mesh {
    /// Builds a mesh from world coordinates in f64; the local origin is the centre of the bounding
    /// box, so local coordinates stay small whatever the georeferencing.
    pub fn from_world(
        positions_world_m: &[Vector3<f64>],
        faces: Vec<[u32; 3]>,
        vertex_normals: Option<Vec<Vec3>>,
    ) -> Result<Self, MeshError> {
        let (origin_m, positions_local_m) = local_positions(positions_world_m)?;
        Self::from_local(origin_m, positions_local_m, faces, vertex_normals)
    }

    /// [`Self::from_world`] taking the f64 positions by value: they are freed before the face
    /// grid is built, so a city-size mesh never holds both at once (readers use this).
    pub fn from_world_owned(
        positions_world_m: Vec<Vector3<f64>>,
        faces: Vec<[u32; 3]>,
        vertex_normals: Option<Vec<Vec3>>,
    ) -> Result<Self, MeshError> {
        let (origin_m, positions_local_m) = local_positions(&positions_world_m)?;
        drop(positions_world_m);
        Self::from_local(origin_m, positions_local_m, faces, vertex_normals)
    }

    /// Builds a mesh from positions already relative to `origin_m`.
    pub fn from_local(
        origin_m: Vector3<f64>,
        positions_local_m: Vec<Vec3>,
        faces: Vec<[u32; 3]>,
        vertex_normals: Option<Vec<Vec3>>,
    ) -> Result<Self, MeshError> {
        if faces.is_empty() {
            return Err(MeshError::NoFaces);
        }
        let vertex_count = positions_local_m.len();
        for (vertex_index, p) in positions_local_m.iter().enumerate() {
            if !p.is_finite() {
                let value = f64::from(
                    p.to_array()
                        .into_iter()
                        .find(|v| !v.is_finite())
                        .unwrap_or(f32::NAN),
                );
                return Err(MeshError::NonFiniteVertex {
                    vertex_index,
                    value,
                });
            }
        }
        for (face_index, face) in faces.iter().enumerate() {
            if let Some(&vertex_index) = face.iter().find(|&&v| v as usize >= vertex_count) {
                return Err(MeshError::IndexOutOfRange {
                    face_index,
                    vertex_index,
                    vertex_count,
                });
            }
        }
        if let Some(normals) = &vertex_normals {
            if normals.len() != vertex_count {
                return Err(MeshError::NormalCount {
                    normal_count: normals.len(),
                    vertex_count,
                });
            }
        }
        let grid = FaceGrid::build(&positions_local_m, &faces);
        Ok(Self {
            origin_m,
            positions_local_m,
            faces,
            vertex_normals,
            grid,
        })
    }

    /// The f64 world position the local coordinates are relative to.
    pub fn origin_m(&self) -> Vector3<f64> {
        self.origin_m
    }

    pub fn positions_local_m(&self) -> &[Vec3] {
        &self.positions_local_m
    }

    pub fn faces(&self) -> &[[u32; 3]] {
        &self.faces
    }

    pub fn vertex_normals(&self) -> Option<&[Vec3]> {
        self.vertex_normals.as_deref()
    }

    /// The faces grouped by place, for frustum culling.
    pub fn grid(&self) -> &FaceGrid {
        &self.grid
    }

    /// The mesh with its faces in one group in index order, every cell with the whole mesh's box
    /// (nothing culled): the reference the culling's tests compare with.
    #[cfg(test)]
    pub(crate) fn with_single_grid_cell(mut self) -> Self {
        let mut min = Vec3::splat(f32::INFINITY);
        let mut max = Vec3::splat(f32::NEG_INFINITY);
        for p in &self.positions_local_m {
            min = min.min(*p);
            max = max.max(*p);
        }
        let face_count = self.faces.len();
        self.grid = FaceGrid::from_groups(
            &self.positions_local_m,
            &self.faces,
            (0..face_count as u32).collect(),
            std::iter::once(0..face_count),
            Some((min, max)),
        );
        self
    }

    pub fn vertex_count(&self) -> usize {
        self.positions_local_m.len()
    }

    pub fn face_count(&self) -> usize {
        self.faces.len()
    }

    /// A vertex in world coordinates (f64).
    pub fn world_position(&self, vertex_index: usize) -> Vector3<f64> {
        let p = self.positions_local_m[vertex_index];
        self.origin_m + Vector3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z))
    }

    /// World-coordinate bounding box `(min, max)`.
    pub fn bounds_world_m(&self) -> (Vector3<f64>, Vector3<f64>) {
        let mut min = Vec3::splat(f32::INFINITY);
        let mut max = Vec3::splat(f32::NEG_INFINITY);
        for p in &self.positions_local_m {
            min = min.min(*p);
            max = max.max(*p);
        }
        let to_world =
            |v: Vec3| self.origin_m + Vector3::new(f64::from(v.x), f64::from(v.y), f64::from(v.z));
        (to_world(min), to_world(max))
    }

    /// Unit normal of a face (counter-clockwise winding, right hand), in the world frame's axes.
    /// Zero for a degenerate face.
    pub fn face_normal(&self, face_index: usize) -> Vec3 {
        let [a, b, c] = self.faces[face_index].map(|v| self.positions_local_m[v as usize]);
        (b - a).cross(c - a).normalize_or_zero()
    }

    /// Area-weighted vertex normals from the faces (replaces any normals read from the file).
    pub fn compute_vertex_normals(&mut self) {
        let mut normals = vec![Vec3::ZERO; self.positions_local_m.len()];
        for face in &self.faces {
            let [a, b, c] = face.map(|v| self.positions_local_m[v as usize]);
            let weighted = (b - a).cross(c - a);
            for &v in face {
                normals[v as usize] += weighted;
            }
        }
        for n in &mut normals {
            *n = n.normalize_or_zero();
        }
        self.vertex_normals = Some(normals);
    }

    /// Drops vertex normals (the renderer then shades with face normals).
    pub fn clear_vertex_normals(&mut self) {
        self.vertex_normals = None;
    }

    /// Appends another mesh (re-expressed in this mesh's local frame).
    pub fn append(&mut self, other: &Mesh) {
        let offset = other.origin_m - self.origin_m;
        let offset = Vec3::new(offset.x as f32, offset.y as f32, offset.z as f32);
        let base = self.positions_local_m.len() as u32;
        self.positions_local_m
            .extend(other.positions_local_m.iter().map(|p| *p + offset));
        self.faces
            .extend(other.faces.iter().map(|f| f.map(|v| v + base)));
        self.vertex_normals = match (self.vertex_normals.take(), &other.vertex_normals) {
            (Some(mut mine), Some(theirs)) => {
                mine.extend_from_slice(theirs);
                Some(mine)
            }
            _ => None,
        };
        self.grid = FaceGrid::build(&self.positions_local_m, &self.faces);
    }
}

/// The local origin (bounding-box centre) of world positions and the positions relative to it in
/// f32; an error names the first non-finite vertex.
fn local_positions(
    positions_world_m: &[Vector3<f64>],
) -> Result<(Vector3<f64>, Vec<Vec3>), MeshError> {
    for (vertex_index, p) in positions_world_m.iter().enumerate() {
        if let Some(value) = p.iter().copied().find(|v| !v.is_finite()) {
            return Err(MeshError::NonFiniteVertex {
                vertex_index,
                value,
            });
        }
    }
    let origin_m = bounds_center(positions_world_m.iter().copied());
    let positions_local_m = positions_world_m
        .iter()
        .map(|p| {
            let local = p - origin_m;
            Vec3::new(local.x as f32, local.y as f32, local.z as f32)
        })
        .collect();
    Ok((origin_m, positions_local_m))
}

fn bounds_center(points: impl Iterator<Item = Vector3<f64>>) -> Vector3<f64> {
    let mut min = Vector3::repeat(f64::INFINITY);
    let mut max = Vector3::repeat(f64::NEG_INFINITY);
    for p in points {
        min = min.inf(&p);
        max = max.sup(&p);
    }
    if min.x.is_finite() {
        (min + max) / 2.0
    } else {
        Vector3::zeros()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn triangle_at(offset: Vector3<f64>) -> Mesh {
        let positions = [
            offset + Vector3::new(0.0, 0.0, 0.0),
            offset + Vector3::new(1.0, 0.0, 0.0),
            offset + Vector3::new(0.0, 1.0, 0.0),
        ];
        Mesh::from_world(&positions, vec![[0, 1, 2]], None).unwrap()
    }

    #[test]
    fn georeferenced_vertices_keep_millimetres() {
        let utm = Vector3::new(512_345.123, 5_401_234.567, 250.001);
        let mesh = triangle_at(utm);
        let p = mesh.world_position(1);
        assert!((p - (utm + Vector3::new(1.0, 0.0, 0.0))).norm() < 1e-6);
        assert!((mesh.face_normal(0) - Vec3::Z).length() < 1e-6);
    }

    #[test]
    fn bad_meshes_are_rejected_with_the_culprit() {
        let positions = [Vector3::zeros(), Vector3::x(), Vector3::y()];
        assert_eq!(
            Mesh::from_world(&positions, vec![], None),
            Err(MeshError::NoFaces)
        );
        assert_eq!(
            Mesh::from_world(&positions, vec![[0, 1, 3]], None),
            Err(MeshError::IndexOutOfRange {
                face_index: 0,
                vertex_index: 3,
                vertex_count: 3
            })
        );
        let with_nan = [
            Vector3::zeros(),
            Vector3::new(f64::NAN, 0.0, 0.0),
            Vector3::y(),
        ];
        assert!(matches!(
            Mesh::from_world(&with_nan, vec![[0, 1, 2]], None),
            Err(MeshError::NonFiniteVertex {
                vertex_index: 1,
                ..
            })
        ));
    }

    /// Every face is in exactly one cell, and its cell's corners name its own vertices.
    fn assert_grid_consistent(mesh: &Mesh) {
        let grid = mesh.grid();
        let mut seen = vec![0u32; mesh.face_count()];
        for cell in grid.cells() {
            let vertices = grid.cell_vertices(cell);
            assert!(vertices.len() <= MAX_CELL_VERTICES);
            for (&face, corners) in grid.cell_faces(cell).iter().zip(grid.cell_corners(cell)) {
                seen[face as usize] += 1;
                assert_eq!(
                    corners.map(|c| vertices[c as usize]),
                    mesh.faces()[face as usize]
                );
                for v in mesh.faces()[face as usize] {
                    let p = mesh.positions_local_m()[v as usize];
                    assert!(p.cmpge(cell.min_local_m).all() && p.cmple(cell.max_local_m).all());
                }
            }
        }
        assert!(seen.iter().all(|&n| n == 1));
    }

    #[test]
    fn grid_cells_list_their_vertices_and_split_above_the_u16_limit() {
        // A strip of 2 × 40 000 vertices: one group of every face needs more than 2^16 vertices.
        let columns = 40_000;
        let positions: Vec<Vector3<f64>> = (0..columns)
            .flat_map(|i| {
                [
                    Vector3::new(i as f64, 0.0, 0.0),
                    Vector3::new(i as f64, 1.0, 0.0),
                ]
            })
            .collect();
        let faces: Vec<[u32; 3]> = (0..columns as u32 - 1)
            .flat_map(|i| {
                [
                    [2 * i, 2 * i + 2, 2 * i + 1],
                    [2 * i + 1, 2 * i + 2, 2 * i + 3],
                ]
            })
            .collect();
        let mesh = Mesh::from_world(&positions, faces, None).unwrap();
        assert!(mesh.grid().cells().len() > 1);
        assert_grid_consistent(&mesh);
        let single = mesh.with_single_grid_cell();
        assert_eq!(single.grid().cells().len(), 2, "80 000 vertices: two cells");
        assert_grid_consistent(&single);
    }

    #[test]
    fn append_keeps_world_positions() {
        let mut a = triangle_at(Vector3::new(100.0, 0.0, 0.0));
        let b = triangle_at(Vector3::new(0.0, 50.0, 0.0));
        a.append(&b);
        assert_eq!(a.face_count(), 2);
        assert!((a.world_position(4) - Vector3::new(1.0, 50.0, 0.0)).norm() < 1e-5);
    }
}
