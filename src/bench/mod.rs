//! Measured figures for `isrf bench`: plain functions that time library code
//! on the procedural demo scenes and return reports that print as tables.
//! Nothing here asserts on time; the figures are for people to read.
//!
//! - [`render`]: rays per second of the CPU reference renderer.
//! - [`segment`]: per-stage times of stroke → mask against the dense
//!   reference implementation, with an identity check of the outputs.
//! - [`strokes`]: stroke-to-mask latency per stage on a user's own field.
//! - [`train`]: trainer throughput per stage and phase.
//! - [`quality`]: segmentation quality with exact ground truth on fields
//!   trained from renders of the demo scenes.
//! - [`separation`]: whether the teacher's own maps, and the field
//!   distilled from them, part neighbours.
//! - [`splats`]: splat import speed; one-stroke selection of splats.

pub mod quality;
pub mod render;
pub mod segment;
pub mod separation;
pub mod splats;
pub mod strokes;
pub mod train;

use std::fmt;
use std::time::Instant;

/// The first four of `wrong` (what a stage selected wrongly, most first)
/// as "name count, ...", or "none".
pub fn wrong_summary(wrong: &[(String, usize)]) -> String {
    if wrong.is_empty() {
        return "none".into();
    }
    let first: Vec<String> = wrong.iter().take(4).map(|(n, c)| format!("{n} {c}")).collect();
    first.join(", ")
}

/// Per-label counts (`per[label]`) named by `labels` ("unlabelled" for
/// 0), `skip` and zero counts left out, most first: what a selection of
/// `skip` took wrongly.
pub fn wrong_by_name(per: &[usize], labels: &crate::demo::labels::Labels, skip: u8) -> Vec<(String, usize)> {
    let mut wrong: Vec<(String, usize)> = (0..=u8::MAX)
        .zip(per)
        .filter(|&(l, &n)| l != skip && n > 0)
        .map(|(l, &n)| (labels.name_of(l).unwrap_or("unlabelled").to_string(), n))
        .collect();
    wrong.sort_by_key(|w| std::cmp::Reverse(w.1));
    wrong
}

/// Milliseconds taken by `f`, and its result.
pub fn time_ms<T>(f: impl FnOnce() -> T) -> (T, f64) {
    let t0 = Instant::now();
    let r = f();
    (r, crate::util::ms_since(t0))
}

/// Median of a non-empty list (mean of the two middle values for even
/// lengths); 0 for an empty one.
pub fn median(xs: &[f64]) -> f64 {
    if xs.is_empty() {
        return 0.0;
    }
    let mut v = xs.to_vec();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Times of repeated runs of one stage, and the last run's result.
#[derive(Clone, Debug)]
pub struct Timed<T> {
    pub runs_ms: Vec<f64>,
    /// CPU time of all threads of the process during each run (empty where
    /// the kernel does not report it).
    pub cpu_ms: Vec<f64>,
    pub value: T,
}

impl<T> Timed<T> {
    pub fn median_ms(&self) -> f64 {
        median(&self.runs_ms)
    }
    pub fn median_cpu_ms(&self) -> Option<f64> {
        (!self.cpu_ms.is_empty()).then(|| median(&self.cpu_ms))
    }
    pub fn runs(&self) -> usize {
        self.runs_ms.len()
    }
}

/// Runs `f` up to `repeats` times (at least once), stopping early once the
/// runs so far took longer than `budget_ms` in total, so that slow baselines
/// at large grids do not take minutes per stage.
pub fn repeat<T>(repeats: usize, budget_ms: f64, mut f: impl FnMut() -> T) -> Timed<T> {
    repeat_with(repeats, budget_ms, || (), |()| f())
}

/// Like [`repeat`], with an untimed `setup` before each run whose result
/// the timed `f` consumes (e.g. a fresh copy of the mask to grow).
pub fn repeat_with<S, T>(
    repeats: usize,
    budget_ms: f64,
    mut setup: impl FnMut() -> S,
    mut f: impl FnMut(S) -> T,
) -> Timed<T> {
    let mut runs_ms = vec![];
    let mut cpu_ms = vec![];
    loop {
        let input = setup();
        let cpu0 = process_cpu_ns();
        let (value, ms) = time_ms(|| f(input));
        runs_ms.push(ms);
        if let (Some(a), Some(b)) = (cpu0, process_cpu_ns()) {
            cpu_ms.push(b.saturating_sub(a) as f64 / 1e6);
        }
        if runs_ms.len() >= repeats.max(1) || runs_ms.iter().sum::<f64>() > budget_ms {
            if cpu_ms.len() != runs_ms.len() {
                cpu_ms.clear();
            }
            return Timed { runs_ms, cpu_ms, value };
        }
    }
}

/// CPU time consumed so far by the live threads of this process, in ns
/// (first field of `/proc/self/task/*/schedstat`, nanosecond resolution).
/// On a shared machine wall time includes waiting for other processes; CPU
/// time does not, so both are reported. `None` where unavailable.
pub fn process_cpu_ns() -> Option<u64> {
    // The kernel brings a running thread's count up to date when it is
    // scheduled; yielding does that for this thread (others are asleep or
    // spinning down, off by at most a scheduler tick).
    std::thread::yield_now();
    let mut total = 0u64;
    for entry in std::fs::read_dir("/proc/self/task").ok()? {
        let path = entry.ok()?.path().join("schedstat");
        // A thread may exit between listing and reading: skip it.
        let Ok(text) = std::fs::read_to_string(path) else {
            continue;
        };
        total += text.split_whitespace().next()?.parse::<u64>().ok()?;
    }
    Some(total)
}

/// The 1-minute load average (`/proc/loadavg`), to judge contention.
pub fn load_average() -> Option<f64> {
    std::fs::read_to_string("/proc/loadavg")
        .ok()?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

/// Resets this process's peak resident set (`VmHWM`) to its current size
/// (Linux `clear_refs` value 5), so a later [`peak_rss_bytes`] measures one
/// phase; false where not supported.
pub fn reset_peak_rss() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

/// A field of `/proc/self/status` in bytes (`VmHWM` = peak resident set,
/// `VmRSS` = current); `None` where the file or field is missing (not Linux).
pub fn proc_status_bytes(field: &str) -> Option<u64> {
    let text = std::fs::read_to_string("/proc/self/status").ok()?;
    parse_status_kb(&text, field).map(|kb| kb * 1024)
}

fn parse_status_kb(text: &str, field: &str) -> Option<u64> {
    text.lines()
        .find_map(|l| l.strip_prefix(field)?.strip_prefix(':'))
        .and_then(|rest| rest.split_whitespace().next()?.parse().ok())
}

/// Peak resident memory of this process so far (`VmHWM`), in bytes.
pub fn peak_rss_bytes() -> Option<u64> {
    proc_status_bytes("VmHWM")
}

/// Bytes as MB (10⁶), for tables.
pub fn mb(bytes: u64) -> f64 {
    bytes as f64 / 1e6
}

/// Formats an optional memory figure.
pub fn mb_or_na(bytes: Option<u64>) -> String {
    bytes.map_or_else(|| "n/a".into(), |b| format!("{:.0} MB", mb(b)))
}

/// A plain text table: a header row, a rule, right-aligned columns (the
/// first column left-aligned).
#[derive(Clone, Debug, Default)]
pub struct Table {
    pub header: Vec<String>,
    pub rows: Vec<Vec<String>>,
}

impl Table {
    pub fn new(header: &[&str]) -> Self {
        Table {
            header: header.iter().map(|s| s.to_string()).collect(),
            rows: vec![],
        }
    }
    pub fn row(&mut self, cells: Vec<String>) {
        self.rows.push(cells);
    }
}

impl fmt::Display for Table {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let ncol = self.header.len();
        let mut width: Vec<usize> = self.header.iter().map(|h| h.chars().count()).collect();
        for r in &self.rows {
            for (w, c) in width.iter_mut().zip(r) {
                *w = (*w).max(c.chars().count());
            }
        }
        let line = |f: &mut fmt::Formatter<'_>, cells: &[String]| -> fmt::Result {
            for (i, w) in width.iter().enumerate() {
                let c = cells.get(i).map_or("", String::as_str);
                let sep = if i + 1 < ncol { "  " } else { "" };
                if i == 0 {
                    write!(f, "{c:<w$}{sep}")?;
                } else {
                    write!(f, "{c:>w$}{sep}")?;
                }
            }
            writeln!(f)
        };
        line(f, &self.header)?;
        let total = width.iter().sum::<usize>() + 2 * ncol.saturating_sub(1);
        writeln!(f, "{}", "-".repeat(total))?;
        for r in &self.rows {
            line(f, r)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_of_odd_and_even_lists() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0, 3.0, 2.0]), 2.5);
        assert_eq!(median(&[]), 0.0);
    }

    #[test]
    fn status_fields_parse_in_kilobytes() {
        let text = "Name:\tisrf\nVmPeak:\t  900 kB\nVmHWM:\t  1234 kB\nVmRSS:\t 1000 kB\n";
        assert_eq!(parse_status_kb(text, "VmHWM"), Some(1234));
        assert_eq!(parse_status_kb(text, "VmRSS"), Some(1000));
        assert_eq!(parse_status_kb(text, "VmSwap"), None);
    }

    #[test]
    fn repeat_stops_at_the_count_or_the_budget() {
        let mut n = 0;
        let t = repeat(5, f64::INFINITY, || {
            n += 1;
            n
        });
        assert_eq!((t.runs(), t.value), (5, 5));
        let t = repeat(5, -1.0, || 7);
        assert_eq!((t.runs(), t.value), (1, 7));
    }

    #[test]
    fn table_aligns_columns() {
        let mut t = Table::new(&["res", "ms"]);
        t.row(vec!["128".into(), "1.5".into()]);
        t.row(vec!["32".into(), "10.25".into()]);
        let s = t.to_string();
        let lines: Vec<&str> = s.lines().collect();
        assert_eq!(lines[0], "res     ms");
        assert_eq!(lines[1], "----------");
        assert_eq!(lines[2], "128    1.5");
        assert_eq!(lines[3], "32   10.25");
    }
}
