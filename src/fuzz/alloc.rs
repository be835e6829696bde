//! An allocator for fuzzing binaries only (`isrf-fuzz`, the fuzz test): it
//! refuses any single allocation over [`CAP`] while a fuzz run is going, so
//! a reader that allocates from an unchecked header is caught even on a
//! machine with the memory to satisfy it. The `isrf` binary does not use it.
//!
//! A refused allocation cannot be turned into a panic (allocators must not
//! unwind): `Vec` & co. then abort with "memory allocation of N bytes
//! failed", `try_reserve` callers get an error. Before that, the allocator
//! prints the size and where the current input is, without allocating.

use std::alloc::{GlobalAlloc, Layout, System};
use std::io::Write;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

/// The largest single allocation allowed during a fuzz run: 1 GiB.
pub const CAP: usize = 1 << 30;

static ARMED: AtomicBool = AtomicBool::new(false);
static INSTALLED: AtomicBool = AtomicBool::new(false);
static REFUSED: AtomicUsize = AtomicUsize::new(0);
/// Where the current input is, for the refusal message (a fixed buffer:
/// the allocator must not allocate).
static INPUT_PATH: std::sync::Mutex<([u8; 512], usize)> = std::sync::Mutex::new(([0; 512], 0));

/// `#[global_allocator] static A: CapAlloc = CapAlloc;` in a fuzzing binary.
pub struct CapAlloc;

impl CapAlloc {
    fn refuse(&self, size: usize) -> bool {
        INSTALLED.store(true, Ordering::Relaxed);
        if size <= CAP || !ARMED.load(Ordering::Relaxed) {
            return false;
        }
        REFUSED.fetch_add(1, Ordering::Relaxed);
        let mut err = std::io::stderr().lock();
        let _ = write!(err, "\nfuzz: refused a {size}-byte allocation (cap {CAP})");
        if let Ok(p) = INPUT_PATH.try_lock() {
            let _ = err.write_all(b"; the input is ");
            let _ = err.write_all(&p.0[..p.1]);
        }
        let _ = err.write_all(b"\n");
        true
    }
}

// SAFETY: every call is passed on to the system allocator unchanged, or
// answered with null (allowed: "allocation failed").
unsafe impl GlobalAlloc for CapAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if self.refuse(layout.size()) {
            return std::ptr::null_mut();
        }
        // SAFETY: the caller's contract is System's.
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if self.refuse(layout.size()) {
            return std::ptr::null_mut();
        }
        // SAFETY: as above.
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if self.refuse(new_size) {
            return std::ptr::null_mut();
        }
        // SAFETY: as above.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: as above.
        unsafe { System.dealloc(ptr, layout) }
    }
}

/// Whether the running binary allocates through [`CapAlloc`] (known after
/// its first allocation, i.e. always by the time anyone asks).
pub fn installed() -> bool {
    INSTALLED.load(Ordering::Relaxed)
}

/// Allocations refused so far.
pub fn refused() -> usize {
    REFUSED.load(Ordering::Relaxed)
}

/// Arms the cap (while a fuzz input runs) or disarms it.
pub fn arm(on: bool) {
    ARMED.store(on, Ordering::Relaxed);
}

/// The path the refusal message names.
pub fn set_input_path(path: &std::path::Path) {
    let s = path.as_os_str().as_encoded_bytes();
    let mut p = INPUT_PATH.lock().unwrap_or_else(|e| e.into_inner());
    let n = s.len().min(p.0.len());
    p.0[..n].copy_from_slice(&s[..n]);
    p.1 = n;
}
