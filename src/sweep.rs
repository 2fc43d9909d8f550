//! Sweeps: run every variant of a parameter grid on a shared cache, give each
//! a status, write a deterministic record of the whole sweep and run the
//! pipeline's aggregate stages on it.
//!
//! # Axes and variants
//!
//! ```toml
//! [sweep]                                   # crossed axes (cartesian product)
//! "scene.preset" = ["tiger", "bison"]
//! [sweep.each]                              # varied one at a time
//! "corrupt.noise_sigma" = [0.0, 0.02, 0.05, 0.1]
//! "corrupt.jitter_deg"  = [0.0, 0.5, 1.0, 2.0]
//! ```
//!
//! Variants = cartesian(crossed axes) x one-at-a-time points. The crossed
//! axes are taken in sorted key order, the last key varying fastest. For each
//! crossed point the one-at-a-time points are: the *base point* (every `each`
//! axis at its first value), then, for each `each` axis in declaration order,
//! every other value of that axis with the other `each` axes held at their
//! first value. The example gives 2 x (1 + 3 + 3) = 14 variants. Every
//! variant's settings list every swept key, held ones included (crossed keys
//! sorted, then `each` keys in declaration order), so a table row describes
//! itself; [`Variant::varied`] names the `each` key a variant moves (`None`
//! for a base point). A key may link several targets, `"scene.seed,codec.seed"
//! = [0, 1]`: every target takes the axis's value (one axis, not a product),
//! for settings that must move together (a scene's seed and its learners',
//! a preset and its species table). `--grid KEY=...` replaces an axis's values (keeping its
//! kind) or adds a crossed axis; `--each KEY=...` replaces or adds a
//! one-at-a-time axis.
//!
//! Each variant is the pipeline with its settings applied, named
//! `<pipeline>@v<N>` (outputs in `out/<pipeline>@v<N>/`), run on the same
//! cache, so a stage upstream of every varied parameter is computed once and
//! hit by every other variant. Locally the variants run one after another;
//! with a remote executor (`--executor slurm`, [`crate::slurm`]) they run at
//! once, their stages as jobs, a key shared by variants being submitted once
//! (the others wait for it and take the entry), and the rows follow in
//! variant order when all are done. Every variant is checked (planned) before any
//! runs: an invalid variant, or an invalid aggregate stage, is a pipeline
//! error (exit 2) and nothing runs.
//!
//! # Status of a variant
//!
//! A sweep does not stop at a failure: variants run with keep-going (a failed
//! stage skips only its dependents, independent branches still run) and every
//! variant ends with a [`VariantStatus`]. The one exception is a full disk: a
//! variant with a stage that failed on ENOSPC ends the sweep there (run one
//! variant at a time; a remote executor runs them all at once), since every
//! later variant would fail stage by stage on the same disk; the CLI then
//! reports it as it reports an interrupted sweep (no record, nothing
//! published, the same command resumes once space is freed). Statuses:
//! - `failed`: some stage failed; reason `"<stage>: <first line of its
//!   error>"` for the first failed stage in plan order, plus `" (+N more)"`
//!   (a first line ending in `:`, like a command's `...; stderr tail:`, takes
//!   the next line along);
//! - `degraded`: no failure, but some stage's `metrics.json` has a non-empty
//!   top-level `warnings` array; reason `"<stage>: <warning>; ..."` (stages
//!   in plan order; non-string elements are shown as compact JSON);
//! - `ok`: neither (empty reason).
//!
//! Paths into the cache's staging directories (named after the process id)
//! are shown as `<staging>` in reasons and warnings, so that a variant that
//! fails the same way gives the same record on every run.
//!
//! # Tables and the record
//!
//! The table has one row per variant: the settings, status, reason, how many
//! stages ran and were cached, the wall seconds, the compute seconds of each
//! stage (of its cache entry, also when it was a hit; Markdown marks hits
//! with `*`), and every number in the stages' `metrics.json` outputs,
//! flattened as `stage.key.subkey` (booleans as 0/1).
//!
//! The record ([`record`], written to `out/<pipeline>/sweep.json`) is the
//! sweep as data for aggregate stages:
//!
//! ```json
//! {"pipeline": "p", "crossed": {"KEY": [values]}, "each": {"KEY": [values]},
//!  "each_order": ["KEY", ...],
//!  "variants": [{"index": 0, "name": "p@v0", "settings": {"KEY": value},
//!                "varied": null, "status": "ok", "reason": "", "failed_stage": null,
//!                "warnings": ["stage: text"], "metrics": {"stage.key": 1.5},
//!                "costs": {"stage": {"seconds": 2.5, "peak_rss_bytes": 1048576, "threads": 2,
//!                                    "other_load": 0.0}}}]}
//! ```
//!
//! Object keys are sorted (so `each_order` keeps the declaration order of
//! the `each` axes); `metrics` leaves out every key whose last component
//! contains `seconds` or `time` (case-insensitive) and holds no paths, so the
//! record of an unchanged, cached sweep is byte-identical from run to run
//! and the aggregate stages keyed on it stay cached. What the stages cost is
//! kept apart, in `costs` (`{"STAGE": {"seconds", "peak_rss_bytes",
//! "threads", "other_load"}}` of each stage's cache entry, the figures of the
//! run that computed it, the size of its thread pool and the cores other work
//! used meanwhile, [`crate::load`]; a figure an entry lacks is left out),
//! which a cached sweep reads back unchanged too. The file is replaced
//! atomically, and only when its bytes change.
//!
//! # Aggregate stages
//!
//! ```toml
//! [aggregate.report]
//! kind = "stability_report"   # any kind with exactly one input port, a `.json` file
//! baseline_drop = 0.2         # parameters, checked like any stage's
//! ```
//!
//! After all variants, the aggregates run as the ordinary cached stages of one
//! pipeline named `<pipeline>` (no other stage), planned and run by
//! [`crate::plan`] and [`crate::exec`] like any pipeline: each one's single
//! input port is bound to the record file (an ordinary file input, so the key
//! is kind, version, parameters and the record's content hash), and outputs
//! land in `out/<pipeline>/<aggregate>/`. The `command` kind declares its
//! ports through `deps`, so a `command` aggregate gets `deps = { sweep =
//! <record> }` from the engine (`{deps.sweep}` in `cmd` is the record's path)
//! and must not set `deps` itself. Aggregates must not share a name with a
//! stage (both would materialise in `out/<pipeline>/<name>/`), take no
//! `inputs`, and run only under `fure sweep`. An aggregate that fails is
//! reported like any failed stage.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use fure_stage_api::{PortKind, Stage, Value};
use serde_json::json;

use crate::cache::Cache;
use crate::command;
use crate::exec::{self, RunOptions, RunReport, Status};
use crate::pipeline::{
    InputDecl, Loc, ParamDecl, Pipeline, PipelineError, PipelineErrors, StageDecl,
};
use crate::plan::{self, show, Plan, Source};
use crate::Engine;

/// One variant of the grid.
#[derive(Debug, Clone)]
pub struct Variant {
    pub index: usize,
    /// Every swept key: crossed keys (sorted), then `each` keys (declared order).
    pub settings: Vec<(String, Value)>,
    /// The `[sweep.each]` key this variant moves off its first value; `None`
    /// for a base point.
    pub varied: Option<String>,
}

/// The axes of a sweep after `--grid` and `--each`.
#[derive(Debug, Clone, Default)]
pub struct Axes {
    /// Crossed axes (cartesian product), sorted by key.
    pub crossed: BTreeMap<String, Vec<Value>>,
    /// One-at-a-time axes, in declaration order.
    pub each: Vec<(String, Vec<Value>)>,
}

impl Axes {
    /// The pipeline's `[sweep]` and `[sweep.each]`, then `grid` (replaces an
    /// axis's values, keeping its kind; a new key is crossed) and `each`
    /// (replaces or adds a one-at-a-time axis).
    pub fn new(
        pipeline: &Pipeline,
        grid: &[(String, Vec<Value>)],
        each: &[(String, Vec<Value>)],
    ) -> Axes {
        let mut a = Axes {
            crossed: pipeline
                .sweep
                .iter()
                .map(|(k, (v, _))| (k.clone(), v.clone()))
                .collect(),
            each: pipeline
                .sweep_each
                .iter()
                .map(|(k, v, _)| (k.clone(), v.clone()))
                .collect(),
        };
        for (k, v) in grid {
            match a.each.iter_mut().find(|(e, _)| e == k) {
                Some(slot) => slot.1 = v.clone(),
                None => {
                    a.crossed.insert(k.clone(), v.clone());
                }
            }
        }
        for (k, v) in each {
            a.crossed.remove(k);
            match a.each.iter_mut().find(|(e, _)| e == k) {
                Some(slot) => slot.1 = v.clone(),
                None => a.each.push((k.clone(), v.clone())),
            }
        }
        a
    }

    /// The axes a sweep record says it ran (its `crossed`, `each` and
    /// `each_order`), so that what a command line's `--grid`/`--each` added
    /// can be found again (`gc --keep`). The record is untrusted input: an
    /// error names the field and what was expected.
    pub fn from_record(record: &serde_json::Value) -> Result<Axes, String> {
        let values = |field: &str, key: &str, v: &serde_json::Value| {
            let list = v
                .as_array()
                .ok_or_else(|| format!("`{field}.{key}`: expected an array of values"))?;
            list.iter()
                .map(|x| {
                    serde_json::from_value::<Value>(x.clone())
                        .map_err(|e| format!("`{field}.{key}`: {e}"))
                })
                .collect::<Result<Vec<Value>, String>>()
        };
        let object = |field: &str| {
            record
                .get(field)
                .and_then(|v| v.as_object())
                .ok_or_else(|| format!("`{field}`: expected an object of axes"))
        };
        let crossed = object("crossed")?
            .iter()
            .map(|(k, v)| Ok((k.clone(), values("crossed", k, v)?)))
            .collect::<Result<BTreeMap<_, _>, String>>()?;
        let each_map = object("each")?;
        let order = record
            .get("each_order")
            .and_then(|v| v.as_array())
            .ok_or("`each_order`: expected an array of keys")?;
        let mut each = Vec::with_capacity(order.len());
        for k in order {
            let k = k.as_str().ok_or("`each_order`: expected strings")?;
            let v = each_map
                .get(k)
                .ok_or_else(|| format!("`each_order` names `{k}`, which `each` lacks"))?;
            each.push((k.to_string(), values("each", k, v)?));
        }
        if each.len() != each_map.len() {
            return Err("`each` has keys `each_order` does not list".into());
        }
        Ok(Axes { crossed, each })
    }

    /// The variants, in the order described in the module docs.
    pub fn variants(&self) -> Vec<Variant> {
        let mut points: Vec<Vec<(String, Value)>> = vec![Vec::new()];
        for (k, values) in &self.crossed {
            let mut next = Vec::with_capacity(points.len() * values.len());
            for p in &points {
                for x in values {
                    let mut s = p.clone();
                    s.push((k.clone(), x.clone()));
                    next.push(s);
                }
            }
            points = next;
        }
        // Empty value lists cannot come from a pipeline file; skip such axes.
        let each: Vec<&(String, Vec<Value>)> =
            self.each.iter().filter(|(_, v)| !v.is_empty()).collect();
        let base: Vec<(String, Value)> = each
            .iter()
            .map(|(k, v)| (k.clone(), v[0].clone()))
            .collect();
        let mut out = Vec::new();
        for p in points {
            let mut first = p.clone();
            first.extend(base.iter().cloned());
            out.push((first, None));
            for (j, (k, values)) in each.iter().enumerate() {
                for x in &values[1..] {
                    let mut s = p.clone();
                    s.extend(base.iter().cloned());
                    s[p.len() + j].1 = x.clone();
                    out.push((s, Some(k.clone())));
                }
            }
        }
        out.into_iter()
            .enumerate()
            .map(|(index, (settings, varied))| Variant {
                index,
                settings,
                varied,
            })
            .collect()
    }
}

/// The variants of a pipeline's `[sweep]`/`[sweep.each]` plus `--grid` axes.
pub fn grid(pipeline: &Pipeline, extra: &[(String, Vec<Value>)]) -> Vec<Variant> {
    Axes::new(pipeline, extra, &[]).variants()
}

/// How a variant ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VariantStatus {
    Ok,
    Degraded,
    Failed,
}

impl VariantStatus {
    pub fn as_str(self) -> &'static str {
        match self {
            VariantStatus::Ok => "ok",
            VariantStatus::Degraded => "degraded",
            VariantStatus::Failed => "failed",
        }
    }
}

/// A stage's cost, from its cache entry (the run that computed it).
#[derive(Debug, Clone, PartialEq)]
pub struct Cost {
    pub seconds: f64,
    pub peak_rss_bytes: u64,
    /// Its pool's threads; 0: not recorded.
    pub threads: u32,
    /// Cores other work used meanwhile ([`crate::load`]).
    pub other_load: Option<f32>,
}

/// The stage runs of `rows` whose cache entries say other work used more than
/// [`crate::load::BUSY_CORES`] cores meanwhile, and the largest such figure.
pub fn busy_stage_runs(rows: &[Row]) -> (usize, f32) {
    rows.iter()
        .flat_map(|r| r.costs.values())
        .filter_map(|c| c.other_load)
        .filter(|&l| l > crate::load::BUSY_CORES)
        .fold((0, 0.0), |(n, max), l| (n + 1, max.max(l)))
}

/// One row of the sweep table.
#[derive(Debug, Clone)]
pub struct Row {
    pub variant: Variant,
    pub name: String,
    pub report: RunReport,
    /// stage -> compute seconds (of the entry), cached?
    pub stage_seconds: BTreeMap<String, (f64, bool)>,
    /// stage -> what its cache entry says it cost.
    pub costs: BTreeMap<String, Cost>,
    /// Every number of every stage's `metrics.json`, flattened.
    pub metrics: BTreeMap<String, f64>,
    pub status: VariantStatus,
    /// Empty for `ok`.
    pub reason: String,
    /// The first failed stage in plan order.
    pub failed_stage: Option<String>,
    /// `"<stage>: <warning>"`, stages in plan order.
    pub warnings: Vec<String>,
}

/// Where the variant's value of `target` was written (for error messages).
fn setting_loc(pipeline: &Pipeline, target: &str) -> Loc {
    if let Some((_, l)) = pipeline.sweep.get(target) {
        return l.clone();
    }
    if let Some((_, _, l)) = pipeline.sweep_each.iter().find(|(k, _, _)| k == target) {
        return l.clone();
    }
    Loc::origin(&format!("--grid/--each {target}"))
}

/// The `STAGE.PARAM` targets of a sweep key: one, or several linked ones
/// separated by commas (`"scene.seed,codec.seed"` sets both to each value).
pub fn linked_targets(key: &str) -> impl Iterator<Item = &str> {
    key.split(',').map(str::trim)
}

/// The pipeline of one variant (settings applied, named `<pipeline>@v<N>`).
pub fn variant_pipeline(pipeline: &Pipeline, v: &Variant) -> Result<Pipeline, PipelineErrors> {
    let mut p = pipeline.clone();
    let mut errors = Vec::new();
    for (key, value) in &v.settings {
        for target in linked_targets(key) {
            if let Err(e) = p.set_param(target, value.clone(), &setting_loc(pipeline, key)) {
                errors.push(e);
            }
        }
    }
    if !errors.is_empty() {
        return Err(PipelineErrors(errors));
    }
    p.name = format!("{}@v{}", pipeline.name, v.index);
    Ok(p)
}

/// Runs every variant, each to the end (keep-going), after checking every
/// variant and every aggregate stage; an invalid one is an error and nothing
/// runs. `on_start` is called before a variant runs (locally, one at a time;
/// not with a remote executor, whose variants run at once), `on_row` when it
/// has ended.
pub fn run_sweep(
    engine: &Engine,
    pipeline: &Pipeline,
    variants: &[Variant],
    cache: &Cache,
    opts: &RunOptions,
    on_start: &mut dyn FnMut(&Variant),
    on_row: &mut dyn FnMut(&Row),
) -> Result<Vec<Row>, PipelineErrors> {
    let mut plans = Vec::new();
    for v in variants {
        let p = variant_pipeline(pipeline, v)?;
        let plan = engine.plan(&p).map_err(|mut e| {
            e.0.insert(
                0,
                PipelineError::bare(format!(
                    "sweep variant {} ({}) is invalid:",
                    v.index,
                    describe(v)
                )),
            );
            e
        })?;
        plans.push(plan);
    }
    // The record does not exist yet: check the aggregates against a stand-in
    // file that always exists.
    plan_aggregates(engine, pipeline, Path::new("/dev/null"))?;
    let opts = RunOptions {
        keep_going: true,
        ..opts.clone()
    };
    let mut rows = Vec::new();
    if opts.executor.is_remote() {
        // Variants run at once, their stages as jobs (the executor bounds
        // the jobs in flight; a key shared by variants is computed once).
        let reports: Vec<RunReport> = std::thread::scope(|s| {
            let handles: Vec<_> = plans
                .iter()
                .map(|plan| {
                    let opts = &opts;
                    s.spawn(move || exec::run(plan, cache, opts))
                })
                .collect();
            handles
                .into_iter()
                .map(|h| h.join().unwrap_or_else(|p| std::panic::resume_unwind(p)))
                .collect()
        });
        for ((v, plan), report) in variants.iter().zip(&plans).zip(reports) {
            let row = make_row(v, plan, report, cache);
            on_row(&row);
            rows.push(row);
        }
        return Ok(rows);
    }
    for (v, plan) in variants.iter().zip(&plans) {
        // Interrupted: the variants not started stay unstarted (see `cmd_sweep`).
        if crate::signals::received().is_some() {
            break;
        }
        on_start(v);
        let report = exec::run(plan, cache, &opts);
        let row = make_row(v, plan, report, cache);
        on_row(&row);
        rows.push(row);
        if stopped_on_full_disk(&rows) {
            break;
        }
    }
    Ok(rows)
}

/// Whether the last variant run had a stage fail on a full disk (the
/// sequential sweep stops there; module doc).
pub fn stopped_on_full_disk(rows: &[Row]) -> bool {
    rows.last()
        .is_some_and(|r| r.report.stages.iter().any(|s| s.failed_on_full_disk()))
}

/// The parsed `metrics.json` of each stage that has one, in plan order.
fn stage_metrics(report: &RunReport, cache: &Cache) -> Vec<(String, serde_json::Value)> {
    let mut out = Vec::new();
    for s in &report.stages {
        for o in s.outputs.values() {
            if !o.path.ends_with("metrics.json") {
                continue;
            }
            let path = if Path::new(&o.path).exists() {
                PathBuf::from(&o.path)
            } else {
                cache.object_path(&o.blake3)
            };
            if let Some(j) = std::fs::read(&path)
                .ok()
                .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
            {
                out.push((s.name.clone(), j));
            }
        }
    }
    out
}

fn make_row(v: &Variant, plan: &Plan, report: RunReport, cache: &Cache) -> Row {
    let mut stage_seconds = BTreeMap::new();
    let mut costs = BTreeMap::new();
    for s in &report.stages {
        if matches!(s.status, Status::Ran | Status::Cached) {
            let entry = cache.lookup(&s.key);
            let secs = entry.as_ref().map(|m| m.seconds).unwrap_or(s.seconds);
            stage_seconds.insert(s.name.clone(), (secs, s.status == Status::Cached));
            if let Some(m) = entry {
                costs.insert(
                    s.name.clone(),
                    Cost {
                        seconds: m.seconds,
                        peak_rss_bytes: m.peak_rss_bytes,
                        threads: m.threads,
                        other_load: m.other_load,
                    },
                );
            }
        }
    }
    let mut metrics = BTreeMap::new();
    let mut warnings = Vec::new();
    for (stage, j) in stage_metrics(&report, cache) {
        flatten(&stage, &j, &mut metrics);
        if let Some(list) = j.get("warnings").and_then(|w| w.as_array()) {
            for w in list {
                let text = match w {
                    serde_json::Value::String(s) => s.clone(),
                    other => other.to_string(),
                };
                warnings.push(format!("{stage}: {}", one_line(&text)));
            }
        }
    }
    let (status, mut reason, failed_stage) = classify(&report, &warnings);
    let staging = staging_prefixes(cache);
    reason = scrub(&reason, &staging);
    for w in &mut warnings {
        *w = scrub(w, &staging);
    }
    Row {
        variant: v.clone(),
        name: plan.name.clone(),
        report,
        stage_seconds,
        costs,
        metrics,
        status,
        reason,
        failed_stage,
        warnings,
    }
}

/// The staging-directory prefixes of a cache (`<root>/tmp/`, as given and canonical).
fn staging_prefixes(cache: &Cache) -> Vec<String> {
    let mut v = vec![format!("{}/", cache.root().join("tmp").display())];
    if let Ok(c) = cache.root().canonicalize() {
        v.push(format!("{}/", c.join("tmp").display()));
    }
    if let Ok(a) = std::path::absolute(cache.root()) {
        v.push(format!("{}/", a.join("tmp").display()));
    }
    // Longest first, so an absolute prefix is not cut by a relative one.
    v.sort_by_key(|p| std::cmp::Reverse(p.len()));
    v.dedup();
    v
}

/// Replaces `<prefix><staging dir name>` by `<staging>`: staging directories
/// are named after the process id, which would make a failed variant's reason
/// (and so the record) differ from run to run.
fn scrub(text: &str, prefixes: &[String]) -> String {
    let mut out = text.to_string();
    for p in prefixes {
        let mut done = String::new();
        let mut rest = out.as_str();
        while let Some(i) = rest.find(p.as_str()) {
            done.push_str(&rest[..i]);
            done.push_str("<staging>");
            let after = &rest[i + p.len()..];
            let end = after.find('/').unwrap_or(after.len());
            rest = &after[end..];
        }
        done.push_str(rest);
        out = done;
    }
    out
}

/// Newlines and tabs as spaces, trimmed.
fn one_line(s: &str) -> String {
    s.split_whitespace().collect::<Vec<_>>().join(" ")
}

/// Status, reason and first failed stage of a variant's run.
fn classify(report: &RunReport, warnings: &[String]) -> (VariantStatus, String, Option<String>) {
    let failed: Vec<_> = report
        .stages
        .iter()
        .filter(|s| s.status == Status::Failed)
        .collect();
    if let Some(first) = failed.first() {
        let mut lines = first
            .error
            .as_deref()
            .unwrap_or("")
            .lines()
            .map(str::trim)
            .filter(|l| !l.is_empty());
        let mut msg = lines.next().unwrap_or("failed").to_string();
        // A first line that announces what follows ("...; stderr tail:")
        // takes the next line too.
        if msg.ends_with(':') {
            if let Some(next) = lines.next() {
                msg = format!("{msg} {next}");
            }
        }
        let mut reason = format!("{}: {msg}", first.name);
        if failed.len() > 1 {
            let _ = write!(reason, " (+{} more)", failed.len() - 1);
        }
        return (VariantStatus::Failed, reason, Some(first.name.clone()));
    }
    // Keep-going leaves skips only below failures; anything else is a failure too.
    if let Some(s) = report.stages.iter().find(|s| s.status == Status::Skipped) {
        return (
            VariantStatus::Failed,
            format!("{}: skipped ({})", s.name, s.reason),
            Some(s.name.clone()),
        );
    }
    if !warnings.is_empty() {
        return (VariantStatus::Degraded, warnings.join("; "), None);
    }
    (VariantStatus::Ok, String::new(), None)
}

/// `STAGE.PARAM=value, ...` of a variant.
pub fn describe(v: &Variant) -> String {
    if v.settings.is_empty() {
        return "base".to_string();
    }
    v.settings
        .iter()
        .map(|(k, x)| format!("{k}={}", show(x)))
        .collect::<Vec<_>>()
        .join(", ")
}

fn flatten(prefix: &str, j: &serde_json::Value, out: &mut BTreeMap<String, f64>) {
    match j {
        serde_json::Value::Number(n) => {
            if let Some(x) = n.as_f64() {
                out.insert(prefix.to_string(), x);
            }
        }
        serde_json::Value::Bool(b) => {
            out.insert(prefix.to_string(), if *b { 1.0 } else { 0.0 });
        }
        serde_json::Value::Object(m) => {
            for (k, v) in m {
                flatten(&format!("{prefix}.{k}"), v, out);
            }
        }
        _ => {}
    }
}

/// Whether a flattened metric is a timing (left out of the record).
fn is_timing(key: &str) -> bool {
    let last = key.rsplit('.').next().unwrap_or(key).to_ascii_lowercase();
    last.contains("seconds") || last.contains("time")
}

fn value_json(v: &Value) -> serde_json::Value {
    serde_json::to_value(v).unwrap_or(serde_json::Value::Null)
}

/// The sweep record (see the module docs); object keys are sorted.
pub fn record(pipeline: &str, axes: &Axes, rows: &[Row]) -> serde_json::Value {
    let variants: Vec<serde_json::Value> = rows.iter().map(variant_entry).collect();
    record_of(pipeline, axes, variants)
}

/// A variant's settings as its record entry writes them.
pub fn settings_json(v: &Variant) -> serde_json::Value {
    serde_json::Value::Object(
        v.settings
            .iter()
            .map(|(k, x)| (k.clone(), value_json(x)))
            .collect(),
    )
}

/// One variant's entry in the record.
fn variant_entry(r: &Row) -> serde_json::Value {
    let metrics: serde_json::Map<String, serde_json::Value> = r
        .metrics
        .iter()
        .filter(|(k, _)| !is_timing(k))
        .map(|(k, x)| (k.clone(), json!(x)))
        .collect();
    let costs: serde_json::Map<String, serde_json::Value> = r
        .costs
        .iter()
        .map(|(k, cost)| {
            let mut c = json!({"seconds": cost.seconds, "peak_rss_bytes": cost.peak_rss_bytes});
            if cost.threads > 0 {
                c["threads"] = json!(cost.threads);
            }
            if let Some(load) = cost.other_load {
                c["other_load"] = json!(load);
            }
            (k.clone(), c)
        })
        .collect();
    json!({
        "costs": costs,
        "index": r.variant.index,
        "name": r.name,
        "settings": settings_json(&r.variant),
        "varied": r.variant.varied,
        "status": r.status.as_str(),
        "reason": r.reason,
        "failed_stage": r.failed_stage,
        "warnings": r.warnings,
        "metrics": metrics,
    })
}

/// The record of a sweep over `axes` whose variants' entries are `variants`
/// (in index order): one machine's rows ([`record`]) or merged shards
/// ([`crate::shard`]).
pub fn record_of(
    pipeline: &str,
    axes: &Axes,
    variants: Vec<serde_json::Value>,
) -> serde_json::Value {
    let crossed: serde_json::Map<String, serde_json::Value> = axes
        .crossed
        .iter()
        .map(|(k, v)| {
            (
                k.clone(),
                serde_json::Value::Array(v.iter().map(value_json).collect()),
            )
        })
        .collect();
    let each: serde_json::Map<String, serde_json::Value> = axes
        .each
        .iter()
        .map(|(k, v)| {
            (
                k.clone(),
                serde_json::Value::Array(v.iter().map(value_json).collect()),
            )
        })
        .collect();
    json!({
        "pipeline": pipeline,
        "crossed": crossed,
        "each": each,
        "each_order": axes.each.iter().map(|(k, _)| k.clone()).collect::<Vec<_>>(),
        "variants": variants,
    })
}

/// The record as pretty JSON with a final newline.
pub fn record_bytes(record: &serde_json::Value) -> Vec<u8> {
    let mut b = serde_json::to_vec_pretty(record).unwrap_or_default();
    b.push(b'\n');
    b
}

/// Writes `bytes` to `path` unless it already holds them (atomic replace).
pub fn write_if_changed(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    if std::fs::read(path).map(|b| b == bytes).unwrap_or(false) {
        return Ok(());
    }
    if let Some(dir) = path.parent() {
        if !dir.as_os_str().is_empty() {
            std::fs::create_dir_all(dir)?;
        }
    }
    let name = path
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = path.with_file_name(format!(".fure-tmp-{}-{name}", std::process::id()));
    std::fs::write(&tmp, bytes)?;
    std::fs::rename(&tmp, path)
}

/// The aggregate stages as a plan named `<pipeline>` whose stages read
/// `record` (`None` when the pipeline has none). Errors are located in the
/// pipeline file.
pub fn plan_aggregates(
    engine: &Engine,
    pipeline: &Pipeline,
    record: &Path,
) -> Result<Option<Plan>, PipelineErrors> {
    if pipeline.aggregates.is_empty() {
        return Ok(None);
    }
    let record_text = record.display().to_string();
    let mut errors = Vec::new();
    let mut decls = Vec::new();
    for decl in &pipeline.aggregates {
        match bind_record(engine, pipeline, decl, &record_text) {
            Ok(d) => decls.push(d),
            Err(e) => errors.push(e),
        }
    }
    if !errors.is_empty() {
        return Err(PipelineErrors(errors));
    }
    let agg = Pipeline {
        name: pipeline.name.clone(),
        description: format!("aggregate stages of the sweep of {}", pipeline.name),
        file: pipeline.file.clone(),
        stages: decls,
        sweep: BTreeMap::new(),
        sweep_each: Vec::new(),
        aggregates: Vec::new(),
        publish: BTreeMap::new(),
        executor: None,
    };
    let mut plan = engine.plan(&agg)?;
    // Show the record by its place in out/, not by an absolute path.
    for s in &mut plan.stages {
        for i in &mut s.inputs {
            if let Source::Path { written, .. } = &mut i.source {
                *written = "sweep.json".to_string();
            }
        }
    }
    Ok(Some(plan))
}

/// One aggregate as an ordinary stage whose one input is the sweep record
/// (`record_text`): a command's `deps`, else the kind's one `.json` port.
/// A missing or unknown kind is left for the planner to report.
fn bind_record(
    engine: &Engine,
    pipeline: &Pipeline,
    decl: &StageDecl,
    record_text: &str,
) -> Result<StageDecl, PipelineError> {
    let mut d = decl.clone();
    if pipeline.stage(&d.name).is_some() {
        return Err(PipelineError::at(
            &d.loc,
            format!(
                "aggregate `{}` has the name of a stage (both would write out/{}/{}/); rename one",
                d.name, pipeline.name, d.name
            ),
        ));
    }
    let Some((kind, kloc)) = d.kind.clone() else {
        return Ok(d); // the planner reports the missing kind
    };
    let Some(stage) = engine.registry.get(&kind) else {
        return Ok(d); // the planner reports the unknown kind
    };
    let base = Arc::new(PathBuf::from("/"));
    if kind == command::KIND {
        if let Some(p) = d.params.get("deps") {
            return Err(PipelineError::at(
                &p.loc,
                format!(
                    "aggregate `{}` (kind `command`): `deps` is set by the engine ({{deps.sweep}} is the sweep record); remove it",
                    d.name
                ),
            ));
        }
        d.params.insert(
            "deps".into(),
            ParamDecl {
                value: Value::Table(BTreeMap::from([(
                    "sweep".to_string(),
                    Value::Str(record_text.to_string()),
                )])),
                loc: kloc,
                base,
            },
        );
        return Ok(d);
    }
    let port = record_port(&**stage, &d, &kind, &kloc)?;
    d.inputs.insert(
        port,
        InputDecl {
            text: record_text.to_string(),
            loc: kloc,
            base,
        },
    );
    Ok(d)
}

/// The port an aggregate of an ordinary kind receives the record on: its
/// kind must declare exactly one input port, a `.json` file, under the
/// aggregate's parameters.
fn record_port(
    stage: &dyn Stage,
    d: &StageDecl,
    kind: &str,
    kloc: &Loc,
) -> Result<String, PipelineError> {
    // The kind's input ports under the given parameters (checked ones
    // where they check; the planner reports the others).
    let specs = stage.params();
    let mut params = BTreeMap::new();
    for spec in &specs {
        let v = match d.params.get(spec.name) {
            Some(p) => plan::check_value(spec, &p.value).ok(),
            None => spec.default.clone(),
        };
        if let Some(v) = v {
            params.insert(spec.name.to_string(), v);
        }
    }
    let ports = stage.inputs(&fure_stage_api::Params(params));
    let json_port = match ports.as_slice() {
        [p] if p.kind == PortKind::File { ext: "json" } => Some(p.name.clone()),
        _ => None,
    };
    if let Some(port) = json_port {
        return Ok(port);
    }
    let have = if ports.is_empty() {
        "none".to_string()
    } else {
        ports
            .iter()
            .map(|p| match p.kind {
                PortKind::Dir => format!("`{}` (directory)", p.name),
                PortKind::File { ext } => format!("`{}` (.{ext})", p.name),
            })
            .collect::<Vec<_>>()
            .join(", ")
    };
    Err(PipelineError::at(
        kloc,
        format!(
            "aggregate `{}`: kind `{kind}` must declare exactly one input port, a `.json` file, to receive the sweep record (it declares: {have})",
            d.name
        ),
    ))
}

/// Runs the aggregate stages on the record file (`None` when there are none).
pub fn run_aggregates(
    engine: &Engine,
    pipeline: &Pipeline,
    record: &Path,
    cache: &Cache,
    opts: &RunOptions,
) -> Result<Option<RunReport>, PipelineErrors> {
    let Some(plan) = plan_aggregates(engine, pipeline, record)? else {
        return Ok(None);
    };
    let opts = RunOptions {
        keep_going: true,
        ..opts.clone()
    };
    Ok(Some(exec::run(&plan, cache, &opts)))
}

struct Table {
    header: Vec<String>,
    rows: Vec<Vec<String>>,
    csv_rows: Vec<Vec<String>>,
}

fn table(rows: &[Row]) -> Table {
    let axes: Vec<String> = rows
        .first()
        .map(|r| r.variant.settings.iter().map(|(k, _)| k.clone()).collect())
        .unwrap_or_default();
    let stages: BTreeSet<String> = rows
        .iter()
        .flat_map(|r| r.stage_seconds.keys().cloned())
        .collect();
    // Keep the pipeline's stage order.
    let order: Vec<String> = rows
        .first()
        .map(|r| {
            r.report
                .stages
                .iter()
                .map(|s| s.name.clone())
                .filter(|n| stages.contains(n))
                .collect()
        })
        .unwrap_or_default();
    let metrics: BTreeSet<String> = rows
        .iter()
        .flat_map(|r| r.metrics.keys().cloned())
        .collect();
    let mut header = vec!["variant".to_string()];
    header.extend(axes.iter().cloned());
    header.extend(["status", "reason", "ran", "cached", "wall_s"].map(String::from));
    header.extend(order.iter().map(|s| format!("{s}_s")));
    header.extend(metrics.iter().cloned());
    let mut out_rows = Vec::new();
    let mut csv_rows = Vec::new();
    for r in rows {
        let mut md = vec![r.variant.index.to_string()];
        let mut csv = md.clone();
        for (_, v) in &r.variant.settings {
            md.push(show(v));
            csv.push(match v {
                Value::Str(s) => s.clone(),
                other => show(other),
            });
        }
        md.push(r.status.as_str().to_string());
        csv.push(r.status.as_str().to_string());
        md.push(r.reason.replace('|', "\\|"));
        csv.push(r.reason.clone());
        for x in [
            r.report.count(Status::Ran).to_string(),
            r.report.count(Status::Cached).to_string(),
            format!("{:.3}", r.report.seconds),
        ] {
            md.push(x.clone());
            csv.push(x);
        }
        for s in &order {
            match r.stage_seconds.get(s) {
                Some((secs, cached)) => {
                    md.push(format!("{secs:.3}{}", if *cached { "*" } else { "" }));
                    csv.push(format!("{secs:.6}"));
                }
                None => {
                    md.push("-".into());
                    csv.push(String::new());
                }
            }
        }
        for m in &metrics {
            match r.metrics.get(m) {
                Some(x) => {
                    md.push(format!("{x:.6}"));
                    csv.push(format!("{x}"));
                }
                None => {
                    md.push("-".into());
                    csv.push(String::new());
                }
            }
        }
        out_rows.push(md);
        csv_rows.push(csv);
    }
    Table {
        header,
        rows: out_rows,
        csv_rows,
    }
}

/// The sweep table as Markdown.
pub fn markdown(rows: &[Row]) -> String {
    let t = table(rows);
    let mut s = String::new();
    let _ = writeln!(s, "| {} |", t.header.join(" | "));
    let _ = writeln!(s, "|{}", "---|".repeat(t.header.len()));
    for r in &t.rows {
        let _ = writeln!(s, "| {} |", r.join(" | "));
    }
    let _ = writeln!(s, "\nStage columns: compute seconds of the stage's cache entry; `*` marks a cache hit in this sweep.");
    s
}

/// The sweep table as CSV (RFC 4180 quoting).
pub fn csv(rows: &[Row]) -> String {
    let t = table(rows);
    let q = |x: &str| {
        if x.contains([',', '"', '\n']) {
            format!("\"{}\"", x.replace('"', "\"\""))
        } else {
            x.to_string()
        }
    };
    let mut s = String::new();
    let _ = writeln!(
        s,
        "{}",
        t.header.iter().map(|h| q(h)).collect::<Vec<_>>().join(",")
    );
    for r in &t.csv_rows {
        let _ = writeln!(
            s,
            "{}",
            r.iter().map(|x| q(x)).collect::<Vec<_>>().join(",")
        );
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::exec::StageReport;

    fn parse(text: &str) -> Pipeline {
        Pipeline::parse_str(text, "s.toml", Path::new("/")).unwrap()
    }

    #[test]
    fn grid_is_the_cartesian_product() {
        let p = parse(
            "[stages.a]\nkind=\"k\"\n[sweep]\n\"a.x\" = [1, 2]\n\"a.y\" = [\"p\", \"q\", \"r\"]\n",
        );
        let g = grid(&p, &[]);
        assert_eq!(g.len(), 6);
        assert_eq!(describe(&g[1]), "a.x=1, a.y=\"q\"");
        assert!(g.iter().all(|v| v.varied.is_none()));
        let g2 = grid(&p, &[("a.x".into(), vec![Value::Int(5)])]);
        assert_eq!(g2.len(), 3);
        let g3 = grid(&p, &[("a.z".into(), vec![Value::Int(5), Value::Int(6)])]);
        assert_eq!(g3.len(), 12);
    }

    #[test]
    fn each_axes_vary_one_at_a_time() {
        let p = parse(
            "[stages.a]\nkind=\"k\"\n[sweep]\n\"a.p\" = [\"t\", \"b\"]\n\
             [sweep.each]\n\"a.n\" = [0.0, 0.02, 0.05, 0.1]\n\"a.j\" = [0.0, 0.5, 1.0, 2.0]\n",
        );
        let g = grid(&p, &[]);
        assert_eq!(g.len(), 2 * (1 + 3 + 3));
        // Settings list every key: crossed (sorted) then each (declared order).
        let keys: Vec<&str> = g[0].settings.iter().map(|(k, _)| k.as_str()).collect();
        assert_eq!(keys, ["a.p", "a.n", "a.j"]);
        assert_eq!(describe(&g[0]), "a.p=\"t\", a.n=0.0, a.j=0.0");
        assert_eq!(g[0].varied, None);
        assert_eq!(describe(&g[1]), "a.p=\"t\", a.n=0.02, a.j=0.0");
        assert_eq!(g[1].varied.as_deref(), Some("a.n"));
        assert_eq!(describe(&g[4]), "a.p=\"t\", a.n=0.0, a.j=0.5");
        assert_eq!(g[6].varied.as_deref(), Some("a.j"));
        assert_eq!(describe(&g[7]), "a.p=\"b\", a.n=0.0, a.j=0.0");
        assert_eq!(g[7].varied, None);
        // --grid on an each key keeps it one-at-a-time; --each moves a crossed key.
        let a = Axes::new(
            &p,
            &[("a.n".into(), vec![Value::Float(0.0), Value::Float(1.0)])],
            &[(
                "a.p".into(),
                vec![Value::Str("t".into()), Value::Str("b".into())],
            )],
        );
        assert!(a.crossed.is_empty());
        assert_eq!(a.variants().len(), 1 + 1 + 3 + 1);
    }

    #[test]
    fn each_keys_are_checked_and_located() {
        let e = Pipeline::parse_str(
            "[stages.a]\nkind=\"k\"\n[sweep]\n\"a.x\" = [1]\n[sweep.each]\nnodot = [1]\n\"a.y\" = []\n\"a.x\" = [2]\n",
            "s.toml",
            Path::new("/"),
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("s.toml:6:1: error: sweep.each key `nodot`"),
            "{e}"
        );
        assert!(e.contains("s.toml:7:"), "{e}");
        assert!(e.contains("non-empty array"), "{e}");
        assert!(
            e.contains("s.toml:8:1: error: sweep key `a.x` is both crossed"),
            "{e}"
        );
    }

    fn stage(name: &str, status: Status, error: Option<&str>) -> StageReport {
        StageReport {
            name: name.into(),
            kind: "k".into(),
            key: String::new(),
            status,
            reason: String::new(),
            seconds: 0.0,
            peak_rss_bytes: 0,
            outputs: BTreeMap::new(),
            error: error.map(String::from),
            notes: Vec::new(),
        }
    }

    #[test]
    fn status_and_reason() {
        let rep = |stages| RunReport {
            pipeline: "p".into(),
            fure_version: String::new(),
            seconds: 0.0,
            stages,
        };
        let r = rep(vec![
            stage("a", Status::Ran, None),
            stage("b", Status::Failed, Some("\nempty hull\nmore")),
            stage("c", Status::Skipped, None),
            stage("d", Status::Failed, Some("x")),
        ]);
        let (s, why, first) = classify(&r, &["a: w".into()]);
        assert_eq!(s, VariantStatus::Failed);
        assert_eq!(why, "b: empty hull (+1 more)");
        let r2 = rep(vec![stage(
            "c",
            Status::Failed,
            Some("`x` exited; stderr tail:\nboom\nz"),
        )]);
        assert_eq!(classify(&r2, &[]).1, "c: `x` exited; stderr tail: boom");
        assert_eq!(first.as_deref(), Some("b"));
        let r = rep(vec![stage("a", Status::Cached, None)]);
        let (s, why, _) = classify(&r, &["a: w1".into(), "a: w2".into()]);
        assert_eq!((s, why.as_str()), (VariantStatus::Degraded, "a: w1; a: w2"));
        let (s, why, _) = classify(&r, &[]);
        assert_eq!((s, why.as_str()), (VariantStatus::Ok, ""));
    }

    #[test]
    fn staging_paths_are_scrubbed() {
        let pre = vec!["/c/tmp/".to_string(), "c/tmp/".to_string()];
        assert_eq!(
            scrub("cannot read /c/tmp/123-0-abc/in/x.png: gone", &pre),
            "cannot read <staging>/in/x.png: gone"
        );
        assert_eq!(scrub("a c/tmp/9-1-k/out b", &pre), "a <staging>/out b");
        assert_eq!(scrub("no path here", &pre), "no path here");
    }

    #[test]
    fn timings_are_not_record_metrics() {
        assert!(is_timing("fit.seconds"));
        assert!(is_timing("fit.train_time_ms"));
        assert!(!is_timing("seconds.fscore"));
        assert!(!is_timing("evaluate.prf.3cm_30deg.fscore"));
    }

    #[test]
    fn metrics_flatten() {
        let j: serde_json::Value =
            serde_json::from_str(r#"{"a": 1, "b": {"c": 2.5, "d": "x"}, "e": true}"#).unwrap();
        let mut m = BTreeMap::new();
        flatten("s", &j, &mut m);
        assert_eq!(m.len(), 3);
        assert_eq!(m["s.b.c"], 2.5);
    }
}
