//! The Slurm executor: each stage that must run becomes one batch job on a
//! cluster whose nodes share the cache directory.
//!
//! # Design
//!
//! The driver (`fure run|sweep --executor slurm`) plans, keys, looks up hits
//! and materialises exactly as a local run does ([`crate::exec`]); only the
//! computation of a miss moves. For a miss the driver writes a *job spec*
//! ([`JobSpec`]: pipeline and stage names, kind, version, every parameter,
//! the key, and each input as an upstream `(key, port, hash)` or a path with
//! its hash) and a two-line shell script under a run directory on the shared
//! file system, and submits the script with `sbatch`. The script runs the
//! hidden `fure worker SPEC` command on a node, which
//!
//! 1. rebuilds the stage from its own registry (unknown kind or another
//!    implementation version: the node's binary is not the driver's, error);
//! 2. reads every upstream input from its (validated) manifest in the cache
//!    and rehashes every path input, checking each hash against the spec;
//! 3. recomputes the key from kind, version, parameters and those hashes and
//!    refuses to run if it differs from the spec's;
//! 4. computes the stage through the very code a local run uses (key lock,
//!    recheck for an entry, staging directory, output checks, objects, the
//!    manifest last), so the entry is byte-identical to a local run's;
//! 5. writes a small result file (ok or the stage's error) and exits 0 or 1.
//!
//! The driver follows its jobs with one monitor thread that polls `squeue`
//! (`-t all`, so finished jobs still in the controller's memory are seen) for
//! every job in flight and asks `scontrol show job` (then `sacct`) for the
//! final state, reason and exit code of each one that ended. A stage's
//! thread waits for its job, prints state changes, then reads the result
//! file and the manifest. A job that failed, timed out, ran out of memory or
//! was cancelled fails its stage with the worker's error (when it got that
//! far), Slurm's state and reason, and the tail of the job's log. Logs of
//! jobs that succeeded are removed; those of failed ones are kept.
//!
//! No key is computed twice at once: the driver claims a key among its own
//! threads before submitting (stages of parallel sweep variants share
//! upstream keys), waits while another process anywhere holds the key's
//! lock and then takes the entry it made; the worker itself computes under
//! the key's lock, which is an OFD record lock that shared file systems
//! arbitrate between nodes (see [`crate::cache`]).
//!
//! On SIGINT/SIGTERM/SIGHUP (see [`crate::signals`]) nothing new is
//! submitted and the monitor `scancel`s every job in flight; their stages
//! fail as interrupted. Dropping the executor cancels whatever is left.
//! Slurm's commands run in their own process group, so a terminal's Ctrl-C
//! reaches fure alone.
//!
//! # Configuration
//!
//! An `[executor]` table in the pipeline (inherited through `extends`, child
//! keys winning) and/or in a user file (`--executor-config FILE`,
//! `$FURE_EXECUTOR_CONFIG`, else `$XDG_CONFIG_HOME/fure/config.toml` or
//! `~/.config/fure/config.toml`, whose `[executor]` table the pipeline's
//! overrides field by field):
//!
//! ```toml
//! [executor]
//! partition = "cpu"          # sbatch --partition
//! account = "lab"            # --account
//! time = "01:00:00"          # --time
//! cpus = 4                   # --cpus-per-task (also the stage's thread count)
//! mem = "8G"                 # --mem
//! sbatch = ["--qos=normal"]  # more sbatch arguments, as given
//! max_jobs = 64              # jobs in flight at once (default 64)
//! poll_seconds = 2.0         # squeue interval (default 2)
//! fure = "/shared/bin/fure"  # the binary on the nodes (default: this one)
//! work_dir = "/shared/fure-jobs"  # specs, scripts, logs (default <cache>/slurm)
//!
//! [executor.kinds.codec_strands]   # per stage kind; sbatch lists add up
//! partition = "gpu"
//! time = "04:00:00"
//! cpus = 8
//! mem = "32G"
//! sbatch = ["--gres=gpu:1"]
//! ```
//!
//! None of it enters a key: where a stage ran never changes its result.

use std::collections::BTreeMap;
use std::fs;
use std::io::Write as _;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use fure_stage_api::{Params, PortKind, PortSpec, Stage, Value};
use serde::{Deserialize, Serialize};

/// Version of the job spec format (a worker refuses another).
pub const JOB_SCHEMA: u32 = 1;

/// Default number of jobs in flight.
pub const DEFAULT_MAX_JOBS: usize = 64;

/// How many bytes of a failed job's log a failure shows.
const LOG_TAIL: usize = 2000;

#[derive(Debug, thiserror::Error)]
pub enum SlurmError {
    #[error("{origin}: [executor]: {message}")]
    Config { origin: String, message: String },
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot run `{program}`: {message}")]
    Command { program: String, message: String },
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> SlurmError + '_ {
    move |source| SlurmError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Resources and placement of one stage's job (all optional).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Resources {
    pub partition: Option<String>,
    pub account: Option<String>,
    /// Slurm time limit (`--time`): `MM`, `HH:MM:SS`, `D-HH:MM`, ...
    pub time: Option<String>,
    pub cpus: Option<u32>,
    /// Memory per node (`--mem`): `500M`, `8G`, ...
    pub mem: Option<String>,
    /// Extra `sbatch` arguments.
    #[serde(default)]
    pub sbatch: Vec<String>,
}

impl Resources {
    /// `over`'s fields where set, else `self`'s; `sbatch` lists add up.
    fn overlaid(&self, over: &Resources) -> Resources {
        Resources {
            partition: over.partition.clone().or_else(|| self.partition.clone()),
            account: over.account.clone().or_else(|| self.account.clone()),
            time: over.time.clone().or_else(|| self.time.clone()),
            cpus: over.cpus.or(self.cpus),
            mem: over.mem.clone().or_else(|| self.mem.clone()),
            sbatch: self.sbatch.iter().chain(&over.sbatch).cloned().collect(),
        }
    }

    /// The `sbatch` arguments for these resources.
    pub fn args(&self) -> Vec<String> {
        let mut a = Vec::new();
        if let Some(p) = &self.partition {
            a.push(format!("--partition={p}"));
        }
        if let Some(p) = &self.account {
            a.push(format!("--account={p}"));
        }
        if let Some(p) = &self.time {
            a.push(format!("--time={p}"));
        }
        if let Some(c) = self.cpus {
            a.push(format!("--cpus-per-task={c}"));
        }
        if let Some(m) = &self.mem {
            a.push(format!("--mem={m}"));
        }
        a.extend(self.sbatch.iter().cloned());
        a
    }
}

/// The `[executor]` table.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExecutorConfig {
    #[serde(flatten)]
    pub defaults: Resources,
    /// Per stage kind, over the defaults.
    #[serde(default)]
    pub kinds: BTreeMap<String, Resources>,
    pub max_jobs: Option<usize>,
    pub poll_seconds: Option<f64>,
    /// The `fure` binary the nodes run (default: the driver's own).
    pub fure: Option<PathBuf>,
    /// Where job specs, scripts and logs go (default `<cache>/slurm`).
    pub work_dir: Option<PathBuf>,
}

impl ExecutorConfig {
    /// Reads the table from a pipeline's `[executor]` value.
    pub fn from_value(v: &Value, origin: &str) -> Result<ExecutorConfig, SlurmError> {
        let json = serde_json::to_value(v).map_err(|e| SlurmError::Config {
            origin: origin.to_string(),
            message: e.to_string(),
        })?;
        let c: ExecutorConfig = serde_json::from_value(json).map_err(|e| SlurmError::Config {
            origin: origin.to_string(),
            message: e.to_string(),
        })?;
        c.check(origin)?;
        Ok(c)
    }

    /// Reads the `[executor]` table of a user configuration file (other
    /// tables are ignored; none: an empty configuration).
    pub fn from_file(path: &Path) -> Result<ExecutorConfig, SlurmError> {
        #[derive(Deserialize)]
        struct File {
            executor: Option<ExecutorConfig>,
        }
        let text = fs::read_to_string(path).map_err(io_err(path))?;
        let origin = path.display().to_string();
        let f: File = toml::from_str(&text).map_err(|e| SlurmError::Config {
            origin: origin.clone(),
            message: e.to_string(),
        })?;
        let c = f.executor.unwrap_or_default();
        c.check(&origin)?;
        Ok(c)
    }

    /// The user configuration file: `explicit`, else `$FURE_EXECUTOR_CONFIG`,
    /// else `$XDG_CONFIG_HOME/fure/config.toml` or
    /// `~/.config/fure/config.toml` when it exists.
    pub fn user_file(explicit: Option<&Path>) -> Option<PathBuf> {
        if let Some(p) = explicit {
            return Some(p.to_path_buf());
        }
        if let Some(p) = std::env::var_os("FURE_EXECUTOR_CONFIG").filter(|p| !p.is_empty()) {
            return Some(PathBuf::from(p));
        }
        let base = std::env::var_os("XDG_CONFIG_HOME")
            .filter(|p| !p.is_empty())
            .map(PathBuf::from)
            .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".config")))?;
        Some(base.join("fure").join("config.toml")).filter(|p| p.is_file())
    }

    fn check(&self, origin: &str) -> Result<(), SlurmError> {
        let bad = |message: String| {
            Err(SlurmError::Config {
                origin: origin.to_string(),
                message,
            })
        };
        if self.max_jobs == Some(0) {
            return bad("`max_jobs` must be at least 1".into());
        }
        if let Some(p) = self.poll_seconds {
            if !(p.is_finite() && p > 0.0) {
                return bad(format!("`poll_seconds` must be positive (got {p})"));
            }
        }
        for (what, r) in std::iter::once(("".to_string(), &self.defaults))
            .chain(self.kinds.iter().map(|(k, r)| (format!("kinds.{k}."), r)))
        {
            if r.cpus == Some(0) {
                return bad(format!("`{what}cpus` must be at least 1"));
            }
            for s in [&r.partition, &r.account, &r.time, &r.mem]
                .into_iter()
                .flatten()
            {
                if s.is_empty() || s.chars().any(|c| c.is_whitespace() || c.is_control()) {
                    return bad(format!("{what}: {s:?} is not a Slurm value (no spaces)"));
                }
            }
        }
        Ok(())
    }

    /// `over` on top of `self`, field by field (kinds merged per kind).
    pub fn overlaid(&self, over: &ExecutorConfig) -> ExecutorConfig {
        let mut kinds = self.kinds.clone();
        for (k, r) in &over.kinds {
            let merged = kinds.get(k).cloned().unwrap_or_default().overlaid(r);
            kinds.insert(k.clone(), merged);
        }
        ExecutorConfig {
            defaults: self.defaults.overlaid(&over.defaults),
            kinds,
            max_jobs: over.max_jobs.or(self.max_jobs),
            poll_seconds: over.poll_seconds.or(self.poll_seconds),
            fure: over.fure.clone().or_else(|| self.fure.clone()),
            work_dir: over.work_dir.clone().or_else(|| self.work_dir.clone()),
        }
    }

    /// The resources of a stage of this kind.
    pub fn resources(&self, kind: &str) -> Resources {
        match self.kinds.get(kind) {
            Some(r) => self.defaults.overlaid(r),
            None => self.defaults.clone(),
        }
    }

    pub fn max_jobs(&self) -> usize {
        self.max_jobs.unwrap_or(DEFAULT_MAX_JOBS).max(1)
    }
}

/// Where a job's stage finds one input.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum JobInput {
    /// Output `port` of the cache entry `key`, whose hash is `blake3`.
    Upstream {
        key: String,
        port: String,
        blake3: String,
    },
    /// A file or directory (absolute path; the same on every node) and its
    /// content hash when the driver keyed the stage.
    Path {
        path: PathBuf,
        written: String,
        blake3: String,
    },
}

/// Everything a worker needs to compute one stage, and check that it
/// computes the stage the driver keyed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobSpec {
    pub schema: u32,
    pub pipeline: String,
    pub stage: String,
    pub kind: String,
    pub version: u32,
    pub key: String,
    /// Every parameter (including ones outside the key, like a command's timeout).
    pub params: BTreeMap<String, Value>,
    pub inputs: BTreeMap<String, JobInput>,
}

/// What a worker leaves for the driver.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct JobResult {
    pub ok: bool,
    /// Computed by this job (false: another run made the entry meanwhile).
    pub computed: bool,
    #[serde(default)]
    pub error: Option<String>,
    pub host: String,
}

/// How a remote stage ended (the driver then reads the entry).
#[derive(Debug)]
pub enum Outcome {
    /// The entry was there before any job was submitted (another run made it).
    Found,
    /// A job ran; `computed` is false when it found the entry made by another run.
    Ran { computed: bool },
}

/// A job's state as the driver last saw it.
#[derive(Debug, Clone, Default)]
struct JobState {
    state: String,
    reason: String,
    nodes: String,
    exit_code: String,
    terminal: bool,
    /// When the job was last listed by squeue.
    last_seen: Option<Instant>,
    submitted: Option<Instant>,
}

fn is_terminal(state: &str) -> bool {
    matches!(
        state.split_whitespace().next().unwrap_or(""),
        "COMPLETED"
            | "FAILED"
            | "TIMEOUT"
            | "CANCELLED"
            | "OUT_OF_MEMORY"
            | "NODE_FAIL"
            | "PREEMPTED"
            | "BOOT_FAIL"
            | "DEADLINE"
            | "REVOKED"
            | "SPECIAL_EXIT"
    )
}

struct Inner {
    config: ExecutorConfig,
    fure_bin: PathBuf,
    cache_root: PathBuf,
    run_dir: PathBuf,
    poll: Duration,
    verbose: bool,
    jobs: Mutex<BTreeMap<u64, JobState>>,
    changed: Condvar,
    /// Jobs in flight (bounded by `max_jobs`).
    slots: Mutex<usize>,
    slot_freed: Condvar,
    shutdown: AtomicBool,
    /// Set once the jobs were cancelled after a signal.
    cancelled: AtomicBool,
    counter: AtomicU64,
    print: Mutex<()>,
}

/// The Slurm executor of one `fure` process (shared by its runs).
pub struct Slurm {
    inner: Arc<Inner>,
    monitor: Mutex<Option<std::thread::JoinHandle<()>>>,
}

impl std::fmt::Debug for Slurm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Slurm")
            .field("run_dir", &self.inner.run_dir)
            .finish()
    }
}

/// Runs a Slurm command in its own process group (a terminal's Ctrl-C is
/// fure's alone); Ok(stdout) on success, Err(message) otherwise.
fn slurm_command(program: &str, args: &[String]) -> Result<String, SlurmError> {
    let out = Command::new(program)
        .args(args)
        .stdin(Stdio::null())
        .process_group(0)
        .output()
        .map_err(|e| SlurmError::Command {
            program: program.to_string(),
            message: if e.kind() == std::io::ErrorKind::NotFound {
                format!("{e} (is Slurm installed, and `{program}` on PATH?)")
            } else {
                e.to_string()
            },
        })?;
    if !out.status.success() {
        return Err(SlurmError::Command {
            program: program.to_string(),
            message: format!(
                "{}: {}",
                out.status,
                String::from_utf8_lossy(&out.stderr).trim()
            ),
        });
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// `'text'` for sh.
fn shell_quote(s: &str) -> String {
    format!("'{}'", s.replace('\'', "'\\''"))
}

/// A file name from a stage or pipeline name (`@` and the like replaced).
fn file_part(s: &str) -> String {
    s.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// The last `max` bytes of a file, from a line start where possible.
pub fn tail(path: &Path, max: usize) -> String {
    let Ok(b) = fs::read(path) else {
        return String::new();
    };
    let start = b.len().saturating_sub(max);
    let mut s = &b[start..];
    if start > 0 {
        if let Some(i) = s.iter().position(|&c| c == b'\n') {
            s = &s[i + 1..];
        }
    }
    String::from_utf8_lossy(s).trim_end().to_string()
}

impl Slurm {
    /// An executor for a cache (its absolute root) with this configuration;
    /// checks that `sbatch` answers.
    pub fn new(
        config: ExecutorConfig,
        cache_root: &Path,
        verbose: bool,
    ) -> Result<Slurm, SlurmError> {
        slurm_command("sbatch", &["--version".to_string()])?;
        let fure_bin = match &config.fure {
            Some(p) => p.clone(),
            None => std::env::current_exe().map_err(io_err(Path::new("/proc/self/exe")))?,
        };
        let work = match &config.work_dir {
            Some(d) => std::path::absolute(d).map_err(io_err(d))?,
            None => cache_root.join("slurm"),
        };
        let ms = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .unwrap_or_default()
            .as_millis();
        let run_dir = work.join(format!(
            "{ms}-{}-{}",
            file_part(&crate::cache::host_name()),
            std::process::id()
        ));
        fs::create_dir_all(&run_dir).map_err(io_err(&run_dir))?;
        let poll = Duration::from_secs_f64(config.poll_seconds.unwrap_or(2.0).clamp(0.05, 600.0));
        let inner = Arc::new(Inner {
            fure_bin,
            cache_root: cache_root.to_path_buf(),
            run_dir,
            poll,
            verbose,
            config,
            jobs: Mutex::new(BTreeMap::new()),
            changed: Condvar::new(),
            slots: Mutex::new(0),
            slot_freed: Condvar::new(),
            shutdown: AtomicBool::new(false),
            cancelled: AtomicBool::new(false),
            counter: AtomicU64::new(0),
            print: Mutex::new(()),
        });
        let m = inner.clone();
        let monitor = std::thread::Builder::new()
            .name("fure-slurm-monitor".into())
            .spawn(move || m.monitor())
            .map_err(io_err(Path::new("monitor thread")))?;
        Ok(Slurm {
            inner,
            monitor: Mutex::new(Some(monitor)),
        })
    }

    pub fn config(&self) -> &ExecutorConfig {
        &self.inner.config
    }

    /// The directory of this process's job specs, scripts and logs.
    pub fn run_dir(&self) -> &Path {
        &self.inner.run_dir
    }

    /// Computes one stage through a job. `found` says whether the cache
    /// already holds a valid entry for the key (checked after the key is
    /// claimed and free, before anything is submitted). Err is the stage's
    /// failure message.
    pub fn run(
        &self,
        cache: &crate::cache::Cache,
        spec: &JobSpec,
        found: &dyn Fn() -> bool,
    ) -> Result<Outcome, String> {
        let inner = &*self.inner;
        let label = format!("{}/{}", spec.pipeline, spec.stage);
        let _claim = cache.claim_key(&spec.key, &|| {
            inner.say(&format!(
                "slurm   {label}  waits: another stage of this run computes the same key"
            ))
        });
        cache
            .wait_key_free(&spec.key, &|holder| {
                inner.say(&format!(
                    "slurm   {label}  waits: another fure process computes it ({holder})"
                ))
            })
            .map_err(|e| e.to_string())?;
        if found() {
            return Ok(Outcome::Found);
        }
        let _slot = inner.take_slot().ok_or_else(|| inner.interrupted())?;
        let files = JobFiles::new(
            &inner.run_dir,
            inner.counter.fetch_add(1, Ordering::Relaxed),
            spec,
        );
        inner.write_job(spec, &files)?;
        let res = inner.config.resources(&spec.kind);
        let id = inner.submit(spec, &files, &res)?;
        inner.track(id);
        inner.say(&format!(
            "slurm   {label}  submitted as job {id}{}",
            res.partition
                .as_ref()
                .map(|p| format!(" (partition {p})"))
                .unwrap_or_default()
        ));
        let end = inner.wait(id, &label);
        let result = read_result(&files.result, &end);
        let ok = end.state.starts_with("COMPLETED") && result.as_ref().is_some_and(|r| r.ok);
        if ok {
            let computed = result.map(|r| r.computed).unwrap_or(true);
            files.remove();
            inner.say(&format!("slurm   {label}  job {id} completed"));
            return Ok(Outcome::Ran { computed });
        }
        let msg = inner.failure_message(id, &end, result, &files.log);
        inner.say(&format!("slurm   {label}  job {id} {}", end.state));
        Err(msg)
    }
}

/// The files of one job under the run directory, named after the job's
/// number in this process and its pipeline and stage.
struct JobFiles {
    spec: PathBuf,
    result: PathBuf,
    script: PathBuf,
    log: PathBuf,
}

impl JobFiles {
    fn new(run_dir: &Path, n: u64, spec: &JobSpec) -> JobFiles {
        let stem = format!(
            "{n}-{}-{}",
            file_part(&spec.pipeline),
            file_part(&spec.stage)
        );
        JobFiles {
            spec: run_dir.join(format!("{stem}.job.json")),
            result: run_dir.join(format!("{stem}.result.json")),
            script: run_dir.join(format!("{stem}.sh")),
            log: run_dir.join(format!("{stem}.log")),
        }
    }

    /// Removes them all (a job that succeeded leaves nothing behind).
    fn remove(&self) {
        for p in [&self.spec, &self.result, &self.script, &self.log] {
            let _ = fs::remove_file(p);
        }
    }
}

/// The worker's result file; on a shared file system it may show up a
/// moment after the job ended.
fn read_result(path: &Path, end: &JobState) -> Option<JobResult> {
    let patience = if end.state.starts_with("COMPLETED") || end.state.starts_with("FAILED") {
        Duration::from_secs(10)
    } else {
        Duration::ZERO
    };
    let t0 = Instant::now();
    loop {
        if let Some(r) = fs::read(path)
            .ok()
            .and_then(|b| serde_json::from_slice::<JobResult>(&b).ok())
        {
            return Some(r);
        }
        if t0.elapsed() >= patience {
            return None;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// A slot of `max_jobs`, freed on drop.
struct Slot<'a>(&'a Inner);

impl Drop for Slot<'_> {
    fn drop(&mut self) {
        let mut n = self.0.slots.lock().unwrap_or_else(|e| e.into_inner());
        *n = n.saturating_sub(1);
        self.0.slot_freed.notify_one();
    }
}

impl Inner {
    /// Writes a job's spec and the script that runs `fure worker` on it
    /// (removing any stale result first).
    fn write_job(&self, spec: &JobSpec, files: &JobFiles) -> Result<(), String> {
        let _ = fs::remove_file(&files.result);
        let json = serde_json::to_vec_pretty(spec).map_err(|e| e.to_string())?;
        crate::cache::write_atomic(&files.spec, &json, true)
            .map_err(|e| format!("{}: {e}", files.spec.display()))?;
        let script = format!(
            "#!/bin/sh\n# fure worker: pipeline {}, stage {}, key {}\nexec {} --cache {} worker {}\n",
            spec.pipeline,
            spec.stage,
            spec.key,
            shell_quote(&self.fure_bin.to_string_lossy()),
            shell_quote(&self.cache_root.to_string_lossy()),
            shell_quote(&files.spec.to_string_lossy()),
        );
        crate::cache::write_atomic(&files.script, script.as_bytes(), true)
            .map_err(|e| format!("{}: {e}", files.script.display()))
    }

    /// `sbatch`es a job's script with its kind's resources (unless a signal
    /// came first): the job id.
    fn submit(&self, spec: &JobSpec, files: &JobFiles, res: &Resources) -> Result<u64, String> {
        let mut args = vec![
            "--parsable".to_string(),
            format!("--job-name=fure:{}:{}", spec.pipeline, spec.stage),
            format!("--output={}", files.log.display()),
            "--open-mode=append".to_string(),
        ];
        if let Ok(cwd) = std::env::current_dir() {
            args.push(format!("--chdir={}", cwd.display()));
        }
        args.extend(res.args());
        args.push(files.script.display().to_string());
        if crate::signals::received().is_some() {
            return Err(self.interrupted());
        }
        let out = slurm_command("sbatch", &args).map_err(|e| format!("submitting the job: {e}"))?;
        // --parsable: "ID" or "ID;CLUSTER".
        out.trim()
            .split(';')
            .next()
            .and_then(|s| s.parse().ok())
            .ok_or_else(|| format!("sbatch printed no job id: {out:?}"))
    }

    /// A failed job's stage error: the worker's error and Slurm's state,
    /// reason, exit code and node (in the order that explains it best),
    /// then the job's log and its tail.
    fn failure_message(
        &self,
        id: u64,
        end: &JobState,
        result: Option<JobResult>,
        log: &Path,
    ) -> String {
        let mut job = format!("slurm job {id} {}", end.state);
        if !end.reason.is_empty() && end.reason != "None" {
            job.push_str(&format!(" ({})", end.reason));
        }
        if !end.exit_code.is_empty() {
            job.push_str(&format!(", exit code {}", end.exit_code));
        }
        if !end.nodes.is_empty() && end.nodes != "(null)" {
            job.push_str(&format!(", on {}", end.nodes));
        }
        if self.cancelled.load(Ordering::SeqCst) {
            job.push_str(": cancelled because fure was interrupted");
        }
        let mut msg = match result.and_then(|r| r.error) {
            // A stage that failed by itself: its own error first, as a local
            // run gives it (sweep reasons are its first line).
            Some(e) if end.state.starts_with("FAILED") => format!("{e}\n{job}"),
            // Slurm stopped it (time limit, memory, cancellation, node
            // failure): that first, then what the worker saw.
            Some(e) => format!("{job}\n{e}"),
            None => job,
        };
        msg.push_str(&format!("; log {}", log.display()));
        let t = tail(log, LOG_TAIL);
        if !t.is_empty() {
            msg.push_str(":\n");
            msg.push_str(&t);
        }
        msg
    }

    fn say(&self, text: &str) {
        if self.verbose {
            let _g = self.print.lock().unwrap_or_else(|e| e.into_inner());
            let mut o = std::io::stdout().lock();
            let _ = writeln!(o, "{text}");
            let _ = o.flush();
        }
    }

    fn interrupted(&self) -> String {
        match crate::signals::received() {
            Some(sig) => format!(
                "not submitted: fure was interrupted by {}",
                crate::signals::name(sig)
            ),
            None => "not submitted: the executor is shutting down".into(),
        }
    }

    /// Waits for a free slot; None after a signal.
    fn take_slot(&self) -> Option<Slot<'_>> {
        let max = self.config.max_jobs();
        let mut n = self.slots.lock().unwrap_or_else(|e| e.into_inner());
        loop {
            if crate::signals::received().is_some() || self.shutdown.load(Ordering::SeqCst) {
                return None;
            }
            if *n < max {
                *n += 1;
                return Some(Slot(self));
            }
            n = self
                .slot_freed
                .wait_timeout(n, Duration::from_millis(200))
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
    }

    fn track(&self, id: u64) {
        let mut jobs = self.jobs.lock().unwrap_or_else(|e| e.into_inner());
        jobs.insert(
            id,
            JobState {
                state: "SUBMITTED".into(),
                submitted: Some(Instant::now()),
                ..JobState::default()
            },
        );
        drop(jobs);
        // A signal between sbatch and here: the monitor may have cancelled
        // the others already.
        if self.cancelled.load(Ordering::SeqCst) {
            let _ = slurm_command("scancel", &[id.to_string()]);
        }
    }

    /// Waits until job `id` ended; prints its state changes; forgets it.
    fn wait(&self, id: u64, label: &str) -> JobState {
        let mut shown = String::new();
        let mut jobs = self.jobs.lock().unwrap_or_else(|e| e.into_inner());
        loop {
            let Some(j) = jobs.get(&id).cloned() else {
                return JobState {
                    state: "UNKNOWN".into(),
                    terminal: true,
                    ..JobState::default()
                };
            };
            if j.terminal {
                jobs.remove(&id);
                return j;
            }
            let now = format!("{} {}", j.state, j.reason);
            if now != shown && j.state != "SUBMITTED" {
                shown = now;
                drop(jobs);
                match j.state.as_str() {
                    "RUNNING" => {
                        self.say(&format!("slurm   {label}  job {id} running on {}", j.nodes))
                    }
                    "PENDING" if !matches!(j.reason.as_str(), "None" | "" | "Priority") => {
                        self.say(&format!("slurm   {label}  job {id} pending ({})", j.reason))
                    }
                    _ => {}
                }
                jobs = self.jobs.lock().unwrap_or_else(|e| e.into_inner());
                continue;
            }
            jobs = self
                .changed
                .wait_timeout(jobs, Duration::from_millis(500))
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
    }

    /// The monitor thread: polls squeue, finalises ended jobs, cancels
    /// everything after a signal.
    fn monitor(&self) {
        let mut last_poll = Instant::now() - self.poll;
        let mut warned: Option<Instant> = None;
        while !self.shutdown.load(Ordering::SeqCst) {
            std::thread::sleep(Duration::from_millis(50));
            if crate::signals::received().is_some() && !self.cancelled.swap(true, Ordering::SeqCst)
            {
                self.cancel_all();
                continue;
            }
            if last_poll.elapsed() < self.poll {
                continue;
            }
            last_poll = Instant::now();
            let ids: Vec<u64> = {
                let jobs = self.jobs.lock().unwrap_or_else(|e| e.into_inner());
                jobs.iter()
                    .filter(|(_, j)| !j.terminal)
                    .map(|(id, _)| *id)
                    .collect()
            };
            if ids.is_empty() {
                continue;
            }
            let Some(listed) = self.squeue(&ids, &mut warned) else {
                continue;
            };
            let ended = self.record_listed(&ids, &parse_squeue(&listed));
            self.finalise(ended);
            self.changed.notify_all();
        }
    }

    /// `squeue` on the jobs in flight (all states, so recently finished ones
    /// are seen): its lines, or None when it failed (warned about now and
    /// then). All of them purged already is an empty listing.
    fn squeue(&self, ids: &[u64], warned: &mut Option<Instant>) -> Option<String> {
        let list = ids.iter().map(u64::to_string).collect::<Vec<_>>().join(",");
        match slurm_command(
            "squeue",
            &[
                "-h".into(),
                "-t".into(),
                "all".into(),
                "-j".into(),
                list,
                "-o".into(),
                "%i|%T|%r|%N".into(),
            ],
        ) {
            Ok(out) => Some(out),
            Err(e) => {
                // All of them purged already answers "Invalid job id";
                // anything else: say so now and then, keep trying.
                if !e.to_string().contains("Invalid job id")
                    && warned.is_none_or(|w| w.elapsed() > Duration::from_secs(60))
                {
                    *warned = Some(Instant::now());
                    self.say(&format!("slurm   warning: {e}"));
                }
                if !e.to_string().contains("Invalid job id") {
                    return None;
                }
                Some(String::new())
            }
        }
    }

    /// Updates the jobs in flight from squeue's listing: the ones that ended
    /// (a terminal state, or gone from the controller's memory).
    fn record_listed(
        &self,
        ids: &[u64],
        seen: &BTreeMap<u64, (String, String, String)>,
    ) -> Vec<u64> {
        let mut ended = Vec::new();
        let mut jobs = self.jobs.lock().unwrap_or_else(|e| e.into_inner());
        for id in ids {
            let Some(j) = jobs.get_mut(id) else { continue };
            match seen.get(id) {
                Some((state, reason, nodes)) => {
                    j.last_seen = Some(Instant::now());
                    j.state = state.clone();
                    j.reason = reason.clone();
                    if !nodes.is_empty() {
                        j.nodes = nodes.clone();
                    }
                    if is_terminal(state) {
                        ended.push(*id);
                    }
                }
                // Gone from the controller's memory (or not yet
                // there, just after sbatch): ask the others.
                None => {
                    if j.submitted
                        .is_some_and(|t| t.elapsed() > Duration::from_secs(5))
                        || j.last_seen.is_some()
                    {
                        ended.push(*id);
                    }
                }
            }
        }
        ended
    }

    /// Marks ended jobs terminal with their final state, reason, nodes and
    /// exit code from scontrol or sacct (a job those still see running is
    /// left in flight).
    fn finalise(&self, ended: Vec<u64>) {
        for id in ended {
            let fin = final_state(id);
            let mut jobs = self.jobs.lock().unwrap_or_else(|e| e.into_inner());
            if let Some(j) = jobs.get_mut(&id) {
                match fin {
                    Some(f) => {
                        if !is_terminal(&f.state) {
                            // Still going after all (squeue was late).
                            continue;
                        }
                        j.state = f.state;
                        if !f.reason.is_empty() {
                            j.reason = f.reason;
                        }
                        if !f.nodes.is_empty() {
                            j.nodes = f.nodes;
                        }
                        j.exit_code = f.exit_code;
                    }
                    None if is_terminal(&j.state) => {}
                    None => {
                        j.state = "UNKNOWN".into();
                        j.reason = "the job is known neither to squeue, scontrol nor sacct".into();
                    }
                }
                j.terminal = true;
            }
        }
    }

    /// scancel every job in flight, and mark them ended.
    fn cancel_all(&self) {
        let ids: Vec<String> = {
            let jobs = self.jobs.lock().unwrap_or_else(|e| e.into_inner());
            jobs.iter()
                .filter(|(_, j)| !j.terminal)
                .map(|(id, _)| id.to_string())
                .collect()
        };
        if ids.is_empty() {
            return;
        }
        self.say(&format!("slurm   cancelling jobs {}", ids.join(" ")));
        if let Err(e) = slurm_command("scancel", &ids) {
            self.say(&format!("slurm   warning: {e}"));
        }
        let mut jobs = self.jobs.lock().unwrap_or_else(|e| e.into_inner());
        for j in jobs.values_mut().filter(|j| !j.terminal) {
            j.state = "CANCELLED".into();
            j.reason = "scancel".into();
            j.terminal = true;
        }
        drop(jobs);
        self.changed.notify_all();
    }
}

/// squeue's `%i|%T|%r|%N` lines: job id -> (state, reason, nodes).
fn parse_squeue(listed: &str) -> BTreeMap<u64, (String, String, String)> {
    let mut seen = BTreeMap::new();
    for line in listed.lines() {
        let f: Vec<&str> = line.trim().split('|').collect();
        if f.len() < 4 {
            continue;
        }
        if let Ok(id) = f[0].parse::<u64>() {
            seen.insert(id, (f[1].to_string(), f[2].to_string(), f[3].to_string()));
        }
    }
    seen
}

/// The final (or current) state of a job from `scontrol show job`, else
/// `sacct` (when accounting is enabled).
fn final_state(id: u64) -> Option<JobState> {
    if let Ok(out) = slurm_command(
        "scontrol",
        &["show".into(), "job".into(), "-o".into(), id.to_string()],
    ) {
        let mut j = JobState::default();
        for field in out.split_whitespace() {
            if let Some((k, v)) = field.split_once('=') {
                match k {
                    "JobState" => j.state = v.to_string(),
                    "Reason" => j.reason = v.to_string(),
                    "ExitCode" => j.exit_code = v.to_string(),
                    "NodeList" => j.nodes = v.to_string(),
                    _ => {}
                }
            }
        }
        if !j.state.is_empty() {
            return Some(j);
        }
    }
    let out = slurm_command(
        "sacct",
        &[
            "-n".into(),
            "-P".into(),
            "-X".into(),
            "-j".into(),
            id.to_string(),
            "-o".into(),
            "State,ExitCode,NodeList".into(),
        ],
    )
    .ok()?;
    let line = out.lines().next()?;
    let f: Vec<&str> = line.split('|').collect();
    Some(JobState {
        state: f.first()?.to_string(),
        exit_code: f.get(1).unwrap_or(&"").to_string(),
        nodes: f.get(2).unwrap_or(&"").to_string(),
        ..JobState::default()
    })
}

impl Drop for Slurm {
    fn drop(&mut self) {
        // Whatever is still in flight (a panic, an early return) is cancelled.
        if !self.inner.cancelled.swap(true, Ordering::SeqCst) {
            self.inner.cancel_all();
        }
        self.inner.shutdown.store(true, Ordering::SeqCst);
        if let Some(h) = self
            .monitor
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .take()
        {
            let _ = h.join();
        }
        // The run directory goes when nothing (no failed job's log) is left.
        let _ = fs::remove_dir(&self.inner.run_dir);
    }
}

/// Why a worker could not compute its stage.
#[derive(Debug, thiserror::Error)]
pub enum WorkerError {
    #[error("job spec {path}: {message}")]
    Spec { path: PathBuf, message: String },
    #[error(
        "stage kind `{0}` is unknown to this fure binary (the nodes must run the driver's fure)"
    )]
    UnknownKind(String),
    #[error(
        "stage kind `{kind}` is version {here} in this fure binary but {driver} in the driver's \
         (the nodes must run the driver's fure)"
    )]
    Version {
        kind: String,
        here: u32,
        driver: u32,
    },
    #[error("stage `{stage}`: {message}")]
    Params { stage: String, message: String },
    #[error("input `{port}`: {message}")]
    Input { port: String, message: String },
    #[error(
        "the key computed on this node ({here}) is not the driver's ({driver}): inputs or \
         binary differ between the machines"
    )]
    Key { here: String, driver: String },
    #[error(transparent)]
    Cache(#[from] crate::cache::CacheError),
    /// The stage itself failed (its message as a local run gives it).
    #[error("{0}")]
    Stage(String),
}

/// The result file of a job spec (`N-...job.json` -> `N-...result.json`).
pub fn result_path(spec_path: &Path) -> PathBuf {
    let name = spec_path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let stem = name.strip_suffix(".job.json").unwrap_or(&name);
    spec_path.with_file_name(format!("{stem}.result.json"))
}

/// Reads a job spec.
pub fn read_spec(path: &Path) -> Result<JobSpec, WorkerError> {
    let spec_err = |message: String| WorkerError::Spec {
        path: path.to_path_buf(),
        message,
    };
    let b = fs::read(path).map_err(|e| spec_err(e.to_string()))?;
    let spec: JobSpec = serde_json::from_slice(&b).map_err(|e| spec_err(e.to_string()))?;
    if spec.schema != JOB_SCHEMA {
        return Err(spec_err(format!(
            "schema {} (this fure reads {JOB_SCHEMA}: the nodes must run the driver's fure)",
            spec.schema
        )));
    }
    if !crate::cache::is_digest(&spec.key) {
        return Err(spec_err(format!("{:?} is not a key", spec.key)));
    }
    Ok(spec)
}

/// `fure worker`: computes the stage of a job spec against the cache,
/// after re-keying it from its own registry and the inputs it finds.
/// Ok(computed here) or the reason it did not.
pub fn worker(
    registry: &crate::plan::Registry,
    cache: &crate::cache::Cache,
    spec: &JobSpec,
    ui: &crate::ui::Ui,
) -> Result<bool, WorkerError> {
    let WorkerStage {
        stage,
        params,
        in_specs,
    } = worker_stage(registry, spec)?;
    let mut hashes = BTreeMap::new();
    let mut inputs = Vec::new();
    for (port, inp) in &spec.inputs {
        let (hash, path) = match inp {
            JobInput::Upstream {
                key,
                port: up,
                blake3,
            } => upstream_input(cache, key, up, blake3),
            JobInput::Path {
                path,
                written,
                blake3,
            } => {
                // Command deps take files and directories alike.
                let expect_dir = (spec.kind != crate::command::KIND).then(|| {
                    in_specs
                        .iter()
                        .find(|p| &p.name == port)
                        .is_some_and(|p| p.kind == PortKind::Dir)
                });
                path_input(cache, path, written, blake3, expect_dir)
            }
        }
        .map_err(|message| WorkerError::Input {
            port: port.clone(),
            message,
        })?;
        hashes.insert(port.clone(), hash);
        inputs.push((port.clone(), path));
    }
    // The stage as the planner would have it; inputs and upstream indices
    // are not needed to compute it (they are given as paths).
    let st = crate::plan::PlannedStage {
        name: spec.stage.clone(),
        kind: spec.kind.clone(),
        version: spec.version,
        stage: stage.clone(),
        outputs: stage.outputs(&params),
        params,
        inputs: Vec::new(),
        upstream: Vec::new(),
        loc: crate::pipeline::Loc::origin("job spec"),
    };
    let preimage = crate::key::Preimage::new(
        &spec.kind,
        spec.version,
        &crate::exec::keyed_params(&st),
        hashes,
    );
    let here = preimage.key();
    if here != spec.key {
        return Err(WorkerError::Key {
            here,
            driver: spec.key.clone(),
        });
    }
    let work = crate::exec::Computation {
        pipeline: spec.pipeline.clone(),
        stage: &st,
        key: spec.key.clone(),
        preimage,
        inputs,
        // A job knows its upstream entries by key, not by stage name.
        origins: BTreeMap::new(),
        threads: worker_threads(),
    };
    let (_, computed) = crate::exec::compute_stage(cache, work, ui, &worker_may_commit)
        .map_err(WorkerError::Stage)?;
    Ok(computed)
}

/// Whether a worker may write its entry, asked after its outputs are
/// stored: not once it got a signal, nor while Slurm ends its job. Slurm
/// ends a job (cancelled, timed out, preempted) by first marking it in the
/// controller and then signalling its processes one at a time, children
/// before parents, so a command's shell can outlive its killed step and exit
/// 0 (`sleep 60; echo done`) before the worker itself is signalled; only the
/// controller then knows that the job is being ended. Its state is asked
/// with `squeue` once per computed stage; where it cannot answer (no job id,
/// no Slurm), the signal alone decides.
fn worker_may_commit() -> Result<(), String> {
    let interrupted = |why: String| {
        Err(format!(
            "the job ended before its entry was written ({why}); nothing is stored"
        ))
    };
    if let Some(sig) = crate::signals::received() {
        return interrupted(format!("the worker got {}", crate::signals::name(sig)));
    }
    if let Some(state) = ending_job_state() {
        return interrupted(format!("Slurm reports the job as {state}"));
    }
    Ok(())
}

/// The state of this process's Slurm job when Slurm is ending it (anything
/// but RUNNING or SUSPENDED; a cancelled job whose processes are being
/// killed is COMPLETING); None when it runs, or when there is no job or no
/// answer.
fn ending_job_state() -> Option<String> {
    let id = std::env::var("SLURM_JOB_ID")
        .ok()
        .filter(|id| !id.is_empty() && id.bytes().all(|b| b.is_ascii_digit()))?;
    let args = ["-h", "-t", "all", "-j", id.as_str(), "-o", "%T"].map(String::from);
    let listed = slurm_command("squeue", &args).ok()?;
    let state = listed.lines().next()?.trim().to_string();
    (!state.is_empty() && state != "RUNNING" && state != "SUSPENDED").then_some(state)
}

/// A job's stage as this binary has it.
struct WorkerStage {
    stage: Arc<dyn Stage>,
    /// The spec's parameters, validated by the stage.
    params: Params,
    /// Its input ports under those parameters.
    in_specs: Vec<PortSpec>,
}

/// The job's stage from this binary's registry, at the driver's version,
/// with its parameters validated and its input ports (every port of the
/// spec must be one of them).
fn worker_stage(
    registry: &crate::plan::Registry,
    spec: &JobSpec,
) -> Result<WorkerStage, WorkerError> {
    let stage = registry
        .get(&spec.kind)
        .ok_or_else(|| WorkerError::UnknownKind(spec.kind.clone()))?
        .clone();
    if stage.version() != spec.version {
        return Err(WorkerError::Version {
            kind: spec.kind.clone(),
            here: stage.version(),
            driver: spec.version,
        });
    }
    let params = Params(spec.params.clone());
    stage.validate(&params).map_err(|e| WorkerError::Params {
        stage: spec.stage.clone(),
        message: e.to_string(),
    })?;
    let in_specs = stage.inputs(&params);
    for port in spec.inputs.keys() {
        if !in_specs.iter().any(|p| &p.name == port) {
            return Err(WorkerError::Input {
                port: port.clone(),
                message: format!("kind `{}` has no such input port", spec.kind),
            });
        }
    }
    Ok(WorkerStage {
        stage,
        params,
        in_specs,
    })
}

/// An upstream input: output `up` of the entry `key`, which must be in the
/// shared cache, valid, and hold the hash the driver keyed with. Err: why
/// not (the caller names the port).
fn upstream_input(
    cache: &crate::cache::Cache,
    key: &str,
    up: &str,
    blake3: &str,
) -> Result<(String, crate::exec::InputPath), String> {
    let m = cache
        .lookup_checked(key)
        .map_err(|e| format!("upstream entry {}: {e}", crate::cache::short(key)))?
        .ok_or_else(|| {
            format!(
                "upstream entry {} is not in the cache {} (do the nodes share it?)",
                crate::cache::short(key),
                cache.root().display()
            )
        })?;
    cache
        .check_entry(&m)
        .map_err(|e| format!("upstream entry {}: {e}", crate::cache::short(key)))?;
    let rec = m.outputs.get(up).cloned().ok_or_else(|| {
        format!(
            "upstream entry {} has no output `{up}`",
            crate::cache::short(key)
        )
    })?;
    if rec.blake3 != blake3 {
        return Err(format!(
            "upstream output `{up}` is {} here but {} for the driver",
            crate::cache::short(&rec.blake3),
            crate::cache::short(blake3)
        ));
    }
    Ok((rec.blake3.clone(), crate::exec::InputPath::Object(rec)))
}

/// A path input, rehashed on this node: it must be a directory or a file
/// as `expect_dir` says (when it says) and unchanged since the driver keyed
/// the stage. Err: why not (the caller names the port).
fn path_input(
    cache: &crate::cache::Cache,
    path: &Path,
    written: &str,
    blake3: &str,
    expect_dir: Option<bool>,
) -> Result<(String, crate::exec::InputPath), String> {
    let (h, _, is_dir) = cache
        .hash_source(path)
        .map_err(|e| format!("cannot read `{written}` ({}): {e}", path.display()))?;
    if let Some(want_dir) = expect_dir.filter(|&want_dir| want_dir != is_dir) {
        return Err(format!(
            "`{written}` is a {} but the port expects a {}",
            if is_dir { "directory" } else { "file" },
            if want_dir { "directory" } else { "file" }
        ));
    }
    if h != blake3 {
        return Err(format!(
            "`{written}` ({}) changed since the driver keyed the stage, or differs \
             on this node",
            path.display()
        ));
    }
    Ok((h, crate::exec::InputPath::Path(path.to_path_buf())))
}

/// The worker's threads: the job's `SLURM_CPUS_PER_TASK`, else every core.
fn worker_threads() -> usize {
    std::env::var("SLURM_CPUS_PER_TASK")
        .ok()
        .and_then(|s| s.parse::<usize>().ok())
        .filter(|&n| n > 0)
        .unwrap_or_else(crate::exec::available_cores)
}

/// Writes a job's result file (atomically, fsynced: the driver reads it
/// from another machine).
pub fn write_result(path: &Path, r: &JobResult) -> std::io::Result<()> {
    let b = serde_json::to_vec_pretty(r).map_err(std::io::Error::other)?;
    crate::cache::write_atomic(path, &b, true)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resources_merge_by_field_and_sbatch_lists_add_up() {
        let user = ExecutorConfig {
            defaults: Resources {
                partition: Some("cpu".into()),
                account: Some("lab".into()),
                sbatch: vec!["--qos=low".into()],
                ..Resources::default()
            },
            ..ExecutorConfig::default()
        };
        let v: Value = toml::from_str::<toml::Value>(
            "partition = \"short\"\ncpus = 2\n[kinds.learn]\npartition = \"gpu\"\nsbatch = [\"--gres=gpu:1\"]\n",
        )
        .map(|t| serde_json::from_value(serde_json::to_value(t).unwrap()).unwrap())
        .unwrap();
        let pipe = ExecutorConfig::from_value(&v, "p.toml").unwrap();
        let c = user.overlaid(&pipe);
        assert_eq!(
            c.resources("other").args(),
            [
                "--partition=short",
                "--account=lab",
                "--cpus-per-task=2",
                "--qos=low"
            ]
        );
        assert_eq!(
            c.resources("learn").args(),
            [
                "--partition=gpu",
                "--account=lab",
                "--cpus-per-task=2",
                "--qos=low",
                "--gres=gpu:1"
            ]
        );
        assert_eq!(c.max_jobs(), DEFAULT_MAX_JOBS);
    }

    #[test]
    fn config_errors_name_the_field() {
        let v = Value::Table(BTreeMap::from([(
            "partiton".to_string(),
            Value::Str("x".into()),
        )]));
        let e = ExecutorConfig::from_value(&v, "p.toml:3:1")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("p.toml:3:1: [executor]") && e.contains("partiton"),
            "{e}"
        );
        let v = Value::Table(BTreeMap::from([("cpus".to_string(), Value::Int(0))]));
        let e = ExecutorConfig::from_value(&v, "p").unwrap_err().to_string();
        assert!(e.contains("cpus"), "{e}");
    }

    #[test]
    fn job_specs_round_trip_exactly() {
        let spec = JobSpec {
            schema: JOB_SCHEMA,
            pipeline: "p@v1".into(),
            stage: "s".into(),
            kind: "k".into(),
            version: 3,
            key: "0".repeat(64),
            params: BTreeMap::from([
                ("x".to_string(), Value::Float(0.1f32 as f64)),
                ("n".to_string(), Value::Int(2)),
                ("f".to_string(), Value::Float(2.0)),
            ]),
            inputs: BTreeMap::from([(
                "a".to_string(),
                JobInput::Path {
                    path: "/x".into(),
                    written: "x".into(),
                    blake3: "1".repeat(64),
                },
            )]),
        };
        let back: JobSpec = serde_json::from_slice(&serde_json::to_vec(&spec).unwrap()).unwrap();
        assert_eq!(back, spec);
    }

    #[test]
    fn quoting_and_tails() {
        assert_eq!(shell_quote("a'b c"), "'a'\\''b c'");
        assert_eq!(file_part("p@v1/x"), "p_v1_x");
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("log");
        fs::write(&p, "one\ntwo\nthree\n").unwrap();
        assert_eq!(tail(&p, 9), "three");
        assert_eq!(tail(&p, 100), "one\ntwo\nthree");
    }
}
