//! An allocation guard for the fuzz runs: a global allocator that forwards to the system one and,
//! only while a fuzz run has armed it, counts what the fuzzing thread allocates, so that a parser
//! that allocates for a count it read (a PLY header claiming 10^12 vertices) is *found*, not just
//! survived thanks to lazy pages.
//!
//! Installed in the `asgreg` binary (for `asgreg fuzz`) and in the library's test binary. Disarmed,
//! its cost is one relaxed atomic load per allocation. Armed:
//! - on the thread being fuzzed (marked with [`track_this_thread`]): live bytes, their peak and
//!   the largest single request since [`reset_thread_counters`];
//! - on every thread: a single request above the hard limit stops the process with a message
//!   naming the input being parsed (unwinding out of an allocator is not allowed, and the system
//!   allocator would abort on such a request anyway); the input is still on disk at that path.
//!
//! Allocations a parser makes on other threads are bounded only by the hard limit.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicBool, AtomicPtr, AtomicUsize, Ordering};

/// The global allocator of the fuzzing binaries (see the module comment).
pub struct GuardedAllocator;

static ARMED: AtomicBool = AtomicBool::new(false);
static HARD_LIMIT_BYTES: AtomicUsize = AtomicUsize::new(usize::MAX);
/// The path of the input being parsed (a leaked byte string), for the abort message.
static CURRENT_INPUT: AtomicPtr<u8> = AtomicPtr::new(std::ptr::null_mut());
static CURRENT_INPUT_LEN: AtomicUsize = AtomicUsize::new(0);

#[derive(Clone, Copy)]
struct ThreadCounters {
    tracking: bool,
    live_bytes: usize,
    peak_bytes: usize,
    largest_request_bytes: usize,
}

thread_local! {
    // `const`, `Copy` and without a destructor: reading it never allocates, so the allocator may.
    static COUNTERS: Cell<ThreadCounters> = const {
        Cell::new(ThreadCounters {
            tracking: false,
            live_bytes: 0,
            peak_bytes: 0,
            largest_request_bytes: 0,
        })
    };
}

/// What the current thread allocated since [`reset_thread_counters`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct AllocationFigures {
    /// The most bytes live at once (allocated since the reset and not yet freed).
    pub peak_bytes: usize,
    /// The largest single request.
    pub largest_request_bytes: usize,
}

/// Arms the guard for the whole process: requests above `hard_limit_bytes` end the process.
pub fn arm(hard_limit_bytes: usize) {
    HARD_LIMIT_BYTES.store(hard_limit_bytes, Ordering::Relaxed);
    ARMED.store(true, Ordering::Release);
}

/// Whether this binary's global allocator is the guard and it is armed (a test checks this, so
/// a fuzz run cannot pass without measuring).
pub fn is_armed() -> bool {
    ARMED.load(Ordering::Acquire)
}

/// Counts this thread's allocations from now on.
pub fn track_this_thread() {
    update(|counters| counters.tracking = true);
}

/// Names the input being parsed in the message of a hard-limit stop. Leaks the few bytes of the
/// path once per call (a fuzz run calls it once per target).
pub fn set_current_input(path: &std::path::Path) {
    let bytes: &'static [u8] = Box::leak(
        path.as_os_str()
            .to_string_lossy()
            .into_owned()
            .into_bytes()
            .into_boxed_slice(),
    );
    CURRENT_INPUT_LEN.store(0, Ordering::Release);
    CURRENT_INPUT.store(bytes.as_ptr().cast_mut(), Ordering::Release);
    CURRENT_INPUT_LEN.store(bytes.len(), Ordering::Release);
}

/// Starts a new measurement on this thread.
pub fn reset_thread_counters() {
    update(|counters| {
        counters.live_bytes = 0;
        counters.peak_bytes = 0;
        counters.largest_request_bytes = 0;
    });
}

/// This thread's figures since the last [`reset_thread_counters`].
pub fn thread_figures() -> AllocationFigures {
    let counters = COUNTERS.try_with(Cell::get).unwrap_or(ThreadCounters {
        tracking: false,
        live_bytes: 0,
        peak_bytes: 0,
        largest_request_bytes: 0,
    });
    AllocationFigures {
        peak_bytes: counters.peak_bytes,
        largest_request_bytes: counters.largest_request_bytes,
    }
}

fn update(change: impl FnOnce(&mut ThreadCounters)) {
    let _ = COUNTERS.try_with(|cell| {
        let mut counters = cell.get();
        change(&mut counters);
        cell.set(counters);
    });
}

#[inline]
fn note_alloc(size: usize) {
    if !ARMED.load(Ordering::Relaxed) {
        return;
    }
    if size > HARD_LIMIT_BYTES.load(Ordering::Relaxed) {
        stop_on_hard_limit(size);
    }
    update(|counters| {
        if counters.tracking {
            counters.live_bytes = counters.live_bytes.saturating_add(size);
            counters.peak_bytes = counters.peak_bytes.max(counters.live_bytes);
            counters.largest_request_bytes = counters.largest_request_bytes.max(size);
        }
    });
}

#[inline]
fn note_dealloc(size: usize) {
    if !ARMED.load(Ordering::Relaxed) {
        return;
    }
    update(|counters| {
        if counters.tracking {
            counters.live_bytes = counters.live_bytes.saturating_sub(size);
        }
    });
}

/// Writes the message with `write(2)` (no allocation here) and aborts.
#[cold]
fn stop_on_hard_limit(size: usize) -> ! {
    let mut message = [0u8; 512];
    let mut length = 0;
    let mut push = |bytes: &[u8]| {
        for &byte in bytes {
            if length < message.len() {
                message[length] = byte;
                length += 1;
            }
        }
    };
    push(b"asgreg fuzz: allocation guard: a request of ");
    let mut digits = [0u8; 20];
    let mut value = size;
    let mut count = 0;
    loop {
        digits[count] = b'0' + (value % 10) as u8;
        value /= 10;
        count += 1;
        if value == 0 {
            break;
        }
    }
    digits[..count].reverse();
    push(&digits[..count]);
    push(b" bytes is above the hard limit; the input being parsed is ");
    let pointer = CURRENT_INPUT.load(Ordering::Acquire);
    let input_length = CURRENT_INPUT_LEN.load(Ordering::Acquire);
    if pointer.is_null() || input_length == 0 {
        push(b"(not set)");
    } else {
        // SAFETY: set_current_input stores a leaked (never freed) byte string and its length.
        push(unsafe { std::slice::from_raw_parts(pointer, input_length) });
    }
    push(b"\n");
    // SAFETY: writing a valid buffer to the standard error descriptor.
    unsafe {
        libc::write(2, message.as_ptr().cast(), length);
    }
    std::process::abort()
}

// SAFETY: every method forwards to `System` with the same arguments; the bookkeeping neither
// allocates nor unwinds.
unsafe impl GlobalAlloc for GuardedAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note_alloc(layout.size());
        // SAFETY: the caller's contract is passed on unchanged.
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        note_alloc(layout.size());
        // SAFETY: as above.
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        note_dealloc(layout.size());
        // SAFETY: as above.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note_alloc(new_size);
        note_dealloc(layout.size());
        // SAFETY: as above.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}
