//! A city-size mesh for the memory and speed measurements of issue #16 (`asgreg bench mesh`): a
//! square grid of lots, each a flat ground quad and a box building (four walls and a roof, each
//! split into 4×4 quads, so triangles are as dense as a photogrammetric mesh's), heights from a
//! hash of the lot. It is written straight to a binary little-endian PLY in georeferenced
//! coordinates (UTM-like, [`CITY_ORIGIN_M`]) without ever being held in memory, so a 10^7-triangle
//! city is made in bounded memory like the one it is meant to test.

use std::io::Write as _;
use std::path::Path;

use crate::io::mesh_file::MeshIoError;

/// Where the city lies: easting, northing, height of its south-west corner (m), a UTM zone 30U
/// position (Brighton), so f32 alone could not keep its millimetres.
pub const CITY_ORIGIN_M: [f64; 3] = [699_000.0, 5_633_000.0, 0.0];
/// Side of one lot, m.
pub const LOT_M: f64 = 30.0;
/// Quads along each side of a wall or roof.
const SPLITS: usize = 4;
/// Triangles of one lot: 2 for the ground, 5 faces of `SPLITS`² quads for the building.
pub const TRIANGLES_PER_LOT: u64 = 2 + 5 * 2 * (SPLITS * SPLITS) as u64;
const VERTICES_PER_LOT: u64 = 4 + 5 * ((SPLITS + 1) * (SPLITS + 1)) as u64;

/// What [`write_city_ply`] wrote.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CityMesh {
    /// Lots per side.
    pub lots_per_side: usize,
    pub triangles: u64,
    pub vertices: u64,
    /// Side of the city, m.
    pub side_m: f64,
}

impl CityMesh {
    /// The city's layout for about `target_triangles` triangles (at least one lot).
    pub fn for_triangles(target_triangles: u64) -> Self {
        let lots = (target_triangles as f64 / TRIANGLES_PER_LOT as f64)
            .sqrt()
            .round()
            .max(1.0) as usize;
        let lot_count = (lots * lots) as u64;
        Self {
            lots_per_side: lots,
            triangles: lot_count * TRIANGLES_PER_LOT,
            vertices: lot_count * VERTICES_PER_LOT,
            side_m: lots as f64 * LOT_M,
        }
    }

    /// Height of the building on lot (`col`, `row`), m (8..60 m, from a hash of the lot).
    pub fn building_height_m(col: usize, row: usize) -> f64 {
        let mut h = (col as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
            ^ (row as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
        h ^= h >> 29;
        h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
        h ^= h >> 32;
        8.0 + (h % 5200) as f64 / 100.0
    }
}

/// The building box of a lot: min and max corners in world coordinates.
fn building_box(col: usize, row: usize) -> ([f64; 3], [f64; 3]) {
    let x0 = CITY_ORIGIN_M[0] + col as f64 * LOT_M + 5.0;
    let y0 = CITY_ORIGIN_M[1] + row as f64 * LOT_M + 5.0;
    let z1 = CITY_ORIGIN_M[2] + CityMesh::building_height_m(col, row);
    ([x0, y0, CITY_ORIGIN_M[2]], [x0 + 20.0, y0 + 20.0, z1])
}

/// The five faces of a box (walls and roof) as (corner, edge u, edge v), outward by right hand.
fn box_faces(min: [f64; 3], max: [f64; 3]) -> [([f64; 3], [f64; 3], [f64; 3]); 5] {
    let (dx, dy, dz) = (max[0] - min[0], max[1] - min[1], max[2] - min[2]);
    [
        // South wall (y = min), normal -y.
        (min, [dx, 0.0, 0.0], [0.0, 0.0, dz]),
        // North wall (y = max), normal +y.
        ([max[0], max[1], min[2]], [-dx, 0.0, 0.0], [0.0, 0.0, dz]),
        // West wall (x = min), normal -x.
        ([min[0], max[1], min[2]], [0.0, -dy, 0.0], [0.0, 0.0, dz]),
        // East wall (x = max), normal +x.
        ([max[0], min[1], min[2]], [0.0, dy, 0.0], [0.0, 0.0, dz]),
        // Roof (z = max), normal +z.
        ([min[0], min[1], max[2]], [dx, 0.0, 0.0], [0.0, dy, 0.0]),
    ]
}

/// Writes the city of about `target_triangles` triangles as a binary PLY (`double x y z`,
/// `list uchar int vertex_indices`) at `path`, streamed lot by lot.
pub fn write_city_ply(path: &Path, target_triangles: u64) -> Result<CityMesh, MeshIoError> {
    let city = CityMesh::for_triangles(target_triangles);
    let write_error = |source| MeshIoError::Write {
        path: path.to_path_buf(),
        source,
    };
    let file = std::fs::File::create(path).map_err(write_error)?;
    let mut out = std::io::BufWriter::with_capacity(1 << 20, file);
    write!(
        out,
        "ply\nformat binary_little_endian 1.0\ncomment asgreg synthetic city, {} x {} lots of {LOT_M} m, UTM-like origin {:?}\nelement vertex {}\nproperty double x\nproperty double y\nproperty double z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
        city.lots_per_side, city.lots_per_side, CITY_ORIGIN_M, city.vertices, city.triangles
    )
    .map_err(write_error)?;
    let lots = city.lots_per_side;
    let mut buffer: Vec<u8> = Vec::with_capacity(VERTICES_PER_LOT as usize * 24);
    for row in 0..lots {
        for col in 0..lots {
            buffer.clear();
            let mut push = |p: [f64; 3]| {
                for c in p {
                    buffer.extend_from_slice(&c.to_le_bytes());
                }
            };
            let gx = CITY_ORIGIN_M[0] + col as f64 * LOT_M;
            let gy = CITY_ORIGIN_M[1] + row as f64 * LOT_M;
            let gz = CITY_ORIGIN_M[2];
            for (dx, dy) in [(0.0, 0.0), (LOT_M, 0.0), (LOT_M, LOT_M), (0.0, LOT_M)] {
                push([gx + dx, gy + dy, gz]);
            }
            let (min, max) = building_box(col, row);
            for (corner, u, v) in box_faces(min, max) {
                for j in 0..=SPLITS {
                    for i in 0..=SPLITS {
                        let (s, t) = (i as f64 / SPLITS as f64, j as f64 / SPLITS as f64);
                        push(std::array::from_fn(|k| corner[k] + s * u[k] + t * v[k]));
                    }
                }
            }
            out.write_all(&buffer).map_err(write_error)?;
        }
    }
    let face = |out: &mut std::io::BufWriter<std::fs::File>, a: u64, b: u64, c: u64| {
        let mut record = [3u8; 13];
        for (k, v) in [a, b, c].into_iter().enumerate() {
            record[1 + 4 * k..5 + 4 * k].copy_from_slice(&(v as i32).to_le_bytes());
        }
        out.write_all(&record)
    };
    for lot in 0..(lots * lots) as u64 {
        let base = lot * VERTICES_PER_LOT;
        face(&mut out, base, base + 1, base + 2).map_err(write_error)?;
        face(&mut out, base, base + 2, base + 3).map_err(write_error)?;
        for box_face in 0..5u64 {
            let start = base + 4 + box_face * ((SPLITS + 1) * (SPLITS + 1)) as u64;
            let stride = (SPLITS + 1) as u64;
            for j in 0..SPLITS as u64 {
                for i in 0..SPLITS as u64 {
                    let a = start + j * stride + i;
                    let (b, c, d) = (a + 1, a + stride + 1, a + stride);
                    face(&mut out, a, b, c).map_err(write_error)?;
                    face(&mut out, a, c, d).map_err(write_error)?;
                }
            }
        }
    }
    out.flush().map_err(write_error)?;
    Ok(city)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::camera::PinholeIntrinsics;
    use crate::core::raster::{Rasterizer, RenderBuffers, RenderOptions};
    use crate::core::rigid::Rigid3;
    use nalgebra::Vector3;

    #[test]
    fn a_small_city_reads_back_georeferenced_and_renders_only_what_the_camera_sees() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("city.ply");
        let city = write_city_ply(&path, 40_000).unwrap();
        let mesh = crate::io::mesh_file::read_mesh(&path).unwrap();
        assert_eq!(mesh.face_count() as u64, city.triangles);
        assert_eq!(mesh.vertex_count() as u64, city.vertices);
        let (min, max) = mesh.bounds_world_m();
        assert!((min.x - CITY_ORIGIN_M[0]).abs() < 1e-6 && (min.y - CITY_ORIGIN_M[1]).abs() < 1e-6);
        assert!((max.x - (CITY_ORIGIN_M[0] + city.side_m)).abs() < 1e-6);
        assert!(
            mesh.grid().cells().len() > 4,
            "the city is split into cells"
        );

        // A camera 120 m above one corner, looking down obliquely: most of the city is outside.
        let eye = Vector3::new(CITY_ORIGIN_M[0] + 20.0, CITY_ORIGIN_M[1] - 40.0, 120.0);
        let target = Vector3::new(CITY_ORIGIN_M[0] + 60.0, CITY_ORIGIN_M[1] + 60.0, 0.0);
        let pose = Rigid3::look_at(&eye, &target, &Vector3::new(0.0, 0.0, 1.0)).unwrap();
        let intrinsics = PinholeIntrinsics::centered(300.0, 320, 180);
        let mut culled = RenderBuffers::new(320, 180);
        let mut rasterizer = Rasterizer::new();
        rasterizer.render(
            &mesh,
            &intrinsics,
            &pose,
            &RenderOptions::default(),
            &mut culled,
        );
        assert!(
            culled.valid_count() > 320 * 180 / 2,
            "the camera sees the city"
        );
        let visible = rasterizer.visible_face_count();
        assert!(
            visible * 2 < mesh.face_count(),
            "frustum culling keeps {visible} of {} faces",
            mesh.face_count()
        );
        // The same picture as with every face drawn (one cell holding the whole mesh).
        let whole = mesh.clone().with_single_grid_cell();
        let mut all = RenderBuffers::new(320, 180);
        Rasterizer::new().render(
            &whole,
            &intrinsics,
            &pose,
            &RenderOptions::default(),
            &mut all,
        );
        assert_eq!(culled.face_index().data(), all.face_index().data());
        assert_eq!(culled.depth_m().data(), all.depth_m().data());
    }
}
