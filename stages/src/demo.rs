//! Small fur-free stages that demonstrate and test the engine.
//!
//! - `demo_numbers`: a seeded list of pseudo-random numbers (splitmix64, so the
//!   bytes depend only on `seed`, `count` and `scale`), one per line.
//! - `demo_sum`: sum and mean of `x^power` over a list of numbers; writes the
//!   sum and a `metrics.json` (what `fure sweep` tabulates).
//! - `demo_concat`: concatenates one or two text files.
//! - `demo_sleep`: waits `seconds` in `steps` steps, reporting progress; can
//!   fail on purpose (`fail = "error"` or `"panic"`) to exercise the engine's
//!   failure paths.
//!
//! None of them knows about caching; all are deterministic.

use std::fmt::Write as _;

use fure_stage_api::{ensure_finite, ParamSpec, Params, PortSpec, Stage, StageContext, StageError};

fn read_numbers(ctx: &StageContext<'_>, port: &str) -> Result<Vec<f64>, StageError> {
    let path = ctx.input(port)?;
    let text = std::fs::read_to_string(path).map_err(|e| StageError::io(path, e))?;
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
        .map(|(i, l)| {
            l.trim().parse::<f64>().map_err(|_| {
                StageError::input(
                    port,
                    path,
                    format!("line {}: expected a number, found `{}`", i + 1, l.trim()),
                )
            })
        })
        .collect()
}

fn write(ctx: &StageContext<'_>, port: &str, text: &str) -> Result<(), StageError> {
    let path = ctx.output(port)?;
    std::fs::write(path, text).map_err(|e| StageError::io(path, e))
}

fn splitmix64(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

fure_stage_api::stage_params! {
    /// `demo_numbers`'s parameters.
    pub struct DemoNumbersParams {
        /// random seed
        seed: i64 = int(1),
        /// how many numbers
        count: usize = int(100).range(0.0, 10_000_000.0),
        /// numbers are in [0, scale)
        scale: f64 = float(1.0).min(0.0),
    }
}

fure_stage_api::stage_params! {
    /// `demo_sum`'s parameters.
    pub struct DemoSumParams {
        /// exponent applied to each number
        power: f64 = float(1.0).range(0.0, 16.0),
    }
}

fure_stage_api::stage_params! {
    /// `demo_concat`'s parameters.
    pub struct DemoConcatParams {
        /// text put between a and b
        separator: String = string(""),
    }
}

fure_stage_api::param_enum! {
    /// Whether `demo_sleep` fails on purpose, and how.
    pub enum Fail {
        /// It does not.
        No = "no",
        /// It returns an error.
        Error = "error",
        /// It panics.
        Panic = "panic",
    }
}

fure_stage_api::stage_params! {
    /// `demo_sleep`'s parameters.
    pub struct DemoSleepParams {
        /// how long to wait
        seconds: f64 = float(1.0).range(0.0, 3600.0),
        /// progress steps
        steps: usize = int(10).range(1.0, 1_000_000.0),
        /// fail on purpose
        fail: Fail = string("no").choices(Fail::NAMES),
        /// text written to the output
        label: String = string(""),
    }
}

/// `demo_numbers`: seeded numbers in [0, scale).
pub struct DemoNumbersStage;

impl Stage for DemoNumbersStage {
    fn kind(&self) -> &'static str {
        "demo_numbers"
    }
    fn version(&self) -> u32 {
        1
    }
    fn doc(&self) -> &'static str {
        "Writes `count` seeded pseudo-random numbers in [0, scale), one per line (demo)."
    }
    fn params(&self) -> Vec<ParamSpec> {
        DemoNumbersParams::specs()
    }
    fn inputs(&self, _: &Params) -> Vec<PortSpec> {
        Vec::new()
    }
    fn outputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![PortSpec::file("numbers", "txt", "one number per line")]
    }
    fn run(&self, ctx: &StageContext<'_>) -> Result<(), StageError> {
        let p = DemoNumbersParams::from_params(ctx.params)?;
        let mut state = p.seed as u64;
        let count = p.count;
        let scale = p.scale;
        ctx.progress.set_total(count as u64);
        let mut s = String::with_capacity(count * 20);
        for i in 0..count {
            let u = (splitmix64(&mut state) >> 11) as f64 / (1u64 << 53) as f64;
            let _ = writeln!(s, "{}", u * scale);
            if (i + 1) % 4096 == 0 {
                ctx.progress.advance(4096);
            }
        }
        write(ctx, "numbers", &s)
    }
}

/// `demo_sum`: sum of powers, with metrics.
pub struct DemoSumStage;

impl Stage for DemoSumStage {
    fn kind(&self) -> &'static str {
        "demo_sum"
    }
    fn version(&self) -> u32 {
        1
    }
    fn doc(&self) -> &'static str {
        "Sums x^power over a list of numbers; writes the sum and metrics.json {sum, mean, count} (demo)."
    }
    fn params(&self) -> Vec<ParamSpec> {
        DemoSumParams::specs()
    }
    fn inputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![PortSpec::file("numbers", "txt", "one number per line")]
    }
    fn outputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![
            PortSpec::file("sum", "txt", "the sum"),
            PortSpec::file("metrics", "json", "sum, mean and count"),
        ]
    }
    fn run(&self, ctx: &StageContext<'_>) -> Result<(), StageError> {
        let power = DemoSumParams::from_params(ctx.params)?.power;
        let xs = read_numbers(ctx, "numbers")?;
        // Fixed order: a plain sequential sum is deterministic.
        let sum: f64 = xs.iter().map(|x| x.powf(power)).sum();
        let mean = if xs.is_empty() {
            0.0
        } else {
            sum / xs.len() as f64
        };
        ensure_finite("sum", [sum as f32, mean as f32])?;
        write(ctx, "sum", &format!("{sum}\n"))?;
        write(
            ctx,
            "metrics",
            &format!(
                "{{\n  \"sum\": {sum},\n  \"mean\": {mean},\n  \"count\": {}\n}}\n",
                xs.len()
            ),
        )
    }
}

/// `demo_concat`: joins text files.
pub struct DemoConcatStage;

impl Stage for DemoConcatStage {
    fn kind(&self) -> &'static str {
        "demo_concat"
    }
    fn version(&self) -> u32 {
        1
    }
    fn doc(&self) -> &'static str {
        "Concatenates text `a` and optional `b`, with `separator` between them (demo)."
    }
    fn params(&self) -> Vec<ParamSpec> {
        DemoConcatParams::specs()
    }
    fn inputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![
            PortSpec::file("a", "txt", "first text"),
            PortSpec::file("b", "txt", "second text").optional(),
        ]
    }
    fn outputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![PortSpec::file("text", "txt", "a, separator, b")]
    }
    fn run(&self, ctx: &StageContext<'_>) -> Result<(), StageError> {
        let read =
            |p: &std::path::Path| std::fs::read_to_string(p).map_err(|e| StageError::io(p, e));
        let mut s = read(ctx.input("a")?)?;
        if let Some(b) = ctx.input_opt("b") {
            s.push_str(&DemoConcatParams::from_params(ctx.params)?.separator);
            s.push_str(&read(b)?);
        }
        write(ctx, "text", &s)
    }
}

/// `demo_sleep`: waits, with progress; fails on request.
pub struct DemoSleepStage;

impl Stage for DemoSleepStage {
    fn kind(&self) -> &'static str {
        "demo_sleep"
    }
    fn version(&self) -> u32 {
        1
    }
    fn doc(&self) -> &'static str {
        "Waits `seconds` in `steps` steps with a progress bar, then writes `done`; \
         `fail = \"error\"` or `\"panic\"` makes it fail after waiting (demo, engine tests)."
    }
    fn params(&self) -> Vec<ParamSpec> {
        DemoSleepParams::specs()
    }
    fn inputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![PortSpec::file("after", "", "anything to wait for").optional()]
    }
    fn outputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![PortSpec::file("done", "txt", "the label")]
    }
    fn run(&self, ctx: &StageContext<'_>) -> Result<(), StageError> {
        let p = DemoSleepParams::from_params(ctx.params)?;
        let seconds = p.seconds;
        let steps = (p.steps as u64).max(1);
        ctx.progress.set_total(steps);
        ctx.progress.message("sleeping");
        for _ in 0..steps {
            ctx.progress.check_interrupted()?;
            std::thread::sleep(std::time::Duration::from_secs_f64(seconds / steps as f64));
            ctx.progress.advance(1);
        }
        match p.fail {
            Fail::Error => return Err(StageError::failed("failing on request (fail = \"error\")")),
            Fail::Panic => panic!("panicking on request (fail = \"panic\")"),
            Fail::No => {}
        }
        ctx.progress.note(&format!("slept {seconds}s"));
        write(ctx, "done", &format!("{}\n", p.label))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use fure_stage_api::NoProgress;
    use std::collections::BTreeMap;

    fn params(stage: &dyn Stage, set: &[(&str, fure_stage_api::Value)]) -> Params {
        let mut p: BTreeMap<String, fure_stage_api::Value> = stage
            .params()
            .into_iter()
            .filter_map(|s| s.default.map(|d| (s.name.to_string(), d)))
            .collect();
        for (k, v) in set {
            p.insert(k.to_string(), v.clone());
        }
        Params(p)
    }

    #[test]
    fn numbers_are_seeded_and_sum_reads_them() {
        let d = tempfile::tempdir().unwrap();
        let run_numbers = |seed: i64, name: &str| {
            let p = params(
                &DemoNumbersStage,
                &[
                    ("seed", fure_stage_api::Value::Int(seed)),
                    ("count", fure_stage_api::Value::Int(50)),
                ],
            );
            let out = d.path().join(name);
            let ctx = StageContext {
                name: "n",
                params: &p,
                inputs: BTreeMap::new(),
                outputs: BTreeMap::from([("numbers".to_string(), out.clone())]),
                progress: &NoProgress,
            };
            DemoNumbersStage.run(&ctx).unwrap();
            std::fs::read_to_string(out).unwrap()
        };
        let a = run_numbers(3, "a.txt");
        assert_eq!(a, run_numbers(3, "b.txt"));
        assert_ne!(a, run_numbers(4, "c.txt"));
        assert_eq!(a.lines().count(), 50);

        let p = params(&DemoSumStage, &[]);
        let ctx = StageContext {
            name: "s",
            params: &p,
            inputs: BTreeMap::from([("numbers".to_string(), d.path().join("a.txt"))]),
            outputs: BTreeMap::from([
                ("sum".to_string(), d.path().join("sum.txt")),
                ("metrics".to_string(), d.path().join("metrics.json")),
            ]),
            progress: &NoProgress,
        };
        DemoSumStage.run(&ctx).unwrap();
        let expect: f64 = a.lines().map(|l| l.parse::<f64>().unwrap()).sum();
        let got: f64 = std::fs::read_to_string(d.path().join("sum.txt"))
            .unwrap()
            .trim()
            .parse()
            .unwrap();
        assert_eq!(got, expect);
        let m: serde_json::Value =
            serde_json::from_slice(&std::fs::read(d.path().join("metrics.json")).unwrap()).unwrap();
        assert_eq!(m["count"], 50);
    }

    #[test]
    fn sum_rejects_bad_numbers_naming_the_line() {
        let d = tempfile::tempdir().unwrap();
        std::fs::write(d.path().join("n.txt"), "1\nx\n").unwrap();
        let p = params(&DemoSumStage, &[]);
        let ctx = StageContext {
            name: "s",
            params: &p,
            inputs: BTreeMap::from([("numbers".to_string(), d.path().join("n.txt"))]),
            outputs: BTreeMap::from([
                ("sum".to_string(), d.path().join("sum.txt")),
                ("metrics".to_string(), d.path().join("metrics.json")),
            ]),
            progress: &NoProgress,
        };
        let e = DemoSumStage.run(&ctx).unwrap_err().to_string();
        assert!(e.contains("line 2"), "{e}");
    }
}
