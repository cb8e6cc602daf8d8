//! The `asgreg` command line: parses arguments, sets up logging and hands each subcommand to its
//! module in `cli/`. Nothing else happens here.

mod cli;

use clap::Parser;

/// Forwards to the system allocator; counts only while `asgreg fuzz` has armed it (one relaxed
/// load per allocation otherwise), so that the fuzz run finds allocation blow-ups.
#[global_allocator]
static ALLOCATOR: asgreg::fuzz::alloc_guard::GuardedAllocator =
    asgreg::fuzz::alloc_guard::GuardedAllocator;

fn main() -> std::process::ExitCode {
    // Freed buffers stay in the heap for the next frame (no page faults); results unchanged.
    asgreg::runtime::heap::keep_freed_memory();
    let args = cli::Cli::parse();
    cli::init_logging(args.verbose);
    match cli::run(args) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {}", one_line(&error));
            cli::exit_code(&error)
        }
    }
}

/// The error and its causes, each cause once: most library errors already write their
/// cause into their message (`{path}: {source}`), which `{:#}` would repeat.
fn one_line(error: &anyhow::Error) -> String {
    let mut message = error.to_string();
    for cause in error.chain().skip(1) {
        let cause = cause.to_string();
        if !message.contains(&cause) {
            message.push_str(": ");
            message.push_str(&cause);
        }
    }
    message
}
