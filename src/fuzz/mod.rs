//! In-process mutation fuzzing of the readers, on stable Rust.
//!
//! Each [`targets::Target`] is one reader (field files, bitmaps, strokes,
//! LLFF poses, ...) with seed inputs: valid files made by the library's own
//! writers plus the committed inputs in `tests/fuzz_corpus/<target>/`
//! (earlier crashes among them). [`run`] mutates seeds (see [`mutate`]),
//! writes each mutant to the file the reader opens and calls the reader
//! under `catch_unwind`: an `Err` is the expected outcome, a panic is a bug
//! and is recorded (and the input saved when a save folder is given). A
//! watchdog reports inputs running longer than [`SLOW`]. Binaries that
//! install [`alloc::CapAlloc`] also refuse single allocations over 1 GiB.

pub mod alloc;
pub mod cli;
pub mod mutate;
pub mod targets;

use crate::error::{Error, Result};
use mutate::{mutate, Rng};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Once};
use std::time::{Duration, Instant};
pub use targets::{find, Target, TARGETS};

/// An input taking longer than this is reported (and saved).
pub const SLOW: Duration = Duration::from_secs(5);

/// When to stop and where to keep findings.
#[derive(Clone, Debug, Default)]
pub struct Options {
    pub seed: u64,
    /// Stop after this many inputs (seeds included)...
    pub max_inputs: Option<u64>,
    /// ...or after this long, whichever comes first.
    pub duration: Option<Duration>,
    /// Panicking and slow inputs are copied here.
    pub save_dir: Option<PathBuf>,
    /// Print each panic as it is found.
    pub verbose: bool,
}

/// What a run found.
#[derive(Clone, Debug, Default)]
pub struct Report {
    pub inputs: u64,
    pub errors: u64,
    pub panics: u64,
    /// Inputs that took longer than [`SLOW`].
    pub slow: u64,
    /// The longest time one input took.
    pub max_input_time: Duration,
    pub elapsed: Duration,
    /// Distinct panic messages (with locations), first input that gave each.
    pub panic_kinds: Vec<(String, Vec<u8>)>,
    /// Files written to the save folder.
    pub saved: Vec<PathBuf>,
}

impl Report {
    /// The summary line of `isrf fuzz`.
    pub fn summary(&self) -> String {
        format!(
            "inputs: {}, errors: {}, panics: {}",
            self.inputs, self.errors, self.panics
        )
    }
}

/// How one input ended.
#[derive(Debug)]
pub enum Outcome {
    Ok,
    Err(Error),
    Panic(String),
}

/// Runs `target`'s reader on `input` in `work` (a folder prepared by
/// [`prepare`]), catching panics.
pub fn run_one(target: &Target, work: &Path, input: &[u8]) -> Outcome {
    let path = work.join(target.file);
    if let Err(e) = write_input(&path, input) {
        return Outcome::Err(Error::io(&path, e));
    }
    install_panic_hook();
    CAPTURING.store(true, Ordering::SeqCst);
    alloc::arm(true);
    let result = catch_unwind(AssertUnwindSafe(|| (target.run)(&path)));
    alloc::arm(false);
    CAPTURING.store(false, Ordering::SeqCst);
    match result {
        Ok(Ok(())) => Outcome::Ok,
        Ok(Err(e)) => Outcome::Err(e),
        Err(_) => Outcome::Panic(take_panic_message()),
    }
}

/// Overwrites the input file in place, then cuts it to length: truncating
/// to zero first (as `fs::write` does) makes ext4 flush the old contents
/// on every rewrite (`auto_da_alloc`), about 2 ms an input.
fn write_input(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    use std::io::Write;
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(false)
        .open(path)?;
    f.write_all(bytes)?;
    f.set_len(bytes.len() as u64)
}

/// Makes a work folder for `target` with the files its reader needs
/// besides the input, and returns the seed inputs.
pub fn prepare(target: &Target, work: &Path) -> Result<Vec<Vec<u8>>> {
    std::fs::create_dir_all(work).map_err(|e| Error::io(work, e))?;
    let mut seeds = (target.seeds)(work)?;
    seeds.extend(target.corpus.iter().map(|(_, b)| b.to_vec()));
    crate::ensure!(!seeds.is_empty(), "fuzz target {} has no seeds", target.name);
    alloc::set_input_path(&work.join(target.file));
    Ok(seeds)
}

/// Fuzzes `target`: first each seed as it is, then mutants, until
/// `opts` says stop. Work files live in `work`.
pub fn run(target: &Target, work: &Path, opts: &Options) -> Result<Report> {
    let seeds = prepare(target, work)?;
    let max_len = 4 * seeds.iter().map(Vec::len).max().unwrap_or(0) + 1024;
    let mut rng = Rng::new(opts.seed ^ hash(target.name.as_bytes()));
    let mut report = Report::default();
    let start = Instant::now();
    let watchdog = Watchdog::start(work.join(target.file), opts.save_dir.clone());
    let mut current: Vec<u8> = Vec::new();
    let mut generation = 0;
    while !done(&report, start, opts) {
        let i = report.inputs as usize;
        let input = if i < seeds.len() {
            seeds[i].clone()
        } else {
            // A random walk: mutate the last mutant a few times, then
            // start again from a seed.
            if generation == 0 || rng.below(4) == 0 {
                current = rng.pick(&seeds).clone();
                generation = 8;
            }
            generation -= 1;
            mutate(&mut rng, &mut current, &seeds, max_len);
            current.clone()
        };
        let t = Instant::now();
        watchdog.begin();
        let outcome = run_one(target, work, &input);
        watchdog.end();
        let took = t.elapsed();
        report.inputs += 1;
        report.max_input_time = report.max_input_time.max(took);
        if took > SLOW {
            report.slow += 1;
            save(opts, target, "slow", &input, &mut report)?;
        }
        match outcome {
            Outcome::Ok => {}
            Outcome::Err(_) => report.errors += 1,
            Outcome::Panic(msg) => {
                report.panics += 1;
                if opts.verbose {
                    eprintln!("panic on input {}: {msg}", report.inputs);
                }
                save(opts, target, "panic", &input, &mut report)?;
                if !report.panic_kinds.iter().any(|(m, _)| *m == msg) {
                    report.panic_kinds.push((msg, input));
                }
            }
        }
    }
    report.elapsed = start.elapsed();
    Ok(report)
}

fn done(r: &Report, start: Instant, opts: &Options) -> bool {
    opts.max_inputs.is_some_and(|n| r.inputs >= n) || opts.duration.is_some_and(|d| start.elapsed() >= d)
}

fn save(opts: &Options, target: &Target, kind: &str, input: &[u8], report: &mut Report) -> Result<()> {
    let Some(dir) = &opts.save_dir else { return Ok(()) };
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let ext = target.file.rsplit_once('.').map_or("bin", |(_, e)| e);
    let path = dir.join(format!("{}-{kind}-{:016x}.{ext}", target.name, hash(input)));
    if !path.exists() {
        std::fs::write(&path, input).map_err(|e| Error::io(&path, e))?;
        report.saved.push(path);
    }
    Ok(())
}

/// FNV-1a: names saved inputs by their content.
pub fn hash(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x100_0000_01b3)
    })
}

// ------------------------------------------------------------- panics

static CAPTURING: AtomicBool = AtomicBool::new(false);
static LAST_PANIC: Mutex<Option<String>> = Mutex::new(None);

/// While an input runs, panics (on any thread: rayon passes worker panics
/// on) are recorded with their location instead of printed; otherwise the
/// previous hook prints them as usual.
fn install_panic_hook() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if !CAPTURING.load(Ordering::SeqCst) {
                return previous(info);
            }
            let msg = info
                .payload()
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| info.payload().downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "(non-string panic)".into());
            let at = info
                .location()
                .map_or(String::new(), |l| format!(" at {}:{}", l.file(), l.line()));
            let mut last = LAST_PANIC.lock().unwrap_or_else(|e| e.into_inner());
            last.get_or_insert(format!("{msg}{at}"));
        }));
    });
}

fn take_panic_message() -> String {
    LAST_PANIC
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .take()
        .unwrap_or_else(|| "(panic)".into())
}

// ------------------------------------------------------------- watchdog

/// A thread that notices an input running past [`SLOW`] while it still
/// runs (a hang never returns to be timed), prints it and saves a copy.
struct Watchdog {
    /// Milliseconds since `epoch` when the current input began; 0 = idle.
    began: Arc<AtomicU64>,
    epoch: Instant,
    stop: Arc<AtomicBool>,
}

impl Watchdog {
    fn start(input: PathBuf, save_dir: Option<PathBuf>) -> Watchdog {
        let (began, stop) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicBool::new(false)));
        let epoch = Instant::now();
        let (b, s) = (began.clone(), stop.clone());
        std::thread::spawn(move || {
            let mut reported = 0;
            while !s.load(Ordering::Relaxed) {
                std::thread::sleep(Duration::from_millis(200));
                let t = b.load(Ordering::Relaxed);
                let now = epoch.elapsed().as_millis() as u64;
                if t != 0 && t != reported && now - t > SLOW.as_millis() as u64 {
                    reported = t;
                    eprintln!(
                        "slow input: running for over {} s ({})",
                        SLOW.as_secs(),
                        input.display()
                    );
                    if let (Some(dir), Ok(bytes)) = (&save_dir, std::fs::read(&input)) {
                        let _ = std::fs::create_dir_all(dir);
                        let _ = std::fs::write(dir.join(format!("hang-{:016x}", hash(&bytes))), bytes);
                    }
                }
            }
        });
        Watchdog { began, epoch, stop }
    }
    fn begin(&self) {
        let ms = self.epoch.elapsed().as_millis() as u64;
        self.began.store(ms.max(1), Ordering::Relaxed);
    }
    fn end(&self) {
        self.began.store(0, Ordering::Relaxed);
    }
}

impl Drop for Watchdog {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}
