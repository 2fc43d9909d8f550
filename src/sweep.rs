//! Sweeps: run every variant of a parameter grid, sharing the cache.
//!
//! The grid is the `[sweep]` table of the pipeline plus `--grid` options (a
//! `--grid` for the same `STAGE.PARAM` replaces the table's values). Variants
//! are the cartesian product, keys in sorted order, the last key varying
//! fastest. Each variant is the pipeline with its settings applied, named
//! `<pipeline>@v<N>` (its outputs go to `out/<pipeline>@v<N>/`), and runs on
//! the same cache, so stages upstream of the swept parameters are computed
//! once and hit for every other variant.
//!
//! The table has one row per variant: the settings, how many stages ran and
//! were cached, the wall seconds, the compute seconds of each stage (the
//! seconds its cache entry took to compute, also when it was a hit; Markdown
//! marks hits with `*`), and every number found in the stages' `metrics.json`
//! outputs, flattened as `stage.key.subkey`.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::Path;

use fure_stage_api::Value;

use crate::cache::Cache;
use crate::exec::{self, RunOptions, RunReport, Status};
use crate::pipeline::{Loc, Pipeline, PipelineError, PipelineErrors};
use crate::plan::show;
use crate::Engine;

/// One variant of the grid.
#[derive(Debug, Clone)]
pub struct Variant {
    pub index: usize,
    pub settings: Vec<(String, Value)>,
}

/// The grid of a pipeline's `[sweep]` plus extra `STAGE.PARAM` -> values.
pub fn grid(pipeline: &Pipeline, extra: &[(String, Vec<Value>)]) -> Vec<Variant> {
    let mut axes: BTreeMap<String, Vec<Value>> = pipeline
        .sweep
        .iter()
        .map(|(k, (v, _))| (k.clone(), v.clone()))
        .collect();
    for (k, v) in extra {
        axes.insert(k.clone(), v.clone());
    }
    let mut variants: Vec<Vec<(String, Value)>> = vec![Vec::new()];
    for (k, values) in &axes {
        let mut next = Vec::with_capacity(variants.len() * values.len());
        for v in &variants {
            for x in values {
                let mut s = v.clone();
                s.push((k.clone(), x.clone()));
                next.push(s);
            }
        }
        variants = next;
    }
    variants
        .into_iter()
        .enumerate()
        .map(|(index, settings)| Variant { index, settings })
        .collect()
}

/// One row of the sweep table.
#[derive(Debug, Clone)]
pub struct Row {
    pub variant: Variant,
    pub name: String,
    pub report: RunReport,
    /// stage -> compute seconds (of the entry), cached?
    pub stage_seconds: BTreeMap<String, (f64, bool)>,
    pub metrics: BTreeMap<String, f64>,
}

/// Runs every variant; stops at the first variant whose pipeline is invalid.
pub fn run_sweep(
    engine: &Engine,
    pipeline: &Pipeline,
    variants: &[Variant],
    cache: &Cache,
    opts: &RunOptions,
    on_row: &mut dyn FnMut(&Row),
) -> Result<Vec<Row>, PipelineErrors> {
    // Check every variant before running any.
    let mut plans = Vec::new();
    for v in variants {
        let mut p = pipeline.clone();
        let mut errors = Vec::new();
        for (target, value) in &v.settings {
            let loc = pipeline
                .sweep
                .get(target)
                .map(|(_, l)| l.clone())
                .unwrap_or_else(|| Loc::origin(&format!("--grid {target}")));
            if let Err(e) = p.set_param(target, value.clone(), &loc) {
                errors.push(e);
            }
        }
        if !errors.is_empty() {
            return Err(PipelineErrors(errors));
        }
        p.name = format!("{}@v{}", pipeline.name, v.index);
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
    let mut rows = Vec::new();
    for (v, plan) in variants.iter().zip(&plans) {
        let report = exec::run(plan, cache, opts);
        let mut stage_seconds = BTreeMap::new();
        let mut metrics = BTreeMap::new();
        for s in &report.stages {
            if matches!(s.status, Status::Ran | Status::Cached) {
                let secs = cache.lookup(&s.key).map(|m| m.seconds).unwrap_or(s.seconds);
                stage_seconds.insert(s.name.clone(), (secs, s.status == Status::Cached));
            }
            for o in s.outputs.values() {
                if o.path.ends_with("metrics.json") {
                    let path = if Path::new(&o.path).exists() {
                        o.path.clone()
                    } else {
                        cache.object_path(&o.blake3).display().to_string()
                    };
                    if let Some(j) = std::fs::read(&path)
                        .ok()
                        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
                    {
                        flatten(&s.name, &j, &mut metrics);
                    }
                }
            }
        }
        let row = Row {
            variant: v.clone(),
            name: plan.name.clone(),
            report,
            stage_seconds,
            metrics,
        };
        on_row(&row);
        let failed = !row.report.ok();
        rows.push(row);
        if failed && !opts.keep_going {
            break;
        }
    }
    Ok(rows)
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
    header.extend(["ran", "cached", "wall_s"].map(String::from));
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

    #[test]
    fn grid_is_the_cartesian_product() {
        let p = Pipeline::parse_str(
            "[stages.a]\nkind=\"k\"\n[sweep]\n\"a.x\" = [1, 2]\n\"a.y\" = [\"p\", \"q\", \"r\"]\n",
            "s.toml",
            Path::new("/"),
        )
        .unwrap();
        let g = grid(&p, &[]);
        assert_eq!(g.len(), 6);
        assert_eq!(describe(&g[1]), "a.x=1, a.y=\"q\"");
        let g2 = grid(&p, &[("a.x".into(), vec![Value::Int(5)])]);
        assert_eq!(g2.len(), 3);
        let g3 = grid(&p, &[("a.z".into(), vec![Value::Int(5), Value::Int(6)])]);
        assert_eq!(g3.len(), 12);
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
