//! CPU z-buffer rasteriser: depth, normals and a validity mask of a mesh for any pose and pinhole
//! camera. Every ASG rendering, every visibility test (δ) and the synthetic photo renderer's
//! geometry pass go through here, so it is parallel and allocation-free when reused.
//!
//! Design:
//! - the pose is folded with the mesh's local origin in f64 (`cam_from_local`), then vertices are
//!   transformed in f32: georeferenced meshes render like meshes at the origin;
//! - triangles are clipped against the near plane (a ground plane passes under a low camera) and
//!   binned into horizontal bands of rows; bands are rasterised in parallel (rayon), each band
//!   walking its triangles in face order, so the result is deterministic;
//! - frustum culling: the mesh's face grid (`Mesh::grid`) is tested cell box by cell box against
//!   the frustum's half-spaces, and only the faces of cells it may see are binned and drawn (a
//!   city mesh seen by one camera); every rendering goes through this one test;
//! - only the vertices of the cells the frustum keeps are transformed and projected, once per
//!   cell that lists them (each cell lists its faces' vertices, `FaceGrid::cell_vertices`, and
//!   names its faces' corners in that list): a rendering's work and scratch buffers follow what
//!   the camera sees, never the mesh's vertex count (a 10^7-triangle city seen by one camera);
//! - binning drops faces whose bounding box holds no pixel centre, and tests the one centre of
//!   boxes that hold exactly one (most triangles of a dense mesh seen from afar are sub-pixel);
//!   where the CPU has AVX2 (detected at run time) eight faces' boxes and single-centre tests go
//!   at once, one face per lane, with the scalar path's very operations (the same bits), and
//!   a single-centre face it keeps leaves only its pixel and depth there, which the band pass
//!   depth-tests without setting the triangle up again; every other face it keeps is stored
//!   once, prepared (corners' projections, face index, pixel box), in its chunk's list, which
//!   the band pass reads in order instead of gathering corners;
//! - a pixel `(col, row)` is covered when its centre `(col + 0.5, row + 0.5)` lies inside the
//!   projected triangle (see `camera.rs` for the convention); the depth pass steps affine edge
//!   functions and `1/z` along each row (perspective-correct depth) and writes only depth and face
//!   index (while a band is drawn, the face's slot in the visible list, turned into the mesh's
//!   face index once the band is done); the nearest surface wins (ties: the lower face index,
//!   whatever order faces come in);
//! - normals are filled afterwards, once per visible pixel, from its winning face: the face
//!   normal, or the vertex normals interpolated with the perspective-correct barycentrics of the
//!   pixel ray's hit on the face (so overdrawn pixels cost no shading);
//! - [`Rasterizer`] keeps its scratch buffers and [`RenderBuffers`] is written in place: rendering
//!   the same mesh again allocates nothing.
//!
//! Distortion is not rasterised: renderings are ideal pinhole images; photos with lens distortion
//! are undistorted first (or their cameras are used without distortion, a choice the caller makes).

use glam::{Mat3, Vec2, Vec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::camera::PinholeIntrinsics;
use super::image::Image;
use super::mesh::Mesh;
use super::rigid::Rigid3;

/// `face_index` value of pixels that show no surface.
pub const NO_FACE: u32 = u32::MAX;

/// Triangles whose bounding box spans fewer columns than this are not worth solving each row's
/// covered span for.
const NARROW_SPAN_PX: usize = 8;

/// Rows per band of the parallel rasteriser.
const BAND_ROWS: usize = 16;

/// Which normals the normal map holds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum NormalSource {
    /// The flat normal of each triangle.
    Face,
    /// Vertex normals interpolated across the triangle; falls back to face normals for meshes
    /// without vertex normals.
    #[default]
    Vertex,
}

/// Rendering options; `Default` is what registration uses.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RenderOptions {
    pub normal_source: NormalSource,
    /// Skip triangles whose front (counter-clockwise) side faces away from the camera.
    pub cull_back_faces: bool,
    /// Near clipping distance along the optical axis, metres.
    pub near_m: f32,
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self {
            normal_source: NormalSource::Vertex,
            cull_back_faces: false,
            near_m: 0.05,
        }
    }
}

/// The output of one rendering: three images of the same size.
#[derive(Clone, Debug, Default)]
pub struct RenderBuffers {
    /// Distance along the optical axis (camera z) in metres; 0 where no surface.
    depth_m: Image<f32>,
    /// Unit surface normal in the camera frame; zero where no surface.
    normal_cam: Image<Vec3>,
    /// Index of the visible face; [`NO_FACE`] where no surface (the validity mask).
    face_index: Image<u32>,
}

impl RenderBuffers {
    pub fn new(width_px: usize, height_px: usize) -> Self {
        let mut buffers = Self::default();
        buffers.resize(width_px, height_px);
        buffers
    }

    /// Sets the size; allocates only when the pixel count grows. The pixels are meaningful only
    /// after the next [`Rasterizer::render`].
    pub fn resize(&mut self, width_px: usize, height_px: usize) {
        self.depth_m.resize(width_px, height_px, 0.0);
        self.normal_cam.resize(width_px, height_px, Vec3::ZERO);
        self.face_index.resize(width_px, height_px, NO_FACE);
    }

    pub fn width_px(&self) -> usize {
        self.depth_m.width_px()
    }

    pub fn height_px(&self) -> usize {
        self.depth_m.height_px()
    }

    /// Distance along the optical axis (camera z) in metres; 0 where no surface.
    pub fn depth_m(&self) -> &Image<f32> {
        &self.depth_m
    }

    /// Unit surface normal in the camera frame; zero where no surface.
    pub fn normal_cam(&self) -> &Image<Vec3> {
        &self.normal_cam
    }

    /// Index of the visible face; [`NO_FACE`] where no surface (the validity mask).
    pub fn face_index(&self) -> &Image<u32> {
        &self.face_index
    }

    /// Whether pixel `(col, row)` shows a surface (`false` outside the image).
    pub fn is_valid(&self, col: usize, row: usize) -> bool {
        self.face_index
            .get(col, row)
            .is_some_and(|&face| face != NO_FACE)
    }

    /// Number of pixels that show a surface.
    pub fn valid_count(&self) -> usize {
        self.face_index
            .data()
            .iter()
            .filter(|&&f| f != NO_FACE)
            .count()
    }
}

/// A vertex projected to the image: pixel position and `1 / z` (z in metres), f32. Three floats
/// in this order (`repr(C)`): the binning's AVX2 gathers read them as floats.
#[derive(Clone, Copy, Debug, Default)]
#[repr(C)]
struct ScreenVertex {
    position_px: Vec2,
    inv_depth: f32,
}

/// A face of a grid cell the frustum may see: its index in the mesh and its corners as slots of
/// the rendering's transformed vertices.
#[derive(Clone, Copy, Debug, Default)]
struct VisibleFace {
    face_index: u32,
    corners: [u32; 3],
}

/// A face the binning kept, with what drawing it needs read once: the draw pass then reads its
/// chunk's prepared faces in order instead of gathering corners through two levels of indices.
#[derive(Clone, Copy, Debug, Default)]
struct PreparedFace {
    /// Projections of the corners (meaningful when `clipped` is false).
    screen: [ScreenVertex; 3],
    /// Position in `visible_faces`.
    slot: u32,
    face_index: u32,
    /// The pixel box `[first, last]` of columns and rows its bounding box covers, clamped to
    /// the image (faces wholly in front of the near plane).
    cols: [u32; 2],
    rows: [u32; 2],
    /// A corner lies behind the near plane: drawn by [`draw_clipped_face`] from its camera-frame
    /// corners.
    clipped: bool,
}

/// A face whose pixel box holds a single pixel centre, which it covers: the binning's vector
/// path has already computed its depth there with `draw_triangle`'s arithmetic, so the draw pass
/// only depth-tests it (most faces of a dense mesh are sub-pixel).
#[derive(Clone, Copy, Debug)]
struct SinglePixel {
    /// The pixel, row-major in the image.
    pixel: u32,
    depth: f32,
    slot: u32,
    face_index: u32,
}

/// Makes `bands` hold `count` empty lists, keeping their storage.
fn empty_bands<T>(bands: &mut Vec<Vec<T>>, count: usize) {
    bands.resize_with(count, Vec::new);
    bands.truncate(count);
    for band in bands.iter_mut() {
        band.clear();
    }
}

/// The binning of a chunk of the visible faces.
#[derive(Debug, Default)]
struct FaceChunk {
    /// The chunk's faces that cover a pixel centre, in face order.
    prepared: Vec<PreparedFace>,
    /// `bands[band]`: positions in `prepared` of the faces that touch the band, ascending.
    bands: Vec<Vec<u32>>,
    /// `singles[band]`: the chunk's single-pixel faces in the band, already depth-computed
    /// (not in `prepared`). The depth test keeps the nearest face (ties: the lower face index)
    /// whatever order faces come in, so the band pass tests these before the chunk's others.
    singles: Vec<Vec<SinglePixel>>,
}

impl FaceChunk {
    /// Keeps a face the binning found covering a pixel centre: prepared, and listed in the bands
    /// its rows touch.
    #[inline(always)]
    fn keep(
        &mut self,
        slot: usize,
        face: &VisibleFace,
        pixel_box: PixelBox,
        vertices_screen: &[ScreenVertex],
    ) {
        let position = self.prepared.len() as u32;
        self.prepared.push(PreparedFace {
            screen: face.corners.map(|v| vertices_screen[v as usize]),
            slot: slot as u32,
            face_index: face.face_index,
            cols: pixel_box.cols,
            rows: pixel_box.rows,
            clipped: pixel_box.clipped,
        });
        let [first_row, last_row] = pixel_box.rows.map(|r| r as usize);
        for band in self
            .bands
            .iter_mut()
            .take(last_row / BAND_ROWS + 1)
            .skip(first_row / BAND_ROWS)
        {
            band.push(position);
        }
    }
}

/// Scratch state reused between renderings; every buffer is sized by the grid cells the frustum
/// keeps, not by the mesh.
#[derive(Default)]
pub struct Rasterizer {
    /// Mesh vertex index of each slot: the vertex lists of the kept cells, one after the other.
    visible_vertices: Vec<u32>,
    /// Camera-frame position of each slot.
    vertices_cam: Vec<Vec3>,
    /// Projection of each slot; meaningful only for vertices in front of the near plane.
    vertices_screen: Vec<ScreenVertex>,
    /// Whether each slot lies in front of the near plane (camera z ≥ near): the binning's test
    /// of a face's corners reads these bytes, not the camera-frame corners.
    vertices_in_front: Vec<bool>,
    /// Camera-frame vertex normal of each slot (meshes with vertex normals).
    normals_cam: Vec<Vec3>,
    /// `bins[chunk]`: the faces of a chunk of the visible faces that cover a pixel centre,
    /// prepared for drawing, and the ones of them that touch each band.
    bins: Vec<FaceChunk>,
    /// Faces of the grid cells the frustum may see (`Mesh::grid`).
    visible_faces: Vec<VisibleFace>,
    /// Depth and face index only ([`Rasterizer::depth_and_faces_only`]).
    skip_normals: bool,
    /// Renderings made so far ([`Rasterizer::renderings`]).
    renderings: u64,
}

/// The viewing frustum as half-spaces in the camera frame, for culling grid cells: a point p is
/// inside when `z ≥ near`, `0 ≤ u·z ≤ W·z` and `0 ≤ v·z ≤ H·z` with `u·z = fx x + s y + cx z`,
/// `v·z = fy y + cy z` (one pixel of margin on each side).
#[derive(Clone, Copy, Debug)]
struct Frustum {
    projector: Projector,
    width: f32,
    height: f32,
}

impl Frustum {
    fn new(projector: &Projector, width: usize, height: usize) -> Self {
        Self {
            projector: *projector,
            width: width as f32,
            height: height as f32,
        }
    }

    /// False only when the box (local coordinates) lies wholly outside one of the half-spaces:
    /// conservative, a box it keeps may still show nothing.
    fn may_see_box(&self, min: Vec3, max: Vec3, rotation: Mat3, translation: Vec3) -> bool {
        let p = &self.projector;
        let margin = 1.0;
        let mut outside = [true; 5];
        for corner in 0..8 {
            let local = Vec3::new(
                if corner & 1 == 0 { min.x } else { max.x },
                if corner & 2 == 0 { min.y } else { max.y },
                if corner & 4 == 0 { min.z } else { max.z },
            );
            let c = rotation * local + translation;
            let uz = p.fx * c.x + p.skew * c.y + p.cx * c.z;
            let vz = p.fy * c.y + p.cy * c.z;
            let inside = [
                c.z >= p.near_m,
                uz >= -margin * c.z,
                uz <= (self.width + margin) * c.z,
                vz >= -margin * c.z,
                vz <= (self.height + margin) * c.z,
            ];
            for (out, inside) in outside.iter_mut().zip(inside) {
                *out &= !inside;
            }
        }
        !outside.iter().any(|&o| o)
    }
}

/// The projection used inside the rasteriser (f32, no distortion).
#[derive(Clone, Copy, Debug)]
struct Projector {
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    skew: f32,
    near_m: f32,
}

impl Projector {
    fn project(&self, p: Vec3) -> Vec2 {
        let inv_z = 1.0 / p.z;
        let x = p.x * inv_z;
        let y = p.y * inv_z;
        Vec2::new(self.fx * x + self.skew * y + self.cx, self.fy * y + self.cy)
    }

    fn screen_vertex(&self, p: Vec3) -> ScreenVertex {
        ScreenVertex {
            position_px: self.project(p),
            inv_depth: 1.0 / p.z,
        }
    }

    /// The camera ray through an image position, scaled so that `z = 1`.
    fn ray(&self, position_px: Vec2) -> Vec3 {
        let y = (position_px.y - self.cy) / self.fy;
        let x = (position_px.x - self.cx - self.skew * y) / self.fx;
        Vec3::new(x, y, 1.0)
    }
}

impl Rasterizer {
    pub fn new() -> Self {
        Self::default()
    }

    /// A rasteriser whose renderings hold depth and face index only (the very values a full
    /// rendering has), the normal map left all zero: for callers that read only where the
    /// surface is (visible points, δ); the per-pixel normal pass is skipped.
    pub fn depth_and_faces_only() -> Self {
        Self {
            skip_normals: true,
            ..Self::default()
        }
    }

    /// Faces the last rendering's frustum culling kept (those of the grid cells it may see).
    /// How many renderings this rasteriser has made (for tests that count what a step renders).
    pub fn renderings(&self) -> u64 {
        self.renderings
    }

    pub fn visible_face_count(&self) -> usize {
        self.visible_faces.len()
    }

    /// Renders `mesh` seen from `cam_from_world` through `intrinsics` into `out`, which must already
    /// have the image size (its normal map all zero from a [`Rasterizer::depth_and_faces_only`]).
    pub fn render(
        &mut self,
        mesh: &Mesh,
        intrinsics: &PinholeIntrinsics,
        cam_from_world: &Rigid3,
        options: &RenderOptions,
        out: &mut RenderBuffers,
    ) {
        self.render_into(mesh, intrinsics, cam_from_world, options, None, out);
    }

    /// [`Rasterizer::render`]'s depth and face index at the pixels of `grid` only (the visible
    /// points' grid, `reprojection`), each the very value a full rendering has there, every
    /// other pixel left empty (no face, depth 0) and no normals. Faces whose pixel box holds no
    /// grid pixel are dropped at binning, so a dense mesh's sub-pixel triangles cost their box
    /// test only.
    pub fn render_grid_points(
        &mut self,
        mesh: &Mesh,
        intrinsics: &PinholeIntrinsics,
        cam_from_world: &Rigid3,
        options: &RenderOptions,
        grid: SampleGrid,
        out: &mut RenderBuffers,
    ) {
        self.render_into(mesh, intrinsics, cam_from_world, options, Some(grid), out);
    }

    fn render_into(
        &mut self,
        mesh: &Mesh,
        intrinsics: &PinholeIntrinsics,
        cam_from_world: &Rigid3,
        options: &RenderOptions,
        grid: Option<SampleGrid>,
        out: &mut RenderBuffers,
    ) {
        let with_normals = !self.skip_normals && grid.is_none();
        self.renderings += 1;
        let width = out.width_px();
        let height = out.height_px();
        out.depth_m.fill(0.0);
        out.normal_cam.fill(Vec3::ZERO);
        out.face_index.fill(NO_FACE);
        if width == 0 || height == 0 {
            return;
        }

        // cam_from_local = cam_from_world ∘ world_from_local, in f64, then to f32.
        let rotation = cam_from_world.rotation_matrix();
        let translation_local = cam_from_world.transform_point(&mesh.origin_m());
        let rotation_f32 = Mat3::from_cols_array(&[
            rotation[(0, 0)] as f32,
            rotation[(1, 0)] as f32,
            rotation[(2, 0)] as f32,
            rotation[(0, 1)] as f32,
            rotation[(1, 1)] as f32,
            rotation[(2, 1)] as f32,
            rotation[(0, 2)] as f32,
            rotation[(1, 2)] as f32,
            rotation[(2, 2)] as f32,
        ]);
        let translation_f32 = Vec3::new(
            translation_local.x as f32,
            translation_local.y as f32,
            translation_local.z as f32,
        );
        let projector = Projector {
            fx: intrinsics.fx_px as f32,
            fy: intrinsics.fy_px as f32,
            cx: intrinsics.cx_px as f32,
            cy: intrinsics.cy_px as f32,
            skew: intrinsics.skew_px as f32,
            near_m: options.near_m,
        };

        // Frustum culling: only the vertices and faces of grid cells whose box the frustum can
        // see; each kept cell's vertex list becomes a run of slots.
        let frustum = Frustum::new(&projector, width, height);
        let face_grid = mesh.grid();
        self.visible_faces.clear();
        self.visible_vertices.clear();
        for cell in face_grid.cells() {
            if frustum.may_see_box(
                cell.min_local_m,
                cell.max_local_m,
                rotation_f32,
                translation_f32,
            ) {
                let base = self.visible_vertices.len() as u32;
                self.visible_vertices
                    .extend_from_slice(face_grid.cell_vertices(cell));
                self.visible_faces.extend(
                    face_grid
                        .cell_faces(cell)
                        .iter()
                        .zip(face_grid.cell_corners(cell))
                        .map(|(&face_index, corners)| VisibleFace {
                            face_index,
                            corners: corners.map(|c| base + u32::from(c)),
                        }),
                );
            }
        }

        // Transform and project the kept vertices, once per slot.
        let slot_count = self.visible_vertices.len();
        let positions = mesh.positions_local_m();
        self.vertices_cam.resize(slot_count, Vec3::ZERO);
        self.vertices_screen
            .resize(slot_count, ScreenVertex::default());
        self.vertices_in_front.resize(slot_count, false);
        self.vertices_cam
            .par_iter_mut()
            .zip(self.vertices_screen.par_iter_mut())
            .zip(self.vertices_in_front.par_iter_mut())
            .zip(self.visible_vertices.par_iter())
            .for_each(|(((cam, screen), in_front), &v)| {
                *cam = rotation_f32 * positions[v as usize] + translation_f32;
                *in_front = cam.z >= projector.near_m;
                if *in_front {
                    *screen = projector.screen_vertex(*cam);
                }
            });

        let use_vertex_normals = with_normals
            && options.normal_source == NormalSource::Vertex
            && mesh.vertex_normals().is_some();
        if let (true, Some(normals)) = (use_vertex_normals, mesh.vertex_normals()) {
            self.normals_cam.resize(slot_count, Vec3::ZERO);
            self.normals_cam
                .par_iter_mut()
                .zip(self.visible_vertices.par_iter())
                .for_each(|(out, &v)| *out = rotation_f32 * normals[v as usize]);
        }

        // Bin faces into bands of rows, per chunk of faces, in parallel. Faces that cover no
        // pixel centre (most sub-pixel triangles of a dense mesh) are dropped here.
        let band_count = height.div_ceil(BAND_ROWS);
        let chunk_count = (rayon::current_num_threads() * 4).max(1);
        self.bins.resize_with(chunk_count, FaceChunk::default);
        let visible_faces = &self.visible_faces;
        let vertices_cam = &self.vertices_cam;
        let vertices_screen = &self.vertices_screen;
        let vertices_in_front = &self.vertices_in_front;
        let chunk_len = visible_faces.len().div_ceil(chunk_count).max(1);
        // Where the CPU has AVX2, eight faces' boxes at a time here and eight pixels of a row at
        // a time when drawing (the same arithmetic lane by lane, so the same bits).
        #[cfg(target_arch = "x86_64")]
        let avx2 = std::arch::is_x86_feature_detected!("avx2");
        #[cfg(not(target_arch = "x86_64"))]
        let avx2 = false;
        // The gathers address the projections as floats through i32 offsets.
        #[cfg(target_arch = "x86_64")]
        let eight_at_once = avx2 && !options.cull_back_faces && slot_count <= i32::MAX as usize / 3;
        self.bins
            .par_iter_mut()
            .enumerate()
            .for_each(|(chunk_index, chunk)| {
                empty_bands(&mut chunk.bands, band_count);
                empty_bands(&mut chunk.singles, band_count);
                chunk.prepared.clear();
                let start = (chunk_index * chunk_len).min(visible_faces.len());
                let end = (start + chunk_len).min(visible_faces.len());
                let scalar_box = |face: &VisibleFace| {
                    let screen = face.corners.map(|v| vertices_screen[v as usize]);
                    let [in_front_0, in_front_1, in_front_2] =
                        face.corners.map(|v| vertices_in_front[v as usize]);
                    // Most faces: wholly in front, no culling; the camera-frame corners are
                    // read only for the others.
                    if in_front_0 & in_front_1 & in_front_2 & !options.cull_back_faces {
                        screen_pixel_box(&screen, width, height)
                    } else {
                        let corners = face.corners.map(|v| vertices_cam[v as usize]);
                        face_pixel_box(&corners, &screen, &projector, options, width, height)
                    }
                };
                // A grid-points rendering keeps only the faces whose box holds a grid pixel.
                let on_grid = |pixel_box: &PixelBox| {
                    grid.is_none_or(|g| g.meets(pixel_box.cols) & g.meets(pixel_box.rows))
                };
                let mut slot = start;
                #[cfg(target_arch = "x86_64")]
                if eight_at_once {
                    while slot + 8 <= end {
                        let faces: &[VisibleFace; 8] = visible_faces[slot..slot + 8]
                            .try_into()
                            .unwrap_or_else(|_| unreachable!("a slice of eight"));
                        // SAFETY: `eight_at_once` only when the CPU has AVX2 and every slot's
                        // float offset fits an i32.
                        let boxes = unsafe {
                            eight_screen_pixel_boxes_avx2(
                                faces,
                                vertices_screen,
                                vertices_in_front,
                                width,
                                height,
                            )
                        };
                        for (lane, face) in faces.iter().enumerate() {
                            if let Some((col, row, depth)) = boxes.single_pixel(lane) {
                                if grid.is_none_or(|g| g.holds(col) & g.holds(row)) {
                                    chunk.singles[row as usize / BAND_ROWS].push(SinglePixel {
                                        pixel: row * width as u32 + col,
                                        depth,
                                        slot: (slot + lane) as u32,
                                        face_index: face.face_index,
                                    });
                                }
                                continue;
                            }
                            let pixel_box = if boxes.scalar & (1 << lane) != 0 {
                                scalar_box(face)
                            } else {
                                boxes.pixel_box(lane)
                            };
                            if let Some(pixel_box) = pixel_box.filter(on_grid) {
                                chunk.keep(slot + lane, face, pixel_box, vertices_screen);
                            }
                        }
                        slot += 8;
                    }
                }
                for (slot, face) in (slot..end).zip(&visible_faces[slot..end]) {
                    if let Some(pixel_box) = scalar_box(face).filter(on_grid) {
                        chunk.keep(slot, face, pixel_box, vertices_screen);
                    }
                }
            });

        // Rasterise bands in parallel: depth and face index first, then the normals of the
        // surviving pixels only (no shading work for overdrawn pixels).
        let bins = &self.bins;
        let normals_cam = &self.normals_cam;
        out.depth_m
            .data_mut()
            .par_chunks_mut(BAND_ROWS * width)
            .zip(out.normal_cam.data_mut().par_chunks_mut(BAND_ROWS * width))
            .zip(out.face_index.data_mut().par_chunks_mut(BAND_ROWS * width))
            .enumerate()
            .for_each(|(band, ((depth, normal), face_out))| {
                let mut band_target = BandTarget {
                    first_row: band * BAND_ROWS,
                    rows: depth.len() / width,
                    width,
                    height,
                    depth,
                    face_slot: face_out,
                    visible_faces,
                    avx2,
                    grid,
                };
                let band_start = band * BAND_ROWS * width;
                for chunk in bins {
                    for single in chunk.singles.get(band).into_iter().flatten() {
                        band_target.depth_test(
                            single.pixel as usize - band_start,
                            single.depth,
                            single.slot,
                            single.face_index,
                        );
                    }
                    let Some(band_faces) = chunk.bands.get(band) else {
                        continue;
                    };
                    for &position in band_faces {
                        let face = &chunk.prepared[position as usize];
                        if face.clipped {
                            let corners = visible_faces[face.slot as usize]
                                .corners
                                .map(|v| vertices_cam[v as usize]);
                            draw_clipped_face(&corners, face, &projector, &mut band_target);
                        } else {
                            draw_triangle(
                                &face.screen,
                                face,
                                face.cols,
                                face.rows,
                                &mut band_target,
                            );
                        }
                    }
                }
                let normal_source = if use_vertex_normals {
                    Some(normals_cam.as_slice())
                } else {
                    None
                };
                if with_normals {
                    shade_band(
                        &band_target,
                        normal,
                        vertices_cam,
                        normal_source,
                        &projector,
                    );
                }
                for pixel in band_target.face_slot.iter_mut() {
                    if *pixel != NO_FACE {
                        *pixel = visible_faces[*pixel as usize].face_index;
                    }
                }
            });
    }
}

/// The band of an output image a face is drawn into.
struct BandTarget<'a> {
    first_row: usize,
    rows: usize,
    width: usize,
    /// The image's height.
    height: usize,
    depth: &'a mut [f32],
    /// Position in `visible_faces` of each pixel's nearest face so far; [`NO_FACE`] where none.
    face_slot: &'a mut [u32],
    visible_faces: &'a [VisibleFace],
    /// The CPU has AVX2: rows of triangles are drawn eight pixels at a time.
    #[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
    avx2: bool,
    /// A grid-points rendering ([`Rasterizer::render_grid_points`]): only these pixels are drawn.
    grid: Option<SampleGrid>,
}

/// A grid of pixels: rows and columns `first + k · stride`. The visible points of δ are
/// sampled on one (`reprojection`), and [`Rasterizer::render_grid_points`] draws only its
/// pixels.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SampleGrid {
    first: u32,
    stride: u32,
}

impl SampleGrid {
    /// The grid every `stride_px` pixels (at least 1) centred in its cells: from `stride_px / 2`.
    pub fn centred(stride_px: usize) -> Self {
        let stride = stride_px.clamp(1, u32::MAX as usize) as u32;
        Self {
            first: stride / 2,
            stride,
        }
    }

    /// The first row (and column) of the grid, px.
    pub fn first_px(&self) -> usize {
        self.first as usize
    }

    /// Pixels between neighbouring rows (and columns) of the grid.
    pub fn stride_px(&self) -> usize {
        self.stride as usize
    }

    /// Whether row (or column) `at` is one of the grid's.
    #[inline(always)]
    fn holds(&self, at: u32) -> bool {
        at >= self.first && (at - self.first) % self.stride == 0
    }

    /// The grid's first row (or column) at or after `at`.
    #[inline(always)]
    fn first_from(&self, at: usize) -> usize {
        let (first, stride) = (self.first as usize, self.stride as usize);
        if at <= first {
            first
        } else {
            first + (at - first).div_ceil(stride) * stride
        }
    }

    /// Whether the rows (or columns) `[first, last]` hold one of the grid's.
    #[inline(always)]
    fn meets(&self, range: [u32; 2]) -> bool {
        self.first_from(range[0] as usize) <= range[1] as usize
    }
}

impl BandTarget<'_> {
    /// Writes `depth` and `slot` at the band's pixel `index` if the face is the nearest so far;
    /// on a tie the lower face index, whatever order faces come in.
    #[inline(always)]
    fn depth_test(&mut self, index: usize, depth: f32, slot: u32, face_index: u32) {
        let current = self.face_slot[index];
        if current != NO_FACE
            && (depth > self.depth[index]
                || (depth == self.depth[index]
                    && face_index > self.visible_faces[current as usize].face_index))
        {
            return;
        }
        self.depth[index] = depth;
        self.face_slot[index] = slot;
    }
}

/// The pixels a face's bounding box may cover: columns and rows `[first, last]`, clamped to the
/// image; `clipped` when a corner lies behind the near plane (then the box is the near-clipped
/// polygon's, and its sub-triangles find their own columns when drawn).
#[derive(Clone, Copy, Debug)]
struct PixelBox {
    cols: [u32; 2],
    rows: [u32; 2],
    clipped: bool,
}

/// The pixel box of a face, or `None` when it cannot be seen or covers no pixel centre. `screen`
/// holds the corners' projections (valid for corners in front of the near plane).
fn face_pixel_box(
    corners: &[Vec3; 3],
    screen: &[ScreenVertex; 3],
    projector: &Projector,
    options: &RenderOptions,
    width: usize,
    height: usize,
) -> Option<PixelBox> {
    let near = projector.near_m;
    let in_front = corners.iter().filter(|p| p.z >= near).count();
    if in_front == 0 {
        return None;
    }
    if options.cull_back_faces && is_back_facing(corners) {
        return None;
    }
    if in_front == 3 {
        return screen_pixel_box(screen, width, height);
    }
    // Project the near-clipped polygon: its corners are the in-front vertices and the
    // crossings of the near plane.
    let mut min = Vec2::splat(f32::INFINITY);
    let mut max = Vec2::splat(f32::NEG_INFINITY);
    let mut extend = |p: Vec3| {
        let s = projector.project(p);
        min = min.min(s);
        max = max.max(s);
    };
    for i in 0..3 {
        let a = corners[i];
        let b = corners[(i + 1) % 3];
        if a.z >= near {
            extend(a);
        }
        if (a.z >= near) != (b.z >= near) {
            let t = (near - a.z) / (b.z - a.z);
            extend(a + (b - a) * t);
        }
    }
    if !min.is_finite() || !max.is_finite() {
        return None;
    }
    let [cols, rows] = pixel_box(min, max, width, height)?;
    Some(PixelBox {
        cols,
        rows,
        clipped: true,
    })
}

/// [`face_pixel_box`] of a face wholly in front of the near plane, from its corners'
/// projections alone (the binning's common case).
#[inline(always)]
fn screen_pixel_box(screen: &[ScreenVertex; 3], width: usize, height: usize) -> Option<PixelBox> {
    let mut min = Vec2::splat(f32::INFINITY);
    let mut max = Vec2::splat(f32::NEG_INFINITY);
    for s in screen {
        min = min.min(s.position_px);
        max = max.max(s.position_px);
    }
    if !(min.is_finite() & max.is_finite()) {
        return None;
    }
    let [cols, rows] = pixel_box(min, max, width, height)?;
    // A box around a single pixel centre (most sub-pixel triangles): test that centre now, with
    // the arithmetic `draw_triangle` uses, instead of binning a triangle that misses it.
    if (rows[0] == rows[1]) & (cols[0] == cols[1]) {
        let centre = Vec2::new(cols[0] as f32 + 0.5, rows[0] as f32 + 0.5);
        let setup = TriangleSetup::new(screen)?;
        let (w_start, inv_depth_start) = setup.at(centre);
        setup.depth(&w_start, inv_depth_start, 0.0)?;
    }
    Some(PixelBox {
        cols,
        rows,
        clipped: false,
    })
}

/// The columns and rows `[first, last]` of the pixel centres a projected triangle's bounding box
/// holds, clamped to the image; `None` when there are none.
fn triangle_pixel_box(
    screen: &[ScreenVertex; 3],
    width: usize,
    height: usize,
) -> Option<[[u32; 2]; 2]> {
    let [p0, p1, p2] = screen.map(|s| s.position_px);
    pixel_box(p0.min(p1).min(p2), p0.max(p1).max(p2), width, height)
}

/// The columns and rows `[first, last]` of the pixel centres (at +0.5) inside the box
/// `min ..= max`, clamped to the image: `ceil(min − 0.5) ..= floor(max − 0.5)`; `None` when the
/// box holds no pixel centre of the image.
#[inline(always)]
fn pixel_box(min: Vec2, max: Vec2, width: usize, height: usize) -> Option<[[u32; 2]; 2]> {
    let (width_f, height_f) = (width as f32, height as f32);
    if (max.x < 0.5) | (max.y < 0.5) | (min.x > width_f - 0.5) | (min.y > height_f - 0.5) {
        return None;
    }
    // Clamp before rounding so that the fast rounding never sees huge values (nor NaN: the
    // clamps return the bound then); the four roundings in one go, `ceil(x) = −floor(−x)`.
    // The results are whole numbers within the image, so integers hold them exactly.
    let [minus_first_col, minus_first_row, last_col, last_row] = floor_px4([
        -(min.x - 0.5).max(-1.0),
        -(min.y - 0.5).max(-1.0),
        (max.x - 0.5).min(width_f),
        (max.y - 0.5).min(height_f),
    ]);
    let first_row = (-minus_first_row).max(0);
    let last_row = last_row.min(height as i32 - 1);
    let first_col = (-minus_first_col).max(0);
    let last_col = last_col.min(width as i32 - 1);
    if !((first_row <= last_row) & (first_col <= last_col)) {
        return None;
    }
    Some([
        [first_col as u32, last_col as u32],
        [first_row as u32, last_row as u32],
    ])
}

/// Signed edge function: positive when `p` is left of `a → b` in image coordinates (y down).
#[inline(always)]
fn edge_function(a: Vec2, b: Vec2, p: Vec2) -> f32 {
    (b.x - a.x) * (p.y - a.y) - (b.y - a.y) * (p.x - a.x)
}

/// A projected triangle set up for depth testing: its edge functions and `1/z` are affine in the
/// image, evaluated at the start of a run of columns and stepped along it. The one arithmetic of
/// [`draw_triangle`]'s spans and of the binning's single-pixel test, so both decide alike.
struct TriangleSetup {
    /// Edge i is opposite corner i.
    edges: [(Vec2, Vec2); 3],
    orientation: f32,
    /// Growth of each edge function per column.
    step_x: [f32; 3],
    /// `1/z` of each corner over the triangle's doubled area.
    inv_depth: [f32; 3],
    inv_depth_step_x: f32,
}

impl TriangleSetup {
    /// `None` for degenerate (or non-finite) triangles, which cover nothing.
    #[inline(always)]
    fn new(screen: &[ScreenVertex; 3]) -> Option<Self> {
        let [p0, p1, p2] = screen.map(|s| s.position_px);
        let signed_area = edge_function(p0, p1, p2);
        if !signed_area.is_finite() | (signed_area.abs() < 1e-12) {
            return None;
        }
        let orientation = signed_area.signum();
        let inv_area = 1.0 / signed_area.abs();
        let edges = [(p1, p2), (p2, p0), (p0, p1)];
        let step_x = edges.map(|(a, b)| -(b.y - a.y) * orientation);
        let inv_depth = screen.map(|s| s.inv_depth * inv_area);
        let inv_depth_step_x =
            step_x[0] * inv_depth[0] + step_x[1] * inv_depth[1] + step_x[2] * inv_depth[2];
        Some(Self {
            edges,
            orientation,
            step_x,
            inv_depth,
            inv_depth_step_x,
        })
    }

    /// The edge functions (positive inside) and the `1/z` sum at the pixel centre `start`.
    #[inline(always)]
    fn at(&self, start: Vec2) -> ([f32; 3], f32) {
        let w_start = self
            .edges
            .map(|(a, b)| edge_function(a, b, start) * self.orientation);
        let inv_depth = &self.inv_depth;
        let inv_depth_start =
            w_start[0] * inv_depth[0] + w_start[1] * inv_depth[1] + w_start[2] * inv_depth[2];
        (w_start, inv_depth_start)
    }

    /// The depth `offset` columns after a run's start (edges included), or `None` when the
    /// pixel centre is outside or the depth is not positive.
    #[inline(always)]
    fn depth(&self, w_start: &[f32; 3], inv_depth_start: f32, offset: f32) -> Option<f32> {
        let step_x = &self.step_x;
        let w0 = w_start[0] + step_x[0] * offset;
        let w1 = w_start[1] + step_x[1] * offset;
        let w2 = w_start[2] + step_x[2] * offset;
        if (w0 < 0.0) | (w1 < 0.0) | (w2 < 0.0) {
            return None;
        }
        let sum_inv_depth = inv_depth_start + self.inv_depth_step_x * offset;
        if sum_inv_depth <= 0.0 {
            return None;
        }
        Some(1.0 / sum_inv_depth)
    }
}

/// `floor` for values whose integer part fits an `i32` (image coordinates), as `f32`. Inlined:
/// the default x86-64 target has no rounding instruction, and `f32::floor` is a libm call.
#[inline(always)]
fn floor_px(x: f32) -> f32 {
    let truncated = x as i32 as f32;
    if truncated > x {
        truncated - 1.0
    } else {
        truncated
    }
}

/// [`floor_px`] of four values at once (finite, integer parts within `i32`), as integers: the
/// same truncate-and-correct arithmetic, so the same whole numbers.
#[inline(always)]
fn floor_px4(x: [f32; 4]) -> [i32; 4] {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{
            __m128i, _mm_add_epi32, _mm_castps_si128, _mm_cmpgt_ps, _mm_cvtepi32_ps,
            _mm_cvttps_epi32, _mm_setr_ps,
        };
        // SAFETY: SSE2 is part of the x86-64 baseline, so these instructions always exist;
        // `__m128i` and `[i32; 4]` have the same size, and every bit pattern is valid for both.
        unsafe {
            let v = _mm_setr_ps(x[0], x[1], x[2], x[3]);
            let truncated = _mm_cvttps_epi32(v);
            // All ones (−1) in the lanes where truncation went up, i.e. below zero.
            let above = _mm_castps_si128(_mm_cmpgt_ps(_mm_cvtepi32_ps(truncated), v));
            let floored: __m128i = _mm_add_epi32(truncated, above);
            std::mem::transmute::<__m128i, [i32; 4]>(floored)
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        x.map(|v| floor_px(v) as i32)
    }
}

/// The pixel boxes of eight consecutive faces ([`eight_screen_pixel_boxes_avx2`]).
#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy, Debug, Default)]
struct EightBoxes {
    /// Bit `lane`: the face needs the scalar path (a corner behind the near plane, or a
    /// projection that is not finite); its box below is meaningless.
    scalar: u8,
    /// Bit `lane`: the face covers a pixel centre, within the box below.
    kept: u8,
    /// Bit `lane`: of the kept faces, one whose box holds a single pixel centre; its depth
    /// there is in `depth` (`draw_triangle`'s).
    single: u8,
    depth: [f32; 8],
    first_col: [i32; 8],
    last_col: [i32; 8],
    first_row: [i32; 8],
    last_row: [i32; 8],
}

#[cfg(target_arch = "x86_64")]
impl EightBoxes {
    /// The box of a lane the vector path decided ([`screen_pixel_box`]'s answer for it).
    #[inline(always)]
    fn pixel_box(&self, lane: usize) -> Option<PixelBox> {
        (self.kept & (1 << lane) != 0).then(|| PixelBox {
            cols: [self.first_col[lane] as u32, self.last_col[lane] as u32],
            rows: [self.first_row[lane] as u32, self.last_row[lane] as u32],
            clipped: false,
        })
    }

    /// The pixel (column, row) and depth of a kept single-pixel lane.
    #[inline(always)]
    fn single_pixel(&self, lane: usize) -> Option<(u32, u32, f32)> {
        (self.single & (1 << lane) != 0).then(|| {
            (
                self.first_col[lane] as u32,
                self.first_row[lane] as u32,
                self.depth[lane],
            )
        })
    }
}

/// [`screen_pixel_box`] of eight faces at once, one face per AVX2 lane: the same f32
/// operations in the same order (no fused multiply-adds), so the same boxes and the same
/// single-pixel decisions. Faces with a corner behind the near plane, or with a corner's
/// projection not finite (where `min`/`max` would treat NaN differently), are left to the
/// scalar path (`scalar` bits).
///
/// # Safety
/// The CPU must have AVX2, and `3 * vertices_screen.len()` must fit an `i32`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn eight_screen_pixel_boxes_avx2(
    faces: &[VisibleFace; 8],
    vertices_screen: &[ScreenVertex],
    vertices_in_front: &[bool],
    width: usize,
    height: usize,
) -> EightBoxes {
    use std::arch::x86_64::*;
    const _: () = assert!(std::mem::size_of::<ScreenVertex>() == 3 * std::mem::size_of::<f32>());

    let mut offsets = [[0i32; 8]; 3];
    let mut scalar = 0u8;
    for (lane, face) in faces.iter().enumerate() {
        let mut in_front = true;
        for (corner, &v) in face.corners.iter().enumerate() {
            // Indexing checks every corner against the slot count (the same length as
            // `vertices_screen`), so the gathers below stay inside the projections.
            in_front &= vertices_in_front[v as usize];
            offsets[corner][lane] = 3 * v as i32;
        }
        scalar |= u8::from(!in_front) << lane;
    }
    let mut out = EightBoxes {
        scalar,
        ..EightBoxes::default()
    };
    // SAFETY: AVX2 is present (the caller's contract); every offset addresses a float of
    // `vertices_screen` (checked above, `ScreenVertex` is three floats, `repr(C)`); the stores
    // write the 8-lane arrays of `out`, unaligned.
    unsafe {
        let base = vertices_screen.as_ptr() as *const f32;
        let sign = _mm256_set1_ps(-0.0);
        let infinity = _mm256_set1_ps(f32::INFINITY);
        let half = _mm256_set1_ps(0.5);
        let zero = _mm256_setzero_ps();
        let mut x = [zero; 3];
        let mut y = [zero; 3];
        let mut inv_depth = [zero; 3];
        let mut finite = _mm256_castsi256_ps(_mm256_set1_epi32(-1));
        for corner in 0..3 {
            let offset = _mm256_loadu_si256(offsets[corner].as_ptr() as *const __m256i);
            x[corner] = _mm256_i32gather_ps::<4>(base, offset);
            y[corner] = _mm256_i32gather_ps::<4>(base.add(1), offset);
            inv_depth[corner] = _mm256_i32gather_ps::<4>(base.add(2), offset);
            for v in [x[corner], y[corner]] {
                finite = _mm256_and_ps(
                    finite,
                    _mm256_cmp_ps::<_CMP_LT_OQ>(_mm256_andnot_ps(sign, v), infinity),
                );
            }
        }
        out.scalar |= !(_mm256_movemask_ps(finite) as u8);

        // The bounding box (all corners finite in the lanes that count, so min/max are exact).
        let min_x = _mm256_min_ps(_mm256_min_ps(x[0], x[1]), x[2]);
        let min_y = _mm256_min_ps(_mm256_min_ps(y[0], y[1]), y[2]);
        let max_x = _mm256_max_ps(_mm256_max_ps(x[0], x[1]), x[2]);
        let max_y = _mm256_max_ps(_mm256_max_ps(y[0], y[1]), y[2]);

        // `pixel_box`.
        let (width_f, height_f) = (width as f32, height as f32);
        let outside = _mm256_or_ps(
            _mm256_or_ps(
                _mm256_cmp_ps::<_CMP_LT_OQ>(max_x, half),
                _mm256_cmp_ps::<_CMP_LT_OQ>(max_y, half),
            ),
            _mm256_or_ps(
                _mm256_cmp_ps::<_CMP_GT_OQ>(min_x, _mm256_set1_ps(width_f - 0.5)),
                _mm256_cmp_ps::<_CMP_GT_OQ>(min_y, _mm256_set1_ps(height_f - 0.5)),
            ),
        );
        let floor = |v: __m256| {
            let truncated = _mm256_cvttps_epi32(v);
            let above = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_GT_OQ>(
                _mm256_cvtepi32_ps(truncated),
                v,
            ));
            _mm256_add_epi32(truncated, above)
        };
        let minus_one = _mm256_set1_ps(-1.0);
        let negate = |v: __m256| _mm256_xor_ps(v, sign);
        let minus_first_col = floor(negate(_mm256_max_ps(_mm256_sub_ps(min_x, half), minus_one)));
        let minus_first_row = floor(negate(_mm256_max_ps(_mm256_sub_ps(min_y, half), minus_one)));
        let last_col = floor(_mm256_min_ps(
            _mm256_sub_ps(max_x, half),
            _mm256_set1_ps(width_f),
        ));
        let last_row = floor(_mm256_min_ps(
            _mm256_sub_ps(max_y, half),
            _mm256_set1_ps(height_f),
        ));
        let zero_i = _mm256_setzero_si256();
        let first_col = _mm256_max_epi32(_mm256_sub_epi32(zero_i, minus_first_col), zero_i);
        let first_row = _mm256_max_epi32(_mm256_sub_epi32(zero_i, minus_first_row), zero_i);
        let last_col = _mm256_min_epi32(last_col, _mm256_set1_epi32(width as i32 - 1));
        let last_row = _mm256_min_epi32(last_row, _mm256_set1_epi32(height as i32 - 1));
        let empty = _mm256_or_si256(
            _mm256_cmpgt_epi32(first_row, last_row),
            _mm256_cmpgt_epi32(first_col, last_col),
        );
        let mut rejected = _mm256_or_ps(outside, _mm256_castsi256_ps(empty));

        // A box around a single pixel centre: `TriangleSetup::new`, `at` and `depth(…, 0.0)`.
        let single = _mm256_andnot_ps(
            rejected,
            _mm256_castsi256_ps(_mm256_and_si256(
                _mm256_cmpeq_epi32(first_row, last_row),
                _mm256_cmpeq_epi32(first_col, last_col),
            )),
        );
        if _mm256_movemask_ps(single) != 0 {
            let edge_function = |ax: __m256, ay: __m256, bx: __m256, by: __m256, px, py| {
                _mm256_sub_ps(
                    _mm256_mul_ps(_mm256_sub_ps(bx, ax), _mm256_sub_ps(py, ay)),
                    _mm256_mul_ps(_mm256_sub_ps(by, ay), _mm256_sub_ps(px, ax)),
                )
            };
            let signed_area = edge_function(x[0], y[0], x[1], y[1], x[2], y[2]);
            let area = _mm256_andnot_ps(sign, signed_area);
            let degenerate = _mm256_or_ps(
                _mm256_cmp_ps::<_CMP_NLT_UQ>(area, infinity),
                _mm256_cmp_ps::<_CMP_LT_OQ>(area, _mm256_set1_ps(1e-12)),
            );
            let orientation = _mm256_or_ps(_mm256_set1_ps(1.0), _mm256_and_ps(signed_area, sign));
            let inv_area = _mm256_div_ps(_mm256_set1_ps(1.0), area);
            let centre_x = _mm256_add_ps(_mm256_cvtepi32_ps(first_col), half);
            let centre_y = _mm256_add_ps(_mm256_cvtepi32_ps(first_row), half);
            let edges = [(1, 2), (2, 0), (0, 1)];
            let mut w = [zero; 3];
            let mut step_x = [zero; 3];
            let mut inv_depth_scaled = [zero; 3];
            for (i, &(a, b)) in edges.iter().enumerate() {
                step_x[i] = _mm256_mul_ps(negate(_mm256_sub_ps(y[b], y[a])), orientation);
                w[i] = _mm256_mul_ps(
                    edge_function(x[a], y[a], x[b], y[b], centre_x, centre_y),
                    orientation,
                );
                inv_depth_scaled[i] = _mm256_mul_ps(inv_depth[i], inv_area);
            }
            let dot = |a: &[__m256; 3], b: &[__m256; 3]| {
                _mm256_add_ps(
                    _mm256_add_ps(_mm256_mul_ps(a[0], b[0]), _mm256_mul_ps(a[1], b[1])),
                    _mm256_mul_ps(a[2], b[2]),
                )
            };
            let inv_depth_step_x = dot(&step_x, &inv_depth_scaled);
            let inv_depth_start = dot(&w, &inv_depth_scaled);
            let mut miss = degenerate;
            for i in 0..3 {
                let at_offset = _mm256_add_ps(w[i], _mm256_mul_ps(step_x[i], zero));
                miss = _mm256_or_ps(miss, _mm256_cmp_ps::<_CMP_LT_OQ>(at_offset, zero));
            }
            let sum = _mm256_add_ps(inv_depth_start, _mm256_mul_ps(inv_depth_step_x, zero));
            miss = _mm256_or_ps(miss, _mm256_cmp_ps::<_CMP_LE_OQ>(sum, zero));
            rejected = _mm256_or_ps(rejected, _mm256_and_ps(single, miss));
            // `TriangleSetup::depth`'s `1 / sum` (IEEE division, as the scalar path).
            let depth = _mm256_div_ps(_mm256_set1_ps(1.0), sum);
            _mm256_storeu_ps(out.depth.as_mut_ptr(), depth);
            out.single = _mm256_movemask_ps(_mm256_andnot_ps(rejected, single)) as u8;
        }
        out.kept = !(_mm256_movemask_ps(rejected) as u8) & !out.scalar;
        out.single &= out.kept;
        _mm256_storeu_si256(out.first_col.as_mut_ptr() as *mut __m256i, first_col);
        _mm256_storeu_si256(out.last_col.as_mut_ptr() as *mut __m256i, last_col);
        _mm256_storeu_si256(out.first_row.as_mut_ptr() as *mut __m256i, first_row);
        _mm256_storeu_si256(out.last_row.as_mut_ptr() as *mut __m256i, last_row);
    }
    out
}

/// `ceil` counterpart of [`floor_px`].
#[inline(always)]
fn ceil_px(x: f32) -> f32 {
    -floor_px(-x)
}

fn is_back_facing(corners: &[Vec3; 3]) -> bool {
    let normal = (corners[1] - corners[0]).cross(corners[2] - corners[0]);
    normal.dot(corners[0]) >= 0.0
}

/// Clips a face that crosses the near plane (up to 4 corners) and draws the resulting triangles.
fn draw_clipped_face(
    corners: &[Vec3; 3],
    face: &PreparedFace,
    projector: &Projector,
    target: &mut BandTarget,
) {
    let near = projector.near_m;
    let mut polygon = [Vec3::ZERO; 4];
    let mut count = 0;
    for i in 0..3 {
        let current = corners[i];
        let next = corners[(i + 1) % 3];
        let current_in = current.z >= near;
        let next_in = next.z >= near;
        if current_in {
            polygon[count] = current;
            count += 1;
        }
        if current_in != next_in {
            let t = (near - current.z) / (next.z - current.z);
            polygon[count] = current.lerp(next, t);
            count += 1;
        }
    }
    let screen = polygon.map(|p| projector.screen_vertex(p));
    for i in 1..count.saturating_sub(1) {
        let triangle = [screen[0], screen[i], screen[i + 1]];
        if let Some([cols, rows]) = triangle_pixel_box(&triangle, target.width, target.height) {
            draw_triangle(&triangle, face, cols, rows, target);
        }
    }
}

/// Depth-tests one projected triangle (entirely in front of the near plane) into the band:
/// writes depth and the face's slot where it is nearest. `cols` and `rows` are the pixel box of
/// its bounding box in the image ([`triangle_pixel_box`]). Edge functions and `1/z` are affine in
/// the image, so each row is evaluated once at its start and stepped along the row; the covered
/// span of a row is solved from the three edge functions, so no time goes to pixels outside it.
fn draw_triangle(
    screen: &[ScreenVertex; 3],
    face: &PreparedFace,
    cols: [u32; 2],
    rows: [u32; 2],
    target: &mut BandTarget,
) {
    let (slot, face_index) = (face.slot, face.face_index);
    let Some(setup) = TriangleSetup::new(screen) else {
        return;
    };
    let step_x = setup.step_x;

    let row_start = (rows[0] as usize).max(target.first_row);
    let row_end = (rows[1] as usize).min(target.first_row + target.rows - 1);
    let (col_start, col_end) = (cols[0] as usize, cols[1] as usize);
    if !(row_start <= row_end && col_start <= col_end) {
        return;
    }

    // A box of at most eight pixels (a small triangle of a dense mesh): every pixel of it in
    // one vector, as the rows below would test them.
    #[cfg(target_arch = "x86_64")]
    if target.avx2
        && target.grid.is_none()
        && (row_end - row_start + 1) * (col_end - col_start + 1) <= 8
    {
        // SAFETY: `target.avx2` only when the CPU has AVX2; the box's rows are the band's and
        // its columns the image's (clamped above).
        unsafe {
            draw_small_box_avx2(
                &setup,
                [col_start, col_end],
                [row_start, row_end],
                slot,
                face_index,
                target,
            )
        };
        return;
    }

    let span_first = col_start as f32;
    let span_last = col_end as f32;

    // A grid-points rendering visits the grid's rows and, below, columns only: each pixel's
    // value depends on the box's first column and its own row and column alone.
    let (first_row, row_step) = target.grid.map_or((row_start, 1), |g| {
        (g.first_from(row_start), g.stride as usize)
    });
    for row in (first_row..=row_end).step_by(row_step) {
        let start = Vec2::new(col_start as f32 + 0.5, row as f32 + 0.5);
        let (w_start, inv_depth_start) = setup.at(start);
        // Columns where every edge function is >= 0, widened by one column against rounding
        // (the per-pixel test below is exact with respect to the stepped values).
        // Narrow boxes (most triangles of a dense mesh) just test every pixel.
        let mut first = span_first;
        let mut last = span_last;
        if col_end - col_start >= NARROW_SPAN_PX {
            let width = span_last - span_first;
            for i in 0..3 {
                if step_x[i] > 0.0 {
                    let bound = (-w_start[i] / step_x[i]).clamp(-1.0, width + 1.0);
                    first = first.max(span_first + ceil_px(bound) - 1.0);
                } else if step_x[i] < 0.0 {
                    let bound = (w_start[i] / -step_x[i]).clamp(-1.0, width + 1.0);
                    last = last.min(span_first + floor_px(bound) + 1.0);
                } else if w_start[i] < 0.0 {
                    first = f32::INFINITY;
                }
            }
            if first > last {
                continue;
            }
        }
        let (first, last) = (first as usize, last as usize);
        let line = (row - target.first_row) * target.width;
        let span = Span {
            w_start,
            inv_depth_start,
            col_start,
            line,
        };
        if let Some(grid) = target.grid {
            for col in (grid.first_from(first)..=last).step_by(grid.stride as usize) {
                span.draw_pixel(&setup, col, slot, face_index, target);
            }
            continue;
        }
        let mut col = first;
        #[cfg(target_arch = "x86_64")]
        if target.avx2 && last + 1 - first >= 8 {
            // SAFETY: `target.avx2` only when the CPU has AVX2; `first..=last` are columns of
            // the band's rows (clamped to the pixel box, inside the image).
            col = unsafe { draw_span_avx2(&setup, &span, first, last, slot, face_index, target) };
        }
        for col in col..=last {
            span.draw_pixel(&setup, col, slot, face_index, target);
        }
    }
}

/// One row of a triangle: its edge functions and `1/z` sum at `col_start` (the pixel box's first
/// column) and where the row starts in the band.
struct Span {
    w_start: [f32; 3],
    inv_depth_start: f32,
    col_start: usize,
    line: usize,
}

impl Span {
    /// Depth-tests the pixel at `col` ([`TriangleSetup::depth`], [`BandTarget::depth_test`]).
    #[inline(always)]
    fn draw_pixel(
        &self,
        setup: &TriangleSetup,
        col: usize,
        slot: u32,
        face_index: u32,
        target: &mut BandTarget,
    ) {
        let offset = (col - self.col_start) as f32;
        if let Some(depth) = setup.depth(&self.w_start, self.inv_depth_start, offset) {
            target.depth_test(self.line + col, depth, slot, face_index);
        }
    }
}

/// [`Span::draw_pixel`] of the columns `first..` eight at a time, one pixel per AVX2 lane: the
/// same f32 operations in the same order (no fused multiply-adds; IEEE division), so the same
/// depths and the same winners. A group where the face ties a pixel's depth with another face
/// (the lower face index wins) goes pixel by pixel. Returns the first column not drawn (fewer
/// than eight left before `last`).
///
/// # Safety
/// The CPU must have AVX2, and `first..=last` must be columns of the band's rows
/// (`last < target.width`).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn draw_span_avx2(
    setup: &TriangleSetup,
    span: &Span,
    first: usize,
    last: usize,
    slot: u32,
    face_index: u32,
    target: &mut BandTarget,
) -> usize {
    use std::arch::x86_64::*;
    let lanes = _mm256_setr_ps(0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0);
    let w_start = span.w_start.map(|w| _mm256_set1_ps(w));
    let step_x = setup.step_x.map(|step| _mm256_set1_ps(step));
    let inv_depth_start = _mm256_set1_ps(span.inv_depth_start);
    let inv_depth_step_x = _mm256_set1_ps(setup.inv_depth_step_x);
    let zero = _mm256_setzero_ps();
    let one = _mm256_set1_ps(1.0);
    let no_face = _mm256_set1_epi32(NO_FACE as i32);
    let slots = _mm256_set1_epi32(slot as i32);
    let all = _mm256_castsi256_ps(_mm256_set1_epi32(-1));
    let mut col = first;
    while col + 8 <= last + 1 {
        // Offsets below 2²⁴: the lane's `(col + lane − col_start) as f32` exactly.
        let offset = _mm256_add_ps(_mm256_set1_ps((col - span.col_start) as f32), lanes);
        let sum_inv_depth = _mm256_add_ps(inv_depth_start, _mm256_mul_ps(inv_depth_step_x, offset));
        let mut outside = _mm256_cmp_ps::<_CMP_LE_OQ>(sum_inv_depth, zero);
        for edge in 0..3 {
            let w = _mm256_add_ps(w_start[edge], _mm256_mul_ps(step_x[edge], offset));
            outside = _mm256_or_ps(outside, _mm256_cmp_ps::<_CMP_LT_OQ>(w, zero));
        }
        let inside = _mm256_andnot_ps(outside, all);
        if _mm256_movemask_ps(inside) != 0 {
            let depth = _mm256_div_ps(one, sum_inv_depth);
            let index = span.line + col;
            // SAFETY: `index + 7 = line + col + 7 <= line + last < line + width`, a pixel of the
            // band (the caller's contract); unaligned loads and masked stores of eight lanes.
            unsafe {
                let depth_at = target.depth.as_mut_ptr().add(index);
                let slot_at = target.face_slot.as_mut_ptr().add(index) as *mut __m256i;
                let current_depth = _mm256_loadu_ps(depth_at);
                let empty =
                    _mm256_castsi256_ps(_mm256_cmpeq_epi32(_mm256_loadu_si256(slot_at), no_face));
                let tied = _mm256_andnot_ps(
                    empty,
                    _mm256_and_ps(inside, _mm256_cmp_ps::<_CMP_EQ_OQ>(depth, current_depth)),
                );
                if _mm256_movemask_ps(tied) != 0 {
                    for lane_col in col..col + 8 {
                        span.draw_pixel(setup, lane_col, slot, face_index, target);
                    }
                } else {
                    let farther = _mm256_cmp_ps::<_CMP_GT_OQ>(depth, current_depth);
                    let write = _mm256_castps_si256(_mm256_and_ps(
                        inside,
                        _mm256_or_ps(empty, _mm256_andnot_ps(farther, all)),
                    ));
                    _mm256_maskstore_ps(depth_at, write, depth);
                    _mm256_maskstore_epi32(slot_at as *mut i32, write, slots);
                }
            }
        }
        col += 8;
    }
    col
}

/// [`draw_triangle`]'s rows of a pixel box of at most eight pixels (narrower than
/// [`NARROW_SPAN_PX`], so every pixel is tested), one pixel per AVX2 lane in row-major order:
/// each lane's row start ([`TriangleSetup::at`]) and its column's step
/// ([`TriangleSetup::depth`]) with the same f32 operations in the same order (no fused
/// multiply-adds; IEEE division), then the scalar depth test of each covered pixel.
///
/// # Safety
/// The CPU must have AVX2; `rows` must be rows of the band and `cols` columns of the image, and
/// the box at most eight pixels.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn draw_small_box_avx2(
    setup: &TriangleSetup,
    cols: [usize; 2],
    rows: [usize; 2],
    slot: u32,
    face_index: u32,
    target: &mut BandTarget,
) {
    use std::arch::x86_64::*;
    let box_cols = cols[1] + 1 - cols[0];
    let pixels = (rows[1] + 1 - rows[0]) * box_cols;
    debug_assert!(pixels <= 8);
    let mut centre_y = [0.0f32; 8];
    let mut offset = [0.0f32; 8];
    for lane in 0..pixels {
        centre_y[lane] = (rows[0] + lane / box_cols) as f32 + 0.5;
        offset[lane] = (lane % box_cols) as f32;
    }
    // SAFETY (whole body): AVX2 is present (the caller's contract); the loads read the
    // eight-lane arrays above and the store writes `depth` below.
    unsafe {
        let centre_y = _mm256_loadu_ps(centre_y.as_ptr());
        let offset = _mm256_loadu_ps(offset.as_ptr());
        let centre_x = _mm256_set1_ps(cols[0] as f32 + 0.5);
        let zero = _mm256_setzero_ps();
        let orientation = _mm256_set1_ps(setup.orientation);
        let mut w_start = [zero; 3];
        for (edge, &(a, b)) in setup.edges.iter().enumerate() {
            // `edge_function(a, b, centre)`, then the orientation.
            let across = _mm256_mul_ps(
                _mm256_set1_ps(b.x - a.x),
                _mm256_sub_ps(centre_y, _mm256_set1_ps(a.y)),
            );
            let along = _mm256_mul_ps(
                _mm256_set1_ps(b.y - a.y),
                _mm256_sub_ps(centre_x, _mm256_set1_ps(a.x)),
            );
            w_start[edge] = _mm256_mul_ps(_mm256_sub_ps(across, along), orientation);
        }
        let inv_depth = setup.inv_depth.map(|v| _mm256_set1_ps(v));
        let inv_depth_start = _mm256_add_ps(
            _mm256_add_ps(
                _mm256_mul_ps(w_start[0], inv_depth[0]),
                _mm256_mul_ps(w_start[1], inv_depth[1]),
            ),
            _mm256_mul_ps(w_start[2], inv_depth[2]),
        );
        let mut outside = _mm256_setzero_ps();
        for (edge, &step) in setup.step_x.iter().enumerate() {
            let w = _mm256_add_ps(w_start[edge], _mm256_mul_ps(_mm256_set1_ps(step), offset));
            outside = _mm256_or_ps(outside, _mm256_cmp_ps::<_CMP_LT_OQ>(w, zero));
        }
        let sum = _mm256_add_ps(
            inv_depth_start,
            _mm256_mul_ps(_mm256_set1_ps(setup.inv_depth_step_x), offset),
        );
        outside = _mm256_or_ps(outside, _mm256_cmp_ps::<_CMP_LE_OQ>(sum, zero));
        let inside = !(_mm256_movemask_ps(outside) as u32) & ((1u32 << pixels) - 1);
        if inside == 0 {
            return;
        }
        let mut depth = [0.0f32; 8];
        _mm256_storeu_ps(depth.as_mut_ptr(), _mm256_div_ps(_mm256_set1_ps(1.0), sum));
        let mut lanes = inside;
        while lanes != 0 {
            let lane = lanes.trailing_zeros() as usize;
            lanes &= lanes - 1;
            let row = rows[0] + lane / box_cols;
            let col = cols[0] + lane % box_cols;
            let index = (row - target.first_row) * target.width + col;
            target.depth_test(index, depth[lane], slot, face_index);
        }
    }
}

/// Fills the normals of a rasterised band from the winning face of each pixel: the face normal,
/// or the vertex normals interpolated with the perspective-correct barycentrics of the point the
/// pixel ray hits on the face (exact for clipped faces too, since it works in 3D).
fn shade_band(
    target: &BandTarget,
    normal_out: &mut [Vec3],
    vertices_cam: &[Vec3],
    vertex_normals_cam: Option<&[Vec3]>,
    projector: &Projector,
) {
    for local_row in 0..target.rows {
        let y = (target.first_row + local_row) as f32 + 0.5;
        let line = local_row * target.width;
        for col in 0..target.width {
            let index = line + col;
            let slot = target.face_slot[index];
            if slot == NO_FACE {
                continue;
            }
            let face = target.visible_faces[slot as usize].corners;
            let [a, b, c] = face.map(|v| vertices_cam[v as usize]);
            let edge_ab = b - a;
            let edge_ac = c - a;
            let face_normal = || edge_ab.cross(edge_ac).normalize_or_zero();
            normal_out[index] = match vertex_normals_cam {
                None => face_normal(),
                Some(normals) => {
                    // Möller–Trumbore from the camera centre along the pixel ray.
                    let ray = projector.ray(Vec2::new(col as f32 + 0.5, y));
                    let p = ray.cross(edge_ac);
                    let determinant = edge_ab.dot(p);
                    let degenerate = determinant * determinant
                        <= f32::EPSILON
                            * f32::EPSILON
                            * edge_ab.length_squared()
                            * edge_ac.length_squared()
                            * ray.length_squared();
                    if degenerate {
                        face_normal()
                    } else {
                        let to_origin = -a;
                        let u = to_origin.dot(p) / determinant;
                        let v = ray.dot(to_origin.cross(edge_ab)) / determinant;
                        let [na, nb, nc] = face.map(|i| normals[i as usize]);
                        let interpolated = na * (1.0 - u - v) + nb * u + nc * v;
                        let normal = interpolated.normalize_or_zero();
                        if normal == Vec3::ZERO {
                            face_normal()
                        } else {
                            normal
                        }
                    }
                }
            };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn four_floors_at_once_are_the_scalar_floors() {
        let mut values = vec![
            0.0f32, -0.0, 0.5, -0.5, 1.0, -1.0, 504.999, 505.0, -1e-7, 1e-7,
        ];
        values.extend((0..2000).map(|k| (k as f32 - 1000.0) * 0.2537));
        for quad in values.chunks(4) {
            let mut x = [0.0f32; 4];
            x[..quad.len()].copy_from_slice(quad);
            assert_eq!(floor_px4(x), x.map(|v| floor_px(v) as i32), "{x:?}");
            assert_eq!(floor_px4(x), x.map(|v| v.floor() as i32), "{x:?}");
        }
    }

    /// The binning's eight-at-once boxes are the scalar path's, face by face: sub-pixel faces
    /// (hits and misses of their one centre), faces across the border and outside, slivers,
    /// degenerate, huge and non-finite projections, corners behind the near plane.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn eight_boxes_at_once_are_the_scalar_boxes() {
        use rand::{Rng, SeedableRng};
        if !std::arch::is_x86_feature_detected!("avx2") {
            return;
        }
        let (width, height) = (505usize, 275usize);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let special = [
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            1e30,
            -1e30,
            0.5,
            505.5,
        ];
        let mut vertices = Vec::new();
        let mut in_front = Vec::new();
        for k in 0..6000 {
            let centre = Vec2::new(
                rng.random_range(-20.0..width as f32 + 20.0),
                rng.random_range(-20.0..height as f32 + 20.0),
            );
            // Triangles of a few tenths of a pixel to tens of pixels, a few with corners on
            // pixel centres or edges, or not finite.
            let size = [0.3f32, 1.0, 3.0, 40.0][k % 4];
            for corner in 0..3 {
                let mut position = centre
                    + Vec2::new(rng.random_range(-size..size), rng.random_range(-size..size));
                if k % 3 == 0 {
                    position = (position * 2.0).round() * 0.5;
                }
                if rng.random_range(0..100) == 0 {
                    position.x = special[rng.random_range(0..special.len())];
                }
                if k % 97 == 0 && corner == 1 {
                    position = vertices
                        .last()
                        .map_or(position, |v: &ScreenVertex| v.position_px);
                }
                vertices.push(ScreenVertex {
                    position_px: position,
                    inv_depth: rng.random_range(-0.05..1.0),
                });
                in_front.push(rng.random_range(0..50) != 0);
            }
        }
        let faces: Vec<VisibleFace> = (0..vertices.len() as u32 / 3)
            .map(|f| VisibleFace {
                face_index: f,
                corners: [3 * f, 3 * f + 1, 3 * f + 2],
            })
            .collect();
        let (mut kept, mut scalar, mut single) = (0, 0, 0);
        // One face drawn alone by `draw_triangle`, pixel by pixel: its depth at `(col, row)`.
        let drawn_depth = |screen: &[ScreenVertex; 3], pixel_box: &PixelBox, col: u32, row: u32| {
            let mut depth = vec![0.0f32; width * height];
            let mut face_slot = vec![NO_FACE; width * height];
            let visible_faces = [VisibleFace {
                face_index: 0,
                corners: [0; 3],
            }];
            let mut target = whole_image(
                width,
                height,
                &mut depth,
                &mut face_slot,
                &visible_faces,
                false,
            );
            let face = prepared(screen, 0, pixel_box);
            draw_triangle(screen, &face, pixel_box.cols, pixel_box.rows, &mut target);
            let index = row as usize * width + col as usize;
            (face_slot[index] == 0).then_some(depth[index])
        };
        for eight in faces.chunks_exact(8) {
            let eight: &[VisibleFace; 8] = eight.try_into().expect("eight faces");
            // SAFETY: AVX2 was detected above; 3 × 18 000 slots fit an i32.
            let boxes = unsafe {
                eight_screen_pixel_boxes_avx2(eight, &vertices, &in_front, width, height)
            };
            for (lane, face) in eight.iter().enumerate() {
                if boxes.scalar & (1 << lane) != 0 {
                    scalar += 1;
                    continue;
                }
                let screen = face.corners.map(|v| vertices[v as usize]);
                let expected = screen_pixel_box(&screen, width, height);
                let got = boxes.pixel_box(lane);
                kept += usize::from(got.is_some());
                assert_eq!(
                    got.map(|b| (b.cols, b.rows, b.clipped)),
                    expected.map(|b| (b.cols, b.rows, b.clipped)),
                    "face {} {screen:?}",
                    face.face_index
                );
                // A single-pixel face carries the depth `draw_triangle` writes there, bit for
                // bit; every other kept face's box holds more than one pixel centre.
                if let (Some((col, row, depth)), Some(pixel_box)) = (boxes.single_pixel(lane), got)
                {
                    single += 1;
                    assert_eq!((pixel_box.cols, pixel_box.rows), ([col; 2], [row; 2]));
                    assert_eq!(
                        drawn_depth(&screen, &pixel_box, col, row).map(f32::to_bits),
                        Some(depth.to_bits()),
                        "face {} {screen:?}",
                        face.face_index
                    );
                } else if let Some(pixel_box) = got {
                    assert!(
                        pixel_box.cols[0] != pixel_box.cols[1]
                            || pixel_box.rows[0] != pixel_box.rows[1],
                        "face {}: a single-pixel box without its depth",
                        face.face_index
                    );
                }
            }
        }
        // Both paths and both answers were exercised.
        assert!(
            kept > 1000 && scalar > 100 && single > 200,
            "kept {kept}, scalar {scalar}, single {single}"
        );
    }

    /// Rows of triangles drawn eight pixels at a time give the depths and winners of the pixel
    /// by pixel path, bit for bit: overlapping triangles of every size, some copies of the one
    /// before (equal depths: the lower face index, drawn first, keeps the pixel), some reaching behind the camera
    /// (`1/z` ≤ 0 over part of them).
    #[test]
    fn eight_pixels_at_once_are_the_pixel_by_pixel_depths_and_faces() {
        use rand::{Rng, SeedableRng};
        if !std::arch::is_x86_feature_detected!("avx2") {
            return;
        }
        let (width, height) = (97usize, 61usize);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let mut triangles: Vec<[ScreenVertex; 3]> = Vec::new();
        for k in 0..400 {
            if k % 5 == 4 {
                let copy = triangles[k - 1];
                triangles.push(copy);
                continue;
            }
            let size = [2.0f32, 9.0, 30.0, 80.0][k % 4];
            let centre = Vec2::new(
                rng.random_range(-10.0..width as f32 + 10.0),
                rng.random_range(-10.0..height as f32 + 10.0),
            );
            triangles.push(std::array::from_fn(|_| ScreenVertex {
                position_px: centre
                    + Vec2::new(rng.random_range(-size..size), rng.random_range(-size..size)),
                inv_depth: rng.random_range(-0.1..1.0),
            }));
        }
        let visible_faces: Vec<VisibleFace> = (0..triangles.len() as u32)
            .map(|f| VisibleFace {
                face_index: f,
                corners: [0; 3],
            })
            .collect();
        let draw = |avx2: bool| {
            let mut depth = vec![f32::INFINITY; width * height];
            let mut face_slot = vec![NO_FACE; width * height];
            let mut target = whole_image(
                width,
                height,
                &mut depth,
                &mut face_slot,
                &visible_faces,
                avx2,
            );
            // In order: each copy meets its original (the lower index) already drawn and loses.
            for (slot, screen) in triangles.iter().enumerate() {
                let Some(pixel_box) = screen_pixel_box(screen, width, height) else {
                    continue;
                };
                let face = prepared(screen, slot as u32, &pixel_box);
                draw_triangle(screen, &face, pixel_box.cols, pixel_box.rows, &mut target);
            }
            (depth, face_slot)
        };
        let (pixel_depth, pixel_faces) = draw(false);
        let (eight_depth, eight_faces) = draw(true);
        let bits = |depth: &[f32]| depth.iter().map(|d| d.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&eight_depth), bits(&pixel_depth));
        assert_eq!(eight_faces, pixel_faces);
        // Most pixels drawn; pixels tied between a face and its copy went to the face.
        let drawn = pixel_faces.iter().filter(|&&f| f != NO_FACE).count();
        let won_by = |rest: u32| {
            pixel_faces
                .iter()
                .filter(|&&f| f != NO_FACE && f % 5 == rest)
                .count()
        };
        assert!(drawn * 2 > width * height, "{drawn}");
        assert!(
            won_by(3) > 50 && won_by(4) == 0,
            "{} {}",
            won_by(3),
            won_by(4)
        );
    }

    /// A 2 m × 2 m square in the plane z = 5 m (world = camera), facing the camera.
    fn square_facing_camera() -> Mesh {
        let positions = [
            Vector3::new(-1.0, -1.0, 5.0),
            Vector3::new(1.0, -1.0, 5.0),
            Vector3::new(1.0, 1.0, 5.0),
            Vector3::new(-1.0, 1.0, 5.0),
        ];
        Mesh::from_world(&positions, vec![[0, 2, 1], [0, 3, 2]], None).unwrap()
    }

    #[test]
    fn square_covers_the_expected_pixels_at_the_expected_depth() {
        let mesh = square_facing_camera();
        let intrinsics = PinholeIntrinsics::centered(100.0, 100, 80);
        let mut out = RenderBuffers::new(100, 80);
        Rasterizer::new().render(
            &mesh,
            &intrinsics,
            &Rigid3::identity(),
            &RenderOptions::default(),
            &mut out,
        );
        // The square spans x in [50 - 20, 50 + 20) and y in [40 - 20, 40 + 20) pixels.
        assert_eq!(out.valid_count(), 40 * 40);
        assert!(out.is_valid(30, 20) && out.is_valid(69, 59));
        assert!(!out.is_valid(29, 40) && !out.is_valid(70, 40));
        assert!((out.depth_m().get(50, 40).unwrap() - 5.0).abs() < 1e-5);
        // Counter-clockwise seen from the camera (y down): the normal points at the camera.
        assert!(
            (*out.normal_cam().get(50, 40).unwrap() - Vec3::new(0.0, 0.0, -1.0)).length() < 1e-5
        );
    }

    #[test]
    fn a_plane_through_the_camera_is_clipped_not_dropped() {
        // A ground plane 2 m below a camera looking along +z, extending behind it.
        let positions = [
            Vector3::new(-50.0, 2.0, -50.0),
            Vector3::new(50.0, 2.0, -50.0),
            Vector3::new(50.0, 2.0, 50.0),
            Vector3::new(-50.0, 2.0, 50.0),
        ];
        let mesh = Mesh::from_world(&positions, vec![[0, 1, 2], [0, 2, 3]], None).unwrap();
        let intrinsics = PinholeIntrinsics::centered(50.0, 100, 100);
        let mut out = RenderBuffers::new(100, 100);
        Rasterizer::new().render(
            &mesh,
            &intrinsics,
            &Rigid3::identity(),
            &RenderOptions::default(),
            &mut out,
        );
        // Below the horizon (row 50) everything is ground; the bottom row is at depth 2 * 50 / 49.5.
        assert!(out.is_valid(10, 99) && out.is_valid(90, 60));
        assert!(!out.is_valid(50, 40));
        let depth = *out.depth_m().get(50, 99).unwrap();
        assert!((depth - 2.0 * 50.0 / 49.5).abs() < 1e-3, "{depth}");
    }

    /// An axis-aligned cube of side `2 * half_m` centred at `centre` (world), outward
    /// counter-clockwise faces, vertex normals pointing away from the centre (corner directions).
    fn cube(centre: Vector3<f64>, half_m: f64) -> Mesh {
        let corners: Vec<Vector3<f64>> = (0..8)
            .map(|i| {
                let sign = |bit: usize| if i & bit != 0 { 1.0 } else { -1.0 };
                centre + Vector3::new(sign(1), sign(2), sign(4)) * half_m
            })
            .collect();
        let normals: Vec<Vec3> = corners
            .iter()
            .map(|c| {
                let d = (c - centre).normalize();
                Vec3::new(d.x as f32, d.y as f32, d.z as f32)
            })
            .collect();
        // Quads as (a, b, c, d) counter-clockwise seen from outside.
        let quads = [
            [0, 2, 3, 1], // z-: normal (0, 0, -1)
            [4, 5, 7, 6], // z+
            [0, 1, 5, 4], // y-
            [2, 6, 7, 3], // y+
            [0, 4, 6, 2], // x-
            [1, 3, 7, 5], // x+
        ];
        let faces = quads
            .iter()
            .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
            .collect();
        Mesh::from_world(&corners, faces, Some(normals)).unwrap()
    }

    fn render_identity(mesh: &Mesh, options: &RenderOptions) -> RenderBuffers {
        let intrinsics = PinholeIntrinsics::centered(100.0, 100, 100);
        let mut out = RenderBuffers::new(100, 100);
        Rasterizer::new().render(mesh, &intrinsics, &Rigid3::identity(), options, &mut out);
        out
    }

    #[test]
    fn depth_and_faces_without_normals_are_those_of_the_full_rendering() {
        // Two cubes, one behind the other (occlusion), plus a plane through the camera (clipping).
        let mut positions: Vec<Vector3<f64>> = Vec::new();
        let mut faces: Vec<[u32; 3]> = Vec::new();
        for mesh in [
            cube(Vector3::new(0.3, 0.1, 5.0), 0.8),
            cube(Vector3::new(-0.4, -0.2, 7.0), 1.5),
        ] {
            let base = positions.len() as u32;
            positions.extend(mesh.positions_local_m().iter().map(|p| {
                mesh.origin_m() + Vector3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z))
            }));
            faces.extend(mesh.faces().iter().map(|f| f.map(|v| v + base)));
        }
        let mesh = Mesh::from_world(&positions, faces, None).unwrap();
        let intrinsics = PinholeIntrinsics::centered(80.0, 120, 90);
        let pose = Rigid3::new(
            nalgebra::UnitQuaternion::from_euler_angles(0.05, -0.1, 0.2),
            nalgebra::Vector3::new(0.1, -0.05, 0.3),
        );
        let options = RenderOptions::default();
        let mut full = RenderBuffers::new(120, 90);
        let mut rasterizer = Rasterizer::new();
        rasterizer.render(&mesh, &intrinsics, &pose, &options, &mut full);
        let mut geometry = RenderBuffers::new(120, 90);
        Rasterizer::depth_and_faces_only().render(
            &mesh,
            &intrinsics,
            &pose,
            &options,
            &mut geometry,
        );
        assert!(full.valid_count() > 1000, "{}", full.valid_count());
        assert_eq!(geometry.face_index().data(), full.face_index().data());
        assert_eq!(geometry.depth_m().data(), full.depth_m().data());
        assert!(geometry
            .normal_cam()
            .data()
            .iter()
            .all(|n| *n == Vec3::ZERO));
        assert!(full.normal_cam().data().iter().any(|n| *n != Vec3::ZERO));
    }

    #[test]
    fn cube_faces_are_wound_outward() {
        let mesh = cube(Vector3::zeros(), 1.0);
        for face_index in 0..mesh.face_count() {
            let [a, b, c] = mesh.faces()[face_index].map(|v| mesh.positions_local_m()[v as usize]);
            let centroid = (a + b + c) / 3.0;
            assert!(
                mesh.face_normal(face_index).dot(centroid) > 0.0,
                "face {face_index}"
            );
        }
    }

    #[test]
    fn unit_cube_depth_and_normals_at_chosen_pixels() {
        // Unit cube centred at (1.5, 0, 5) (camera = world frame, f = 100 px, 100 × 100 px).
        // Its front face z = 4.5 spans x in [1, 2] → columns 50 + [22.2, 44.4]; its left face
        // x = 1 (seen from the camera on its left) spans columns 50 + [100/5.5, 100/4.5] =
        // [68.18, 72.22].
        let mesh = cube(Vector3::new(1.5, 0.0, 5.0), 0.5);
        let face = render_identity(
            &mesh,
            &RenderOptions {
                normal_source: NormalSource::Face,
                ..RenderOptions::default()
            },
        );
        let vertex = render_identity(&mesh, &RenderOptions::default());
        let at = |col: usize, row: usize| row * 100 + col;
        let close = |a: Vec3, b: Vec3| (a - b).length() < 1e-5;

        // Front face, pixel (80, 42): ray (0.305, -0.075), depth 4.5.
        let p = at(80, 42);
        assert!(
            (face.depth_m.data()[p] - 4.5).abs() < 1e-5,
            "{}",
            face.depth_m.data()[p]
        );
        assert!(close(face.normal_cam.data()[p], Vec3::new(0.0, 0.0, -1.0)));
        // Vertex normals interpolate linearly over the face: n ∝ (2 (X − 1.5), 2 Y, −1) with
        // X = 0.305 · 4.5, Y = −0.075 · 4.5 (both triangles of the face fit the same linear map).
        let (x, y) = (0.305 * 4.5 - 1.5, -0.075 * 4.5);
        let expected = Vec3::new(2.0 * x, 2.0 * y, -1.0).normalize();
        assert!(
            close(vertex.normal_cam.data()[p], expected),
            "{} vs {expected}",
            vertex.normal_cam.data()[p]
        );
        assert_eq!(vertex.depth_m.data()[p], face.depth_m.data()[p]);

        // Left face, pixel (70, 50): ray (0.205, 0.005) meets x = 1 at z = 1 / 0.205.
        let p = at(70, 50);
        let z = 1.0 / 0.205;
        assert!(
            (face.depth_m.data()[p] - z).abs() < 1e-4,
            "{} vs {z}",
            face.depth_m.data()[p]
        );
        assert!(close(face.normal_cam.data()[p], Vec3::new(-1.0, 0.0, 0.0)));
        // On x = 1: n ∝ (−1, 2 Y, 2 (Z − 5)).
        let expected = Vec3::new(-1.0, 2.0 * 0.005 * z, 2.0 * (z - 5.0)).normalize();
        assert!(
            close(vertex.normal_cam.data()[p], expected),
            "{} vs {expected}",
            vertex.normal_cam.data()[p]
        );
        // The face index tells the two apart: x− is quad 4 (faces 8, 9), z− quad 0 (faces 0, 1).
        assert!(matches!(face.face_index.data()[p], 8 | 9));
        assert!(matches!(face.face_index.data()[at(80, 42)], 0 | 1));
    }

    #[test]
    fn silhouette_edges_land_on_the_expected_pixels() {
        // Cube centred on the axis at z = 5: its front face z = 4.5 spans ±0.5 / 4.5 · 100 =
        // ±11.11 px around the centre 50 → [38.89, 61.11]. Pixel centres inside: 39.5 … 60.5,
        // so columns and rows 39..=60 (22 of each) are covered, 38 and 61 are not.
        let mesh = cube(Vector3::new(0.0, 0.0, 5.0), 0.5);
        let out = render_identity(&mesh, &RenderOptions::default());
        for i in 0..100 {
            let inside = (39..=60).contains(&i);
            assert_eq!(out.is_valid(i, 50), inside, "column {i}");
            assert_eq!(out.is_valid(50, i), inside, "row {i}");
        }
        assert_eq!(out.valid_count(), 22 * 22);
        // Shifted right by 0.7 px (0.0315 m at 4.5 m): the edges move to 39.59 and 61.81, past
        // the centres 39.5 and 61.5, so the first and last covered columns become 40 and 61.
        let mesh = cube(Vector3::new(0.7 * 4.5 / 100.0, 0.0, 5.0), 0.5);
        let out = render_identity(&mesh, &RenderOptions::default());
        assert!(!out.is_valid(39, 50) && out.is_valid(40, 50));
        assert!(out.is_valid(61, 50) && !out.is_valid(62, 50));
    }

    /// A hilly ground with a cube on it, and an oblique camera, both shifted by `offset`.
    fn oblique_scene(offset: Vector3<f64>) -> (Mesh, Rigid3) {
        let mut positions = Vec::new();
        let cells = 20;
        for j in 0..=cells {
            for i in 0..=cells {
                let (x, y) = (i as f64 * 5.0 - 50.0, j as f64 * 5.0 - 50.0);
                let z = 2.0 * (x * 0.07).sin() * (y * 0.05).cos();
                positions.push(Vector3::new(x, y, z) + offset);
            }
        }
        let mut faces = Vec::new();
        let row = cells + 1;
        for j in 0..cells {
            for i in 0..cells {
                let v = (j * row + i) as u32;
                let r = row as u32;
                faces.push([v, v + 1, v + r + 1]);
                faces.push([v, v + r + 1, v + r]);
            }
        }
        let mut mesh = Mesh::from_world(&positions, faces, None).unwrap();
        mesh.append(&cube(Vector3::new(5.0, -3.0, 6.0) + offset, 6.0));
        mesh.compute_vertex_normals();
        let eye = Vector3::new(30.0, -35.0, 40.0) + offset;
        let pose = Rigid3::look_at(&eye, &offset, &Vector3::z()).unwrap();
        (mesh, pose)
    }

    #[test]
    fn a_georeferenced_scene_renders_like_the_same_scene_at_the_origin() {
        let intrinsics = PinholeIntrinsics::centered(150.0, 160, 120);
        let render = |offset: Vector3<f64>| {
            let (mesh, pose) = oblique_scene(offset);
            let mut out = RenderBuffers::new(160, 120);
            Rasterizer::new().render(
                &mesh,
                &intrinsics,
                &pose,
                &RenderOptions::default(),
                &mut out,
            );
            out
        };
        let local = render(Vector3::zeros());
        let utm = render(Vector3::new(512_345.0, 5_401_234.0, 250.0));
        assert!(
            local.valid_count() > 160 * 120 * 3 / 4,
            "{}",
            local.valid_count()
        );
        let mut worst_m = 0.0f32;
        for (a, b) in local.depth_m.data().iter().zip(utm.depth_m.data()) {
            assert_eq!(*a == 0.0, *b == 0.0);
            worst_m = worst_m.max((a - b).abs());
        }
        assert!(worst_m < 1e-3, "worst depth difference {worst_m} m");
        let differing_faces = local
            .face_index
            .data()
            .iter()
            .zip(utm.face_index.data())
            .filter(|(a, b)| a != b)
            .count();
        assert!(
            differing_faces < 20,
            "{differing_faces} pixels see another face"
        );
    }

    /// A whole image (one band) for `draw_triangle`.
    fn whole_image<'a>(
        width: usize,
        height: usize,
        depth: &'a mut [f32],
        face_slot: &'a mut [u32],
        visible_faces: &'a [VisibleFace],
        avx2: bool,
    ) -> BandTarget<'a> {
        BandTarget {
            first_row: 0,
            rows: height,
            width,
            height,
            depth,
            face_slot,
            visible_faces,
            avx2,
            grid: None,
        }
    }

    /// A face wholly in front of the near plane, slot and face index `slot`, as the binning
    /// prepares it.
    fn prepared(screen: &[ScreenVertex; 3], slot: u32, pixel_box: &PixelBox) -> PreparedFace {
        PreparedFace {
            screen: *screen,
            slot,
            face_index: slot,
            cols: pixel_box.cols,
            rows: pixel_box.rows,
            clipped: false,
        }
    }

    /// A ground of `cells` × `cells` square quads `quad_m` wide (two triangles each) at
    /// heights `height_m(x, y)`.
    fn ground(cells: usize, quad_m: f64, height_m: impl Fn(f64, f64) -> f64) -> Mesh {
        let row = cells + 1;
        let positions: Vec<Vector3<f64>> = (0..row * row)
            .map(|k| {
                let (x, y) = ((k % row) as f64 * quad_m, (k / row) as f64 * quad_m);
                Vector3::new(x, y, height_m(x, y))
            })
            .collect();
        let faces: Vec<[u32; 3]> = (0..cells * cells)
            .flat_map(|k| {
                let v = ((k / cells) * row + k % cells) as u32;
                let r = row as u32;
                [[v, v + 1, v + r + 1], [v, v + r + 1, v + r]]
            })
            .collect();
        Mesh::from_world(&positions, faces, None).unwrap()
    }

    #[test]
    fn culling_changes_no_pixel_of_depth_face_index_or_interpolated_normals() {
        // A hilly 300 m × 300 m ground of 2 m quads (45 000 faces, many grid cells) with a cube,
        // vertex normals, seen obliquely from one corner: most cells are culled.
        let mut mesh = ground(150, 2.0, |x, y| 3.0 * (x * 0.05).sin() * (y * 0.04).cos());
        mesh.append(&cube(Vector3::new(40.0, 40.0, 8.0), 6.0));
        mesh.compute_vertex_normals();
        let eye = Vector3::new(-10.0, -10.0, 40.0);
        let pose = Rigid3::look_at(&eye, &Vector3::new(25.0, 25.0, 0.0), &Vector3::z()).unwrap();
        let intrinsics = PinholeIntrinsics::centered(150.0, 160, 120);
        let options = RenderOptions::default();
        let mut rasterizer = Rasterizer::new();
        let mut culled = RenderBuffers::new(160, 120);
        rasterizer.render(&mesh, &intrinsics, &pose, &options, &mut culled);
        assert!(mesh.grid().cells().len() > 10);
        assert!(
            rasterizer.visible_face_count() * 2 < mesh.face_count(),
            "culling keeps {} of {} faces",
            rasterizer.visible_face_count(),
            mesh.face_count()
        );
        assert!(rasterizer.vertices_cam.len() * 2 < mesh.vertex_count());
        assert!(culled.valid_count() > 160 * 120 / 2);
        let whole = mesh.with_single_grid_cell();
        let mut all = RenderBuffers::new(160, 120);
        Rasterizer::new().render(&whole, &intrinsics, &pose, &options, &mut all);
        assert_eq!(culled.depth_m, all.depth_m);
        assert_eq!(culled.face_index, all.face_index);
        assert_eq!(culled.normal_cam, all.normal_cam);
    }

    /// A grid-points rendering holds, at each grid pixel, the full rendering's depth and face bit
    /// for bit, and nothing elsewhere: a dense ground of sub-pixel triangles seen from afar and
    /// from just above it (faces through the near plane), with a cube, at several strides.
    #[test]
    fn grid_points_are_the_full_renderings_pixels() {
        let mut mesh = ground(240, 0.5, |x, y| 0.8 * (x * 0.3).sin() * (y * 0.2).cos());
        mesh.append(&cube(Vector3::new(60.0, 60.0, 4.0), 5.0));
        mesh.compute_vertex_normals();
        let target = Vector3::new(60.0, 60.0, 0.0);
        let poses = [
            Rigid3::look_at(&Vector3::new(-60.0, -40.0, 90.0), &target, &Vector3::z()).unwrap(),
            Rigid3::look_at(&Vector3::new(20.0, 15.0, 0.9), &target, &Vector3::z()).unwrap(),
        ];
        let intrinsics = PinholeIntrinsics::centered(150.0, 161, 119);
        let options = RenderOptions::default();
        let mut full = RenderBuffers::new(161, 119);
        let mut points = RenderBuffers::new(161, 119);
        let mut sampled = Rasterizer::depth_and_faces_only();
        let mut drawn = 0;
        for pose in &poses {
            Rasterizer::new().render(&mesh, &intrinsics, pose, &options, &mut full);
            for stride in [1, 3, 4, 5] {
                let grid = SampleGrid::centred(stride);
                sampled.render_grid_points(&mesh, &intrinsics, pose, &options, grid, &mut points);
                for row in 0..119 {
                    for col in 0..161 {
                        let index = row * 161 + col;
                        let (depth, face) = (
                            points.depth_m.data()[index],
                            points.face_index.data()[index],
                        );
                        if grid.holds(row as u32) && grid.holds(col as u32) {
                            drawn += usize::from(face != NO_FACE);
                            assert_eq!(
                                (depth.to_bits(), face),
                                (
                                    full.depth_m.data()[index].to_bits(),
                                    full.face_index.data()[index]
                                ),
                                "stride {stride}, pixel ({col}, {row})"
                            );
                        } else {
                            assert_eq!(
                                (depth, face),
                                (0.0, NO_FACE),
                                "stride {stride}, ({col}, {row})"
                            );
                        }
                    }
                }
                assert!(points.normal_cam.data().iter().all(|n| *n == Vec3::ZERO));
            }
        }
        assert!(drawn > 161 * 119, "{drawn} grid pixels with a face");
    }

    #[test]
    fn re_rendering_into_the_same_buffers_allocates_nothing() {
        let (mesh, pose) = oblique_scene(Vector3::zeros());
        let intrinsics = PinholeIntrinsics::centered(150.0, 160, 120);
        let mut rasterizer = Rasterizer::new();
        let mut out = RenderBuffers::new(160, 120);
        let options = RenderOptions::default();
        rasterizer.render(&mesh, &intrinsics, &pose, &options, &mut out);
        let fingerprint = |r: &Rasterizer, out: &RenderBuffers| {
            let mut prints = vec![
                (
                    out.depth_m.data().as_ptr() as usize,
                    out.depth_m.pixel_count(),
                ),
                (
                    out.normal_cam.data().as_ptr() as usize,
                    out.normal_cam.pixel_count(),
                ),
                (
                    out.face_index.data().as_ptr() as usize,
                    out.face_index.pixel_count(),
                ),
                (r.vertices_cam.as_ptr() as usize, r.vertices_cam.capacity()),
                (r.normals_cam.as_ptr() as usize, r.normals_cam.capacity()),
                (
                    r.vertices_screen.as_ptr() as usize,
                    r.vertices_screen.capacity(),
                ),
                (
                    r.vertices_in_front.as_ptr() as usize,
                    r.vertices_in_front.capacity(),
                ),
                (r.bins.as_ptr() as usize, r.bins.capacity()),
                (
                    r.visible_faces.as_ptr() as usize,
                    r.visible_faces.capacity(),
                ),
                (
                    r.visible_vertices.as_ptr() as usize,
                    r.visible_vertices.capacity(),
                ),
            ];
            for chunk in &r.bins {
                prints.push((chunk.bands.as_ptr() as usize, chunk.bands.capacity()));
                prints.push((chunk.prepared.as_ptr() as usize, chunk.prepared.capacity()));
                for band in &chunk.bands {
                    prints.push((band.as_ptr() as usize, band.capacity()));
                }
            }
            prints
        };
        let before = fingerprint(&rasterizer, &out);
        let first_depth = out.depth_m.clone();
        rasterizer.render(&mesh, &intrinsics, &pose, &options, &mut out);
        assert_eq!(fingerprint(&rasterizer, &out), before);
        assert_eq!(out.depth_m, first_depth);
    }

    #[test]
    fn back_face_culling_drops_faces_turned_away() {
        // The square of the first test with its winding reversed: it faces away.
        let positions = [
            Vector3::new(-1.0, -1.0, 5.0),
            Vector3::new(1.0, -1.0, 5.0),
            Vector3::new(1.0, 1.0, 5.0),
            Vector3::new(-1.0, 1.0, 5.0),
        ];
        let away = Mesh::from_world(&positions, vec![[0, 1, 2], [0, 2, 3]], None).unwrap();
        let culled = RenderOptions {
            cull_back_faces: true,
            ..RenderOptions::default()
        };
        let shown = render_identity(&away, &RenderOptions::default());
        assert_eq!(shown.valid_count(), 40 * 40);
        // Without culling the normal is the face's, pointing away from the camera.
        assert!(
            (shown.normal_cam.data()[50 * 100 + 50] - Vec3::new(0.0, 0.0, 1.0)).length() < 1e-5
        );
        assert_eq!(render_identity(&away, &culled).valid_count(), 0);
        assert_eq!(
            render_identity(&square_facing_camera(), &culled).valid_count(),
            40 * 40
        );
        // A closed cube looks the same either way (its front faces win the depth test) ...
        let mesh = cube(Vector3::new(0.3, -0.2, 5.0), 0.5);
        let plain = render_identity(&mesh, &RenderOptions::default());
        let with_culling = render_identity(&mesh, &culled);
        assert_eq!(plain.depth_m, with_culling.depth_m);
        assert_eq!(plain.face_index, with_culling.face_index);
        // ... but seen from inside, culling removes every face.
        let inside = cube(Vector3::new(0.0, 0.0, 0.0), 3.0);
        assert_eq!(
            render_identity(&inside, &RenderOptions::default()).valid_count(),
            100 * 100
        );
        assert_eq!(render_identity(&inside, &culled).valid_count(), 0);
    }
}
