//! A process-local rayon pool keyed by pid.
//!
//! rayon's global pool deadlocks in a child forked after it was used (its worker threads do not
//! exist in the child), and torch's DataLoader forks. Every native call runs inside `install`,
//! which builds a fresh pool the first time it is used in a new process. The thread count follows
//! `RAYON_NUM_THREADS` (or `MORPHGS_NUM_THREADS`), else the number of CPUs.
use std::sync::{Arc, Mutex};

use rayon::{ThreadPool, ThreadPoolBuilder};

static POOL: Mutex<Option<(u32, Arc<ThreadPool>)>> = Mutex::new(None);

fn threads_from_env() -> usize {
    for var in ["MORPHGS_NUM_THREADS", "RAYON_NUM_THREADS"] {
        if let Some(n) = std::env::var(var)
            .ok()
            .and_then(|v| v.trim().parse::<usize>().ok())
        {
            if n > 0 {
                return n;
            }
        }
    }
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

/// The pool of the current process (created on first use after start or fork); `None` only when
/// the OS refuses to start threads, in which case work runs on the calling thread.
pub fn pool() -> Option<Arc<ThreadPool>> {
    let pid = std::process::id();
    let mut guard = match POOL.lock() {
        Ok(g) => g,
        Err(poisoned) => poisoned.into_inner(),
    };
    if let Some((owner, pool)) = guard.as_ref() {
        if *owner == pid {
            return Some(Arc::clone(pool));
        }
    }
    // A pool inherited through fork has no threads in this process: never drop it (its drop
    // would signal workers that do not exist); leak it and build a new one.
    if let Some(old) = guard.take() {
        std::mem::forget(old);
    }
    let pool = ThreadPoolBuilder::new()
        .num_threads(threads_from_env())
        .thread_name(|i| format!("morphgs-{i}"))
        .build()
        .map(Arc::new)
        .ok()?;
    *guard = Some((pid, Arc::clone(&pool)));
    Some(pool)
}

/// Run `f` in this process's pool.
pub fn install<T: Send>(f: impl FnOnce() -> T + Send) -> T {
    match pool() {
        Some(p) => p.install(f),
        None => f(),
    }
}

/// Number of threads the pool uses.
pub fn num_threads() -> usize {
    pool().map_or(1, |p| p.current_num_threads())
}
