//! The `stability_report` stage: where FurE, the dense baseline and the fixed-length ablation break
//! under corrupted input, from a sweep record.
//!
//! # Input
//! `sweep` is the engine's sweep record (`sweep.json`, written by `fure sweep` and bound to an
//! `[aggregate.NAME]` stage's single input): `crossed` (keys crossed with everything, e.g.
//! `scene.preset`: one *group* per combination, normally one per animal), `each` (keys varied one
//! at a time, the others at their first value; the first value of each list is the clean one), and
//! `variants`, each with its `settings`, `varied` (the `each` key it varies, `null` for the base
//! point of a group), the engine's `status` (`ok` / `degraded` / `failed`), `reason`,
//! `failed_stage`, `warnings` and `metrics` (every number of every stage's `metrics.json`, flattened
//! as `stage.key.subkey`), and `each_order` (the declaration order of the `each` keys, which the
//! sorted object loses; axes are charted and tabulated in that order). Missing or mistyped keys are errors naming the key (`variants[3].status`);
//! `crossed`, `reason`, `failed_stage`, `warnings`, `varied`, `index` and `name` may be absent.
//!
//! # Methods and status
//! A method is a metric key prefix (parameters `fure_prefix`, `dense_prefix`, `fixed_prefix`,
//! defaults `evaluate`, `evaluate_dense`, `evaluate_fixed`); its F-scores are
//! `<prefix>.prf.{2cm_20deg,3cm_30deg,4cm_40deg}.fscore` and the status uses F3 (3 cm / 30 deg).
//! The defurring error (`defur_key`, default `defur.root_to_skin_mean_frac`: mean distance of M_root
//! to the GT skin as a fraction of the GT fur thickness) belongs to the preprocessing, which all
//! three methods share: it is one value per variant, reported with every method and drawn once.
//!
//! Per method and variant:
//! - `failed` when the method's F3 is missing: with the engine's reason (and failed stage) when the
//!   variant failed, else "no metric `KEY` in the record";
//! - `degraded` when the engine said degraded (its warnings are the reason), or F3 fell more than
//!   `baseline_drop` (relative, default 0.25) below the same method's F3 at the base point of the
//!   same group, or the defurring error rose more than `defur_rise` (relative, default 0.5) above the
//!   base point's; the reason says which, with both values and the relative change;
//! - `ok` otherwise (also when the variant failed in another branch, e.g. the dense learner, while
//!   this method's metric exists: the reason then names the failed stage). With no usable base point (missing or failed) nothing can be compared: the
//!   status then only reflects the engine, and the reason says that no clean reference exists.
//!
//! "Largest corruption survived as ok" (`metrics.json`, `survives`): an axis's values are taken in
//! the order the pipeline lists them (clean first, then increasingly severe; for `mask_morph_px`,
//! whose values go both ways, that is still the listed order); the answer is the last value reached
//! before the first non-ok status, `null` when even the clean value is not ok.
//!
//! # Outputs
//! - `charts/`: per group and `each` axis, `<group>__<axis>.png` and `.svg`: top panel F3 against
//!   the corruption value, one line per method (filled dot ok, ring degraded); a method that failed
//!   at a value is a cross ON the axis (F = 0) in its colour with a label `<method> failed`, never a
//!   silent gap; bottom panel the defurring error, failed variants as black crosses on the axis.
//!   Non-numeric axis values are drawn at their list position.
//! - `summary.md`: counts, the survival table, then per group and axis one table (the base point
//!   first), every row a variant x method with status, reason, F2/F3/F4 and the defurring error.
//! - `summary.csv`: one row per variant x method: `group,axis,value,variant,method,status,reason,
//!   f2,f3,f4,defur_error` (the base point has axis `base` and an empty value).
//! - `metrics.json`: counts of ok/degraded/failed per method, `survives`, and the thresholds used.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use fure_stage_api::{ParamSpec, Params, PortSpec, Stage, StageContext, StageError};
use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use serde_json::{json, Map, Value as Json};

use crate::evaluation::charts::{chart_err, write_png_chart, write_svg_chart};

/// The engine's verdict on a variant.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EngineStatus {
    Ok,
    Degraded,
    Failed,
}

/// One variant of the sweep record.
#[derive(Debug, Clone, PartialEq)]
pub struct VariantRecord {
    pub index: usize,
    pub name: String,
    pub settings: Map<String, Json>,
    pub varied: Option<String>,
    pub status: EngineStatus,
    pub reason: String,
    pub failed_stage: Option<String>,
    pub warnings: Vec<String>,
    pub metrics: BTreeMap<String, f64>,
    /// The record's optional `costs`, flattened: `STAGE.seconds`, `STAGE.peak_rss_bytes`,
    /// `STAGE.threads`, `STAGE.other_load`.
    pub costs: BTreeMap<String, f64>,
}

/// The sweep record (`sweep.json`).
#[derive(Debug, Clone, PartialEq)]
pub struct SweepRecord {
    pub pipeline: String,
    pub crossed: Vec<(String, Vec<Json>)>,
    pub each: Vec<(String, Vec<Json>)>,
    pub variants: Vec<VariantRecord>,
}

/// A record problem: the key path and what was expected.
fn bad(path: &Path, key: &str, msg: impl std::fmt::Display) -> StageError {
    StageError::input("sweep", path, format!("`{key}`: {msg}"))
}

fn json_kind(v: &Json) -> &'static str {
    match v {
        Json::Null => "null",
        Json::Bool(_) => "a boolean",
        Json::Number(_) => "a number",
        Json::String(_) => "a string",
        Json::Array(_) => "an array",
        Json::Object(_) => "an object",
    }
}

fn axes(
    path: &Path,
    root: &Map<String, Json>,
    key: &str,
    required: bool,
) -> Result<Vec<(String, Vec<Json>)>, StageError> {
    match root.get(key) {
        None | Some(Json::Null) if !required => Ok(Vec::new()),
        None => Err(bad(
            path,
            key,
            "missing (expected an object of KEY: [values])",
        )),
        Some(Json::Object(m)) => m
            .iter()
            .map(|(k, v)| match v {
                Json::Array(a) if !a.is_empty() => Ok((k.clone(), a.clone())),
                other => Err(bad(
                    path,
                    &format!("{key}.{k}"),
                    format!(
                        "expected a non-empty array of values, found {}",
                        json_kind(other)
                    ),
                )),
            })
            .collect(),
        Some(other) => Err(bad(
            path,
            key,
            format!(
                "expected an object of KEY: [values], found {}",
                json_kind(other)
            ),
        )),
    }
}

/// Flattens nested numbers (`a.b.c`); non-numbers are skipped.
fn flatten(prefix: &str, v: &Json, out: &mut BTreeMap<String, f64>) {
    match v {
        Json::Number(n) => {
            if let Some(x) = n.as_f64() {
                if x.is_finite() {
                    out.insert(prefix.to_string(), x);
                }
            }
        }
        Json::Object(m) => {
            for (k, x) in m {
                let key = if prefix.is_empty() {
                    k.clone()
                } else {
                    format!("{prefix}.{k}")
                };
                flatten(&key, x, out);
            }
        }
        _ => {}
    }
}

impl SweepRecord {
    /// Reads and checks a record file.
    pub fn read(path: &Path) -> Result<SweepRecord, StageError> {
        let root: Json = crate::formats::json::read_json(path)?;
        Self::from_json(path, &root)
    }

    /// Checks a parsed record; `path` only names the file in errors.
    pub fn from_json(path: &Path, root: &Json) -> Result<SweepRecord, StageError> {
        let root = root.as_object().ok_or_else(|| {
            bad(
                path,
                "(top level)",
                format!("expected an object, found {}", json_kind(root)),
            )
        })?;
        let pipeline = match root.get("pipeline") {
            Some(Json::String(s)) => s.clone(),
            None | Some(Json::Null) => String::new(),
            Some(o) => {
                return Err(bad(
                    path,
                    "pipeline",
                    format!("expected a string, found {}", json_kind(o)),
                ))
            }
        };
        let crossed = axes(path, root, "crossed", false)?;
        let each = each_in_order(path, root, axes(path, root, "each", true)?)?;
        let list = match root.get("variants") {
            Some(Json::Array(a)) => a,
            None => {
                return Err(bad(
                    path,
                    "variants",
                    "missing (expected an array of variants)",
                ))
            }
            Some(o) => {
                return Err(bad(
                    path,
                    "variants",
                    format!("expected an array, found {}", json_kind(o)),
                ))
            }
        };
        let variants = list
            .iter()
            .enumerate()
            .map(|(i, v)| VariantRecord::from_json(path, i, v, &crossed, &each))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(SweepRecord {
            pipeline,
            crossed,
            each,
            variants,
        })
    }
}

/// The `each` axes in `each_order` (when present), which restores the
/// declaration order the sorted object loses.
fn each_in_order(
    path: &Path,
    root: &Map<String, Json>,
    mut each: Vec<(String, Vec<Json>)>,
) -> Result<Vec<(String, Vec<Json>)>, StageError> {
    match root.get("each_order") {
        None | Some(Json::Null) => Ok(each),
        Some(Json::Array(order)) => {
            let mut sorted = Vec::with_capacity(each.len());
            for (j, k) in order.iter().enumerate() {
                let k = k.as_str().ok_or_else(|| {
                    bad(
                        path,
                        &format!("each_order[{j}]"),
                        "expected a key of `each`",
                    )
                })?;
                let pos = each.iter().position(|(e, _)| e == k).ok_or_else(|| {
                    bad(
                        path,
                        &format!("each_order[{j}]"),
                        format!("`{k}` is not a key of `each`"),
                    )
                })?;
                sorted.push(each.remove(pos));
            }
            sorted.append(&mut each);
            Ok(sorted)
        }
        Some(o) => Err(bad(
            path,
            "each_order",
            format!("expected an array of keys, found {}", json_kind(o)),
        )),
    }
}

/// The fields of variant `i` of a record, each read with its key path in
/// errors (`variants[3].status`).
struct VariantFields<'a> {
    path: &'a Path,
    i: usize,
    obj: &'a Map<String, Json>,
}

impl VariantFields<'_> {
    fn at(&self, k: &str) -> String {
        format!("variants[{}].{k}", self.i)
    }

    fn bad(&self, k: &str, msg: impl std::fmt::Display) -> StageError {
        bad(self.path, &self.at(k), msg)
    }

    fn opt_str(&self, k: &str) -> Result<Option<String>, StageError> {
        match self.obj.get(k) {
            None | Some(Json::Null) => Ok(None),
            Some(Json::String(s)) => Ok(Some(s.clone())),
            Some(o) => Err(self.bad(
                k,
                format!("expected a string or null, found {}", json_kind(o)),
            )),
        }
    }

    fn status(&self) -> Result<EngineStatus, StageError> {
        match self.obj.get("status") {
            Some(Json::String(s)) => match s.as_str() {
                "ok" => Ok(EngineStatus::Ok),
                "degraded" => Ok(EngineStatus::Degraded),
                "failed" => Ok(EngineStatus::Failed),
                other => Err(self.bad(
                    "status",
                    format!("expected ok, degraded or failed, found `{other}`"),
                )),
            },
            None => Err(self.bad("status", "missing (expected ok, degraded or failed)")),
            Some(o) => Err(self.bad(
                "status",
                format!("expected a string, found {}", json_kind(o)),
            )),
        }
    }

    fn warnings(&self) -> Result<Vec<String>, StageError> {
        match self.obj.get("warnings") {
            None | Some(Json::Null) => Ok(Vec::new()),
            Some(Json::Array(a)) => a
                .iter()
                .enumerate()
                .map(|(j, w)| match w {
                    Json::String(s) => Ok(s.clone()),
                    o => Err(self.bad(
                        &format!("warnings[{j}]"),
                        format!("expected a string, found {}", json_kind(o)),
                    )),
                })
                .collect(),
            Some(o) => Err(self.bad(
                "warnings",
                format!("expected an array of strings, found {}", json_kind(o)),
            )),
        }
    }

    /// An object of (nested) numbers, flattened; `required` or null/absent.
    fn numbers(&self, k: &str, required: bool) -> Result<BTreeMap<String, f64>, StageError> {
        let mut out = BTreeMap::new();
        match (self.obj.get(k), required) {
            (Some(m @ Json::Object(_)), _) => flatten("", m, &mut out),
            (None, true) => return Err(self.bad(k, "missing (expected an object of numbers)")),
            (None | Some(Json::Null), false) => {}
            (Some(o), _) => {
                return Err(self.bad(k, format!("expected an object, found {}", json_kind(o))))
            }
        }
        Ok(out)
    }
}

impl VariantRecord {
    /// Checks variant `i` of a record against its axes.
    fn from_json(
        path: &Path,
        i: usize,
        v: &Json,
        crossed: &[(String, Vec<Json>)],
        each: &[(String, Vec<Json>)],
    ) -> Result<VariantRecord, StageError> {
        let obj = v.as_object().ok_or_else(|| {
            bad(
                path,
                &format!("variants[{i}]"),
                format!("expected an object, found {}", json_kind(v)),
            )
        })?;
        let f = VariantFields { path, i, obj };
        let settings = match obj.get("settings") {
            Some(Json::Object(m)) => m.clone(),
            None => return Err(f.bad("settings", "missing")),
            Some(o) => {
                return Err(f.bad(
                    "settings",
                    format!("expected an object, found {}", json_kind(o)),
                ))
            }
        };
        let status = f.status()?;
        let varied = f.opt_str("varied")?;
        if let Some(k) = &varied {
            if !each.iter().any(|(e, _)| e == k) {
                return Err(f.bad("varied", format!("`{k}` is not a key of `each`")));
            }
        }
        let warnings = f.warnings()?;
        let metrics = f.numbers("metrics", true)?;
        let costs = f.numbers("costs", false)?;
        let index = match obj.get("index") {
            None | Some(Json::Null) => i,
            Some(x) => x.as_u64().ok_or_else(|| {
                f.bad(
                    "index",
                    format!("expected a non-negative integer, found {}", json_kind(x)),
                )
            })? as usize,
        };
        // Every crossed and each key must be set.
        for (k, _) in crossed.iter().chain(each) {
            if !settings.contains_key(k) {
                return Err(f.bad(
                    &format!("settings.{k}"),
                    "missing (every sweep key must be set)",
                ));
            }
        }
        Ok(VariantRecord {
            index,
            name: f.opt_str("name")?.unwrap_or_else(|| format!("v{index}")),
            settings,
            varied,
            status,
            reason: f.opt_str("reason")?.unwrap_or_default(),
            failed_stage: f.opt_str("failed_stage")?,
            warnings,
            metrics,
            costs,
        })
    }
}

/// Thresholds and metric keys of the report.
#[derive(Debug, Clone, PartialEq)]
pub struct ReportConfig {
    /// (display name, metric key prefix).
    pub methods: Vec<(String, String)>,
    pub defur_key: String,
    pub baseline_drop: f64,
    pub defur_rise: f64,
}

impl Default for ReportConfig {
    /// The stage's declared defaults.
    fn default() -> Self {
        StabilityReportParams::defaults()
            .and_then(|p| config(&p))
            .expect("the declared defaults make a valid report configuration")
    }
}

/// The three F-score thresholds' key parts.
const F_KEYS: [&str; 3] = ["2cm_20deg", "3cm_30deg", "4cm_40deg"];

fn f_key(prefix: &str, k: usize) -> String {
    format!("{prefix}.prf.{}.fscore", F_KEYS[k])
}

/// A method's verdict on one variant.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Status {
    Ok,
    Degraded,
    Failed,
}

impl Status {
    pub fn as_str(self) -> &'static str {
        match self {
            Status::Ok => "ok",
            Status::Degraded => "degraded",
            Status::Failed => "failed",
        }
    }
}

/// One row: a variant seen by one method.
#[derive(Debug, Clone, PartialEq)]
pub struct Row {
    pub group: String,
    /// Index into `SweepRecord::variants`.
    pub variant: usize,
    /// Index into `ReportConfig::methods`.
    pub method: usize,
    pub status: Status,
    pub reason: String,
    /// F-scores at 2/3/4 cm.
    pub f: [Option<f64>; 3],
    pub defur: Option<f64>,
}

/// A group's label: its crossed values joined by `_` (strings unquoted), `all` without crossed keys.
fn group_of(rec: &SweepRecord, v: &VariantRecord) -> String {
    if rec.crossed.is_empty() {
        return "all".into();
    }
    rec.crossed
        .iter()
        .map(|(k, _)| value_label(&v.settings[k]))
        .collect::<Vec<_>>()
        .join("_")
}

fn value_label(v: &Json) -> String {
    match v {
        Json::String(s) => s.clone(),
        Json::Number(n) => match n.as_f64() {
            Some(x) => fmt_value(x),
            None => n.to_string(),
        },
        other => other.to_string(),
    }
}

fn fmt_value(x: f64) -> String {
    if x == x.trunc() && x.abs() < 1e15 {
        format!("{}", x as i64)
    } else {
        let s = format!("{x:.4}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    }
}

fn rel_change(x: f64, base: f64) -> f64 {
    (x - base) / base.abs().max(1e-12)
}

/// Statuses of every variant for every method.
pub fn assess(rec: &SweepRecord, cfg: &ReportConfig) -> Vec<Row> {
    // Base points per group (the first with `varied == null`).
    let mut base: BTreeMap<String, usize> = BTreeMap::new();
    for (i, v) in rec.variants.iter().enumerate() {
        if v.varied.is_none() {
            base.entry(group_of(rec, v)).or_insert(i);
        }
    }
    let mut rows = Vec::new();
    for (vi, v) in rec.variants.iter().enumerate() {
        let group = group_of(rec, v);
        let b = base.get(&group).map(|&i| &rec.variants[i]);
        let defur = v.metrics.get(&cfg.defur_key).copied();
        for (mi, (name, prefix)) in cfg.methods.iter().enumerate() {
            let f = [0, 1, 2].map(|k| v.metrics.get(&f_key(prefix, k)).copied());
            let mut reasons = Vec::new();
            let status = match f[1] {
                None => {
                    if v.status == EngineStatus::Failed {
                        // The engine's reason normally starts with `<stage>: `.
                        let reason = match v.failed_stage.as_deref() {
                            Some(st) if !v.reason.starts_with(&format!("{st}:")) => {
                                format!("{st}: {}", v.reason)
                            }
                            _ => v.reason.clone(),
                        };
                        reasons.push(if reason.is_empty() {
                            "the variant failed (no reason given)".to_string()
                        } else {
                            reason
                        });
                    } else {
                        reasons.push(format!(
                            "no metric `{}` in the record (engine status {})",
                            f_key(prefix, 1),
                            match v.status {
                                EngineStatus::Ok => "ok",
                                EngineStatus::Degraded => "degraded",
                                EngineStatus::Failed => "failed",
                            }
                        ));
                    }
                    Status::Failed
                }
                Some(f3) => {
                    let mut s = Status::Ok;
                    if v.status == EngineStatus::Failed {
                        // Another branch failed (this method's metric exists): said, not held against it.
                        let stage = v.failed_stage.as_deref().unwrap_or("another stage");
                        reasons.push(format!("(variant failed elsewhere, at {stage})"));
                    } else if v.status == EngineStatus::Degraded {
                        s = Status::Degraded;
                        let why = if v.warnings.is_empty() {
                            v.reason.clone()
                        } else {
                            v.warnings.join("; ")
                        };
                        reasons.push(format!(
                            "engine: {}",
                            if why.is_empty() { "degraded" } else { &why }
                        ));
                    }
                    let bf3 = b.and_then(|b| b.metrics.get(&f_key(prefix, 1)).copied());
                    let bdefur = b.and_then(|b| b.metrics.get(&cfg.defur_key).copied());
                    match bf3 {
                        Some(bf) if bf > 0.0 => {
                            let c = rel_change(f3, bf);
                            if -c > cfg.baseline_drop {
                                s = Status::Degraded;
                                reasons.push(format!(
                                    "F-score {f3:.1} is {:.0}% below the clean {bf:.1} (limit {:.0}%)",
                                    -100.0 * c,
                                    100.0 * cfg.baseline_drop
                                ));
                            }
                        }
                        _ => {
                            reasons.push(format!("no clean reference for {name} in group {group}"))
                        }
                    }
                    if let (Some(d), Some(bd)) = (defur, bdefur) {
                        if bd > 0.0 {
                            let c = rel_change(d, bd);
                            if c > cfg.defur_rise {
                                s = Status::Degraded;
                                reasons.push(format!(
                                    "defurring error {d:.3} is {:.0}% above the clean {bd:.3} (limit {:.0}%)",
                                    100.0 * c,
                                    100.0 * cfg.defur_rise
                                ));
                            }
                        }
                    }
                    s
                }
            };
            rows.push(Row {
                group: group.clone(),
                variant: vi,
                method: mi,
                status,
                reason: reasons.join("; "),
                f,
                defur,
            });
        }
    }
    rows
}

/// The position of a variant on an axis: the numeric setting, or its index in the axis list.
fn axis_x(values: &[Json], v: &Json) -> f64 {
    v.as_f64()
        .unwrap_or_else(|| values.iter().position(|x| x == v).unwrap_or(values.len()) as f64)
}

/// Variants on an axis of a group: the base point(s) and the variants varying that key, in the
/// order of the axis's list (clean first; stable).
fn axis_points(rec: &SweepRecord, group: &str, axis: &str) -> Vec<usize> {
    let values = &rec
        .each
        .iter()
        .find(|(k, _)| k == axis)
        .expect("axis of the record")
        .1;
    let mut pts: Vec<usize> = rec
        .variants
        .iter()
        .enumerate()
        .filter(|(_, v)| {
            group_of(rec, v) == group && (v.varied.is_none() || v.varied.as_deref() == Some(axis))
        })
        .map(|(i, _)| i)
        .collect();
    let pos = |i: usize| {
        let v = &rec.variants[i].settings[axis];
        values.iter().position(|x| x == v).unwrap_or(values.len())
    };
    pts.sort_by_key(|&i| pos(i));
    pts
}

/// The group labels in record order.
fn groups(rec: &SweepRecord) -> Vec<String> {
    let mut g: Vec<String> = Vec::new();
    for v in &rec.variants {
        let l = group_of(rec, v);
        if !g.contains(&l) {
            g.push(l);
        }
    }
    g
}

/// Per axis, group and method: the last listed value survived as ok before the first non-ok one.
pub fn survival(rec: &SweepRecord, cfg: &ReportConfig, rows: &[Row]) -> Json {
    let mut out = Map::new();
    let status_of = |vi: usize, mi: usize| {
        rows.iter()
            .find(|r| r.variant == vi && r.method == mi)
            .map(|r| r.status)
    };
    for (axis, values) in &rec.each {
        let mut per_group = Map::new();
        for g in groups(rec) {
            let pts = axis_points(rec, &g, axis);
            let mut per_method = Map::new();
            for (mi, (name, _)) in cfg.methods.iter().enumerate() {
                let mut survived = Json::Null;
                for val in values {
                    // The variant at this value: a varying one first, else the base point.
                    let at = pts
                        .iter()
                        .copied()
                        .filter(|&i| &rec.variants[i].settings[axis] == val)
                        .max_by_key(|&i| rec.variants[i].varied.is_some());
                    match at.and_then(|i| status_of(i, mi)) {
                        Some(Status::Ok) => survived = val.clone(),
                        _ => break,
                    }
                }
                per_method.insert(name.clone(), survived);
            }
            per_group.insert(g, Json::Object(per_method));
        }
        out.insert(axis.clone(), Json::Object(per_group));
    }
    Json::Object(out)
}

const METHOD_COLORS: [RGBColor; 4] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
];

fn method_color(i: usize) -> RGBColor {
    METHOD_COLORS[i % METHOD_COLORS.len()]
}

/// A method's chart points: (x, F3 or None when failed, status).
pub type MethodPoints = Vec<(f64, Option<f64>, Status)>;

/// One chart's data: per method the (x, F3, status) points, the defurring points (x, value or
/// None when missing, failure label), the x range and labels.
pub struct ChartData {
    pub title: String,
    pub axis: String,
    pub methods: Vec<(String, MethodPoints)>,
    pub defur: Vec<(f64, Option<f64>, String)>,
    /// Tick labels for non-numeric axes.
    pub tick_labels: Option<Vec<String>>,
}

fn chart_data(
    rec: &SweepRecord,
    cfg: &ReportConfig,
    rows: &[Row],
    group: &str,
    axis: &str,
) -> ChartData {
    let values = &rec.each.iter().find(|(k, _)| k == axis).expect("axis").1;
    let mut pts = axis_points(rec, group, axis);
    pts.sort_by(|&a, &b| {
        axis_x(values, &rec.variants[a].settings[axis])
            .total_cmp(&axis_x(values, &rec.variants[b].settings[axis]))
    });
    let numeric = values.iter().all(|v| v.as_f64().is_some());
    let methods = cfg
        .methods
        .iter()
        .enumerate()
        .map(|(mi, (name, _))| {
            let p = pts
                .iter()
                .filter_map(|&vi| {
                    let r = rows.iter().find(|r| r.variant == vi && r.method == mi)?;
                    Some((
                        axis_x(values, &rec.variants[vi].settings[axis]),
                        r.f[1],
                        r.status,
                    ))
                })
                .collect();
            (name.clone(), p)
        })
        .collect();
    let defur = pts
        .iter()
        .map(|&vi| {
            let v = &rec.variants[vi];
            let label = match &v.failed_stage {
                Some(s) => format!("failed at {s}"),
                None => "no defurring metric".into(),
            };
            (
                axis_x(values, &v.settings[axis]),
                v.metrics.get(&cfg.defur_key).copied(),
                label,
            )
        })
        .collect();
    ChartData {
        title: format!("{group}: {axis}"),
        axis: axis.to_string(),
        methods,
        defur,
        tick_labels: if numeric {
            None
        } else {
            Some(values.iter().map(value_label).collect())
        },
    }
}

/// Draws the two panels (F3 per method, defurring error) of one chart.
pub fn draw_chart<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    d: &ChartData,
) -> Result<(), String> {
    root.fill(&WHITE).map_err(chart_err)?;
    let root = root
        .titled(&d.title, ("sans-serif", 22))
        .map_err(chart_err)?;
    let (top, bottom) = root.split_vertically((root.dim_in_pixel().1 as f64 * 0.58) as u32);
    let x = XAxis {
        range: x_range(d),
        ticks: d.tick_labels.clone(),
    };
    let fmt_x = |v: &f64| x.label(v);
    draw_fscore_panel(&top, d, x.range, &fmt_x)?;
    draw_defur_panel(&bottom, d, x.range, &fmt_x)?;
    root.present().map_err(chart_err)?;
    Ok(())
}

/// A panel's cartesian chart: x along the swept axis, y the panel's value.
type Panel<'a, DB> = ChartContext<'a, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// The shared x axis of both panels: its range and, for non-numeric axes, the tick labels.
struct XAxis {
    range: (f64, f64),
    ticks: Option<Vec<String>>,
}

impl XAxis {
    /// The tick label at `x`: the listed value at whole positions of a non-numeric axis (empty
    /// between them), else the number.
    fn label(&self, x: &f64) -> String {
        match &self.ticks {
            Some(t) => {
                let i = x.round();
                if (x - i).abs() < 1e-6 && i >= 0.0 && (i as usize) < t.len() {
                    t[i as usize].clone()
                } else {
                    String::new()
                }
            }
            None => fmt_value(*x),
        }
    }
}

/// The x range of all points of both panels, padded by 12 % of its width (1 if it has none).
fn x_range(d: &ChartData) -> (f64, f64) {
    let xs: Vec<f64> = d
        .methods
        .iter()
        .flat_map(|(_, p)| p.iter().map(|q| q.0))
        .chain(d.defur.iter().map(|q| q.0))
        .collect();
    let (mut x0, mut x1) = (
        xs.iter().copied().fold(f64::MAX, f64::min),
        xs.iter().copied().fold(f64::MIN, f64::max),
    );
    if xs.is_empty() {
        (x0, x1) = (0.0, 1.0);
    }
    let pad = if x1 > x0 { 0.12 * (x1 - x0) } else { 1.0 };
    (x0 - pad, x1 + pad)
}

/// The top panel: each method's F-score line with its status markers, and the legend.
fn draw_fscore_panel<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    d: &ChartData,
    (x0, x1): (f64, f64),
    fmt_x: &dyn Fn(&f64) -> String,
) -> Result<(), String> {
    let fmax = d
        .methods
        .iter()
        .flat_map(|(_, p)| p.iter().filter_map(|q| q.1))
        .fold(0.0, f64::max);
    let ymax = ((fmax / 10.0).ceil() * 10.0 + 10.0).clamp(10.0, 110.0);
    let mut chart = ChartBuilder::on(area)
        .caption(
            "F-score (dot ok, ring degraded, cross on the axis failed)",
            ("sans-serif", 15),
        )
        .margin(10)
        .x_label_area_size(36)
        .y_label_area_size(56)
        .build_cartesian_2d(x0..x1, 0.0..ymax)
        .map_err(chart_err)?;
    chart
        .configure_mesh()
        .x_desc(d.axis.as_str())
        .y_desc("F-score 3 cm / 30\u{b0} (%)")
        .x_labels(12)
        .x_label_formatter(fmt_x)
        .y_label_formatter(&|y| format!("{y:.0}"))
        .label_style(("sans-serif", 13))
        .axis_desc_style(("sans-serif", 14))
        .draw()
        .map_err(chart_err)?;
    for (mi, (name, pts)) in d.methods.iter().enumerate() {
        draw_method_series(&mut chart, mi, name, pts, ymax)?;
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 13))
        .draw()
        .map_err(chart_err)?;
    Ok(())
}

/// Method `mi`'s F-score line (in the legend) and one marker per point: a dot when ok, a ring
/// when degraded, a cross on the axis with a "failed" note (stacked per method) when failed.
fn draw_method_series<DB: DrawingBackend>(
    chart: &mut Panel<'_, DB>,
    mi: usize,
    name: &str,
    pts: &[(f64, Option<f64>, Status)],
    ymax: f64,
) -> Result<(), String> {
    let c = method_color(mi);
    let line: Vec<(f64, f64)> = pts.iter().filter_map(|p| p.1.map(|f| (p.0, f))).collect();
    chart
        .draw_series(LineSeries::new(line.clone(), c.stroke_width(2)))
        .map_err(chart_err)?
        .label(name)
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2)));
    for p in pts {
        match (p.1, p.2) {
            (Some(f), Status::Ok) => {
                chart
                    .draw_series(std::iter::once(Circle::new((p.0, f), 4, c.filled())))
                    .map_err(chart_err)?;
            }
            (Some(f), _) => {
                chart
                    .draw_series(std::iter::once(Circle::new((p.0, f), 6, c.stroke_width(2))))
                    .map_err(chart_err)?;
            }
            (None, _) => {
                chart
                    .draw_series(std::iter::once(Cross::new(
                        (p.0, 0.0),
                        7,
                        c.stroke_width(3),
                    )))
                    .map_err(chart_err)?;
                chart
                    .draw_series(std::iter::once(Text::new(
                        format!("{name} failed"),
                        (p.0, ymax * (0.05 + 0.07 * mi as f64)),
                        ("sans-serif", 13)
                            .into_font()
                            .color(&c)
                            .pos(Pos::new(HPos::Center, VPos::Bottom)),
                    )))
                    .map_err(chart_err)?;
            }
        }
    }
    Ok(())
}

/// The bottom panel: the defurring error line shared by all methods, with a cross and the
/// failure label where it is missing.
fn draw_defur_panel<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    d: &ChartData,
    (x0, x1): (f64, f64),
    fmt_x: &dyn Fn(&f64) -> String,
) -> Result<(), String> {
    let dmax = d.defur.iter().filter_map(|q| q.1).fold(0.0, f64::max);
    let dy = if dmax > 0.0 { dmax * 1.3 } else { 1.0 };
    let mut chart = ChartBuilder::on(area)
        .margin(10)
        .x_label_area_size(36)
        .y_label_area_size(56)
        .build_cartesian_2d(x0..x1, 0.0..dy)
        .map_err(chart_err)?;
    chart
        .configure_mesh()
        .x_desc(d.axis.as_str())
        .y_desc("defurring error (x GT thickness)")
        .x_labels(12)
        .x_label_formatter(fmt_x)
        .y_label_formatter(&|y| format!("{y:.2}"))
        .label_style(("sans-serif", 13))
        .axis_desc_style(("sans-serif", 14))
        .draw()
        .map_err(chart_err)?;
    let grey = RGBColor(60, 60, 60);
    let line: Vec<(f64, f64)> = d
        .defur
        .iter()
        .filter_map(|p| p.1.map(|v| (p.0, v)))
        .collect();
    chart
        .draw_series(LineSeries::new(line.clone(), grey.stroke_width(2)))
        .map_err(chart_err)?
        .label("defurring (shared by all methods)")
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], grey.stroke_width(2)));
    chart
        .draw_series(line.iter().map(|p| Circle::new(*p, 4, grey.filled())))
        .map_err(chart_err)?;
    for p in d.defur.iter().filter(|p| p.1.is_none()) {
        chart
            .draw_series(std::iter::once(Cross::new(
                (p.0, 0.0),
                7,
                BLACK.stroke_width(3),
            )))
            .map_err(chart_err)?;
        chart
            .draw_series(std::iter::once(Text::new(
                p.2.clone(),
                (p.0, dy * 0.08),
                ("sans-serif", 13)
                    .into_font()
                    .color(&BLACK)
                    .pos(Pos::new(HPos::Center, VPos::Bottom)),
            )))
            .map_err(chart_err)?;
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 13))
        .draw()
        .map_err(chart_err)?;
    Ok(())
}

/// A file-name-safe version of a label.
fn safe(s: &str) -> String {
    s.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '.' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

fn fmt_opt(x: Option<f64>, digits: usize) -> String {
    match x {
        Some(v) => format!("{v:.digits$}"),
        None => "-".into(),
    }
}

fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

fn md_cell(s: &str) -> String {
    s.replace('|', "\\|").replace('\n', " ")
}

/// Counts per method.
fn counts(cfg: &ReportConfig, rows: &[Row]) -> Vec<[usize; 3]> {
    let mut c = vec![[0usize; 3]; cfg.methods.len()];
    for r in rows {
        c[r.method][r.status as usize] += 1;
    }
    c
}

/// The Markdown and CSV summaries.
pub fn summaries(
    rec: &SweepRecord,
    cfg: &ReportConfig,
    rows: &[Row],
    survives: &Json,
) -> (String, String) {
    let mut md = String::new();
    write_md_overview(&mut md, rec, cfg, rows);
    write_md_survival(&mut md, cfg, survives);
    write_md_variants(&mut md, rec, cfg, rows);
    (md, summary_csv(rec, cfg, rows))
}

/// The Markdown title, the status rules and the per-method status counts.
fn write_md_overview(md: &mut String, rec: &SweepRecord, cfg: &ReportConfig, rows: &[Row]) {
    let name = if rec.pipeline.is_empty() {
        "sweep"
    } else {
        &rec.pipeline
    };
    let _ = writeln!(md, "# Stability: `{name}`\n");
    let _ = writeln!(
        md,
        "{} variants x {} methods. A method is **failed** on a variant without its F-score (3 cm / 30\u{b0}), \
         **degraded** when the engine said so, its F-score fell more than {:.0}% below the clean base point \
         of the same group, or the defurring error (`{}`) rose more than {:.0}% above it.\n",
        rec.variants.len(),
        cfg.methods.len(),
        100.0 * cfg.baseline_drop,
        cfg.defur_key,
        100.0 * cfg.defur_rise
    );
    let _ = writeln!(
        md,
        "| method | metric prefix | ok | degraded | failed |\n|---|---|---:|---:|---:|"
    );
    for ((name, prefix), c) in cfg.methods.iter().zip(counts(cfg, rows)) {
        let _ = writeln!(
            md,
            "| {name} | `{prefix}` | {} | {} | {} |",
            c[0], c[1], c[2]
        );
    }
}

/// The Markdown table of the largest corruption each method survived as ok, per axis and group.
fn write_md_survival(md: &mut String, cfg: &ReportConfig, survives: &Json) {
    let _ = writeln!(md, "\n## Largest corruption survived as ok\n");
    let _ = write!(md, "| axis | group |");
    for (n, _) in &cfg.methods {
        let _ = write!(md, " {n} |");
    }
    let _ = write!(md, "\n|---|---|");
    for _ in &cfg.methods {
        let _ = write!(md, "---:|");
    }
    md.push('\n');
    if let Json::Object(axes) = survives {
        for (axis, per_group) in axes {
            if let Json::Object(pg) = per_group {
                for (g, per_method) in pg {
                    let _ = write!(md, "| `{axis}` | {g} |");
                    for (n, _) in &cfg.methods {
                        let v = per_method.get(n).cloned().unwrap_or(Json::Null);
                        let _ = write!(
                            md,
                            " {} |",
                            if v.is_null() {
                                "none".into()
                            } else {
                                value_label(&v)
                            }
                        );
                    }
                    md.push('\n');
                }
            }
        }
    }
}

/// Per group and axis, a Markdown table of every variant's rows along the axis.
fn write_md_variants(md: &mut String, rec: &SweepRecord, cfg: &ReportConfig, rows: &[Row]) {
    for g in groups(rec) {
        let _ = writeln!(md, "\n## {g}");
        for (axis, _) in &rec.each {
            let _ = writeln!(
                md,
                "\n### `{axis}`\n\n| value | variant | method | status | F 2cm | F 3cm | F 4cm | defur error | reason |\n|---|---|---|---|---:|---:|---:|---:|---|"
            );
            for vi in axis_points(rec, &g, axis) {
                let v = &rec.variants[vi];
                for r in rows.iter().filter(|r| r.variant == vi) {
                    let value = value_label(&v.settings[axis]);
                    write_md_row(md, rec, cfg, r, &value, v.varied.is_none());
                }
            }
        }
    }
}

/// One Markdown table row: the axis value (marked when it is the clean base point), variant,
/// method, status, F-scores, defurring error and reason.
fn write_md_row(
    md: &mut String,
    rec: &SweepRecord,
    cfg: &ReportConfig,
    r: &Row,
    value: &str,
    base: bool,
) {
    let v = &rec.variants[r.variant];
    let _ = writeln!(
        md,
        "| {}{} | {} | {} | **{}** | {} | {} | {} | {} | {} |",
        value,
        if base { " (clean)" } else { "" },
        md_cell(&v.name),
        cfg.methods[r.method].0,
        r.status.as_str(),
        fmt_opt(r.f[0], 1),
        fmt_opt(r.f[1], 1),
        fmt_opt(r.f[2], 1),
        fmt_opt(r.defur, 3),
        md_cell(&r.reason)
    );
}

/// The CSV summary: one line per row, in row order.
fn summary_csv(rec: &SweepRecord, cfg: &ReportConfig, rows: &[Row]) -> String {
    let mut csv =
        String::from("group,axis,value,variant,method,status,reason,f2,f3,f4,defur_error\n");
    for r in rows {
        let v = &rec.variants[r.variant];
        let (axis, value) = match &v.varied {
            Some(a) => (a.clone(), value_label(&v.settings[a])),
            None => ("base".to_string(), String::new()),
        };
        let num = |x: Option<f64>| x.map(|x| format!("{x}")).unwrap_or_default();
        let _ = writeln!(
            csv,
            "{},{},{},{},{},{},{},{},{},{},{}",
            csv_field(&r.group),
            csv_field(&axis),
            csv_field(&value),
            csv_field(&v.name),
            csv_field(&cfg.methods[r.method].0),
            r.status.as_str(),
            csv_field(&r.reason),
            num(r.f[0]),
            num(r.f[1]),
            num(r.f[2]),
            num(r.defur)
        );
    }
    csv
}

/// Everything the stage writes, from a record: charts into `charts`, the other outputs to paths.
pub fn report(
    rec: &SweepRecord,
    cfg: &ReportConfig,
    charts: &Path,
    size: (u32, u32),
) -> Result<(String, String, Json), StageError> {
    let rows = assess(rec, cfg);
    let survives = survival(rec, cfg, &rows);
    for g in groups(rec) {
        for (axis, _) in &rec.each {
            let d = chart_data(rec, cfg, &rows, &g, axis);
            let stem = format!("{}__{}", safe(&g), safe(axis));
            write_png_chart(&charts.join(format!("{stem}.png")), size, |r| {
                draw_chart(r, &d)
            })?;
            write_svg_chart(&charts.join(format!("{stem}.svg")), size, |r| {
                draw_chart(r, &d)
            })?;
        }
    }
    let (md, csv) = summaries(rec, cfg, &rows, &survives);
    let mut per_method = Map::new();
    for ((name, _), c) in cfg.methods.iter().zip(counts(cfg, &rows)) {
        per_method.insert(
            name.clone(),
            json!({"ok": c[0], "degraded": c[1], "failed": c[2]}),
        );
    }
    let metrics = json!({
        "variants": rec.variants.len(),
        "methods": per_method,
        "survives": survives,
        "baseline_drop": cfg.baseline_drop,
        "defur_rise": cfg.defur_rise,
        "defur_key": cfg.defur_key,
    });
    Ok((md, csv, metrics))
}

/// Stage `stability_report`.
pub struct StabilityReportStage;

fure_stage_api::stage_params! {
    /// The `stability_report` stage's parameters.
    pub struct StabilityReportParams {
        /// metric key prefix of FurE's evaluation
        fure_prefix: String = string("evaluate"),
        /// metric key prefix of the dense baseline's evaluation
        dense_prefix: String = string("evaluate_dense"),
        /// metric key prefix of the fixed-length ablation's evaluation
        fixed_prefix: String = string("evaluate_fixed"),
        /// metric key of the defurring error
        defur_key: String = string("defur.root_to_skin_mean_frac"),
        /// relative F-score drop below the clean base point that makes a variant degraded
        baseline_drop: f64 = float(0.25).range(0.0, 1.0),
        /// relative defurring-error rise above the clean base point that makes a variant degraded
        defur_rise: f64 = float(0.5).range(0.0, 1000.0),
        /// chart width (px)
        width: u32 = int(900).range(300.0, 8000.0),
        /// chart height (px)
        height: u32 = int(760).range(300.0, 8000.0),
    }
}

fn config(p: &StabilityReportParams) -> Result<ReportConfig, StageError> {
    let mut methods = Vec::new();
    for (name, param, value) in [
        ("FurE", "fure_prefix", &p.fure_prefix),
        ("dense", "dense_prefix", &p.dense_prefix),
        ("fixed", "fixed_prefix", &p.fixed_prefix),
    ] {
        let prefix = value.trim().to_string();
        if prefix.is_empty() {
            return Err(StageError::param(
                param,
                "expected a metric key prefix such as `evaluate`",
            ));
        }
        methods.push((name.to_string(), prefix));
    }
    let defur_key = p.defur_key.trim().to_string();
    if defur_key.is_empty() {
        return Err(StageError::param("defur_key", "expected a metric key"));
    }
    Ok(ReportConfig {
        methods,
        defur_key,
        baseline_drop: p.baseline_drop,
        defur_rise: p.defur_rise,
    })
}

impl Stage for StabilityReportStage {
    fn kind(&self) -> &'static str {
        "stability_report"
    }
    fn version(&self) -> u32 {
        2
    }
    fn doc(&self) -> &'static str {
        "Stability sweep report from the engine's sweep record: per group (animal) and corruption axis, \
         charts (PNG + SVG) of the F-score at 3cm/30deg of FurE, dense and the fixed-length ablation and \
         of the defurring error against the corruption value (failed variants marked on the axis); a \
         status per method and variant (ok / degraded / failed with the reason), Markdown and CSV \
         summaries and the largest corruption each method survives."
    }
    fn params(&self) -> Vec<ParamSpec> {
        StabilityReportParams::specs()
    }
    fn inputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![PortSpec::file(
            "sweep",
            "json",
            "the engine's sweep record (sweep.json)",
        )]
    }
    fn outputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![
            PortSpec::dir("charts", "per group and axis: <group>__<axis>.png and .svg"),
            PortSpec::file(
                "summary",
                "md",
                "counts, survival table, per-variant statuses",
            ),
            PortSpec::file("summary_csv", "csv", "one row per variant x method"),
            PortSpec::file(
                "metrics",
                "json",
                "counts per method and the largest corruption survived",
            ),
        ]
    }
    fn validate(&self, params: &Params) -> Result<(), StageError> {
        config(&StabilityReportParams::from_params(params)?).map(|_| ())
    }
    fn run(&self, ctx: &StageContext<'_>) -> Result<(), StageError> {
        let params = StabilityReportParams::from_params(ctx.params)?;
        let cfg = config(&params)?;
        let size = (params.width, params.height);
        let rec = SweepRecord::read(ctx.input("sweep")?)?;
        ctx.progress.message("charting");
        let (md, csv, metrics) = report(&rec, &cfg, ctx.output("charts")?, size)?;
        let write = |port: &str, text: &str| -> Result<(), StageError> {
            let p = ctx.output(port)?;
            std::fs::write(p, text).map_err(|e| StageError::io(p, e))
        };
        write("summary", &md)?;
        write("summary_csv", &csv)?;
        crate::formats::json::write_json(ctx.output("metrics")?, &metrics)?;
        let c = counts(&cfg, &assess(&rec, &cfg));
        ctx.progress.note(&format!(
            "{} variants; {}",
            rec.variants.len(),
            cfg.methods
                .iter()
                .zip(&c)
                .map(|((n, _), c)| format!("{n}: {} ok, {} degraded, {} failed", c[0], c[1], c[2]))
                .collect::<Vec<_>>()
                .join("; ")
        ));
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A hand-written record: two animals, noise (3 values) and views (2 values). The tiger's
    /// noise 0.1 variant failed at `outer`; its views 6 variant lost the dense metric only (dense
    /// failed, the engine kept going) and has a degraded FurE F-score; the bison's noise 0.05 has
    /// an engine warning and a large defurring error.
    fn record() -> Json {
        let m = |fure: Option<f64>, dense: Option<f64>, fixed: Option<f64>, defur: Option<f64>| {
            let mut o = Map::new();
            for (p, f) in [
                ("evaluate", fure),
                ("evaluate_dense", dense),
                ("evaluate_fixed", fixed),
            ] {
                if let Some(f) = f {
                    o.insert(format!("{p}.prf.2cm_20deg.fscore"), json!(f - 20.0));
                    o.insert(format!("{p}.prf.3cm_30deg.fscore"), json!(f));
                    o.insert(format!("{p}.prf.4cm_40deg.fscore"), json!(f + 10.0));
                }
            }
            if let Some(d) = defur {
                o.insert("defur.root_to_skin_mean_frac".into(), json!(d));
            }
            o.insert("corrupt.training_views_out".into(), json!(36));
            Json::Object(o)
        };
        let v = |i: usize,
                 animal: &str,
                 noise: f64,
                 views: i64,
                 varied: Json,
                 status: &str,
                 reason: &str,
                 stage: Json,
                 warnings: Json,
                 metrics: Json| {
            json!({"index": i, "name": format!("stability@v{i}"),
                   "settings": {"scene.preset": animal, "corrupt.noise_sigma": noise, "corrupt.views": views},
                   "varied": varied, "status": status, "reason": reason, "failed_stage": stage,
                   "warnings": warnings, "metrics": metrics})
        };
        let n = Json::Null;
        let noise = json!("corrupt.noise_sigma");
        let views = json!("corrupt.views");
        json!({
            "pipeline": "stability",
            "crossed": {"scene.preset": ["tiger", "bison"]},
            "each": {"corrupt.noise_sigma": [0.0, 0.05, 0.1], "corrupt.views": [0, 6]},
            "each_order": ["corrupt.views", "corrupt.noise_sigma"],
            "variants": [
                v(0, "tiger", 0.0, 0, n.clone(), "ok", "", n.clone(), json!([]), m(Some(60.0), Some(50.0), Some(40.0), Some(0.5))),
                v(1, "tiger", 0.05, 0, noise.clone(), "ok", "", n.clone(), json!([]), m(Some(55.0), Some(45.0), Some(38.0), Some(0.6))),
                v(2, "tiger", 0.1, 0, noise.clone(), "failed", "empty visual hull", json!("outer"), json!([]), json!({})),
                v(3, "tiger", 0.0, 6, views.clone(), "failed", "NaN in strands", json!("dense"), json!([]), m(Some(40.0), None, Some(39.0), Some(0.55))),
                v(4, "bison", 0.0, 0, n.clone(), "ok", "", n.clone(), json!([]), m(Some(70.0), Some(60.0), Some(50.0), Some(1.0))),
                v(5, "bison", 0.05, 0, noise.clone(), "degraded", "", n.clone(), json!(["frosting: loss rose"]), m(Some(69.0), Some(59.0), Some(49.0), Some(1.8))),
                v(6, "bison", 0.1, 0, noise, "ok", "", n.clone(), json!([]), m(Some(68.0), Some(58.0), Some(48.0), Some(1.1))),
                v(7, "bison", 0.0, 6, views, "ok", "", n, json!([]), m(Some(66.0), Some(57.0), None, Some(1.2))),
            ]
        })
    }

    fn parse(j: &Json) -> Result<SweepRecord, StageError> {
        SweepRecord::from_json(Path::new("sweep.json"), j)
    }

    fn row(rows: &[Row], v: usize, m: usize) -> &Row {
        rows.iter()
            .find(|r| r.variant == v && r.method == m)
            .unwrap()
    }

    #[test]
    fn statuses_follow_the_rules() {
        let rec = parse(&record()).unwrap();
        let keys: Vec<&str> = rec.each.iter().map(|(k, _)| k.as_str()).collect();
        assert_eq!(
            keys,
            ["corrupt.views", "corrupt.noise_sigma"],
            "each_order kept"
        );
        let cfg = ReportConfig::default();
        let rows = assess(&rec, &cfg);
        assert_eq!(rows.len(), 8 * 3);
        // Base points are ok.
        for m in 0..3 {
            assert_eq!(row(&rows, 0, m).status, Status::Ok);
            assert_eq!(row(&rows, 4, m).status, Status::Ok);
        }
        // Small drop: ok (55 vs 60 is -8%).
        assert_eq!(row(&rows, 1, 0).status, Status::Ok);
        // Failed upstream: every method failed with the engine's reason and stage.
        for m in 0..3 {
            let r = row(&rows, 2, m);
            assert_eq!(r.status, Status::Failed);
            assert!(
                r.reason.contains("outer") && r.reason.contains("empty visual hull"),
                "{}",
                r.reason
            );
            assert_eq!(r.f, [None; 3]);
        }
        // Dense failed, FurE and fixed kept their metrics: FurE degraded (40 vs 60 = -33%), fixed ok.
        let r = row(&rows, 3, 1);
        assert_eq!(r.status, Status::Failed);
        assert!(
            r.reason.contains("dense") && r.reason.contains("NaN"),
            "{}",
            r.reason
        );
        let r = row(&rows, 3, 0);
        assert_eq!(r.status, Status::Degraded);
        assert!(
            r.reason.contains("33% below the clean 60.0"),
            "{}",
            r.reason
        );
        assert_eq!(r.f, [Some(20.0), Some(40.0), Some(50.0)]);
        assert_eq!(row(&rows, 3, 2).status, Status::Ok);
        // Engine degraded + defurring error +80%: both reasons.
        let r = row(&rows, 5, 2);
        assert_eq!(r.status, Status::Degraded);
        assert!(r.reason.contains("frosting: loss rose"), "{}", r.reason);
        assert!(
            r.reason
                .contains("defurring error 1.800 is 80% above the clean 1.000"),
            "{}",
            r.reason
        );
        // +10% defurring error: ok.
        assert_eq!(row(&rows, 6, 0).status, Status::Ok);
        // A missing metric on an ok variant: failed, naming the key.
        let r = row(&rows, 7, 2);
        assert_eq!(r.status, Status::Failed);
        assert!(
            r.reason.contains("evaluate_fixed.prf.3cm_30deg.fscore"),
            "{}",
            r.reason
        );
        // Thresholds are parameters: a stricter drop limit degrades variant 1.
        let strict = ReportConfig {
            baseline_drop: 0.05,
            ..ReportConfig::default()
        };
        assert_eq!(row(&assess(&rec, &strict), 1, 0).status, Status::Degraded);
    }

    #[test]
    fn survival_and_counts() {
        let rec = parse(&record()).unwrap();
        let cfg = ReportConfig::default();
        let rows = assess(&rec, &cfg);
        let s = survival(&rec, &cfg, &rows);
        assert_eq!(s["corrupt.noise_sigma"]["tiger"]["FurE"], json!(0.05));
        // Bison noise: 0.05 is degraded (engine), so only the clean value survives.
        assert_eq!(s["corrupt.noise_sigma"]["bison"]["dense"], json!(0.0));
        assert_eq!(s["corrupt.views"]["tiger"]["fixed"], json!(6));
        assert_eq!(s["corrupt.views"]["tiger"]["dense"], json!(0));
        assert_eq!(s["corrupt.views"]["bison"]["fixed"], json!(0));
        let c = counts(&cfg, &rows);
        // FurE: ok at 0, 1, 4, 6, 7; degraded at 3, 5; failed at 2.
        assert_eq!(c[0], [5, 2, 1]);
        assert_eq!(
            c.iter()
                .map(|x| x.iter().sum::<usize>())
                .collect::<Vec<_>>(),
            vec![8, 8, 8]
        );
    }

    #[test]
    fn outputs_are_written() {
        let rec = parse(&record()).unwrap();
        let cfg = ReportConfig::default();
        let dir = tempfile::tempdir().unwrap();
        let (md, csv, metrics) = report(&rec, &cfg, dir.path(), (600, 500)).unwrap();
        // To look at the charts: FURE_KEEP_CHARTS=/some/dir cargo test ... outputs_are_written
        if let Some(keep) = std::env::var_os("FURE_KEEP_CHARTS") {
            for f in std::fs::read_dir(dir.path()).unwrap() {
                let f = f.unwrap().path();
                std::fs::create_dir_all(&keep).unwrap();
                std::fs::copy(&f, Path::new(&keep).join(f.file_name().unwrap())).unwrap();
            }
        }
        for g in ["tiger", "bison"] {
            for a in ["corrupt.noise_sigma", "corrupt.views"] {
                let png = dir.path().join(format!("{g}__{a}.png"));
                let img = crate::formats::images::read_png(&png).unwrap();
                assert_eq!((img.width, img.height), (600, 500));
                // Not a blank image: some dark pixels (text, axes) and some coloured ones (lines).
                assert!(img
                    .data
                    .chunks(3)
                    .any(|p| p[0] < 0.2 && p[1] < 0.2 && p[2] < 0.2));
                assert!(
                    img.data.chunks(3).any(|p| p[2] > 0.5 && p[0] < 0.3),
                    "a FurE-blue mark"
                );
                let svg =
                    std::fs::read_to_string(dir.path().join(format!("{g}__{a}.svg"))).unwrap();
                assert!(svg.starts_with("<svg") && svg.contains(a));
            }
        }
        // The failed tiger variant is marked and labelled on the noise chart.
        let svg =
            std::fs::read_to_string(dir.path().join("tiger__corrupt.noise_sigma.svg")).unwrap();
        assert!(
            svg.contains("FurE failed") && svg.contains("failed at outer"),
            "labels of the failure"
        );
        let svg =
            std::fs::read_to_string(dir.path().join("bison__corrupt.noise_sigma.svg")).unwrap();
        assert!(!svg.contains("FurE failed") && !svg.contains("failed at"));
        // CSV: header + one row per variant x method.
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines.len(), 1 + 24);
        assert!(lines[0]
            .starts_with("group,axis,value,variant,method,status,reason,f2,f3,f4,defur_error"));
        assert!(lines
            .iter()
            .any(|l| l.starts_with("tiger,corrupt.noise_sigma,0.1,stability@v2,dense,failed,")));
        assert!(lines
            .iter()
            .any(|l| l.starts_with("bison,base,,stability@v4,FurE,ok,")));
        // Markdown: counts and the rows.
        assert!(md.contains("| FurE | `evaluate` | 5 | 2 | 1 |"), "{md}");
        assert!(
            md.contains("| `corrupt.views` | tiger | 0 | 6 | 6 |")
                || md.contains("| `corrupt.views` | tiger | 0 | 0 | 6 |"),
            "{md}"
        );
        assert!(md.contains("## bison") && md.contains("**failed**"));
        assert_eq!(
            metrics["methods"]["dense"],
            json!({"ok": 5, "degraded": 1, "failed": 2})
        );
        assert_eq!(
            metrics["survives"]["corrupt.noise_sigma"]["tiger"]["FurE"],
            json!(0.05)
        );
    }

    #[test]
    fn missing_keys_are_named() {
        let base = record();
        type Edit = Box<dyn Fn(&mut Json)>;
        let cases: Vec<(Edit, &str)> = vec![
            (
                Box::new(|j| {
                    j.as_object_mut().unwrap().remove("variants");
                }),
                "`variants`",
            ),
            (
                Box::new(|j| {
                    j.as_object_mut().unwrap().remove("each");
                }),
                "`each`",
            ),
            (
                Box::new(|j| {
                    j["variants"][3].as_object_mut().unwrap().remove("status");
                }),
                "`variants[3].status`",
            ),
            (
                Box::new(|j| {
                    j["variants"][2]["status"] = json!("crashed");
                }),
                "`variants[2].status`",
            ),
            (
                Box::new(|j| {
                    j["variants"][5].as_object_mut().unwrap().remove("metrics");
                }),
                "`variants[5].metrics`",
            ),
            (
                Box::new(|j| {
                    j["variants"][1]["settings"]
                        .as_object_mut()
                        .unwrap()
                        .remove("corrupt.views");
                }),
                "`variants[1].settings.corrupt.views`",
            ),
            (
                Box::new(|j| {
                    j["variants"][1]["varied"] = json!("corrupt.jitter_deg");
                }),
                "`variants[1].varied`",
            ),
            (
                Box::new(|j| {
                    j["variants"][0]["warnings"] = json!([1]);
                }),
                "`variants[0].warnings[0]`",
            ),
            (
                Box::new(|j| {
                    j["each"]["corrupt.views"] = json!([]);
                }),
                "`each.corrupt.views`",
            ),
            (
                Box::new(|j| {
                    *j = json!([1, 2]);
                }),
                "(top level)",
            ),
        ];
        for (edit, key) in cases {
            let mut j = base.clone();
            edit(&mut j);
            let e = parse(&j).unwrap_err();
            assert!(e.to_string().contains(key), "{key}: {e}");
            assert!(e.to_string().contains("sweep.json"), "{e}");
        }
        // Optional keys may be absent; an empty record charts nothing but does not fail.
        let mut j = base.clone();
        for v in j["variants"].as_array_mut().unwrap() {
            let o = v.as_object_mut().unwrap();
            for k in ["reason", "failed_stage", "warnings", "index", "name"] {
                o.remove(k);
            }
        }
        j.as_object_mut().unwrap().remove("pipeline");
        let rec = parse(&j).unwrap();
        assert_eq!(rec.variants[2].name, "v2");
        assert_eq!(
            row(&assess(&rec, &ReportConfig::default()), 2, 0).status,
            Status::Failed
        );
        let empty = parse(&json!({"each": {}, "variants": []})).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let (_, csv, m) = report(&empty, &ReportConfig::default(), dir.path(), (400, 400)).unwrap();
        assert_eq!(csv.lines().count(), 1);
        assert_eq!(m["variants"], json!(0));
    }

    #[test]
    fn missing_base_point_is_said() {
        let mut j = record();
        // Drop the bison base point: no reference, statuses only from the engine.
        j["variants"].as_array_mut().unwrap().remove(4);
        let rec = parse(&j).unwrap();
        let rows = assess(&rec, &ReportConfig::default());
        let r = rows
            .iter()
            .find(|r| rec.variants[r.variant].index == 6 && r.method == 0)
            .unwrap();
        assert_eq!(r.status, Status::Ok);
        assert!(r.reason.contains("no clean reference"), "{}", r.reason);
        let s = survival(&rec, &ReportConfig::default(), &rows);
        assert_eq!(s["corrupt.noise_sigma"]["bison"]["FurE"], Json::Null);
    }
}
