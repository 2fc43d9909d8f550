//! Speed against accuracy (stage `speed_accuracy`): F-score of the codec and dense learners' recorded
//! strand snapshots against training wall time and against the number of optimised parameters, as PNG
//! and SVG charts, Markdown and CSV tables, and the headline speed-up.
//!
//! # Inputs
//! `codec` and `dense`: the `snapshots` directories of the learning stages (stages/src/growth/learn):
//! `index.json` is a JSON array of `{file, seconds, iteration, optimised_parameters}` in training order,
//! `file` being a `.hair` strand file in the same directory and `seconds` the training wall time when it
//! was taken (the clock is paused while snapshots are written). A directory holding `snapshots/index.json`
//! is accepted too. `gt_strands` and `gt_scene` (`s_cm`) are the ground truth.
//!
//! # What is computed
//! Every snapshot is scored with [`crate::evaluation::evaluate::strand_prf_sets`] (unsigned rule, the paper's three
//! thresholds, `spacing_cm` resampling) against one ground-truth [`crate::evaluation::evaluate::OrientedSet`] built
//! once. The charts and the speed-up use the F-score at 3 cm / 30 degrees.
//!
//! Query subsampling. Scoring every point of every snapshot (~400k oriented points a side on the
//! synthetic tiger, about 60 snapshots) took ~10 s a snapshot on 2 cores even with the exact matcher's
//! prunings, because every unmatched query scans its whole 4 cm ball. So each side evaluates a
//! deterministic pseudo-random subset of about `max_queries` query points
//! ([`crate::evaluation::evaluate::query_subset`]; default 40,000; the reference side is always complete, so a
//! sampled query is matched exactly as in the full evaluation). Precision and recall are fractions over
//! those queries: unbiased, with a sampling error of about `sqrt(0.25 / n)` = 0.25 percentage points at
//! most (one standard deviation, n = 40,000). `max_queries = 0` scores every point. The `evaluate`
//! stages score the final strands exactly; the final snapshots (the same strands) show the measured
//! effect (docs/history.md, "Speed against accuracy").
//!
//! `speedup_to_dense_final_fscore` = `t_dense / t_codec`, with `F*` the dense baseline's final F-score
//! (its last snapshot), `t_dense` the training time of the FIRST dense snapshot whose F-score reaches `F*`
//! (so a dense run that plateaus early is credited with its early time, which can only lower the ratio),
//! and `t_codec` the training time of the first codec snapshot whose F-score reaches `F*`. Times are those
//! of snapshots, not interpolated. A learner's clock starts before its untrained snapshot (iteration 0):
//! the colour fit runs first, so reaching `F*` there still takes that time. When dense's own untrained
//! snapshot already reaches `F*` (its training never improved on its start at 3 cm), there is no
//! training time of dense's to compare with, and the speed-up is `null` (`dense_start_reaches_final`);
//! when the codec's untrained snapshot reaches it (`codec_reached_dense_final_at_start`), the ratio is
//! dense's time over the codec's colour fit. The learners take snapshots at geometrically spaced training times
//! (ratio `g`, 1.1 by default, from 0.5 s), so each time is an upper bound within a factor `g` and the
//! ratio is known within a factor `g` either way, at any time scale. When no codec snapshot reaches `F*`
//! the speed-up is `null` and `speedup_note` says so.
//!
//! The same speed-up is computed at the strict 1 cm / 10 degrees, signed (`strict` in
//! metrics.json): on a scene where both learners start at 99.9 at 3 cm (the cat), 3 cm compares
//! hundredths of a point, while the strict score still separates them. Each snapshot is scored
//! at the four thresholds in one pass (the matching grid's cell is then the strict 1 cm).
//!
//! The reverse question, asked because dense's final F-score can lie below the codec's untrained
//! start (the ratio then compares dense's climb with the codec's colour fit):
//! `dense_seconds_to_codec_final` is the training time of the first dense snapshot whose F-score
//! reaches the codec's final one, `null` when none does (`dense_reached_codec_final` 0).
//!
//! Charts are drawn with [`crate::evaluation::charts`]; time axes are logarithmic, snapshots at 0 s
//! are drawn at 0.01 s.

use std::path::{Path, PathBuf};

use fure_stage_api::{ParamSpec, Params, PortSpec, Stage, StageContext, StageError};
use plotters::coord::Shift;
use plotters::prelude::*;
use serde::{Deserialize, Serialize};

use crate::data::strands::Strands;
use crate::evaluation::charts::{chart_err, fmt_num, write_png_chart, write_svg_chart};
use crate::evaluation::evaluate::{
    match_cell, strand_prf_sets, threshold_key, OrientedSet, Prf, PAPER_THRESHOLDS,
    STRICT_THRESHOLD,
};

/// One snapshot entry of `snapshots/index.json` (as written by the learning stages).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Snapshot {
    pub file: String,
    pub seconds: f64,
    #[serde(default)]
    pub iteration: usize,
    #[serde(default)]
    pub optimised_parameters: usize,
}

/// A scored snapshot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScoredSnapshot {
    pub method: String,
    pub file: String,
    pub seconds: f64,
    pub iteration: usize,
    pub optimised_parameters: usize,
    /// Unsigned PRF (percent) at the paper's three thresholds.
    pub prf: Vec<Prf>,
    /// Signed F-score (percent) at the strict 1 cm / 10 degrees (`None` in records written
    /// before it was scored).
    #[serde(default)]
    pub strict_signed: Option<f32>,
}

impl ScoredSnapshot {
    /// F-score at 3 cm / 30 degrees.
    pub fn f3(&self) -> f64 {
        self.prf
            .iter()
            .find(|p| p.dist_cm == 3.0 && p.angle_deg == 30.0)
            .map(|p| p.fscore as f64)
            .unwrap_or(0.0)
    }

    /// Signed F-score at the strict 1 cm / 10 degrees (0 when not scored).
    pub fn f_strict(&self) -> f64 {
        self.strict_signed.map_or(0.0, f64::from)
    }
}

/// The speed-up (module doc).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Speedup {
    pub dense_final_fscore: f64,
    pub dense_seconds_to_final: f64,
    pub dense_seconds_total: f64,
    pub codec_seconds_to_dense_final: Option<f64>,
    pub codec_final_fscore: f64,
    pub codec_seconds_total: f64,
    pub speedup_to_dense_final_fscore: Option<f64>,
    /// The speed-up the snapshot times allow: each learner crossed the target somewhere between
    /// its previous snapshot and the one that reached it, so the ratio lies in
    /// `[dense previous / codec reached, dense reached / codec previous]` (`None` when the codec
    /// never reached the target; the upper end `None` when the codec reached it at its first
    /// snapshot).
    pub speedup_bracket: Option<(f64, Option<f64>)>,
    pub speedup_note: String,
    /// The codec's untrained snapshot (iteration 0) already reaches the target.
    pub codec_at_start: bool,
    /// Dense's untrained snapshot already reaches its own final F-score: the ratio is undefined.
    pub dense_start_reaches_final: bool,
    /// Training time of the first dense snapshot reaching the codec's final F-score (`None`:
    /// dense never reaches it).
    pub dense_seconds_to_codec_final: Option<f64>,
}

/// Computes [`Speedup`] at 3 cm / 30 degrees (unsigned) from time-ordered scored snapshots of
/// both methods (each non-empty).
pub fn speedup(codec: &[ScoredSnapshot], dense: &[ScoredSnapshot]) -> Option<Speedup> {
    speedup_at(codec, dense, &ScoredSnapshot::f3, "3cm/30deg")
}

/// [`speedup`] with the F-score `f` of each snapshot (named `label` in the notes).
pub fn speedup_at(
    codec: &[ScoredSnapshot],
    dense: &[ScoredSnapshot],
    f: &dyn Fn(&ScoredSnapshot) -> f64,
    label: &str,
) -> Option<Speedup> {
    let dl = dense.last()?;
    let cl = codec.last()?;
    let target = f(dl);
    let t_dense = dense
        .iter()
        .find(|s| f(s) >= target)
        .map(|s| s.seconds)
        .unwrap_or(dl.seconds);
    let i_dense = dense.iter().position(|s| f(s) >= target);
    let i_codec = codec.iter().position(|s| f(s) >= target);
    let t_codec = i_codec.map(|i| codec[i].seconds);
    let before = |snaps: &[ScoredSnapshot], i: Option<usize>| {
        i.and_then(|i| i.checked_sub(1)).map(|j| snaps[j].seconds)
    };
    let bracket = match (t_codec, before(codec, i_codec)) {
        (Some(tc), prev) if tc > 0.0 => Some((
            before(dense, i_dense).unwrap_or(0.0) / tc,
            prev.filter(|&p| p > 0.0).map(|p| t_dense / p),
        )),
        _ => None,
    };
    let untrained_reaches = |s: &[ScoredSnapshot]| {
        s.first()
            .is_some_and(|x| x.iteration == 0 && f(x) >= target)
    };
    let codec_at_start = untrained_reaches(codec);
    let dense_start_reaches_final = untrained_reaches(dense);
    let (ratio, note) = match t_codec {
        _ if dense_start_reaches_final => (
            None,
            format!(
                "dense's untrained start already reaches its final F-score {target:.2} at \
                 {label} (its training did not improve on it): no training time to compare, \
                 ratio undefined"
            ),
        ),
        Some(tc) if tc > 0.0 => (
            Some(t_dense / tc),
            format!(
                "dense reaches its final F-score {target:.2} at {label} after {t_dense:.1} s; \
                 codec reaches it after {tc:.1} s{}",
                if codec_at_start {
                    " (at its untrained start: the time of its colour fit)"
                } else {
                    ""
                }
            ),
        ),
        Some(_) => (
            None,
            "codec reached the dense final F-score at 0 s of training: ratio undefined".to_string(),
        ),
        None => (
            None,
            format!(
                "codec never reached the dense final F-score {target:.2} at {label} (its best: {:.2})",
                codec.iter().map(f).fold(0.0, f64::max)
            ),
        ),
    };
    Some(Speedup {
        dense_final_fscore: target,
        dense_seconds_to_final: t_dense,
        dense_seconds_total: dl.seconds,
        codec_seconds_to_dense_final: t_codec,
        codec_final_fscore: f(cl),
        codec_seconds_total: cl.seconds,
        speedup_to_dense_final_fscore: ratio,
        speedup_bracket: bracket.filter(|_| !dense_start_reaches_final),
        speedup_note: note,
        codec_at_start,
        dense_start_reaches_final,
        dense_seconds_to_codec_final: dense.iter().find(|s| f(s) >= f(cl)).map(|s| s.seconds),
    })
}

const CODEC_COLOR: RGBColor = RGBColor(31, 119, 180);
const DENSE_COLOR: RGBColor = RGBColor(214, 39, 40);

fn method_color(m: &str) -> RGBColor {
    if m == "codec" {
        CODEC_COLOR
    } else {
        DENSE_COLOR
    }
}

/// F-score at 3cm/30deg against training time (log axis), one line per method.
pub fn draw_time_chart<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    series: &[(&str, &[ScoredSnapshot])],
    dense_final: Option<f64>,
) -> Result<(), String> {
    root.fill(&WHITE).map_err(chart_err)?;
    let pts: Vec<(f64, f64)> = series
        .iter()
        .flat_map(|(_, s)| s.iter().map(|x| (x.seconds.max(0.01), x.f3())))
        .collect();
    let tmin = pts.iter().map(|p| p.0).fold(f64::MAX, f64::min).min(1.0);
    let tmax = pts.iter().map(|p| p.0).fold(0.0, f64::max).max(tmin * 10.0);
    let fmax = pts.iter().map(|p| p.1).fold(0.0, f64::max);
    let ymax = ((fmax / 10.0).ceil() * 10.0).clamp(10.0, 100.0);
    let mut chart = ChartBuilder::on(root)
        .caption(
            "F-score (3 cm / 30\u{b0}) vs strand-training time",
            ("sans-serif", 22),
        )
        .margin(14)
        .x_label_area_size(44)
        .y_label_area_size(56)
        .build_cartesian_2d((tmin * 0.8..tmax * 1.25).log_scale(), 0.0..ymax)
        .map_err(chart_err)?;
    chart
        .configure_mesh()
        .x_desc("strand-training wall time (s, log scale)")
        .y_desc("F-score at 3 cm / 30\u{b0} (%)")
        .x_label_formatter(&|x| fmt_num(*x))
        .y_label_formatter(&|y| format!("{y:.0}"))
        .label_style(("sans-serif", 14))
        .axis_desc_style(("sans-serif", 15))
        .draw()
        .map_err(chart_err)?;
    for (name, s) in series {
        let c = method_color(name);
        let data: Vec<(f64, f64)> = s.iter().map(|x| (x.seconds.max(0.01), x.f3())).collect();
        chart
            .draw_series(LineSeries::new(data.clone(), c.stroke_width(2)))
            .map_err(chart_err)?
            .label(name.to_string())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2)));
        chart
            .draw_series(data.iter().map(|p| Circle::new(*p, 3, c.filled())))
            .map_err(chart_err)?;
    }
    if let Some(f) = dense_final {
        let grey = RGBColor(120, 120, 120);
        chart
            .draw_series(DashedLineSeries::new(
                vec![(tmin * 0.8, f), (tmax * 1.25, f)],
                6,
                4,
                grey.stroke_width(1),
            ))
            .map_err(chart_err)?
            .label("dense final F-score")
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], grey.stroke_width(1))
            });
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 14))
        .draw()
        .map_err(chart_err)?;
    root.present().map_err(chart_err)?;
    Ok(())
}

/// Final F-score at 3cm/30deg against the number of optimised parameters (log axis), one point per
/// method.
pub fn draw_params_chart<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    finals: &[(&str, f64, f64)],
) -> Result<(), String> {
    root.fill(&WHITE).map_err(chart_err)?;
    let pmin = finals.iter().map(|f| f.1).fold(f64::MAX, f64::min).max(1.0);
    let pmax = finals
        .iter()
        .map(|f| f.1)
        .fold(1.0, f64::max)
        .max(pmin * 10.0);
    let fmax = finals.iter().map(|f| f.2).fold(0.0, f64::max);
    let ymax = ((fmax / 10.0).ceil() * 10.0 + 10.0).clamp(10.0, 100.0);
    let mut chart = ChartBuilder::on(root)
        .caption(
            "F-score (3 cm / 30\u{b0}) vs optimised parameters",
            ("sans-serif", 22),
        )
        .margin(14)
        .x_label_area_size(44)
        .y_label_area_size(56)
        .build_cartesian_2d((pmin / 3.0..pmax * 3.0).log_scale(), 0.0..ymax)
        .map_err(chart_err)?;
    chart
        .configure_mesh()
        .x_desc("optimised geometry parameters (log scale)")
        .y_desc("final F-score at 3 cm / 30\u{b0} (%)")
        .x_label_formatter(&|x| fmt_num(*x))
        .y_label_formatter(&|y| format!("{y:.0}"))
        .label_style(("sans-serif", 14))
        .axis_desc_style(("sans-serif", 15))
        .draw()
        .map_err(chart_err)?;
    for (name, params, f) in finals {
        let c = method_color(name);
        chart
            .draw_series(std::iter::once(Circle::new(
                (params.max(1.0), *f),
                6,
                c.filled(),
            )))
            .map_err(chart_err)?;
        chart
            .draw_series(std::iter::once(Text::new(
                format!("{name}: {f:.1}%"),
                (params.max(1.0) * 1.15, *f + ymax * 0.03),
                ("sans-serif", 15).into_font().color(&c),
            )))
            .map_err(chart_err)?;
    }
    root.present().map_err(chart_err)?;
    Ok(())
}

/// The Markdown and CSV tables of all scored snapshots.
pub fn tables(rows: &[ScoredSnapshot]) -> (String, String) {
    let keys: Vec<String> = PAPER_THRESHOLDS
        .iter()
        .map(|&(d, a)| threshold_key(d, a))
        .collect();
    let mut md = String::from("| method | snapshot | iteration | seconds | optimised parameters |");
    let mut csv = String::from("method,snapshot,iteration,seconds,optimised_parameters");
    for k in &keys {
        md.push_str(&format!(" P {k} | R {k} | F {k} |"));
        csv.push_str(&format!(",precision_{k},recall_{k},fscore_{k}"));
    }
    md.push('\n');
    csv.push('\n');
    md.push_str("|---|---|---:|---:|---:|");
    for _ in &keys {
        md.push_str("---:|---:|---:|");
    }
    md.push('\n');
    for r in rows {
        md.push_str(&format!(
            "| {} | {} | {} | {:.2} | {} |",
            r.method, r.file, r.iteration, r.seconds, r.optimised_parameters
        ));
        csv.push_str(&format!(
            "{},{},{},{:.3},{}",
            r.method, r.file, r.iteration, r.seconds, r.optimised_parameters
        ));
        for p in &r.prf {
            md.push_str(&format!(
                " {:.2} | {:.2} | {:.2} |",
                p.precision, p.recall, p.fscore
            ));
            csv.push_str(&format!(
                ",{:.4},{:.4},{:.4}",
                p.precision, p.recall, p.fscore
            ));
        }
        md.push('\n');
        csv.push('\n');
    }
    (md, csv)
}

/// Reads a snapshots directory (or a directory holding `snapshots/`).
pub fn read_snapshots(port: &str, dir: &Path) -> Result<(PathBuf, Vec<Snapshot>), StageError> {
    let d = if dir.join("index.json").is_file() {
        dir.to_path_buf()
    } else if dir.join("snapshots").join("index.json").is_file() {
        dir.join("snapshots")
    } else {
        return Err(StageError::input(
            port,
            dir,
            "no index.json (expected a learning stage's `snapshots` directory)",
        ));
    };
    let list: Vec<Snapshot> = crate::formats::json::read_json(d.join("index.json"))?;
    if list.is_empty() {
        return Err(StageError::input(
            port,
            &d.join("index.json"),
            "lists no snapshot",
        ));
    }
    for (i, s) in list.iter().enumerate() {
        if !(s.seconds.is_finite() && s.seconds >= 0.0) {
            return Err(StageError::input(
                port,
                &d.join("index.json"),
                format!(
                    "entry {i}: field `seconds` is {}, expected a finite number >= 0",
                    s.seconds
                ),
            ));
        }
    }
    Ok((d, list))
}

fure_stage_api::stage_params! {
    /// The `speed_accuracy` stage's parameters.
    pub struct SpeedAccuracyParams {
        /// arc-length resampling of both strand sets (cm)
        spacing_cm: f32 = float(0.5).range(0.01, 100.0),
        /// evaluate at most this many evenly strided query points per side (0 = all; module doc)
        max_queries: usize = int(40_000).min(0.0),
        /// chart width (px)
        width: u32 = int(900).range(200.0, 8000.0),
        /// chart height (px)
        height: u32 = int(560).range(150.0, 8000.0),
    }
}

/// Stage `speed_accuracy`.
pub struct SpeedAccuracyStage;

impl Stage for SpeedAccuracyStage {
    fn kind(&self) -> &'static str {
        "speed_accuracy"
    }
    fn version(&self) -> u32 {
        // 8: the speed-up at the strict threshold too (signed).
        8
    }
    fn doc(&self) -> &'static str {
        "Scores the codec and dense learners' strand snapshots against GT strands and charts F-score at \
         3cm/30deg against training time (log) and optimised parameters (PNG + SVG), with Markdown/CSV \
         tables and the speed-up to the dense baseline's final F-score."
    }
    fn params(&self) -> Vec<ParamSpec> {
        SpeedAccuracyParams::specs()
    }
    fn inputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![
            PortSpec::dir("codec", "codec_strands snapshots directory"),
            PortSpec::dir("dense", "dense_strands snapshots directory"),
            PortSpec::file("gt_strands", "hair", "ground-truth strands"),
            PortSpec::file("gt_scene", "json", "scene.json with s_cm"),
        ]
    }
    fn outputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![
            PortSpec::file("chart_time", "png", "F-score vs training time"),
            PortSpec::file("chart_time_svg", "svg", "F-score vs training time"),
            PortSpec::file("chart_params", "png", "F-score vs optimised parameters"),
            PortSpec::file("chart_params_svg", "svg", "F-score vs optimised parameters"),
            PortSpec::file(
                "table_md",
                "md",
                "all snapshots, P/R/F at the three thresholds",
            ),
            PortSpec::file("table_csv", "csv", "the same as CSV"),
            PortSpec::file("metrics", "json", "speed-up and per-snapshot scores"),
        ]
    }
    fn run(&self, ctx: &StageContext<'_>) -> Result<(), StageError> {
        let p = SpeedAccuracyParams::from_params(ctx.params)?;
        let spacing = p.spacing_cm;
        let max_q = p.max_queries;
        let size = (p.width, p.height);
        let s_cm = crate::evaluation::gt_scale_cm(ctx)?;
        let gt = read_gt_strands(ctx)?;
        // The ground truth's oriented points and grid, built once for every snapshot.
        let cell = match_cell(&SCORED);
        let scoring = Scoring {
            gt_set: OrientedSet::new(&gt, s_cm, spacing, cell),
            s_cm,
            spacing,
            cell,
            max_q,
        };
        let scored = scoring.score_all(ctx)?;
        let (codec, dense) = (&scored[0], &scored[1]);
        let sp =
            speedup(codec, dense).ok_or_else(|| StageError::failed("no snapshots to compare"))?;
        ctx.progress.note(&sp.speedup_note);
        // The same at the strict threshold, signed: where 3 cm saturates (both learners at 99.9
        // from the start) it still separates them.
        let strict = speedup_at(codec, dense, &ScoredSnapshot::f_strict, "1cm/10deg signed");

        ctx.progress.message("drawing charts");
        write_charts(ctx, size, codec, dense, sp.dense_final_fscore)?;
        let all: Vec<ScoredSnapshot> = scored.iter().flatten().cloned().collect();
        write_tables(ctx, &all, &sp)?;
        let metrics = serde_json::json!({
            "speedup_to_dense_final_fscore": sp.speedup_to_dense_final_fscore,
            "speedup_low": sp.speedup_bracket.map(|b| b.0),
            "speedup_high": sp.speedup_bracket.and_then(|b| b.1),
            "speedup_note": sp.speedup_note,
            "dense_final_fscore_3cm_30deg": sp.dense_final_fscore,
            "dense_seconds_to_final": sp.dense_seconds_to_final,
            "dense_seconds_total": sp.dense_seconds_total,
            "codec_seconds_to_dense_final": sp.codec_seconds_to_dense_final,
            "codec_final_fscore_3cm_30deg": sp.codec_final_fscore,
            "codec_seconds_total": sp.codec_seconds_total,
            "dense_seconds_to_codec_final": sp.dense_seconds_to_codec_final,
            "dense_reached_codec_final": f64::from(u8::from(sp.dense_seconds_to_codec_final.is_some())),
            "dense_best_fscore_3cm_30deg": dense.iter().map(|s| s.f3()).fold(0.0, f64::max),
            "codec_best_fscore_3cm_30deg": codec.iter().map(|s| s.f3()).fold(0.0, f64::max),
            // The untrained start (first snapshot) and whether the codec reached dense's final
            // F-score at all, and already there: numbers, so a sweep record keeps them.
            "codec_start_fscore_3cm_30deg": codec.first().map(|s| s.f3()),
            "dense_start_fscore_3cm_30deg": dense.first().map(|s| s.f3()),
            "codec_reached_dense_final": u8::from(sp.codec_seconds_to_dense_final.is_some()),
            "codec_reached_dense_final_at_start": u8::from(sp.codec_at_start),
            "dense_start_reaches_final": u8::from(sp.dense_start_reaches_final),
            "strict": strict.as_ref().map(|st| serde_json::json!({
                "speedup_to_dense_final_fscore": st.speedup_to_dense_final_fscore,
                "speedup_note": st.speedup_note,
                "dense_final_fscore": st.dense_final_fscore,
                "codec_final_fscore": st.codec_final_fscore,
                "codec_start_fscore": codec.first().map(|s| s.f_strict()),
                "dense_start_fscore": dense.first().map(|s| s.f_strict()),
                "codec_reached_dense_final": u8::from(st.codec_seconds_to_dense_final.is_some()),
                "codec_reached_dense_final_at_start": u8::from(st.codec_at_start),
                "dense_start_reaches_final": u8::from(st.dense_start_reaches_final),
                "dense_reached_codec_final": u8::from(st.dense_seconds_to_codec_final.is_some()),
            })),
            "spacing_cm": spacing,
            "max_queries": max_q,
            "gt_oriented_points": scoring.gt_set.len(),
            "snapshots": all,
        });
        crate::formats::json::write_json(ctx.output("metrics")?, &metrics)?;
        Ok(())
    }
}

/// The ground-truth strands, at least one.
fn read_gt_strands(ctx: &StageContext<'_>) -> Result<Strands, StageError> {
    let gt = crate::evaluation::evaluate::read_strands_any(ctx.input("gt_strands")?)?;
    if gt.is_empty() {
        return Err(StageError::input(
            "gt_strands",
            ctx.input("gt_strands")?,
            "holds no strands",
        ));
    }
    Ok(gt)
}

/// The thresholds every snapshot is scored at: the strict one (its signed F-score is kept), then
/// the paper's three (unsigned, the charts' and tables').
const SCORED: [(f32, f32); 4] = [
    STRICT_THRESHOLD,
    PAPER_THRESHOLDS[0],
    PAPER_THRESHOLDS[1],
    PAPER_THRESHOLDS[2],
];

/// Scores snapshots against the ground truth's oriented points at [`SCORED`].
struct Scoring {
    gt_set: OrientedSet,
    s_cm: f32,
    spacing: f32,
    cell: f32,
    max_q: usize,
}

impl Scoring {
    /// The scored snapshots of `codec`, then `dense`, each in time order.
    fn score_all(&self, ctx: &StageContext<'_>) -> Result<Vec<Vec<ScoredSnapshot>>, StageError> {
        let lists: Vec<(&str, PathBuf, Vec<Snapshot>)> = ["codec", "dense"]
            .iter()
            .map(|m| read_snapshots(m, ctx.input(m)?).map(|(d, l)| (*m, d, l)))
            .collect::<Result<_, _>>()?;
        ctx.progress
            .set_total(lists.iter().map(|l| l.2.len() as u64).sum());
        let mut scored: Vec<Vec<ScoredSnapshot>> = Vec::new();
        for (method, dir, list) in &lists {
            let mut v = Vec::new();
            for s in list {
                ctx.progress.check_interrupted()?;
                ctx.progress
                    .message(&format!("scoring {method} {}", s.file));
                v.push(self.score(method, dir, s)?);
                ctx.progress.advance(1);
            }
            // Time order (the learners write them in order; sorting makes it a guarantee).
            v.sort_by(|a, b| a.seconds.total_cmp(&b.seconds));
            scored.push(v);
        }
        Ok(scored)
    }

    /// One snapshot of `method` (in directory `dir`) with its precision, recall and F-scores.
    fn score(&self, method: &str, dir: &Path, s: &Snapshot) -> Result<ScoredSnapshot, StageError> {
        let strands: Strands = crate::evaluation::evaluate::read_strands_any(&dir.join(&s.file))?;
        let pred = OrientedSet::new(&strands, self.s_cm, self.spacing, self.cell);
        let (mut prf, signed) = strand_prf_sets(&pred, &self.gt_set, &SCORED, self.max_q);
        let strict = signed[0].fscore;
        prf.remove(0);
        fure_stage_api::ensure_finite(
            "snapshot scores",
            prf.iter()
                .flat_map(|x| [x.precision, x.recall, x.fscore])
                .chain([strict]),
        )?;
        Ok(ScoredSnapshot {
            method: method.to_string(),
            file: s.file.clone(),
            seconds: s.seconds,
            iteration: s.iteration,
            optimised_parameters: s.optimised_parameters,
            prf,
            strict_signed: Some(strict),
        })
    }
}

/// The F-score charts against training time (with the dense final F-score `dense_final`) and
/// against optimised parameters, each as PNG and SVG.
fn write_charts(
    ctx: &StageContext<'_>,
    size: (u32, u32),
    codec: &[ScoredSnapshot],
    dense: &[ScoredSnapshot],
    dense_final: f64,
) -> Result<(), StageError> {
    let series: Vec<(&str, &[ScoredSnapshot])> = vec![("codec", codec), ("dense", dense)];
    let finals: Vec<(&str, f64, f64)> = series
        .iter()
        .filter_map(|(n, s)| {
            s.last()
                .map(|l| (*n, l.optimised_parameters as f64, l.f3()))
        })
        .collect();
    let df = Some(dense_final);
    write_png_chart(ctx.output("chart_time")?, size, |r| {
        draw_time_chart(r, &series, df)
    })?;
    write_svg_chart(ctx.output("chart_time_svg")?, size, |r| {
        draw_time_chart(r, &series, df)
    })?;
    write_png_chart(ctx.output("chart_params")?, size, |r| {
        draw_params_chart(r, &finals)
    })?;
    write_svg_chart(ctx.output("chart_params_svg")?, size, |r| {
        draw_params_chart(r, &finals)
    })?;
    Ok(())
}

/// The Markdown (headed by the speed-up) and CSV tables of all snapshots.
fn write_tables(
    ctx: &StageContext<'_>,
    all: &[ScoredSnapshot],
    sp: &Speedup,
) -> Result<(), StageError> {
    let (md, csv) = tables(all);
    let md = format!(
        "# Speed against accuracy\n\n{}\n\nSpeed-up to the dense final F-score at 3cm/30deg: {}\n\n{md}",
        sp.speedup_note,
        sp.speedup_to_dense_final_fscore
            .map(|x| format!("{x:.2}x"))
            .unwrap_or_else(|| "n/a".into())
    );
    let md_path = ctx.output("table_md")?;
    std::fs::write(md_path, md).map_err(|e| StageError::io(md_path, e))?;
    let csv_path = ctx.output("table_csv")?;
    std::fs::write(csv_path, csv).map_err(|e| StageError::io(csv_path, e))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    fn snap(method: &str, seconds: f64, f: f32, params: usize) -> ScoredSnapshot {
        ScoredSnapshot {
            method: method.into(),
            file: format!("snap_{seconds}.hair"),
            seconds,
            iteration: seconds as usize,
            optimised_parameters: params,
            prf: PAPER_THRESHOLDS
                .iter()
                .map(|&(d, a)| Prf {
                    dist_cm: d,
                    angle_deg: a,
                    precision: f,
                    recall: f,
                    fscore: f,
                })
                .collect(),
            strict_signed: Some(f / 2.0),
        }
    }

    #[test]
    fn the_strict_speedup_separates_learners_where_3_cm_saturates() {
        let at =
            |method: &str, seconds: f64, iteration: usize, f3: f32, strict: f32| ScoredSnapshot {
                iteration,
                strict_signed: Some(strict),
                ..snap(method, seconds, f3, 100)
            };
        // Both learners sit at 99.9 at 3 cm from the start; at 1 cm dense climbs 80 -> 85
        // in 40 s, the codec starts at 86 after a 2 s colour fit.
        let dense = vec![
            at("dense", 1.0, 0, 99.9, 80.0),
            at("dense", 40.0, 900, 99.9, 85.0),
        ];
        let codec = vec![
            at("codec", 2.0, 0, 99.9, 86.0),
            at("codec", 5.0, 100, 99.9, 87.0),
        ];
        let s3 = speedup(&codec, &dense).unwrap();
        assert!(s3.dense_start_reaches_final);
        assert_eq!(s3.speedup_to_dense_final_fscore, None);
        let st = speedup_at(
            &codec,
            &dense,
            &ScoredSnapshot::f_strict,
            "1cm/10deg signed",
        )
        .unwrap();
        assert!(!st.dense_start_reaches_final && st.codec_at_start);
        assert_eq!(st.speedup_to_dense_final_fscore, Some(20.0));
        assert_eq!(st.codec_final_fscore, 87.0);
        assert!(
            st.speedup_note.contains("1cm/10deg signed"),
            "{}",
            st.speedup_note
        );
        // A record written before the strict score: 0, never a reached target.
        let old = ScoredSnapshot {
            strict_signed: None,
            ..snap("codec", 1.0, 50.0, 1)
        };
        assert_eq!(old.f_strict(), 0.0);
    }

    #[test]
    fn speedup_uses_first_snapshots_reaching_the_dense_final() {
        let dense = vec![
            snap("dense", 100.0, 10.0, 5000),
            snap("dense", 1000.0, 30.0, 5000),
            snap("dense", 2000.0, 30.0, 5000),
        ];
        let codec = vec![
            snap("codec", 10.0, 20.0, 500),
            snap("codec", 50.0, 31.0, 500),
            snap("codec", 90.0, 35.0, 500),
        ];
        let s = speedup(&codec, &dense).unwrap();
        assert_eq!(s.dense_final_fscore, 30.0);
        assert_eq!(s.dense_seconds_to_final, 1000.0);
        assert_eq!(s.codec_seconds_to_dense_final, Some(50.0));
        assert_eq!(s.speedup_to_dense_final_fscore, Some(20.0));
        // Dense never reaches the codec's final 35.
        assert_eq!(s.dense_seconds_to_codec_final, None);
        let s = speedup(&codec[..2], &dense).unwrap();
        assert_eq!(
            s.dense_seconds_to_codec_final, None,
            "31 is above dense's best 30"
        );
        let s = speedup(&codec[..1], &dense).unwrap();
        assert_eq!(s.dense_seconds_to_codec_final, Some(1000.0));
        // A codec that never gets there: null with a note.
        let slow = vec![snap("codec", 10.0, 20.0, 500)];
        let s = speedup(&slow, &dense).unwrap();
        assert_eq!(s.speedup_to_dense_final_fscore, None);
        assert!(s.speedup_note.contains("never"));
        assert!(!s.codec_at_start && !s.dense_start_reaches_final);
    }

    #[test]
    fn untrained_starts_are_told_apart_from_training() {
        // Snapshots at iteration 0 taken after a colour fit (seconds > 0).
        let at = |method: &str, seconds: f64, iteration: usize, f: f32| ScoredSnapshot {
            iteration,
            ..snap(method, seconds, f, 100)
        };
        // Dense improves from 20 to 30 in training; the codec starts at 31.
        let dense = vec![at("dense", 2.0, 0, 20.0), at("dense", 100.0, 50, 30.0)];
        let codec = vec![at("codec", 4.0, 0, 31.0), at("codec", 9.0, 10, 33.0)];
        let s = speedup(&codec, &dense).unwrap();
        assert!(s.codec_at_start && !s.dense_start_reaches_final);
        assert_eq!(s.speedup_to_dense_final_fscore, Some(25.0));
        assert!(
            s.speedup_note.contains("untrained start"),
            "{}",
            s.speedup_note
        );
        // Dense drifts down from an untrained start above its final: undefined.
        let drifting = vec![at("dense", 2.0, 0, 32.0), at("dense", 100.0, 50, 30.0)];
        let s = speedup(&codec, &drifting).unwrap();
        assert!(s.dense_start_reaches_final);
        assert_eq!(s.speedup_to_dense_final_fscore, None);
        assert_eq!(s.speedup_bracket, None);
        assert!(
            s.speedup_note.contains("did not improve"),
            "{}",
            s.speedup_note
        );
    }

    #[test]
    fn charts_and_tables_render_files() {
        let dense = vec![
            snap("dense", 20.0, 12.0, 90000),
            snap("dense", 400.0, 33.0, 90000),
        ];
        let codec = vec![
            snap("codec", 2.0, 25.0, 3000),
            snap("codec", 30.0, 36.5, 3000),
        ];
        let dir = tempfile::tempdir().unwrap();
        let series: Vec<(&str, &[ScoredSnapshot])> = vec![("codec", &codec), ("dense", &dense)];
        let png = dir.path().join("t.png");
        write_png_chart(&png, (480, 320), |r| {
            draw_time_chart(r, &series, Some(33.0))
        })
        .unwrap();
        let img = crate::formats::images::read_png(&png).unwrap();
        assert_eq!((img.width, img.height), (480, 320));
        // Not blank: the codec colour and dark text pixels are present.
        let has = |rgb: [f32; 3]| {
            img.data.chunks(3).any(|p| {
                (p[0] - rgb[0]).abs() < 0.02
                    && (p[1] - rgb[1]).abs() < 0.02
                    && (p[2] - rgb[2]).abs() < 0.02
            })
        };
        assert!(has([31.0 / 255.0, 119.0 / 255.0, 180.0 / 255.0]));
        let dark = img
            .data
            .chunks(3)
            .filter(|p| p[0] + p[1] + p[2] < 0.6)
            .count();
        assert!(dark > 500, "text and axes drawn: {dark} dark pixels");
        let svg = dir.path().join("t.svg");
        write_svg_chart(&svg, (480, 320), |r| {
            draw_time_chart(r, &series, Some(33.0))
        })
        .unwrap();
        let s = std::fs::read_to_string(&svg).unwrap();
        assert!(s.starts_with("<svg") && s.contains("strand-training wall time"));
        let finals = vec![("codec", 3000.0, 36.5), ("dense", 90000.0, 33.0)];
        let png2 = dir.path().join("p.png");
        write_png_chart(&png2, (480, 320), |r| draw_params_chart(r, &finals)).unwrap();
        assert!(png2.metadata().unwrap().len() > 1000);
        let all: Vec<ScoredSnapshot> = codec.iter().chain(&dense).cloned().collect();
        let (md, csv) = tables(&all);
        assert_eq!(md.lines().count(), 2 + 4);
        assert_eq!(csv.lines().count(), 1 + 4);
        assert!(csv
            .lines()
            .nth(1)
            .unwrap()
            .starts_with("codec,snap_2.hair,2,2.000,3000,25.0000"));
    }

    #[test]
    fn stage_scores_snapshot_dirs() {
        use std::collections::BTreeMap;
        // GT: a patch of straight strands; codec snapshots converge to it, dense snapshots slower.
        let patch = |shift: f32| {
            let mut s = Strands::new();
            for i in 0..6 {
                for j in 0..6 {
                    let r = Vec3::new(i as f32 * 0.05, j as f32 * 0.05, 0.0);
                    let pts: Vec<Vec3> = (0..5)
                        .map(|k| r + Vec3::new(shift, 0.0, 0.01 * k as f32))
                        .collect();
                    s.push(&pts, 0, 0.001, [0.5; 3]);
                }
            }
            s
        };
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        crate::formats::hair::write_hair(root.join("gt.hair"), &patch(0.0)).unwrap();
        let scene = serde_json::json!({"s_cm": 100.0, "eyes": [[0,0,0],[1,0,0]], "parts": {}});
        std::fs::write(root.join("scene.json"), scene.to_string()).unwrap();
        for (m, shifts, secs) in [
            ("codec", [0.05f32, 0.0], [5.0, 10.0]),
            ("dense", [0.05, 0.0], [50.0, 200.0]),
        ] {
            let d = root.join(m);
            std::fs::create_dir_all(&d).unwrap();
            let mut idx = Vec::new();
            for (i, (sh, t)) in shifts.iter().zip(secs).enumerate() {
                let f = format!("snap_{i:03}.hair");
                crate::formats::hair::write_hair(d.join(&f), &patch(*sh)).unwrap();
                idx.push(Snapshot {
                    file: f,
                    seconds: t,
                    iteration: i,
                    optimised_parameters: 100,
                });
            }
            crate::formats::json::write_json(d.join("index.json"), &idx).unwrap();
        }
        let out = root.join("out");
        std::fs::create_dir_all(&out).unwrap();
        let st = SpeedAccuracyStage;
        let mut params = Params::default();
        for spec in st.params() {
            params
                .0
                .insert(spec.name.to_string(), spec.default.clone().unwrap());
        }
        let inputs: BTreeMap<String, PathBuf> = [
            ("codec", root.join("codec")),
            ("dense", root.join("dense")),
            ("gt_strands", root.join("gt.hair")),
            ("gt_scene", root.join("scene.json")),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
        let outputs: BTreeMap<String, PathBuf> = st
            .outputs(&params)
            .iter()
            .map(|p| (p.name.clone(), out.join(p.file_name())))
            .collect();
        let ctx = StageContext {
            name: "sa",
            params: &params,
            inputs,
            outputs: outputs.clone(),
            progress: &fure_stage_api::NoProgress,
        };
        st.run(&ctx).unwrap();
        let m: serde_json::Value = crate::formats::json::read_json(&outputs["metrics"]).unwrap();
        // Both reach 100% at their second snapshot: 200 s / 10 s.
        assert_eq!(m["speedup_to_dense_final_fscore"].as_f64(), Some(20.0));
        for p in outputs.values() {
            assert!(p.metadata().unwrap().len() > 100, "{}", p.display());
        }
    }
}
