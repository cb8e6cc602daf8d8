//! The streaming pipeline's commands: `run` (all stages as threads of this process; with no
//! config it makes a synthetic scene: the embedded default), `stage` (one stage worker as its own
//! process), `launch` (the ground-station supervisor), `subscribe` (print PoseResults, change
//! results and the final change set as they arrive) and `bench pipeline` (frames/s per
//! flow-worker count). `main` only wires: the loops are in `asgreg::runtime`.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Context};
use asgreg::io::mesh_file::{check_mesh_fits, read_mesh, read_mesh_within};
use asgreg::io::output::prepare_output_dir;
use asgreg::msg::{ChangeResult, ChangeSet, Header, PoseResult};
use asgreg::runtime::collect::{summary, Collected, Delivered};
use asgreg::runtime::config::PipelineConfig;
use asgreg::runtime::journal;
use asgreg::runtime::launch::{absolute, launch, start_router, StageCommand};
use asgreg::runtime::nodes::{self, NodeContext};
use asgreg::runtime::{run_in_process, run_state_parent};
use asgreg::stage::ingest::SourceConfig;
use asgreg::transport::{self, Backend};

use super::synth::{SceneArg, SynthArgs};

#[derive(clap::Args, Debug)]
pub struct RunArgs {
    /// Pipeline configuration (TOML, see deploy/). Without it: a synthetic scene is made in
    /// OUT/scene and registered (the embedded default).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Where the embedded default writes its scene and every run its results.
    #[arg(long, default_value = "asgreg-run")]
    pub out: PathBuf,
    /// Override the configuration's backend (crossbeam, iceoryx2, zenoh: all in this process).
    #[arg(long)]
    pub backend: Option<BackendArg>,
    /// Override the number of flow workers.
    #[arg(long)]
    pub flow_workers: Option<u32>,
    /// Override the number of change detection workers (0: no change detection).
    #[arg(long)]
    pub change_workers: Option<u32>,
    /// Frames of the embedded default scene.
    #[arg(long, default_value_t = 8)]
    pub frames: usize,
    /// Refuse a mesh that would take more memory than this to load (MiB), judged from its
    /// header before any stage starts (over the configuration's `max_mesh_mib`).
    #[arg(long, value_name = "MIB")]
    pub max_mesh_mib: Option<u64>,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug)]
pub enum BackendArg {
    Crossbeam,
    Iceoryx2,
    Zenoh,
}

impl From<BackendArg> for Backend {
    fn from(value: BackendArg) -> Self {
        match value {
            BackendArg::Crossbeam => Backend::Crossbeam,
            BackendArg::Iceoryx2 => Backend::Iceoryx2,
            BackendArg::Zenoh => Backend::Zenoh,
        }
    }
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum StageName {
    Ingest,
    Render,
    Flow,
    Pose,
    Verify,
    Change,
    Fusion,
}

#[derive(clap::Args, Debug)]
pub struct StageArgs {
    /// Which stage this process runs.
    pub stage: StageName,
    /// Pipeline configuration (TOML).
    #[arg(long)]
    pub config: PathBuf,
    /// Worker index among the stage's workers (0-based).
    #[arg(long, default_value_t = 0)]
    pub worker: u32,
    /// Refuse a mesh that would take more memory than this to load (MiB), over the
    /// configuration's `max_mesh_mib` (`launch` passes its own).
    #[arg(long, value_name = "MIB")]
    pub max_mesh_mib: Option<u64>,
}

#[derive(clap::Args, Debug)]
pub struct LaunchArgs {
    /// Deployment configuration, e.g. deploy/ground-station.toml.
    pub config: PathBuf,
    /// Where results.jsonl and summary.txt go.
    #[arg(long, default_value = "asgreg-launch")]
    pub out: PathBuf,
    /// Refuse a mesh that would take more memory than this to load (MiB), judged from its
    /// header before any stage starts (over the configuration's `max_mesh_mib`; the stages get
    /// it too).
    #[arg(long, value_name = "MIB")]
    pub max_mesh_mib: Option<u64>,
}

#[derive(clap::Args, Debug)]
pub struct SubscribeArgs {
    /// Pipeline configuration (backend, pipeline name, zenoh endpoints).
    #[arg(long)]
    pub config: PathBuf,
    /// Exit after this many results (0: run until the end of the stream).
    #[arg(long, default_value_t = 0)]
    pub count: usize,
}

#[derive(clap::Args, Debug)]
pub struct BenchArgs {
    /// What to benchmark: `pipeline` (whole-pipeline runs) or `mesh` (a synthetic city of
    /// `--triangles`: load time, render ms per frame, culling, one registration, peak RSS).
    pub what: BenchWhat,
    /// `mesh`: triangles of the synthetic city.
    #[arg(long, default_value_t = 1_000_000)]
    pub triangles: u64,
    /// Scene folder as `asgreg synth` writes it; default: make one in OUT/scene.
    #[arg(long)]
    pub scene: Option<PathBuf>,
    #[arg(long, default_value = "asgreg-bench")]
    pub out: PathBuf,
    /// Frames per run.
    #[arg(long, default_value_t = 8)]
    pub frames: usize,
    /// Flow worker counts to compare.
    #[arg(long, value_delimiter = ',', default_value = "1,2,4")]
    pub flow_workers: Vec<u32>,
    /// Backends to compare (all stages as threads of this process).
    #[arg(long, value_delimiter = ',', default_value = "crossbeam")]
    pub backends: Vec<BackendArg>,
    /// The real loops, ports, dispatchers and transports, but every stage sleeps a measured
    /// per-job time instead of computing (`stage::simulate`), so that many flow workers fit on
    /// a few cores; frames are then the scene's photos repeated.
    #[arg(long)]
    pub simulate: bool,
    /// `--simulate`: every simulated time multiplied by this (shorter runs, same ratios).
    #[arg(long, default_value_t = 1.0)]
    pub time_scale: f64,
    /// `--simulate`: render time per coarse view, ms (default: measured, `SimulatedWork`).
    #[arg(long)]
    pub render_view_ms: Option<f64>,
    /// `--simulate`: flow time per job, ms.
    #[arg(long)]
    pub flow_job_ms: Option<f64>,
    /// `--simulate`: pose time per coarse pose, ms.
    #[arg(long)]
    pub pose_job_ms: Option<f64>,
    /// `--simulate`: verify's decision per frame, ms.
    #[arg(long)]
    pub verify_frame_ms: Option<f64>,
    /// Frames per run at least this many times the flow workers (steady state with many workers).
    #[arg(long, default_value_t = 0)]
    pub frames_per_flow_worker: usize,
    /// Render workers (0: enough for the flow workers by the simulated times).
    #[arg(long, default_value_t = 1)]
    pub render_workers: u32,
    /// Pose workers (0: enough for the flow workers by the simulated times).
    #[arg(long, default_value_t = 1)]
    pub pose_workers: u32,
    /// Verify's deciding threads (0: enough for the flow workers by the simulated times).
    #[arg(long, default_value_t = 1)]
    pub verify_threads: u32,
    /// Without step "neighbour" (`registration.neighbour_pose.enabled = false`): its cost in
    /// frames/s and latency, against a run with it.
    #[arg(long)]
    pub no_neighbours: bool,
    /// Step "neighbour"'s look-ahead, frames (`registration.neighbour_pose.lookahead_frames`: a
    /// frame's result waits for that many frames after it).
    #[arg(long, default_value_t = asgreg::core::frame::NeighbourPoseConfig::default().lookahead_frames)]
    pub neighbour_lookahead: usize,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug)]
pub enum BenchWhat {
    Pipeline,
    Mesh,
}

/// The embedded default scene: a town block, `frames` photos at 505×275, 30 px initial poses.
fn default_scene(out: &Path, frames: usize) -> anyhow::Result<PathBuf> {
    default_scene_at(&out.join("scene"), frames)
}

fn default_scene_at(scene: &Path, frames: usize) -> anyhow::Result<PathBuf> {
    synthetic_scene_at(scene, frames, (505, 275))
}

/// A town-block scene of `frames` photos of `width`×`height` with 30 px initial poses in
/// `scene`, made unless one with that many photos is there.
pub(super) fn synthetic_scene_at(
    scene: &Path,
    frames: usize,
    size: (u32, u32),
) -> anyhow::Result<PathBuf> {
    synthetic_scene_with(scene, frames, size, 30, false)
}

/// As [`synthetic_scene_at`], with initial poses of `level_px` and, with `changes`, changes
/// between the model and the photos (`synth --changes`).
pub(super) fn synthetic_scene_with(
    scene: &Path,
    frames: usize,
    (width, height): (u32, u32),
    level_px: u32,
    changes: bool,
) -> anyhow::Result<PathBuf> {
    let scene = scene.to_path_buf();
    let initial = scene.join(format!("initial/{level_px}/images.txt"));
    if scene.join("scene.json").is_file() && initial.is_file() {
        let listed = asgreg::io::colmap::read_images_txt(&initial)?;
        if listed.len() == frames {
            println!("using the synthetic scene in {}", scene.display());
            return Ok(scene);
        }
    }
    println!(
        "making a synthetic scene in {} ({frames} photos of a town block seen from 30–60 m, {width}x{height}, initial poses {level_px} px off)",
        scene.display()
    );
    let args = SynthArgs {
        out: scene.clone(),
        seed: 1,
        width,
        height,
        images: frames,
        // The product's case (docs/design.md §1: a drone over a town). The paper's free-standing house
        // (`asgreg synth --scene house`) is harder: see the #4 note in README.
        scene: SceneArg::Block,
        levels: vec![f64::from(level_px)],
        changes,
        no_heading_level: true,
        triangles: 1_000_000,
        heading_min_deg: asgreg::synth::initial::HeadingNoise::default().heading_min_deg,
        heading_max_deg: asgreg::synth::initial::HeadingNoise::default().heading_max_deg,
        heading_flip_every: asgreg::synth::initial::HeadingNoise::default().flip_every,
        flight_path: false,
    };
    asgreg::synth::generate_scene(&args.config(), &scene)?;
    Ok(scene)
}

pub(super) fn scene_config(scene: &Path) -> PipelineConfig {
    PipelineConfig {
        mesh: scene.join("model.ply"),
        source: SourceConfig::scene(scene, 30),
        ..PipelineConfig::default()
    }
}

/// Prints what the collector hands on: results, change results, the final change set.
fn print_delivered(delivered: Delivered<'_>) {
    match delivered {
        Delivered::Pose(header, result) => print_result(header, result),
        Delivered::Change(result) => print_change(result),
        Delivered::ChangeSet(set) => print_change_set(set),
    }
}

fn print_change(result: &ChangeResult) {
    match &result.failure {
        Some(why) => println!(
            "change {:>3} {:<20} none ({why})",
            result.frame_id, result.name
        ),
        None => {
            let regions: Vec<String> = result
                .regions
                .iter()
                .map(|r| {
                    format!(
                        "{} {:.0} m² {:.1} m high at ({:.1}, {:.1})",
                        r.kind.name(),
                        r.footprint_area_m2,
                        r.height_m,
                        r.centroid_m[0],
                        r.centroid_m[1]
                    )
                })
                .collect();
            println!(
                "change {:>3} {:<20} {} regions ({} added, {} removed px) in {:.1} ms (worker {}){}{}",
                result.frame_id,
                result.name,
                result.regions.len(),
                result.counts.added,
                result.counts.removed,
                result.change_ms,
                result.change_worker.map_or("-".to_string(), |w| w.to_string()),
                if regions.is_empty() { "" } else { ": " },
                regions.join("; ")
            )
        }
    }
}

fn print_change_set(set: &ChangeSet) {
    println!(
        "change set: {} objects ({} confirmed) from {} change maps of {} frames",
        set.objects.len(),
        set.objects.iter().filter(|o| o.confirmed).count(),
        set.frames_with_map,
        set.frames_with_result
    );
    for (index, object) in set.objects.iter().enumerate() {
        let free_space = set
            .free_space
            .iter()
            .find(|check| check.object == index)
            .map_or(String::new(), |check| {
                format!(
                    " (free space: seen through by frames {:?}, agreed by {:?}{})",
                    check.seen_through_by,
                    check.agreed_by,
                    if check.refuted { ", refuted" } else { "" }
                )
            });
        println!(
            "  {:<7} {:>7.1} m² footprint, {:>5.1} m high, at ({:.1}, {:.1}), frames {:?}{}{free_space}",
            object.kind.name(),
            object.footprint_area_m2,
            object.height_m,
            object.centroid_m[0],
            object.centroid_m[1],
            object.frames,
            if object.confirmed {
                ", confirmed"
            } else {
                ", unconfirmed"
            }
        );
    }
}

fn print_result(_header: &Header, result: &PoseResult) {
    let pose = result
        .cam_from_world
        .map(|p| {
            format!(
                " q=[{:.5} {:.5} {:.5} {:.5}] t=[{:.3} {:.3} {:.3}]",
                p.qvec_wxyz[0],
                p.qvec_wxyz[1],
                p.qvec_wxyz[2],
                p.qvec_wxyz[3],
                p.tvec_m[0],
                p.tvec_m[1],
                p.tvec_m[2]
            )
        })
        .unwrap_or_default();
    println!(
        "frame {:>4} {:<20} {} confidence {:.2} latency {:>6.0} ms{}{}",
        result.frame_id,
        result.name,
        if result.accepted {
            "ACCEPTED"
        } else {
            "failed  "
        },
        result.confidence,
        result.times.latency_ms,
        pose,
        result
            .failure
            .as_deref()
            .map(|f| format!(" ({f})"))
            .unwrap_or_default()
    );
}

/// Prints the summary, writes results.jsonl and summary.txt, and fails unless every frame has
/// exactly one result.
fn report(out: &Path, collected: &Collected, backend: &str) -> anyhow::Result<()> {
    let text = summary(collected, backend);
    println!("{text}");
    write_outputs(out, collected, &text)?;
    check_complete(collected)
}

pub(super) fn write_outputs(out: &Path, collected: &Collected, text: &str) -> anyhow::Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let path = out.join("results.jsonl");
    let mut file = std::io::BufWriter::new(
        std::fs::File::create(&path).with_context(|| format!("cannot write {}", path.display()))?,
    );
    for result in collected.by_frame() {
        serde_json::to_writer(&mut file, result)?;
        writeln!(file)?;
    }
    file.flush()?;
    if !collected.change_results.is_empty() || collected.change_set.is_some() {
        let path = out.join("changes.jsonl");
        let mut file = std::io::BufWriter::new(
            std::fs::File::create(&path)
                .with_context(|| format!("cannot write {}", path.display()))?,
        );
        for result in collected.changes_by_frame() {
            serde_json::to_writer(&mut file, result)?;
            writeln!(file)?;
        }
        file.flush()?;
        if let Some(set) = &collected.change_set {
            let path = out.join("change_set.json");
            std::fs::write(&path, serde_json::to_string_pretty(set)?)
                .with_context(|| format!("cannot write {}", path.display()))?;
        }
    }
    std::fs::write(out.join("summary.txt"), text)?;
    println!(
        "results: {}, summary: {}",
        path.display(),
        out.join("summary.txt").display()
    );
    Ok(())
}

pub(super) fn check_complete(collected: &Collected) -> anyhow::Result<()> {
    let missing = collected.missing();
    if collected.frame_count.is_none() {
        bail!(
            "the stream did not end: {} results arrived before the deadline",
            collected.results.len()
        );
    }
    if !missing.is_empty() || !collected.duplicates.is_empty() {
        bail!(
            "frames without exactly one result: missing {missing:?}, duplicated {:?}",
            collected.duplicates
        );
    }
    if !collected.change_results.is_empty() || collected.change_set.is_some() {
        let missing = collected.missing_changes();
        if !missing.is_empty() || !collected.change_duplicates.is_empty() {
            bail!(
                "frames without exactly one change result: missing {missing:?}, duplicated {:?}",
                collected.change_duplicates
            );
        }
        if collected.change_set.is_none() {
            bail!("the change stream did not end: no complete change set arrived");
        }
    }
    Ok(())
}

/// Makes the configuration's synthetic scene if it asks for one that is not there yet.
fn ensure_synthetic_scene(config: &PipelineConfig, frames: usize) -> anyhow::Result<()> {
    if let Some(scene) = &config.synthetic_scene {
        if !scene.join("initial/30/images.txt").is_file() {
            default_scene_at(scene, frames)?;
        }
    }
    Ok(())
}

/// The environment of a pipeline run, checked before any stage starts (a station that would
/// find out an hour in, or leave stages crash-looping, learns it in a second): the output folder
/// and the state folder (`state`) can be written. Each error is one line naming the folder and
/// what to do.
fn check_folders(out: &Path, state: &Path) -> anyhow::Result<()> {
    prepare_output_dir(out)?;
    journal::prepare_state_dir(state)?;
    Ok(())
}

/// The mesh fits the memory limit (`max_mesh_mib`), judged from its header before any stage
/// loads it.
fn check_mesh_limit(config: &PipelineConfig) -> anyhow::Result<()> {
    if let Some(limit_mib) = config.max_mesh_mib {
        check_mesh_fits(&config.mesh, limit_mib)?;
    }
    Ok(())
}

pub fn run(args: &RunArgs) -> anyhow::Result<()> {
    let mut config = match &args.config {
        Some(path) => PipelineConfig::read(path)?,
        None => scene_config(&args.out.join("scene")),
    };
    if let Some(backend) = args.backend {
        config.backend = backend.into();
    }
    if let Some(flow) = args.flow_workers {
        config.workers.flow = flow;
    }
    if let Some(change) = args.change_workers {
        config.workers.change = change;
    }
    if let Some(limit_mib) = args.max_mesh_mib {
        config.max_mesh_mib = Some(limit_mib);
    }
    config.validate(args.config.as_deref().unwrap_or(Path::new("(defaults)")))?;
    check_folders(&args.out, &run_state_parent(&config))?;
    match &args.config {
        Some(_) => ensure_synthetic_scene(&config, args.frames)?,
        None => {
            default_scene(&args.out, args.frames)?;
        }
    }
    check_mesh_limit(&config)?;
    let mesh = read_mesh(&config.mesh)?;
    let transport = transport::open(config.backend, &config.transport, &config.zenoh)?;
    let change_stages = if config.changes_enabled() {
        format!(", {} change and fusion", config.workers.change)
    } else {
        String::new()
    };
    println!(
        "running ingest, {} render, {} flow, {} pose, verify{change_stages} as threads over {}",
        config.workers.render,
        config.workers.flow,
        config.workers.pose,
        config.backend.name()
    );
    let collected = run_in_process(
        &config,
        transport.as_ref(),
        &mesh,
        Duration::from_secs_f64(config.launch.deadline_s),
        &mut print_delivered,
    )?;
    report(&args.out, &collected, config.backend.name())
}

pub fn stage(args: &StageArgs) -> anyhow::Result<()> {
    let config = PipelineConfig::read(&args.config)?;
    let _span = tracing::info_span!("stage", name = ?args.stage, worker = args.worker).entered();
    let transport = transport::open(config.backend, &config.transport, &config.zenoh)?;
    // SIGTERM/SIGINT stop the stage cleanly (the launcher sends SIGTERM to stop it).
    let stop = nodes::termination_flag()?;
    let context = NodeContext {
        transport: transport.as_ref(),
        config: &config,
        worker_index: args.worker,
        stop,
    };
    let needs_mesh = matches!(
        args.stage,
        StageName::Render | StageName::Flow | StageName::Verify | StageName::Change
    );
    let mesh = if needs_mesh {
        Some(read_mesh_within(
            &config.mesh,
            args.max_mesh_mib.or(config.max_mesh_mib),
        )?)
    } else {
        None
    };
    let mesh = mesh.as_ref();
    let metrics = match (args.stage, mesh) {
        (StageName::Ingest, _) => nodes::run_ingest(&context)?,
        (StageName::Render, Some(mesh)) => nodes::run_render(&context, mesh)?,
        (StageName::Flow, Some(mesh)) => nodes::run_flow(&context, mesh)?,
        (StageName::Pose, _) => nodes::run_pose(&context)?,
        (StageName::Verify, Some(mesh)) => nodes::run_verify(&context, mesh)?,
        (StageName::Change, Some(mesh)) => nodes::run_change(&context, mesh)?,
        (StageName::Fusion, _) => nodes::run_fusion(&context)?,
        (stage, None) => bail!("stage {stage:?} needs the mesh"),
    };
    tracing::info!(
        "done: {} in, {} out",
        metrics.messages_in,
        metrics.messages_out
    );
    Ok(())
}

pub fn launch_command(args: &LaunchArgs, verbose: u8) -> anyhow::Result<()> {
    let mut config = PipelineConfig::read(&args.config)?;
    if let Some(limit_mib) = args.max_mesh_mib {
        config.max_mesh_mib = Some(limit_mib);
    }
    check_folders(&args.out, &journal::state_dir(&config))?;
    ensure_synthetic_scene(&config, 8)?;
    check_mesh_limit(&config)?;
    let collected = launch_pipeline(
        &config,
        &args.config,
        verbose,
        &mut |stage, worker, pid| eprintln!("launch: {stage} worker {worker} pid {pid}"),
        &mut print_delivered,
    )?;
    report(&args.out, &collected, config.backend.name())
}

/// Runs `config` (read from `config_path`, which the stage processes read too) as one process
/// per stage worker: cleans stale iceoryx2 resources or starts the zenoh router, supervises the
/// stages, and returns what the collector saw.
pub(super) fn launch_pipeline(
    config: &PipelineConfig,
    config_path: &Path,
    verbose: u8,
    on_started: &mut dyn FnMut(&str, u32, u32),
    on_result: &mut dyn FnMut(Delivered<'_>),
) -> anyhow::Result<Collected> {
    if config.backend == Backend::Crossbeam {
        bail!(
            "{}: backend 'crossbeam' is one process; launch needs backend = \"iceoryx2\" or \"zenoh\" (or use `asgreg run`)",
            config_path.display()
        );
    }
    if config.backend == Backend::Iceoryx2 {
        let cleaned = transport::clean_stale_resources()?;
        if cleaned > 0 {
            println!("cleaned the shared-memory resources of {cleaned} dead process(es)");
        }
    }
    // zenoh's router runs in a process of its own (next to slow subscribers in one process it
    // can deadlock, see transport::zenoh), supervised by `launch` like a stage.
    let program = std::env::current_exe().context("cannot find the asgreg executable")?;
    let command = StageCommand {
        program,
        config_path: absolute(config_path),
        global_args: (0..verbose).map(|_| "-v".to_string()).collect(),
        // The stages check the limit the launcher was given (its own, or the file's).
        stage_args: config
            .max_mesh_mib
            .map(|limit_mib| vec!["--max-mesh-mib".to_string(), limit_mib.to_string()])
            .unwrap_or_default(),
    };
    let mut router = start_router(config, &command)?;
    if let Some(router) = &router {
        eprintln!(
            "launch: zenoh router pid {} on {}",
            router.id(),
            config.launch.zenoh_router_listen.join(", ")
        );
    }
    let transport = match transport::open(config.backend, &config.transport, &config.zenoh) {
        Ok(transport) => transport,
        Err(error) => {
            if let Some(router) = &mut router {
                let _ = router.kill();
                let _ = router.wait();
            }
            return Err(error.into());
        }
    };
    let collected = launch(
        config,
        transport.as_ref(),
        &command,
        router,
        on_started,
        on_result,
    );
    drop(transport);
    if config.backend == Backend::Iceoryx2 {
        // What killed stages left that their successors' cleanups could not remove.
        match transport::clean_stale_resources_after_exit() {
            Ok(0) => {}
            Ok(cleaned) => eprintln!(
                "launch: cleaned the shared-memory resources of {cleaned} dead process(es)"
            ),
            Err(error) => eprintln!("launch: {error}"),
        }
    }
    Ok(collected?)
}

#[derive(clap::Args, Debug)]
pub struct RouterArgs {
    /// Endpoint to listen on, e.g. tcp/192.168.10.1:7447 or tls/192.168.10.1:7448 (repeat for
    /// several). With --config: replaces the file's listen endpoints.
    #[arg(long, required_unless_present = "config")]
    pub listen: Vec<String>,
    /// A zenoh json5 router config to start from (TLS, access control: deploy/zenoh/).
    #[arg(long)]
    pub config: Option<PathBuf>,
}

/// `asgreg zenoh-router`: the ground station's zenoh router, until killed.
pub fn router(args: &RouterArgs) -> anyhow::Result<()> {
    let _router = transport::zenoh::RouterHandle::open(&transport::zenoh::ZenohSettings {
        mode: transport::zenoh::ZenohMode::Router,
        listen: (!args.listen.is_empty()).then(|| args.listen.clone()),
        connect: None,
        config_file: args.config.clone(),
        ..transport::zenoh::ZenohSettings::default()
    })?;
    tracing::info!(
        "zenoh router listening on {}{}",
        if args.listen.is_empty() {
            "the config file's endpoints".to_string()
        } else {
            args.listen.join(", ")
        },
        args.config
            .as_ref()
            .map(|path| format!(" (config {})", path.display()))
            .unwrap_or_default()
    );
    loop {
        std::thread::sleep(Duration::from_secs(3600));
    }
}

pub fn subscribe(args: &SubscribeArgs) -> anyhow::Result<()> {
    let config = PipelineConfig::read(&args.config)?;
    let transport = transport::open(config.backend, &config.transport, &config.zenoh)?;
    let mut collector = asgreg::runtime::collect::Collector::open(
        transport.as_ref(),
        config.changes_enabled(),
        false,
    )?;
    let seen = std::cell::Cell::new(0usize);
    let count = args.count;
    let collected = collector.collect(
        Duration::from_secs_f64(config.launch.deadline_s),
        &mut |delivered| {
            if let Delivered::Pose(..) = delivered {
                seen.set(seen.get() + 1);
            }
            print_delivered(delivered);
        },
        &mut || count == 0 || seen.get() < count,
    )?;
    println!("{} results", collected.results.len());
    Ok(())
}

pub fn bench(args: &BenchArgs) -> anyhow::Result<()> {
    if let BenchWhat::Mesh = args.what {
        return super::bench_mesh::bench_mesh(&args.out, args.triangles, args.frames);
    }
    // Every run writes its summary into OUT: make it first (a given `--scene` made nothing there).
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating the output folder {}", args.out.display()))?;
    let scene = match &args.scene {
        Some(scene) => scene.clone(),
        None => default_scene(&args.out, args.frames)?,
    };
    // Absolute: the stage processes read the configuration from another folder.
    let scene = absolute(&scene);
    let mut base = scene_config(&scene);
    base.source.max_frames = args.frames;
    base.registration.neighbour_pose.enabled = !args.no_neighbours;
    base.registration.neighbour_pose.lookahead_frames = args.neighbour_lookahead;
    let mesh = read_mesh(&base.mesh)?;
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let step = &base.registration.neighbour_pose;
    println!(
        "whole-pipeline runs (crossbeam: threads of one process; iceoryx2, zenoh: one process per stage worker), {} frames at 505x275, {} coarse poses each, step \"neighbour\" {}, on {cores} cores",
        args.frames,
        base.registration.coarse_pose_count,
        if step.enabled {
            format!("on (look-ahead {} frames)", step.lookahead_frames)
        } else {
            "off".to_string()
        }
    );
    let simulated = args.simulate.then(|| simulated_work(args));
    if let Some(work) = &simulated {
        println!(
            "simulated: render {:.1} ms/view x {} views, flow {:.1} ms/job, pose {:.1} ms/job, verify {:.1} ms/frame (stages sleep instead of computing; --time-scale {})",
            work.render_view_ms, work.coarse_views, work.flow_job_ms, work.pose_job_ms, work.verify_frame_ms, args.time_scale
        );
    }
    let mut rows = Vec::new();
    for backend in &args.backends {
        for &flow in &args.flow_workers {
            let mut config = base.clone();
            config.backend = (*backend).into();
            config.workers.flow = flow;
            let frames = args.frames.max(args.frames_per_flow_worker * flow as usize);
            config.source.max_frames = frames;
            if let Some(work) = simulated {
                config.simulate = Some(work);
                if frames > base_frame_count(&config)? {
                    repeat_frames(&mut config, frames, &args.out)?;
                }
            }
            config.workers.render = match args.render_workers {
                0 => stage_workers(simulated, flow, |w| w.render_view_ms),
                n => n,
            }
            .min(flow);
            config.workers.pose = match args.pose_workers {
                0 => stage_workers(simulated, flow, |w| w.pose_job_ms),
                n => n,
            };
            config.workers.verify_threads = match args.verify_threads {
                0 => stage_workers(simulated, flow, |w| {
                    w.verify_frame_ms / f64::from(w.coarse_views.max(1))
                }),
                n => n,
            };
            config.transport.pipeline = format!("bench-{}-{flow}", std::process::id());
            // When each result arrived: the steady rate leaves out the pipeline's filling.
            let mut arrivals = Vec::new();
            let mut on_result = |delivered: Delivered<'_>| {
                if let Delivered::Pose(..) = delivered {
                    arrivals.push(std::time::Instant::now());
                }
            };
            let collected = if config.backend == Backend::Crossbeam {
                let transport = transport::open(config.backend, &config.transport, &config.zenoh)?;
                run_in_process(
                    &config,
                    transport.as_ref(),
                    &mesh,
                    Duration::from_secs(3600),
                    &mut on_result,
                )?
            } else {
                // One process per stage worker, as deployed.
                if config.backend == Backend::Zenoh {
                    let port = std::net::TcpListener::bind("127.0.0.1:0")?
                        .local_addr()?
                        .port();
                    let endpoint = format!("tcp/127.0.0.1:{port}");
                    config.launch.zenoh_router_listen = vec![endpoint.clone()];
                    config.zenoh.connect = Some(vec![endpoint]);
                }
                std::fs::create_dir_all(&args.out)?;
                let path = args
                    .out
                    .join(format!("bench-{}-{flow}.toml", config.backend.name()));
                std::fs::write(&path, toml::to_string(&config)?)?;
                launch_pipeline(&config, &path, 0, &mut |_, _, _| {}, &mut on_result)?
            };
            let steady = match (arrivals.first(), arrivals.last()) {
                (Some(first), Some(last)) if arrivals.len() > 1 && last > first => {
                    (arrivals.len() - 1) as f64 / last.duration_since(*first).as_secs_f64()
                }
                _ => collected.frames_per_s(),
            };
            check_complete(&collected)?;
            // Each run's per-stage table (messages, compute, send and decode time per worker):
            // where the time went when a run scales worse than its workers.
            let summary = args.out.join(format!(
                "bench-{}-{flow}-summary.txt",
                config.backend.name()
            ));
            std::fs::write(
                &summary,
                asgreg::runtime::collect::summary(&collected, config.backend.name()),
            )
            .with_context(|| format!("{}", summary.display()))?;
            let stages = format!(
                "{}/{}/{}",
                config.workers.render, config.workers.pose, config.workers.verify_threads
            );
            // Each run as it ends (the table follows at the end).
            println!(
                "run: {} flow {flow} render/pose/verify {stages}: {} frames, {:.3} frames/s, steady {steady:.3} frames/s",
                config.backend.name(),
                collected.results.len(),
                collected.frames_per_s()
            );
            rows.push((config.backend.name(), flow, stages, steady, collected));
        }
    }
    println!(
        "{:<10} {:>5} {:>13} {:>6} {:>9} {:>9} {:>8} {:>8} {:>8} {:>10} {:>8}  p50 stage ms: render/frame flow/job pose/job verify/frame; flow jobs per worker",
        "backend", "flow", "rend/pose/ver", "frames", "frames/s", "steady/s", "speedup", "p50_ms", "p90_ms", "transport%", "accepted"
    );
    // Speedup: steady rate (first to last result) over the first row's.
    let baseline = rows.first().map_or(1.0, |(_, _, _, steady, _)| *steady);
    for (backend, flow, stages, steady, collected) in &rows {
        let latencies = collected.latencies_ms();
        let median = |value: &dyn Fn(&PoseResult) -> Option<f64>| {
            let values: Vec<f64> = collected.results.iter().filter_map(value).collect();
            asgreg::runtime::collect::percentile(&values, 0.5)
        };
        let per_job = |total: f64, r: &PoseResult| {
            (!r.flow_workers.is_empty()).then(|| total / r.flow_workers.len() as f64)
        };
        let split = collected.flow_split();
        let split: Vec<usize> = split.values().copied().collect();
        let split = if split.len() > 8 {
            format!(
                "min {} max {} of {}",
                split.iter().min().unwrap_or(&0),
                split.iter().max().unwrap_or(&0),
                split.len()
            )
        } else {
            format!("{split:?}")
        };
        println!(
            "{:<10} {:>5} {:>13} {:>6} {:>9.3} {:>9.3} {:>8.2} {:>8.0} {:>8.0} {:>10.2} {:>8}  {:.0} {:.0} {:.1} {:.0}; {split}",
            backend,
            flow,
            stages,
            collected.results.len(),
            collected.frames_per_s(),
            steady,
            steady / baseline,
            asgreg::runtime::collect::percentile(&latencies, 0.5),
            asgreg::runtime::collect::percentile(&latencies, 0.9),
            collected.transport_share_percent(),
            collected.accepted(),
            median(&|r| (!r.flow_workers.is_empty()).then_some(r.times.render_ms)),
            median(&|r| per_job(r.times.flow_ms, r)),
            median(&|r| per_job(r.times.pose_ms, r)),
            median(&|r| (!r.flow_workers.is_empty()).then_some(r.times.verify_ms)),
        );
    }
    Ok(())
}

/// The simulated per-job times: the measured defaults, each overridden by its argument, scaled.
fn simulated_work(args: &BenchArgs) -> asgreg::stage::simulate::SimulatedWork {
    let defaults = asgreg::stage::simulate::SimulatedWork::default();
    asgreg::stage::simulate::SimulatedWork {
        render_view_ms: args.render_view_ms.unwrap_or(defaults.render_view_ms),
        flow_job_ms: args.flow_job_ms.unwrap_or(defaults.flow_job_ms),
        pose_job_ms: args.pose_job_ms.unwrap_or(defaults.pose_job_ms),
        verify_frame_ms: args.verify_frame_ms.unwrap_or(defaults.verify_frame_ms),
        ..defaults
    }
    .scaled(args.time_scale)
}

/// Workers a stage needs to keep up with `flow` flow workers when one of its jobs (per coarse
/// pose) takes `job_ms` of the simulated times (with a quarter to spare); 1 without simulation.
fn stage_workers(
    simulated: Option<asgreg::stage::simulate::SimulatedWork>,
    flow: u32,
    job_ms: impl Fn(&asgreg::stage::simulate::SimulatedWork) -> f64,
) -> u32 {
    simulated.map_or(1, |work| {
        let share = job_ms(&work) / work.flow_job_ms.max(1e-9);
        ((f64::from(flow) * share * 1.25).ceil() as u32).max(1)
    })
}

fn base_frame_count(config: &PipelineConfig) -> anyhow::Result<usize> {
    Ok(asgreg::io::colmap::read_images_txt(&config.source.poses)?.len())
}

/// A source of `frames` frames: the scene's photos repeated (links under OUT, each frame its
/// own name and image id), for simulated runs longer than the scene.
fn repeat_frames(config: &mut PipelineConfig, frames: usize, out: &Path) -> anyhow::Result<()> {
    let listed = asgreg::io::colmap::read_images_txt(&config.source.poses)?;
    if listed.is_empty() {
        bail!("{}: no images", config.source.poses.display());
    }
    let folder = absolute(&out.join(format!("repeated-{frames}")));
    let images = folder.join("images");
    std::fs::create_dir_all(&images)?;
    let mut repeated = Vec::with_capacity(frames);
    for index in 0..frames {
        let original = &listed[index % listed.len()];
        let extension = Path::new(&original.name)
            .extension()
            .map_or(String::new(), |e| format!(".{}", e.to_string_lossy()));
        let name = format!("frame_{index:05}{extension}");
        let link = images.join(&name);
        if std::fs::symlink_metadata(&link).is_err() {
            std::os::unix::fs::symlink(config.source.images.join(&original.name), &link)
                .with_context(|| format!("{}", link.display()))?;
        }
        repeated.push(asgreg::io::colmap::ImagePose {
            image_id: index as u32 + 1,
            name,
            ..original.clone()
        });
    }
    let poses = folder.join("images.txt");
    asgreg::io::colmap::write_images_txt(&poses, &repeated)?;
    config.source.images = images;
    config.source.poses = poses;
    Ok(())
}
