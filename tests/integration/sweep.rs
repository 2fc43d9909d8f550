//! Sweeps through the `fure` binary: one-at-a-time axes, variant status and
//! reasons, the sweep record and aggregate stages. Demo and `command` (`sh`)
//! stages only, on temporary directories.

use std::process::Output;

use super::engine::{data, signal_and_wait, Project};

/// `fure` through [`Project`], read as a sweep's output.
trait SweepRun {
    fn sweep(&self, args: &[&str]) -> Sweep;
}

impl SweepRun for Project {
    fn sweep(&self, args: &[&str]) -> Sweep {
        Sweep {
            out: self.fure(args),
        }
    }
}

struct Sweep {
    out: Output,
}

impl Sweep {
    fn code(&self) -> i32 {
        self.out.status.code().unwrap_or(-1)
    }
    fn stdout(&self) -> String {
        String::from_utf8_lossy(&self.out.stdout).into_owned()
    }
    fn all(&self) -> String {
        format!(
            "stdout:\n{}\nstderr:\n{}",
            self.stdout(),
            String::from_utf8_lossy(&self.out.stderr)
        )
    }
    /// The per-variant line printed for variant `i`.
    fn line(&self, i: usize) -> String {
        let head = format!("variant {i} (");
        self.stdout()
            .lines()
            .find(|l| l.starts_with(&head))
            .unwrap_or_else(|| panic!("no line for variant {i}:\n{}", self.all()))
            .to_string()
    }
}

fn json(text: &str) -> serde_json::Value {
    serde_json::from_str(text).expect("valid JSON")
}

#[test]
fn each_axes_statuses_record_and_aggregate() {
    let p = Project::new();
    std::fs::copy(data("sweep_each.toml"), p.path("sw.toml")).unwrap();
    let s = p.sweep(&["sweep", "sw.toml", "--jobs", "1"]);
    assert_eq!(s.code(), 0, "{}", s.all());
    let text = s.stdout();
    // 2 crossed points x (base + 2 more powers + 2 more modes).
    assert!(text.contains("sweep sw: 10 variants"), "{text}");
    assert!(
        text.contains("2 of 10 variants failed, 2 degraded"),
        "{text}"
    );
    // After every variant but the last: how long the rest would take at the pace so far.
    for done in 1..10 {
        let head = format!("sweep: {done} of 10 variants done in ");
        assert!(
            text.lines()
                .any(|l| l.starts_with(&head) && l.ends_with(" left at this pace")),
            "{text}"
        );
    }
    assert!(!text.contains("sweep: 10 of 10 variants done"), "{text}");

    // Upstream `gen` is computed once per crossed point, hit by the others.
    assert!(
        s.line(0).contains("4 ran, 0 cached, 0 failed"),
        "{}",
        s.line(0)
    );
    assert!(s.line(1).contains("1 ran, 3 cached"), "{}", s.line(1));
    // power 3 is `other`'s key: a hit.
    assert!(s.line(2).contains("0 ran, 4 cached"), "{}", s.line(2));
    assert!(
        s.line(3).contains("0 ran, 3 cached, 1 failed"),
        "{}",
        s.line(3)
    );
    assert!(
        s.line(4).contains("1 ran, 3 cached, 0 failed"),
        "{}",
        s.line(4)
    );
    assert!(s.line(5).contains("4 ran, 0 cached"), "{}", s.line(5));

    let record_text = p.read("out/sw/sweep.json");
    let r = json(&record_text);
    assert_eq!(r["pipeline"], "sw");
    assert_eq!(r["crossed"]["gen.scale"], json("[1.0, 2.0]"));
    assert_eq!(r["each"]["sq.power"], json("[1.0, 2.0, 3.0]"));
    assert_eq!(r["each_order"], json(r#"["sq.power", "check.env"]"#));
    let v = r["variants"].as_array().unwrap();
    assert_eq!(v.len(), 10);
    // Order and settings: every swept key in every variant, held ones included.
    let expect = [
        (1.0, 1.0, "ok", None),
        (1.0, 2.0, "ok", Some("sq.power")),
        (1.0, 3.0, "ok", Some("sq.power")),
        (1.0, 1.0, "fail", Some("check.env")),
        (1.0, 1.0, "warn", Some("check.env")),
        (2.0, 1.0, "ok", None),
    ];
    for (i, (scale, power, mode, varied)) in expect.iter().enumerate() {
        let st = &v[i]["settings"];
        assert_eq!(v[i]["index"], i, "{}", v[i]);
        assert_eq!(v[i]["name"], format!("sw@v{i}"));
        assert_eq!(st.as_object().unwrap().len(), 3, "{st}");
        assert_eq!(st["gen.scale"].as_f64(), Some(*scale), "{st}");
        assert_eq!(st["sq.power"].as_f64(), Some(*power), "{st}");
        assert_eq!(st["check.env"]["MODE"], *mode, "{st}");
        assert_eq!(v[i]["varied"].as_str(), *varied, "{}", v[i]);
    }
    // Statuses and reasons.
    for i in [0, 1, 2, 5] {
        assert_eq!(v[i]["status"], "ok", "{}", v[i]);
        assert_eq!(v[i]["reason"], "");
        assert!(v[i]["failed_stage"].is_null());
    }
    for i in [3, 8] {
        assert_eq!(v[i]["status"], "failed", "{}", v[i]);
        assert_eq!(v[i]["failed_stage"], "check");
        let why = v[i]["reason"].as_str().unwrap();
        assert!(why.starts_with("check: "), "{why}");
        assert!(why.contains("exited with status 3"), "{why}");
        assert!(why.contains("boom: bad mode"), "{why}");
        // The other branches of the failed variant still ran (or hit).
        assert!(v[i]["metrics"]["other.mean"].is_number(), "{}", v[i]);
        assert!(v[i]["metrics"]["sq.mean"].is_number(), "{}", v[i]);
    }
    for i in [4, 9] {
        assert_eq!(v[i]["status"], "degraded", "{}", v[i]);
        assert_eq!(v[i]["reason"], "check: x");
        assert_eq!(v[i]["warnings"], json(r#"["check: x"]"#));
    }
    assert!(s
        .line(3)
        .ends_with(&format!("failed ({})", v[3]["reason"].as_str().unwrap())));
    assert!(s.line(4).ends_with("degraded (check: x)"), "{}", s.line(4));
    // Metrics: numbers of every metrics.json, timings left out.
    let m = &v[0]["metrics"];
    assert_eq!(m["check.score"].as_f64(), Some(2.0), "{m}");
    assert!(m.get("check.wall_seconds").is_none(), "{m}");
    assert!(m.get("check.fit_time").is_none(), "{m}");
    assert_ne!(v[0]["metrics"]["sq.mean"], v[1]["metrics"]["sq.mean"]);
    // No absolute path anywhere in the record.
    assert!(
        !record_text.contains(p.path("").to_str().unwrap().trim_end_matches('/')),
        "{record_text}"
    );

    // Tables carry status and reason.
    let csv = p.read("out/sw/sweep.csv");
    let header: Vec<&str> = csv.lines().next().unwrap().split(',').collect();
    let col = |h: &str| header.iter().position(|x| *x == h).unwrap();
    let row3 = csv.lines().nth(4).unwrap();
    assert!(row3.contains(",failed,"), "{row3}");
    assert!(col("status") + 1 == col("reason"), "{csv}");
    assert!(p
        .read("out/sw/sweep.md")
        .contains("| degraded | check: x |"));

    // The aggregate ran once on the record.
    assert!(text.contains("aggregate summary: ran"), "{text}");
    assert_eq!(p.read("out/sw/summary/failed.txt").trim(), "2");
    assert_eq!(p.read("out/sw/summary/seen.json"), record_text);

    // A second sweep: the same record, byte for byte, and the aggregate is a hit.
    let s2 = p.sweep(&["sweep", "sw.toml", "--jobs", "1"]);
    assert_eq!(s2.code(), 0, "{}", s2.all());
    assert_eq!(p.read("out/sw/sweep.json"), record_text);
    assert!(
        s2.stdout().contains("aggregate summary: cached"),
        "{}",
        s2.all()
    );
    // Only the failing stage runs again.
    assert!(s2.line(0).contains("0 ran, 4 cached"), "{}", s2.line(0));
    assert!(
        s2.line(3).contains("0 ran, 3 cached, 1 failed"),
        "{}",
        s2.line(3)
    );

    // gc --keep of a sweep keeps every variant and the aggregate, and nothing
    // else: an ablation of one stage's parameter outside the sweep goes.
    let off = p.fure(&["run", "sw.toml", "--set", "other.power=5"]);
    assert_eq!(off.status.code(), Some(0));
    let g = p.fure(&["gc", "--keep", "sw.toml"]);
    let gc_text = String::from_utf8_lossy(&g.stdout);
    assert!(gc_text.contains("removed 1 entries"), "{gc_text}");
    let s_gc = p.sweep(&["sweep", "sw.toml", "--jobs", "1"]);
    assert!(s_gc.line(0).contains("0 ran, 4 cached"), "{}", s_gc.all());
    assert!(s_gc.line(9).contains("0 ran, 4 cached"), "{}", s_gc.all());
    assert!(
        s_gc.stdout().contains("aggregate summary: cached"),
        "{}",
        s_gc.all()
    );

    // --grid replaces an each axis's values; --each adds one.
    let grid = [
        "sweep",
        "sw.toml",
        "--grid",
        "sq.power=1,2",
        "--each",
        "other.power=3,4",
        "--table",
        "t3",
    ];
    let s3 = p.sweep(&grid);
    assert_eq!(s3.code(), 0, "{}", s3.all());
    assert!(
        s3.stdout().contains("sweep sw: 10 variants"),
        "{}",
        s3.all()
    );
    assert!(s3.line(4).contains("other.power=4"), "{}", s3.line(4));
    assert!(
        s3.stdout().contains("aggregate summary: ran"),
        "{}",
        s3.all()
    );

    // gc --keep also keeps what the last sweep's command line added: the
    // same grid afterwards runs nothing but the stage that always fails.
    let g3 = p.fure(&["gc", "--keep", "sw.toml"]);
    assert_eq!(g3.status.code(), Some(0), "{g3:?}");
    let s4 = p.sweep(&grid);
    assert_eq!(s4.code(), 0, "{}", s4.all());
    for i in 0..10 {
        assert!(s4.line(i).contains(": 0 ran, "), "{}", s4.all());
    }
    assert!(
        s4.stdout().contains("aggregate summary: cached"),
        "{}",
        s4.all()
    );
}

#[test]
fn a_failed_variant_keeps_going_and_later_variants_run() {
    let p = Project::new();
    p.write(
        "k.toml",
        r#"
[stages.bad]
kind = "command"
cmd = ["sh", "-c", "if [ \"$MODE\" = fail ]; then echo 'no convergence' >&2; exit 1; fi; echo 1 > out.txt"]
env = { MODE = "ok" }
outs = ["out.txt"]

[stages.after]
kind = "demo_sum"
inputs = { numbers = "bad.out.txt" }

[stages.late]
kind = "demo_numbers"
count = 5

[sweep.each]
"bad.env" = [{ MODE = "fail" }, { MODE = "ok" }]
"#,
    );
    // A dry run checks and lists the variants, runs and writes nothing.
    let d = p.sweep(&["sweep", "k.toml", "--dry-run"]);
    assert_eq!(d.code(), 0, "{}", d.all());
    assert!(
        d.line(1).contains("varying bad.env: 0 cached, 3 will run"),
        "{}",
        d.all()
    );
    assert!(!p.path("out").exists());
    let s = p.sweep(&["sweep", "k.toml", "--jobs", "1"]);
    assert_eq!(s.code(), 0, "{}", s.all());
    // `bad` fails first; `late` (independent, declared after it) still runs; `after` is skipped.
    assert!(
        s.line(0).contains("1 ran, 0 cached, 1 failed"),
        "{}",
        s.line(0)
    );
    assert!(s.line(0).contains("failed (bad: "), "{}", s.line(0));
    assert!(p.path("out/k@v0/late/numbers.txt").exists());
    assert!(!p.path("out/k@v0/after").exists());
    // The next variant ran to the end.
    assert!(
        s.line(1).contains("2 ran, 1 cached, 0 failed"),
        "{}",
        s.line(1)
    );
    assert!(s.line(1).ends_with(": ok"), "{}", s.line(1));
    assert!(s.stdout().contains("1 of 2 variants failed"), "{}", s.all());
    // Progress inside a variant: a line as it starts, then its stage lines.
    let out = s.stdout();
    let start = out
        .find("starting variant 1 (2 of 2): ")
        .unwrap_or_else(|| panic!("{}", s.all()));
    let done = out[start..]
        .find("done    after")
        .unwrap_or_else(|| panic!("{}", s.all()));
    assert!(out[start..start + done].lines().count() >= 2, "{}", s.all());
    assert!(out.contains("failed  bad  "), "{}", s.all());
    // --quiet: only the variant lines.
    let q = p.sweep(&["sweep", "k.toml", "--jobs", "1", "--quiet"]);
    assert!(!q.stdout().contains("starting variant"), "{}", q.all());
    assert!(q.line(1).ends_with(": ok"), "{}", q.all());
    let r = json(&p.read("out/k/sweep.json"));
    assert_eq!(r["variants"][0]["status"], "failed");
    assert_eq!(r["variants"][1]["status"], "ok");
    assert_eq!(r["each"]["bad.env"][0]["MODE"], "fail");
    assert!(r["crossed"].as_object().unwrap().is_empty());
}

#[test]
fn aggregate_errors_are_located_and_nothing_runs() {
    let p = Project::new();
    let base = r#"
[stages.gen]
kind = "demo_numbers"
count = 5

[sweep]
"gen.seed" = [1, 2]
"#;
    let cases = [
        // kind with a .txt input port
        (
            "[aggregate.r]\nkind = \"demo_sum\"\n",
            "a.toml:10:8: error: aggregate `r`: kind `demo_sum` must declare exactly one input port, a `.json` file",
        ),
        // a parameter checked like any stage's
        (
            "[aggregate.r]\nkind = \"command\"\ncmd = [\"true\"]\nouts = []\n",
            "stage `r` (kind `command`): parameter `outs`",
        ),
        // no inputs, no deps
        (
            "[aggregate.r]\nkind = \"command\"\ncmd = [\"true\"]\nouts = [\"x\"]\ninputs = { a = \"gen.numbers\" }\n",
            "a.toml:13:",
        ),
        (
            "[aggregate.r]\nkind = \"command\"\ncmd = [\"true\"]\nouts = [\"x\"]\ndeps = [\"gen.numbers\"]\n",
            "a.toml:13:1: error: aggregate `r` (kind `command`): `deps` is set by the engine",
        ),
        // the name of a stage
        (
            "[aggregate.gen]\nkind = \"command\"\ncmd = [\"true\"]\nouts = [\"x\"]\n",
            "a.toml:9:12: error: aggregate `gen` has the name of a stage",
        ),
        (
            "[aggregate.r]\nkind = \"nope\"\n",
            "a.toml:10:8: error: stage `r`: unknown kind `nope`",
        ),
    ];
    for (agg, want) in cases {
        p.write("a.toml", &format!("{base}\n{agg}"));
        let s = p.sweep(&["sweep", "a.toml"]);
        assert_eq!(s.code(), 2, "{agg}\n{}", s.all());
        assert!(s.all().contains(want), "{agg}\nwant {want}\n{}", s.all());
        assert!(!p.path("out/a@v0").exists(), "nothing runs: {}", s.all());
    }
    // A failing aggregate is a failed stage: exit 1, after every variant ran.
    p.write(
        "a.toml",
        &format!(
            "{base}\n[aggregate.r]\nkind = \"command\"\ncmd = [\"sh\", \"-c\", \"echo no >&2; exit 4\"]\nouts = [\"x\"]\n"
        ),
    );
    let s = p.sweep(&["sweep", "a.toml"]);
    assert_eq!(s.code(), 1, "{}", s.all());
    assert!(s.stdout().contains("0 of 2 variants failed"), "{}", s.all());
    assert!(
        s.all().contains("aggregate stage `r` (command) failed"),
        "{}",
        s.all()
    );
}

#[test]
fn each_axes_merge_through_extends() {
    let p = Project::new();
    p.write(
        "parent.toml",
        r#"
[stages.gen]
kind = "demo_numbers"
count = 5
[stages.sum]
kind = "demo_sum"
inputs = { numbers = "gen.numbers" }
[sweep]
"gen.count" = [5, 6]
[sweep.each]
"gen.seed" = [1, 2]
"sum.power" = [1.0, 2.0]
[aggregate.r]
kind = "command"
cmd = ["sh", "-c", "cp {deps.sweep} r.json"]
outs = ["r.json"]
"#,
    );
    p.write(
        "child.toml",
        r#"
extends = "parent.toml"
[sweep]
"gen.seed" = [3]
[sweep.each]
"gen.count" = [5, 7, 8]
"sum.power" = [1.0, 3.0, 4.0]
[aggregate.r]
cmd = ["sh", "-c", "cp {deps.sweep} r.json # child"]
"#,
    );
    let s = p.sweep(&["sweep", "child.toml"]);
    assert_eq!(s.code(), 0, "{}", s.all());
    // gen.seed crossed (1 value); each: sum.power (kept position), gen.count (moved) -> 1 + 2 + 2.
    assert!(
        s.stdout().contains("sweep child: 5 variants"),
        "{}",
        s.all()
    );
    let r = json(&p.read("out/child/r/r.json"));
    assert_eq!(r["each_order"], json(r#"["sum.power", "gen.count"]"#));
    assert_eq!(r["crossed"], json(r#"{"gen.seed": [3]}"#));
    assert_eq!(r["variants"][1]["varied"], "sum.power");
    assert_eq!(r["variants"][4]["settings"]["gen.count"], 8);
}

#[test]
fn linked_keys_costs_and_publish() {
    let p = Project::new();
    p.write(
        "pipes/lk.toml",
        r#"[pipeline]
name = "lk"

[stages.a]
kind = "demo_numbers"
count = 5

[stages.b]
kind = "demo_numbers"
count = 5

[sweep]
"a.scale,b.scale" = [1.0, 3.0]

[aggregate.report]
kind = "command"
cmd = ["sh", "-c", "printf '# R\n<!-- fure:provenance -->\nend\n' > results.md; mkdir charts; cp {deps.sweep} charts/record.json"]
outs = ["results.md", "charts/"]

[publish]
"report.results.md" = "../docs/results.md"
"report.charts" = "../docs/charts"
"#,
    );
    let s = p.sweep(&["sweep", "pipes/lk.toml", "--jobs", "1"]);
    assert_eq!(s.code(), 0, "{}", s.all());
    assert!(s.stdout().contains("sweep lk: 2 variants"), "{}", s.all());
    let r = json(&p.read("out/lk/sweep.json"));
    // One axis, two targets: both stages take each value.
    let v1 = &r["variants"][1];
    assert_eq!(v1["settings"]["a.scale,b.scale"], 3.0, "{r}");
    assert_eq!(
        p.read("out/lk@v1/a/numbers.txt"),
        p.read("out/lk@v1/b/numbers.txt")
    );
    assert_ne!(
        p.read("out/lk@v0/a/numbers.txt"),
        p.read("out/lk@v1/a/numbers.txt")
    );
    // Costs of every stage's cache entry.
    assert!(v1["costs"]["a"]["seconds"].as_f64().unwrap() >= 0.0, "{r}");
    assert!(v1["costs"]["b"]["peak_rss_bytes"].is_u64(), "{r}");
    // Published next to the pipeline's directory, the Markdown stamped.
    let md = p.read("docs/results.md");
    assert!(md.starts_with("# R\nGenerated "), "{md}");
    assert!(
        md.contains("by `fure sweep pipes/lk.toml --jobs 1`"),
        "{md}"
    );
    assert!(md.ends_with("end\n"), "{md}");
    assert_eq!(json(&p.read("docs/charts/record.json")), r);

    // A sweep changed on the command line (one value of the axis, another setting) reports under
    // `out` and leaves the published documents alone: they describe the pipeline as declared.
    for flags in [
        &["--grid", "a.scale,b.scale=2.0"][..],
        &["--set", "a.count=4"][..],
    ] {
        let s = p.sweep(&[&["sweep", "pipes/lk.toml", "--jobs", "1"][..], flags].concat());
        assert_eq!(s.code(), 0, "{}", s.all());
        assert!(
            s.stdout()
                .contains(&format!("not published: {} changed the sweep", flags[0])),
            "{}",
            s.all()
        );
        assert_eq!(p.read("docs/results.md"), md);
        assert_eq!(json(&p.read("docs/charts/record.json")), r);
        assert_ne!(json(&p.read("out/lk/sweep.json")), r);
    }

    // A sweep with a failed variant (a full disk, a broken scene) leaves the published documents
    // as they were, unless --publish-failed asks for a report with failures.
    p.write(
        "pipes/lkf.toml",
        r#"extends = "lk.toml"

[stages.c]
kind = "command"
cmd = ["sh", "-c", "if [ \"$MODE\" = fail ]; then echo 'disk full' >&2; exit 1; fi; echo 1 > out.txt"]
outs = ["out.txt"]

[sweep]
"c.env" = [{ MODE = "ok" }, { MODE = "fail" }]
"#,
    );
    let s = p.sweep(&["sweep", "pipes/lkf.toml", "--jobs", "1"]);
    assert!(s.stdout().contains("variants failed"), "{}", s.all());
    assert!(
        s.stdout().contains("not published: ")
            && s.stdout().contains("variants failed (--publish-failed"),
        "{}",
        s.all()
    );
    assert_eq!(p.read("docs/results.md"), md);
    assert_eq!(json(&p.read("docs/charts/record.json")), r);
    let s = p.sweep(&["sweep", "pipes/lkf.toml", "--jobs", "1", "--publish-failed"]);
    assert!(s.stdout().contains("published "), "{}", s.all());
    assert_ne!(json(&p.read("docs/charts/record.json")), r);
    assert!(
        json(&p.read("docs/charts/record.json"))["variants"]
            .as_array()
            .unwrap()
            .iter()
            .any(|v| v["status"] == "failed"),
        "{}",
        p.read("docs/charts/record.json")
    );

    // A publish key naming no aggregate is a located usage error; nothing runs.
    p.write(
        "pipes/bad.toml",
        "extends = \"lk.toml\"\n[publish]\n\"nope.results\" = \"x.md\"\n",
    );
    let s = p.sweep(&["sweep", "pipes/bad.toml"]);
    assert_eq!(s.code(), 2, "{}", s.all());
    assert!(
        s.all()
            .contains("bad.toml:3:1: publish `nope.results`: no aggregate stage `nope`"),
        "{}",
        s.all()
    );

    // A section destination whose file lacks the markers fails before anything runs, naming
    // the file and the marker expected.
    p.write("docs/README.md", "# no markers\n");
    p.write(
        "pipes/bad.toml",
        "extends = \"lk.toml\"\n[publish]\n\"report.results.md\" = \"../docs/README.md#head\"\n",
    );
    let s = p.sweep(&["sweep", "pipes/bad.toml"]);
    assert_eq!(s.code(), 2, "{}", s.all());
    assert!(
        s.all()
            .contains("README.md: expected exactly one line `<!-- fure:begin head -->`")
            && s.all().contains("(0 begin and 0 end markers)"),
        "{}",
        s.all()
    );
    assert!(!p.path("out/bad").exists(), "{}", s.all());
}

/// Two busy processes beside a sweep (not its children): every stage run records the cores
/// other work used, in its cache entry and in the sweep record the report reads, and the sweep
/// says so.
#[test]
fn other_work_beside_a_stage_is_recorded_with_its_cost() {
    if std::fs::metadata("/proc/stat").is_err() {
        return; // only Linux says how busy the machine is
    }
    let p = Project::new();
    p.write(
        "busy.toml",
        r#"[pipeline]
name = "busy"

[stages.wait]
kind = "command"
cmd = ["sh", "-c", "sleep 1.2; echo $N > w.txt"]
outs = ["w.txt"]

[sweep]
"wait.env" = [{ N = "1" }, { N = "2" }]
"#,
    );
    let spinners: Vec<std::process::Child> = (0..2)
        .map(|_| {
            std::process::Command::new("sh")
                .args(["-c", "while :; do :; done"])
                .spawn()
                .unwrap()
        })
        .collect();
    let s = p.sweep(&["sweep", "busy.toml", "--jobs", "1"]);
    for mut c in spinners {
        let _ = c.kill();
        let _ = c.wait();
    }
    assert_eq!(s.code(), 0, "{}", s.all());
    let r = json(&p.read("out/busy/sweep.json"));
    for v in r["variants"].as_array().unwrap() {
        // The two spinners use the cores the sleeping stage leaves (two on CI, at least one
        // anywhere); the stage's own shell and sleep are not counted (they are the stage's).
        let load = v["costs"]["wait"]["other_load"].as_f64().unwrap_or(-1.0);
        assert!(load >= 0.8, "{load} in {r}");
    }
    assert!(
        s.stdout()
            .contains("note: 2 stage run(s) were measured beside other work"),
        "{}",
        s.all()
    );
}

/// SIGTERM during a sweep: the running in-process stage stops between two of its steps, no
/// later variant starts, nothing is cached or left in staging, and the last complete sweep's
/// record stays as it was.
#[test]
fn an_interrupted_sweep_stops_soon_and_keeps_the_last_record() {
    use std::process::Stdio;
    use std::time::{Duration, Instant};
    let p = Project::new();
    p.write(
        "s.toml",
        r#"
[stages.wait]
kind = "demo_sleep"
seconds = 0.01
steps = 1

[sweep]
"wait.label" = ["a", "b"]
"#,
    );
    let s = p.sweep(&["sweep", "s.toml", "--jobs", "1", "--quiet"]);
    assert_eq!(s.code(), 0, "{}", s.all());
    let before = p.read("out/s/sweep.json");
    // Each variant now waits ten minutes, in steps of a tenth of a second.
    let child = p
        .cmd(&[
            "sweep",
            "s.toml",
            "--jobs",
            "1",
            "--quiet",
            "--grid",
            "wait.seconds=600",
            "--grid",
            "wait.steps=6000",
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let staging = |p: &Project| {
        std::fs::read_dir(p.path("cache/tmp"))
            .map(|d| d.count())
            .unwrap_or(0)
    };
    let t = Instant::now();
    while staging(&p) == 0 {
        assert!(
            t.elapsed() < Duration::from_secs(30),
            "the stage never started"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let (out, took) = signal_and_wait(child, "TERM");
    assert!(took < Duration::from_secs(10), "fure took {took:?}");
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert_eq!(out.status.code(), Some(143), "{stdout}\n{stderr}");
    assert!(stderr.contains("interrupted by SIGTERM"), "{stderr}");
    assert!(stderr.contains("0 of 2 variants complete"), "{stderr}");
    assert!(
        stdout.contains("stopped: the run was interrupted"),
        "{stdout}"
    );
    assert!(!stdout.contains("variant 1 ("), "{stdout}");
    assert_eq!(p.read("out/s/sweep.json"), before);
    assert_eq!(staging(&p), 0);
}

#[test]
fn a_sweep_stops_at_a_full_disk_and_says_so() {
    // Every variant runs the same command, which cannot fit on the disk: three variants (the
    // first fails, two are never started) and one (the last fails: no record either).
    for (labels, said) in [
        (
            r#"["a", "b", "c"]"#,
            "0 of 3 variants complete (cached), 2 not started",
        ),
        (
            r#"["a"]"#,
            "0 of 1 variants complete (cached), the previous record",
        ),
    ] {
        let p = Project::new();
        p.write(
            "s.toml",
            &format!(
                r#"
[stages.wait]
kind = "demo_sleep"
seconds = 0.01
steps = 1

[stages.fill]
kind = "command"
cmd = ["sh", "-c", "head -c 300000 /dev/zero > big.bin"]
outs = ["big.bin"]

[sweep]
"wait.label" = {labels}
"#
            ),
        );
        let Some(out) = p.on_a_full_disk("sweep s.toml --jobs 1 --quiet", "", "small/cache") else {
            eprintln!("skipped: no private tmpfs here");
            return;
        };
        let (stdout, stderr) = (
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr),
        );
        assert_eq!(out.status.code(), Some(1), "{stdout}\n{stderr}");
        assert!(stdout.contains("No space left on device"), "{stdout}");
        assert!(
            stderr.contains("stopped, the disk is full (variant 0 failed on it)"),
            "{stderr}"
        );
        assert!(stderr.contains(said), "{stderr}");
        assert!(stderr.contains("fure gc"), "{stderr}");
        assert!(!stdout.contains("variant 1 ("), "{stdout}");
        assert!(!p.path("out/s/sweep.json").exists());
    }
}

/// The costs of a record's variants left out: what differs between machines.
fn without_costs(mut r: serde_json::Value) -> serde_json::Value {
    for v in r["variants"].as_array_mut().unwrap() {
        v.as_object_mut().unwrap().remove("costs");
    }
    r
}

/// Three machines that share no cache: two run a shard of a sweep each, a third merges the
/// shard files into the record one machine's whole sweep writes, runs the aggregate on it and
/// publishes, its stamp naming where each shard ran. Shards that are not the whole sweep as
/// given (one missing, another sweep's, edited, from a dirty tree) are refused by name.
#[test]
fn a_sweep_in_shards_merges_into_the_whole_sweeps_record() {
    let pipeline = r#"[pipeline]
name = "sh"

[stages.a]
kind = "demo_numbers"
count = 5

[stages.s]
kind = "demo_sum"
inputs = { numbers = "a.numbers" }

[sweep]
"a.scale" = [1.0, 2.0, 3.0]

[aggregate.report]
kind = "command"
cmd = ["sh", "-c", "printf '# R\n<!-- fure:provenance -->\n' > results.md; cp {deps.sweep} record.json"]
outs = ["results.md", "record.json"]

[publish]
"report.results.md" = "../docs/results.md"
"#;
    let machines: Vec<Project> = (0..4).map(|_| Project::new()).collect();
    for m in &machines {
        m.write("pipes/sh.toml", pipeline);
    }
    let [whole, one, two, merger] = &machines[..] else {
        unreachable!()
    };
    let s = whole.sweep(&["sweep", "pipes/sh.toml", "--jobs", "1"]);
    assert_eq!(s.code(), 0, "{}", s.all());
    let record = json(&whole.read("out/sh/sweep.json"));

    for (m, k) in [(one, "1/2"), (two, "2/2")] {
        let s = m.sweep(&["sweep", "pipes/sh.toml", "--jobs", "1", "--shard", k]);
        assert_eq!(s.code(), 0, "{}", s.all());
        assert!(s.stdout().contains(&format!("shard {k}: ")), "{}", s.all());
        // No aggregate ran, nothing was published, no whole record was written.
        assert!(!m.path("out/sh/report").exists(), "{}", s.all());
        assert!(!m.path("docs/results.md").exists(), "{}", s.all());
        assert!(!m.path("out/sh/sweep.json").exists(), "{}", s.all());
    }
    // Variants 0 and 2 in shard 1 of 2, variant 1 in shard 2.
    let first = json(&one.read("out/sh/shards/1-of-2.json"));
    let indices: Vec<u64> = first["variants"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v["index"].as_u64().unwrap())
        .collect();
    assert_eq!(indices, [0, 2], "{first}");
    assert_eq!(first["shard"]["variants"], 3, "{first}");

    let shard_texts = [
        one.read("out/sh/shards/1-of-2.json"),
        two.read("out/sh/shards/2-of-2.json"),
    ];
    merger.write("kept/1-of-2.json", &shard_texts[0]);
    merger.write("kept/2-of-2.json", &shard_texts[1]);
    let merge = |files: &[&str], extra: &[&str]| {
        let mut args = vec!["sweep", "pipes/sh.toml", "--merge"];
        args.extend(files);
        args.extend(extra);
        merger.sweep(&args)
    };
    let both = ["kept/2-of-2.json", "kept/1-of-2.json"];
    let s = merge(&both, &[]);
    assert_eq!(s.code(), 0, "{}", s.all());
    let merged = json(&merger.read("out/sh/sweep.json"));
    assert_eq!(
        without_costs(merged.clone()),
        without_costs(record),
        "{}",
        s.all()
    );
    assert_eq!(json(&merger.read("out/sh/report/record.json")), merged);
    let md = merger.read("docs/results.md");
    assert!(
        md.contains("Its variants ran in shards: shard 1/2 by `fure sweep pipes/sh.toml --jobs 1 --shard 1/2`")
            && md.contains("; shard 2/2 by `fure sweep pipes/sh.toml --jobs 1 --shard 2/2`"),
        "{md}"
    );

    // Refused, each naming what is wrong; nothing is written over the merged record.
    let refused = |s: &Sweep, want: &str| {
        assert_eq!(s.code(), 2, "{}", s.all());
        assert!(s.all().contains(want), "want {want:?}: {}", s.all());
        assert_eq!(json(&merger.read("out/sh/sweep.json")), merged);
    };
    refused(&merge(&both[..1], &[]), "shards missing: 1/2");
    refused(
        &merge(&[both[0], both[0]], &[]),
        "shard 2/2 is also given as kept/2-of-2.json",
    );
    // The pipeline as given differs from the one the shards ran.
    refused(
        &merge(&both, &["--set", "a.count=6"]),
        "kept/2-of-2.json: `shard.fingerprint`: made from another sweep",
    );
    // Edited or damaged files, and a shard made from a tree with uncommitted changes.
    for (edit, want) in [
        (
            ("\"a.scale\": 2.0", "\"a.scale\": 2.5"),
            "kept/bad.json: `variants[0]`: `settings`: not variant 1's settings",
        ),
        (
            ("\"dirty\": false", "\"dirty\": true"),
            "`shard.origin.dirty`: made from a tree with uncommitted changes",
        ),
        (
            ("\"index\": 1", "\"index\": 0"),
            "`variants[0]`: variant 0 is not one of shard 2/2's",
        ),
        (("\"k\": 2", "\"k\": 3"), "`shard`: 3/2 is no shard"),
        (("{", "["), "kept/bad.json: not JSON"),
    ] {
        assert!(shard_texts[1].contains(edit.0), "{}", shard_texts[1]);
        merger.write("kept/bad.json", &shard_texts[1].replacen(edit.0, edit.1, 1));
        refused(&merge(&[both[1], "kept/bad.json"], &[]), want);
    }
}
