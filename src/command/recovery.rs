//! Crash recovery: the editor's edit log on disk, rewritten atomically after
//! every command, so that a crash or a killed process loses nothing.
//!
//! A recovery file is JSON: what the editor was started with ([`Inputs`]),
//! the composition the session was opened from (if any, with a copy of it
//! as it was when opened: saving over the original must not spoil the
//! replay), the edits since
//! opening as a script's command list (`commands`, the same serialised
//! [`Command`]s `isrf run` reads), the input files those name with their
//! size and CRC-32, and a digest of the state the commands produced.
//! Restoring opens the composition again, checks the files are unchanged,
//! replays the commands and compares the digest: equal digests mean the
//! identical state (fields, placements, every object's bitmap, edits,
//! parameters).
//!
//! Starts with equal inputs share one file (named by a hash of the inputs,
//! in [`default_dir`] unless told otherwise). Before a session first
//! overwrites a file it did not write, the old one is kept as
//! `<name>.previous.json`.

use super::session::Session;
use super::state::State;
use super::{Command, Edit};
use crate::error::{write_atomic, Error, Result};
use crate::util::Progress;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

pub const FORMAT: &str = "isrf-recovery";
pub const VERSION: u32 = 1;

/// One start-up step of the editor: open a composition, or apply a command
/// (the fields named on the command line, the `--script`'s commands).
// A start-up holds a handful: boxing the large `Command` buys nothing.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StartStep {
    Open(PathBuf),
    Apply(Command),
}

/// What the editor was started with. Equal inputs, same recovery file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Inputs {
    /// The working folder (relative paths in commands resolve against it).
    pub cwd: PathBuf,
    pub start: Vec<StartStep>,
}

impl Inputs {
    /// The recovery file of these inputs in `dir`: `<16 hex digits>.json`.
    pub fn file_in(&self, dir: &Path) -> PathBuf {
        let text = serde_json::to_string(self).expect("inputs serialise");
        dir.join(format!("{}.json", digest_bytes(text.as_bytes())))
    }

    /// The session a fresh start would reach: the last composition opened
    /// and the commands applied after it.
    fn fresh(&self) -> (Option<&Path>, Vec<&Edit>) {
        let last_open = self.start.iter().rposition(|s| matches!(s, StartStep::Open(_)));
        let opened = last_open.and_then(|i| match &self.start[i] {
            StartStep::Open(p) => Some(p.as_path()),
            StartStep::Apply(_) => None,
        });
        let after = last_open.map_or(0, |i| i + 1);
        let cmds = self.start[after..]
            .iter()
            .filter_map(|s| match s {
                StartStep::Apply(c) => c.as_edit(),
                StartStep::Open(_) => None,
            })
            .collect();
        (opened, cmds)
    }
}

/// An input file as it was when the session used it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileStamp {
    pub path: PathBuf,
    pub bytes: u64,
    pub crc32: u32,
}

impl FileStamp {
    pub fn of(path: &Path) -> Result<FileStamp> {
        let data = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        Ok(FileStamp {
            path: path.to_path_buf(),
            bytes: data.len() as u64,
            crc32: crc32fast::hash(&data),
        })
    }
}

/// The recovery file's contents.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RecoveryDoc {
    pub format: String,
    pub version: u32,
    pub inputs: Inputs,
    /// The folders the session resolved input and output paths against.
    pub base_dir: PathBuf,
    pub out_dir: PathBuf,
    /// The composition the session was opened from.
    pub opened: Option<PathBuf>,
    /// A copy of it saved when it was opened (beside the recovery file);
    /// replay opens this one, so the user may save over the original.
    #[serde(default)]
    pub opened_copy: Option<PathBuf>,
    /// The edits since opening, oldest first (undone ones excluded).
    pub commands: Vec<Edit>,
    /// The input files the composition and the commands read.
    pub files: Vec<FileStamp>,
    /// [`state_digest`] of the state the commands produced.
    pub state: String,
    /// Seconds since the Unix epoch when it was written.
    pub written: u64,
}

impl RecoveryDoc {
    pub fn load(path: &Path) -> Result<RecoveryDoc> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let doc: RecoveryDoc =
            serde_json::from_str(&text).map_err(|e| Error::bad_file(path, format!("not a recovery file: {e}")))?;
        if doc.format != FORMAT || doc.version > VERSION {
            return Err(Error::bad_file(
                path,
                format!("not a recovery file this isrf reads ({} v{})", doc.format, doc.version),
            ));
        }
        Ok(doc)
    }

    /// Whether it holds work a fresh start with its inputs would not redo:
    /// another composition, or a command the start-up does not apply (a
    /// start that died half-way, or had a failing step, holds less).
    pub fn has_edits_beyond_start(&self) -> bool {
        let (opened, start) = self.inputs.fresh();
        if self.opened.as_deref() != opened {
            return true;
        }
        let mut rest = start.into_iter();
        !self.commands.iter().all(|c| rest.any(|s| s == c))
    }

    /// Every recorded input file still has its recorded size and CRC-32.
    pub fn check_files(&self) -> Result<()> {
        for s in &self.files {
            let now = FileStamp::of(&s.path)
                .map_err(|e| Error::invalid(format!("cannot restore: an input file is gone ({e})")))?;
            crate::ensure!(
                now.bytes == s.bytes && now.crc32 == s.crc32,
                "cannot restore: '{}' has changed since the session was recorded (replaying would not give the same state)",
                s.path.display()
            );
        }
        Ok(())
    }
}

/// Where recovery files go: `$ISRF_RECOVERY_DIR`, else
/// `$XDG_STATE_HOME/isrf/recovery`, else `~/.local/state/isrf/recovery`,
/// else the temporary folder.
pub fn default_dir() -> PathBuf {
    let env = |k: &str| std::env::var_os(k).filter(|v| !v.is_empty()).map(PathBuf::from);
    if let Some(d) = env("ISRF_RECOVERY_DIR") {
        return d;
    }
    let state = env("XDG_STATE_HOME").or_else(|| env("HOME").map(|h| h.join(".local").join("state")));
    match state {
        Some(s) => s.join("isrf").join("recovery"),
        None => std::env::temp_dir().join("isrf-recovery"),
    }
}

/// Writes a session's recovery file after each command.
#[derive(Debug)]
pub struct Recorder {
    pub path: PathBuf,
    pub inputs: Inputs,
    /// The composition the session was opened from and its copy (see
    /// [`Recorder::opened`], [`Recorder::restored`]).
    pub opened: Option<PathBuf>,
    pub opened_copy: Option<PathBuf>,
    /// Stamps of files already seen (a field file is read once).
    stamps: HashMap<PathBuf, FileStamp>,
    /// Whether the file at `path` is ours (an older one was moved aside).
    owns_file: bool,
}

impl Recorder {
    pub fn new(path: PathBuf, inputs: Inputs) -> Recorder {
        Recorder {
            path,
            inputs,
            opened: None,
            opened_copy: None,
            stamps: HashMap::new(),
            owns_file: false,
        }
    }

    /// Where an older recovery file goes before the first write.
    pub fn previous_path(&self) -> PathBuf {
        Recorder::previous_of(&self.path)
    }
    /// `<name>.previous.json` beside the recovery file `path`.
    pub fn previous_of(path: &Path) -> PathBuf {
        path.with_extension("previous.json")
    }

    /// `session` was just opened from the composition `path`: a copy of
    /// it goes beside the recovery file (`<name>.opened.json` and its
    /// bitmaps; field files by absolute path), for the replay.
    pub fn opened(&mut self, path: &Path, session: &Session) -> Result<()> {
        // Without a copy, the replay opens the original.
        self.opened = Some(path.to_path_buf());
        self.opened_copy = None;
        let copy = self.path.with_extension("opened.json");
        super::composition::save(session, &copy)?;
        self.stamps.remove(&copy);
        self.opened_copy = Some(copy);
        Ok(())
    }

    /// The session was just restored from `doc`.
    pub fn restored(&mut self, doc: &RecoveryDoc) {
        self.opened = doc.opened.clone();
        self.opened_copy = doc.opened_copy.clone();
    }

    /// The recovery document of `session` as it stands.
    pub fn doc(&mut self, session: &Session) -> Result<RecoveryDoc> {
        let mut commands = session.log().to_vec();
        let mut files = Vec::new();
        let replayed = self.opened_copy.as_ref().or(self.opened.as_ref());
        for p in input_files(session, replayed.map(PathBuf::as_path), &mut commands) {
            if !self.stamps.contains_key(&p) {
                let s = FileStamp::of(&p)?;
                self.stamps.insert(p.clone(), s);
            }
            files.push(self.stamps[&p].clone());
        }
        let written = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        Ok(RecoveryDoc {
            format: FORMAT.into(),
            version: VERSION,
            inputs: self.inputs.clone(),
            base_dir: session.base_dir.clone(),
            out_dir: session.out_dir.clone(),
            opened: self.opened.clone(),
            opened_copy: self.opened_copy.clone(),
            commands,
            files,
            state: state_digest(session.state()),
            written,
        })
    }

    /// Writes the recovery file of `session` atomically (a crash during
    /// the write leaves the previous version).
    pub fn record(&mut self, session: &Session) -> Result<()> {
        let doc = self.doc(session)?;
        if !self.owns_file && self.path.exists() {
            let prev = self.previous_path();
            std::fs::rename(&self.path, &prev).map_err(|e| Error::io(&prev, e))?;
        }
        self.owns_file = true;
        let text = serde_json::to_string_pretty(&doc).map_err(|e| Error::invalid(e.to_string()))?;
        write_atomic(&self.path, text.as_bytes())
    }
}

/// The input files a session's composition and commands read, absolute,
/// without repeats (`commands` is mutable only because [`Edit::input_mut`]
/// is how an edit hands out its path; nothing is changed).
fn input_files(session: &Session, opened: Option<&Path>, commands: &mut [Edit]) -> Vec<PathBuf> {
    let mut out: Vec<PathBuf> = opened.map(|p| session.resolve(p)).into_iter().collect();
    for c in commands {
        if let Some(p) = c.input_mut().map(|p| session.resolve(p)) {
            if !out.contains(&p) {
                out.push(p);
            }
        }
    }
    out
}

/// What a restore did.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RestoreReport {
    /// Commands replayed.
    pub applied: usize,
    pub total: usize,
    /// The first command that failed on replay (the ones after it are not
    /// replayed), with the reason.
    pub failed: Option<String>,
    /// The replayed state's digest equals the recorded one.
    pub identical: bool,
}

impl RestoreReport {
    pub fn message(&self) -> String {
        match (&self.failed, self.identical) {
            (None, true) => format!(
                "restored {} edits: the state is identical to the recorded one",
                self.total
            ),
            (None, false) => format!(
                "restored {} edits, but the state differs from the recorded one (digest mismatch)",
                self.total
            ),
            (Some(e), _) => format!("restored {} of {} edits; {e}", self.applied, self.total),
        }
    }
}

/// Rebuilds the session a recovery file describes: checks the input files,
/// opens its composition (or starts empty), replays the commands. A
/// command that fails on replay stops the replay; the session holds the
/// edits before it (reported, not an error, so that they are not lost).
pub fn restore(doc: &RecoveryDoc, progress: &Progress) -> Result<(Session, RestoreReport)> {
    doc.check_files()?;
    let mut session = match doc.opened_copy.as_ref().or(doc.opened.as_ref()) {
        Some(p) => super::composition::load(p, &doc.out_dir)?,
        None => Session::new(&doc.base_dir, &doc.out_dir),
    };
    session.progress = progress.clone();
    let mut failed = None;
    let mut applied = 0;
    for (i, c) in doc.commands.iter().enumerate() {
        if let Err(e) = session.apply(c) {
            failed = Some(format!("step {} ({}) failed on replay: {e}", i + 1, c.kind()));
            break;
        }
        applied += 1;
    }
    let identical = failed.is_none() && state_digest(session.state()) == doc.state;
    let report = RestoreReport {
        applied,
        total: doc.commands.len(),
        failed,
        identical,
    };
    Ok((session, report))
}

/// 64-bit digest (16 hex digits) of bytes: two CRC-32s with different
/// initial values. Not cryptographic: it tells states and inputs apart.
fn digest_bytes(bytes: &[u8]) -> String {
    let mut d = Digest::new();
    d.bytes(bytes);
    d.hex()
}

struct Digest(crc32fast::Hasher, crc32fast::Hasher);

impl Digest {
    fn new() -> Digest {
        Digest(
            crc32fast::Hasher::new(),
            crc32fast::Hasher::new_with_initial(0x9e37_79b9),
        )
    }
    fn bytes(&mut self, b: &[u8]) {
        // Length first, so that concatenations of different parts differ.
        for h in [&mut self.0, &mut self.1] {
            h.update(&(b.len() as u64).to_le_bytes());
            h.update(b);
        }
    }
    fn floats(&mut self, v: &[f32]) {
        let b: Vec<u8> = v.iter().flat_map(|x| x.to_bits().to_le_bytes()).collect();
        self.bytes(&b);
    }
    fn json(&mut self, v: &impl Serialize) {
        self.bytes(serde_json::to_string(v).expect("serialises").as_bytes());
    }
    fn hex(self) -> String {
        format!("{:08x}{:08x}", self.0.finalize(), self.1.finalize())
    }
}

/// Digest of everything a session's state holds: each field's name, source,
/// placement and visibility; each object's name, field, bitmap, placement,
/// flags and appearance edit; the segmentation parameters and background.
/// Floats count by their bits, so "identical" means bit-identical. Field
/// grids count through their source (a file is checked by its stamp).
pub fn state_digest(st: &State) -> String {
    let mut d = Digest::new();
    // Ids are not part of it: they differ between runs; names identify.
    for f in &st.fields {
        d.bytes(f.name.as_bytes());
        d.json(&f.source);
        d.floats(&f.placement.transform.to_cols_array());
        d.bytes(&[f.placement.visible as u8]);
    }
    d.bytes(b"objects");
    for o in &st.objects {
        let p = &o.placement;
        d.bytes(o.name.as_bytes());
        d.bytes(st.field(o.field).map_or(&b""[..], |f| f.name.as_bytes()));
        d.json(&o.mask.res());
        d.bytes(&o.mask.to_bytes());
        d.floats(&p.transform.to_cols_array());
        d.bytes(&[p.removed as u8, p.visible as u8, p.duplicate as u8]);
        d.json(&p.color_edit);
    }
    d.json(&st.params);
    d.floats(&st.background);
    d.hex()
}
