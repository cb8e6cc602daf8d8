//! Renderer benchmark: a procedural ~1M-triangle town (terrain heightfield + box buildings on a
//! grid, vertex normals) seen from an oblique aerial pose, rendered and turned into an ASG image
//! at the paper's 505×275 and at 1920×1080. One rendering per coarse pose per frame goes through
//! this path, so its speed bounds frames per second.
//!
//! `cargo bench --bench render` runs criterion and then prints a summary per size from its own
//! timing loop: median and minimum wall ms per frame, CPU ms per frame (all threads, from
//! `/proc/self/stat`: the figure least disturbed by other load on a shared machine) and
//! triangles per second. `cargo bench --bench render -- no_such_bench` prints only the summary.

use std::time::Instant;

use asgreg::core::camera::PinholeIntrinsics;
use asgreg::core::image::Image;
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
