//! No-op `fure run` benchmark: generated pipelines of 100, 1,000 and 10,000
//! command stages, all cached; prints the wall time of a full `fure run`
//! process.
//!
//! Run with `cargo bench --bench engine_noop` (release build). Targets:
//! at most 15 ms for 100 stages, 100 ms for 1,000 stages and 1 s for 10,000
//! stages on a 2-core machine. Each size: one populating run (3.5 minutes
//! for 10,000 stages on a busy 2-core machine), two warm-up no-op runs (the
//! hint table settles once files are two seconds old), then `REPEAT` timed
//! no-op runs (`REPEAT_LARGE` at 10,000 stages); prints min / median / max
//! and checks every stage was cached.
//!
//! The generated pipeline is a layered DAG: stage i reads stage i-1 and
//! stage i/2 (so it is neither a flat list nor a single chain), each stage a
//! `sh -c` that writes one small file.

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

const REPEAT: usize = 15;
const REPEAT_LARGE: usize = 7;

fn pipeline(n: usize) -> String {
    let mut s = String::from("[pipeline]\nname = \"noop\"\n");
    for i in 0..n {
        s.push_str(&format!("\n[stages.s{i}]\nkind = \"command\"\n"));
        if i == 0 {
            s.push_str("cmd = [\"sh\", \"-c\", \"echo 0 > o.txt\"]\n");
        } else {
            s.push_str(&format!(
                "cmd = [\"sh\", \"-c\", \"cat {{deps.0}} {{deps.1}} | wc -c > o.txt; echo {i} >> o.txt\"]\ndeps = [\"s{}.o.txt\", \"s{}.o.txt\"]\n",
                i - 1,
                i / 2
            ));
        }
        s.push_str("outs = [\"o.txt\"]\n");
    }
    s
}

fn run(dir: &Path) -> (Duration, String) {
    let t = Instant::now();
    let out = Command::new(env!("CARGO_BIN_EXE_fure"))
        .args(["run", "p.toml", "--plain", "--jobs", "2"])
        .current_dir(dir)
        .env("FURE_CACHE", dir.join("cache"))
        .output()
        .expect("run fure");
    let d = t.elapsed();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    (d, stdout.lines().last().unwrap_or("").to_string())
}

fn main() {
    // `cargo bench` passes `--bench`; ignore arguments.
    let cores = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1);
    println!("engine_noop: no-op `fure run` of generated command-stage pipelines ({cores} cores)");
    for (n, target_ms) in [(100usize, 15.0f64), (1000, 100.0), (10_000, 1000.0)] {
        let repeat = if n >= 10_000 { REPEAT_LARGE } else { REPEAT };
        let dir = tempfile::tempdir().expect("temp dir");
        std::fs::write(dir.path().join("p.toml"), pipeline(n)).unwrap();
        let t = Instant::now();
        let (_, summary) = run(dir.path());
        println!(
            "  {n:>5} stages: first run {:.2}s ({summary})",
            t.elapsed().as_secs_f64()
        );
        // Let every file age past the hint-trust window, then warm up.
        std::thread::sleep(Duration::from_millis(2100));
        run(dir.path());
        run(dir.path());
        let mut times = Vec::with_capacity(repeat);
        for _ in 0..repeat {
            let (d, summary) = run(dir.path());
            assert!(
                summary.contains(&format!("0 ran, {n} cached")),
                "not a no-op: {summary}"
            );
            times.push(d.as_secs_f64() * 1000.0);
        }
        times.sort_by(f64::total_cmp);
        let median = times[times.len() / 2];
        println!(
            "  {n:>5} stages: no-op wall ms min {:.1} median {:.1} max {:.1} (target {target_ms} ms: {})",
            times[0],
            median,
            times[times.len() - 1],
            if median <= target_ms { "met" } else { "MISSED" }
        );
    }
}
