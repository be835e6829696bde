//! Scripts: RON or JSON files holding a list of [`Command`]s, either a bare
//! list or `{ "commands": [...] }` / `(commands: [...])`.
//!
//! `isrf run` first parses the whole script (an unknown command or a bad
//! parameter is reported with its step number), then checks it symbolically
//! (every field and object it names exists at that step, files exist,
//! parameters are valid), then executes it into a staging folder inside the
//! output folder and moves the results into place only when every step has
//! succeeded, so a failing script leaves the output folder untouched.

use super::{CameraSource, Command, Export, FieldSource, Session, StrokeSource};
use crate::error::{write_atomic, Error, Result};
use crate::render::ColorEdit;
use serde::de::{self, Deserializer, SeqAccess, Visitor};
use serde::{Deserialize, Serialize};
use std::collections::HashSet;
use std::path::{Path, PathBuf};

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Script {
    pub commands: Vec<Command>,
}

/// A list of commands whose element errors carry their step number.
struct Steps(Vec<Command>);

impl<'de> Deserialize<'de> for Steps {
    fn deserialize<D: Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = Steps;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a list of commands")
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> std::result::Result<Steps, A::Error> {
                let mut v = vec![];
                loop {
                    match seq.next_element::<Command>() {
                        Ok(Some(c)) => v.push(c),
                        Ok(None) => return Ok(Steps(v)),
                        Err(e) => return Err(de::Error::custom(format!("step {}: {e}", v.len() + 1))),
                    }
                }
            }
        }
        d.deserialize_seq(V)
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    Ron,
    Json,
}

impl Format {
    pub fn of(path: &Path) -> Result<Format> {
        match path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .as_deref()
        {
            Some("ron") => Ok(Format::Ron),
            Some("json") => Ok(Format::Json),
            _ => Err(Error::invalid(format!(
                "{}: scripts must end in .ron or .json",
                path.display()
            ))),
        }
    }
}

/// Parses a script; errors name the step (1-based) and what is wrong.
pub fn parse_script(text: &str, format: Format) -> Result<Script> {
    // Try the wrapped form only if the text looks like it, so that errors
    // inside a bare list are reported as they are.
    let ron_text = with_implicit_some(text);
    let body = text
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with("//") && !l.starts_with("#!"))
        .unwrap_or("");
    let wrapped = body.starts_with('{') || body.starts_with('(');
    let steps = match (format, wrapped) {
        (Format::Json, true) => serde_json::from_str::<WrappedJson>(text)
            .map(|w| w.commands)
            .map_err(|e| e.to_string()),
        (Format::Json, false) => serde_json::from_str::<Steps>(text).map_err(|e| e.to_string()),
        (Format::Ron, true) => ron_options()
            .from_str::<WrappedJson>(&ron_text)
            .map(|w| w.commands)
            .map_err(|e| e.to_string()),
        (Format::Ron, false) => ron_options().from_str::<Steps>(&ron_text).map_err(|e| e.to_string()),
    }
    .map_err(Error::invalid)?;
    Ok(Script { commands: steps.0 })
}

/// RON with `implicit_some`, so optional parameters are written plainly
/// (`k: 5`, not `k: Some(5)`).
fn ron_options() -> ron::Options {
    ron::Options::default().with_default_extension(ron::extensions::Extensions::IMPLICIT_SOME)
}

/// Enables `implicit_some` in the text itself (the parser option alone does
/// not reach nested enum variants); on the first line, so that line numbers
/// in error messages stay right.
fn with_implicit_some(text: &str) -> std::borrow::Cow<'_, str> {
    if text.contains("implicit_some") {
        text.into()
    } else {
        format!("#![enable(implicit_some)] {text}").into()
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct WrappedJson {
    commands: Steps,
}

pub fn load_script(path: &Path) -> Result<Script> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    parse_script(&text, Format::of(path)?).map_err(|e| Error::bad_file(path, e.to_string()))
}

/// Writes a script (format from the extension), atomically.
pub fn save_script(script: &Script, path: &Path) -> Result<()> {
    let text = match Format::of(path)? {
        Format::Json => serde_json::to_string_pretty(script).map_err(|e| Error::invalid(e.to_string()))?,
        Format::Ron => ron::ser::to_string_pretty(script, ron::ser::PrettyConfig::default())
            .map_err(|e| Error::invalid(e.to_string()))?,
    };
    write_atomic(path, text.as_bytes())
}

/// Symbolic check of a whole script before anything runs: names defined
/// before use, input files present, parameters valid. `base` resolves
/// relative input paths. Errors read "step N (kind): ...".
pub fn validate_script(script: &Script, base: &Path) -> Result<()> {
    let mut fields: HashSet<String> = HashSet::new();
    let mut demo_fields: HashSet<String> = HashSet::new();
    let mut objects: HashSet<String> = HashSet::new();
    let mut params = crate::segment::SegmentParams::default();
    for (i, c) in script.commands.iter().enumerate() {
        check_step(c, base, &mut fields, &mut demo_fields, &mut objects, &mut params)
            .map_err(|e| Error::invalid(format!("step {} ({}): {e}", i + 1, c.kind())))?;
    }
    if script.commands.is_empty() {
        return Err(Error::invalid("the script has no commands"));
    }
    Ok(())
}

fn exists(base: &Path, p: &Path) -> Result<()> {
    let full = if p.is_absolute() { p.to_path_buf() } else { base.join(p) };
    crate::ensure!(full.exists(), "file '{}' does not exist", full.display());
    Ok(())
}

fn check_step(
    c: &Command,
    base: &Path,
    fields: &mut HashSet<String>,
    demo_fields: &mut HashSet<String>,
    objects: &mut HashSet<String>,
    params: &mut crate::segment::SegmentParams,
) -> Result<()> {
    let need = |set: &HashSet<String>, kind: &str, n: &str| -> Result<()> {
        crate::ensure!(set.contains(n), "no {kind} named '{n}' at this step");
        Ok(())
    };
    let fresh = |f: &HashSet<String>, o: &HashSet<String>, n: &str| -> Result<()> {
        crate::ensure!(!n.trim().is_empty(), "names must not be empty");
        crate::ensure!(!f.contains(n) && !o.contains(n), "the name '{n}' is already used");
        Ok(())
    };
    let check_cameras = |cams: &CameraSource, demo_fields: &HashSet<String>| -> Result<()> {
        cams.validate()?;
        match cams {
            CameraSource::File(p) => exists(base, p),
            CameraSource::Demo { field, .. } => {
                crate::ensure!(demo_fields.contains(field), "'{field}' is not a loaded demo field");
                Ok(())
            }
            CameraSource::Orbit { .. } => Ok(()),
        }
    };
    match c {
        Command::LoadField {
            name,
            source,
            transform,
        } => {
            fresh(fields, objects, name)?;
            match source {
                FieldSource::File(p) => {
                    exists(base, p)?;
                    crate::field::io::read_header(&if p.is_absolute() { p.clone() } else { base.join(p) })?;
                }
                FieldSource::Demo { scene, res, .. } => {
                    crate::ensure!(
                        crate::demo::names().contains(&scene.as_str()),
                        "unknown demo scene '{scene}' (known: {})",
                        crate::demo::names().join(", ")
                    );
                    crate::ensure!(
                        (16..=512).contains(res),
                        "demo resolution {res} is out of range (16..=512)"
                    );
                    demo_fields.insert(name.clone());
                }
            }
            if let Some(t) = transform {
                t.validate()?;
            }
            fields.insert(name.clone());
        }
        Command::TransformField { field, transform } => {
            need(fields, "field", field)?;
            transform.validate()?;
        }
        Command::SetParams { .. } => *params = c.merged_params(params)?,
        Command::Stroke {
            object, field, source, ..
        } => {
            if let Some(f) = field {
                need(fields, "field", f)?;
            }
            crate::ensure!(!fields.is_empty(), "no field is loaded to stroke on");
            if !objects.contains(object) {
                fresh(fields, objects, object)?;
            }
            match source {
                StrokeSource::Inline(doc) => {
                    doc.to_stroke()?;
                }
                StrokeSource::File(p) => {
                    let full = if p.is_absolute() { p.clone() } else { base.join(p) };
                    crate::segment::stroke::check_strokes(&full)?;
                }
                StrokeSource::Scribble { path, camera } => {
                    exists(base, path)?;
                    camera.to_camera()?;
                }
                StrokeSource::Demo { .. } => {
                    let f = field.clone().unwrap_or_default();
                    crate::ensure!(
                        field.is_none() || demo_fields.contains(&f),
                        "field '{f}' is not a demo scene"
                    );
                    crate::ensure!(
                        !demo_fields.is_empty(),
                        "no demo field is loaded: built-in strokes need one"
                    );
                }
            }
            objects.insert(object.clone());
        }
        Command::Grow { object, .. } | Command::Remove { object } | Command::Restore { object } => {
            need(objects, "object", object)?
        }
        Command::SetVisible { target, .. } => {
            crate::ensure!(
                fields.contains(target) || objects.contains(target),
                "no field or object named '{target}' at this step"
            )
        }
        Command::Transform { object, transform } => {
            need(objects, "object", object)?;
            transform.validate()?;
        }
        Command::Duplicate {
            object,
            name,
            transform,
        } => {
            need(objects, "object", object)?;
            fresh(fields, objects, name)?;
            if let Some(t) = transform {
                t.validate()?;
            }
            objects.insert(name.clone());
        }
        Command::Appearance { object, edit } => {
            need(objects, "object", object)?;
            ColorEdit::validate(edit)?;
        }
        Command::Rename { target, name } => {
            fresh(fields, objects, name)?;
            if fields.remove(target) {
                fields.insert(name.clone());
                if demo_fields.remove(target) {
                    demo_fields.insert(name.clone());
                }
            } else if objects.remove(target) {
                objects.insert(name.clone());
            } else {
                return Err(Error::invalid(format!(
                    "no field or object named '{target}' at this step"
                )));
            }
        }
        Command::Delete { target } => {
            crate::ensure!(
                fields.remove(target) || objects.remove(target),
                "no field or object named '{target}' at this step"
            );
        }
        Command::Render { cameras, downscale, .. } => {
            crate::ensure!(*downscale >= 1, "downscale must be at least 1");
            check_cameras(cameras, demo_fields)?;
        }
        Command::Export(e) => match e {
            Export::Masks {
                object,
                cameras,
                downscale,
                ..
            } => {
                need(objects, "object", object)?;
                crate::ensure!(*downscale >= 1, "downscale must be at least 1");
                check_cameras(cameras, demo_fields)?;
            }
            Export::ObjectField { object, .. } | Export::Bitmap { object, .. } => need(objects, "object", object)?,
            Export::Mesh { target, out, iso } => {
                crate::ensure!(
                    fields.contains(target) || objects.contains(target),
                    "no field or object named '{target}' at this step"
                );
                let ext = out
                    .extension()
                    .and_then(|e| e.to_str())
                    .unwrap_or("")
                    .to_ascii_lowercase();
                crate::ensure!(
                    ext == "ply" || ext == "glb",
                    "mesh output '{}' must end in .ply or .glb",
                    out.display()
                );
                crate::ensure!(
                    iso.is_none_or(|v| v.is_finite() && v > 0.0),
                    "iso level must be positive"
                );
            }
            Export::Composition { .. } => {}
            Export::Script { out } => {
                Format::of(out)?;
            }
        },
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
/// [`super::session::FrameRenderer`]).
pub fn run_script_with(
    script: &Script,
    base: &Path,
    out: &Path,
    mut frames: Option<&mut dyn super::session::FrameRenderer>,
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
        let r = session
            .apply_with(c, frames.as_mut().map(|f| &mut **f as _))
            .map_err(|e| Error::invalid(format!("step {} ({}): {e}", i + 1, c.kind())))?;
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
