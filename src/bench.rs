//! `fure bench`: a reproducible benchmark of a pipeline.
//!
//! Runs the pipeline `repeat` times, each on a fresh temporary cache (so every
//! stage computes), without materialising outputs, and records per stage the
//! seconds (min / median / max) and the largest peak RSS, together with what
//! is needed to reproduce the figures: git revision (and whether the tree was
//! dirty), fure version, machine (CPU model, cores, memory), every stage's
//! parameters and the parameters that look like seeds (name contains `seed`).

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use serde::Serialize;

use crate::cache::{self, Access, Cache};
use crate::exec::{self, RunOptions, Status, FURE_VERSION};
use crate::plan::Plan;

#[derive(Debug, Clone, Serialize)]
pub struct Machine {
    pub cpu_model: String,
    pub cores: usize,
    pub memory_bytes: u64,
    pub os: String,
}

#[derive(Debug, Clone, Serialize)]
pub struct StageBench {
    pub name: String,
    pub kind: String,
    pub seconds_min: f64,
    pub seconds_median: f64,
    pub seconds_max: f64,
    pub peak_rss_bytes: u64,
    pub params: BTreeMap<String, fure_stage_api::Value>,
}

#[derive(Debug, Clone, Serialize)]
pub struct BenchReport {
    pub pipeline: String,
    pub fure_version: String,
    pub git_revision: String,
    pub git_dirty: bool,
    pub machine: Machine,
    pub repeat: usize,
    pub jobs: usize,
    pub total_seconds: Vec<f64>,
    pub seeds: BTreeMap<String, fure_stage_api::Value>,
    pub stages: Vec<StageBench>,
}

/// What this machine is.
pub fn machine() -> Machine {
    let cpuinfo = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let cpu_model = cpuinfo
        .lines()
        .find(|l| l.starts_with("model name"))
        .and_then(|l| l.split_once(':'))
        .map(|(_, v)| v.trim().to_string())
        .unwrap_or_else(|| "unknown".into());
    let meminfo = std::fs::read_to_string("/proc/meminfo").unwrap_or_default();
    let memory_bytes = meminfo
        .lines()
        .find(|l| l.starts_with("MemTotal:"))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|x| x.parse::<u64>().ok())
        .map(|kb| kb * 1024)
        .unwrap_or(0);
    Machine {
        cpu_model,
        cores: exec::available_cores(),
        memory_bytes,
        os: format!("{} {}", std::env::consts::OS, std::env::consts::ARCH),
    }
}

/// The git revision of the repository holding `dir`, and whether it is dirty.
pub fn git_revision(dir: &Path) -> (String, bool) {
    let run = |args: &[&str]| {
        std::process::Command::new("git")
            .args(args)
            .current_dir(dir)
            .stderr(std::process::Stdio::null())
            .output()
            .ok()
            .filter(|o| o.status.success())
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
    };
    match run(&["rev-parse", "HEAD"]) {
        Some(rev) => {
            let dirty = run(&["status", "--porcelain", "--untracked-files=no"])
                .map(|s| !s.is_empty())
                .unwrap_or(false);
            (rev, dirty)
        }
        None => ("unknown".into(), false),
    }
}

/// Runs the benchmark. Err: a run failed (message names the stage).
pub fn bench(
    plan: &Plan,
    repeat: usize,
    opts: &RunOptions,
    on_run: &mut dyn FnMut(usize, f64),
) -> Result<BenchReport, String> {
    let repeat = repeat.max(1);
    let mut per_stage: BTreeMap<String, (Vec<f64>, u64)> = BTreeMap::new();
    let mut totals = Vec::new();
    let opts = RunOptions {
        out_root: None,
        dry_run: false,
        ..opts.clone()
    };
    for r in 0..repeat {
        let dir = std::env::temp_dir().join(format!("fure-bench-{}-{r}", std::process::id()));
        let _ = cache::remove_tree(&dir);
        let report = {
            let cache = Cache::open(&dir, Access::Shared).map_err(|e| e.to_string())?;
            exec::run(plan, &cache, &opts)
        };
        let _ = cache::remove_tree(&dir);
        if !report.ok() {
            let why = report
                .stages
                .iter()
                .find(|s| s.status == Status::Failed)
                .map(|s| {
                    format!(
                        "stage `{}` failed: {}",
                        s.name,
                        s.error.clone().unwrap_or_default()
                    )
                })
                .unwrap_or_else(|| "a stage did not run".into());
            return Err(format!("run {} of {repeat}: {why}", r + 1));
        }
        for s in &report.stages {
            let e = per_stage.entry(s.name.clone()).or_default();
            e.0.push(s.seconds);
            e.1 = e.1.max(s.peak_rss_bytes);
        }
        totals.push(report.seconds);
        on_run(r, report.seconds);
    }
    let dir = plan
        .file
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_default();
    let dir = if dir.as_os_str().is_empty() {
        Path::new(".").to_path_buf()
    } else {
        dir
    };
    let (git_revision, git_dirty) = git_revision(&dir);
    let mut seeds = BTreeMap::new();
    let stages = plan
        .stages
        .iter()
        .map(|st| {
            for (k, v) in &st.params.0 {
                if k.contains("seed") {
                    seeds.insert(format!("{}.{k}", st.name), v.clone());
                }
            }
            let (mut secs, peak) = per_stage.remove(&st.name).unwrap_or_default();
            secs.sort_by(f64::total_cmp);
            let pick = |f: fn(&[f64]) -> f64| if secs.is_empty() { 0.0 } else { f(&secs) };
            StageBench {
                name: st.name.clone(),
                kind: st.kind.clone(),
                seconds_min: pick(|s| s[0]),
                seconds_median: pick(median),
                seconds_max: pick(|s| s[s.len() - 1]),
                peak_rss_bytes: peak,
                params: st.params.0.clone(),
            }
        })
        .collect();
    Ok(BenchReport {
        pipeline: plan.name.clone(),
        fure_version: FURE_VERSION.into(),
        git_revision,
        git_dirty,
        machine: machine(),
        repeat,
        jobs: opts.jobs,
        total_seconds: totals,
        seeds,
        stages,
    })
}

/// Median of sorted values.
pub fn median(s: &[f64]) -> f64 {
    let n = s.len();
    if n == 0 {
        0.0
    } else if n % 2 == 1 {
        s[n / 2]
    } else {
        0.5 * (s[n / 2 - 1] + s[n / 2])
    }
}

/// The benchmark as Markdown.
pub fn markdown(b: &BenchReport) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "# Benchmark: {}\n", b.pipeline);
    let _ = writeln!(
        s,
        "fure {} at {}{}; {} ({} cores, {:.1} GiB, {}); {} runs, --jobs {}\n",
        b.fure_version,
        b.git_revision,
        if b.git_dirty { " (dirty)" } else { "" },
        b.machine.cpu_model,
        b.machine.cores,
        b.machine.memory_bytes as f64 / (1u64 << 30) as f64,
        b.machine.os,
        b.repeat,
        b.jobs
    );
    let mut tot = b.total_seconds.clone();
    tot.sort_by(f64::total_cmp);
    if !tot.is_empty() {
        let _ = writeln!(
            s,
            "Total wall seconds: min {:.3}, median {:.3}, max {:.3}\n",
            tot[0],
            median(&tot),
            tot[tot.len() - 1]
        );
    }
    let _ = writeln!(
        s,
        "| stage | kind | min s | median s | max s | peak RSS MiB |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|");
    for st in &b.stages {
        let _ = writeln!(
            s,
            "| {} | {} | {:.3} | {:.3} | {:.3} | {:.1} |",
            st.name,
            st.kind,
            st.seconds_min,
            st.seconds_median,
            st.seconds_max,
            st.peak_rss_bytes as f64 / (1u64 << 20) as f64
        );
    }
    if !b.seeds.is_empty() {
        let _ = writeln!(
            s,
            "\nSeeds: {}",
            b.seeds
                .iter()
                .map(|(k, v)| format!("{k}={}", crate::plan::show(v)))
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_of_even_and_odd() {
        assert_eq!(median(&[1.0, 2.0, 10.0]), 2.0);
        assert_eq!(median(&[1.0, 2.0, 4.0, 10.0]), 3.0);
        assert_eq!(median(&[]), 0.0);
    }
}
