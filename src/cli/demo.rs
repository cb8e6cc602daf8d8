//! `asgreg demo`: the main job on an embedded default. It makes a small synthetic scene (no
//! downloads), renders the model's ASG image and the photo's gradient image for one frame, draws
//! the model over the photo under the ground-truth and the initial pose, registers the frames from
//! their 30 px initial poses and prints δ to ground truth before and after, then says where it all is.

use std::path::PathBuf;

use anyhow::Context;
use asgreg::core::image::Image;
use asgreg::core::raster::NormalSource;
use asgreg::core::shading::gradient_magnitude;
use asgreg::io::colmap::read_images_txt;
use asgreg::io::images::{load_gray, load_rgb, save_gray_png, save_rgb_png};
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
    #[arg(long, default_value_t = 6)]
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
        scene: SceneArg::Block,
        levels: vec![30.0, 57.0, 80.0, 104.0],
        changes: false,
        no_heading_level: false,
        triangles: 1_000_000,
        heading_min_deg: asgreg::synth::initial::HeadingNoise::default().heading_min_deg,
        heading_max_deg: asgreg::synth::initial::HeadingNoise::default().heading_max_deg,
        heading_flip_every: asgreg::synth::initial::HeadingNoise::default().flip_every,
        flight_path: false,
    };
    println!("1/4 making a synthetic scene: a town block seen obliquely from 30–60 m, {} photos at 505x275", args.images);
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

    println!("2/4 gradient images of {first}: the model's ASG and the photo's gradient magnitude");
    let started = std::time::Instant::now();
    let render = render_view(
        &inputs.mesh,
        camera,
        &image.cam_from_world,
        NormalSource::Vertex,
    );
    let render_ms = started.elapsed().as_secs_f64() * 1e3;
    let asg_path = args.out.join(format!("{stem}_asg.png"));
    save_gray_png(&asg_path, asg_display_image(&render, None).view())?;
    let photo_path = scene_dir.join("images").join(&first);
    let photo = load_gray(&photo_path)?;
    let mut gradient = Image::default();
    gradient_magnitude(photo.view(), &mut gradient);
    let gradient_path = args.out.join(format!("{stem}_photo_gradient.png"));
    save_gray_png(
        &gradient_path,
        normalize_for_display(gradient.view()).view(),
    )?;
    println!(
        "    rendered the model in {render_ms:.1} ms -> {}",
        asg_path.display()
    );
    println!("    photo gradient -> {}", gradient_path.display());

    println!(
        "3/4 the model over the photo under the ground-truth pose and the 104 px initial pose"
    );
    let rgb = load_rgb(&photo_path)?;
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
        let picture = overlay_model(rgb.view(), &render, OverlayStyle::NormalsAndEdges, 0.45)?;
        let path = args.out.join(format!("{stem}_overlay_{label}.png"));
        save_rgb_png(&path, picture.view())?;
        println!("    {label} -> {}", path.display());
    }
    register_scene(&scene_dir, &inputs, &args.out, args.seed)?;
    Ok(())
}

/// Step 4: registers every frame from its 30 px initial pose (known intrinsics, query from the
/// photo's depth map) and prints δ to ground truth before and after.
fn register_scene(
    scene_dir: &std::path::Path,
    inputs: &super::inputs::PosedInputs,
    out: &std::path::Path,
    seed: u64,
) -> anyhow::Result<()> {
    use super::eval::register_scene_frame;
    use super::register::{registration_config, CoarseArgs, IntrinsicsArg};
    use asgreg::core::reprojection::{mutual_reprojection_error_px, ReprojectionWorkspace};

    println!("4/4 registering every frame from its 30 px initial pose (known intrinsics, query = ASG of the photo's depth)");
    let initial = read_images_txt(&scene_dir.join("initial/30/images.txt"))?;
    let config = registration_config(
        asgreg::core::frame::QueryMode::DepthAsg,
        IntrinsicsArg::Known,
        &CoarseArgs::default(),
    );
    let mut workspace = ReprojectionWorkspace::new();
    let (mut accepted, mut sum_before, mut sum_after) = (0usize, 0.0f64, 0.0f64);
    for start in &initial {
        let gt = inputs
            .images
            .iter()
            .find(|g| g.name == start.name)
            .with_context(|| format!("{} has no ground truth", start.name))?;
        let camera = *inputs
            .cameras
            .get(&gt.camera_id)
            .with_context(|| format!("camera {} of {} is missing", gt.camera_id, gt.name))?;
        let (report, after) = register_scene_frame(
            &inputs.mesh,
            scene_dir,
            start,
            gt,
            camera,
            IntrinsicsArg::Known.mode(),
            true,
            &config,
            seed,
            &mut workspace,
        );
        let before = mutual_reprojection_error_px(
            &inputs.mesh,
            &camera,
            &start.cam_from_world,
            &camera,
            &gt.cam_from_world,
            &mut workspace,
        )
        .unwrap_or(f64::NAN);
        match after.filter(|_| report.accepted) {
            Some(after) => {
                accepted += 1;
                sum_before += before;
                sum_after += after;
                println!(
                    "    {}: δ {before:6.1} px → {after:6.2} px (confidence {:.2}, {:.1} s)",
                    start.name,
                    report.confidence,
                    report.timings.total_ms / 1e3
                );
            }
            None => println!(
                "    {}: δ {before:6.1} px → not accepted: {}",
                start.name,
                report.reason.as_deref().unwrap_or("unknown")
            ),
        }
    }
    if accepted > 0 {
        println!(
            "done: {accepted} of {} frames accepted, their mean δ {:.1} px → {:.1} px. Pictures are in {}; `asgreg eval --scene {}` runs the full protocol.",
            initial.len(),
            sum_before / accepted as f64,
            sum_after / accepted as f64,
            out.display(),
            scene_dir.display()
        );
    } else {
        println!(
            "done: no frame was accepted (see the reasons above). Pictures are in {}.",
            out.display()
        );
    }
    Ok(())
}
