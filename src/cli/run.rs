//! `isrf run SCRIPT --out DIR`: validate a whole edit script, then execute it
//! headless with a progress bar; nothing is written if any step fails.

use anyhow::Result;
use indicatif::{ProgressBar, ProgressStyle};
use isrf::command::script::load_script;
use isrf::command::FrameRenderer;
use isrf::command::{run_script_with, validate_script};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Script (.ron or .json): a list of commands.
    pub script: PathBuf,
    /// Output folder for renders and exports (relative outputs land here).
    #[arg(long, default_value = "out")]
    pub out: PathBuf,
    /// Only validate the script.
    #[arg(long)]
    pub check: bool,
    /// Draw `render` frames with the GPU ray marcher (window-less; needs the
    /// `editor` feature and a Vulkan adapter, lavapipe included). Depth
    /// images and masks still come from the CPU renderer.
    #[arg(long)]
    pub gpu: bool,
}

pub fn run(a: Args) -> Result<()> {
    let script = load_script(&a.script)?;
    let base = a
        .script
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .map(PathBuf::from)
        .unwrap_or_else(|| ".".into());
    validate_script(&script, &base).map_err(|e| anyhow::anyhow!("{}: {e}", a.script.display()))?;
    if a.check {
        println!("{}: {} steps, valid", a.script.display(), script.commands.len());
        return Ok(());
    }
    let bar = ProgressBar::new(script.commands.len() as u64);
    bar.set_style(ProgressStyle::with_template("{bar:40} step {pos}/{len} {elapsed} {msg}").unwrap());
    let mut gpu = gpu_frames(a.gpu)?;
    let written = run_script_with(
        &script,
        &base,
        &a.out,
        gpu.as_mut().map(|g| &mut **g as _),
        |i, _, msg| {
            bar.set_position(i as u64);
            bar.set_message(msg.to_string());
        },
    )
    .map_err(|e| anyhow::anyhow!("{}: {e}", a.script.display()))?;
    bar.finish_and_clear();
    println!(
        "{}: {} steps done, {} files written to {}",
        a.script.display(),
        script.commands.len(),
        written.len(),
        a.out.display()
    );
    Ok(())
}

#[cfg(feature = "editor")]
fn gpu_frames(on: bool) -> Result<Option<Box<dyn FrameRenderer>>> {
    use isrf::app::headless::{gpu_available, GpuFrames};
    if !on {
        return Ok(None);
    }
    anyhow::ensure!(
        gpu_available(),
        "--gpu: no GPU adapter (on a machine without a GPU install mesa-vulkan-drivers for lavapipe)"
    );
    Ok(Some(Box::new(GpuFrames::default())))
}

#[cfg(not(feature = "editor"))]
fn gpu_frames(on: bool) -> Result<Option<Box<dyn FrameRenderer>>> {
    anyhow::ensure!(
        !on,
        "--gpu needs the GPU ray marcher: rebuild with `cargo build --features editor`"
    );
    Ok(None)
}
