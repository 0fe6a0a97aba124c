//! The `posediff` command: `posediff estimate <folder or images> [--weights <ckpt>] --out <dir>`;
//! one module per command in `cli/`.
// The commands print their summaries on stdout.
#![allow(clippy::print_stdout)]

mod cli;

use std::process::ExitCode;

use clap::Parser;

#[derive(Parser)]
#[command(
    name = "posediff",
    version,
    about = "Camera poses from a handful of photos (PoseDiffusion in Rust)"
)]
struct Cli {
    #[command(subcommand)]
    command: cli::Command,
}

/// mimalloc keeps freed pages for reuse: the networks allocate and free tensors of tens of
/// megabytes per layer, which glibc's allocator hands back to the kernel each time (measured:
/// 2.1 million page faults and a third of the run in the kernel for one LightGlue pair).
/// Built with `no_thp`: mimalloc otherwise advises transparent huge pages on its regions, and
/// every freed and retouched 2 MiB page is cleared anew by the kernel (47 % of ALIKED's
/// extraction in a profile; without the advice the kernel's share of 6 images and 15 pairs
/// halves, 2.1 → 1.0 s, and the extraction is 10 % faster).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> ExitCode {
    // Logs go to stderr; `RUST_LOG=info` shows the stages, warnings are on by default.
    env_logger::Builder::from_env(env_logger::Env::default().default_filter_or("warn")).init();
    match Cli::parse().command.run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
