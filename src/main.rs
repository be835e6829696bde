//! The `isrf` command line. Each subcommand lives in its own file under
//! `src/cli/`; this file only declares them. Errors from the library reach
//! the user as one line through `anyhow`.

mod cli;

use clap::{Parser, Subcommand};

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

/// How the C allocator keeps memory, by what a command does most.
#[derive(Clone, Copy)]
enum Memory {
    /// Training and importing: buffers of 1 MB and more (decoded photos,
    /// grids, gradient arrays) are mapped on their own and go back to the
    /// system when freed. glibc would otherwise raise its mmap threshold
    /// after the first such free (up to 32 MB) and serve later ones from
    /// its per-thread heaps, which keep freed memory resident: training
    /// lego at 800×800 held 1.6 GB of released photos that way, in 27
    /// heaps of 64 MB.
    Release,
    /// Segmenting (editor, scripts, eval, segmentation benchmarks): every
    /// stroke allocates and frees the same working set (the cut's graph,
    /// distances, flags: tens of MB). With `Release` each stroke paid for
    /// it again in page faults (16k per lego stroke: the kernel zeroing
    /// 64 MB), also because glibc trims a heap whenever 128 kB lie free
    /// at its top. Buffers up to 8 MB come from the heaps here, which
    /// keep up to 16 MB free: lego's 320³ stroke faults 2.5k pages instead
    /// of 16k and takes 119–153 ms (median 141) instead of 145–180
    /// (median 175; six runs each, interleaved), for 40 MB more peak
    /// memory in the editor's fern walk (2.30 GB against 2.26). 16 MB / 64
    /// MB were no faster and cost 110 MB.
    Reuse,
}

impl Memory {
    fn of(command: &Command) -> Self {
        use cli::bench::What;
        match command {
            Command::Train(_) | Command::Features(_) | Command::Import(_) => Memory::Release,
            Command::Bench(b) => match b.what {
                What::Train(_) | What::Quality(_) | What::Import(_) | What::Splats(_) => Memory::Release,
                What::Render(_) | What::Segment(_) | What::Editor(_) => Memory::Reuse,
            },
            _ => Memory::Reuse,
        }
    }

    /// Sets the allocator's thresholds; at startup, before any thread exists.
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    fn apply(self) {
        let (mmap, trim) = match self {
            Memory::Release => (1 << 20, None),
            Memory::Reuse => (8 << 20, Some(16 << 20)),
        };
        // SAFETY: malloc tuning calls at startup, before any thread exists.
        unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, mmap);
            if let Some(t) = trim {
                libc::mallopt(libc::M_TRIM_THRESHOLD, t);
            }
        }
    }

    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    fn apply(self) {}
}

fn main() {
    restore_sigpipe();
    let cli = Cli::parse();
    Memory::of(&cli.command).apply();
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
