//! `asgreg fuzz`: the full form of the fuzz run (issue #15 item 4), a dev command. Runs every
//! target (or those named) for the given number of mutated inputs and prints one Markdown row per
//! target; exits non-zero when anything was found. Findings are saved under `<work-dir>/findings`.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context as _;
use clap::Args;

use asgreg::fuzz::{self, FindingKind, FuzzOptions};

#[derive(Args, Debug)]
pub struct FuzzArgs {
    /// Targets to run (`--list` names them); all when none is given.
    #[arg(long = "target")]
    pub targets: Vec<String>,
    /// Mutated inputs per target.
    #[arg(long, default_value_t = 10_000)]
    pub inputs: usize,
    /// The run's seed (with the target and the input's index it fixes every input).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// First input index: `--from I --inputs 1` reruns input I alone.
    #[arg(long, default_value_t = 0)]
    pub from: usize,
    /// An input that takes longer than this is a hang.
    #[arg(long, default_value_t = 1000)]
    pub time_limit_ms: u64,
    /// Where inputs and findings are written (default: a new folder in /dev/shm, or the temporary folder).
    #[arg(long)]
    pub work_dir: Option<PathBuf>,
    /// The repository root (the seeds are its tests/data and deploy files).
    #[arg(long, default_value = ".")]
    pub repo: PathBuf,
    /// Print the targets and their seed counts, and stop.
    #[arg(long)]
    pub list: bool,
    /// Minimise each panicking input found (for a regression test) and save it as `*.min`.
    #[arg(long)]
    pub minimise: bool,
}

pub fn run(args: &FuzzArgs) -> anyhow::Result<()> {
    let work_dir = match &args.work_dir {
        Some(dir) => dir.clone(),
        None => fuzz::default_work_root().join(format!("asgreg-fuzz-{}", std::process::id())),
    };
    let targets = fuzz::all_targets(&args.repo, &work_dir.join("seeds"))?;
    if args.list {
        for target in &targets {
            println!("{} ({} seeds)", target.name, target.seeds.len());
        }
        return Ok(());
    }
    for name in &args.targets {
        anyhow::ensure!(
            targets.iter().any(|target| &target.name == name),
            "no fuzz target '{name}'; `asgreg fuzz --list` names them"
        );
    }
    let mut options = FuzzOptions::new(args.inputs, args.seed, work_dir.clone());
    options.first_input = args.from;
    options.time_limit = Duration::from_millis(args.time_limit_ms);
    eprintln!(
        "fuzz: {} inputs per target, seed {}, inputs and findings in {}",
        args.inputs,
        args.seed,
        work_dir.display()
    );
    println!("{}", fuzz::MARKDOWN_HEADER);
    let mut total_findings = 0;
    for target in targets
        .iter()
        .filter(|target| args.targets.is_empty() || args.targets.contains(&target.name))
    {
        let report = fuzz::run_target(target, &options)
            .with_context(|| format!("fuzz target {}", target.name))?;
        println!("{}", fuzz::markdown_row(&report));
        total_findings += report.total_findings();
        for finding in &report.findings {
            eprintln!(
                "  {} input {}: {:?}: {}{}",
                target.name,
                finding
                    .input_index
                    .map_or_else(|| "(seed)".to_string(), |index| index.to_string()),
                finding.kind,
                finding.detail,
                finding
                    .saved_to
                    .as_ref()
                    .map(|path| format!(" (saved as {})", path.display()))
                    .unwrap_or_default()
            );
            if args.minimise && finding.kind == FindingKind::Panic {
                let scratch = work_dir.join("minimise").join(target.file_name);
                std::fs::create_dir_all(work_dir.join("minimise"))?;
                let minimised = fuzz::minimise_panic(target, &scratch, &finding.input, 5000);
                if let Some(saved) = &finding.saved_to {
                    let path = saved.with_extension("min");
                    std::fs::write(&path, &minimised)
                        .with_context(|| format!("writing {}", path.display()))?;
                    eprintln!(
                        "    minimised to {} bytes: {}",
                        minimised.len(),
                        path.display()
                    );
                }
            }
        }
        if std::env::var_os("ASGREG_FUZZ_SAMPLES").is_some() {
            for sample in &report.sample_errors {
                eprintln!("  sample error: {sample}");
            }
        }
    }
    anyhow::ensure!(
        total_findings == 0,
        "fuzz: {total_findings} findings (saved under {})",
        work_dir.join("findings").display()
    );
    Ok(())
}
