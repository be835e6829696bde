//! `isrf run`: a parsed script is first checked as a dry run (the session's
//! own rules on a [`Session::dry`]: names defined before use, files
//! present, parameters valid), then executed into a staging folder inside
//! the output folder; the results move into place only when every step has
//! succeeded, so a failing script leaves the output folder untouched.

use super::output::{self, FrameRenderer};
use super::script::Script;
use super::{Command, Session};
use crate::error::{Error, Result};
use std::path::{Path, PathBuf};

/// Checks a whole script before anything runs, by applying it to a dry
/// session: the same rules as running it, without the work. `base`
/// resolves relative input paths. Errors are [`Error::Step`]s
/// ("step N (kind): ...").
pub fn validate_script(script: &Script, base: &Path) -> Result<()> {
    let mut session = Session::dry(base);
    for (i, c) in script.commands.iter().enumerate() {
        let r = match c {
            Command::Edit(e) => session.apply(e).map(drop),
            Command::Output(o) => output::check(&session, o),
        };
        r.map_err(|e| e.at_step(i + 1, c.kind()))?;
    }
    if script.commands.is_empty() {
        return Err(Error::invalid("the script has no commands"));
    }
    Ok(())
}

/// Runs a validated script headless into `out`. Outputs are staged and moved
/// into `out` only if every step succeeds. `progress` is called after each
/// step with (step, total, message).
pub fn run_script(
    script: &Script,
    base: &Path,
    out: &Path,
    progress: impl FnMut(usize, usize, &str),
) -> Result<Vec<PathBuf>> {
    run_script_with(script, base, out, None, progress)
}

/// [`run_script`] with `Render` frames drawn by `frames` (see
/// [`FrameRenderer`]).
pub fn run_script_with(
    script: &Script,
    base: &Path,
    out: &Path,
    mut frames: Option<&mut dyn FrameRenderer>,
    mut progress: impl FnMut(usize, usize, &str),
) -> Result<Vec<PathBuf>> {
    validate_script(script, base)?;
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let stage = tempfile::Builder::new()
        .prefix(".isrf-run-")
        .tempdir_in(out)
        .map_err(|e| Error::io(out, e))?;
    let mut session = Session::new(base, stage.path());
    let n = script.commands.len();
    for (i, c) in script.commands.iter().enumerate() {
        let r = output::perform(&mut session, c, frames.as_mut().map(|f| &mut **f as _))
            .map_err(|e| e.at_step(i + 1, c.kind()))?;
        progress(i + 1, n, &r.message);
    }
    // Move every staged entry into place (replacing what was there).
    let mut written = vec![];
    for entry in walk(stage.path()) {
        let rel = entry.strip_prefix(stage.path()).expect("inside the stage");
        let dest = out.join(rel);
        if let Some(parent) = dest.parent() {
            std::fs::create_dir_all(parent).map_err(|e| Error::io(parent, e))?;
        }
        std::fs::rename(&entry, &dest).map_err(|e| Error::io(&dest, e))?;
        written.push(dest);
    }
    Ok(written)
}

/// Files under `dir`, sorted.
fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut out = vec![];
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}
