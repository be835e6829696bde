//! The `isrf` command line. Each subcommand lives in its own file under
//! `src/cli/`; this file only declares them. Errors from the library reach
//! the user as one line through `anyhow`.

mod cli;

use clap::{Parser, Subcommand};
use isrf::heap::Heap;

#[derive(Parser)]
#[command(
    name = "isrf",
    version,
    about = "Segment, edit and composite radiance fields with brush strokes"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Print a human summary of a field file (sizes, kinds, occupancy, memory).
    Info(cli::info::Args),
    /// Build the procedural demo scenes (field, ground-truth labels, cameras, strokes).
    Demo(cli::demo::Args),
    /// Render field files from a camera set to PNGs (colour, depth, features, object masks).
    Render(cli::render::Args),
    /// Segment an object from brush strokes into a 3D bitmap.
    Segment(cli::segment::Args),
    /// Fit a field to a capture (Blender, LLFF, nerfstudio, COLMAP), optionally distilling teacher features.
    Train(cli::train::Args),
    /// Score segmentation against ground truth (demo scenes or NVOS layout), as JSON.
    Eval(cli::eval::Args),
    /// Run an edit script (RON or JSON list of commands) headless.
    Run(cli::run::Args),
    /// Measured figures printed as tables (render: rays/s; segment: stroke-to-mask stages).
    Bench(cli::bench::Args),
    /// The interactive editor (bevy; needs the `editor` cargo feature).
    Edit(cli::edit::Args),
    /// Mutation-fuzz one of the file readers (`--list` names them); ends with `inputs: n, errors: n, panics: n`.
    Fuzz(cli::fuzz::Args),
    /// Import a 3D Gaussian splat .ply (INRIA layout) as a field.
    Import(cli::import::Args),
    /// Add teacher features to a field, its geometry frozen (from a capture or rendered orbit views).
    Features(cli::features::Args),
    /// Write a field, an object or its complement as a 3D Gaussian splat .ply.
    ExportSplats(cli::splats::Args),
}

/// `isrf info F | head` must end quietly when its reader goes away, as Unix
/// tools do: Rust ignores SIGPIPE, so a print to a closed pipe fails and
/// `println!` panics; the default action ends the process instead.
#[cfg(unix)]
fn restore_sigpipe() {
    // SAFETY: setting a signal's disposition to its default at startup,
    // before any thread exists.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

#[cfg(not(unix))]
fn restore_sigpipe() {}

/// The allocator policy for what `command` does most ([`Heap`]).
fn heap_of(command: &Command) -> Heap {
    use cli::bench::What;
    match command {
        Command::Train(_) | Command::Features(_) | Command::Import(_) => Heap::Release,
        Command::Bench(b) => match b.what {
            What::Train(_) | What::Quality(_) | What::Import(_) | What::Splats(_) => Heap::Release,
            What::Render(_) | What::Segment(_) | What::Editor(_) => Heap::Reuse,
        },
        _ => Heap::Reuse,
    }
}

fn main() {
    restore_sigpipe();
    let cli = Cli::parse();
    isrf::heap::set(heap_of(&cli.command));
    let result = match cli.command {
        Command::Info(a) => cli::info::run(a),
        Command::Demo(a) => cli::demo::run(a),
        Command::Render(a) => cli::render::run(a),
        Command::Segment(a) => cli::segment::run(a),
        Command::Train(a) => cli::train::run(a),
        Command::Eval(a) => cli::eval::run(a),
        Command::Run(a) => cli::run::run(a),
        Command::Bench(a) => cli::bench::run(a),
        Command::Edit(a) => cli::edit::run(a),
        Command::Fuzz(a) => cli::fuzz::run(a),
        Command::Import(a) => cli::import::run(a),
        Command::Features(a) => cli::features::run(a),
        Command::ExportSplats(a) => cli::splats::run(a),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
