//! `asgreg bench mesh`: a city-size mesh in bounded memory (issue #16). Writes the synthetic city
//! (`synth::city`, binary PLY, georeferenced) of `--triangles` triangles, loads it (streamed PLY
//! reader), renders aerial frames through the frustum-culled rasteriser, registers one frame (its
//! photo and depth rendered from a true pose, started from a disturbed one) and prints load time,
//! render ms per frame, faces kept by the culling and the process's peak RSS.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use asgreg::core::camera::{Camera, PinholeIntrinsics};
use asgreg::core::frame::{register_frame, FrameInput, IntrinsicsMode, QueryMode};
use asgreg::core::raster::{Rasterizer, RenderBuffers, RenderOptions};
use asgreg::core::reprojection::{mutual_reprojection_error_px, ReprojectionWorkspace};
use asgreg::core::rigid::Rigid3;
use asgreg::io::mesh_file::read_mesh;
use asgreg::synth::city::{write_city_ply, CityMesh, CITY_ORIGIN_M};
use nalgebra::{UnitQuaternion, Vector3};

use super::render::asg_display_image;

/// The process's resident memory now and at its peak, MiB (Linux /proc/self/status).
pub(crate) fn rss_mib() -> (f64, f64) {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let field = |name: &str| {
        status
            .lines()
            .find(|line| line.starts_with(name))
            .and_then(|line| line.split_whitespace().nth(1))
            .and_then(|kib| kib.parse::<f64>().ok())
            .map_or(f64::NAN, |kib| kib / 1024.0)
    };
    (field("VmRSS:"), field("VmHWM:"))
}

/// Runs the mesh benchmark with `triangles` triangles, files in `out`, `frames` rendered frames.
pub fn bench_mesh(out: &std::path::Path, triangles: u64, frames: usize) -> anyhow::Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let path: PathBuf = out.join(format!("city_{triangles}.ply"));
    let layout = CityMesh::for_triangles(triangles);
    if !path.is_file() {
        let started = Instant::now();
        write_city_ply(&path, triangles)?;
        println!(
            "wrote {} ({} triangles, {:.0} MB) in {:.1} s",
            path.display(),
            layout.triangles,
            std::fs::metadata(&path).map_or(0.0, |m| m.len() as f64 / 1e6),
            started.elapsed().as_secs_f64()
        );
    }
    let (rss_before, _) = rss_mib();
    let started = Instant::now();
    let mesh = read_mesh(&path)?;
    let load_s = started.elapsed().as_secs_f64();
    let (rss_loaded, peak_loaded) = rss_mib();
    println!(
        "loaded {} faces, {} vertices, {} grid cells in {load_s:.2} s; RSS {rss_before:.0} → {rss_loaded:.0} MiB, peak {peak_loaded:.0} MiB",
        mesh.face_count(),
        mesh.vertex_count(),
        mesh.grid().cells().len()
    );

    // Aerial oblique views over the city: 150 m up, looking 200 m ahead, headings around.
    let side = layout.side_m;
    let camera = Camera::pinhole(505, 275, PinholeIntrinsics::centered(450.0, 505, 275));
    let poses: Vec<Rigid3> = (0..frames.max(1))
        .filter_map(|k| {
            let t = (k as f64 + 0.5) / frames.max(1) as f64;
            let heading = t * std::f64::consts::TAU;
            let centre = Vector3::new(
                CITY_ORIGIN_M[0] + side * (0.2 + 0.6 * t),
                CITY_ORIGIN_M[1] + side * (0.5 + 0.3 * (heading * 2.0).sin()),
                0.0,
            );
            let eye = centre + Vector3::new(-200.0 * heading.cos(), -200.0 * heading.sin(), 150.0);
            Rigid3::look_at(&eye, &centre, &Vector3::new(0.0, 0.0, 1.0))
        })
        .collect();
    let mut rasterizer = Rasterizer::new();
    let mut render = RenderBuffers::new(505, 275);
    let options = RenderOptions::default();
    // The first rendering sizes the scratch buffers; time the rest.
    rasterizer.render(&mesh, &camera.intrinsics, &poses[0], &options, &mut render);
    let mut render_ms = Vec::new();
    let mut kept = Vec::new();
    for pose in &poses {
        let started = Instant::now();
        rasterizer.render(&mesh, &camera.intrinsics, pose, &options, &mut render);
        render_ms.push(started.elapsed().as_secs_f64() * 1e3);
        kept.push(rasterizer.visible_face_count() as f64 / mesh.face_count() as f64);
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    println!(
        "render 505x275: {:.1} ms per frame (mean of {}, range {:.1}..{:.1}); culling kept {:.2} % of the faces",
        mean(&render_ms),
        render_ms.len(),
        render_ms.iter().copied().fold(f64::INFINITY, f64::min),
        render_ms.iter().copied().fold(0.0, f64::max),
        100.0 * mean(&kept)
    );

    // One frame registered: photo = the ASG of the true pose's rendering, depth = its depth;
    // start 1.5° and 4 m away.
    let truth = poses[0];
    rasterizer.render(&mesh, &camera.intrinsics, &truth, &options, &mut render);
    let photo = asg_display_image(&render, None);
    let depth = render.depth_m().clone();
    let turn = UnitQuaternion::from_euler_angles(0.015, -0.01, 0.02);
    let initial = Rigid3::new(
        turn * truth.rotation,
        turn * truth.translation + Vector3::new(3.0, -2.0, 2.0),
    );
    let config = asgreg::core::frame::RegistrationConfig {
        query_mode: QueryMode::DepthAsg,
        ..Default::default()
    };
    let started = Instant::now();
    let result = register_frame(
        &mesh,
        &FrameInput {
            photo: photo.view(),
            depth_m: Some(depth.view()),
            camera: &camera,
            intrinsics: IntrinsicsMode::Known,
            initial_cam_from_world: initial,
            seed: 1,
        },
        &config,
    )?;
    let register_s = started.elapsed().as_secs_f64();
    let mut workspace = ReprojectionWorkspace::new();
    let mut delta = |pose: &Rigid3| {
        mutual_reprojection_error_px(&mesh, &camera, pose, &camera, &truth, &mut workspace)
            .unwrap_or(f64::NAN)
    };
    let initial_delta = delta(&initial);
    let final_delta = result
        .verdict
        .chosen()
        .map_or(f64::NAN, |h| delta(&h.cam_from_world));
    let (_, peak) = rss_mib();
    println!(
        "registered one frame in {register_s:.1} s: {} (confidence {:.2}), δ to the true pose {initial_delta:.1} px → {final_delta:.2} px",
        if result.verdict.accepted() {
            "accepted"
        } else {
            "rejected"
        },
        result.verdict.confidence
    );
    println!(
        "summary: triangles {} | load {load_s:.2} s | render {:.1} ms/frame | culling kept {:.2} % | peak RSS {peak:.0} MiB",
        mesh.face_count(),
        mean(&render_ms),
        100.0 * mean(&kept)
    );
    Ok(())
}
