//! The CPU engine allocates nothing per frame pair once its buffers have grown to the frame
//! size: a controller that runs for hours must not churn the heap in its 33 ms loop. This file
//! is its own test binary, so the counting allocator sees this engine and nothing else.

use flownav::flow::cpu::CpuFlow;
use flownav::flow::{FlowEngine, FlowParams};
use hal::LumaImage;
use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

struct Counting;

static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

// SAFETY: forwards every call to the system allocator unchanged; it only counts.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        // SAFETY: the caller's contract is passed on as is.
        unsafe { System.alloc(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: as above.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        // SAFETY: as above.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// A textured frame and the same texture moved by (dx, dy).
fn pair(w: usize, h: usize, dx: i64, dy: i64) -> (LumaImage, LumaImage) {
    let tex = |x: i64, y: i64| {
        let v = (x.wrapping_mul(7_919) ^ y.wrapping_mul(104_729)).wrapping_mul(2_654_435_761) >> 13;
        (v & 0xff) as u8
    };
    let a = LumaImage::from_fn(w, h, |x, y| tex(x as i64, y as i64));
    let b = LumaImage::from_fn(w, h, |x, y| tex(x as i64 - dx, y as i64 - dy));
    (a, b)
}

/// Allocations made by `pairs` further computes after two to warm the engine up.
fn allocations(params: FlowParams, pairs: usize) -> usize {
    let frames = [pair(320, 240, 3, -2), pair(320, 240, -5, 4), pair(320, 240, 1, 7)];
    let mut engine = CpuFlow::new(params).expect("CPU engine");
    for (a, b) in &frames[..2] {
        engine.compute(a, b).expect("flow");
    }
    let before = ALLOCATIONS.load(Ordering::Relaxed);
    for k in 0..pairs {
        let (a, b) = &frames[k % frames.len()];
        engine.compute(a, b).expect("flow");
    }
    ALLOCATIONS.load(Ordering::Relaxed) - before
}

#[test]
fn the_cpu_engine_allocates_nothing_per_pair() {
    let base = FlowParams { rows: 6, cols: 8, block: 16, radius: 8, ..FlowParams::default() };
    let pairs = 64;
    // One thread first: a pool dropped by a two-thread engine winds its threads down in the
    // background, and their exit would be counted here.
    for levels in [1, 3] {
        let one = FlowParams { cpu_threads: 1, pyramid_levels: levels, refine_radius: 2, ..base.clone() };
        assert_eq!(allocations(one, pairs), 0, "one thread, {levels} level(s)");
    }
    for levels in [1, 3] {
        // With a worker, the thread pool boxes one job per level, and its queues allocate now
        // and then (new blocks, deferred frees); the engine's own buffers would add at least
        // two per level.
        let two = FlowParams { cpu_threads: 2, pyramid_levels: levels, refine_radius: 2, ..base.clone() };
        let jobs = levels * pairs;
        let n = allocations(two, pairs);
        assert!(n < 2 * jobs, "two threads, {levels} level(s): {n} allocations in {pairs} pairs");
    }
}
