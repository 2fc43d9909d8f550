//! The benchmark report's targets: the first method's figures read against the goals the
//! project set for it (issue 15), one table per split, so that whether a goal holds on every
//! test scene is read off one place instead of gathered from each scene's section.
//!
//! The table reads the report's own machine-readable figures (the `scenes` and `verdicts` of
//! its metrics.json), never the runs, so it cannot disagree with the tables it summarises. Each
//! goal is a rule over those figures, and a cell says `met`, `missed`, `undecided` (one seed:
//! the seed-spread rule cannot judge) or `-` (the figure is absent):
//!
//! - **At least another method** (`target_against`: dense and the fixed-length ablation by
//!   default): the first method's signed F at 2, 3 and 4 cm by the suite's verdicts, met when
//!   none is lost. A tie is inside the seed spread, no evidence of being behind, so it meets a
//!   goal of "at least". The strict 1 cm score is reported beside the ceiling, not judged: the
//!   goal is to report it.
//! - **Not below the untrained start**: the first method's and dense's final F (3 cm,
//!   unsigned, the snapshots' scoring) against their own untrained starts, met when neither
//!   is lost.
//! - **Speed-up** (`target_speedup`, 10): to dense's final 3 cm F in wall time, met when the
//!   first method reached it in every seed and the mean ratio is at least the target; `-`
//!   where dense's own start already reaches its final F in every seed (no ratio exists).
//! - **Direction error** (`target_direction_deg`, 20): the mean in-plane error at most the
//!   target.
//! - **Shape** (`target_curvature_ratio`, 2): the local curvature variance over the GT's
//!   within a factor of the target either way; `-` where the report does not judge the ratio
//!   (short grooms, straight GT strands). The cell adds the same ratio for the GT redrawn with
//!   the method's points per strand (evaluate's `gt_at_points`): the goal is read against the
//!   GT, and this says how far a perfect strand at that resolution would sit from it.

use std::fmt::Write;

use serde_json::{json, Map, Value as Json};

use super::benchmark::{fmt_stat, stat_from_json};

/// The goals the targets table reads the first method against.
#[derive(Debug, Clone, PartialEq)]
pub struct Goals {
    /// Methods (by name) the first must match or beat at 2, 3 and 4 cm.
    pub against: Vec<String>,
    /// The least speed-up to dense's final 3 cm F.
    pub speedup: f64,
    /// The largest mean in-plane direction error, degrees.
    pub direction_deg: f64,
    /// The curvature variance over the GT's must lie within this factor either way.
    pub curvature_ratio: f64,
}

/// A goal's state on one scene.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Status {
    Met,
    Missed,
    Undecided,
    NotJudged,
}

impl Status {
    pub fn label(self) -> &'static str {
        match self {
            Status::Met => "met",
            Status::Missed => "missed",
            Status::Undecided => "undecided",
            Status::NotJudged => "-",
        }
    }
}

/// One cell: the goal's state and the figures behind it.
struct Cell {
    status: Status,
    detail: String,
}

impl Cell {
    fn new(status: Status, detail: impl Into<String>) -> Self {
        Cell {
            status,
            detail: detail.into(),
        }
    }

    fn markdown(&self) -> String {
        match self.status {
            Status::NotJudged => "-".into(),
            s => format!("{} ({})", s.label(), self.detail),
        }
    }
}

/// The goals after the "at least" ones, in the table's column order.
const OTHER_GOALS: [&str; 4] = [
    "untrained start",
    "speed-up",
    "direction error",
    "curvature",
];

/// The verdict thresholds the "at least" goals read: 2, 3 and 4 cm.
const AGAINST_THRESHOLDS: [&str; 3] = ["2cm_20deg", "3cm_30deg", "4cm_40deg"];

/// A verdict as a cell shows it: "undecided (1 seed)" is the one way to be undecided, so
/// "1 seed" says it.
fn short_verdict(label: &str) -> &str {
    if label.starts_with("undecided") {
        "1 seed"
    } else {
        label
    }
}

/// The first method against `other` on `scene`, from the report's verdicts.
fn against(verdicts: &Json, scene: &str, other: &str) -> Cell {
    let v = &verdicts[format!("{scene}|{other}")];
    let labels: Vec<Option<&str>> = AGAINST_THRESHOLDS.iter().map(|t| v[*t].as_str()).collect();
    if labels.iter().any(Option::is_none) {
        return Cell::new(Status::NotJudged, "");
    }
    let labels: Vec<&str> = labels.into_iter().flatten().collect();
    let status = if labels.contains(&"lost") {
        Status::Missed
    } else if labels.iter().any(|l| l.starts_with("undecided")) {
        Status::Undecided
    } else {
        Status::Met
    };
    let short: Vec<&str> = labels.iter().map(|l| short_verdict(l)).collect();
    Cell::new(status, short.join(", "))
}

/// Both learners' final F against their untrained starts (the scene's `speedup` figures).
fn untrained_start(speedup: &Json) -> Cell {
    let (Some(first), Some(dense)) = (
        speedup["codec_against_start"].as_str(),
        speedup["dense_against_start"].as_str(),
    ) else {
        return Cell::new(Status::NotJudged, "");
    };
    let status = if first == "lost" || dense == "lost" {
        Status::Missed
    } else if first.starts_with("undecided") || dense.starts_with("undecided") {
        Status::Undecided
    } else {
        Status::Met
    };
    Cell::new(
        status,
        format!("{} / {}", short_verdict(first), short_verdict(dense)),
    )
}

/// The speed-up to dense's final 3 cm F against the target.
fn speedup(speedup: &Json, target: f64) -> Cell {
    let seeds = speedup["seeds"].as_u64().unwrap_or(0);
    let reached = speedup["reached"].as_u64().unwrap_or(0);
    let Some(ratio) = stat_from_json(&speedup["ratio"]) else {
        return Cell::new(Status::NotJudged, "");
    };
    let text = fmt_stat(Some(ratio), 1);
    if reached < seeds {
        return Cell::new(
            Status::Missed,
            format!("{text}; reached in {reached} of {seeds} seeds"),
        );
    }
    let status = if ratio.mean >= target {
        Status::Met
    } else {
        Status::Missed
    };
    Cell::new(status, text)
}

/// A figure whose mean must satisfy `ok`.
fn bounded(figure: &Json, digits: usize, ok: impl Fn(f64) -> bool) -> Cell {
    match stat_from_json(figure) {
        None => Cell::new(Status::NotJudged, ""),
        Some(s) => Cell::new(
            if ok(s.mean) {
                Status::Met
            } else {
                Status::Missed
            },
            fmt_stat(Some(s), digits),
        ),
    }
}

/// Writes one targets table per split (scenes in `order`, as `(scene, split)`) from the
/// report's `scenes` and `verdicts`; returns each scene's goal states (`{scene: {goal:
/// state}}`).
pub fn write_targets(
    md: &mut String,
    order: &[(&str, &str)],
    scenes: &Json,
    verdicts: &Json,
    first: &str,
    goals: &Goals,
) -> Json {
    let mut states = Map::new();
    let r = goals.curvature_ratio;
    for split in ["dev", "test", "unsplit"] {
        let in_split: Vec<&str> = order
            .iter()
            .filter(|(_, s)| *s == split)
            .map(|(name, _)| *name)
            .collect();
        if in_split.is_empty() {
            continue;
        }
        let _ = writeln!(md, "## Targets, {split} split: {first}\n");
        let mut head = "| scene |".to_string();
        let mut rule = "|---|".to_string();
        for o in &goals.against {
            let _ = write!(head, " at least {o} (2 / 3 / 4 cm) |");
            rule.push_str("---|");
        }
        let _ = writeln!(
            md,
            "{head} not below its untrained start ({first} / dense) | speed-up to dense's final F (at least {}) | direction error (at most {}°) | curvature var. / GT ({:.2}–{}) | strict 1 cm F (ceiling) |\n{rule}---|---|---|---|---|",
            goals.speedup, goals.direction_deg, 1.0 / r, r
        );
        // Goal name -> scenes missing it, in order.
        let mut missed: Vec<(String, Vec<&str>)> = Vec::new();
        for name in &in_split {
            let sc = &scenes[*name];
            let fm = &sc[first];
            let mut cells: Vec<(String, Cell)> = goals
                .against
                .iter()
                .map(|o| (format!("against {o}"), against(verdicts, name, o)))
                .collect();
            let [start_goal, speed_goal, direction_goal, curvature_goal] = OTHER_GOALS;
            cells.push((start_goal.into(), untrained_start(&sc["speedup"])));
            cells.push((speed_goal.into(), speedup(&sc["speedup"], goals.speedup)));
            cells.push((
                direction_goal.into(),
                bounded(&fm["direction_error_deg"], 1, |m| m <= goals.direction_deg),
            ));
            let mut curvature = bounded(&fm["curvature_variance_vs_gt"], 2, |m| {
                m >= 1.0 / r && m <= r
            });
            if let (Some(exact), Some(points)) = (
                stat_from_json(&fm["gt_at_points_curvature_vs_gt"]),
                stat_from_json(&fm["points_per_strand"]),
            ) {
                // Learners give every strand of a scene one count: a spread only when seeds differ.
                let points = match points.sd {
                    Some(sd) if sd > 0.0 => fmt_stat(Some(points), 0),
                    _ => format!("{:.0}", points.mean),
                };
                let _ = write!(
                    curvature.detail,
                    "; the GT at {points} points: {}",
                    fmt_stat(Some(exact), 2)
                );
            }
            cells.push((curvature_goal.into(), curvature));
            let strict = format!(
                "{} ({})",
                fmt_stat(stat_from_json(&fm["signed_f_1cm_10deg"]), 1),
                fmt_stat(stat_from_json(&sc["ceiling"]["signed_f_1cm_10deg"]), 1)
            );
            let mut row = format!("| {name} |");
            let mut sj = Map::new();
            for (goal, cell) in &cells {
                let _ = write!(row, " {} |", cell.markdown());
                sj.insert(goal.clone(), cell.status.label().into());
                if cell.status == Status::Missed {
                    match missed.iter_mut().find(|(g, _)| g == goal) {
                        Some((_, s)) => s.push(name),
                        None => missed.push((goal.clone(), vec![name])),
                    }
                }
            }
            let _ = writeln!(md, "{row} {strict} |");
            states.insert((*name).to_string(), sj.into());
        }
        // In the table's column order.
        missed.sort_by_key(|(g, _)| {
            goals
                .against
                .iter()
                .map(|o| format!("against {o}"))
                .chain(OTHER_GOALS.iter().map(|c| c.to_string()))
                .position(|name| &name == g)
        });
        let summary = if missed.is_empty() {
            format!("every goal met or not judged on every {split} scene")
        } else {
            missed
                .iter()
                .map(|(g, s)| format!("{g} ({})", s.join(", ")))
                .collect::<Vec<_>>()
                .join("; ")
        };
        let _ = writeln!(
            md,
            "\nMissed on the {split} split: {summary}. A goal of \"at least\" is met when no \
             threshold is lost by the seed-spread rule (a tie is not evidence of being behind); \
             the speed-up needs the first method to reach dense's final F in every seed \
             (evaluation::targets).\n"
        );
    }
    json!(states)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn goals() -> Goals {
        Goals {
            against: vec!["dense".into(), "fixed".into()],
            speedup: 10.0,
            direction_deg: 20.0,
            curvature_ratio: 2.0,
        }
    }

    fn stat(mean: f64, sd: f64) -> Json {
        json!({"mean": mean, "sd": sd, "n": 3})
    }

    fn scene(direction: f64, curvature: Json, ratio: Json, reached: u64) -> Json {
        json!({
            "split": "test",
            "A": {"direction_error_deg": stat(direction, 0.5), "curvature_variance_vs_gt": curvature,
                  "signed_f_1cm_10deg": stat(48.6, 2.1)},
            "ceiling": {"signed_f_1cm_10deg": stat(96.9, 0.1)},
            "speedup": {"ratio": ratio, "reached": reached, "seeds": 3,
                        "codec_against_start": "tie", "dense_against_start": "won"},
        })
    }

    #[test]
    fn each_goal_is_read_by_its_rule() {
        let mut scenes = json!({
            "panda": scene(17.0, stat(2.8, 0.3), stat(78.8, 27.2), 3),
            "bison": scene(24.0, stat(0.9, 0.1), stat(8.0, 1.0), 3),
            "wolf": scene(12.0, Json::Null, stat(40.0, 5.0), 2),
        });
        // The GT redrawn at the method's points per strand is shown beside the ratio; the goal
        // stays the ratio against the GT (the bison's, met, reads 0.9 whatever the redrawn GT's).
        scenes["bison"]["A"]["gt_at_points_curvature_vs_gt"] = stat(3.1, 0.2);
        scenes["bison"]["A"]["points_per_strand"] = json!({"mean": 8.0, "sd": 0.0, "n": 3});
        let v = |a: &str, b: &str, c: &str| json!({"1cm_10deg": "won", "2cm_20deg": a, "3cm_30deg": b, "4cm_40deg": c});
        let verdicts = json!({
            "panda|dense": v("won", "won", "tie"), "panda|fixed": v("tie", "tie", "tie"),
            "bison|dense": v("won", "won", "won"), "bison|fixed": v("lost", "lost", "tie"),
            "wolf|dense": v("undecided (1 seed)", "won", "won"),
        });
        let order = [("panda", "test"), ("bison", "test"), ("wolf", "test")];
        let mut md = String::new();
        let s = write_targets(&mut md, &order, &scenes, &verdicts, "A", &goals());
        assert_eq!(s["panda"]["against dense"], "met", "{s}");
        assert_eq!(s["panda"]["against fixed"], "met");
        assert_eq!(s["bison"]["against fixed"], "missed");
        assert_eq!(s["wolf"]["against dense"], "undecided");
        // The wolf has no verdicts against the fixed length: not judged, not met.
        assert_eq!(s["wolf"]["against fixed"], "-");
        assert_eq!(s["panda"]["untrained start"], "met");
        assert_eq!(s["panda"]["speed-up"], "met");
        assert_eq!(s["bison"]["speed-up"], "missed");
        // Reached in 2 seeds of 3: missed whatever the ratio.
        assert_eq!(s["wolf"]["speed-up"], "missed");
        assert_eq!(s["bison"]["direction error"], "missed");
        assert_eq!(s["panda"]["direction error"], "met");
        assert_eq!(s["panda"]["curvature"], "missed");
        assert_eq!(s["bison"]["curvature"], "met");
        assert_eq!(s["wolf"]["curvature"], "-");
        assert!(md.contains("## Targets, test split: A"), "{md}");
        assert!(
            md.contains("| panda | met (won, won, tie) | met (tie, tie, tie) | met (tie / won) | met (78.8 ± 27.2) | met (17.0 ± 0.5) | missed (2.80 ± 0.30) | 48.6 ± 2.1 (96.9 ± 0.1) |"),
            "{md}"
        );
        assert!(
            md.contains("| met (0.90 ± 0.10; the GT at 8 points: 3.10 ± 0.20) |"),
            "{md}"
        );
        assert!(
            md.contains("missed (40.0 ± 5.0; reached in 2 of 3 seeds)"),
            "{md}"
        );
        assert!(
            md.contains("Missed on the test split: against fixed (bison); speed-up (bison, wolf); direction error (bison); curvature (panda)."),
            "{md}"
        );
        assert!(!md.contains("dev split"));
    }

    #[test]
    fn a_lost_start_misses_and_one_seed_is_undecided() {
        let lost = json!({"codec_against_start": "tie", "dense_against_start": "lost"});
        assert_eq!(untrained_start(&lost).status, Status::Missed);
        let one =
            json!({"codec_against_start": "undecided (1 seed)", "dense_against_start": "won"});
        let cell = untrained_start(&one);
        assert_eq!(cell.status, Status::Undecided);
        assert_eq!(cell.detail, "1 seed / won");
        assert_eq!(untrained_start(&json!({})).status, Status::NotJudged);
    }
}
