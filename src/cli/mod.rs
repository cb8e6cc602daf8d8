//! Subcommands of the `asgreg` binary. Each file parses its own arguments and calls the library;
//! errors are `anyhow` here (and only here) so they can carry the file and what to do.

mod bench_mesh;
mod calibrate;
mod changes;
mod compare;
mod demo;
mod eval;
mod eval_changes;
mod flow;
mod fuzz;
mod inputs;
mod overlay;
mod pipeline;
mod priors;
mod register;
mod render;
mod soak;
mod synth;

use clap::{Parser, Subcommand};

#[derive(Parser, Debug)]
#[command(
    name = "asgreg",
    version,
    about = "Register aerial photographs to an untextured 3D mesh (Average Shading Gradients + SIFT flow)"
)]
pub struct Cli {
    /// More log output (-v: debug, -vv: trace). RUST_LOG overrides.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    pub verbose: u8,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// The main job on an embedded default: make a synthetic scene and show its renderings.
    Demo(demo::DemoArgs),
    /// Refine initial poses of a folder of photos against a mesh (the main batch job).
    Register(register::RegisterArgs),
    /// Evaluate registration on a scene folder the paper's way (tables, JSON, plot).
    Eval(eval::EvalArgs),
    /// Compare two `eval` runs of the same scene frame by frame (paired figures, frames that
    /// changed).
    Compare(compare::CompareArgs),
    /// Fit the confidence model and its accept threshold on `eval` results with ground truth.
    Calibrate(calibrate::CalibrateArgs),
    /// Change detection on registered photos: masks, overlays, changes.geojson, report.json.
    Changes(changes::ChangesArgs),
    /// Dense SIFT flow between two images, written as Middlebury .flo.
    Flow(flow::FlowArgs),
    /// Write an honest synthetic test scene (photos, degraded model, depth, ground truth, initial poses).
    Synth(synth::SynthArgs),
    /// Render the mesh under an image's pose: ASG gradient image, normals or depth, as PNG.
    Render(render::RenderArgs),
    /// Run the streaming pipeline, all stages as threads of this process (no config: a
    /// synthetic scene, the embedded default).
    Run(pipeline::RunArgs),
    /// Run one stage worker of the pipeline as its own process.
    Stage(pipeline::StageArgs),
    /// Start and supervise every stage as its own process (the ground-station deployment).
    Launch(pipeline::LaunchArgs),
    /// Run a zenoh router (the ground station's; `launch` starts one when configured).
    ZenohRouter(pipeline::RouterArgs),
    /// Print PoseResults as they arrive.
    Subscribe(pipeline::SubscribeArgs),
    /// Benchmarks that run whole processes (`bench pipeline`: frames/s per flow-worker count).
    Bench(pipeline::BenchArgs),
    /// Draw the mesh over a photo under its pose (normal colours and edges), as PNG.
    Overlay(overlay::OverlayArgs),
    /// Initial poses from the photos themselves (GPS and DJI gimbal angles in EXIF/XMP, or an
    /// exiftool CSV) in the mesh's local UTM frame, as a COLMAP model with the frame's offset.
    Priors(priors::PriorsArgs),
    /// Dev command: fuzz every reader of user files and every message decoder with mutated
    /// inputs (panics, hangs, allocation blow-ups); one Markdown row per target.
    Fuzz(fuzz::FuzzArgs),
    /// Dev command: stream many small synthetic frames through `launch` while a chaos loop
    /// SIGKILLs a random stage, flow worker or the router every few seconds; checks exactly one
    /// result per frame, memory and shared-memory/socket counts; prints the figures.
    Soak(soak::SoakArgs),
}

pub fn init_logging(verbose: u8) {
    let default_level = match verbose {
        0 => "info",
        1 => "debug",
        _ => "trace",
    };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default_level));
    // Colour codes only on a terminal: a log redirected to a file or a journal stays plain text.
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_writer(std::io::stderr)
        .with_target(false)
        .init();
}

/// The process's exit status for an error: [`asgreg::runtime::EXIT_NEEDS_OPERATOR`] when a
/// restart cannot mend it (a stage's damaged results journal: `launch` then does not restart
/// the stage), 1 otherwise.
pub fn exit_code(error: &anyhow::Error) -> std::process::ExitCode {
    let needs_operator = error.chain().any(|cause| {
        cause
            .downcast_ref::<asgreg::runtime::nodes::NodeError>()
            .is_some_and(|error| error.needs_operator())
            || cause
                .downcast_ref::<asgreg::runtime::journal::JournalError>()
                .is_some_and(|error| error.needs_operator())
    });
    if needs_operator {
        std::process::ExitCode::from(asgreg::runtime::EXIT_NEEDS_OPERATOR)
    } else {
        std::process::ExitCode::FAILURE
    }
}

pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Run(args) => pipeline::run(&args),
        Command::Stage(args) => pipeline::stage(&args),
        Command::Launch(args) => pipeline::launch_command(&args, cli.verbose),
        Command::Subscribe(args) => pipeline::subscribe(&args),
        Command::ZenohRouter(args) => pipeline::router(&args),
        Command::Bench(args) => pipeline::bench(&args),
        Command::Demo(args) => demo::run(&args),
        Command::Register(args) => register::run(&args),
        Command::Eval(args) => eval::run(&args),
        Command::Calibrate(args) => calibrate::run(&args),
        Command::Compare(args) => compare::run(&args),
        Command::Changes(args) => changes::run(&args),
        Command::Flow(args) => flow::run(&args),
        Command::Synth(args) => synth::run(&args),
        Command::Render(args) => render::run(&args),
        Command::Overlay(args) => overlay::run(&args),
        Command::Priors(args) => priors::run(&args),
        Command::Fuzz(args) => fuzz::run(&args),
        Command::Soak(args) => soak::run(&args),
    }
}
