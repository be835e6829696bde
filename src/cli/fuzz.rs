//! `isrf fuzz TARGET --secs N`: the long fuzz run of one reader (see
//! `isrf::fuzz`); `isrf fuzz --list` names the targets.

pub use isrf::fuzz::cli::Args;

pub fn run(a: Args) -> anyhow::Result<()> {
    Ok(isrf::fuzz::cli::run(a)?)
}
