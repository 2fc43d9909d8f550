//! Other work on the machine while a stage runs.
//!
//! A stage's `seconds` are wall time, and the benchmark report turns them
//! into speed-ups and charts. The thread count of the stage's pool (recorded
//! beside them) says what the stage was given, not what it got: a second
//! `fure` process, a build or anything else competing for the cores
//! stretches the seconds, and a cached entry keeps them for every later run
//! that reuses it. So while a stage runs, a sampler thread reads how many
//! tasks the kernel has runnable (`procs_running` in `/proc/stat`) and
//! subtracts those of this process and its descendants (each task's state
//! in `/proc/<pid>/task/<tid>/stat`; descendants through
//! `/proc/<pid>/task/<tid>/children`, which reach a command stage's child).
//! The mean over the samples, [`Sampler::finish`], is the cores other work
//! kept busy on average: about 0 on a quiet machine, about 2 beside another
//! two-thread stage. It is recorded in the cache entry (informative, outside
//! the key and the seal) and the report warns when it is above a threshold.
//!
//! Only Linux has these files; elsewhere, or when they cannot be read, the
//! figure is absent rather than guessed. A sample is two small reads per
//! task, taken every [`SAMPLE_PERIOD`]: negligible beside a stage.

use std::fs;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

/// Time between samples.
pub const SAMPLE_PERIOD: Duration = Duration::from_millis(200);

/// Samples other work in the background until [`Sampler::finish`].
pub struct Sampler {
    stop: Arc<AtomicBool>,
    handle: Option<JoinHandle<Option<f32>>>,
}

impl Sampler {
    /// Starts sampling (the first sample at once). A machine without
    /// `/proc/stat` gets a sampler that reports nothing.
    pub fn start() -> Sampler {
        let stop = Arc::new(AtomicBool::new(false));
        let flag = Arc::clone(&stop);
        let handle = std::thread::Builder::new()
            .name("fure-load-sampler".into())
            .spawn(move || {
                let (mut sum, mut n) = (0u64, 0u64);
                loop {
                    match other_runnable() {
                        Some(x) => {
                            sum += x as u64;
                            n += 1;
                        }
                        None => return None,
                    }
                    if flag.load(Ordering::SeqCst) {
                        break;
                    }
                    std::thread::park_timeout(SAMPLE_PERIOD);
                    if flag.load(Ordering::SeqCst) {
                        break;
                    }
                }
                // Hundredths: the record holds a figure, not float noise.
                (n > 0).then(|| (sum as f32 / n as f32 * 100.0).round() / 100.0)
            })
            .ok();
        Sampler { stop, handle }
    }

    /// Stops sampling: the mean number of runnable tasks of other
    /// processes over the samples (cores kept busy by other work), or None
    /// where it could not be read.
    pub fn finish(mut self) -> Option<f32> {
        self.stop.store(true, Ordering::SeqCst);
        let h = self.handle.take()?;
        h.thread().unpark();
        h.join().ok().flatten()
    }
}

impl Drop for Sampler {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(h) = self.handle.take() {
            h.thread().unpark();
            let _ = h.join();
        }
    }
}

/// Runnable tasks on the machine that are neither this process's threads
/// nor its descendants' (the sampler's own thread is among this process's,
/// so it cancels out). None where `/proc` cannot be read.
pub fn other_runnable() -> Option<u32> {
    let all = procs_running(&fs::read_to_string("/proc/stat").ok()?)?;
    let own = own_runnable(std::process::id())?;
    Some(all.saturating_sub(own))
}

/// `procs_running` of a `/proc/stat` text.
fn procs_running(stat: &str) -> Option<u32> {
    stat.lines()
        .find_map(|l| l.strip_prefix("procs_running"))
        .and_then(|v| v.trim().parse().ok())
}

/// Runnable threads of `pid` and its descendants.
fn own_runnable(pid: u32) -> Option<u32> {
    let mut stack = vec![pid];
    let mut running = 0u32;
    let mut seen = 0usize;
    while let Some(p) = stack.pop() {
        // A process tree deeper or wider than this is not a stage's.
        seen += 1;
        if seen > 4096 {
            break;
        }
        let Ok(tasks) = fs::read_dir(format!("/proc/{p}/task")) else {
            // The root must be readable; a child may have exited meanwhile.
            if p == pid {
                return None;
            }
            continue;
        };
        for t in tasks.flatten() {
            let dir = t.path();
            if let Ok(s) = fs::read_to_string(dir.join("stat")) {
                if task_state(&s) == Some('R') {
                    running += 1;
                }
            }
            if let Ok(c) = fs::read_to_string(dir.join("children")) {
                stack.extend(c.split_whitespace().filter_map(|x| x.parse::<u32>().ok()));
            }
        }
    }
    Some(running)
}

/// The state letter of a `/proc/.../stat` line: the field after the
/// command name, which is in parentheses and may itself hold spaces and
/// parentheses (so the last `)` ends it).
fn task_state(stat: &str) -> Option<char> {
    let rest = &stat[stat.rfind(')')? + 1..];
    rest.split_whitespace().next()?.chars().next()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_the_fields_it_needs_from_proc_texts() {
        let stat = "cpu  1 2 3\nctxt 5\nprocs_running 7\nprocs_blocked 0\n";
        assert_eq!(procs_running(stat), Some(7));
        assert_eq!(procs_running("cpu 1\n"), None);
        assert_eq!(task_state("123 (a) b) c) S 1 2 3"), Some('S'));
        assert_eq!(task_state("9 (fure-stage-pool-0) R 1"), Some('R'));
        assert_eq!(task_state("garbled"), None);
    }

    #[test]
    fn this_process_and_its_children_are_not_other_work() {
        let me = std::process::id();
        if fs::metadata(format!("/proc/{me}/task/{me}/children")).is_err() {
            return; // a kernel without the children files (or no /proc)
        }
        let stop = Arc::new(AtomicBool::new(false));
        let s = Arc::clone(&stop);
        let thread = std::thread::spawn(move || {
            while !s.load(Ordering::Relaxed) {
                std::hint::spin_loop();
            }
        });
        let mut child = std::process::Command::new("sh")
            .args(["-c", "while :; do :; done"])
            .spawn()
            .unwrap();
        std::thread::sleep(Duration::from_millis(200));
        // Runnable means running or waiting for a core, so on a loaded
        // machine too: the reading thread, the spinning thread, the child.
        let own = own_runnable(me);
        let _ = child.kill();
        let _ = child.wait();
        stop.store(true, Ordering::Relaxed);
        thread.join().unwrap();
        assert!(own.unwrap() >= 3, "{own:?}");
    }
}
