//! `asgreg register`: refines the initial poses of a folder of photos against a mesh and writes
//! the accepted poses (COLMAP text and binary, omega-phi-kappa CSV), a per-frame report and
//! before/after overlays. Photos are registered with their working camera (undistorted, at the
//! working width: `frame_files`) and the poses are written for their own camera.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::Context;
use asgreg::batch::{register_batch_frame_with, BatchFrame, FrameReport};
use asgreg::core::edge_align::EdgeAlignConfig;
use asgreg::core::frame::{IntrinsicsMode, QueryMode, RegistrationConfig};
use asgreg::core::image::Image;
use asgreg::core::undistort::WorkingCamera;
use asgreg::core::verify::VerifyConfig;
use asgreg::frame_files::{depth_path_for, FrameLoader, DEFAULT_WORKING_WIDTH_PX};
use asgreg::io::colmap::{ColmapModel, ImagePose};
use asgreg::io::colmap_model::write_model_dir;
use asgreg::io::images::{load_rgb, save_rgb_png};
use asgreg::io::mesh_file::check_mesh_fits;
use asgreg::io::opk::{write_opk_csv, OPK_FILE};
use asgreg::io::output::prepare_output_dir;
use asgreg::viz::{overlay_model, OverlayStyle};

use super::inputs::load_posed_inputs;
use super::render::render_view;

#[derive(clap::Args, Debug)]
pub struct RegisterArgs {
    /// The untextured mesh (PLY or OBJ).
    #[arg(long)]
    pub mesh: PathBuf,
    /// Folder with the photos named in the poses file.
    #[arg(long)]
    pub images: PathBuf,
    /// COLMAP cameras.txt or cameras.bin, or a model folder (known intrinsics, or the nominal ones when unknown).
    #[arg(long)]
    pub cameras: PathBuf,
    /// COLMAP images.txt or images.bin, or a model folder, with the initial poses.
    #[arg(long)]
    pub poses: PathBuf,
    /// Known intrinsics (EPnP) or unknown (DLT, estimated per image).
    #[arg(long, value_enum, default_value_t = IntrinsicsArg::Known)]
    pub intrinsics: IntrinsicsArg,
    /// Folder of the photos' depth maps (`<image stem>.pfm`): the query becomes the ASG of the
    /// depth's normals (the paper's mode) instead of the photo's gradient.
    #[arg(long)]
    pub depth: Option<PathBuf>,
    /// Output folder.
    #[arg(long)]
    pub out: PathBuf,
    /// Seed of the random draws (coarse poses, RANSAC): the same seed gives the same poses.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    #[command(flatten)]
    pub coarse: CoarseArgs,
    /// Width (px) at which photos are registered: wider ones are averaged down to it (height in
    /// proportion) and the poses are written for the photo's own camera; 0 registers every
    /// photo at its own size. The default is the paper's 505 px width. Photos whose camera has
    /// lens distortion (SIMPLE_RADIAL, RADIAL, OPENCV) are also undistorted to a PINHOLE camera
    /// the way COLMAP's image_undistorter does it; the output keeps their camera.
    #[arg(long, default_value_t = DEFAULT_WORKING_WIDTH_PX, value_name = "PX")]
    pub working_width: u32,
    /// Register only the first N frames of the poses file.
    #[arg(long)]
    pub limit: Option<usize>,
    /// Skip the overlay pictures.
    #[arg(long)]
    pub no_overlays: bool,
    /// Refuse a mesh that would take more memory than this to load (MiB), judged from its header
    /// before loading it (PLY: declared vertices and faces; OBJ: the file's size).
    #[arg(long, value_name = "MIB")]
    pub max_mesh_mib: Option<u64>,
}

/// How the coarse poses are drawn around the initial pose, and how far their refined poses must
/// converge to be accepted. Every default is the library's (`RegistrationConfig::default()`).
#[derive(clap::Args, Debug, Clone, Copy)]
pub struct CoarseArgs {
    /// Coarse poses per frame.
    #[arg(long, default_value_t = RegistrationConfig::default().coarse_pose_count)]
    pub coarse_poses: usize,
    /// Rotation noise of the coarse poses, degrees (σ per axis).
    #[arg(long, default_value_t = RegistrationConfig::default().coarse_rotation_sigma_deg)]
    pub coarse_rotation_deg: f64,
    /// Camera-centre noise of the coarse poses, as a fraction of the median scene depth (σ per axis).
    #[arg(long, default_value_t = RegistrationConfig::default().coarse_translation_sigma_fraction)]
    pub coarse_translation_fraction: f64,
    /// Verification: the agreeing refined poses' spread may be at most this fraction of their
    /// coarse poses' spread (1 or more turns the convergence test off).
    #[arg(long, default_value_t = RegistrationConfig::default().verify.max_convergence_ratio)]
    pub max_convergence_ratio: f64,
    /// Lifting: matches within this many px of a depth discontinuity of the rendering are not
    /// lifted (0: every match is).
    #[arg(long, default_value_t = RegistrationConfig::default().lift_edge_margin_px)]
    pub lift_edge_margin_px: usize,
    /// Skip the final refinement (alignment of the chosen pose with the photo's edges).
    #[arg(long)]
    pub no_edge_align: bool,
    /// Final refinement: search half-length of its first level, px (levels halve it down to 2).
    #[arg(long, default_value_t = RegistrationConfig::default().edge_align.initial_search_radius_px)]
    pub edge_search_px: f64,
    /// Skip the pose search before the coarse poses (heading, pitch, roll grid scored on the
    /// photo's oriented edges, beams refined by edge alignment): the paper's method alone.
    #[arg(long)]
    pub no_pose_search: bool,
}

impl Default for CoarseArgs {
    fn default() -> Self {
        let defaults = RegistrationConfig::default();
        Self {
            coarse_poses: defaults.coarse_pose_count,
            coarse_rotation_deg: defaults.coarse_rotation_sigma_deg,
            coarse_translation_fraction: defaults.coarse_translation_sigma_fraction,
            max_convergence_ratio: defaults.verify.max_convergence_ratio,
            lift_edge_margin_px: defaults.lift_edge_margin_px,
            no_edge_align: false,
            edge_search_px: defaults.edge_align.initial_search_radius_px,
            no_pose_search: false,
        }
    }
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum IntrinsicsArg {
    Known,
    Unknown,
}

impl IntrinsicsArg {
    pub fn mode(self) -> IntrinsicsMode {
        match self {
            IntrinsicsArg::Known => IntrinsicsMode::Known,
            IntrinsicsArg::Unknown => IntrinsicsMode::Unknown,
        }
    }
}

/// The registration settings the command line selects.
pub fn registration_config(with_depth: bool, coarse: &CoarseArgs) -> RegistrationConfig {
    RegistrationConfig {
        query_mode: if with_depth {
            QueryMode::DepthAsg
        } else {
            QueryMode::ImageGradient
        },
        coarse_pose_count: coarse.coarse_poses,
        coarse_rotation_sigma_deg: coarse.coarse_rotation_deg,
        coarse_translation_sigma_fraction: coarse.coarse_translation_fraction,
        lift_edge_margin_px: coarse.lift_edge_margin_px,
        verify: VerifyConfig {
            max_convergence_ratio: coarse.max_convergence_ratio,
            ..VerifyConfig::default()
        },
        edge_align: EdgeAlignConfig {
            enabled: !coarse.no_edge_align,
            initial_search_radius_px: coarse.edge_search_px,
            ..EdgeAlignConfig::default()
        },
        pose_search: asgreg::core::pose_search::PoseSearchConfig {
            enabled: !coarse.no_pose_search,
            ..Default::default()
        },
        ..RegistrationConfig::default()
    }
}

/// A progress bar on stderr for `count` frames.
pub fn progress_bar(count: usize, what: &str) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(count as u64);
    if let Ok(style) = indicatif::ProgressStyle::with_template(
        "{msg} [{bar:30}] {pos}/{len} frames, {elapsed} elapsed, ETA {eta}",
    ) {
        bar.set_style(style.progress_chars("=> "));
    }
    bar.set_message(what.to_string());
    bar
}

pub fn run(args: &RegisterArgs) -> anyhow::Result<()> {
    // The environment first: an output folder that cannot be written, or a mesh too large for the
    // memory given, fail in a second, not after the registration.
    prepare_output_dir(&args.out)?;
    if let Some(limit_mib) = args.max_mesh_mib {
        check_mesh_fits(&args.mesh, limit_mib)?;
    }
    let inputs = load_posed_inputs(&args.mesh, &args.cameras, &args.poses)?;
    let config = registration_config(args.depth.is_some(), &args.coarse);
    config.validate()?;
    let mut frames = Vec::new();
    for image in inputs.images.iter().take(args.limit.unwrap_or(usize::MAX)) {
        let camera = inputs.cameras.get(&image.camera_id).with_context(|| {
            format!(
                "image '{}' in {} uses camera {}, which {} does not define",
                image.name,
                args.poses.display(),
                image.camera_id,
                args.cameras.display()
            )
        })?;
        frames.push(BatchFrame {
            image_id: image.image_id,
            camera_id: image.camera_id,
            name: image.name.clone(),
            image_path: args.images.join(&image.name),
            depth_path: args
                .depth
                .as_ref()
                .map(|dir| depth_path_for(dir, &image.name)),
            camera: *camera,
            intrinsics: args.intrinsics.mode(),
            initial_cam_from_world: image.cam_from_world,
        });
    }

    let loader = FrameLoader::new((args.working_width > 0).then_some(args.working_width));
    let bar = progress_bar(frames.len(), "registering");
    let mut reports = Vec::with_capacity(frames.len());
    for frame in &frames {
        let report = register_batch_frame_with(&inputs.mesh, frame, &loader, &config, args.seed);
        bar.println(format!(
            "{}: {}",
            report.name,
            if report.accepted {
                format!(
                    "accepted (confidence {:.2}, {} of {} poses agree, consensus {}, {:.0} ms)",
                    report.confidence,
                    report.component_size,
                    report.hypotheses,
                    report.consensus,
                    report.timings.total_ms
                )
            } else {
                format!("FAILED: {}", report.reason.as_deref().unwrap_or("unknown"))
            }
        ));
        bar.inc(1);
        reports.push(report);
    }
    bar.finish_and_clear();

    write_outputs(args, &inputs.mesh, &frames, &reports, &config, &loader)?;
    let accepted = reports.iter().filter(|r| r.accepted).count();
    println!(
        "registered {accepted} of {} frames; poses in {}, report in {}",
        reports.len(),
        args.out.join("images.txt").display(),
        args.out.join("report.json").display()
    );
    Ok(())
}

fn write_outputs(
    args: &RegisterArgs,
    mesh: &asgreg::core::mesh::Mesh,
    frames: &[BatchFrame],
    reports: &[FrameReport],
    config: &RegistrationConfig,
    loader: &FrameLoader,
) -> anyhow::Result<()> {
    let mut cameras = BTreeMap::new();
    let mut poses = Vec::new();
    for (frame, report) in frames.iter().zip(reports) {
        let (Some(camera), Some(cam_from_world)) = (report.camera, report.cam_from_world) else {
            continue;
        };
        // Unknown intrinsics: one camera per image (its id is the image id).
        let camera_id = if args.intrinsics.mode() == IntrinsicsMode::Unknown {
            let mut camera = camera;
            camera.intrinsics.skew_px = 0.0;
            cameras.insert(frame.image_id, camera);
            frame.image_id
        } else {
            cameras.insert(frame.camera_id, frame.camera);
            frame.camera_id
        };
        poses.push(ImagePose {
            image_id: frame.image_id,
            camera_id,
            name: frame.name.clone(),
            cam_from_world,
        });
    }
    // The accepted poses as a COLMAP model, text and binary, and as omega-phi-kappa for GIS.
    write_opk_csv(&args.out.join(OPK_FILE), &poses)?;
    write_model_dir(
        &args.out,
        &ColmapModel {
            cameras,
            images: poses,
        },
    )?;
    let report_path = args.out.join("report.json");
    let json = serde_json::json!({
        "config": config,
        "intrinsics": args.intrinsics.mode(),
        "working_width_px": (args.working_width > 0).then_some(args.working_width),
        "frames": reports,
    });
    std::fs::write(&report_path, serde_json::to_string_pretty(&json)?)
        .with_context(|| format!("writing {}", report_path.display()))?;

    if !args.no_overlays {
        let overlay_dir = args.out.join("overlays");
        std::fs::create_dir_all(&overlay_dir)
            .with_context(|| format!("creating {}", overlay_dir.display()))?;
        for (frame, report) in frames.iter().zip(reports) {
            if let Err(error) = write_overlays(mesh, frame, report, loader, &overlay_dir) {
                tracing::warn!("{}: no overlay: {error:#}", frame.name);
            }
        }
    }
    Ok(())
}

/// The frame's photo with the model drawn over it at the initial and (when accepted) the
/// registered pose, as registration saw it: with the working camera (undistorted, at the working
/// width), so that a lens's distortion does not show as misalignment.
fn write_overlays(
    mesh: &asgreg::core::mesh::Mesh,
    frame: &BatchFrame,
    report: &FrameReport,
    loader: &FrameLoader,
    overlay_dir: &Path,
) -> anyhow::Result<()> {
    let working = loader.working_camera(&frame.image_path, frame.camera_id, &frame.camera)?;
    let rgb = working_rgb(&working, &load_rgb(&frame.image_path)?)?;
    let stem = Path::new(&frame.name)
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| frame.name.clone());
    let mut views = vec![("before", working.working, frame.initial_cam_from_world)];
    if let (Some(camera), Some(pose)) = (report.camera, report.cam_from_world) {
        views.push(("after", working.working_camera_for(&camera), pose));
    }
    for (label, camera, pose) in views {
        let render = render_view(
            mesh,
            &camera,
            &pose,
            asgreg::core::raster::NormalSource::Vertex,
        );
        let picture = overlay_model(rgb.view(), &render, OverlayStyle::NormalsAndEdges, 0.4)?;
        save_rgb_png(
            &overlay_dir.join(format!("{stem}_{label}.png")),
            picture.view(),
        )?;
    }
    Ok(())
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
