//! `asgreg render`: the mesh under one image's pose as an ASG gradient image (what registration
//! matches against), a normal map or a depth map.

use std::path::{Path, PathBuf};

use anyhow::Context;
use asgreg::core::camera::Camera;
use asgreg::core::image::Image;
use asgreg::core::mesh::Mesh;
use asgreg::core::raster::{NormalSource, Rasterizer, RenderBuffers, RenderOptions};
use asgreg::core::rigid::Rigid3;
use asgreg::core::shading::{asg_of_rendering, AsgOptions};
use asgreg::io::images::{save_gray_png, save_rgb_png};
use asgreg::viz::normalize_for_display;

use super::inputs::load_posed_inputs;

#[derive(clap::Args, Debug)]
pub struct RenderArgs {
    /// The mesh (PLY or OBJ).
    #[arg(long)]
    pub mesh: PathBuf,
    /// COLMAP cameras.txt or cameras.bin, or a model folder.
    #[arg(long)]
    pub cameras: PathBuf,
    /// COLMAP images.txt or images.bin, or a model folder, with the pose to render from.
    #[arg(long)]
    pub poses: PathBuf,
    /// The image whose pose and camera to use (its NAME in images.txt).
    #[arg(long)]
    pub image: String,
    /// What to write.
    #[arg(long, value_enum, default_value_t = RenderWhat::Asg)]
    pub what: RenderWhat,
    /// Normals to shade with.
    #[arg(long, value_enum, default_value_t = NormalsArg::Vertex)]
    pub normals: NormalsArg,
    /// ASG: add occlusion contours from the depth, as `register --asg-occlusion-contours` does.
    #[arg(long, value_name = "DEPTH_RATIO")]
    pub asg_occlusion_contours: Option<f32>,
    /// Output PNG.
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum RenderWhat {
    /// Average Shading Gradient image (paper eq. 4), scaled for display.
    Asg,
    /// Camera-frame normals as colours.
    Normals,
    /// Depth along the optical axis, near = bright.
    Depth,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum NormalsArg {
    Face,
    Vertex,
}

/// Renders `mesh` as `camera` sees it from `cam_from_world` (pinhole part of the camera).
pub fn render_view(
    mesh: &Mesh,
    camera: &Camera,
    cam_from_world: &Rigid3,
    normal_source: NormalSource,
) -> RenderBuffers {
    let mut buffers = RenderBuffers::new(camera.width_px as usize, camera.height_px as usize);
    let options = RenderOptions {
        normal_source,
        ..RenderOptions::default()
    };
    Rasterizer::new().render(
        mesh,
        &camera.intrinsics,
        cam_from_world,
        &options,
        &mut buffers,
    );
    buffers
}

/// The ASG image of a rendering as registration computes it (`core::shading::asg_of_rendering`;
/// with `occlusion_depth_ratio`, its occlusion contours too), scaled to 0..1 for display.
pub fn asg_display_image(render: &RenderBuffers, occlusion_depth_ratio: Option<f32>) -> Image<f32> {
    let options = AsgOptions {
        occlusion_depth_ratio,
        ..AsgOptions::default()
    };
    let mut asg = Image::default();
    asg_of_rendering(
        render.normal_cam().view(),
        render.depth_m().view(),
        &options,
        &mut asg,
    );
    normalize_for_display(asg.view())
}

pub fn write_render(
    render: &RenderBuffers,
    what: RenderWhat,
    occlusion_depth_ratio: Option<f32>,
    out: &Path,
) -> anyhow::Result<()> {
    match what {
        RenderWhat::Asg => {
            save_gray_png(out, asg_display_image(render, occlusion_depth_ratio).view())?
        }
        RenderWhat::Normals => {
            let rgb = render.normal_cam().map(|n| {
                if *n == glam::Vec3::ZERO {
                    [0, 0, 0]
                } else {
                    [n.x, -n.y, -n.z].map(|c| ((c * 0.5 + 0.5) * 255.0).round() as u8)
                }
            });
            save_rgb_png(out, rgb.view())?;
        }
        RenderWhat::Depth => {
            let inverse = render
                .depth_m()
                .map(|d| if *d > 0.0 { 1.0 / d } else { 0.0 });
            save_gray_png(out, normalize_for_display(inverse.view()).view())?;
        }
    }
    Ok(())
}

pub fn run(args: &RenderArgs) -> anyhow::Result<()> {
    let inputs = load_posed_inputs(&args.mesh, &args.cameras, &args.poses)?;
    let (image, camera) = inputs.find_image(&args.image, &args.poses, &args.cameras)?;
    let normal_source = match args.normals {
        NormalsArg::Face => NormalSource::Face,
        NormalsArg::Vertex => NormalSource::Vertex,
    };
    let started = std::time::Instant::now();
    let render = render_view(&inputs.mesh, camera, &image.cam_from_world, normal_source);
    let render_ms = started.elapsed().as_secs_f64() * 1e3;
    if let Some(ratio) = args.asg_occlusion_contours {
        anyhow::ensure!(
            ratio.is_finite() && ratio > 0.0,
            "--asg-occlusion-contours {ratio}: give a positive share of the nearer depth, e.g. 0.1"
        );
    }
    write_render(&render, args.what, args.asg_occlusion_contours, &args.out)
        .with_context(|| format!("writing {}", args.out.display()))?;
    let coverage = render.valid_count() as f64 / (render.width_px() * render.height_px()) as f64;
    println!(
        "rendered {} ({}x{} px, {:.1} ms, model covers {:.0} % of the image) -> {}",
        image.name,
        render.width_px(),
        render.height_px(),
        render_ms,
        coverage * 100.0,
        args.out.display()
    );
    if render.valid_count() == 0 {
        tracing::warn!("the model is not visible from this pose: check the pose file's convention (cam_from_world)");
    }
    Ok(())
}
