//! Renderer benchmark: a procedural ~1M-triangle town (terrain heightfield + box buildings on a
//! grid, vertex normals) seen from an oblique aerial pose, rendered and turned into an ASG image
//! at the paper's 505×275 and at 1920×1080. One rendering per coarse pose per frame goes through
//! this path, so its speed bounds frames per second.
//!
//! `cargo bench --bench render` runs criterion and then prints a summary per size from its own
//! timing loop: median and minimum wall ms per frame, CPU ms per frame (all threads, from
//! `/proc/self/stat`: the figure least disturbed by other load on a shared machine) and
//! triangles per second. `cargo bench --bench render -- no_such_bench` prints only the summary.
//!
//! Scene mode: `RENDER_BENCH_SCENE=<folder of asgreg synth>` renders that scene's model at the
//! poses of its `gt` and `initial/*` models instead (the meshes and poses a frame renders;
//! `RENDER_BENCH_MODEL=model_lod.ply` for the simplified model `eval --model lod` registers to),
//! and prints the CPU ms per rendering (full: depth, normals, face index; + ASG; depth and faces
//! only; depth and faces at the 4-px grid of δ's visible points only)
//! and a hash of every output bit per pose and in all (`RENDER_BENCH_HASHES=1` per pose), so that
//! two builds can be checked to render the very same bits. Run it with `RAYON_NUM_THREADS=1` for
//! the CPU of one rendering without the threads' overhead.

use std::time::Instant;

use asgreg::core::camera::{Camera, PinholeIntrinsics};
use asgreg::core::image::Image;
use asgreg::core::mesh::Mesh;
use asgreg::core::raster::{Rasterizer, RenderBuffers, RenderOptions, SampleGrid};
use asgreg::core::reprojection::ReprojectionOptions;
use asgreg::core::rigid::Rigid3;
use asgreg::core::shading::{asg_from_normals, AsgOptions};
use asgreg::io::colmap::ColmapModel;
use asgreg::io::mesh_file::read_mesh;
use criterion::Criterion;
use nalgebra::Vector3;

/// Terrain cells per side (2 triangles each) and building grid per side (10 triangles each).
const TERRAIN_CELLS: usize = 600;
const TERRAIN_CELL_M: f64 = 2.0;
const BUILDINGS_PER_SIDE: usize = 168;

fn terrain_height_m(x: f64, y: f64) -> f64 {
    6.0 * (x * 0.004).sin() * (y * 0.005).cos() + 1.5 * (x * 0.031 + y * 0.017).sin()
}

/// A town: 720k terrain triangles + 28k buildings × 10 triangles ≈ 1.0M triangles.
fn procedural_town() -> Mesh {
    let extent_m = TERRAIN_CELLS as f64 * TERRAIN_CELL_M;
    let half_m = extent_m / 2.0;
    let mut positions = Vec::new();
    let mut faces = Vec::new();
    let row = TERRAIN_CELLS + 1;
    for j in 0..row {
        for i in 0..row {
            let (x, y) = (
                i as f64 * TERRAIN_CELL_M - half_m,
                j as f64 * TERRAIN_CELL_M - half_m,
            );
            positions.push(Vector3::new(x, y, terrain_height_m(x, y)));
        }
    }
    for j in 0..TERRAIN_CELLS {
        for i in 0..TERRAIN_CELLS {
            let v = (j * row + i) as u32;
            let r = row as u32;
            faces.push([v, v + 1, v + r + 1]);
            faces.push([v, v + r + 1, v + r]);
        }
    }
    let spacing_m = extent_m / BUILDINGS_PER_SIDE as f64;
    for j in 0..BUILDINGS_PER_SIDE {
        for i in 0..BUILDINGS_PER_SIDE {
            let cx = (i as f64 + 0.5) * spacing_m - half_m;
            let cy = (j as f64 + 0.5) * spacing_m - half_m;
            let hash = (i * 7919 + j * 104_729) % 97;
            let half_x = 1.5 + (hash % 5) as f64 * 0.4;
            let half_y = 1.5 + (hash % 7) as f64 * 0.3;
            let ground = terrain_height_m(cx, cy) - 0.5;
            let height = 4.0 + (hash % 11) as f64 * 1.5;
            let base = positions.len() as u32;
            for z in [ground, ground + height] {
                positions.extend([
                    Vector3::new(cx - half_x, cy - half_y, z),
                    Vector3::new(cx + half_x, cy - half_y, z),
                    Vector3::new(cx + half_x, cy + half_y, z),
                    Vector3::new(cx - half_x, cy + half_y, z),
                ]);
            }
            faces.push([base + 4, base + 5, base + 6]);
            faces.push([base + 4, base + 6, base + 7]);
            for k in 0..4u32 {
                let l = (k + 1) % 4;
                faces.push([base + k, base + l, base + 4 + l]);
                faces.push([base + k, base + 4 + l, base + 4 + k]);
            }
        }
    }
    let mut mesh = match Mesh::from_world(&positions, faces, None) {
        Ok(mesh) => mesh,
        Err(error) => panic!("procedural town: {error}"),
    };
    mesh.compute_vertex_normals();
    mesh
}

/// An oblique aerial pose: 250 m up, 350 m off the town centre, looking at it.
fn oblique_pose() -> Rigid3 {
    let eye = Vector3::new(-250.0, -250.0, 250.0);
    match Rigid3::look_at(&eye, &Vector3::new(0.0, 0.0, 0.0), &Vector3::z()) {
        Some(pose) => pose,
        None => panic!("look_at failed"),
    }
}

/// The same view from four times as far: most triangles cover less than a pixel, as in a
/// frame's renderings of a dense mesh (the synthetic block), so the binning dominates.
fn far_oblique_pose() -> Rigid3 {
    let eye = Vector3::new(-1000.0, -1000.0, 1000.0);
    match Rigid3::look_at(&eye, &Vector3::new(0.0, 0.0, 0.0), &Vector3::z()) {
        Some(pose) => pose,
        None => panic!("look_at failed"),
    }
}

struct Frame {
    rasterizer: Rasterizer,
    buffers: RenderBuffers,
    asg: Image<f32>,
    intrinsics: PinholeIntrinsics,
}

impl Frame {
    fn new(width_px: usize, height_px: usize) -> Self {
        // 60° horizontal field of view.
        let focal_px = width_px as f64 / 2.0 / (30f64.to_radians()).tan();
        Self {
            rasterizer: Rasterizer::new(),
            buffers: RenderBuffers::new(width_px, height_px),
            asg: Image::filled(width_px, height_px, 0.0),
            intrinsics: PinholeIntrinsics::centered(focal_px, width_px as u32, height_px as u32),
        }
    }

    fn render(&mut self, mesh: &Mesh, pose: &Rigid3) {
        self.rasterizer.render(
            mesh,
            &self.intrinsics,
            pose,
            &RenderOptions::default(),
            &mut self.buffers,
        );
    }

    fn asg(&mut self) {
        asg_from_normals(
            self.buffers.normal_cam().view(),
            &AsgOptions::default(),
            &mut self.asg,
        );
    }
}

/// CPU seconds used by this process so far (all threads, user + system), from `/proc/self/stat`
/// (clock ticks of 10 ms, the Linux default); `None` where that file does not exist.
fn process_cpu_s() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    let after_name = &stat[stat.rfind(')')? + 2..];
    let fields: Vec<&str> = after_name.split_whitespace().collect();
    // Fields 14 and 15 of stat(5) are utime and stime; `after_name` starts at field 3.
    let ticks: f64 = fields.get(11)?.parse::<f64>().ok()? + fields.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}

/// Timing of one call: median and minimum wall milliseconds, and CPU milliseconds (all threads).
struct Timing {
    median_ms: f64,
    min_ms: f64,
    cpu_ms: Option<f64>,
}

/// Times calls of `f` filling about `budget_s` (at least 5). On a shared machine the minimum wall
/// time and the CPU time are the least disturbed figures.
fn timing(budget_s: f64, mut f: impl FnMut()) -> Timing {
    f();
    let cpu_start = process_cpu_s();
    let start = Instant::now();
    let mut samples = Vec::new();
    while samples.len() < 5 || start.elapsed().as_secs_f64() < budget_s {
        let call = Instant::now();
        f();
        samples.push(call.elapsed().as_secs_f64() * 1e3);
    }
    let cpu_ms = match (cpu_start, process_cpu_s()) {
        (Some(before), Some(after)) => Some((after - before) * 1e3 / samples.len() as f64),
        _ => None,
    };
    samples.sort_by(f64::total_cmp);
    Timing {
        median_ms: samples[samples.len() / 2],
        min_ms: samples[0],
        cpu_ms,
    }
}

impl std::fmt::Display for Timing {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:.1} ms (min {:.1}", self.median_ms, self.min_ms)?;
        if let Some(cpu_ms) = self.cpu_ms {
            write!(f, ", CPU {cpu_ms:.1}")?;
        }
        write!(f, ")")
    }
}

/// FNV-1a over 32-bit words.
fn hash_words(hash: &mut u64, words: impl Iterator<Item = u32>) {
    for word in words {
        for byte in word.to_le_bytes() {
            *hash ^= u64::from(byte);
            *hash = hash.wrapping_mul(0x100_0000_01b3);
        }
    }
}

/// Hash of every bit of a rendering's outputs and of its ASG.
fn render_hash(buffers: &RenderBuffers, asg: &Image<f32>) -> u64 {
    let mut hash = 0xcbf2_9ce4_8422_2325;
    hash_words(
        &mut hash,
        buffers.depth_m().data().iter().map(|d| d.to_bits()),
    );
    hash_words(
        &mut hash,
        buffers
            .normal_cam()
            .data()
            .iter()
            .flat_map(|n| n.to_array().map(f32::to_bits)),
    );
    hash_words(&mut hash, buffers.face_index().data().iter().copied());
    hash_words(&mut hash, asg.data().iter().map(|v| v.to_bits()));
    hash
}

/// Scene mode (see the module doc): the synthetic scene's model at its ground-truth and initial
/// poses.
fn scene_bench(scene: &std::path::Path) {
    let model = std::env::var("RENDER_BENCH_MODEL").unwrap_or_else(|_| "model.ply".into());
    let mesh = match read_mesh(&scene.join(&model)) {
        Ok(mesh) => mesh,
        Err(error) => panic!("{}: {error}", scene.display()),
    };
    let mut models = vec![scene.join("gt")];
    if let Ok(levels) = std::fs::read_dir(scene.join("initial")) {
        let mut levels: Vec<_> = levels.filter_map(|e| e.ok().map(|e| e.path())).collect();
        levels.sort();
        models.extend(levels);
    }
    let mut views = Vec::new();
    for dir in &models {
        let model = match ColmapModel::read_model(dir) {
            Ok(model) => model,
            Err(error) => panic!("{}: {error}", dir.display()),
        };
        for image in &model.images {
            if let Some(camera) = model.camera_of(image) {
                views.push((*camera, image.cam_from_world));
            }
        }
    }
    assert!(
        !views.is_empty(),
        "{}: no posed image in gt/ or initial/*: nothing to render",
        scene.display()
    );
    let per_pose = std::env::var_os("RENDER_BENCH_HASHES").is_some();
    let options = RenderOptions::default();
    let mut full = Rasterizer::new();
    let mut geometry = Rasterizer::depth_and_faces_only();
    let mut buffers = RenderBuffers::default();
    let mut asg = Image::filled(0, 0, 0.0);
    let mut all = 0xcbf2_9ce4_8422_2325u64;
    let mut valid = 0usize;
    for (k, (camera, pose)) in views.iter().enumerate() {
        buffers.resize(camera.width_px as usize, camera.height_px as usize);
        full.render(&mesh, &camera.intrinsics, pose, &options, &mut buffers);
        asg_from_normals(
            buffers.normal_cam().view(),
            &AsgOptions::default(),
            &mut asg,
        );
        valid += buffers.valid_count();
        let full_hash = render_hash(&buffers, &asg);
        geometry.render(&mesh, &camera.intrinsics, pose, &options, &mut buffers);
        let geometry_hash = render_hash(&buffers, &asg);
        hash_words(
            &mut all,
            [full_hash, geometry_hash]
                .into_iter()
                .flat_map(|h| [h as u32, (h >> 32) as u32]),
        );
        if per_pose {
            println!("pose {k}: full {full_hash:016x}, depth+faces {geometry_hash:016x}");
        }
    }
    let cycle = |f: &mut dyn FnMut(&Camera, &Rigid3)| {
        let mut k = 0;
        timing(3.0, || {
            let (camera, pose) = &views[k % views.len()];
            k += 1;
            f(camera, pose);
        })
    };
    let full_timing = cycle(&mut |camera, pose| {
        full.render(&mesh, &camera.intrinsics, pose, &options, &mut buffers);
    });
    let asg_timing = cycle(&mut |camera, pose| {
        full.render(&mesh, &camera.intrinsics, pose, &options, &mut buffers);
        asg_from_normals(
            buffers.normal_cam().view(),
            &AsgOptions::default(),
            &mut asg,
        );
    });
    let geometry_timing = cycle(&mut |camera, pose| {
        geometry.render(&mesh, &camera.intrinsics, pose, &options, &mut buffers);
    });
    // The visibility rendering of δ (`reprojection::visible_points`): its grid's pixels (4 px).
    let grid = SampleGrid::centred(ReprojectionOptions::default().grid_stride_px);
    let mut grid_hash = 0xcbf2_9ce4_8422_2325u64;
    let grid_points = |rasterizer: &mut Rasterizer,
                       buffers: &mut RenderBuffers,
                       camera: &Camera,
                       pose: &Rigid3| {
        rasterizer.render_grid_points(&mesh, &camera.intrinsics, pose, &options, grid, buffers);
    };
    for (camera, pose) in &views {
        buffers.resize(camera.width_px as usize, camera.height_px as usize);
        grid_points(&mut geometry, &mut buffers, camera, pose);
        let hash = render_hash(&buffers, &Image::filled(0, 0, 0.0));
        hash_words(
            &mut grid_hash,
            [hash as u32, (hash >> 32) as u32].into_iter(),
        );
    }
    let grid_timing = cycle(&mut |camera, pose| {
        grid_points(&mut geometry, &mut buffers, camera, pose);
    });
    let (width, height) = (buffers.width_px(), buffers.height_px());
    println!(
        "scene {} ({model}): {} triangles, {} poses at {width}x{height}, {} rayon threads, coverage {:.0} %",
        scene.display(),
        mesh.face_count(),
        views.len(),
        rayon::current_num_threads(),
        100.0 * valid as f64 / (views.len() * width * height).max(1) as f64
    );
    println!("  full rendering        {full_timing}");
    println!("  full rendering + ASG  {asg_timing}");
    println!("  depth and faces only  {geometry_timing}");
    println!("  4-px grid points only {grid_timing}");
    println!(
        "  output hash (all poses, full and depth-only) {all:016x}, grid points {grid_hash:016x}"
    );
}

fn main() {
    if let Some(scene) = std::env::var_os("RENDER_BENCH_SCENE") {
        scene_bench(std::path::Path::new(&scene));
        return;
    }
    let mesh = procedural_town();
    let pose = oblique_pose();
    let sizes = [(505usize, 275usize), (1920, 1080)];

    let mut criterion = Criterion::default()
        .sample_size(10)
        .measurement_time(std::time::Duration::from_secs(4))
        .configure_from_args();
    for &(width, height) in &sizes {
        let mut frame = Frame::new(width, height);
        let mut group = criterion.benchmark_group(format!("render_{width}x{height}"));
        group.bench_function("rasterise", |b| b.iter(|| frame.render(&mesh, &pose)));
        group.bench_function("asg", |b| b.iter(|| frame.asg()));
        // Depth and face index only (verify's visible points, δ): the binning and the depth
        // pass without the normals, the part of a rendering that sub-pixel faces dominate.
        let mut depth_only = Frame {
            rasterizer: Rasterizer::depth_and_faces_only(),
            ..Frame::new(width, height)
        };
        group.bench_function("depth_and_faces_only", |b| {
            b.iter(|| depth_only.render(&mesh, &pose))
        });
        // The same from far away: sub-pixel faces, nearly all time in the binning.
        let far_pose = far_oblique_pose();
        group.bench_function("depth_and_faces_only_far", |b| {
            b.iter(|| depth_only.render(&mesh, &far_pose))
        });
        group.bench_function("rasterise+asg", |b| {
            b.iter(|| {
                frame.render(&mesh, &pose);
                frame.asg();
            })
        });
        group.finish();
    }
    criterion.final_summary();

    println!(
        "\nsummary: {} triangles, {} vertices, {} rayon threads",
        mesh.face_count(),
        mesh.vertex_count(),
        rayon::current_num_threads()
    );
    for &(width, height) in &sizes {
        let mut frame = Frame::new(width, height);
        frame.render(&mesh, &pose);
        let coverage = frame.buffers.valid_count() as f64 / (width * height) as f64;
        let render = timing(3.0, || frame.render(&mesh, &pose));
        let asg = timing(2.0, || frame.asg());
        println!(
            "{width}x{height}: rasterise {render}, ASG {asg}, total {:.1} ms/frame (median), \
             {:.1} M triangles/s (median; {:.1} at the minimum), coverage {:.0} %",
            render.median_ms + asg.median_ms,
            mesh.face_count() as f64 / (render.median_ms * 1e-3) / 1e6,
            mesh.face_count() as f64 / (render.min_ms * 1e-3) / 1e6,
            coverage * 100.0
        );
    }
}
