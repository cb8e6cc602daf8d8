//! `asgreg overlay`: the mesh drawn over a photo under a pose, the picture that shows at a glance
//! whether a pose is right.

use std::path::PathBuf;

use anyhow::Context;
use asgreg::core::raster::NormalSource;
use asgreg::io::images::{check_image_matches_camera, load_rgb, save_rgb_png};
use asgreg::viz::{overlay_model, OverlayStyle};

use super::inputs::load_posed_inputs;
use super::render::render_view;

#[derive(clap::Args, Debug)]
pub struct OverlayArgs {
    /// The mesh (PLY or OBJ).
    #[arg(long)]
    pub mesh: PathBuf,
    /// The photo; its file name must be listed in the poses file.
    #[arg(long)]
    pub image: PathBuf,
    /// COLMAP cameras.txt or cameras.bin, or a model folder.
    #[arg(long)]
    pub cameras: PathBuf,
    /// COLMAP images.txt or images.bin, or a model folder, with the pose to draw the model under.
    #[arg(long)]
    pub poses: PathBuf,
    /// Output PNG.
    #[arg(long)]
    pub out: PathBuf,
    /// Normal colours with edges, or edges only.
    #[arg(long, value_enum, default_value_t = StyleArg::Normals)]
    pub style: StyleArg,
    /// Opacity of the normal colours, 0..1.
    #[arg(long, default_value_t = 0.45)]
    pub alpha: f32,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum StyleArg {
    Normals,
    Edges,
}

pub fn run(args: &OverlayArgs) -> anyhow::Result<()> {
    let inputs = load_posed_inputs(&args.mesh, &args.cameras, &args.poses)?;
    let name = args
        .image
        .file_name()
        .map(|f| f.to_string_lossy().into_owned())
        .unwrap_or_default();
    let (image, camera) = inputs.find_image(&name, &args.poses, &args.cameras)?;
    let photo = load_rgb(&args.image)?;
    check_image_matches_camera(
        &args.image,
        photo.width_px(),
        photo.height_px(),
        image.camera_id,
        camera,
    )?;
    let render = render_view(
        &inputs.mesh,
        camera,
        &image.cam_from_world,
        NormalSource::Vertex,
    );
    let style = match args.style {
        StyleArg::Normals => OverlayStyle::NormalsAndEdges,
        StyleArg::Edges => OverlayStyle::Edges,
    };
    let picture = overlay_model(photo.view(), &render, style, args.alpha)?;
    save_rgb_png(&args.out, picture.view())
        .with_context(|| format!("writing {}", args.out.display()))?;
    println!(
        "drew {} over {} under the pose in {} -> {}",
        args.mesh.display(),
        args.image.display(),
        args.poses.display(),
        args.out.display()
    );
    Ok(())
}
