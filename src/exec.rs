//! Running a plan: keys, cache lookups, the scheduler, materialisation and
//! the run report.
//!
//! The scheduler walks the plan in topological order on the calling thread.
//! A stage whose upstream stages are resolved gets its key (input hashes come
//! from upstream manifests, or from files through the hint table); a hit is
//! resolved at once (manifest read, objects checked by size and hint), so a
//! no-op run reads only manifests. Misses are queued and started on worker
//! threads, at most `jobs` at a time.
//!
//! CPU budget: the engine owns `cores` tokens (default: all cores). A stage
//! starts only while tokens are free and takes
//! `max(1, free / min(jobs - running, queued))` of them; it runs inside a
//! rayon pool of exactly that many threads, so concurrently running stages
//! together never use more threads than cores. Command stages take one token.
//!
//! Early cutoff needs no special case: a downstream key contains the content
//! hashes of its inputs, so if a rerun upstream stage writes identical bytes
//! the downstream key is unchanged and it stays cached.
//!
//! Failures: a stage that fails (error, panic, missing output) caches
//! nothing; stages already running finish and are cached; stages not yet
//! started are skipped; the run exits with status 1.
//!
//! Peak memory: command stages report their child's max RSS (`wait4`).
//! In-process stages report the process's peak RSS over the stage's run
//! (`VmHWM`, reset through `/proc/self/clear_refs` when no other in-process
//! stage is running), which is exact with `--jobs 1` and an upper bound with
//! parallel stages.

use std::collections::{BTreeMap, VecDeque};
use std::fs;
use std::os::unix::fs::MetadataExt;
use std::panic::AssertUnwindSafe;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc;
use std::time::Instant;

use fure_stage_api::{PortKind, StageContext};
use serde::{Deserialize, Serialize};

use crate::cache::{self, Cache, IndexEntry, Manifest, OutputRecord};
use crate::command;
use crate::key::{canonical_value, Preimage};
use crate::plan::{Plan, PlannedStage, Source};
use crate::ui::{StageProgress, Ui, UiMode};

/// The fure version recorded in manifests and reports.
pub const FURE_VERSION: &str = env!("CARGO_PKG_VERSION");

/// How to run a plan.
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// Stages running at once.
    pub jobs: usize,
    /// CPU threads shared by running stages.
    pub cores: usize,
    /// Where to materialise outputs (`<out_root>/<pipeline>/<stage>/`); None: nowhere.
    pub out_root: Option<PathBuf>,
    /// Only report what would run.
    pub dry_run: bool,
    pub ui: UiMode,
    /// Keep running independent stages after a failure.
    pub keep_going: bool,
    /// Where the stages that must run are computed.
    pub executor: Executor,
}

/// Where the stages that must run are computed. Keys, hits, the index and
/// materialisation are the driver's in every case.
#[derive(Clone, Default)]
pub enum Executor {
    /// In this process, on worker threads under the CPU-token budget.
    #[default]
    Local,
    /// One Slurm job per stage (see [`crate::slurm`]); `jobs` bounds the
    /// jobs of one run in flight, CPU tokens play no part.
    Slurm(std::sync::Arc<crate::slurm::Slurm>),
}

impl Executor {
    pub fn is_remote(&self) -> bool {
        !matches!(self, Executor::Local)
    }
}

impl std::fmt::Debug for Executor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Executor::Local => f.write_str("Local"),
            Executor::Slurm(s) => write!(f, "Slurm({s:?})"),
        }
    }
}

impl Default for RunOptions {
    fn default() -> Self {
        let cores = available_cores();
        RunOptions {
            jobs: cores,
            cores,
            out_root: Some(PathBuf::from("out")),
            dry_run: false,
            ui: UiMode::Quiet,
            keep_going: false,
            executor: Executor::Local,
        }
    }
}

/// Number of CPU cores available to this process.
pub fn available_cores() -> usize {
    std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1)
}

/// What happened to a stage.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Status {
    Ran,
    Cached,
    Failed,
    Skipped,
    /// Dry runs and `status`: would run.
    WillRun,
}

/// One output in a report.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct OutputReport {
    pub path: String,
    pub blake3: String,
    pub bytes: u64,
}

/// One stage in a report.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct StageReport {
    pub name: String,
    pub kind: String,
    /// Empty when the key could not be computed (upstream will run or failed).
    pub key: String,
    pub status: Status,
    pub reason: String,
    pub seconds: f64,
    pub peak_rss_bytes: u64,
    pub outputs: BTreeMap<String, OutputReport>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// The notes of the run that computed the entry (also for cache hits).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub notes: Vec<String>,
}

impl StageReport {
    /// Whether the stage failed because a disk was full (ENOSPC, as the
    /// operating system's message or a command's stderr reports it).
    pub fn failed_on_full_disk(&self) -> bool {
        self.error.as_deref().is_some_and(is_disk_full)
    }
}

/// Whether an error message says a disk is full (ENOSPC).
pub fn is_disk_full(message: &str) -> bool {
    message.contains("No space left on device") || message.contains("os error 28")
}

/// The run report (`--report FILE`, and `runs/` in the cache).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunReport {
    pub pipeline: String,
    pub fure_version: String,
    pub seconds: f64,
    pub stages: Vec<StageReport>,
}

impl RunReport {
    pub fn ok(&self) -> bool {
        self.stages
            .iter()
            .all(|s| s.status != Status::Failed && s.status != Status::Skipped)
    }
    pub fn count(&self, status: Status) -> usize {
        self.stages.iter().filter(|s| s.status == status).count()
    }
    pub fn stage(&self, name: &str) -> Option<&StageReport> {
        self.stages.iter().find(|s| s.name == name)
    }
}

/// A stage whose key is known.
struct Keyed {
    key: String,
    preimage: Preimage,
    entry: IndexEntry,
}

enum State {
    Pending,
    Queued,
    Running,
    Done(BTreeMap<String, OutputRecord>),
    /// Failed, skipped, or (dry run) will run: dependents cannot resolve.
    Blocked,
}

struct WorkDone {
    index: usize,
    result: Result<(Manifest, bool), String>,
    progress: StageProgress,
    tokens: usize,
}

/// Runs (or, with `dry_run`, inspects) a plan against a cache.
pub fn run(plan: &Plan, cache: &Cache, opts: &RunOptions) -> RunReport {
    let t0 = Instant::now();
    let ui = Ui::new(opts.ui);
    if !opts.dry_run {
        cache.clean_tmp();
    }
    let inproc_running = AtomicUsize::new(0);
    let mut sched = Scheduler::new(plan, cache, opts, &ui);
    std::thread::scope(|scope| {
        let (tx, rx) = mpsc::channel::<WorkDone>();
        loop {
            sched.resolve_ready();
            sched.launch(scope, &tx, &inproc_running);
            if sched.running == 0 {
                if sched.queue.is_empty() {
                    // The resolution pass is in topological order, so nothing
                    // is pending any more.
                    break;
                }
                // Not started because of a failure: skip them, then mark
                // their dependents in one more pass.
                sched.skip_queued();
                continue;
            }
            let Ok(done) = rx.recv() else { break };
            sched.collect(done);
        }
    });
    sched.finish(t0)
}

/// The scheduler's state over one run: resolve ([`Scheduler::resolve_ready`]),
/// launch ([`Scheduler::launch`]), collect ([`Scheduler::collect`]).
struct Scheduler<'a> {
    plan: &'a Plan,
    cache: &'a Cache,
    opts: &'a RunOptions,
    ui: &'a Ui,
    old_index: BTreeMap<String, IndexEntry>,
    new_index: BTreeMap<String, IndexEntry>,
    states: Vec<State>,
    reports: Vec<Option<StageReport>>,
    keyed: Vec<Option<Keyed>>,
    queue: VecDeque<(usize, String)>,
    run_reasons: Vec<String>,
    jobs: usize,
    running: usize,
    free_tokens: usize,
    failed: bool,
}

impl<'a> Scheduler<'a> {
    fn new(plan: &'a Plan, cache: &'a Cache, opts: &'a RunOptions, ui: &'a Ui) -> Self {
        let old_index = cache.load_index(&plan.name);
        let n = plan.stages.len();
        Scheduler {
            plan,
            cache,
            opts,
            ui,
            new_index: old_index.clone(),
            old_index,
            states: (0..n).map(|_| State::Pending).collect(),
            reports: vec![None; n],
            keyed: (0..n).map(|_| None).collect(),
            queue: VecDeque::new(),
            run_reasons: vec![String::new(); n],
            jobs: opts.jobs.max(1),
            running: 0,
            free_tokens: opts.cores.max(1),
            failed: false,
        }
    }

    /// Stage `i` failed: reported, blocked, and the run marked failed.
    fn fail(
        &mut self,
        i: usize,
        key: &str,
        reason: String,
        error: String,
        progress: Option<StageProgress>,
    ) {
        let st = &self.plan.stages[i];
        self.ui.failed(&st.name, &error, progress);
        self.reports[i] = Some(report_without_outputs(
            st,
            key,
            Status::Failed,
            reason,
            Some(error),
        ));
        self.states[i] = State::Blocked;
        self.failed = true;
    }

    /// Resolves every stage whose upstream stages are resolved (one pass
    /// suffices: the plan is in topological order).
    fn resolve_ready(&mut self) {
        for i in 0..self.plan.stages.len() {
            if !matches!(self.states[i], State::Pending) {
                continue;
            }
            let st = &self.plan.stages[i];
            let mut blocked_by = None;
            let mut all_done = true;
            for &u in &st.upstream {
                match &self.states[u] {
                    State::Done(_) => {}
                    State::Blocked => {
                        blocked_by = Some(u);
                    }
                    _ => all_done = false,
                }
            }
            if let Some(u) = blocked_by {
                self.block(i, u);
            } else if all_done {
                self.resolve(i);
            }
        }
    }

    /// Stage `i` cannot resolve because upstream stage `u` is blocked.
    fn block(&mut self, i: usize, u: usize) {
        let st = &self.plan.stages[i];
        let up = &self.plan.stages[u].name;
        let (status, reason) = match self.reports[u].as_ref().map(|r| r.status) {
            Some(Status::WillRun) => {
                let mut why = match self.old_index.get(&st.name) {
                    None => vec!["new stage".to_string()],
                    Some(o) => explain_params(o, &st.kind, st.version, &keyed_params(st).0),
                };
                why.push(format!("input from `{up}`, which will run"));
                (Status::WillRun, why.join("; "))
            }
            Some(Status::Failed) => (Status::Skipped, format!("upstream `{up}` failed")),
            _ => (Status::Skipped, format!("upstream `{up}` did not run")),
        };
        if status == Status::WillRun {
            self.ui.will_run(&st.name, &reason);
        } else {
            self.ui.skipped(&st.name, &reason);
        }
        self.reports[i] = Some(report_without_outputs(st, "", status, reason, None));
        self.states[i] = State::Blocked;
    }

    /// Keys stage `i` (its upstream stages are done) and takes its cache
    /// entry, or queues it (dry run: reports it as will run).
    fn resolve(&mut self, i: usize) {
        let (plan, cache, opts, ui) = (self.plan, self.cache, self.opts, self.ui);
        let st = &plan.stages[i];
        let k = match key_stage(plan, i, &self.states, cache) {
            Ok(k) => k,
            Err(e) => return self.fail(i, "", String::new(), e, None),
        };
        let (hit, damage) = match cache.lookup_checked(&k.key) {
            Ok(Some(m)) => {
                let d = entry_fits(st, &m)
                    .and_then(|()| cache.check_entry(&m))
                    .err();
                (Some(m), d)
            }
            Ok(None) => (None, None),
            // Present but invalid: damaged, recomputed and rewritten.
            Err(e) => (None, Some(e)),
        };
        match (hit, damage) {
            (Some(m), None) => {
                let reason = cutoff_reason(plan, i, &self.reports);
                ui.cached(&st.name, &k.key, &reason);
                let outputs = if opts.dry_run {
                    Ok(output_reports(cache, &m, None))
                } else {
                    materialise_outputs(cache, opts, plan, st, &m)
                };
                let outputs = match outputs {
                    Ok(o) => o,
                    Err(e) => return self.fail(i, &k.key, reason, e, None),
                };
                self.reports[i] = Some(StageReport {
                    name: st.name.clone(),
                    kind: st.kind.clone(),
                    key: k.key.clone(),
                    status: Status::Cached,
                    reason,
                    seconds: 0.0,
                    peak_rss_bytes: m.peak_rss_bytes,
                    outputs,
                    error: None,
                    notes: m.notes.clone(),
                });
                self.new_index.insert(st.name.clone(), k.entry.clone());
                self.states[i] = State::Done(m.outputs);
                self.keyed[i] = Some(k);
            }
            (_, damage) => {
                let reason = match damage {
                    Some(d) => {
                        ui.line(&format!(
                            "warning: {}: cached entry {} is damaged ({d}); recomputing",
                            st.name,
                            cache::short(&k.key)
                        ));
                        format!("cached entry damaged: {d}")
                    }
                    _ => explain(self.old_index.get(&st.name), &k.entry),
                };
                if opts.dry_run {
                    ui.will_run(&st.name, &reason);
                    self.reports[i] = Some(report_without_outputs(
                        st,
                        &k.key,
                        Status::WillRun,
                        reason,
                        None,
                    ));
                    self.states[i] = State::Blocked;
                } else {
                    self.queue.push_back((i, reason));
                    self.states[i] = State::Queued;
                }
                self.keyed[i] = Some(k);
            }
        }
    }

    /// Starts queued stages while jobs and CPU tokens allow. After
    /// SIGINT/SIGTERM/SIGHUP nothing new starts (see `signals`).
    fn launch<'scope>(
        &mut self,
        scope: &'scope std::thread::Scope<'scope, '_>,
        tx: &mpsc::Sender<WorkDone>,
        inproc: &'scope AtomicUsize,
    ) where
        'a: 'scope,
    {
        let (plan, cache, opts, ui) = (self.plan, self.cache, self.opts, self.ui);
        let remote = opts.executor.is_remote();
        while self.running < self.jobs
            && (self.free_tokens > 0 || remote)
            && (opts.keep_going || !self.failed)
            && crate::signals::received().is_none()
        {
            let Some((i, reason)) = self.queue.pop_front() else {
                break;
            };
            let st = &plan.stages[i];
            let share = (self.jobs - self.running).min(self.queue.len() + 1).max(1);
            let tokens = if remote {
                0
            } else if st.kind == command::KIND {
                1
            } else {
                (self.free_tokens / share).max(1)
            };
            self.free_tokens -= tokens.min(self.free_tokens);
            self.running += 1;
            self.states[i] = State::Running;
            let progress = ui.started(&st.name, &reason);
            self.run_reasons[i] = reason;
            let k = self.keyed[i].as_ref().expect("queued stages are keyed");
            let work = Computation {
                pipeline: plan.name.clone(),
                stage: st,
                key: k.key.clone(),
                preimage: k.preimage.clone(),
                inputs: stage_inputs(plan, i, &self.states),
                origins: input_origins(plan, i),
                threads: tokens,
            };
            let job = match &opts.executor {
                Executor::Local => None,
                Executor::Slurm(s) => {
                    Some((s.clone(), job_spec(plan, i, &self.states, &self.keyed)))
                }
            };
            let tx = tx.clone();
            let spawned = std::thread::Builder::new()
                .name(format!("fure-stage-{}", st.name))
                .spawn_scoped(scope, move || {
                    let result = match job {
                        None => execute(cache, work, &progress, ui, inproc, &|| Ok(())),
                        Some((slurm, spec)) => execute_remote(&slurm, cache, st, &spec),
                    };
                    let _ = tx.send(WorkDone {
                        index: i,
                        result,
                        progress,
                        tokens,
                    });
                });
            if let Err(e) = spawned {
                self.running -= 1;
                self.free_tokens += tokens;
                let msg = format!("cannot start a thread: {e}");
                self.fail(i, "", String::new(), msg, None);
            }
        }
    }

    /// Skips the queued stages that were not started (after a failure or a
    /// signal).
    fn skip_queued(&mut self) {
        for (i, reason) in std::mem::take(&mut self.queue) {
            let st = &self.plan.stages[i];
            let why = match crate::signals::received() {
                Some(sig) => format!(
                    "not started: fure was interrupted by {} ({reason})",
                    crate::signals::name(sig)
                ),
                None => format!("not started after a failure ({reason})"),
            };
            self.ui.skipped(&st.name, &why);
            let key = self.keyed[i].as_ref().map(|k| k.key.as_str()).unwrap_or("");
            self.reports[i] = Some(report_without_outputs(st, key, Status::Skipped, why, None));
            self.states[i] = State::Blocked;
        }
    }

    /// Takes in a finished stage: its report, index entry and outputs.
    fn collect(&mut self, done: WorkDone) {
        let (plan, cache, opts, ui) = (self.plan, self.cache, self.opts, self.ui);
        self.running -= 1;
        self.free_tokens += done.tokens;
        let i = done.index;
        let st = &plan.stages[i];
        let key = self.keyed[i]
            .as_ref()
            .expect("ran stages are keyed")
            .key
            .clone();
        let (m, computed) = match done.result {
            Ok(r) => r,
            Err(e) => {
                let reason = std::mem::take(&mut self.run_reasons[i]);
                return self.fail(i, &key, reason, e, Some(done.progress));
            }
        };
        let (status, seconds, reason) = if computed {
            ui.done(&st.name, m.seconds, done.progress);
            (
                Status::Ran,
                m.seconds,
                std::mem::take(&mut self.run_reasons[i]),
            )
        } else {
            drop(done.progress);
            ui.cached(&st.name, &key, "computed by a concurrent run");
            (
                Status::Cached,
                0.0,
                "computed by a concurrent run".to_string(),
            )
        };
        let entry = self.keyed[i]
            .as_ref()
            .expect("ran stages are keyed")
            .entry
            .clone();
        self.new_index.insert(st.name.clone(), entry);
        match materialise_outputs(cache, opts, plan, st, &m) {
            Ok(outputs) => {
                self.reports[i] = Some(StageReport {
                    name: st.name.clone(),
                    kind: st.kind.clone(),
                    key,
                    status,
                    reason,
                    seconds,
                    peak_rss_bytes: m.peak_rss_bytes,
                    outputs,
                    error: None,
                    notes: m.notes.clone(),
                });
                self.states[i] = State::Done(m.outputs);
            }
            // Cached, but the run did not deliver its outputs.
            Err(e) => self.fail(i, &key, reason, e, None),
        }
    }

    /// The run's report; saves the status index and hash hints.
    fn finish(self, t0: Instant) -> RunReport {
        let stages: Vec<StageReport> = self
            .reports
            .into_iter()
            .zip(&self.plan.stages)
            .map(|(r, st)| {
                r.unwrap_or_else(|| {
                    report_without_outputs(st, "", Status::Skipped, "not reached".into(), None)
                })
            })
            .collect();
        if !self.opts.dry_run {
            if self.new_index != self.old_index {
                self.cache.save_index(&self.plan.name, &self.new_index);
            }
            self.cache.save_hints();
        }
        RunReport {
            pipeline: self.plan.name.clone(),
            fure_version: FURE_VERSION.to_string(),
            seconds: t0.elapsed().as_secs_f64(),
            stages,
        }
    }
}

fn report_without_outputs(
    st: &PlannedStage,
    key: &str,
    status: Status,
    reason: String,
    error: Option<String>,
) -> StageReport {
    StageReport {
        name: st.name.clone(),
        kind: st.kind.clone(),
        key: key.to_string(),
        status,
        reason,
        seconds: 0.0,
        peak_rss_bytes: 0,
        outputs: BTreeMap::new(),
        error,
        notes: Vec::new(),
    }
}

/// The cached-stage reason: early cutoff when an upstream stage ran.
fn cutoff_reason(plan: &Plan, i: usize, reports: &[Option<StageReport>]) -> String {
    let ran: Vec<&str> = plan.stages[i]
        .upstream
        .iter()
        .filter(|&&u| {
            reports[u]
                .as_ref()
                .map(|r| r.status == Status::Ran)
                .unwrap_or(false)
        })
        .map(|&u| plan.stages[u].name.as_str())
        .collect();
    if ran.is_empty() {
        String::new()
    } else {
        format!(
            "early cutoff: upstream {} reran with identical outputs",
            ran.iter()
                .map(|s| format!("`{s}`"))
                .collect::<Vec<_>>()
                .join(", ")
        )
    }
}

/// The parameters that enter a stage's key: a command's timeout bounds the
/// run, not the result, so it is left out; so is a parameter declared with
/// `omit_default_from_key` while it holds its default (an option added to a
/// stage keeps the keys made before it existed).
pub(crate) fn keyed_params(st: &PlannedStage) -> fure_stage_api::Params {
    let mut params = st.params.clone();
    if st.kind == command::KIND {
        params.0.remove(command::TIMEOUT_PARAM);
    }
    for spec in st.stage.params().iter().filter(|s| s.omit_default_from_key) {
        if let (Some(v), Some(d)) = (params.get(spec.name), &spec.default) {
            if canonical_value(v) == canonical_value(d) {
                params.0.remove(spec.name);
            }
        }
    }
    params
}

/// Computes a stage's key from its parameters and the hashes of its inputs.
fn key_stage(plan: &Plan, i: usize, states: &[State], cache: &Cache) -> Result<Keyed, String> {
    let st = &plan.stages[i];
    let mut hashes = BTreeMap::new();
    let mut inputs = BTreeMap::new();
    for inp in &st.inputs {
        let hash = match &inp.source {
            Source::Upstream { stage, port } => match &states[*stage] {
                State::Done(outs) => outs.get(port).map(|o| o.blake3.clone()).ok_or_else(|| {
                    format!(
                        "upstream `{}` has no output `{port}` in its cache entry",
                        plan.stages[*stage].name
                    )
                })?,
                _ => return Err("internal: upstream not resolved".into()),
            },
            Source::Path { path, written } => {
                let (h, _, is_dir) = cache.hash_source(path).map_err(|e| {
                    format!(
                        "input `{}`: cannot read `{written}` ({}): {e}",
                        inp.port,
                        path.display()
                    )
                })?;
                let want_dir = inp.spec.kind == PortKind::Dir;
                if st.kind != command::KIND && is_dir != want_dir {
                    return Err(format!(
                        "input `{}`: `{written}` is a {} but the port expects a {}",
                        inp.port,
                        if is_dir { "directory" } else { "file" },
                        if want_dir { "directory" } else { "file" }
                    ));
                }
                h
            }
        };
        inputs.insert(
            inp.port.clone(),
            (plan.source_label(&inp.source), hash.clone()),
        );
        hashes.insert(inp.port.clone(), hash);
    }
    let params = keyed_params(st);
    let preimage = Preimage::new(&st.kind, st.version, &params, hashes);
    let key = preimage.key();
    Ok(Keyed {
        entry: IndexEntry {
            key: key.clone(),
            kind: st.kind.clone(),
            version: st.version,
            params: params.0,
            inputs,
        },
        key,
        preimage,
    })
}

/// Why a stage must run, by comparison with what the index remembers.
pub fn explain(old: Option<&IndexEntry>, new: &IndexEntry) -> String {
    let Some(old) = old else {
        return "new stage".to_string();
    };
    let mut why = explain_params(old, &new.kind, new.version, &new.params);
    for (port, (src, hash)) in &new.inputs {
        match old.inputs.get(port) {
            None => why.push(format!("input {port} connected to {src}")),
            Some((osrc, _)) if osrc != src => {
                why.push(format!("input {port} now from {src} (was {osrc})"))
            }
            Some((_, ohash)) if ohash != hash => why.push(format!("input {port} changed ({src})")),
            _ => {}
        }
    }
    for port in old.inputs.keys() {
        if !new.inputs.contains_key(port) {
            why.push(format!("input {port} disconnected"));
        }
    }
    if why.is_empty() {
        if old.key == new.key {
            "no cache entry (removed by gc or verify)".to_string()
        } else {
            "key changed (cache schema or engine change)".to_string()
        }
    } else {
        why.join("; ")
    }
}

/// Differences of kind, version and parameters.
fn explain_params(
    old: &IndexEntry,
    kind: &str,
    version: u32,
    params: &BTreeMap<String, fure_stage_api::Value>,
) -> Vec<String> {
    let mut why = Vec::new();
    if old.kind != kind {
        why.push(format!("kind changed from `{}` to `{kind}`", old.kind));
    } else if old.version != version {
        why.push(format!(
            "implementation version changed from {} to {version}",
            old.version
        ));
    }
    for (k, v) in params {
        match old.params.get(k) {
            None => why.push(format!("parameter {k} set to {}", crate::plan::show(v))),
            Some(o) if o != v => why.push(format!(
                "parameter {k} changed from {} to {}",
                crate::plan::show(o),
                crate::plan::show(v)
            )),
            _ => {}
        }
    }
    for (k, o) in &old.params {
        if !params.contains_key(k) {
            why.push(format!(
                "parameter {k} unset or back to a default the key leaves out (was {})",
                crate::plan::show(o)
            ));
        }
    }
    why
}

/// Where a running stage finds an input.
pub(crate) enum InputPath {
    Object(OutputRecord),
    Path(PathBuf),
}

/// Per input port of stage `i` fed by another stage, that output as the pipeline names it.
fn input_origins(plan: &Plan, i: usize) -> BTreeMap<String, String> {
    plan.stages[i]
        .inputs
        .iter()
        .filter_map(|inp| match &inp.source {
            Source::Upstream { stage, port } => Some((
                inp.port.clone(),
                format!("{}.{port}", plan.stages[*stage].name),
            )),
            Source::Path { .. } => None,
        })
        .collect()
}

/// A failed stage's message with the paths of its staging directory (gone once it fails)
/// replaced by what the pipeline calls them: an input by the upstream output it was staged
/// from (`stage.port`, or `` upstream output of `port` `` where the origin is not known), an
/// output by `stage.port`. Longest paths first, so that one staged path inside another is not
/// cut in two.
fn readable_staged_paths(message: String, staged: &[(String, String)]) -> String {
    let mut staged: Vec<&(String, String)> = staged.iter().collect();
    staged.sort_by_key(|(path, _)| std::cmp::Reverse(path.len()));
    staged
        .into_iter()
        .fold(message, |m, (path, name)| m.replace(path.as_str(), name))
}

fn stage_inputs(plan: &Plan, i: usize, states: &[State]) -> Vec<(String, InputPath)> {
    plan.stages[i]
        .inputs
        .iter()
        .map(|inp| {
            let p = match &inp.source {
                Source::Upstream { stage, port } => match &states[*stage] {
                    State::Done(outs) => InputPath::Object(outs[port].clone()),
                    _ => InputPath::Path(PathBuf::new()),
                },
                Source::Path { path, .. } => InputPath::Path(path.clone()),
            };
            (inp.port.clone(), p)
        })
        .collect()
}

fn link_or_copy(src: &Path, dst: &Path) -> std::io::Result<()> {
    if let Some(p) = dst.parent() {
        fs::create_dir_all(p)?;
    }
    match fs::hard_link(src, dst) {
        Ok(()) => Ok(()),
        Err(_) => fs::copy(src, dst).map(|_| ()),
    }
}

/// Links an output's objects under `dest` (`dest` is the file or directory itself).
fn link_output(cache: &Cache, o: &OutputRecord, dest: &Path) -> std::io::Result<()> {
    if o.dir {
        fs::create_dir_all(dest)?;
        for f in &o.files {
            link_or_copy(&cache.object_path(&f.blake3), &dest.join(&f.path))?;
        }
        Ok(())
    } else {
        link_or_copy(&cache.object_path(&o.blake3), dest)
    }
}

fn peak_rss() -> u64 {
    fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines().find(|l| l.starts_with("VmHWM:")).and_then(|l| {
                l.split_whitespace()
                    .nth(1)
                    .and_then(|x| x.parse::<u64>().ok())
            })
        })
        .map(|kb| kb * 1024)
        .unwrap_or(0)
}

/// The job spec of a queued stage (its upstream stages are resolved).
fn job_spec(
    plan: &Plan,
    i: usize,
    states: &[State],
    keyed: &[Option<Keyed>],
) -> crate::slurm::JobSpec {
    use crate::slurm::JobInput;
    let st = &plan.stages[i];
    let k = keyed[i].as_ref().expect("queued stages are keyed");
    let inputs = st
        .inputs
        .iter()
        .map(|inp| {
            let hash = k
                .entry
                .inputs
                .get(&inp.port)
                .map(|(_, h)| h.clone())
                .unwrap_or_default();
            let ji = match &inp.source {
                Source::Upstream { stage, port } => JobInput::Upstream {
                    key: keyed[*stage]
                        .as_ref()
                        .map(|u| u.key.clone())
                        .unwrap_or_default(),
                    port: port.clone(),
                    blake3: match &states[*stage] {
                        State::Done(outs) => outs.get(port).map(|o| o.blake3.clone()),
                        _ => None,
                    }
                    .unwrap_or(hash),
                },
                Source::Path { path, written } => JobInput::Path {
                    path: path.clone(),
                    written: written.clone(),
                    blake3: hash,
                },
            };
            (inp.port.clone(), ji)
        })
        .collect();
    crate::slurm::JobSpec {
        schema: crate::slurm::JOB_SCHEMA,
        pipeline: plan.name.clone(),
        stage: st.name.clone(),
        kind: st.kind.clone(),
        version: st.version,
        key: k.key.clone(),
        params: st.params.0.clone(),
        inputs,
    }
}

/// A valid entry of `key` that is exactly `st`'s, if the cache has one.
fn fitting_entry(cache: &Cache, st: &PlannedStage, key: &str) -> Option<Manifest> {
    let m = cache.lookup_checked(key).ok().flatten()?;
    entry_fits(st, &m)
        .and_then(|()| cache.check_entry(&m))
        .ok()?;
    Some(m)
}

/// Computes one stage through a Slurm job (worker thread of the driver),
/// then reads the entry the job stored. Ok((manifest, computed_by_us)).
fn execute_remote(
    slurm: &crate::slurm::Slurm,
    cache: &Cache,
    st: &PlannedStage,
    spec: &crate::slurm::JobSpec,
) -> Result<(Manifest, bool), String> {
    let found = || fitting_entry(cache, st, &spec.key).is_some();
    let computed = match slurm.run(cache, spec, &found)? {
        crate::slurm::Outcome::Found => false,
        crate::slurm::Outcome::Ran { computed } => computed,
    };
    // The job's manifest was renamed into place on another machine: give a
    // shared file system's attribute cache a moment to show it.
    let t0 = Instant::now();
    loop {
        if let Some(m) = fitting_entry(cache, st, &spec.key) {
            return Ok((m, computed));
        }
        if t0.elapsed() > std::time::Duration::from_secs(10) {
            let why = match cache.lookup_checked(&spec.key) {
                Ok(None) => "no entry".to_string(),
                Ok(Some(m)) => entry_fits(st, &m)
                    .and_then(|()| cache.check_entry(&m))
                    .err()
                    .unwrap_or_default(),
                Err(e) => e,
            };
            return Err(format!(
                "the job ended well but the cache has no valid entry for key {} ({why}); \
                 do the nodes share the cache directory {}?",
                cache::short(&spec.key),
                cache.root().display()
            ));
        }
        std::thread::sleep(std::time::Duration::from_millis(200));
    }
}

/// One stage to compute in this process: which stage of which pipeline,
/// under which key and preimage, from which inputs, on how many threads.
pub(crate) struct Computation<'a> {
    pub pipeline: String,
    pub stage: &'a PlannedStage,
    pub key: String,
    pub preimage: Preimage,
    pub inputs: Vec<(String, InputPath)>,
    /// Per input port fed by another stage, how the pipeline names that output
    /// (`stage.port`): a failing stage's message names its staged inputs so,
    /// since the staging directory is gone once it fails.
    pub origins: BTreeMap<String, String>,
    /// The size of the stage's rayon pool (its CPU tokens).
    pub threads: usize,
}

/// Computes one stage in this process, as a `fure worker` does for a job:
/// under the key's lock, rechecking for an entry first, through the same
/// code as a local run (so the entry is the same, byte for byte). `commit`
/// is asked right before the manifest is written: Err(why) fails the stage
/// and stores no entry (a job that is being cancelled).
/// Ok((manifest, computed_here)).
pub(crate) fn compute_stage(
    cache: &Cache,
    work: Computation<'_>,
    ui: &Ui,
    commit: &dyn Fn() -> Result<(), String>,
) -> Result<(Manifest, bool), String> {
    let progress = ui.started(&work.stage.name, "slurm job");
    let inproc = AtomicUsize::new(0);
    execute(cache, work, &progress, ui, &inproc, commit)
}

/// Computes one stage (worker thread); `commit` may still refuse the entry
/// after the outputs are stored (then they are orphan objects until `gc`).
/// Ok((manifest, computed_here)).
fn execute(
    cache: &Cache,
    work: Computation<'_>,
    progress: &StageProgress,
    ui: &Ui,
    inproc: &AtomicUsize,
    commit: &dyn Fn() -> Result<(), String>,
) -> Result<(Manifest, bool), String> {
    let st = work.stage;
    let key = work.key.as_str();
    let _lock = lock_key_for(cache, st, key, ui)?;
    // Another process may have finished it while we waited.
    if let Some(m) = fitting_entry(cache, st, key) {
        return Ok((m, false));
    }
    let staging = cache.staging(key).map_err(|e| e.to_string())?;
    let in_dir = staging.path.join("in");
    let out_dir = staging.path.join("out");
    fs::create_dir_all(&out_dir).map_err(|e| format!("{}: {e}", out_dir.display()))?;
    let mut staged: Vec<(String, String)> = work
        .inputs
        .iter()
        .filter_map(|(port, p)| match p {
            InputPath::Object(o) => Some((
                in_dir.join(port).join(&o.file_name).display().to_string(),
                work.origins
                    .get(port)
                    .cloned()
                    .unwrap_or_else(|| format!("upstream output of `{port}`")),
            )),
            InputPath::Path(_) => None,
        })
        .collect();
    let ctx = StageContext {
        name: &st.name,
        params: &st.params,
        inputs: stage_input_paths(cache, &in_dir, work.inputs)?,
        outputs: stage_output_paths(st, &out_dir)?,
        progress,
    };
    staged.extend(
        ctx.outputs
            .iter()
            .map(|(port, path)| (path.display().to_string(), format!("{}.{port}", st.name))),
    );
    let t = Instant::now();
    let load = crate::load::Meter::start();
    let (result, peak) = if st.kind == command::KIND {
        match command::run_command(&ctx) {
            Ok(peak) => (Ok(()), peak),
            Err(e) => (Err(e.to_string()), 0),
        }
    } else {
        run_in_process(st, &ctx, work.threads, inproc)?
    };
    let seconds = t.elapsed().as_secs_f64();
    let other_load = load.finish();
    result.map_err(|e| readable_staged_paths(e, &staged))?;
    let outputs =
        store_outputs(cache, st, &ctx.outputs).map_err(|e| readable_staged_paths(e, &staged))?;
    let m = Manifest {
        schema: cache::CACHE_SCHEMA,
        key: key.to_string(),
        kind: st.kind.clone(),
        pipeline: work.pipeline,
        stage: st.name.clone(),
        preimage: work.preimage,
        outputs,
        seconds,
        peak_rss_bytes: peak,
        threads: work.threads as u32,
        other_load,
        fure_version: FURE_VERSION.to_string(),
        created_unix: cache::created_now(),
        notes: progress.notes(),
        seal: String::new(),
    }
    .seal();
    commit()?;
    cache.write_manifest(&m).map_err(|e| e.to_string())?;
    Ok((m, true))
}

/// Takes the key's lock, saying who computes it while it waits.
fn lock_key_for(
    cache: &Cache,
    st: &PlannedStage,
    key: &str,
    ui: &Ui,
) -> Result<cache::KeyLock, String> {
    cache
        .lock_key(key, &|holder| {
            ui.line(&format!(
                "wait    {}  ({})",
                st.name,
                if holder == "this run" {
                    "another stage of this run with the same key is computing it".to_string()
                } else {
                    format!("another fure process is computing it: {holder}")
                }
            ))
        })
        .map_err(|e| e.to_string())
}

/// Each input port's path for the stage: paths as they are, cache objects
/// linked under `in_dir` (the stage reads only these).
fn stage_input_paths(
    cache: &Cache,
    in_dir: &Path,
    inputs: Vec<(String, InputPath)>,
) -> Result<BTreeMap<String, PathBuf>, String> {
    let mut ctx_inputs = BTreeMap::new();
    for (port, p) in inputs {
        let path = match p {
            InputPath::Path(p) => p,
            InputPath::Object(o) => {
                let dest = in_dir.join(&port).join(&o.file_name);
                link_output(cache, &o, &dest)
                    .map_err(|e| format!("preparing input `{port}`: {e}"))?;
                dest
            }
        };
        ctx_inputs.insert(port, path);
    }
    Ok(ctx_inputs)
}

/// Each output port's path under `out_dir` (directory ports created).
fn stage_output_paths(
    st: &PlannedStage,
    out_dir: &Path,
) -> Result<BTreeMap<String, PathBuf>, String> {
    let mut ctx_outputs = BTreeMap::new();
    for spec in &st.outputs {
        let p = out_dir.join(spec.file_name());
        if spec.kind == PortKind::Dir {
            fs::create_dir_all(&p).map_err(|e| format!("{}: {e}", p.display()))?;
        }
        ctx_outputs.insert(spec.name.clone(), p);
    }
    Ok(ctx_outputs)
}

/// Runs an in-process stage inside its own rayon pool of `threads`, a panic
/// caught as its failure: (the stage's result, peak RSS). The peak is reset
/// first when no other in-process stage runs (see the module doc).
fn run_in_process(
    st: &PlannedStage,
    ctx: &StageContext<'_>,
    threads: usize,
    inproc: &AtomicUsize,
) -> Result<(Result<(), String>, u64), String> {
    // The pool first: a failure to build it must not leave the stage counted in.
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads.max(1))
        .thread_name(|i| format!("fure-stage-pool-{i}"))
        .build()
        .map_err(|e| format!("cannot build a thread pool: {e}"))?;
    if inproc.fetch_add(1, Ordering::SeqCst) == 0 {
        let _ = fs::write("/proc/self/clear_refs", "5");
    }
    let r = pool.install(|| std::panic::catch_unwind(AssertUnwindSafe(|| st.stage.run(ctx))));
    inproc.fetch_sub(1, Ordering::SeqCst);
    let r = match r {
        Ok(Ok(())) => Ok(()),
        Ok(Err(e)) => Err(e.to_string()),
        Err(payload) => Err(format!("panicked: {}", panic_message(&payload))),
    };
    Ok((r, peak_rss()))
}

/// Checks every output the stage wrote (present, of its port's type, no
/// link) and stores it as cache objects, in port order.
fn store_outputs(
    cache: &Cache,
    st: &PlannedStage,
    paths: &BTreeMap<String, PathBuf>,
) -> Result<BTreeMap<String, OutputRecord>, String> {
    let mut outputs = BTreeMap::new();
    for spec in &st.outputs {
        let p = &paths[&spec.name];
        // lstat: an output that is a link is refused by store_output, not followed.
        let md = fs::symlink_metadata(p).map_err(|_| {
            format!(
                "did not write its output `{}` ({})",
                spec.name,
                spec.file_name()
            )
        })?;
        let dir = spec.kind == PortKind::Dir;
        if md.is_dir() != dir || !(md.is_dir() || md.is_file()) {
            return Err(format!(
                "output `{}` should be {} but is {}{}",
                spec.name,
                if dir { "a directory" } else { "a regular file" },
                crate::key::file_type_name(&md.file_type()),
                if md.file_type().is_symlink() {
                    " (fure stores no links: copy the file instead)"
                } else {
                    ""
                }
            ));
        }
        let rec = cache
            .store_output(p, &spec.file_name(), dir)
            .map_err(|e| e.to_string())?;
        outputs.insert(spec.name.clone(), rec);
    }
    Ok(outputs)
}

/// The message of a panic payload.
pub fn panic_message(payload: &Box<dyn std::any::Any + Send>) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        s.to_string()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "(no message)".to_string()
    }
}

fn output_reports(
    cache: &Cache,
    m: &Manifest,
    dir: Option<&Path>,
) -> BTreeMap<String, OutputReport> {
    m.outputs
        .iter()
        .map(|(port, o)| {
            let path = match dir {
                Some(d) => d.join(&o.file_name),
                None if o.dir => PathBuf::new(),
                None => cache.object_path(&o.blake3),
            };
            (
                port.clone(),
                OutputReport {
                    path: path.display().to_string(),
                    blake3: o.blake3.clone(),
                    bytes: o.bytes,
                },
            )
        })
        .collect()
}

/// Materialises a resolved stage's outputs (when the run has an `out/`);
/// Err is the stage's failure message.
fn materialise_outputs(
    cache: &Cache,
    opts: &RunOptions,
    plan: &Plan,
    st: &PlannedStage,
    m: &Manifest,
) -> Result<BTreeMap<String, OutputReport>, String> {
    let Some(root) = &opts.out_root else {
        return Ok(output_reports(cache, m, None));
    };
    let dir = root.join(&plan.name).join(&st.name);
    materialise(cache, m, &dir)
        .map_err(|e| format!("cannot materialise outputs in {}: {e}", dir.display()))?;
    Ok(output_reports(cache, m, Some(&dir)))
}

/// Whether a (validated) manifest has exactly the outputs the planned stage
/// declares, under the names it declares: a manifest is never trusted to
/// say where its files go.
fn entry_fits(st: &PlannedStage, m: &Manifest) -> Result<(), String> {
    if m.outputs.len() != st.outputs.len() {
        return Err("the manifest's outputs are not the stage's".into());
    }
    for spec in &st.outputs {
        let ok = m.outputs.get(&spec.name).is_some_and(|o| {
            o.file_name == spec.file_name() && o.dir == (spec.kind == PortKind::Dir)
        });
        if !ok {
            return Err(format!(
                "the manifest's output `{}` is not the stage's",
                spec.name
            ));
        }
    }
    Ok(())
}

/// The temporary-name prefix of materialisation; `<prefix><pid>-` marks whose.
const TMP_PREFIX: &str = ".fure-tmp-";

/// Whether a name is another live process's materialisation temporary (a
/// concurrent run into the same `out/` must not lose it).
fn live_foreign_tmp(name: &str) -> bool {
    name.strip_prefix(TMP_PREFIX)
        .and_then(|r| r.split('-').next())
        .and_then(|p| p.parse::<u32>().ok())
        .is_some_and(|pid| pid != std::process::id() && Path::new(&format!("/proc/{pid}")).exists())
}

/// Removes a file, a missing one being fine (a concurrent run may have
/// removed it first).
fn remove_file_if_there(p: &Path) -> std::io::Result<()> {
    match fs::remove_file(p) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(e),
        _ => Ok(()),
    }
}

/// Everything but directories under `root` (links not followed), with
/// relative paths: what may have to go from a materialised directory.
fn non_dirs(root: &Path) -> std::io::Result<Vec<(String, PathBuf)>> {
    fn walk(dir: &Path, rel: &str, out: &mut Vec<(String, PathBuf)>) -> std::io::Result<()> {
        for e in fs::read_dir(dir)? {
            let e = e?;
            let name = e.file_name().to_string_lossy().into_owned();
            let r = if rel.is_empty() {
                name
            } else {
                format!("{rel}/{name}")
            };
            if e.file_type()?.is_dir() {
                walk(&e.path(), &r, out)?;
            } else {
                out.push((r, e.path()));
            }
        }
        Ok(())
    }
    let mut out = Vec::new();
    walk(root, "", &mut out)?;
    Ok(out)
}

/// Makes `dir` hold exactly the entry's outputs, as hard links to objects
/// (copies where linking is refused; a copy with the object's size and
/// content is kept, so a no-op run copies nothing again).
pub fn materialise(cache: &Cache, m: &Manifest, dir: &Path) -> std::io::Result<()> {
    static N: AtomicUsize = AtomicUsize::new(0);
    let mut changed = false;
    fs::create_dir_all(dir)?;
    for o in m.outputs.values() {
        for (hash, bytes, rel) in o.objects() {
            let obj = cache.object_path(hash);
            let target = dir.join(&rel);
            let same = match (fs::symlink_metadata(&target), fs::symlink_metadata(&obj)) {
                (Ok(t), Ok(ob)) if t.is_file() => {
                    (t.ino() == ob.ino() && t.dev() == ob.dev())
                        || (t.len() == bytes
                            && cache
                                .hash_file_hinted(&target)
                                .is_ok_and(|(h, _)| h == hash))
                }
                _ => false,
            };
            if same {
                continue;
            }
            changed = true;
            if let Ok(md) = fs::symlink_metadata(&target) {
                if md.is_dir() {
                    cache::remove_tree(&target)?;
                }
            }
            if let Some(p) = target.parent() {
                if fs::symlink_metadata(p).is_ok_and(|md| !md.is_dir()) {
                    fs::remove_file(p)?;
                }
                fs::create_dir_all(p)?;
            }
            // Unique per process and call, so concurrent runs never share one.
            let tmp = target.with_file_name(format!(
                "{TMP_PREFIX}{}-{}-{}",
                std::process::id(),
                N.fetch_add(1, Ordering::Relaxed),
                target
                    .file_name()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_default()
            ));
            let _ = fs::remove_file(&tmp);
            let res = link_or_copy(&obj, &tmp).and_then(|()| fs::rename(&tmp, &target));
            if let Err(e) = res {
                // No partial temporary is left behind (a full disk, say).
                let _ = fs::remove_file(&tmp);
                return Err(e);
            }
        }
    }
    if changed {
        // Remove what is not an output any more.
        let keep: std::collections::BTreeSet<String> =
            m.outputs.values().map(|o| o.file_name.clone()).collect();
        for e in fs::read_dir(dir)?.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            if !keep.contains(&name) && !live_foreign_tmp(&name) {
                let p = e.path();
                if e.file_type().is_ok_and(|t| t.is_dir()) {
                    cache::remove_tree(&p)?;
                } else {
                    remove_file_if_there(&p)?;
                }
            }
        }
        for o in m.outputs.values().filter(|o| o.dir) {
            let wanted: std::collections::BTreeSet<&str> =
                o.files.iter().map(|f| f.path.as_str()).collect();
            for (rel, p) in non_dirs(&dir.join(&o.file_name))? {
                let name = rel.rsplit('/').next().unwrap_or(&rel);
                if !wanted.contains(rel.as_str()) && !live_foreign_tmp(name) {
                    remove_file_if_there(&p)?;
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use fure_stage_api::Value;

    fn entry(version: u32, x: f64, hash: &str) -> IndexEntry {
        IndexEntry {
            key: format!("{version}{x}{hash}"),
            kind: "k".into(),
            version,
            params: BTreeMap::from([("x".to_string(), Value::Float(x))]),
            inputs: BTreeMap::from([("src".to_string(), ("a.out".to_string(), hash.to_string()))]),
        }
    }

    #[test]
    fn explains_each_kind_of_change() {
        let old = entry(1, 1.0, "h");
        assert_eq!(explain(None, &old), "new stage");
        assert_eq!(
            explain(Some(&old), &entry(2, 1.0, "h")),
            "implementation version changed from 1 to 2"
        );
        assert_eq!(
            explain(Some(&old), &entry(1, 2.5, "h")),
            "parameter x changed from 1.0 to 2.5"
        );
        assert_eq!(
            explain(Some(&old), &entry(1, 1.0, "h2")),
            "input src changed (a.out)"
        );
        assert_eq!(
            explain(Some(&old), &old),
            "no cache entry (removed by gc or verify)"
        );
        let mut moved = old.clone();
        moved
            .inputs
            .insert("src".into(), ("b.out".into(), "h".into()));
        assert_eq!(
            explain(Some(&old), &moved),
            "input src now from b.out (was a.out)"
        );
    }

    /// A stage whose later version gains an option `extra` (weight 0 = as before).
    struct Growing {
        with_option: bool,
    }

    impl fure_stage_api::Stage for Growing {
        fn kind(&self) -> &'static str {
            "growing"
        }
        fn version(&self) -> u32 {
            1
        }
        fn doc(&self) -> &'static str {
            "test stage"
        }
        fn params(&self) -> Vec<fure_stage_api::ParamSpec> {
            let mut specs = vec![fure_stage_api::ParamSpec::float("x", 1.0, "a value")];
            if self.with_option {
                specs.push(
                    fure_stage_api::ParamSpec::float("extra", 0.0, "an added option")
                        .omit_default_from_key(),
                );
            }
            specs
        }
        fn inputs(&self, _: &fure_stage_api::Params) -> Vec<fure_stage_api::PortSpec> {
            Vec::new()
        }
        fn outputs(&self, _: &fure_stage_api::Params) -> Vec<fure_stage_api::PortSpec> {
            Vec::new()
        }
        fn run(
            &self,
            _: &fure_stage_api::StageContext<'_>,
        ) -> Result<(), fure_stage_api::StageError> {
            Ok(())
        }
    }

    fn growing_key(with_option: bool, params: &[(&str, Value)]) -> String {
        let st = PlannedStage {
            name: "s".into(),
            kind: "growing".into(),
            version: 1,
            stage: std::sync::Arc::new(Growing { with_option }),
            params: fure_stage_api::Params(
                params
                    .iter()
                    .map(|(k, v)| (k.to_string(), v.clone()))
                    .collect(),
            ),
            inputs: Vec::new(),
            outputs: Vec::new(),
            upstream: Vec::new(),
            loc: crate::pipeline::Loc::origin("test"),
        };
        Preimage::new(&st.kind, st.version, &keyed_params(&st), BTreeMap::new()).key()
    }

    #[test]
    fn an_option_at_its_default_keeps_the_key_it_had_before_it_existed() {
        // The stage's key for `x`, before the option existed (`None`) or with it set.
        let key = |x: f64, extra: Option<f64>| {
            let mut params = vec![("x", Value::Float(x))];
            params.extend(extra.map(|e| ("extra", Value::Float(e))));
            growing_key(extra.is_some(), &params)
        };
        let before = key(1.0, None);
        assert_eq!(before, key(1.0, Some(0.0)));
        // -0.0 is the key's 0.0.
        assert_eq!(before, key(1.0, Some(-0.0)));
        // Set to anything else, it enters the key as any parameter does.
        assert_ne!(before, key(1.0, Some(0.3)));
        // Parameters without the flag stay in the key: a new `x` is a new key, with or
        // without the option, and so is an `x` left out.
        assert_ne!(before, key(2.0, Some(0.0)));
        assert_ne!(before, growing_key(false, &[]));
    }

    #[test]
    fn a_parameter_read_back_from_the_index_is_unchanged() {
        // f32 defaults widened to f64 have long decimal forms; the index
        // stores them as JSON numbers and must read back the same bits, or
        // the reason line reports a change the key does not see.
        for x in [0.03f32 as f64, 0.1f32 as f64, 1e-13, 0.005f32 as f64] {
            let old = entry(1, x, "h");
            let json = serde_json::to_string(&old).unwrap();
            let back: IndexEntry = serde_json::from_str(&json).unwrap();
            assert_eq!(
                explain(Some(&back), &old),
                "no cache entry (removed by gc or verify)",
                "{x:e}"
            );
        }
    }
}
