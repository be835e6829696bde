//! `isrf fuzz` and `isrf-fuzz`: arguments and the long run's report.

use super::{alloc, Options, Report, Target, TARGETS};
use crate::error::{Error, Result};
use std::path::PathBuf;
use std::time::Duration;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The reader to fuzz (see --list), or `all` for each in turn.
    #[arg(required_unless_present = "list")]
    pub target: Option<String>,
    /// Name the targets and exit.
    #[arg(long)]
    pub list: bool,
    /// Seconds to run (per target with `all`).
    #[arg(long, default_value_t = 60)]
    pub secs: u64,
    /// Seed of the mutation sequence (the same seed tries the same inputs).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Stop after this many inputs (per target).
    #[arg(long)]
    pub max_inputs: Option<u64>,
    /// Keep panicking and slow inputs here.
    #[arg(long)]
    pub save_dir: Option<PathBuf>,
    /// Folder for the files the readers open (default: a temporary folder).
    #[arg(long)]
    pub work_dir: Option<PathBuf>,
}

/// Runs the command; the last line printed is `inputs: n, errors: n, panics: n`.
pub fn run(a: Args) -> Result<()> {
    if a.list {
        for t in TARGETS {
            println!("{:<20} {}", t.name, t.about);
        }
        return Ok(());
    }
    let name = a.target.as_deref().unwrap_or_default();
    let targets: Vec<&Target> = match name {
        "all" => TARGETS.iter().collect(),
        _ => vec![super::find(name).ok_or_else(|| {
            let names: Vec<&str> = TARGETS.iter().map(|t| t.name).collect();
            Error::invalid(format!("no fuzz target '{name}' (targets: {}, all)", names.join(", ")))
        })?],
    };
    let tmp = tempfile::tempdir().map_err(|e| Error::io(std::path::Path::new("tmp"), e))?;
    let work = a.work_dir.clone().unwrap_or_else(|| tmp.path().to_path_buf());
    println!(
        "allocation cap: {}",
        match alloc::installed() {
            true => format!("single allocations over {} bytes are refused", alloc::CAP),
            false => "off in this binary (isrf-fuzz, built with --features fuzz-cap, has it)".into(),
        }
    );
    let mut total = Report::default();
    for t in targets {
        let opts = Options {
            seed: a.seed,
            max_inputs: a.max_inputs,
            duration: Some(Duration::from_secs(a.secs)),
            save_dir: a.save_dir.clone(),
            verbose: false,
        };
        let r = super::run(t, &work.join(t.name), &opts)?;
        print_target(t, &r);
        total.inputs += r.inputs;
        total.errors += r.errors;
        total.panics += r.panics;
        total.slow += r.slow;
    }
    if total.slow > 0 {
        println!("slow inputs (over {} s): {}", super::SLOW.as_secs(), total.slow);
    }
    println!("{}", total.summary());
    Ok(())
}

fn print_target(t: &Target, r: &Report) {
    let secs = r.elapsed.as_secs_f64().max(1e-9);
    println!(
        "{:<20} {:>9} inputs {:>9.0}/s  errors {:>9}  ok {:>8}  panics {:>4}  slow {:>3}  max {:.3} s",
        t.name,
        r.inputs,
        r.inputs as f64 / secs,
        r.errors,
        r.inputs - r.errors - r.panics,
        r.panics,
        r.slow,
        r.max_input_time.as_secs_f64()
    );
    for (msg, input) in &r.panic_kinds {
        println!("  panic: {msg} ({} byte input)", input.len());
    }
    for p in &r.saved {
        println!("  saved {}", p.display());
    }
}
