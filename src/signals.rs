//! SIGINT, SIGTERM and SIGHUP: forwarded to the running commands.
//!
//! Every command stage runs in its own process group (so a terminal's
//! Ctrl-C reaches fure alone). The handler records the first signal and
//! sends it to every registered group; in-process stages see it through
//! their progress sink (`Progress::interrupted`, checked between steps: a
//! thread cannot be killed, and a learner would otherwise run its minutes
//! out); the scheduler, and a sweep's loop over variants, then start nothing
//! new, the killed commands fail (as does one that exits 0 after the
//! signal: its outputs may be partial), their staging directories are removed,
//! and `fure` exits with 128 + the signal number. A second signal of the
//! same kind gets the default action (fure dies at once; each command's
//! watchdog then kills its group, see `command`).
//!
//! The handler only reads atomics and calls `kill` and `signal`, which are
//! async-signal-safe.

use std::sync::atomic::{AtomicI32, Ordering};

/// Process groups of running commands (0: free slot). More concurrent
/// commands than slots are not forwarded to, but still die with their
/// watchdog when fure exits.
static GROUPS: [AtomicI32; 256] = [const { AtomicI32::new(0) }; 256];

/// The first signal received (0: none).
static RECEIVED: AtomicI32 = AtomicI32::new(0);

extern "C" fn on_signal(sig: libc::c_int) {
    let _ = RECEIVED.compare_exchange(0, sig, Ordering::SeqCst, Ordering::SeqCst);
    for g in &GROUPS {
        let pgid = g.load(Ordering::SeqCst);
        if pgid > 0 {
            // SAFETY: kill is async-signal-safe; a negative pid names a group.
            unsafe { libc::kill(-pgid, sig) };
        }
    }
    // SAFETY: signal is async-signal-safe; the next one is fatal.
    unsafe { libc::signal(sig, libc::SIG_DFL) };
}

/// Installs the handlers (the `fure` binary does, at start).
pub fn install() {
    for sig in [libc::SIGINT, libc::SIGTERM, libc::SIGHUP] {
        // SAFETY: a plain handler with SA_RESTART, so blocking calls of other
        // threads resume instead of failing with EINTR.
        unsafe {
            let mut sa: libc::sigaction = std::mem::zeroed();
            sa.sa_sigaction = on_signal as extern "C" fn(libc::c_int) as usize;
            sa.sa_flags = libc::SA_RESTART;
            libc::sigemptyset(&mut sa.sa_mask);
            libc::sigaction(sig, &sa, std::ptr::null_mut());
        }
    }
}

/// The first signal received, if any.
pub fn received() -> Option<i32> {
    match RECEIVED.load(Ordering::SeqCst) {
        0 => None,
        s => Some(s),
    }
}

/// The name of a signal number, for messages.
pub fn name(sig: i32) -> String {
    match sig {
        libc::SIGINT => "SIGINT".into(),
        libc::SIGTERM => "SIGTERM".into(),
        libc::SIGHUP => "SIGHUP".into(),
        libc::SIGKILL => "SIGKILL".into(),
        s => format!("signal {s}"),
    }
}

/// A registered process group, unregistered on drop.
pub struct Registered(Option<usize>);

impl Drop for Registered {
    fn drop(&mut self) {
        if let Some(i) = self.0 {
            GROUPS[i].store(0, Ordering::SeqCst);
        }
    }
}

/// Registers a command's process group for forwarding; a signal that came
/// before the registration is sent at once.
pub fn register(pgid: i32) -> Registered {
    let slot = GROUPS.iter().position(|g| {
        g.compare_exchange(0, pgid, Ordering::SeqCst, Ordering::SeqCst)
            .is_ok()
    });
    if let Some(sig) = received() {
        // SAFETY: signalling our own child's group.
        unsafe { libc::kill(-pgid, sig) };
    }
    Registered(slot)
}
