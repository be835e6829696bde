//! Library error type. Every user-facing failure (bad file, bad shape, bad
//! parameter) becomes one of these with a message naming the problem; the
//! binary turns them into one-line reasons with `anyhow` at its edge.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum Error {
    // The I/O error is part of the message, not a `#[source]` (thiserror
    // would make a field named `source` one): the CLI prints the chain,
    // which would repeat it.
    #[error("{path}: {error}")]
    Io { path: PathBuf, error: std::io::Error },
    /// A file that exists but whose contents are not what we expect.
    #[error("{path}: {reason}")]
    BadFile { path: PathBuf, reason: String },
    /// Bad in-memory input: wrong shapes, NaN, bad parameters.
    #[error("{0}")]
    Invalid(String),
    /// A step of a script (1-based) that is invalid or failed, with why.
    #[error("step {step} ({kind}): {error}")]
    Step {
        step: usize,
        kind: &'static str,
        error: Box<Error>,
    },
    /// A script step (1-based) that does not parse: an unknown command, a
    /// misspelt or missing parameter, a value of the wrong type. `message`
    /// is the parser's, naming the step and where it is in the text.
    #[error("{message}")]
    ScriptSyntax { step: usize, message: String },
    /// A field or object name that names nothing; `known` lists what does.
    #[error("no {kind} named '{name}' (there are: {})", list_or_none(.known))]
    UnknownName {
        kind: &'static str,
        name: String,
        known: Vec<String>,
    },
    /// A number outside what is accepted (resolutions, counts, image sizes).
    #[error("{0}")]
    OutOfRange(String),
    /// More than the GPU or the machine allows (texture sizes, buffer sizes).
    #[error("{0}")]
    DeviceLimit(String),
}

fn list_or_none(names: &[String]) -> String {
    if names.is_empty() {
        "none".into()
    } else {
        names.join(", ")
    }
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            error: source,
        }
    }
    pub fn bad_file(path: impl Into<PathBuf>, reason: impl Into<String>) -> Self {
        Error::BadFile {
            path: path.into(),
            reason: reason.into(),
        }
    }
    pub fn invalid(reason: impl Into<String>) -> Self {
        Error::Invalid(reason.into())
    }
    pub fn out_of_range(reason: impl Into<String>) -> Self {
        Error::OutOfRange(reason.into())
    }
    pub fn device_limit(reason: impl Into<String>) -> Self {
        Error::DeviceLimit(reason.into())
    }
    pub fn unknown_name(kind: &'static str, name: &str, known: &[&str]) -> Self {
        Error::UnknownName {
            kind,
            name: name.into(),
            known: known.iter().map(|n| n.to_string()).collect(),
        }
    }
    /// `self` as the failure of script step `step` (1-based) of `kind`.
    pub fn at_step(self, step: usize, kind: &'static str) -> Self {
        Error::Step {
            step,
            kind,
            error: Box::new(self),
        }
    }
    /// The script step (1-based) an error is about, if any.
    pub fn step(&self) -> Option<usize> {
        match self {
            Error::Step { step, .. } | Error::ScriptSyntax { step, .. } => Some(*step),
            Error::BadFile { .. } | Error::Io { .. } | Error::Invalid(_) => None,
            Error::UnknownName { .. } | Error::OutOfRange(_) | Error::DeviceLimit(_) => None,
        }
    }
    /// The error inside any step wrapping (what actually went wrong).
    pub fn root(&self) -> &Error {
        match self {
            Error::Step { error, .. } => error.root(),
            e => e,
        }
    }
}

/// Return early with `Error::Invalid` when `cond` does not hold.
#[macro_export]
macro_rules! ensure {
    ($cond:expr, $($fmt:tt)+) => {
        if !($cond) {
            return Err($crate::error::Error::Invalid(format!($($fmt)+)));
        }
    };
}

/// [`ensure!`] for a limit: returns `Error::$kind` (`OutOfRange`,
/// `DeviceLimit`) when `cond` does not hold, so callers can tell a value
/// out of range or a device too small from other bad input.
#[macro_export]
macro_rules! ensure_within {
    ($kind:ident, $cond:expr, $($fmt:tt)+) => {
        if !($cond) {
            return Err($crate::error::Error::$kind(format!($($fmt)+)));
        }
    };
}

/// Writes `bytes` to `path` atomically: a temporary file in the same
/// directory ([`temp_beside`]), fsync, then rename, so a crash never leaves
/// a half-written file and never destroys the previous version.
pub fn write_atomic(path: &std::path::Path, bytes: &[u8]) -> Result<()> {
    use std::io::Write;
    let mut tmp = temp_beside(path)?;
    tmp.write_all(bytes).map_err(|e| Error::io(path, e))?;
    failpoint("write_atomic.before_rename");
    tmp.as_file().sync_all().map_err(|e| Error::io(path, e))?;
    tmp.persist(path).map_err(|e| Error::io(path, e.error))?;
    Ok(())
}

/// A temporary file in `path`'s folder (made if missing), to write `path`
/// through and rename over it. It gets the permissions of the file it will
/// replace, or those of a plain new file (0666 less the umask on Unix), not
/// the owner-only ones temporary files are made with: what isrf writes is
/// the user's output, for others to read too.
pub fn temp_beside(path: &std::path::Path) -> Result<tempfile::NamedTempFile> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
    let mut builder = tempfile::Builder::new();
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        builder.permissions(std::fs::Permissions::from_mode(0o666));
    }
    let tmp = builder.tempfile_in(&dir).map_err(|e| Error::io(&dir, e))?;
    if let Ok(old) = std::fs::metadata(path) {
        tmp.as_file()
            .set_permissions(old.permissions())
            .map_err(|e| Error::io(path, e))?;
    }
    Ok(tmp)
}

/// Runs `f`, turning a panic inside it into an error naming `what`, so that
/// a bug in one command cannot take a long-running program (the editor)
/// down with the user's session. Callers must only use state that `f`
/// leaves consistent when it unwinds (e.g. a session that swaps in its
/// next state only on success).
pub fn catch_panic<T>(what: &str, f: impl FnOnce() -> Result<T>) -> Result<T> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(payload) => {
            let msg = payload
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown cause".into());
            Err(Error::invalid(format!(
                "{what} failed on an internal error (a bug): {msg}"
            )))
        }
    }
}

/// Test hook: with `ISRF_FAILPOINT=<name>` in the environment the process
/// kills itself (SIGKILL, no clean-up) when it reaches `failpoint(name)`.
/// The tests use it to cut a save at an exact point between its writes.
pub fn failpoint(name: &str) {
    if std::env::var_os("ISRF_FAILPOINT").is_some_and(|v| v == name) {
        #[cfg(unix)]
        // SAFETY: kill(2) on our own PID.
        unsafe {
            libc::kill(libc::getpid(), libc::SIGKILL);
        }
        std::process::abort();
    }
}

#[cfg(all(test, unix))]
mod tests {
    use super::*;
    use std::os::unix::fs::PermissionsExt;

    fn mode(p: &std::path::Path) -> u32 {
        std::fs::metadata(p).unwrap().permissions().mode() & 0o7777
    }

    #[test]
    fn atomic_writes_get_a_plain_files_permissions_or_keep_the_old_ones() {
        let dir = tempfile::tempdir().unwrap();
        // What a plain create gives here (0666 less this process's umask).
        let plain = dir.path().join("plain");
        std::fs::File::create(&plain).unwrap();
        let new = dir.path().join("new.bin");
        write_atomic(&new, b"one").unwrap();
        assert_eq!(mode(&new), mode(&plain), "a new file is created as any file is");
        // A file replaced keeps its mode, even one the umask would not give.
        std::fs::set_permissions(&new, std::fs::Permissions::from_mode(0o640)).unwrap();
        write_atomic(&new, b"two").unwrap();
        assert_eq!(mode(&new), 0o640);
        assert_eq!(std::fs::read(&new).unwrap(), b"two");

        // Fields and checkpoints stream through their own writer, with the
        // same temporary file.
        let tensors = dir.path().join("t.safetensors");
        let data = [1u8, 2, 3];
        let write = || {
            let t = [(safetensors::Dtype::U8, vec![3], &data[..])];
            crate::field::io::write_tensors(&tensors, &["x".to_string()], &t, Default::default()).unwrap();
        };
        write();
        assert_eq!(mode(&tensors), mode(&plain));
        // Even a read-only file is replaced and stays read-only.
        std::fs::set_permissions(&tensors, std::fs::Permissions::from_mode(0o444)).unwrap();
        write();
        assert_eq!(mode(&tensors), 0o444);
    }
}
