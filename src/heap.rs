//! How the C allocator (glibc) keeps memory, set per command and, for the
//! teacher's network, per phase.
//!
//! glibc serves a buffer at or above its mmap threshold with a mapping of
//! its own, which goes back to the system when freed and is faulted in,
//! page by page, when allocated again. Below it, buffers come from the
//! per-thread heaps, which keep freed memory resident (up to the trim
//! threshold at their top). Which is right depends on what a command does
//! most, so each command picks a [`Heap`] at startup, and the teacher's
//! network runs under [`Heap::Scratch`] ([`scoped`]).

use std::sync::atomic::{AtomicU8, Ordering};

/// An allocator policy.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum Heap {
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
    /// The teacher's network (tract): each layer allocates and frees
    /// activations of a few MB to 14 MB (a 48×48-token map times 1536
    /// channels). Under `Release` every one was faulted in again: the fern's
    /// 17 images (2×2 shifted runs at 448) took 40.0 s and 14.6 M page
    /// faults, under `Reuse` 30.7 s and 4.4 M, with buffers up to 32 MB
    /// from the heaps (64 MB kept free) 26.5 s and 0.8 M.
    Scratch,
}

/// The policy in force (a `Heap` as u8).
static CURRENT: AtomicU8 = AtomicU8::new(Heap::Release as u8);

impl Heap {
    fn from_u8(v: u8) -> Heap {
        match v {
            0 => Heap::Release,
            1 => Heap::Reuse,
            _ => Heap::Scratch,
        }
    }

    /// (mmap threshold, trim threshold; `None` keeps glibc's 128 kB).
    fn thresholds(self) -> (i32, Option<i32>) {
        match self {
            Heap::Release => (1 << 20, None),
            Heap::Reuse => (8 << 20, Some(16 << 20)),
            Heap::Scratch => (32 << 20, Some(64 << 20)),
        }
    }
}

/// The policy set last.
pub fn current() -> Heap {
    Heap::from_u8(CURRENT.load(Ordering::Relaxed))
}

/// Puts `policy` in force. Safe while other threads allocate: glibc reads
/// the thresholds on each call and `mallopt` takes the allocator's lock.
pub fn set(policy: Heap) {
    CURRENT.store(policy as u8, Ordering::Relaxed);
    apply(policy);
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn apply(policy: Heap) {
    let (mmap, trim) = policy.thresholds();
    // glibc's trim threshold when none is given.
    let trim = trim.unwrap_or(128 << 10);
    // SAFETY: malloc tuning calls; glibc serialises them with its own lock.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, mmap);
        libc::mallopt(libc::M_TRIM_THRESHOLD, trim);
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn apply(_policy: Heap) {}

/// Gives the heaps' free memory back to the system (after a phase that
/// kept it, so that what follows does not carry it in its peak).
fn release_free() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only returns free memory; it takes each arena's lock.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// `policy` until the guard drops, then the one before it (and the heaps'
/// free memory back to the system, if they were keeping more than before).
pub fn scoped(policy: Heap) -> Scoped {
    let before = current();
    set(policy);
    Scoped { before, policy }
}

/// Restores the policy in force before [`scoped`] when dropped.
pub struct Scoped {
    before: Heap,
    policy: Heap,
}

impl Drop for Scoped {
    fn drop(&mut self) {
        set(self.before);
        if self.policy.thresholds().1 > self.before.thresholds().1 {
            release_free();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The policy is global; one test walks every change so that tests run
    /// in parallel do not see each other's.
    #[test]
    fn scoped_policies_restore_the_one_before() {
        set(Heap::Reuse);
        {
            let _outer = scoped(Heap::Scratch);
            assert_eq!(current(), Heap::Scratch);
            {
                let _inner = scoped(Heap::Release);
                assert_eq!(current(), Heap::Release);
            }
            assert_eq!(current(), Heap::Scratch);
            // Allocating and freeing under the policy works as ever.
            let v = vec![7u8; 20 << 20];
            assert_eq!(v.iter().map(|&b| b as usize).sum::<usize>(), 7 * (20 << 20));
        }
        assert_eq!(current(), Heap::Reuse);
        set(Heap::Release);
        assert_eq!(current(), Heap::Release);
    }
}
