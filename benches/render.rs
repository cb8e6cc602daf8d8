//! Renderer benchmark: a procedural ~1M-triangle town (terrain heightfield + box buildings on a
//! grid, vertex normals) seen from an oblique aerial pose, rendered and turned into an ASG image
//! at the paper's 505×275 and at 1920×1080. One rendering per coarse pose per frame goes through
//! this path, so its speed bounds frames per second.
//!
//! `cargo bench --bench render` runs criterion and then prints ms per frame and triangles per
//! second for each size (the summary uses its own timing loop, so it is printed also with
//! `-- --quick` style arguments).

use std::time::Instant;

use asgreg::core::camera::PinholeIntrinsics;
use asgreg::core::mesh::Mesh;
use asgreg::core::raster::{Rasterizer, RenderBuffers, RenderOptions};
use asgreg::core::rigid::Rigid3;
use asgreg::core::shading::{asg_from_normals, AsgOptions};
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

struct Frame {
    rasterizer: Rasterizer,
    buffers: RenderBuffers,
    asg: Vec<f32>,
    intrinsics: PinholeIntrinsics,
    width_px: usize,
    height_px: usize,
}

impl Frame {
    fn new(width_px: usize, height_px: usize) -> Self {
        // 60° horizontal field of view.
        let focal_px = width_px as f64 / 2.0 / (30f64.to_radians()).tan();
        Self {
            rasterizer: Rasterizer::new(),
            buffers: RenderBuffers::new(width_px, height_px),
            asg: vec![0.0; width_px * height_px],
            intrinsics: PinholeIntrinsics::centered(focal_px, width_px as u32, height_px as u32),
            width_px,
            height_px,
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
            &self.buffers.normal_cam,
            self.width_px,
            self.height_px,
            &AsgOptions::default(),
            &mut self.asg,
        );
    }
}

/// Mean milliseconds of `f` over enough repetitions to fill about `budget_s`.
fn mean_ms(budget_s: f64, mut f: impl FnMut()) -> f64 {
    f();
    let start = Instant::now();
    let mut count = 0u32;
    while count < 3 || start.elapsed().as_secs_f64() < budget_s {
        f();
        count += 1;
    }
    start.elapsed().as_secs_f64() * 1e3 / f64::from(count)
}

fn main() {
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
        let render_ms = mean_ms(3.0, || frame.render(&mesh, &pose));
        let asg_ms = mean_ms(2.0, || frame.asg());
        let total_ms = render_ms + asg_ms;
        println!(
            "{width}x{height}: rasterise {render_ms:.1} ms, ASG {asg_ms:.2} ms, total {total_ms:.1} ms/frame, \
             {:.1} M triangles/s (rasterise), coverage {:.0} %",
            mesh.face_count() as f64 / (render_ms * 1e-3) / 1e6,
            coverage * 100.0
        );
    }
}
