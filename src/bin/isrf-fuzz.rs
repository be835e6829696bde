//! `isrf-fuzz`: `isrf fuzz` with the 1 GiB single-allocation cap of
//! [`isrf::fuzz::alloc::CapAlloc`] (which the `isrf` binary does not carry).
//! Built only with `--features fuzz-cap`.

use clap::Parser;

#[global_allocator]
static ALLOC: isrf::fuzz::alloc::CapAlloc = isrf::fuzz::alloc::CapAlloc;

#[derive(Parser)]
#[command(name = "isrf-fuzz", about = "Fuzz isrf's readers (with a 1 GiB allocation cap)")]
struct Cli {
    #[command(flatten)]
    args: isrf::fuzz::cli::Args,
}

fn main() {
    if let Err(e) = isrf::fuzz::cli::run(Cli::parse().args) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
