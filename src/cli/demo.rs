//! `asgreg demo`: the main job on an embedded default. It makes a small synthetic scene (no
//! downloads), renders the model's ASG image and the photo's gradient image for one frame, and draws
//! the model over the photo under the ground-truth and the initial pose, then says where it all is.

use std::path::PathBuf;

use anyhow::Context;
use asgreg::core::raster::NormalSource;
use asgreg::core::shading::gradient_magnitude;
use asgreg::io::colmap::read_images_txt;
use asgreg::io::images::{load_gray, load_rgb, save_gray_png, save_rgb_png, GrayImage};
use asgreg::viz::{normalize_for_display, overlay_model, OverlayStyle};

use super::inputs::load_posed_inputs;
use super::render::{asg_display_image, render_view};
use super::synth::{print_summary, SceneArg, SynthArgs};

#[derive(clap::Args, Debug)]
pub struct DemoArgs {
    /// Where to write the scene and the pictures.
    #[arg(long, default_value = "asgreg-demo")]
    pub out: PathBuf,
    /// Random seed of the scene.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Number of photos in the scene.
    #[arg(long, default_value_t = 12)]
    pub images: usize,
}

pub fn run(args: &DemoArgs) -> anyhow::Result<()> {
    let scene_dir = args.out.join("scene");
    let synth_args = SynthArgs {
        out: scene_dir.clone(),
        seed: args.seed,
        width: 505,
        height: 275,
        images: args.images,
        scene: SceneArg::House,
        levels: vec![30.0, 57.0, 80.0, 104.0],
    };
    println!("1/3 making a synthetic scene: a house photographed from 2, 8 and 15 m, {} photos at 505x275", args.images);
    let started = std::time::Instant::now();
    let summary = asgreg::synth::generate_scene(&synth_args.config(), &scene_dir)?;
    print_summary(&summary, &scene_dir, started.elapsed().as_secs_f64());

    let gt_cameras = scene_dir.join("gt/cameras.txt");
    let gt_poses = scene_dir.join("gt/images.txt");
    let inputs = load_posed_inputs(&scene_dir.join("model.ply"), &gt_cameras, &gt_poses)?;
    let first = inputs
        .images
        .first()
        .context("the synthetic scene has no images")?
        .name
        .clone();
    let (image, camera) = inputs.find_image(&first, &gt_poses, &gt_cameras)?;
    let stem = first.trim_end_matches(".jpg").to_string();

    println!("2/3 gradient images of {first}: the model's ASG and the photo's gradient magnitude");
    let started = std::time::Instant::now();
    let render = render_view(
        &inputs.mesh,
        camera,
        &image.cam_from_world,
        NormalSource::Vertex,
    );
    let render_ms = started.elapsed().as_secs_f64() * 1e3;
    let asg_path = args.out.join(format!("{stem}_asg.png"));
    save_gray_png(&asg_path, &asg_display_image(&render))?;
    let photo_path = scene_dir.join("images").join(&first);
    let photo = load_gray(&photo_path)?;
    let mut gradient = vec![0.0f32; photo.pixels.len()];
    gradient_magnitude(
        &photo.pixels,
        photo.width_px,
        photo.height_px,
        &mut gradient,
    );
    let gradient_path = args.out.join(format!("{stem}_photo_gradient.png"));
    save_gray_png(
        &gradient_path,
        &GrayImage {
            width_px: photo.width_px,
            height_px: photo.height_px,
            pixels: normalize_for_display(&gradient),
        },
    )?;
    println!(
        "    rendered the model in {render_ms:.1} ms -> {}",
        asg_path.display()
    );
    println!("    photo gradient -> {}", gradient_path.display());

    println!(
        "3/3 the model over the photo under the ground-truth pose and the 104 px initial pose"
    );
    let (width_px, height_px, rgb) = load_rgb(&photo_path)?;
    let initial_poses_path = scene_dir.join("initial/104/images.txt");
    let initial = read_images_txt(&initial_poses_path)?;
    let initial_pose = initial
        .iter()
        .find(|i| i.name == first)
        .with_context(|| format!("{first} is missing from {}", initial_poses_path.display()))?;
    for (label, pose) in [
        ("gt", &image.cam_from_world),
        ("initial104", &initial_pose.cam_from_world),
    ] {
        let render = render_view(&inputs.mesh, camera, pose, NormalSource::Vertex);
        let picture = overlay_model(&rgb, &render, OverlayStyle::NormalsAndEdges, 0.45);
        let path = args.out.join(format!("{stem}_overlay_{label}.png"));
        save_rgb_png(&path, width_px, height_px, &picture)?;
        println!("    {label} -> {}", path.display());
    }
    println!(
        "done. Registration (SIFT flow, pose solving, verification) is not built yet; the scene in {} is its test input.",
        scene_dir.display()
    );
    Ok(())
}
