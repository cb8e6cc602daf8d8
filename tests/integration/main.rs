//! Integration tests: one binary (ripgrep's layout), one module per area. They run the `asgreg`
//! binary the way a user would and check what it prints and how it exits.

mod acks;
mod bad_environment;
mod bad_input;
mod changes_cli;
mod cli_pictures;
mod colmap_cli;
mod flow_cli;
mod honest_tests;
mod pipeline;
mod priors_cli;
mod register_cli;
mod report_page;
mod soak;
mod tls;
mod util;
