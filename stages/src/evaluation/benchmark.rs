//! The `benchmark_report` stage: the benchmark suite's results document, from a sweep record.
//!
//! `pipelines/benchmark.toml` sweeps scenes x seeds (linked keys: the preset with the baseline's
//! species table, the scene seed with every learner's seed) over the method and its ablations; this
//! stage, its aggregate, turns the engine's record (`sweep.json`, see [`crate::evaluation::stability`] for its
//! reader) into `results.md`, charts, a CSV of every run and `metrics.json` with the aggregates.
//!
//! # Protocol (what the document states and the code enforces)
//! - Scenes belong to declared splits: `dev` (the only scenes a default may be tuned on) and `test`
//!   (reported, never used to choose). A scene in neither is listed as `unsplit`.
//! - Per scene and method every figure is the mean and the sample standard deviation over seeds
//!   (`n - 1` in the denominator; with one seed the spread is unknown and shown as `-`).
//! - A comparison A vs B at a threshold is **won** only when A's mean is ahead by more than the
//!   seed spread, taken as the larger of the two standard deviations; behind by more is **lost**;
//!   anything else is a **tie**. With fewer than two seeds a side it is **undecided**: one run says
//!   nothing about the spread.
//! - The headline is the signed F-score (growth direction counted). Each scene's **ceiling** is the
//!   same animal regrown with another seed, scored against the GT (`ceiling` prefix): what a
//!   reconstruction could reach when only the seed's draws differ.
//! - The **targets** tables read the first method's figures, as this report states them,
//!   against the goals set for it (`target_*` parameters; the rules in
//!   [`crate::evaluation::targets`]): met, missed, undecided or not judged, per scene.
//!
//! # Keys read from the record
//! A method is `NAME=EVAL[:LEARNER]`: `EVAL` the prefix of its `evaluate` stage
//! (`EVAL.prf_signed.<d>cm_<a>deg.fscore`, `EVAL.direction_error_deg`, the worst part of
//! `EVAL.direction_error_by_part.PART.deg` and boundary of `EVAL.seams.excess.by_boundary.A|B`,
//! `EVAL.local_curvature_variance_vs_gt`, `EVAL.psnr`, `EVAL.ssim`), `LEARNER` its learning stage
//! (`LEARNER.optimised_parameters`, and the compute seconds `costs.LEARNER.seconds`). Preprocessing
//! time is the sum of `costs.S.seconds` over the `preprocessing` stages; peak memory the largest
//! `costs.*.peak_rss_bytes` of the variant. Fur thickness: `defur.{outer,root,baseline}_to_skin_mean_frac`,
//! `frosting.gt_vertex.pearson`, `frosting.resolution.{median_width_px,gt_median_thickness_px}`,
//! `lengths.length_error_mean_pct` (and, carried through the first method's learned part scales
//! `LEARNER.part_length_scale.P`, from `lengths.length_error_signed_pct.P`), and for the V2 lengths (species
//! reference lengths, issue 14: reported beside V1, never instead) `V2.length_error_mean_pct` with
//! `V2` the `v2_lengths` parameter. Speed: `speed_accuracy.speedup_*`; each learner's final against its untrained
//! start: `speed_accuracy.{codec,dense}_{start,final}_fscore_3cm_30deg`; the same at the strict
//! threshold, signed: `speed_accuracy.strict.*`. The size the first
//! method chose, named on its F vs model-size chart: `LEARNER.strands`,
//! `LEARNER.points_per_strand`, `basis.k`.
//! A missing key is a missing figure (`-`), never a zero.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use fure_stage_api::{ParamSpec, Params, PortSpec, Stage, StageContext, StageError};
use plotters::coord::Shift;
use plotters::prelude::*;
use serde_json::{json, Map, Value as Json};

use crate::evaluation::charts::{chart_err, fmt_num, write_png_chart, write_svg_chart};
use crate::evaluation::stability::{SweepRecord, VariantRecord};
use crate::evaluation::targets::{write_targets, Goals};

/// The line `fure sweep`'s `[publish]` replaces with the date, machine, revision and command
/// (the engine's `publish::PROVENANCE_MARK`): a cached output cannot say when it was made.
pub const PROVENANCE_MARK: &str = "<!-- fure:provenance -->";

/// The thresholds of the signed F-score, strict first (cm, degrees).
pub const THRESHOLDS: [(f32, f32); 4] = [(1.0, 10.0), (2.0, 20.0), (3.0, 30.0), (4.0, 40.0)];

/// One method of the suite: a display name, its evaluation prefix and its learner stage.
#[derive(Debug, Clone, PartialEq)]
pub struct Method {
    pub name: String,
    pub eval: String,
    pub learner: Option<String>,
}

/// Parses `NAME=EVAL[:LEARNER]`.
pub fn parse_method(s: &str) -> Result<Method, String> {
    let (name, rest) = s
        .split_once('=')
        .ok_or_else(|| format!("`{s}`: expected NAME=EVAL_STAGE[:LEARNER_STAGE]"))?;
    let (eval, learner) = match rest.split_once(':') {
        Some((e, l)) => (e.trim(), Some(l.trim().to_string())),
        None => (rest.trim(), None),
    };
    if name.trim().is_empty() || eval.is_empty() || learner.as_deref() == Some("") {
        return Err(format!(
            "`{s}`: expected NAME=EVAL_STAGE[:LEARNER_STAGE], none of them empty"
        ));
    }
    Ok(Method {
        name: name.trim().to_string(),
        eval: eval.to_string(),
        learner,
    })
}

/// What the report needs besides the record.
#[derive(Debug, Clone)]
pub struct Config {
    pub dev: Vec<String>,
    pub test: Vec<String>,
    pub scene_setting: String,
    pub seed_setting: String,
    pub methods: Vec<Method>,
    pub ceiling: String,
    pub preprocessing: Vec<String>,
    pub speedup: String,
    /// The lengths stage with species reference lengths (V2), reported beside `lengths`.
    pub v2_lengths: String,
    /// Where the published charts are, relative to the published document.
    pub charts_link: String,
    /// What the targets table reads the first method against.
    pub goals: Goals,
}

/// Mean, sample standard deviation (`None` below two values) and count.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stat {
    pub mean: f64,
    pub sd: Option<f64>,
    pub n: usize,
}

/// [`Stat`] of the finite values, `None` when there are none.
pub fn stat(values: &[f64]) -> Option<Stat> {
    let v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    let n = v.len();
    let mean = v.iter().sum::<f64>() / n as f64;
    let sd = (n > 1)
        .then(|| (v.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / (n - 1) as f64).sqrt());
    Some(Stat { mean, sd, n })
}

/// The protocol's verdict on A against B.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    Won,
    Lost,
    Tie,
    Undecided,
}

impl Verdict {
    pub fn label(self) -> &'static str {
        match self {
            Verdict::Won => "won",
            Verdict::Lost => "lost",
            Verdict::Tie => "tie",
            Verdict::Undecided => "undecided (1 seed)",
        }
    }
}

/// A vs B: won when A's mean is ahead by more than the larger standard deviation (module doc).
pub fn verdict(a: &Stat, b: &Stat) -> Verdict {
    let (Some(sa), Some(sb)) = (a.sd, b.sd) else {
        return Verdict::Undecided;
    };
    let spread = sa.max(sb);
    let d = a.mean - b.mean;
    if d > spread {
        Verdict::Won
    } else if -d > spread {
        Verdict::Lost
    } else {
        Verdict::Tie
    }
}

fn f_key(eval: &str, t: (f32, f32)) -> String {
    format!(
        "{eval}.prf_signed.{}.fscore",
        crate::evaluation::evaluate::threshold_key(t.0, t.1)
    )
}

/// The value of the setting whose (possibly linked) key names `target`.
fn setting<'a>(v: &'a VariantRecord, target: &str) -> Option<&'a Json> {
    v.settings
        .iter()
        .find(|(k, _)| k.split(',').any(|t| t.trim() == target))
        .map(|(_, x)| x)
}

fn label(x: &Json) -> String {
    match x {
        Json::String(s) => s.clone(),
        other => other.to_string(),
    }
}

/// The runs of one scene: its variants (each one seed).
struct Scene<'a> {
    name: String,
    split: &'static str,
    runs: Vec<&'a VariantRecord>,
}

fn scenes<'a>(rec: &'a SweepRecord, cfg: &Config) -> Vec<Scene<'a>> {
    let mut by: BTreeMap<String, Vec<&VariantRecord>> = BTreeMap::new();
    for v in &rec.variants {
        let name = setting(v, &cfg.scene_setting)
            .map(label)
            .unwrap_or_else(|| "-".into());
        by.entry(name).or_default().push(v);
    }
    let mut out = Vec::new();
    let mut take =
        |name: &str, split: &'static str, by: &mut BTreeMap<String, Vec<&'a VariantRecord>>| {
            if let Some(runs) = by.remove(name) {
                out.push(Scene {
                    name: name.to_string(),
                    split,
                    runs,
                });
            }
        };
    for s in &cfg.dev {
        take(s, "dev", &mut by);
    }
    for s in &cfg.test {
        take(s, "test", &mut by);
    }
    let rest: Vec<String> = by.keys().cloned().collect();
    for s in rest {
        take(&s, "unsplit", &mut by);
    }
    out
}

/// The values of `key` over a scene's runs that have it.
fn values(sc: &Scene<'_>, key: &str) -> Vec<f64> {
    sc.runs
        .iter()
        .filter_map(|v| v.metrics.get(key).copied())
        .collect()
}

fn cost(v: &VariantRecord, stage: &str) -> Option<f64> {
    v.costs.get(&format!("{stage}.seconds")).copied()
}

fn peak_rss(v: &VariantRecord) -> Option<f64> {
    v.costs
        .iter()
        .filter(|(k, _)| k.ends_with(".peak_rss_bytes"))
        .map(|(_, x)| *x)
        .reduce(f64::max)
}

/// The mean per-part length error (%) of `learner`'s trained strands: each part's error in
/// `lengths.length_error_signed_pct.P` carried through the learner's learned scale
/// `LEARNER.part_length_scale.P`. `None` without learned scales.
fn trained_length_error(v: &VariantRecord, learner: &str) -> Option<f64> {
    let prefix = "lengths.length_error_signed_pct.";
    let scales = format!("{learner}.part_length_scale.");
    if !v.metrics.keys().any(|k| k.starts_with(&scales)) {
        return None;
    }
    let errors: Vec<f64> = v
        .metrics
        .iter()
        .filter_map(|(k, &e)| {
            let part = k.strip_prefix(prefix)?;
            let scale = v.metrics.get(&format!("{scales}{part}")).copied()?;
            Some(((1.0 + e / 100.0) * scale - 1.0).abs() * 100.0)
        })
        .collect();
    (!errors.is_empty()).then(|| errors.iter().sum::<f64>() / errors.len() as f64)
}

fn preprocessing_seconds(v: &VariantRecord, cfg: &Config) -> Option<f64> {
    let s: Vec<f64> = cfg
        .preprocessing
        .iter()
        .filter_map(|st| cost(v, st))
        .collect();
    (!s.is_empty()).then(|| s.iter().sum())
}

pub(crate) fn fmt_stat(s: Option<Stat>, digits: usize) -> String {
    match s {
        None => "-".into(),
        Some(Stat {
            mean, sd: Some(sd), ..
        }) => format!("{mean:.digits$} ± {sd:.digits$}"),
        Some(Stat { mean, .. }) => format!("{mean:.digits$}"),
    }
}

fn stat_json(s: Option<Stat>) -> Json {
    match s {
        None => Json::Null,
        Some(s) => json!({"mean": s.mean, "sd": s.sd, "n": s.n}),
    }
}

/// The inverse of [`stat_json`]: `None` for a null or malformed figure.
pub(crate) fn stat_from_json(j: &Json) -> Option<Stat> {
    Some(Stat {
        mean: j["mean"].as_f64()?,
        sd: j["sd"].as_f64(),
        n: j["n"].as_u64()? as usize,
    })
}

/// Everything the stage writes except the charts.
pub struct Report {
    /// The whole results document (results.md).
    pub results: String,
    /// Only the headline tables, with a provenance mark: what the README quotes.
    pub headline: String,
    /// One row per run and method (runs.csv).
    pub runs: String,
    /// Per scene and method: mean, sd, n of every figure; verdicts (metrics.json).
    pub metrics: Json,
}

/// The report of a sweep record.
pub fn report(rec: &SweepRecord, cfg: &Config) -> Report {
    let scenes = scenes(rec, cfg);
    let mut md = String::new();
    let mut out = Map::new();
    write_preamble(&mut md, rec, cfg);
    let mut headline = String::new();
    write_headlines(&mut headline, &scenes, cfg);
    md.push_str(&headline);
    let verdicts = write_comparisons(&mut md, &scenes, cfg);
    // The scenes' sections come after the targets, which read their figures.
    let mut scenes_md = String::new();
    let per_scene: Json = scenes
        .iter()
        .map(|sc| (sc.name.clone(), write_scene(&mut scenes_md, sc, cfg)))
        .collect::<Map<String, Json>>()
        .into();
    if let (Some(first), Some(verdicts)) = (cfg.methods.first(), &verdicts) {
        let order: Vec<(&str, &str)> = scenes.iter().map(|s| (s.name.as_str(), s.split)).collect();
        let states = write_targets(
            &mut md,
            &order,
            &per_scene,
            verdicts,
            &first.name,
            &cfg.goals,
        );
        out.insert("targets".into(), states);
    }
    if let Some(verdicts) = verdicts {
        out.insert("verdicts".into(), verdicts);
    }
    let _ = writeln!(md, "## Per scene\n");
    md.push_str(&scenes_md);
    out.insert("scenes".into(), per_scene);
    out.insert("runs".into(), rec.variants.len().into());
    out.insert("stage_threads".into(), thread_counts(rec).into());
    let load = other_load(rec);
    if let Some(max) = load.max {
        out.insert("stage_other_load_max".into(), max.into());
    }
    Report {
        results: md,
        headline: format!(
            "{PROVENANCE_MARK}\n\n{}",
            headline.replace("## Headline", "### Headline")
        ),
        runs: runs_csv(&scenes, cfg),
        metrics: Json::Object(out),
    }
}

/// The distinct thread counts the variants' stages ran on (`costs.S.threads`,
/// sorted; entries that did not record one are left out).
fn thread_counts(rec: &SweepRecord) -> Vec<u64> {
    let mut t: Vec<u64> = rec
        .variants
        .iter()
        .flat_map(|v| v.costs.iter())
        .filter(|(k, x)| k.ends_with(".threads") && **x > 0.0)
        .map(|(_, x)| *x as u64)
        .collect();
    t.sort_unstable();
    t.dedup();
    t
}

/// Above this many cores used by other work on average, a stage's seconds are flagged (the
/// engine's `load::BUSY_CORES`; this crate does not depend on the engine).
pub const OTHER_LOAD_WARN: f64 = 0.5;

/// What the record says of other work while its stages ran (`costs.S.other_load`).
#[derive(Debug, Default, PartialEq)]
struct OtherLoad {
    /// Stage runs in the record, and those that recorded the figure.
    stages: usize,
    measured: usize,
    /// The largest figure.
    max: Option<f64>,
    /// (variant, stage, cores) above [`OTHER_LOAD_WARN`], worst first.
    above: Vec<(String, String, f64)>,
}

fn other_load(rec: &SweepRecord) -> OtherLoad {
    let mut o = OtherLoad::default();
    for v in &rec.variants {
        for (k, _) in v.costs.iter().filter(|(k, _)| k.ends_with(".seconds")) {
            let stage = &k[..k.len() - ".seconds".len()];
            o.stages += 1;
            let Some(&load) = v.costs.get(&format!("{stage}.other_load")) else {
                continue;
            };
            o.measured += 1;
            o.max = Some(o.max.map_or(load, |m: f64| m.max(load)));
            if load > OTHER_LOAD_WARN {
                o.above.push((v.name.clone(), stage.to_string(), load));
            }
        }
    }
    o.above.sort_by(|a, b| {
        b.2.total_cmp(&a.2)
            .then_with(|| (&a.0, &a.1).cmp(&(&b.0, &b.1)))
    });
    o
}

/// The sentence on other work beside the stages, if the record measured any.
fn other_load_note(rec: &SweepRecord) -> Option<String> {
    let o = other_load(rec);
    let max = o.max?;
    let unmeasured = if o.measured < o.stages {
        format!(
            " ({} of {} stage runs not measured: entries made before fure recorded it)",
            o.stages - o.measured,
            o.stages
        )
    } else {
        String::new()
    };
    Some(match o.above.first() {
        None => format!(
            "Other work on the machine used at most {max:.2} cores while a stage ran{unmeasured}.\n"
        ),
        Some((name, stage, worst)) => format!(
            "**Some stage seconds were measured beside other work**: in {} of {} measured stage \
             runs, other processes used more than {OTHER_LOAD_WARN} cores on average (the \
             worst: `{stage}` of {name}, {worst:.2} cores){unmeasured}. Those seconds, and the \
             speed-ups and charts made from them, are longer than the machine alone gives: \
             rerun on a quiet machine with a cache of the suite's own \
             (`costs.STAGE.other_load` in the sweep record).\n",
            o.above.len(),
            o.measured
        ),
    })
}

/// Title, provenance mark, splits, seeds and the rules the tables follow.
fn write_preamble(md: &mut String, rec: &SweepRecord, cfg: &Config) {
    let _ = writeln!(md, "# Benchmark results: `{}`\n", rec.pipeline);
    let _ = writeln!(md, "{}\n", PROVENANCE_MARK);
    let seeds: Vec<String> = {
        let mut s: Vec<String> = rec
            .variants
            .iter()
            .filter_map(|v| setting(v, &cfg.seed_setting).map(label))
            .collect();
        s.sort();
        s.dedup();
        s
    };
    let _ =
        writeln!(
        md,
        "Splits: **dev** {} (the only scenes any default may be tuned on); **test** {} (reported, \
         never used to choose). Seeds: {} (each regrows the animal and reseeds every learner). \
         {} runs, {} failed.\n",
        list_or_none(&cfg.dev),
        list_or_none(&cfg.test),
        if seeds.is_empty() { "-".into() } else { seeds.join(", ") },
        rec.variants.len(),
        rec.variants
            .iter()
            .filter(|v| v.status == crate::evaluation::stability::EngineStatus::Failed)
            .count(),
    );
    let _ = writeln!(
        md,
        "Every figure is mean ± sample standard deviation over seeds. A comparison is **won** only \
         when the mean is ahead by more than the seed spread (the larger standard deviation of the \
         two), **lost** when behind by more, a **tie** otherwise, and **undecided** with one seed. \
         F-scores are signed (growth direction counted), in %; the **ceiling** is the same animal \
         regrown with another seed, scored against the GT. The curvature variance over the GT's \
         is `-` where fewer than half of the method's or the GT's strands are long enough to carry \
         it (three resampled segments, about 1.5 cm): a short groom is not judged by its few \
         longest strands; and where the GT's strands are straight (Blender's hair): a ratio over \
         rounding noise says nothing. Beside it, the targets give the same ratio for the GT itself \
         redrawn with the method's points per strand: what an exact reconstruction at that \
         resolution would read (few points lose fine waves and turn tight curls uneven).\n"
    );
    // Seconds come from the cache entries, whose pools may differ in size
    // (a study at `--jobs 2` leaves entries a later `--jobs 1` suite reuses).
    match thread_counts(rec).as_slice() {
        [] => {}
        [one] => {
            let _ = writeln!(
                md,
                "Stage seconds come from runs on {one} thread(s) each.\n"
            );
        }
        many => {
            let list: Vec<String> = many.iter().map(|t| t.to_string()).collect();
            let _ = writeln!(
                md,
                "**Stage seconds mix thread counts** ({} threads): a cached stage keeps the \
                 seconds of the run that made it. Compare seconds and speed-ups only between \
                 runs on one count (`costs.STAGE.threads` in the sweep record), or rerun with \
                 a cache of the suite's own.\n",
                list.join(", ")
            );
        }
    }
    if let Some(note) = other_load_note(rec) {
        let _ = writeln!(md, "{note}");
    }
}

/// Headline: signed F at 3 cm / 30 deg and the strict 1 cm / 10 deg, per split, scene and method.
fn write_headlines(md: &mut String, scenes: &[Scene<'_>], cfg: &Config) {
    let t3 = THRESHOLDS[2];
    let t1 = THRESHOLDS[0];
    for split in ["dev", "test", "unsplit"] {
        let in_split: Vec<&Scene<'_>> = scenes.iter().filter(|s| s.split == split).collect();
        if in_split.is_empty() {
            continue;
        }
        let _ = writeln!(
            md,
            "## Headline, {split} split: signed F at 3 cm / 30° (strict 1 cm / 10° below)\n"
        );
        let mut head = "| scene | seeds |".to_string();
        let mut rule = "|---|---|".to_string();
        for m in &cfg.methods {
            let _ = write!(head, " {} |", m.name);
            rule.push_str("---|");
        }
        let _ = writeln!(md, "{head} ceiling |\n{rule}---|");
        for sc in &in_split {
            for t in [t3, t1] {
                let mut row = format!(
                    "| {}{} | {} |",
                    sc.name,
                    if t == t1 { " (1 cm)" } else { "" },
                    sc.runs.len()
                );
                for m in &cfg.methods {
                    let _ = write!(
                        row,
                        " {} |",
                        fmt_stat(stat(&values(sc, &f_key(&m.eval, t))), 1)
                    );
                }
                let _ = write!(
                    row,
                    " {} |",
                    fmt_stat(stat(&values(sc, &f_key(&cfg.ceiling, t))), 1)
                );
                let _ = writeln!(md, "{row}");
            }
        }
        let _ = writeln!(md);
    }
}

/// Verdicts of the first method against each other one, per scene and threshold (the JSON
/// `verdicts`; `None` without methods).
fn write_comparisons(md: &mut String, scenes: &[Scene<'_>], cfg: &Config) -> Option<Json> {
    if let Some((first, others)) = cfg.methods.split_first() {
        let _ = writeln!(
            md,
            "## Comparisons: {} against each method (signed F)\n",
            first.name
        );
        let _ = writeln!(md, "| scene | split | against | 1 cm | 2 cm | 3 cm | 4 cm |\n|---|---|---|---|---|---|---|");
        let mut verdicts = Map::new();
        for sc in scenes {
            for o in others {
                let mut row = format!("| {} | {} | {} |", sc.name, sc.split, o.name);
                let mut vj = Map::new();
                for t in THRESHOLDS {
                    let a = stat(&values(sc, &f_key(&first.eval, t)));
                    let b = stat(&values(sc, &f_key(&o.eval, t)));
                    let cell = match (a, b) {
                        (Some(a), Some(b)) => {
                            let v = verdict(&a, &b);
                            vj.insert(
                                crate::evaluation::evaluate::threshold_key(t.0, t.1),
                                v.label().into(),
                            );
                            format!("{} ({:+.1})", v.label(), a.mean - b.mean)
                        }
                        _ => "-".into(),
                    };
                    let _ = write!(row, " {cell} |");
                }
                let _ = writeln!(md, "{row}");
                verdicts.insert(format!("{}|{}", sc.name, o.name), vj.into());
            }
        }
        let _ = writeln!(md);
        return Some(verdicts.into());
    }
    None
}

/// One scene's section: every method in full, the fur-thickness and speed figures; its JSON.
fn write_scene(md: &mut String, sc: &Scene<'_>, cfg: &Config) -> Json {
    let mut sj = Map::new();
    let worst = write_method_table(md, sc, cfg, &mut sj);
    write_seams(md, &worst.seams);
    write_direction_parts(md, &worst.direction_parts);
    write_thickness_and_speed(md, sc, cfg, &mut sj);
    sj.insert("split".into(), sc.split.into());
    let _ = writeln!(
        md,
        "![F vs training time, {0}]({2}/f_vs_time_{1}.svg) ![F vs model size, {0}]({2}/f_vs_size_{1}.svg)\n",
        sc.name,
        safe(&sc.name),
        cfg.charts_link
    );
    sj.into()
}

/// Each row's worst part seam and worst part for the direction error: (method, where, mean
/// over seeds).
#[derive(Default)]
struct WorstParts {
    seams: Vec<(String, String, Stat)>,
    direction_parts: Vec<(String, String, Stat)>,
}

/// The scene's table: F-scores, direction and shape errors, PSNR/SSIM, time and size per method.
/// Returns each row's worst part seam and direction part, for [`write_seams`] and
/// [`write_direction_parts`].
fn write_method_table(
    md: &mut String,
    sc: &Scene<'_>,
    cfg: &Config,
    sj: &mut Map<String, Json>,
) -> WorstParts {
    let mut worst_parts = WorstParts::default();
    let _ = writeln!(
        md,
        "### {} ({} split, {} seeds)\n",
        sc.name,
        sc.split,
        sc.runs.len()
    );
    let _ = writeln!(
        md,
        "| method | F 1 cm | F 2 cm | F 3 cm | F 4 cm | direction error (°) | part seams (°) | curvature var. / GT | PSNR (dB) | SSIM | learning stage (s) | parameters |\n|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    let rows = cfg
        .methods
        .iter()
        .map(|m| (m.name.clone(), m.eval.clone(), m.learner.clone()))
        .chain(std::iter::once((
            "ceiling".to_string(),
            cfg.ceiling.clone(),
            None,
        )));
    for (name, eval, learner) in rows {
        let fs: Vec<Option<Stat>> = THRESHOLDS
            .iter()
            .map(|&t| stat(&values(sc, &f_key(&eval, t))))
            .collect();
        let dir = stat(&values(sc, &format!("{eval}.direction_error_deg")));
        let seam = stat(&values(sc, &format!("{eval}.{SEAM_EXCESS_KEY}")));
        let curv = stat(&values(
            sc,
            &format!("{eval}.local_curvature_variance_vs_gt"),
        ));
        let curv_at_points = stat(&values(sc, &format!("{eval}.gt_at_points.vs_gt")));
        let points = stat(&values(
            sc,
            &format!("{eval}.gt_at_points.points_per_strand"),
        ));
        let psnr = stat(&values(sc, &format!("{eval}.psnr")));
        let ssim = stat(&values(sc, &format!("{eval}.ssim")));
        let (secs, params) = match &learner {
            Some(l) => (
                stat(
                    &sc.runs
                        .iter()
                        .filter_map(|v| cost(v, l))
                        .collect::<Vec<_>>(),
                ),
                stat(&values(sc, &format!("{l}.optimised_parameters"))),
            ),
            None => (None, None),
        };
        let mut row = format!("| {name} |");
        for f in &fs {
            let _ = write!(row, " {} |", fmt_stat(*f, 1));
        }
        let _ = writeln!(
            md,
            "{row} {} | {} | {} | {} | {} | {} | {} |",
            fmt_stat(dir, 1),
            fmt_stat(seam, 1),
            fmt_stat(curv, 2),
            fmt_stat(psnr, 2),
            fmt_stat(ssim, 3),
            fmt_stat(secs, 1),
            fmt_stat(params, 0)
        );
        let mut mj = Map::new();
        for (t, f) in THRESHOLDS.iter().zip(&fs) {
            mj.insert(
                format!(
                    "signed_f_{}",
                    crate::evaluation::evaluate::threshold_key(t.0, t.1)
                ),
                stat_json(*f),
            );
        }
        mj.insert("direction_error_deg".into(), stat_json(dir));
        mj.insert("part_seam_excess_deg".into(), stat_json(seam));
        if let Some((parts, worst)) =
            worst_entry(sc, &format!("{eval}.{SEAM_BOUNDARY_PREFIX}"), "", None)
        {
            mj.insert(
                "worst_part_seam".into(),
                json!({"boundary": parts, "excess_deg": stat_json(Some(worst))}),
            );
            worst_parts.seams.push((name.clone(), parts, worst));
        }
        if let Some((part, worst)) = worst_entry(
            sc,
            &format!("{eval}.{DIRECTION_PART_PREFIX}"),
            ".deg",
            Some((".strands", MIN_DIRECTION_PART_STRANDS)),
        ) {
            mj.insert(
                "worst_direction_part".into(),
                json!({"part": part, "direction_error_deg": stat_json(Some(worst))}),
            );
            worst_parts
                .direction_parts
                .push((name.clone(), part, worst));
        }
        mj.insert("curvature_variance_vs_gt".into(), stat_json(curv));
        mj.insert(
            "gt_at_points_curvature_vs_gt".into(),
            stat_json(curv_at_points),
        );
        mj.insert("points_per_strand".into(), stat_json(points));
        mj.insert("psnr".into(), stat_json(psnr));
        mj.insert("ssim".into(), stat_json(ssim));
        mj.insert("training_seconds".into(), stat_json(secs));
        mj.insert("optimised_parameters".into(), stat_json(params));
        sj.insert(name, mj.into());
    }
    let _ = writeln!(md);
    worst_parts
}

/// The key of a method's mean seam excess at part boundaries, after its evaluation prefix.
const SEAM_EXCESS_KEY: &str = "seams.excess.mean_excess_deg";
/// Each boundary's seam excess is `EVAL.` this `A|B`.
const SEAM_BOUNDARY_PREFIX: &str = "seams.excess.by_boundary.";
/// Each part's direction error is `EVAL.` this `PART.deg`.
const DIRECTION_PART_PREFIX: &str = "direction_error_by_part.";

/// A part enters the worst direction part only in the seeds where at least this many strands
/// are rooted on it: the few strands whose roots fall on a bare part (an eye, a nose, a pad)
/// make a mean of a handful of angles, noise that would name the same bare part every time.
const MIN_DIRECTION_PART_STRANDS: f64 = 50.0;

/// Among the metrics `PREFIX NAME SUFFIX`, the name whose value is largest in the mean over
/// seeds, with that mean; with `count = (COUNT_SUFFIX, MIN)` a seed's value counts only where
/// `PREFIX NAME COUNT_SUFFIX` is at least `MIN`. Names present in fewer than half of the seeds
/// are left out (a part boundary or a part some seeds do not judge).
fn worst_entry(
    sc: &Scene<'_>,
    prefix: &str,
    suffix: &str,
    count: Option<(&str, f64)>,
) -> Option<(String, Stat)> {
    let mut by: BTreeMap<&str, Vec<f64>> = BTreeMap::new();
    for v in &sc.runs {
        for (k, x) in &v.metrics {
            let Some(name) = k.strip_prefix(prefix).and_then(|r| r.strip_suffix(suffix)) else {
                continue;
            };
            let counted = count.is_none_or(|(count_suffix, min)| {
                v.metrics
                    .get(&format!("{prefix}{name}{count_suffix}"))
                    .is_some_and(|&n| n >= min)
            });
            if counted {
                by.entry(name).or_default().push(*x);
            }
        }
    }
    by.into_iter()
        .filter(|(_, xs)| 2 * xs.len() >= sc.runs.len())
        .filter_map(|(name, xs)| stat(&xs).map(|s| (name.to_string(), s)))
        .max_by(|a, b| a.1.mean.total_cmp(&b.1.mean))
}

/// `method where mean ± sd; ...` for a report line, or `None` when no method has a figure.
fn worst_list(worst: &[(String, String, Stat)]) -> Option<String> {
    let items: Vec<String> = worst
        .iter()
        .map(|(name, at, s)| format!("{name} {at} {}", fmt_stat(Some(*s), 1)))
        .collect();
    (!items.is_empty()).then(|| items.join("; "))
}

/// One line naming each method's worst part boundary (evaluation::seams).
fn write_seams(md: &mut String, worst_seams: &[(String, String, Stat)]) {
    let Some(worst) = worst_list(worst_seams) else {
        return;
    };
    let _ = writeln!(
        md,
        "Part seams (evaluation::seams): around each root near a part boundary, the angle \
         between the mean growth directions of its neighbours (in-plane, within the evaluation's `seam_radius_cm`, 3 cm by default) on either \
         side, minus the same for the GT there (0: the boundary turns the fur as much as the GT's \
         does; positive: a seam). The column is the mean over boundaries; here the worst \
         boundary, mean over seeds (°): {worst}.\n"
    );
}

/// One line naming each method's part with the largest direction error (evaluation::evaluate,
/// `direction_error_by_part`).
fn write_direction_parts(md: &mut String, worst: &[(String, String, Stat)]) {
    let Some(worst) = worst_list(worst) else {
        return;
    };
    let _ = writeln!(
        md,
        "Direction error by part (evaluate's `direction_error_by_part`: the in-plane direction \
         error of the strands rooted on each part of the GT skin, parts with at least {} strands \
         in a seed): each method's worst part, mean over seeds (°): {worst}.\n",
        MIN_DIRECTION_PART_STRANDS,
    );
}

/// A learner's final F against its untrained start: the protocol's verdict (`None` without
/// both figures) and the report's text, `FINAL against START (verdict)`.
fn against_start(fin: Option<Stat>, start: Option<Stat>) -> (Option<&'static str>, String) {
    let v = match (fin, start) {
        (Some(f), Some(s)) => Some(verdict(&f, &s).label()),
        _ => None,
    };
    let text = format!(
        "{} against {} ({})",
        fmt_stat(fin, 1),
        fmt_stat(start, 1),
        v.unwrap_or("-")
    );
    (v, text)
}

/// Fur thickness, lengths and preprocessing (shared by every method of the scene), and the
/// speed-up to dense's final F.
fn write_thickness_and_speed(
    md: &mut String,
    sc: &Scene<'_>,
    cfg: &Config,
    sj: &mut Map<String, Json>,
) {
    // Fur thickness and preprocessing, shared by every method of the scene.
    let g = |k: &str| stat(&values(sc, k));
    let outer = g("defur.outer_to_skin_mean_frac");
    let root = g("defur.root_to_skin_mean_frac");
    let base = g("defur.baseline_to_skin_mean_frac");
    let corr = g("frosting.gt_vertex.pearson");
    let width_px = g("frosting.resolution.median_width_px");
    let coat_px = g("frosting.resolution.gt_median_thickness_px");
    let inside = g("defur.root_inside_body_frac");
    let len_err = g("lengths.length_error_mean_pct");
    let len_err_trained = cfg
        .methods
        .first()
        .and_then(|m| m.learner.as_deref())
        .map(|learner| {
            stat(
                &sc.runs
                    .iter()
                    .filter_map(|v| trained_length_error(v, learner))
                    .collect::<Vec<_>>(),
            )
        })
        .unwrap_or(None);
    let len_err_v2 = g(&format!("{}.length_error_mean_pct", cfg.v2_lengths));
    let pre = stat(
        &sc.runs
            .iter()
            .filter_map(|v| preprocessing_seconds(v, cfg))
            .collect::<Vec<_>>(),
    );
    let mem = stat(
        &sc.runs
            .iter()
            .filter_map(|v| peak_rss(v))
            .map(|b| b / (1u64 << 20) as f64)
            .collect::<Vec<_>>(),
    );
    let _ = writeln!(
        md,
        "Fur thickness (fractions of the GT fur thickness, mean distance to the GT skin): M_outer {}, \
         M_root {} (FurE defurring; fraction of its fur surface inside the GT body {}), NeuralFur baseline {}; Frosting widths vs true outer-to-skin \
         distance, per-vertex Pearson {}, median width {} px of the training views (the GT's fur, median \
         over parts: {} px); mean per-part length error {} % (after the first method's learned \
         part scales: {} %; V2, species reference lengths: {} %). Preprocessing {} s; peak \
         memory of a stage {} MiB.\n",
        fmt_stat(outer, 2),
        fmt_stat(root, 2),
        fmt_stat(inside, 3),
        fmt_stat(base, 2),
        fmt_stat(corr, 2),
        fmt_stat(width_px, 2),
        fmt_stat(coat_px, 2),
        fmt_stat(len_err, 0),
        fmt_stat(len_err_trained, 0),
        fmt_stat(len_err_v2, 0),
        fmt_stat(pre, 1),
        fmt_stat(mem, 0),
    );
    let sp = g(&format!("{}.speedup_to_dense_final_fscore", cfg.speedup));
    let lo = values(sc, &format!("{}.speedup_low", cfg.speedup))
        .into_iter()
        .reduce(f64::min);
    let hi = values(sc, &format!("{}.speedup_high", cfg.speedup))
        .into_iter()
        .reduce(f64::max);
    // Seeds whose flag under `key` is set.
    let count_key = |key: &str| values(sc, key).iter().filter(|&&x| x > 0.0).count();
    let count = |k: &str| count_key(&format!("{}.{k}", cfg.speedup));
    let reached = count("codec_reached_dense_final");
    let at_start = count("codec_reached_dense_final_at_start");
    let dense_flat = count("dense_start_reaches_final");
    let dense_caught_up = count("dense_reached_codec_final");
    let start_codec = g(&format!("{}.codec_start_fscore_3cm_30deg", cfg.speedup));
    let start_dense = g(&format!("{}.dense_start_fscore_3cm_30deg", cfg.speedup));
    let final_codec = g(&format!("{}.codec_final_fscore_3cm_30deg", cfg.speedup));
    let final_dense = g(&format!("{}.dense_final_fscore_3cm_30deg", cfg.speedup));
    // Issue 15's "both >= their own untrained start", by the protocol's rule.
    let (codec_vs_start, codec_vs_start_md) = against_start(final_codec, start_codec);
    let (dense_vs_start, dense_vs_start_md) = against_start(final_dense, start_dense);
    // The strict threshold's speed-up (speed_accuracy's `strict`), where 3 cm saturates.
    let strict = |k: &str| format!("{}.strict.{k}", cfg.speedup);
    let sp_strict = g(&strict("speedup_to_dense_final_fscore"));
    let strict_seeds = values(sc, &strict("dense_final_fscore")).len();
    let strict_line = if strict_seeds == 0 {
        String::new()
    } else {
        let learner = |l: &str| {
            against_start(
                g(&strict(&format!("{l}_final_fscore"))),
                g(&strict(&format!("{l}_start_fscore"))),
            )
            .1
        };
        format!(
            " At the strict 1 cm / 10° (signed, the same snapshots): speed-up {} (the codec reached \
             dense's final F in {} of {strict_seeds} seeds, {} of them at its untrained start; \
             undefined in {} seeds where dense's untrained start already reaches it); final against \
             start: codec {}, dense {}.",
            fmt_stat(sp_strict, 1),
            count_key(&strict("codec_reached_dense_final")),
            count_key(&strict("codec_reached_dense_final_at_start")),
            count_key(&strict("dense_start_reaches_final")),
            learner("codec"),
            learner("dense"),
        )
    };
    let _ = writeln!(
        md,
        "Speed-up of the first method to dense's final F (3 cm, unsigned, from the snapshots): {} \
         (the codec reached dense's final F in {reached} of {} seeds, {at_start} of them at its \
         untrained start, where its time is its colour fit's; undefined in {dense_flat} seeds \
         where dense's own untrained start already reaches its final F; snapshot bracket {}–{}). \
         Dense reached the codec's final F in {dense_caught_up} of {} seeds. Final against \
         untrained start, F at 3 cm unsigned (the snapshots' scoring): codec {codec_vs_start_md}, \
         dense {dense_vs_start_md}.{strict_line}\n",
        fmt_stat(sp, 1),
        sc.runs.len(),
        lo.map_or("-".into(), |x| format!("{x:.1}")),
        hi.map_or("-".into(), |x| format!("{x:.1}")),
        sc.runs.len(),
    );
    sj.insert(
        "preprocessing".into(),
        json!({
            "outer_to_skin_frac": stat_json(outer),
            "root_to_skin_frac": stat_json(root),
            "root_inside_body_frac": stat_json(inside),
            "baseline_to_skin_frac": stat_json(base),
            "frosting_vertex_pearson": stat_json(corr),
            "length_error_mean_pct": stat_json(len_err),
            "length_error_trained_mean_pct": stat_json(len_err_trained),
            "length_error_v2_mean_pct": stat_json(len_err_v2),
            "seconds": stat_json(pre),
            "peak_rss_mib": stat_json(mem),
        }),
    );
    sj.insert(
        "speedup".into(),
        json!({"ratio": stat_json(sp), "reached": reached, "reached_at_start": at_start, "dense_start_reaches_final": dense_flat, "dense_reached_codec_final": dense_caught_up, "seeds": sc.runs.len(), "low": lo, "high": hi, "codec_start": stat_json(start_codec), "dense_start": stat_json(start_dense), "codec_final": stat_json(final_codec), "dense_final": stat_json(final_dense), "codec_against_start": codec_vs_start, "dense_against_start": dense_vs_start, "strict_ratio": stat_json(sp_strict)}),
    );
}

/// One CSV row per run and method (and the ceiling).
fn runs_csv(scenes: &[Scene<'_>], cfg: &Config) -> String {
    let mut csv = String::from("scene,split,seed,variant,status,method");
    for t in THRESHOLDS {
        let _ = write!(
            csv,
            ",signed_f_{}",
            crate::evaluation::evaluate::threshold_key(t.0, t.1)
        );
    }
    csv.push_str(
        ",direction_error_deg,part_seam_excess_deg,curvature_vs_gt,psnr,ssim,training_seconds,optimised_parameters\n",
    );
    let num = |x: Option<f64>| x.map_or(String::new(), |x| format!("{x}"));
    for sc in scenes {
        for v in &sc.runs {
            let seed = setting(v, &cfg.seed_setting).map(label).unwrap_or_default();
            let status = match v.status {
                crate::evaluation::stability::EngineStatus::Ok => "ok",
                crate::evaluation::stability::EngineStatus::Degraded => "degraded",
                crate::evaluation::stability::EngineStatus::Failed => "failed",
            };
            let all = cfg
                .methods
                .iter()
                .map(|m| (m.name.as_str(), m.eval.as_str(), m.learner.as_deref()))
                .chain(std::iter::once(("ceiling", cfg.ceiling.as_str(), None)));
            for (name, eval, learner) in all {
                let _ = write!(
                    csv,
                    "{},{},{},{},{status},{}",
                    sc.name, sc.split, seed, v.name, name
                );
                for t in THRESHOLDS {
                    let _ = write!(csv, ",{}", num(v.metrics.get(&f_key(eval, t)).copied()));
                }
                let m = |k: &str| num(v.metrics.get(&format!("{eval}.{k}")).copied());
                let _ = writeln!(
                    csv,
                    ",{},{},{},{},{},{},{}",
                    m("direction_error_deg"),
                    m(SEAM_EXCESS_KEY),
                    m("local_curvature_variance_vs_gt"),
                    m("psnr"),
                    m("ssim"),
                    num(learner.and_then(|l| cost(v, l))),
                    num(learner.and_then(|l| v
                        .metrics
                        .get(&format!("{l}.optimised_parameters"))
                        .copied())),
                );
            }
        }
    }
    csv
}

fn list_or_none(v: &[String]) -> String {
    if v.is_empty() {
        "(none)".into()
    } else {
        v.join(", ")
    }
}

/// A file-name-safe form of a scene name.
fn safe(s: &str) -> String {
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

const PALETTE: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(255, 127, 14),
    RGBColor(127, 127, 127),
];

/// A scatter chart, one colour per series, x on a log axis; a series' points are its seeds.
/// With `chosen`, the first series' points are ringed and the text is written in the plot's
/// lower left: the size the first method chose for itself.
fn draw_scatter<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    x_desc: &str,
    series: &[(String, Vec<(f64, f64)>)],
    chosen: Option<&str>,
) -> Result<(), String> {
    root.fill(&WHITE).map_err(chart_err)?;
    let pts: Vec<(f64, f64)> = series.iter().flat_map(|(_, p)| p.iter().copied()).collect();
    let xmin = pts.iter().map(|p| p.0).fold(f64::MAX, f64::min).max(1e-3);
    let xmax = pts.iter().map(|p| p.0).fold(0.0, f64::max).max(xmin * 10.0);
    let ymax =
        ((pts.iter().map(|p| p.1).fold(0.0, f64::max) / 10.0).ceil() * 10.0).clamp(10.0, 100.0);
    let mut chart = ChartBuilder::on(root)
        .caption(title, ("sans-serif", 20))
        .margin(14)
        .x_label_area_size(44)
        .y_label_area_size(56)
        .build_cartesian_2d((xmin * 0.7..xmax * 1.4).log_scale(), 0.0..ymax)
        .map_err(chart_err)?;
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .y_desc("signed F-score at 3 cm / 30\u{b0} (%)")
        .x_label_formatter(&|x| fmt_num(*x))
        .y_label_formatter(&|y| format!("{y:.0}"))
        .label_style(("sans-serif", 14))
        .axis_desc_style(("sans-serif", 15))
        .draw()
        .map_err(chart_err)?;
    for (i, (name, p)) in series.iter().enumerate() {
        let c = PALETTE[i % PALETTE.len()];
        chart
            .draw_series(p.iter().map(|&q| Circle::new(q, 5, c.filled())))
            .map_err(chart_err)?
            .label(name.clone())
            .legend(move |(x, y)| Circle::new((x + 10, y), 5, c.filled()));
    }
    if let (Some(text), Some((_, first))) = (chosen, series.first()) {
        let ring = PALETTE[0].stroke_width(2);
        chart
            .draw_series(first.iter().map(|&q| Circle::new(q, 11, ring)))
            .map_err(chart_err)?;
        // Bottom left, clear of the points (F near the top) and of the legend (bottom right).
        let (_, h) = root.dim_in_pixel();
        root.draw(&Text::new(
            text.to_string(),
            (76, h as i32 - 80),
            ("sans-serif", 14).into_font().color(&PALETTE[0]),
        ))
        .map_err(chart_err)?;
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 14))
        .position(SeriesLabelPosition::LowerRight)
        .draw()
        .map_err(chart_err)?;
    root.present().map_err(chart_err)
}

/// The size a learner chose from the views, over a scene's runs: strand count (mean over
/// seeds), points per strand and, where the record has the `basis` stage's rank, the basis
/// rank (`roots_per_pixel`, `strand_basis`'s automatic points and rank), and the components
/// the codec trains (`min_component_px`, mean over seeds). None without the learner's strand
/// count.
fn chosen_size(runs: &[&VariantRecord], learner: &str, method: &str) -> Option<String> {
    let mean = |key: String| -> Option<f64> {
        let v: Vec<f64> = runs
            .iter()
            .filter_map(|r| r.metrics.get(&key).copied())
            .collect();
        (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
    };
    let strands = mean(format!("{learner}.strands"))?;
    let mut text = format!(
        "ringed: {method} as chosen from the views, {} strands",
        fmt_num(strands.round())
    );
    if let Some(l) = mean(format!("{learner}.points_per_strand")) {
        let _ = write!(text, " x {l:.0} points");
    }
    if let Some(k) = mean("basis.k".to_string()) {
        let _ = write!(text, ", basis rank {k:.0}");
    }
    if let Some(t) = mean(format!("{learner}.components.trained")) {
        let digits = if t.fract() == 0.0 { 0 } else { 1 };
        let _ = write!(text, ", {t:.digits$} components trained");
    }
    Some(text)
}

/// Per scene: F (3 cm, signed) against training seconds and against optimised parameters.
fn write_charts(rec: &SweepRecord, cfg: &Config, dir: &Path) -> Result<(), StageError> {
    std::fs::create_dir_all(dir).map_err(|e| StageError::io(dir, e))?;
    let t3 = THRESHOLDS[2];
    for sc in scenes(rec, cfg) {
        let mut time = Vec::new();
        let mut size = Vec::new();
        for m in &cfg.methods {
            let Some(l) = &m.learner else { continue };
            let f = |v: &VariantRecord| v.metrics.get(&f_key(&m.eval, t3)).copied();
            time.push((
                m.name.clone(),
                sc.runs
                    .iter()
                    .filter_map(|v| Some((cost(v, l)?, f(v)?)))
                    .collect::<Vec<_>>(),
            ));
            size.push((
                m.name.clone(),
                sc.runs
                    .iter()
                    .filter_map(|v| {
                        Some((*v.metrics.get(&format!("{l}.optimised_parameters"))?, f(v)?))
                    })
                    .collect::<Vec<_>>(),
            ));
        }
        let chosen = cfg
            .methods
            .first()
            .and_then(|m| chosen_size(&sc.runs, m.learner.as_deref()?, &m.name));
        for (stem, title, xdesc, series, chosen) in [
            (
                "f_vs_time",
                format!("{}: F vs strand-training time", sc.name),
                "learning stage compute time (s, log)",
                &time,
                None,
            ),
            (
                "f_vs_size",
                format!("{}: F vs model size", sc.name),
                "optimised parameters (log)",
                &size,
                chosen.as_deref(),
            ),
        ] {
            if series.iter().all(|(_, p)| p.is_empty()) {
                continue;
            }
            let name = format!("{stem}_{}", safe(&sc.name));
            let size = (820, 600);
            write_png_chart(&dir.join(format!("{name}.png")), size, |r| {
                draw_scatter(r, &title, xdesc, series, chosen)
            })?;
            write_svg_chart(&dir.join(format!("{name}.svg")), size, |r| {
                draw_scatter(r, &title, xdesc, series, chosen)
            })?;
        }
    }
    Ok(())
}

fure_stage_api::stage_params! {
    /// The `benchmark_report` stage's parameters.
    pub struct BenchmarkReportParams {
        /// dev split: the only scenes defaults may be tuned on
        dev: Vec<String> = str_list(&["tiger", "fox"]),
        /// test split: reported, never used to choose
        test: Vec<String> = str_list(&["panda", "cat", "bison", "wolf"]),
        /// the swept STAGE.PARAM naming the scene (a linked key containing it counts)
        scene_setting: String = string("scene.preset"),
        /// the swept STAGE.PARAM naming the seed (a linked key containing it counts)
        seed_setting: String = string("scene.seed"),
        /// NAME=EVAL_STAGE[:LEARNER_STAGE]; the first is compared with every other
        methods: Vec<String> = str_list(&[
            "FurE codec=evaluate:codec",
            "dense=evaluate_dense:dense",
            "fixed length=evaluate_fixed:codec_fixed",
            "shape prior=evaluate_prior:codec_prior",
        ]),
        /// evaluation of the regrown GT against the GT
        ceiling: String = string("evaluate_ceiling"),
        /// stages whose compute seconds add up to the preprocessing time
        preprocessing: Vec<String> = str_list(&[
            "outer",
            "parts",
            "frosting",
            "lengths",
            "defur",
            "roots",
            "basis",
            "orientation",
        ]),
        /// the speed_accuracy stage's metric prefix
        speedup: String = string("speed_accuracy"),
        /// the lengths stage with species reference lengths (V2), reported beside V1 when present
        v2_lengths: String = string("lengths_v2"),
        /// where the published charts are, relative to the published results.md
        charts_link: String = string("benchmark"),
        /// targets table: methods (by name) the first must match or beat at 2, 3 and 4 cm
        target_against: Vec<String> = str_list(&["dense", "fixed length"]),
        /// targets table: the least speed-up to dense's final 3 cm F
        target_speedup: f64 = float(10.0).range(0.0, 1e6),
        /// targets table: the largest mean in-plane direction error (degrees)
        target_direction_deg: f64 = float(20.0).range(0.0, 180.0),
        /// targets table: curvature variance over the GT's within this factor either way
        target_curvature_ratio: f64 = float(2.0).range(1.0, 1e6),
    }
}

fn config(p: &Params) -> Result<Config, StageError> {
    let p = BenchmarkReportParams::from_params(p)?;
    let methods = p
        .methods
        .iter()
        .map(|s| parse_method(s))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| StageError::param("methods", e))?;
    if methods.is_empty() {
        return Err(StageError::param(
            "methods",
            "expected at least one NAME=EVAL[:LEARNER]",
        ));
    }
    if let Some(unknown) = p
        .target_against
        .iter()
        .find(|n| !methods.iter().skip(1).any(|m| &&m.name == n))
    {
        let names: Vec<&str> = methods.iter().skip(1).map(|m| m.name.as_str()).collect();
        return Err(StageError::param(
            "target_against",
            format!(
                "`{unknown}` is not a method the first is compared with (expected one of: {})",
                names.join(", ")
            ),
        ));
    }
    if let Some(s) = p.dev.iter().find(|s| p.test.contains(s)) {
        return Err(StageError::param(
            "test",
            format!("scene `{s}` is in both splits"),
        ));
    }
    Ok(Config {
        dev: p.dev,
        test: p.test,
        scene_setting: p.scene_setting,
        seed_setting: p.seed_setting,
        methods,
        ceiling: p.ceiling,
        preprocessing: p.preprocessing,
        speedup: p.speedup,
        v2_lengths: p.v2_lengths,
        charts_link: p.charts_link,
        goals: Goals {
            against: p.target_against,
            speedup: p.target_speedup,
            direction_deg: p.target_direction_deg,
            curvature_ratio: p.target_curvature_ratio,
        },
    })
}

/// Stage `benchmark_report`.
pub struct BenchmarkReportStage;

impl Stage for BenchmarkReportStage {
    fn kind(&self) -> &'static str {
        "benchmark_report"
    }
    fn version(&self) -> u32 {
        // 14: the size chart names the components the codec trains.
        // 15: the other work beside the stages (`costs.S.other_load`).
        // 16: each method's worst part for the direction error.
        // 17: only parts with enough strands.
        // 18: the targets tables.
        18
    }
    fn doc(&self) -> &'static str {
        "Benchmark suite report from the engine's sweep record: per split and scene, signed F-scores \
         (1/2/3/4 cm) of every method as mean ± sd over seeds beside the scene's ceiling, won / lost / \
         tie verdicts by the seed-spread rule, direction and shape errors, PSNR/SSIM, fur-thickness \
         figures, preprocessing and training time, peak memory, the speed-up; results.md, charts (F vs \
         training time, F vs model size), a CSV of every run and metrics.json."
    }
    fn params(&self) -> Vec<ParamSpec> {
        BenchmarkReportParams::specs()
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
            PortSpec::file(
                "results",
                "md",
                "the results document (publish it to docs/results.md)",
            ),
            PortSpec::dir(
                "charts",
                "per scene: f_vs_time_<scene> and f_vs_size_<scene>, PNG and SVG",
            ),
            PortSpec::file(
                "headline",
                "md",
                "the headline tables alone (publish it into the README's section)",
            ),
            PortSpec::file("runs", "csv", "one row per run and method"),
            PortSpec::file(
                "metrics",
                "json",
                "per scene and method: mean, sd, n of every figure; verdicts",
            ),
        ]
    }
    fn validate(&self, params: &Params) -> Result<(), StageError> {
        config(params).map(|_| ())
    }
    fn run(&self, ctx: &StageContext<'_>) -> Result<(), StageError> {
        let cfg = config(ctx.params)?;
        let path = ctx.input("sweep")?;
        let rec = SweepRecord::read(path)?;
        let report = report(&rec, &cfg);
        write_charts(&rec, &cfg, ctx.output("charts")?)?;
        for (port, text) in [
            ("results", &report.results),
            ("headline", &report.headline),
            ("runs", &report.runs),
        ] {
            let out = ctx.output(port)?;
            std::fs::write(out, text).map_err(|e| StageError::io(out, e))?;
        }
        crate::formats::json::write_json(ctx.output("metrics")?, &report.metrics)?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(runs: &[(&str, u64, f64, f64)]) -> SweepRecord {
        record_on(runs, &|_| 2)
    }

    /// [`record`] with variant `i`'s codec run on `threads(i)` threads.
    fn record_on(runs: &[(&str, u64, f64, f64)], threads: &dyn Fn(usize) -> u64) -> SweepRecord {
        record_costing(
            runs,
            &|i| json!({"seconds": 10.0, "peak_rss_bytes": 1048576, "threads": threads(i)}),
        )
    }

    /// [`record`] with variant `i`'s codec cost `codec_cost(i)`.
    fn record_costing(
        runs: &[(&str, u64, f64, f64)],
        codec_cost: &dyn Fn(usize) -> Json,
    ) -> SweepRecord {
        // (scene, seed, codec F3, dense F3)
        let variants: Vec<Json> = runs
            .iter()
            .enumerate()
            .map(|(i, (scene, seed, fc, fd))| {
                json!({
                    "index": i, "name": format!("b@v{i}"), "status": "ok",
                    "settings": {"scene.preset,defur_baseline.species": scene, "scene.seed,codec.seed": seed},
                    "metrics": {
                        "evaluate": {"prf_signed": {"3cm_30deg": {"fscore": fc}}},
                        "evaluate_dense": {"prf_signed": {"3cm_30deg": {"fscore": fd}}},
                        "codec": {"optimised_parameters": 1000, "strands": 40000 + 2000 * i, "points_per_strand": 8, "components": {"trained": 3 + i % 2}},
                        "basis": {"k": 14},
                    },
                    "costs": {"codec": codec_cost(i), "frosting": {"seconds": 5.0, "peak_rss_bytes": 2097152}},
                })
            })
            .collect();
        let root =
            json!({"pipeline": "benchmark", "crossed": {}, "each": {}, "variants": variants});
        SweepRecord::from_json(Path::new("sweep.json"), &root).unwrap()
    }

    fn cfg() -> Config {
        Config {
            dev: vec!["tiger".into()],
            test: vec!["panda".into()],
            scene_setting: "scene.preset".into(),
            seed_setting: "scene.seed".into(),
            methods: vec![
                parse_method("FurE=evaluate:codec").unwrap(),
                parse_method("dense=evaluate_dense:dense").unwrap(),
            ],
            ceiling: "evaluate_ceiling".into(),
            preprocessing: vec!["frosting".into()],
            speedup: "speed_accuracy".into(),
            v2_lengths: "lengths_v2".into(),
            charts_link: "benchmark".into(),
            goals: Goals {
                against: vec!["dense".into()],
                speedup: 10.0,
                direction_deg: 20.0,
                curvature_ratio: 2.0,
            },
        }
    }

    #[test]
    fn the_report_says_when_stage_seconds_mix_thread_counts() {
        let runs = [("tiger", 0, 60.0, 50.0), ("tiger", 1, 62.0, 51.0)];
        let one = report(&record(&runs), &cfg());
        assert!(
            one.results.contains("runs on 2 thread(s) each"),
            "{}",
            one.results
        );
        assert!(!one.results.contains("mix thread counts"));
        assert_eq!(one.metrics["stage_threads"], json!([2]));
        let mixed = report(&record_on(&runs, &|i| 1 + i as u64), &cfg());
        assert!(mixed
            .results
            .contains("**Stage seconds mix thread counts** (1, 2 threads)"));
        assert_eq!(mixed.metrics["stage_threads"], json!([1, 2]));
    }

    #[test]
    fn the_report_says_when_other_work_ran_beside_the_stages() {
        let runs = [("tiger", 0, 60.0, 50.0), ("tiger", 1, 62.0, 51.0)];
        let cost = |load: f64| json!({"seconds": 10.0, "peak_rss_bytes": 1, "threads": 2, "other_load": load});
        // Entries from before the figure was recorded: nothing is said.
        let old = report(&record(&runs), &cfg());
        assert!(!old.results.contains("other work"), "{}", old.results);
        assert!(old.metrics.get("stage_other_load_max").is_none());
        // A quiet machine: the largest figure, and which entries did not record one.
        let quiet = report(&record_costing(&runs, &|i| cost(0.1 * i as f64)), &cfg());
        assert!(
            quiet.results.contains(
                "Other work on the machine used at most 0.10 cores while a stage ran \
                 (2 of 4 stage runs not measured"
            ),
            "{}",
            quiet.results
        );
        assert!(!quiet.results.contains("beside other work"));
        assert_eq!(quiet.metrics["stage_other_load_max"], json!(0.1));
        // One codec run shared the machine: flagged, naming the worst run.
        let busy = report(&record_costing(&runs, &|i| cost([0.0, 1.9][i])), &cfg());
        assert!(
            busy.results.contains(
                "**Some stage seconds were measured beside other work**: in 1 of 2 measured \
                 stage runs, other processes used more than 0.5 cores on average (the \
                 worst: `codec` of b@v1, 1.90 cores)"
            ),
            "{}",
            busy.results
        );
    }

    #[test]
    fn the_trained_length_error_carries_each_part_through_its_learned_scale() {
        let v = |scales: Json| {
            let root = json!({"pipeline": "b", "crossed": {}, "each": {}, "variants": [{
                "index": 0, "name": "b@v0", "status": "ok", "settings": {},
                "metrics": {
                    "lengths": {"length_error_signed_pct": {"torso": 100.0, "ears": -50.0}},
                    "codec": scales,
                },
                "costs": {},
            }]});
            SweepRecord::from_json(Path::new("sweep.json"), &root).unwrap()
        };
        // Torso read twice too long and halved, ears read half too short and doubled: exact.
        let rec = v(json!({"part_length_scale": {"torso": 0.5, "ears": 2.0}}));
        assert_eq!(trained_length_error(&rec.variants[0], "codec"), Some(0.0));
        // Left as read: the mean of 100 % and 50 %.
        let rec = v(json!({"part_length_scale": {"torso": 1.0, "ears": 1.0}}));
        assert_eq!(trained_length_error(&rec.variants[0], "codec"), Some(75.0));
        // No learned scales: no figure, not the untrained one.
        let rec = v(json!({"strands": 10}));
        assert_eq!(trained_length_error(&rec.variants[0], "codec"), None);
    }

    #[test]
    fn verdicts_follow_the_seed_spread() {
        let s = |m: f64, sd: Option<f64>| Stat { mean: m, sd, n: 3 };
        assert_eq!(
            verdict(&s(50.0, Some(1.0)), &s(48.5, Some(1.0))),
            Verdict::Won
        );
        assert_eq!(
            verdict(&s(50.0, Some(2.0)), &s(48.5, Some(1.0))),
            Verdict::Tie
        );
        assert_eq!(
            verdict(&s(40.0, Some(2.0)), &s(48.5, Some(1.0))),
            Verdict::Lost
        );
        assert_eq!(
            verdict(&s(90.0, None), &s(10.0, Some(1.0))),
            Verdict::Undecided
        );
        let st = stat(&[1.0, 2.0, 3.0, f64::NAN]).unwrap();
        assert_eq!((st.mean, st.n), (2.0, 3));
        assert!((st.sd.unwrap() - 1.0).abs() < 1e-12);
        assert!(stat(&[]).is_none());
    }

    #[test]
    fn report_groups_by_linked_scene_key_and_splits() {
        let rec = record(&[
            ("tiger", 0, 60.0, 50.0),
            ("tiger", 1, 62.0, 51.0),
            ("tiger", 2, 61.0, 52.0),
            ("panda", 0, 40.0, 45.0),
            ("panda", 1, 41.0, 47.0),
            ("wolf", 0, 30.0, 30.0),
        ]);
        let Report {
            results: md,
            headline,
            runs: csv,
            metrics: m,
        } = report(&rec, &cfg());
        // Tiger: codec 61 +- 1 vs dense 51 +- 1: won; panda: lost; wolf: one seed, undecided.
        assert_eq!(m["verdicts"]["tiger|dense"]["3cm_30deg"], "won", "{m}");
        assert_eq!(m["verdicts"]["panda|dense"]["3cm_30deg"], "lost", "{m}");
        assert_eq!(
            m["verdicts"]["wolf|dense"]["3cm_30deg"], "undecided (1 seed)",
            "{m}"
        );
        assert_eq!(m["scenes"]["tiger"]["split"], "dev");
        assert_eq!(m["scenes"]["wolf"]["split"], "unsplit");
        let f = &m["scenes"]["tiger"]["FurE"]["signed_f_3cm_30deg"];
        assert_eq!(f["mean"], 61.0);
        assert_eq!(f["n"], 3);
        // Missing figures are missing, not zero.
        assert!(m["scenes"]["tiger"]["FurE"]["psnr"].is_null());
        assert!(
            md.contains("| tiger | 3 | 61.0 ± 1.0 | 51.0 ± 1.0 | - |"),
            "{md}"
        );
        assert!(md.find("Headline, dev").unwrap() < md.find("Headline, test").unwrap());
        assert_eq!(
            m["scenes"]["tiger"]["preprocessing"]["seconds"]["mean"],
            5.0
        );
        assert_eq!(
            m["scenes"]["tiger"]["preprocessing"]["peak_rss_mib"]["mean"],
            2.0
        );
        // One row per run and method (+ ceiling).
        assert_eq!(csv.lines().count(), 1 + 6 * 3);
        // The headline is the results' headline tables alone, under a provenance mark.
        assert!(headline.starts_with(PROVENANCE_MARK), "{headline}");
        assert!(headline.contains("| tiger | 3 | 61.0 ± 1.0 | 51.0 ± 1.0 | - |"));
        assert!(headline.contains("### Headline, test") && !headline.contains("Comparisons"));
    }

    #[test]
    fn the_worst_part_seam_is_the_worst_in_the_mean_over_seeds() {
        let mut rec = record(&[("tiger", 0, 60.0, 50.0), ("tiger", 1, 62.0, 51.0)]);
        // Seed 0's worst boundary is ears|neck, but over both seeds hind_legs|torso is.
        for (v, (ears, legs)) in rec.variants.iter_mut().zip([(12.0, 10.0), (2.0, 9.0)]) {
            let by = "evaluate.seams.excess.by_boundary.";
            v.metrics.insert(format!("{by}ears|neck"), ears);
            v.metrics.insert(format!("{by}hind_legs|torso"), legs);
            v.metrics
                .insert(format!("evaluate.{SEAM_EXCESS_KEY}"), (ears + legs) / 2.0);
        }
        let Report {
            results: md,
            metrics: m,
            ..
        } = report(&rec, &cfg());
        let worst = &m["scenes"]["tiger"]["FurE"]["worst_part_seam"];
        assert_eq!(worst["boundary"], "hind_legs|torso", "{m}");
        assert_eq!(worst["excess_deg"]["mean"], 9.5);
        assert_eq!(
            m["scenes"]["tiger"]["FurE"]["part_seam_excess_deg"]["mean"],
            8.25
        );
        assert!(md.contains("FurE hind_legs|torso 9.5 ± 0.7"), "{md}");
        // Dense has no seam figures: its column is missing, not zero, and the line skips it.
        assert!(m["scenes"]["tiger"]["dense"]["part_seam_excess_deg"].is_null());
        assert!(!md.contains("dense hind_legs"));
    }

    #[test]
    fn the_worst_direction_part_is_the_worst_in_the_mean_over_seeds() {
        let mut rec = record(&[
            ("tiger", 0, 60.0, 50.0),
            ("tiger", 1, 62.0, 51.0),
            ("tiger", 2, 61.0, 50.0),
        ]);
        // Seed 0's worst part is the head, but over the seeds the legs are; the tail is judged
        // in one seed of three only, so its 90 degrees do not count, and the nose has too few
        // strands in every seed.
        for (i, (v, (head, legs))) in rec
            .variants
            .iter_mut()
            .zip([(30.0, 20.0), (5.0, 22.0), (7.0, 24.0)])
            .enumerate()
        {
            let by = format!("evaluate.{DIRECTION_PART_PREFIX}");
            v.metrics.insert(format!("{by}head.deg"), head);
            v.metrics.insert(format!("{by}head.strands"), 100.0);
            v.metrics.insert(format!("{by}legs.deg"), legs);
            v.metrics.insert(format!("{by}legs.strands"), 400.0);
            if i == 0 {
                v.metrics.insert(format!("{by}tail.deg"), 90.0);
                v.metrics.insert(format!("{by}tail.strands"), 300.0);
            }
            // A bare part a few strands fall on: never named, however large its angle.
            v.metrics.insert(format!("{by}nose.deg"), 120.0);
            v.metrics.insert(format!("{by}nose.strands"), 3.0);
        }
        let Report {
            results: md,
            metrics: m,
            ..
        } = report(&rec, &cfg());
        let worst = &m["scenes"]["tiger"]["FurE"]["worst_direction_part"];
        assert_eq!(worst["part"], "legs", "{m}");
        assert_eq!(worst["direction_error_deg"]["mean"], 22.0);
        assert!(md.contains("Direction error by part"), "{md}");
        assert!(md.contains("FurE legs 22.0 ± 2.0"), "{md}");
        assert!(m["scenes"]["tiger"]["dense"]["worst_direction_part"].is_null());
    }

    #[test]
    fn each_learner_is_judged_against_its_untrained_start() {
        let mut rec = record(&[("tiger", 0, 60.0, 50.0), ("tiger", 1, 62.0, 51.0)]);
        // The codec ends where it started (a tie); dense ends below its start by more than
        // the spread (lost).
        for (v, (cs, cf, ds, df)) in rec
            .variants
            .iter_mut()
            .zip([(90.0, 90.5, 95.0, 90.0), (91.0, 90.5, 95.5, 90.5)])
        {
            for (k, x) in [
                ("codec_start", cs),
                ("codec_final", cf),
                ("dense_start", ds),
                ("dense_final", df),
            ] {
                v.metrics
                    .insert(format!("speed_accuracy.{k}_fscore_3cm_30deg"), x);
            }
            // At the strict threshold the codec starts above dense's final, at 2 s against 40.
            for (k, x) in [
                ("speedup_to_dense_final_fscore", 20.0),
                ("codec_reached_dense_final", 1.0),
                ("codec_reached_dense_final_at_start", 1.0),
                ("dense_start_reaches_final", 0.0),
                ("codec_start_fscore", 86.0),
                ("codec_final_fscore", 87.0),
                ("dense_start_fscore", 80.0),
                ("dense_final_fscore", 85.0),
            ] {
                v.metrics.insert(format!("speed_accuracy.strict.{k}"), x);
            }
        }
        let Report {
            results: md,
            metrics: m,
            ..
        } = report(&rec, &cfg());
        let sp = &m["scenes"]["tiger"]["speedup"];
        assert_eq!(sp["codec_against_start"], "tie", "{m}");
        assert_eq!(sp["dense_against_start"], "lost", "{m}");
        assert!(
            md.contains("codec 90.5 ± 0.0 against 90.5 ± 0.7 (tie), dense 90.2 ± 0.4 against 95.2 ± 0.4 (lost)"),
            "{md}"
        );
        assert!(
            md.contains("At the strict 1 cm / 10° (signed, the same snapshots): speed-up 20.0 ± 0.0 (the codec reached dense's final F in 2 of 2 seeds, 2 of them at its untrained start; undefined in 0 seeds"),
            "{md}"
        );
        assert!(md.contains("codec 87.0 ± 0.0 against 86.0 ± 0.0 (won), dense 85.0 ± 0.0 against 80.0 ± 0.0 (won)."), "{md}");
    }

    #[test]
    fn methods_parse_or_say_what_is_expected() {
        assert_eq!(
            parse_method("dense=evaluate_dense:dense").unwrap(),
            Method {
                name: "dense".into(),
                eval: "evaluate_dense".into(),
                learner: Some("dense".into())
            }
        );
        assert_eq!(parse_method("c=ev").unwrap().learner, None);
        assert!(parse_method("nothing")
            .unwrap_err()
            .contains("NAME=EVAL_STAGE"));
        assert!(parse_method("x=ev:").is_err());
    }

    #[test]
    fn charts_are_written_per_scene() {
        let rec = record(&[("tiger", 0, 60.0, 50.0), ("tiger", 1, 62.0, 51.0)]);
        let dir = tempfile::tempdir().unwrap();
        write_charts(&rec, &cfg(), dir.path()).unwrap();
        for f in [
            "f_vs_time_tiger.png",
            "f_vs_time_tiger.svg",
            "f_vs_size_tiger.svg",
        ] {
            assert!(dir.path().join(f).is_file(), "{f}");
        }
        // The size chart names the size the first method chose (mean strands over seeds).
        let svg = std::fs::read_to_string(dir.path().join("f_vs_size_tiger.svg")).unwrap();
        assert!(
            svg.contains(
                "ringed: FurE as chosen from the views, 41000 strands x 8 points, basis rank 14, \
                 3.5 components trained"
            ),
            "{svg}"
        );
        let time = std::fs::read_to_string(dir.path().join("f_vs_time_tiger.svg")).unwrap();
        assert!(!time.contains("ringed"));
    }
}
