//! Other work on the machine while a stage runs.
//!
//! A stage's `seconds` are wall time, and the benchmark report turns them
//! into speed-ups and charts. The thread count of the stage's pool (recorded
//! beside them) says what the stage was given, not what it got: a second
//! `fure` process, a build or anything else competing for the cores
//! stretches the seconds, and a cached entry keeps them for every later run
//! that reuses it. So [`Meter`] reads, when a stage starts and when it ends,
//! the CPU time the whole machine spent busy (the `cpu` line of
//! `/proc/stat`) and the CPU time of this process and the children it
//! reaped (`/proc/self/stat`: a command stage's child is reaped before the
//! stage ends). Their difference over the wall time is the cores other work
//! used on average: about 0 on a quiet machine; two busy processes beside a
//! sleeping stage read 2 on two cores (the integration test). It is CPU
//! used, not CPU wanted: a process that only waits for a core reads nothing,
//! and one that takes the cores a stage leaves idle (a build at `nice 19`
//! beside its serial stretches) reads what it took, which also slows the
//! stage through the shared caches and memory bus. It is recorded in the
//! cache entry (informative, outside the key and the seal), and the report
//! and `fure sweep` say when it is above [`BUSY_CORES`].
//!
//! Stages that run beside each other in this process (`--jobs` above 1) are
//! this process's CPU time, so they do not read as other work: the figure
//! speaks for what ran outside fure, and a timing meant to be the stage's
//! own wants `--jobs 1` as well (the benchmark suites run so).
//!
//! Only Linux has these files; elsewhere, or when they cannot be read, or
//! for a stage shorter than [`MIN_SECONDS`] (a few clock ticks), the figure
//! is absent rather than guessed.

use std::fs;
use std::time::{Duration, Instant};

/// Above this many cores used by other work, on average, a stage's seconds
/// are said to be measured beside other work.
pub const BUSY_CORES: f32 = 0.5;

/// Stages shorter than this get no figure: the kernel counts CPU time in
/// ticks of 10 ms, too coarse for them.
pub const MIN_SECONDS: f64 = 0.5;

/// The kernel's clock ticks per second for `/proc` CPU times (`USER_HZ`,
/// 100 on every Linux architecture fure builds on).
const TICKS_PER_SECOND: f64 = 100.0;

/// CPU-time readings at a stage's start.
pub struct Meter {
    start: Instant,
    machine_busy: Option<u64>,
    own: Option<u64>,
}

impl Meter {
    /// Takes the start readings.
    pub fn start() -> Meter {
        Meter {
            start: Instant::now(),
            machine_busy: machine_busy_ticks(),
            own: own_ticks(),
        }
    }

    /// The cores other work used on average since [`Meter::start`],
    /// rounded to hundredths; None where it cannot be read or the stage was
    /// shorter than [`MIN_SECONDS`].
    pub fn finish(self) -> Option<f32> {
        let wall = self.start.elapsed();
        other_cores(
            (self.machine_busy?, machine_busy_ticks()?),
            (self.own?, own_ticks()?),
            wall,
        )
    }
}

/// Other work's cores from the machine's and this process's busy ticks at
/// the start and the end of `wall`.
fn other_cores(machine: (u64, u64), own: (u64, u64), wall: Duration) -> Option<f32> {
    let secs = wall.as_secs_f64();
    if secs < MIN_SECONDS {
        return None;
    }
    let machine = machine.1.saturating_sub(machine.0) as f64;
    let own = own.1.saturating_sub(own.0) as f64;
    let cores = ((machine - own).max(0.0) / TICKS_PER_SECOND / secs) as f32;
    // Hundredths: the record holds a figure, not float noise.
    Some((cores * 100.0).round() / 100.0)
}

/// Busy ticks of the whole machine (every field of `/proc/stat`'s `cpu`
/// line but idle and iowait; guest time is already inside user).
fn machine_busy_ticks() -> Option<u64> {
    busy_ticks(&fs::read_to_string("/proc/stat").ok()?)
}

fn busy_ticks(stat: &str) -> Option<u64> {
    let line = stat.lines().find(|l| l.starts_with("cpu "))?;
    let f: Vec<u64> = line
        .split_whitespace()
        .skip(1)
        .map(|x| x.parse().ok())
        .collect::<Option<_>>()?;
    // user nice system idle iowait irq softirq steal [guest guest_nice]
    if f.len() < 8 {
        return None;
    }
    Some(f[0] + f[1] + f[2] + f[5] + f[6] + f[7])
}

/// This process's CPU ticks and those of its reaped children.
fn own_ticks() -> Option<u64> {
    process_ticks(&fs::read_to_string("/proc/self/stat").ok()?)
}

/// utime + stime + cutime + cstime of a `/proc/<pid>/stat` line. The
/// command name (field 2) is in parentheses and may hold spaces and
/// parentheses, so fields are counted after the last `)`.
fn process_ticks(stat: &str) -> Option<u64> {
    let rest = &stat[stat.rfind(')')? + 1..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    // After the name: state (3), ..., utime (14), stime (15), cutime (16), cstime (17).
    let field =
        |n: usize| -> Option<u64> { f.get(n - 3)?.parse::<i64>().ok().map(|x| x.max(0) as u64) };
    Some(field(14)? + field(15)? + field(16)? + field(17)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_the_fields_it_needs_from_proc_texts() {
        let stat = "cpu  10 1 5 1000 7 2 3 4 0 0\ncpu0 5 0 2 500 3 1 1 2 0 0\nprocs_running 7\n";
        assert_eq!(busy_ticks(stat), Some(10 + 1 + 5 + 2 + 3 + 4));
        assert_eq!(busy_ticks("cpu0 1 2 3\n"), None);
        assert_eq!(busy_ticks("cpu  1 2 3\n"), None);
        let own = "4242 (a (b) c) S 1 2 3 4 5 6 7 8 9 10 11 12 13 14 15 20";
        // utime 11, stime 12, cutime 13, cstime 14.
        assert_eq!(process_ticks(own), Some(11 + 12 + 13 + 14));
        assert_eq!(process_ticks("garbled"), None);
    }

    #[test]
    fn other_work_is_the_machine_less_this_process_per_second() {
        let s = Duration::from_secs(2);
        // The machine busy 400 ticks in 2 s, this process 150 of them: 1.25 other cores.
        assert_eq!(other_cores((1000, 1400), (50, 200), s), Some(1.25));
        // Never negative (the counters are read a moment apart).
        assert_eq!(other_cores((0, 100), (0, 120), s), Some(0.0));
        // Too short to say.
        assert_eq!(
            other_cores((0, 10), (0, 0), Duration::from_millis(100)),
            None
        );
    }

    #[test]
    fn a_reaped_childs_cpu_time_is_this_processs() {
        let Some(before) = own_ticks() else {
            return; // no /proc
        };
        let status = std::process::Command::new("sh")
            .args(["-c", "i=0; while [ $i -lt 300000 ]; do i=$((i+1)); done"])
            .status()
            .unwrap();
        assert!(status.success());
        let after = own_ticks().unwrap();
        // The child's loop takes tenths of a second of CPU; none of it is this thread's.
        assert!(after >= before + 5, "{before} -> {after}");
    }
}
