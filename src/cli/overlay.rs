//! `asgreg overlay`: the mesh drawn over a photo under a pose, the picture that shows at a glance
//! whether a pose is right.

use std::path::{Path, PathBuf};

use anyhow::Context;
use asgreg::core::camera::Camera;
use asgreg::core::image::Image;
use asgreg::core::mesh::Mesh;
use asgreg::core::raster::NormalSource;
use asgreg::core::rigid::Rigid3;
use asgreg::core::undistort::WorkingCamera;
use asgreg::frame_files::FrameLoader;
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

/// One view to draw a frame's model under: a label, the camera (the photo's own, or an estimate
/// of it; None: the photo's camera) and the pose.
pub struct OverlayView<'a> {
    pub label: &'a str,
    pub camera: Option<Camera>,
    pub cam_from_world: Rigid3,
}

/// The model drawn over a frame's photo under each of `views`, as registration saw the photo:
/// with the loader's working camera (undistorted, at the working width), so that a lens's
/// distortion does not show as misalignment. The one overlay of `register`, `eval` and `changes`
/// (loose PNGs and report.html).
pub fn working_overlays(
    mesh: &Mesh,
    loader: &FrameLoader,
    image_path: &Path,
    camera_id: u32,
    camera: &Camera,
    views: &[OverlayView<'_>],
) -> anyhow::Result<Vec<(String, Image<[u8; 3]>)>> {
    let working = loader.working_camera(image_path, camera_id, camera)?;
    let rgb = working_rgb(&working, &load_rgb(image_path)?)?;
    let mut pictures = Vec::with_capacity(views.len());
    for view in views {
        let view_camera = match &view.camera {
            Some(estimated) => working.working_camera_for(estimated),
            None => working.working,
        };
        let render = render_view(
            mesh,
            &view_camera,
            &view.cam_from_world,
            NormalSource::Vertex,
        );
        let picture = overlay_model(rgb.view(), &render, OverlayStyle::NormalsAndEdges, 0.4)?;
        pictures.push((view.label.to_string(), picture));
    }
    Ok(pictures)
}

/// A colour photo as the working camera sees it (each channel resampled like the grey photo).
fn working_rgb(working: &WorkingCamera, rgb: &Image<[u8; 3]>) -> anyhow::Result<Image<[u8; 3]>> {
    if working.is_identity() {
        return Ok(rgb.clone());
    }
    let mut channels = Vec::with_capacity(3);
    for channel in 0..3 {
        let plane = rgb.map(|pixel| f32::from(pixel[channel]) / 255.0);
        channels.push(working.photo(plane.view())?);
    }
    let (width_px, height_px) = channels[0].size();
    Ok(Image::from_fn(width_px, height_px, |col, row| {
        std::array::from_fn(|channel| {
            let value = channels[channel].get(col, row).copied().unwrap_or(0.0);
            (value.clamp(0.0, 1.0) * 255.0).round() as u8
        })
    }))
}
