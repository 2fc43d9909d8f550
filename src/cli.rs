//! The `fure` command line.
//!
//! Exit codes: 0 success; 1 a stage failed (or `verify` found damage);
//! 2 a bad pipeline or bad usage. `sweep` exits 0 when every variant got a
//! status, failed variants included (they are results, in the table and the
//! record), and 1 only when an aggregate stage fails or a file cannot be
//! written. Every command takes `--cache DIR` (or the
//! `FURE_CACHE` environment variable; default `cache/` in the current
//! directory).

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Parser, Subcommand, ValueEnum};
use fure_stage_api::{PortKind, Stage};

use crate::cache::{self, Access, Cache, GcOptions};
use crate::exec::{self, RunOptions, RunReport, Status};
use crate::pipeline::{parse_cli_list, PipelineErrors};
use crate::plan::{show, Plan, Source};
use crate::ui::UiMode;
use crate::{bench, sweep, Engine};

#[derive(Parser, Debug)]
#[command(
    name = "fure",
    version,
    about = "Strand-based fur reconstruction on a cached dataflow engine"
)]
pub struct Cli {
    /// Cache directory.
    #[arg(long, global = true, env = "FURE_CACHE", default_value = "cache")]
    pub cache: PathBuf,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Run a pipeline (only what is not cached).
    Run(RunArgs),
    /// For every stage: cached, or will run and why.
    Status(StatusArgs),
    /// Print the stage graph.
    Dag(DagArgs),
    /// Run every variant of a parameter grid ([sweep], [sweep.each], --grid, --each), then
    /// the [aggregate.NAME] stages on the sweep record.
    Sweep(SweepArgs),
    /// Remove cache entries and objects.
    Gc(GcArgs),
    /// Rehash every object; drop corrupted entries.
    Verify,
    /// Reproducible benchmark: N runs on fresh temporary caches.
    Bench(BenchArgs),
    /// List the stage kinds with their parameters and ports.
    Stages(StagesArgs),
    /// Compute the one stage of a Slurm job spec against the cache (what
    /// `--executor slurm` submits; see docs/cluster.md).
    #[command(hide = true)]
    Worker(WorkerArgs),
}

// The subcommands' arguments. Their help text is the variant's doc comment
// in `Command`, so these structs carry none of their own.

#[derive(clap::Args, Debug)]
pub struct RunArgs {
    pub pipeline: PathBuf,
    /// Override a parameter: STAGE.PARAM=VALUE (VALUE is TOML; bare words are strings).
    #[arg(long = "set", value_name = "STAGE.PARAM=VALUE")]
    pub sets: Vec<String>,
    /// Stages running at once (default: number of cores).
    #[arg(long, short)]
    pub jobs: Option<usize>,
    /// Run only this stage and what it depends on.
    #[arg(long)]
    pub until: Option<String>,
    /// Write the run report (JSON) here.
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Show what would run, run nothing.
    #[arg(long)]
    pub dry_run: bool,
    /// Where outputs are materialised (`<out>/<pipeline>/<stage>/`).
    #[arg(long, default_value = "out")]
    pub out: PathBuf,
    /// Plain lines even on a terminal.
    #[arg(long)]
    pub plain: bool,
    /// Keep running independent stages after a failure.
    #[arg(long)]
    pub keep_going: bool,
    #[command(flatten)]
    pub executor: ExecutorArgs,
    /// Sets parameter `device` (auto, cpu, gpu) on every stage that declares one.
    #[arg(long, value_name = "DEVICE")]
    pub device: Option<String>,
}

#[derive(clap::Args, Debug)]
pub struct StatusArgs {
    pub pipeline: PathBuf,
    #[arg(long = "set", value_name = "STAGE.PARAM=VALUE")]
    pub sets: Vec<String>,
    #[arg(long)]
    pub until: Option<String>,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Args, Debug)]
pub struct DagArgs {
    pub pipeline: PathBuf,
    #[arg(long, value_enum, default_value = "text")]
    pub format: DagFormat,
    #[arg(long = "set", value_name = "STAGE.PARAM=VALUE")]
    pub sets: Vec<String>,
}

#[derive(clap::Args, Debug)]
pub struct SweepArgs {
    pub pipeline: PathBuf,
    /// A crossed axis: STAGE.PARAM=V1,V2,... (or a TOML array); replaces a
    /// [sweep] or [sweep.each] axis's values.
    #[arg(long = "grid", value_name = "STAGE.PARAM=V1,V2,...")]
    pub grids: Vec<String>,
    /// A one-at-a-time axis (like [sweep.each]): STAGE.PARAM=V1,V2,...
    #[arg(long = "each", value_name = "STAGE.PARAM=V1,V2,...")]
    pub eaches: Vec<String>,
    #[arg(long = "set", value_name = "STAGE.PARAM=VALUE")]
    pub sets: Vec<String>,
    #[arg(long, short)]
    pub jobs: Option<usize>,
    #[arg(long, default_value = "out")]
    pub out: PathBuf,
    /// Table path prefix (writes PREFIX.md and PREFIX.csv); default `<out>/<pipeline>/sweep`.
    #[arg(long)]
    pub table: Option<PathBuf>,
    /// Check every variant and aggregate, show per variant what is cached
    /// and what would run; run nothing, write nothing.
    #[arg(long)]
    pub dry_run: bool,
    /// Plain stage lines even on a terminal.
    #[arg(long, conflicts_with = "quiet")]
    pub plain: bool,
    /// Only one line per variant, no stage lines.
    #[arg(long)]
    pub quiet: bool,
    /// Publish the `[publish]` documents even when variants failed (the report lists them);
    /// without it, a sweep with failed variants leaves the documents as they were.
    #[arg(long)]
    pub publish_failed: bool,
    /// Run only shard K of N (the variants whose index is K-1 modulo N) and write their
    /// record to `<out>/<pipeline>/shards/K-of-N.json`; no aggregate runs, nothing is
    /// published (docs/guide.md, "A sweep in shards").
    #[arg(long, value_name = "K/N", conflicts_with = "merge")]
    pub shard: Option<crate::shard::Shard>,
    /// Run no variant: check that these shard files (`--shard`) are the whole sweep as given,
    /// write its record from them, run the aggregates on it and publish.
    #[arg(long, value_name = "SHARD_FILE", num_args = 1.., conflicts_with = "dry_run")]
    pub merge: Vec<PathBuf>,
    #[command(flatten)]
    pub executor: ExecutorArgs,
    /// Sets parameter `device` (auto, cpu, gpu) on every stage that declares one.
    #[arg(long, value_name = "DEVICE")]
    pub device: Option<String>,
}

#[derive(clap::Args, Debug)]
pub struct GcArgs {
    /// Keep only the entries these pipelines currently resolve to (repeatable).
    /// A sweep keeps every variant, those its last record (`<out>/<pipeline>/sweep.json`)
    /// names included (a `--grid`/`--each` run's), and its aggregate stages as they read
    /// that record.
    #[arg(long = "keep", value_name = "PIPELINE")]
    pub keep: Vec<PathBuf>,
    /// Where sweeps wrote their records (as `fure sweep --out`).
    #[arg(long, default_value = "out")]
    pub out: PathBuf,
    /// Evict entries (not kept ones) until the cache fits: 500M, 10G, ...
    #[arg(long)]
    pub max_size: Option<String>,
}

#[derive(clap::Args, Debug)]
pub struct BenchArgs {
    pub pipeline: PathBuf,
    #[arg(long, default_value_t = 3)]
    pub repeat: usize,
    #[arg(long = "set", value_name = "STAGE.PARAM=VALUE")]
    pub sets: Vec<String>,
    #[arg(long, short)]
    pub jobs: Option<usize>,
    /// Output prefix (writes PREFIX.json and PREFIX.md); default `out/<pipeline>/bench`.
    #[arg(long)]
    pub output: Option<PathBuf>,
}

#[derive(clap::Args, Debug)]
pub struct StagesArgs {
    /// Show only this kind.
    pub kind: Option<String>,
}

#[derive(clap::Args, Debug)]
pub struct WorkerArgs {
    pub spec: PathBuf,
}

/// Where the stages that must run are computed.
#[derive(clap::Args, Debug, Clone)]
pub struct ExecutorArgs {
    /// `local` (this machine) or `slurm` (one batch job per stage that must
    /// run, on nodes sharing the cache; see docs/cluster.md).
    #[arg(long, value_enum, env = "FURE_EXECUTOR", default_value = "local")]
    pub executor: ExecutorKind,
    /// A file whose `[executor]` table sets partition, account, time, cpus,
    /// mem, sbatch flags (the pipeline's `[executor]` overrides it); default
    /// $FURE_EXECUTOR_CONFIG, else ~/.config/fure/config.toml if present.
    #[arg(long, value_name = "FILE")]
    pub executor_config: Option<PathBuf>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ExecutorKind {
    Local,
    Slurm,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum DagFormat {
    Text,
    Dot,
    Mermaid,
}

/// Exit status for a bad pipeline or bad usage.
const EXIT_USAGE: u8 = 2;
const EXIT_FAILED: u8 = 1;

/// Runs the command line with these stage kinds.
pub fn main_with(stages: Vec<Box<dyn Stage>>) -> ExitCode {
    install_panic_hook();
    let cli = Cli::parse();
    crate::signals::install();
    let engine = match Engine::new(stages) {
        Ok(e) => e,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(EXIT_USAGE);
        }
    };
    let result = dispatch(&engine, &cli);
    if let Some(sig) = crate::signals::received() {
        // Interrupted: the commands were stopped, their staging dirs removed.
        eprintln!("fure: interrupted by {}", crate::signals::name(sig));
        return ExitCode::from(128u8.saturating_add(sig as u8));
    }
    match result {
        Ok(code) => code,
        Err(Failure::Usage(msg)) => {
            eprintln!("{msg}");
            ExitCode::from(EXIT_USAGE)
        }
        Err(Failure::Failed(msg)) => {
            eprintln!("{msg}");
            ExitCode::from(EXIT_FAILED)
        }
    }
}

/// Panics inside stages are reported as stage failures by the engine: keep
/// their default message off the terminal.
fn install_panic_hook() {
    let default = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let in_stage = std::thread::current()
            .name()
            .map(|n| n.starts_with("fure-stage"))
            .unwrap_or(false);
        if !in_stage {
            default(info);
        }
    }));
}

enum Failure {
    Usage(String),
    Failed(String),
}

impl From<PipelineErrors> for Failure {
    fn from(e: PipelineErrors) -> Self {
        Failure::Usage(e.to_string())
    }
}

fn open_cache(dir: &Path, access: Access) -> Result<Cache, Failure> {
    Cache::open(dir, access).map_err(|e| Failure::Failed(format!("error: {e}")))
}

/// `--set STAGE.PARAM=VALUE` for every stage whose kind declares `param`,
/// before the user's own `--set`s (which so win); the engine gives the name
/// no meaning (`--device`).
fn param_sets(
    engine: &Engine,
    path: &Path,
    sets: &[String],
    param: &str,
    value: Option<&str>,
) -> Result<Vec<String>, Failure> {
    let Some(value) = value else {
        return Ok(sets.to_vec());
    };
    let p = engine.load(path, sets)?;
    let mut out: Vec<String> = p
        .stages
        .iter()
        .filter(|s| {
            let kind = s.kind.as_ref().and_then(|(k, _)| engine.registry.get(k));
            kind.is_some_and(|k| k.params().iter().any(|ps| ps.name == param))
        })
        .map(|s| format!("{}.{param}={value}", s.name))
        .collect();
    if out.is_empty() {
        eprintln!("note: --{param} {value}: no stage of this pipeline has a `{param}` parameter");
    }
    out.extend(sets.iter().cloned());
    Ok(out)
}

fn load_plan(
    engine: &Engine,
    path: &Path,
    sets: &[String],
    until: Option<&str>,
) -> Result<Plan, Failure> {
    let p = engine.load(path, sets)?;
    let plan = engine.plan(&p)?;
    match until {
        Some(u) => plan.until(u).map_err(|e| Failure::Usage(e.to_string())),
        None => Ok(plan),
    }
}

fn write_file(path: &Path, bytes: &[u8]) -> Result<(), Failure> {
    if let Some(p) = path.parent() {
        if !p.as_os_str().is_empty() {
            std::fs::create_dir_all(p)
                .map_err(|e| Failure::Failed(format!("error: {}: {e}", p.display())))?;
        }
    }
    std::fs::write(path, bytes)
        .map_err(|e| Failure::Failed(format!("error: {}: {e}", path.display())))
}

fn jobs_or_default(jobs: Option<usize>) -> Result<usize, Failure> {
    match jobs {
        Some(0) => Err(Failure::Usage("error: --jobs must be at least 1".into())),
        Some(j) => Ok(j),
        None => Ok(exec::available_cores()),
    }
}

/// The executor of a run or sweep (local for dry runs) and the default
/// `--jobs` that goes with it.
fn executor(
    args: &ExecutorArgs,
    pipeline: Option<&(fure_stage_api::Value, crate::pipeline::Loc)>,
    cache: &Cache,
    dry_run: bool,
) -> Result<(exec::Executor, Option<usize>), Failure> {
    use crate::slurm::{ExecutorConfig, Slurm};
    if args.executor == ExecutorKind::Local || dry_run {
        return Ok((exec::Executor::Local, None));
    }
    let user = match ExecutorConfig::user_file(args.executor_config.as_deref()) {
        Some(f) => {
            ExecutorConfig::from_file(&f).map_err(|e| Failure::Usage(format!("error: {e}")))?
        }
        None => ExecutorConfig::default(),
    };
    let config = match pipeline {
        Some((v, loc)) => user.overlaid(
            &ExecutorConfig::from_value(v, &loc.to_string())
                .map_err(|e| Failure::Usage(format!("error: {e}")))?,
        ),
        None => user,
    };
    let jobs = config.max_jobs();
    let slurm = Slurm::new(config, cache.root(), true)
        .map_err(|e| Failure::Failed(format!("error: --executor slurm: {e}")))?;
    Ok((
        exec::Executor::Slurm(std::sync::Arc::new(slurm)),
        Some(jobs),
    ))
}

fn dispatch(engine: &Engine, cli: &Cli) -> Result<ExitCode, Failure> {
    match &cli.command {
        Command::Run(a) => cmd_run(engine, &cli.cache, a),
        Command::Status(a) => cmd_status(engine, &cli.cache, a),
        Command::Dag(a) => {
            let plan = load_plan(engine, &a.pipeline, &a.sets, None)?;
            print!("{}", dag(&plan, a.format));
            Ok(ExitCode::SUCCESS)
        }
        Command::Sweep(a) => cmd_sweep(engine, &cli.cache, a),
        Command::Gc(a) => cmd_gc(engine, &cli.cache, a),
        Command::Verify => cmd_verify(&cli.cache),
        Command::Bench(a) => cmd_bench(engine, a),
        Command::Worker(a) => cmd_worker(engine, &cli.cache, &a.spec),
        Command::Stages(a) => cmd_stages(engine, a.kind.as_deref()),
    }
}

/// `--jobs`, else the remote executor's default, else the number of cores.
fn jobs_for(jobs: Option<usize>, remote_jobs: Option<usize>) -> Result<usize, Failure> {
    match (jobs, remote_jobs) {
        (None, Some(j)) => Ok(j),
        _ => jobs_or_default(jobs),
    }
}

/// Options of a run that only looks (`status`, `gc --keep`).
fn inspect_options() -> RunOptions {
    RunOptions {
        dry_run: true,
        out_root: None,
        ui: UiMode::Quiet,
        ..RunOptions::default()
    }
}

fn exit_code(ok: bool) -> ExitCode {
    if ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(EXIT_FAILED)
    }
}

fn cmd_run(engine: &Engine, cache_dir: &Path, a: &RunArgs) -> Result<ExitCode, Failure> {
    let sets = &param_sets(engine, &a.pipeline, &a.sets, "device", a.device.as_deref())?;
    let t0 = std::time::Instant::now();
    let plan = load_plan(engine, &a.pipeline, sets, a.until.as_deref())?;
    let t_plan = t0.elapsed();
    let cache = open_cache(cache_dir, Access::Shared)?;
    let (executor, remote_jobs) = if a.executor.executor == ExecutorKind::Local {
        (exec::Executor::Local, None)
    } else {
        let p = engine.load(&a.pipeline, sets)?;
        executor(&a.executor, p.executor.as_ref(), &cache, a.dry_run)?
    };
    let opts = RunOptions {
        jobs: jobs_for(a.jobs, remote_jobs)?,
        cores: exec::available_cores(),
        out_root: Some(a.out.clone()),
        dry_run: a.dry_run,
        ui: if a.plain {
            UiMode::Plain
        } else {
            UiMode::detect()
        },
        keep_going: a.keep_going,
        executor,
    };
    let rep = exec::run(&plan, &cache, &opts);
    let json = serde_json::to_vec_pretty(&rep).unwrap_or_default();
    if !a.dry_run {
        cache.save_run_report(&plan.name, &json);
    }
    if let Some(path) = &a.report {
        write_file(path, &json)?;
    }
    print_summary(&rep, a.dry_run, &a.out);
    if std::env::var_os("FURE_TIMING").is_some() {
        eprintln!(
            "timing: load+plan {:.1} ms, run {:.1} ms, total {:.1} ms",
            t_plan.as_secs_f64() * 1e3,
            rep.seconds * 1e3,
            t0.elapsed().as_secs_f64() * 1e3
        );
    }
    Ok(exit_code(rep.ok()))
}

fn cmd_status(engine: &Engine, cache_dir: &Path, a: &StatusArgs) -> Result<ExitCode, Failure> {
    let plan = load_plan(engine, &a.pipeline, &a.sets, a.until.as_deref())?;
    let cache = open_cache(cache_dir, Access::Shared)?;
    let rep = exec::run(&plan, &cache, &inspect_options());
    if a.json {
        println!("{}", serde_json::to_string_pretty(&rep).unwrap_or_default());
    } else {
        let w = rep.stages.iter().map(|s| s.name.len()).max().unwrap_or(0);
        for s in &rep.stages {
            let (state, reason) = match s.status {
                Status::Cached => (
                    "cached",
                    if s.reason.is_empty() {
                        "up to date".to_string()
                    } else {
                        s.reason.clone()
                    },
                ),
                Status::WillRun => ("will run", s.reason.clone()),
                Status::Failed => ("error", s.error.clone().unwrap_or_default()),
                _ => ("blocked", s.reason.clone()),
            };
            println!("{:<w$}  {:<8}  {}", s.name, state, reason, w = w);
        }
        println!(
            "{}: {} cached, {} will run",
            rep.pipeline,
            rep.count(Status::Cached),
            rep.count(Status::WillRun)
        );
    }
    Ok(exit_code(rep.count(Status::Failed) == 0))
}

/// `--grid`/`--each` values: STAGE.PARAM=V1,V2,...
fn axis_list(
    opt: &str,
    list: &[String],
) -> Result<Vec<(String, Vec<fure_stage_api::Value>)>, Failure> {
    list.iter()
        .map(|g| {
            let (k, v) = g.split_once('=').ok_or_else(|| {
                Failure::Usage(format!(
                    "error: {opt} `{g}`: expected STAGE.PARAM=V1,V2,..."
                ))
            })?;
            Ok((k.trim().to_string(), parse_cli_list(v)))
        })
        .collect()
}

fn cmd_sweep(engine: &Engine, cache_dir: &Path, a: &SweepArgs) -> Result<ExitCode, Failure> {
    let sets = &param_sets(engine, &a.pipeline, &a.sets, "device", a.device.as_deref())?;
    let p = engine.load(&a.pipeline, sets)?;
    let axes = sweep::Axes::new(
        &p,
        &axis_list("--grid", &a.grids)?,
        &axis_list("--each", &a.eaches)?,
    );
    let mut variants = axes.variants();
    crate::publish::check(&p).map_err(|e| Failure::Usage(format!("error: {e}")))?;
    let cache = open_cache(cache_dir, Access::Shared)?;
    // A shard's record, and a merge, carry the whole sweep's fingerprint (crate::shard).
    let fingerprint = match (a.shard.is_some() || !a.merge.is_empty()) && !a.dry_run {
        true => Some(sweep_fingerprint(engine, &p, &variants, &cache)?),
        false => None,
    };
    if !a.merge.is_empty() {
        let fingerprint = fingerprint.unwrap_or_default();
        return merge_shards(engine, &p, &axes, &variants, &fingerprint, &cache, a);
    }
    let all = variants.len();
    if let Some(shard) = a.shard {
        variants.retain(|v| shard.holds(v.index));
        println!(
            "sweep {}: shard {shard}: {} of {all} variants",
            p.name,
            variants.len()
        );
    }
    let (executor, remote_jobs) = executor(&a.executor, p.executor.as_ref(), &cache, a.dry_run)?;
    // Stage lines show progress inside a long variant; a remote executor runs
    // the variants at once, whose interleaved lines would not say which is which.
    let ui = if a.quiet || a.dry_run || executor.is_remote() {
        UiMode::Quiet
    } else if a.plain {
        UiMode::Plain
    } else {
        UiMode::detect()
    };
    let opts = RunOptions {
        jobs: jobs_for(a.jobs, remote_jobs)?,
        cores: exec::available_cores(),
        out_root: if a.dry_run { None } else { Some(a.out.clone()) },
        dry_run: a.dry_run,
        ui,
        keep_going: true,
        executor,
    };
    let total = variants.len();
    println!("sweep {}: {total} variants", p.name);
    let (started, mut done, remote) = (std::time::Instant::now(), 0, opts.executor.is_remote());
    // The cache's disk: what the variants that ran used of it, to say early when the rest
    // would not fit (a sweep stopped on a full disk hours in loses the time, not the work).
    let free_at_start = cache.free_bytes();
    let (mut ran, mut warned_disk) = (0usize, false);
    let rows = sweep::run_sweep(
        engine,
        &p,
        &variants,
        &cache,
        &opts,
        &mut |v| {
            if ui != UiMode::Quiet {
                println!(
                    "starting variant {} ({} of {total}): {}",
                    v.index,
                    v.index + 1,
                    sweep::describe(v)
                );
            }
        },
        &mut |row| {
            print_variant(row, a.dry_run, &cache);
            done += 1;
            ran += (row.report.count(Status::Ran) > 0) as usize;
            // A remote executor runs the variants at once, so their pace says nothing.
            if !a.dry_run && !remote {
                if let Some(line) = pace(started.elapsed().as_secs_f64(), done, total) {
                    println!("{line}");
                }
                let forecast = free_at_start.zip(cache.free_bytes()).and_then(|(s, now)| {
                    disk_forecast(s.saturating_sub(now), ran, total - done, now)
                });
                if let (Some(line), false) = (forecast, warned_disk) {
                    eprintln!("{line}");
                    warned_disk = true;
                }
            }
        },
    )?;
    if !opts.executor.is_remote() && sweep::stopped_on_full_disk(&rows) {
        // As an interrupted sweep: no record, no aggregate, nothing published (the last
        // variant too: the record and the aggregates would write to the same full disk). A
        // remote executor ran every variant at once: nothing stopped, its record is written.
        let complete = complete_variants(&rows);
        let later = total - rows.len();
        let not_started = if later > 0 {
            format!(", {later} not started (each would fail on it too)")
        } else {
            String::new()
        };
        eprintln!(
            "sweep {}: stopped, the disk is full (variant {} failed on it); {complete} of \
             {total} variants complete (cached){not_started}, the previous record, tables and \
             published documents kept",
            p.name,
            rows.last().map_or(0, |r| r.variant.index),
        );
        eprintln!("{DISK_FULL_HINT}");
        return Ok(ExitCode::from(EXIT_FAILED));
    }
    if crate::signals::received().is_some() {
        // An interrupted sweep writes no record and runs no aggregate: the last complete
        // sweep's tables, record and published documents stay as they were. What finished
        // is cached, so the same command resumes.
        let complete = complete_variants(&rows);
        eprintln!(
            "sweep {}: interrupted; {complete} of {total} variants complete (cached), the \
             previous record, tables and published documents kept; rerun the same command to \
             resume",
            p.name
        );
        return Ok(ExitCode::from(EXIT_FAILED));
    }
    if a.dry_run {
        if !p.aggregates.is_empty() {
            println!(
                "aggregates (run after the variants): {}",
                p.aggregates
                    .iter()
                    .map(|a| a.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
        return Ok(ExitCode::SUCCESS);
    }
    let shard = a.shard.zip(fingerprint.as_deref());
    let record_path = write_sweep_results(&p, &axes, &rows, a, shard, all)?;
    if let Some((shard, _)) = shard {
        println!(
            "shard {shard} written; no aggregate runs and nothing is published until every shard \
             is merged: fure sweep {} --merge <the {} shard files>",
            a.pipeline.display(),
            shard.n
        );
        return Ok(ExitCode::SUCCESS);
    }
    // Aggregates read the record through an absolute path (it is not
    // part of any key: only its content is).
    let abs = std::path::absolute(&record_path)
        .map_err(|e| Failure::Failed(format!("error: {}: {e}", record_path.display())))?;
    let failed = rows
        .iter()
        .filter(|r| r.status == sweep::VariantStatus::Failed)
        .count();
    let withheld = withheld(a, failed, rows.len());
    match sweep::run_aggregates(engine, &p, &abs, &cache, &opts)? {
        Some(rep) => report_aggregates(&p, &rep, &cache, &a.out, withheld.as_deref(), None),
        None => Ok(ExitCode::SUCCESS),
    }
}

/// This command as typed, the program named `fure`: the published documents' stamp.
fn command_line() -> String {
    let words: Vec<String> = std::env::args()
        .enumerate()
        .map(|(i, a)| if i == 0 { "fure".into() } else { a })
        .collect();
    words.join(" ")
}

/// Why a sweep's documents are not published, if they are not. They describe the pipeline as
/// declared: a sweep narrowed or changed on the command line (`--set`, `--grid`, `--each`: a
/// study, a dev-only rerun) keeps its report under `out`. A sweep some of whose variants failed
/// (a full disk, a killed job, a broken scene) would replace a complete report with a partial
/// one; it is published only when asked for.
fn withheld(a: &SweepArgs, failed: usize, total: usize) -> Option<String> {
    let changed_by: Vec<&str> = [
        ("--grid", !a.grids.is_empty()),
        ("--each", !a.eaches.is_empty()),
        ("--set", !a.sets.is_empty()),
    ]
    .into_iter()
    .filter_map(|(flag, used)| used.then_some(flag))
    .collect();
    if !changed_by.is_empty() {
        Some(format!("{} changed the sweep", changed_by.join(", ")))
    } else if failed > 0 && !a.publish_failed {
        Some(format!(
            "{failed} of {total} variants failed (--publish-failed publishes a report with failures)"
        ))
    } else {
        None
    }
}

/// The fingerprint of every variant of the sweep (crate::shard).
fn sweep_fingerprint(
    engine: &Engine,
    p: &crate::pipeline::Pipeline,
    variants: &[sweep::Variant],
    cache: &Cache,
) -> Result<String, Failure> {
    let mut plans = Vec::with_capacity(variants.len());
    for v in variants {
        plans.push(engine.plan(&sweep::variant_pipeline(p, v)?)?);
    }
    crate::shard::fingerprint(&plans, cache).map_err(|e| Failure::Failed(format!("error: {e}")))
}

/// `fure sweep --merge`: the shards' record in place of the variants' runs, then the
/// aggregates and `[publish]` as after a whole sweep.
fn merge_shards(
    engine: &Engine,
    p: &crate::pipeline::Pipeline,
    axes: &sweep::Axes,
    variants: &[sweep::Variant],
    fingerprint: &str,
    cache: &Cache,
    a: &SweepArgs,
) -> Result<ExitCode, Failure> {
    let expected: Vec<serde_json::Value> = variants.iter().map(sweep::settings_json).collect();
    let files: Vec<&Path> = a.merge.iter().map(PathBuf::as_path).collect();
    let merged = crate::shard::merge(&files, &p.name, &expected, fingerprint)
        .map_err(|e| Failure::Usage(format!("error: {e}")))?;
    let failed = merged
        .variants
        .iter()
        .filter(|v| v["status"] == "failed")
        .count();
    let record = sweep::record_of(&p.name, axes, merged.variants);
    let record_path = a.out.join(&p.name).join("sweep.json");
    sweep::write_if_changed(&record_path, &sweep::record_bytes(&record))
        .map_err(|e| Failure::Failed(format!("error: {}: {e}", record_path.display())))?;
    println!(
        "sweep {}: {} variants from {} shards, {failed} failed; record: {}",
        p.name,
        variants.len(),
        merged.origins.len(),
        record_path.display()
    );
    let abs = std::path::absolute(&record_path)
        .map_err(|e| Failure::Failed(format!("error: {}: {e}", record_path.display())))?;
    let withheld = withheld(a, failed, variants.len());
    let opts = RunOptions {
        jobs: jobs_for(a.jobs, None)?,
        cores: exec::available_cores(),
        out_root: Some(a.out.clone()),
        dry_run: false,
        ui: UiMode::Quiet,
        keep_going: true,
        executor: exec::Executor::Local,
    };
    let stamp = crate::shard::provenance(&merged.origins);
    match sweep::run_aggregates(engine, p, &abs, cache, &opts)? {
        Some(rep) => report_aggregates(p, &rep, cache, &a.out, withheld.as_deref(), Some(&stamp)),
        None => Ok(ExitCode::SUCCESS),
    }
}

/// Variants that finished without a failure (their entries are cached): what a stopped sweep
/// keeps.
fn complete_variants(rows: &[sweep::Row]) -> usize {
    rows.iter()
        .filter(|r| r.status != sweep::VariantStatus::Failed)
        .count()
}

/// After `done` of `total` variants in `elapsed` seconds, how long the rest would take at
/// that pace (cached variants count as done, so a resumed sweep's first estimates run
/// short); `None` once every variant is done.
fn pace(elapsed: f64, done: usize, total: usize) -> Option<String> {
    if done == 0 || done >= total {
        return None;
    }
    let left = elapsed / done as f64 * (total - done) as f64;
    Some(format!(
        "sweep: {done} of {total} variants done in {}, about {} left at this pace",
        clock(elapsed),
        clock(left)
    ))
}

/// A warning when the `left` variants, each using as much of the cache's disk as the `ran`
/// variants that ran stages used on average (`used` bytes together), would need more than the
/// `free` bytes left; `None` when they fit or nothing is known yet. Cached variants use
/// nothing, so a resumed sweep's warning is an upper bound.
fn disk_forecast(used: u64, ran: usize, left: usize, free: u64) -> Option<String> {
    if ran == 0 || left == 0 || used == 0 {
        return None;
    }
    let need = used as f64 / ran as f64 * left as f64;
    (need > free as f64).then(|| {
        let ran = match ran {
            1 => "the variant that ran".to_string(),
            n => format!("the {n} variants that ran"),
        };
        let left = match left {
            1 => "the one left".to_string(),
            n => format!("the {n} left"),
        };
        format!(
            "warning: {ran} used {} of the cache's disk; {left} \
             would need about {} at that rate and {} is free, so the sweep may stop on a full \
             disk (interrupt it, free space with `fure gc --keep PIPELINE` or `fure gc \
             --max-size SIZE`, and rerun: what finished is cached)",
            byte_size(used),
            byte_size(need as u64),
            byte_size(free)
        )
    })
}

/// Seconds as `42 s`, `7 min` or `1 h 38 min`, the precision a sweep's estimate has.
fn clock(seconds: f64) -> String {
    let s = seconds.max(0.0).round() as u64;
    let m = (s + 30) / 60;
    if s < 90 {
        format!("{s} s")
    } else if m < 60 {
        format!("{m} min")
    } else {
        format!("{} h {} min", m / 60, m % 60)
    }
}

/// One line per finished (or, dry run, inspected) sweep variant; the
/// variant's run report goes to the cache.
fn print_variant(row: &sweep::Row, dry_run: bool, cache: &Cache) {
    if dry_run {
        println!(
            "variant {} ({}){}: {} cached, {} will run",
            row.variant.index,
            sweep::describe(&row.variant),
            row.variant
                .varied
                .as_ref()
                .map(|k| format!(" varying {k}"))
                .unwrap_or_default(),
            row.report.count(Status::Cached),
            row.report.count(Status::WillRun)
        );
        return;
    }
    println!(
        "variant {} ({}): {} ran, {} cached, {} failed, {:.2}s: {}{}",
        row.variant.index,
        sweep::describe(&row.variant),
        row.report.count(Status::Ran),
        row.report.count(Status::Cached),
        row.report.count(Status::Failed),
        row.report.seconds,
        row.status.as_str(),
        if row.reason.is_empty() {
            String::new()
        } else {
            format!(" ({})", row.reason)
        }
    );
    if let Ok(json) = serde_json::to_vec_pretty(&row.report) {
        cache.save_run_report(&row.name, &json);
    }
}

/// Writes the sweep's tables and its record; returns the record's path.
fn write_sweep_results(
    p: &crate::pipeline::Pipeline,
    axes: &sweep::Axes,
    rows: &[sweep::Row],
    a: &SweepArgs,
    shard: Option<(crate::shard::Shard, &str)>,
    all: usize,
) -> Result<PathBuf, Failure> {
    // A shard's table and record go beside the others', named after the shard.
    let stem = match shard {
        Some((s, _)) => Path::new("shards").join(format!("{}-of-{}", s.k, s.n)),
        None => PathBuf::from("sweep"),
    };
    let prefix = a
        .table
        .clone()
        .unwrap_or_else(|| a.out.join(&p.name).join(&stem));
    let md = sweep::markdown(rows);
    write_file(&prefix.with_extension("md"), md.as_bytes())?;
    write_file(&prefix.with_extension("csv"), sweep::csv(rows).as_bytes())?;
    println!("\n{md}");
    println!(
        "table: {} and {}",
        prefix.with_extension("md").display(),
        prefix.with_extension("csv").display()
    );
    let record_path = a.out.join(&p.name).join(stem.with_extension("json"));
    let mut record = sweep::record(&p.name, axes, rows);
    if let Some((s, fingerprint)) = shard {
        let repo = p.file.parent().unwrap_or(Path::new("."));
        let origin = crate::publish::Origin::here(repo, &command_line());
        if origin.dirty {
            eprintln!(
                "warning: the tree has uncommitted changes: `--merge` refuses this shard (nothing \
                 could say what it ran); rerun it from a clean checkout"
            );
        }
        record = crate::shard::shard_record(record, s, all, fingerprint, &origin);
    }
    sweep::write_if_changed(&record_path, &sweep::record_bytes(&record))
        .map_err(|e| Failure::Failed(format!("error: {}: {e}", record_path.display())))?;
    println!("record: {}", record_path.display());
    let failed = rows
        .iter()
        .filter(|r| r.status == sweep::VariantStatus::Failed)
        .count();
    let degraded = rows
        .iter()
        .filter(|r| r.status == sweep::VariantStatus::Degraded)
        .count();
    println!(
        "{failed} of {} variants failed, {degraded} degraded",
        rows.len()
    );
    if let Some(hint) = disk_full_hint(rows.iter().map(|r| r.reason.as_str())) {
        eprintln!("{hint}");
    }
    let (busy, max) = sweep::busy_stage_runs(rows);
    if busy > 0 {
        println!(
            "note: {busy} stage run(s) were measured beside other work (up to {max:.1} cores used \
             by others on average; `costs.STAGE.other_load` in the record): their seconds are longer than \
             the machine alone gives"
        );
    }
    Ok(record_path)
}

/// Prints the aggregate stages' outcome and, when all succeeded and nothing
/// `withheld` them (the reason: a flag changed the sweep, variants failed),
/// publishes the pipeline's `[publish]` files.
fn report_aggregates(
    p: &crate::pipeline::Pipeline,
    rep: &RunReport,
    cache: &Cache,
    out: &Path,
    withheld: Option<&str>,
    shards: Option<&str>,
) -> Result<ExitCode, Failure> {
    if let Ok(json) = serde_json::to_vec_pretty(rep) {
        cache.save_run_report(&rep.pipeline, &json);
    }
    for s in &rep.stages {
        println!(
            "aggregate {}: {}{}",
            s.name,
            match s.status {
                Status::Ran => "ran",
                Status::Cached => "cached",
                Status::Failed => "failed",
                _ => "skipped",
            },
            match s.status {
                Status::Ran | Status::Cached =>
                    format!("; outputs in {}", out.join(&p.name).join(&s.name).display()),
                _ => String::new(),
            }
        );
    }
    if !rep.ok() {
        for s in rep.stages.iter().filter(|s| s.status == Status::Failed) {
            eprintln!(
                "error: aggregate stage `{}` ({}) failed: {}",
                s.name,
                s.kind,
                s.error.clone().unwrap_or_default()
            );
        }
        return Ok(ExitCode::from(EXIT_FAILED));
    }
    if let (false, Some(why)) = (p.publish.is_empty(), withheld) {
        println!(
            "not published: {why}; the documents of [publish] describe {} as declared and are \
             left as they were; the report is in {}",
            p.file.display(),
            out.join(&p.name).display()
        );
    } else if !p.publish.is_empty() {
        let repo = p.file.parent().unwrap_or(Path::new("."));
        let mut stamp = crate::publish::provenance(&command_line(), repo);
        if let Some(shards) = shards {
            stamp = format!("{stamp} {shards}");
        }
        let written = crate::publish::publish(p, rep, &stamp)
            .map_err(|e| Failure::Failed(format!("error: {e}")))?;
        for w in written {
            println!("published {}", w.display());
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// The plans `gc --keep PIPELINE` keeps: the pipeline itself, and for a
/// sweep every variant (as `fure sweep` runs it with no `--grid`/`--each`),
/// every variant of the last sweep's record under `out` (so an ablation run
/// with `--grid` keeps its extra points too), and the aggregate stages over
/// that record.
fn kept_plans(engine: &Engine, path: &Path, out: &Path) -> Result<Vec<Plan>, Failure> {
    let p = engine.load(path, &[])?;
    let mut plans = vec![engine.plan(&p)?];
    if p.sweep.is_empty() && p.sweep_each.is_empty() {
        return Ok(plans);
    }
    let mut variants = sweep::grid(&p, &[]);
    let record = out.join(&p.name).join("sweep.json");
    let recorded = if record.is_file() {
        let bad = |e: String| Failure::Failed(format!("error: {}: {e}", record.display()));
        let bytes = std::fs::read(&record).map_err(|e| bad(e.to_string()))?;
        let json: serde_json::Value =
            serde_json::from_slice(&bytes).map_err(|e| bad(e.to_string()))?;
        variants.extend(sweep::Axes::from_record(&json).map_err(bad)?.variants());
        Some(std::path::absolute(&record).map_err(|e| bad(e.to_string()))?)
    } else {
        None
    };
    for v in variants {
        plans.push(engine.plan(&sweep::variant_pipeline(&p, &v)?)?);
    }
    if let Some(abs) = recorded {
        plans.extend(sweep::plan_aggregates(engine, &p, &abs)?);
    }
    Ok(plans)
}

fn cmd_gc(engine: &Engine, cache_dir: &Path, a: &GcArgs) -> Result<ExitCode, Failure> {
    let max_size = match &a.max_size {
        Some(s) => Some(
            cache::parse_size(s).map_err(|e| Failure::Usage(format!("error: --max-size {e}")))?,
        ),
        None => None,
    };
    let keep_keys = if a.keep.is_empty() {
        None
    } else {
        // Keys the kept pipelines resolve to now (as far as the cache can tell).
        let mut keys = BTreeSet::new();
        let cache = open_cache(cache_dir, Access::Shared)?;
        for k in &a.keep {
            for plan in kept_plans(engine, k, &a.out)? {
                let rep = exec::run(&plan, &cache, &inspect_options());
                keys.extend(
                    rep.stages
                        .into_iter()
                        .filter(|s| s.status == Status::Cached)
                        .map(|s| s.key),
                );
            }
        }
        drop(cache);
        Some(keys)
    };
    let cache = open_cache(cache_dir, Access::Exclusive)?;
    let rep = cache.gc(&GcOptions {
        keep: keep_keys,
        max_size,
    });
    println!(
        "gc: kept {} entries ({}), removed {} entries and {} objects ({} freed), {} stale staging dirs",
        rep.entries_kept,
        byte_size(rep.bytes_kept),
        rep.entries_removed,
        rep.objects_removed,
        byte_size(rep.bytes_freed),
        rep.tmp_removed
    );
    if rep.bytes_linked_outside > 0 {
        println!(
            "gc: {} of the removed objects stay on disk: outputs outside the cache (out/ folders \
             of earlier runs) are hard links to them; delete those outputs to free the space",
            byte_size(rep.bytes_linked_outside)
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// A size for people: MiB from one MiB up (gc's sizes are usually that), else KiB or bytes, so
/// a few kilobytes do not read as "0.0 MiB".
fn byte_size(bytes: u64) -> String {
    const KIB: u64 = 1024;
    const MIB: u64 = 1024 * 1024;
    if bytes >= MIB {
        format!("{:.1} MiB", bytes as f64 / MIB as f64)
    } else if bytes >= KIB {
        format!("{:.1} KiB", bytes as f64 / KIB as f64)
    } else {
        format!("{bytes} bytes")
    }
}

fn cmd_verify(cache_dir: &Path) -> Result<ExitCode, Failure> {
    let cache = open_cache(cache_dir, Access::Exclusive)?;
    let rep = cache.verify();
    for o in &rep.corrupted_objects {
        println!("corrupted object {o} (removed)");
    }
    for e in &rep.dropped_entries {
        println!("dropped entry {e}");
    }
    for m in &rep.broken_manifests {
        println!("invalid manifest: {m} (removed)");
    }
    for v in &rep.violations {
        println!("not fure's: {v}");
    }
    println!(
        "verify: {} objects, {} entries checked; {} corrupted objects, {} entries dropped, {} invalid manifests, {} stray paths{}",
        rep.objects_checked,
        rep.entries_checked,
        rep.corrupted_objects.len(),
        rep.dropped_entries.len(),
        rep.broken_manifests.len(),
        rep.violations.len(),
        if rep.clean() { "; clean" } else { "" }
    );
    Ok(exit_code(rep.clean()))
}

fn cmd_bench(engine: &Engine, a: &BenchArgs) -> Result<ExitCode, Failure> {
    let plan = load_plan(engine, &a.pipeline, &a.sets, None)?;
    let opts = RunOptions {
        jobs: jobs_or_default(a.jobs)?,
        ui: UiMode::Quiet,
        ..RunOptions::default()
    };
    let repeat = a.repeat;
    let rep = bench::bench(&plan, repeat, &opts, &mut |r, s| {
        println!("run {}/{}: {:.3}s", r + 1, repeat, s);
    })
    .map_err(|e| Failure::Failed(format!("error: {e}")))?;
    let prefix = a
        .output
        .clone()
        .unwrap_or_else(|| Path::new("out").join(&plan.name).join("bench"));
    let md = bench::markdown(&rep);
    write_file(
        &prefix.with_extension("json"),
        &serde_json::to_vec_pretty(&rep).unwrap_or_default(),
    )?;
    write_file(&prefix.with_extension("md"), md.as_bytes())?;
    println!("\n{md}");
    println!(
        "written: {} and {}",
        prefix.with_extension("json").display(),
        prefix.with_extension("md").display()
    );
    Ok(ExitCode::SUCCESS)
}

fn cmd_worker(engine: &Engine, cache_dir: &Path, spec: &Path) -> Result<ExitCode, Failure> {
    let result_path = crate::slurm::result_path(spec);
    let host = cache::host_name();
    let outcome = (|| -> Result<bool, String> {
        let s = crate::slurm::read_spec(spec).map_err(|e| e.to_string())?;
        println!(
            "fure worker: pipeline {}, stage {} ({}), key {}, on {host}",
            s.pipeline,
            s.stage,
            s.kind,
            cache::short(&s.key)
        );
        let cache = Cache::open(cache_dir, Access::Shared).map_err(|e| e.to_string())?;
        let ui = crate::ui::Ui::new(UiMode::Plain);
        crate::slurm::worker(&engine.registry, &cache, &s, &ui).map_err(|e| e.to_string())
    })();
    let result = crate::slurm::JobResult {
        ok: outcome.is_ok(),
        computed: outcome.as_ref().is_ok_and(|c| *c),
        error: outcome.as_ref().err().cloned(),
        host,
    };
    crate::slurm::write_result(&result_path, &result)
        .map_err(|e| Failure::Failed(format!("error: {}: {e}", result_path.display())))?;
    match outcome {
        Ok(computed) => {
            println!(
                "fure worker: {}",
                if computed {
                    "computed and stored"
                } else {
                    "another run had stored it"
                }
            );
            Ok(ExitCode::SUCCESS)
        }
        Err(e) => Err(Failure::Failed(format!("error: {e}"))),
    }
}

fn cmd_stages(engine: &Engine, kind: Option<&str>) -> Result<ExitCode, Failure> {
    let mut found = false;
    for s in engine.registry.iter() {
        if kind.map(|k| k != s.kind()).unwrap_or(false) {
            continue;
        }
        found = true;
        print!("{}", describe_kind(s.as_ref()));
    }
    if !found {
        return Err(Failure::Usage(format!(
            "error: no stage kind `{}`",
            kind.unwrap_or_default()
        )));
    }
    Ok(ExitCode::SUCCESS)
}

fn print_summary(rep: &RunReport, dry_run: bool, out: &Path) {
    if dry_run {
        println!(
            "{} (dry run): {} cached, {} will run",
            rep.pipeline,
            rep.count(Status::Cached),
            rep.count(Status::WillRun)
        );
        return;
    }
    println!(
        "{}: {} ran, {} cached, {} failed, {} skipped in {:.2}s; outputs in {}",
        rep.pipeline,
        rep.count(Status::Ran),
        rep.count(Status::Cached),
        rep.count(Status::Failed),
        rep.count(Status::Skipped),
        rep.seconds,
        out.join(&rep.pipeline).display()
    );
    for s in rep.stages.iter().filter(|s| s.status == Status::Failed) {
        eprintln!(
            "error: stage `{}` ({}) failed: {}",
            s.name,
            s.kind,
            s.error.clone().unwrap_or_default()
        );
    }
    if let Some(hint) = disk_full_hint(rep.stages.iter().filter_map(|s| s.error.as_deref())) {
        eprintln!("{hint}");
    }
}

/// What to do when a failure says the disk is full (ENOSPC), or `None`.
fn disk_full_hint<'a>(mut errors: impl Iterator<Item = &'a str>) -> Option<&'static str> {
    errors.any(exec::is_disk_full).then_some(DISK_FULL_HINT)
}

const DISK_FULL_HINT: &str = "hint: the disk is full. `fure gc --keep PIPELINE` (repeatable) \
     removes the cache entries those pipelines no longer resolve to, `fure gc --max-size 20G` \
     evicts the rest down to a size; what finished is cached, and the same command resumes.";

/// A kind's documentation for `fure stages`.
pub fn describe_kind(s: &dyn Stage) -> String {
    use std::fmt::Write as _;
    let mut o = String::new();
    let _ = writeln!(o, "{} (version {})", s.kind(), s.version());
    let _ = writeln!(o, "  {}", s.doc());
    let specs = s.params();
    if !specs.is_empty() {
        let _ = writeln!(o, "  parameters:");
        for p in &specs {
            let mut extra = String::new();
            match &p.default {
                Some(d) => {
                    let _ = write!(extra, " = {}", show(d));
                }
                None if p.optional => extra.push_str(" (optional)"),
                None => extra.push_str(" (required)"),
            }
            if p.min.is_some() || p.max.is_some() {
                let _ = write!(
                    extra,
                    " in {}{}, {}]",
                    if p.min_exclusive { "(" } else { "[" },
                    p.min
                        .map(|x| x.to_string())
                        .unwrap_or_else(|| "-inf".into()),
                    p.max.map(|x| x.to_string()).unwrap_or_else(|| "inf".into())
                );
            }
            if !p.choices.is_empty() {
                let _ = write!(extra, " one of {}", p.choices.join("|"));
            }
            let _ = writeln!(o, "    {}: {}{} -- {}", p.name, p.ty.name(), extra, p.doc);
        }
    }
    let defaults = fure_stage_api::Params(
        specs
            .iter()
            .filter_map(|p| p.default.clone().map(|d| (p.name.to_string(), d)))
            .collect(),
    );
    let port = |p: &fure_stage_api::PortSpec| {
        let what = match p.kind {
            PortKind::Dir => "directory".to_string(),
            PortKind::File { ext: "" } => "file".to_string(),
            PortKind::File { ext } => format!(".{ext}"),
        };
        format!(
            "{} ({what}{}) -- {}",
            p.name,
            if p.required { "" } else { ", optional" },
            p.doc
        )
    };
    let ins = s.inputs(&defaults);
    if !ins.is_empty() {
        let _ = writeln!(o, "  inputs:");
        for p in &ins {
            let _ = writeln!(o, "    {}", port(p));
        }
    }
    let outs = s.outputs(&defaults);
    if !outs.is_empty() {
        let _ = writeln!(o, "  outputs:");
        for p in &outs {
            let _ = writeln!(o, "    {}", port(p));
        }
    }
    o.push('\n');
    o
}

/// The stage graph as text, Graphviz dot or Mermaid.
pub fn dag(plan: &Plan, format: DagFormat) -> String {
    use std::fmt::Write as _;
    let mut o = String::new();
    match format {
        DagFormat::Text => {
            let _ = writeln!(o, "pipeline {} ({} stages)", plan.name, plan.stages.len());
            for s in &plan.stages {
                let _ = writeln!(o, "{} [{}]", s.name, s.kind);
                for i in &s.inputs {
                    let _ = writeln!(o, "  {} <- {}", i.port, plan.source_label(&i.source));
                }
                let outs: Vec<String> = s.outputs.iter().map(|p| p.file_name()).collect();
                let _ = writeln!(o, "  -> {}", outs.join(", "));
            }
        }
        DagFormat::Dot => {
            let _ = writeln!(o, "digraph \"{}\" {{\n  rankdir=LR;", plan.name);
            for s in &plan.stages {
                let _ = writeln!(
                    o,
                    "  \"{}\" [shape=box, label=\"{}\\n{}\"];",
                    s.name, s.name, s.kind
                );
            }
            for s in &plan.stages {
                for i in &s.inputs {
                    match &i.source {
                        Source::Upstream { stage, port } => {
                            let _ = writeln!(
                                o,
                                "  \"{}\" -> \"{}\" [label=\"{} -> {}\"];",
                                plan.stages[*stage].name, s.name, port, i.port
                            );
                        }
                        Source::Path { written, .. } => {
                            let _ = writeln!(
                                o,
                                "  \"file:{written}\" [shape=note, label=\"{written}\"];"
                            );
                            let _ = writeln!(
                                o,
                                "  \"file:{written}\" -> \"{}\" [label=\"{}\"];",
                                s.name, i.port
                            );
                        }
                    }
                }
            }
            o.push_str("}\n");
        }
        DagFormat::Mermaid => {
            o.push_str("flowchart LR\n");
            let id = |n: &str| n.replace('-', "_");
            for s in &plan.stages {
                let _ = writeln!(o, "  {}[\"{}<br/>{}\"]", id(&s.name), s.name, s.kind);
            }
            let mut files = 0;
            for s in &plan.stages {
                for i in &s.inputs {
                    match &i.source {
                        Source::Upstream { stage, port } => {
                            let _ = writeln!(
                                o,
                                "  {} -->|{} to {}| {}",
                                id(&plan.stages[*stage].name),
                                port,
                                i.port,
                                id(&s.name)
                            );
                        }
                        Source::Path { written, .. } => {
                            files += 1;
                            let _ = writeln!(
                                o,
                                "  file{files}[/\"{written}\"/] -->|{}| {}",
                                i.port,
                                id(&s.name)
                            );
                        }
                    }
                }
            }
        }
    }
    o
}

#[cfg(test)]
mod tests {
    use super::{byte_size, clock, disk_forecast, disk_full_hint, pace};

    #[test]
    fn a_sweep_warns_when_the_rest_would_not_fit_on_the_disk() {
        const MIB: u64 = 1024 * 1024;
        // Two variants used 800 MiB; 25 more at 400 MiB each need 10,000 MiB.
        let line = disk_forecast(800 * MIB, 2, 25, 6000 * MIB).expect("10 GB do not fit in 6");
        assert!(
            line.contains("used 800.0 MiB")
                && line.contains("about 10000.0 MiB")
                && line.contains("6000.0 MiB is free"),
            "{line}"
        );
        assert!(
            line.starts_with("warning: the 2 variants that ran used"),
            "{line}"
        );
        let one = disk_forecast(500 * MIB, 1, 1, 100 * MIB).expect("500 MiB do not fit in 100");
        assert!(
            one.starts_with("warning: the variant that ran used 500.0 MiB of the cache's disk; the one left would need about 500.0 MiB"),
            "{one}"
        );
        assert_eq!(disk_forecast(800 * MIB, 2, 25, 10_001 * MIB), None);
        // Nothing known yet, nothing left, or nothing used: no warning.
        assert_eq!(disk_forecast(800 * MIB, 0, 25, 0), None);
        assert_eq!(disk_forecast(800 * MIB, 2, 0, 0), None);
        assert_eq!(disk_forecast(0, 2, 25, 0), None);
    }

    #[test]
    fn a_sweep_says_how_long_the_rest_takes_at_its_pace() {
        // 8 of 27 variants in 40 minutes: 19 left at 5 minutes each.
        assert_eq!(
            pace(2400.0, 8, 27).as_deref(),
            Some("sweep: 8 of 27 variants done in 40 min, about 1 h 35 min left at this pace")
        );
        assert_eq!(
            pace(30.0, 1, 3).as_deref(),
            Some("sweep: 1 of 3 variants done in 30 s, about 60 s left at this pace")
        );
        assert_eq!(pace(100.0, 3, 3), None);
        assert_eq!(pace(0.0, 0, 3), None);
        assert_eq!(clock(89.4), "89 s");
        assert_eq!(clock(90.0), "2 min");
        assert_eq!(clock(3569.0), "59 min");
        assert_eq!(clock(3599.0), "1 h 0 min");
        assert_eq!(clock(3600.0), "1 h 0 min");
        assert_eq!(clock(7199.0), "2 h 0 min");
    }

    #[test]
    fn sizes_read_in_the_unit_that_shows_them() {
        assert_eq!(byte_size(0), "0 bytes");
        assert_eq!(byte_size(1023), "1023 bytes");
        assert_eq!(byte_size(3 * 1024 + 512), "3.5 KiB");
        assert_eq!(byte_size(12_642_937_651), "12057.2 MiB");
    }

    #[test]
    fn a_full_disk_gets_a_hint_and_other_failures_do_not() {
        let full = "codec: out/snapshots/snap_006.hair: No space left on device (os error 28)";
        assert!(disk_full_hint(["no convergence", full].into_iter())
            .is_some_and(|h| h.contains("fure gc --keep")));
        assert!(disk_full_hint(["write failed (os error 28)"].into_iter()).is_some());
        assert!(disk_full_hint(["no convergence", "os error 2"].into_iter()).is_none());
        assert!(disk_full_hint(std::iter::empty()).is_none());
    }
}
