//! Scripts on disk: RON or JSON files holding a list of [`Command`]s,
//! either a bare list or `{ "commands": [...] }` / `(commands: [...])`.
//! Parsing reports an unknown command or a bad parameter with its step
//! number; running a script is `command::run`.

use super::Command;
use crate::error::{write_atomic, Error, Result};
use serde::de::{self, Deserializer, SeqAccess, Visitor};
use serde::{Deserialize, Serialize};
use std::path::Path;

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Script {
    pub commands: Vec<Command>,
}

/// A list of commands whose element errors carry their step number.
struct Steps(Vec<Command>);

thread_local! {
    /// The step whose parse failed last on this thread: the parser's error
    /// type (serde_json's, ron's) cannot carry it, so [`parse_script`]
    /// reads it here to return [`Error::ScriptSyntax`].
    static FAILED_STEP: std::cell::Cell<Option<usize>> = const { std::cell::Cell::new(None) };
}

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
                        Err(e) => {
                            let step = v.len() + 1;
                            FAILED_STEP.with(|s| s.set(Some(step)));
                            return Err(de::Error::custom(format!("step {step}: {e}")));
                        }
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
        match crate::util::extension(path).as_str() {
            "ron" => Ok(Format::Ron),
            "json" => Ok(Format::Json),
            _ => Err(Error::invalid(format!(
                "{}: scripts must end in .ron or .json",
                path.display()
            ))),
        }
    }
}

/// Parses a script; errors name the step (1-based) and what is wrong
/// ([`Error::ScriptSyntax`] when a step does not parse).
pub fn parse_script(text: &str, format: Format) -> Result<Script> {
    FAILED_STEP.with(|s| s.set(None));
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
    .map_err(|message| match FAILED_STEP.with(|s| s.take()) {
        Some(step) => Error::ScriptSyntax { step, message },
        None => Error::Invalid(message),
    })?;
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
    parse_script(&text, Format::of(path)?).map_err(|e| match e {
        // Still matchable by step, with the file named as for other errors.
        Error::ScriptSyntax { step, message } => Error::ScriptSyntax {
            step,
            message: format!("{}: {message}", path.display()),
        },
        e => Error::bad_file(path, e.to_string()),
    })
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
