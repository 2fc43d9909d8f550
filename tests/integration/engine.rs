//! Engine tests through the `fure` binary: caching, reasons, errors, crash
//! safety, corruption, concurrency, sweeps and command stages. They use only
//! the demo stages and `command` stages (`sh`), on temporary directories.

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

pub(crate) fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/engine")
        .join(name)
}

/// Sends `kill -SIG` (`"TERM"`, `"INT"`, ...) to a running fure and waits for it: its output
/// and how long it took to end after the signal.
pub(crate) fn signal_and_wait(child: std::process::Child, sig: &str) -> (Output, Duration) {
    let t = Instant::now();
    let k = Command::new("kill")
        .args([&format!("-{sig}"), &child.id().to_string()])
        .status()
        .unwrap();
    assert!(k.success(), "kill -{sig}");
    let out = child.wait_with_output().unwrap();
    (out, t.elapsed())
}

/// A project directory with its own cache (shared by the other integration modules).
pub(crate) struct Project {
    dir: tempfile::TempDir,
}

impl Project {
    pub(crate) fn new() -> Project {
        Project {
            dir: tempfile::tempdir().expect("temp dir"),
        }
    }
    pub(crate) fn path(&self, rel: &str) -> PathBuf {
        self.dir.path().join(rel)
    }
    pub(crate) fn write(&self, rel: &str, text: &str) {
        let p = self.path(rel);
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(p, text).unwrap();
    }
    pub(crate) fn read(&self, rel: &str) -> String {
        std::fs::read_to_string(self.path(rel)).unwrap_or_else(|e| panic!("{rel}: {e}"))
    }
    pub(crate) fn cmd(&self, args: &[&str]) -> Command {
        let mut c = Command::new(env!("CARGO_BIN_EXE_fure"));
        c.args(args)
            .current_dir(self.dir.path())
            .env("FURE_CACHE", self.path("cache"));
        c
    }
    pub(crate) fn fure(&self, args: &[&str]) -> Output {
        self.cmd(args).output().expect("run fure")
    }
    /// Runs `sh -c "FURE_COMMAND; AFTER"` in the project directory, in a private mount
    /// namespace where `small/` is a 64 KiB tmpfs (a full disk) and with the cache at
    /// `cache` (under `small/` to put it on that disk). `None` where the test may not create
    /// such a namespace (the caller skips its case).
    pub(crate) fn on_a_full_disk(
        &self,
        fure_args: &str,
        after: &str,
        cache: &str,
    ) -> Option<Output> {
        std::fs::create_dir_all(self.path("small")).unwrap();
        let script = format!(
            "mount -t tmpfs -o size=64k tmpfs small || exit 99; {} {fure_args}; c=$?; {after} exit $c",
            env!("CARGO_BIN_EXE_fure")
        );
        let out = Command::new("unshare")
            .args(["-rm", "sh", "-c", &script])
            .current_dir(self.dir.path())
            .env("FURE_CACHE", self.path(cache))
            .output();
        match out {
            Ok(out) if out.status.code() != Some(99) && !out.stderr.starts_with(b"unshare") => {
                Some(out)
            }
            _ => None,
        }
    }
    /// `fure run` with a report; returns (exit code, stage -> (status, reason), full report).
    pub(crate) fn run(&self, pipeline: &str, extra: &[&str]) -> Run {
        let report = self.path("report.json");
        let _ = std::fs::remove_file(&report);
        let mut args = vec![
            "run",
            pipeline,
            "--report",
            report.to_str().unwrap(),
            "--plain",
        ];
        args.extend_from_slice(extra);
        let out = self.fure(&args);
        let json: serde_json::Value = std::fs::read(&report)
            .ok()
            .and_then(|b| serde_json::from_slice(&b).ok())
            .unwrap_or(serde_json::Value::Null);
        let mut stages = BTreeMap::new();
        if let Some(list) = json["stages"].as_array() {
            for s in list {
                stages.insert(
                    s["name"].as_str().unwrap().to_string(),
                    (
                        s["status"].as_str().unwrap().to_string(),
                        s["reason"].as_str().unwrap_or("").to_string(),
                    ),
                );
            }
        }
        Run { out, stages, json }
    }
}

pub(crate) struct Run {
    pub(crate) out: Output,
    pub(crate) stages: BTreeMap<String, (String, String)>,
    pub(crate) json: serde_json::Value,
}

impl Run {
    pub(crate) fn code(&self) -> i32 {
        self.out.status.code().unwrap_or(-1)
    }
    pub(crate) fn stdout(&self) -> String {
        String::from_utf8_lossy(&self.out.stdout).into_owned()
    }
    pub(crate) fn stderr(&self) -> String {
        String::from_utf8_lossy(&self.out.stderr).into_owned()
    }
    pub(crate) fn status(&self, stage: &str) -> &str {
        self.stages
            .get(stage)
            .map(|s| s.0.as_str())
            .unwrap_or("absent")
    }
    pub(crate) fn reason(&self, stage: &str) -> &str {
        self.stages.get(stage).map(|s| s.1.as_str()).unwrap_or("")
    }
    /// Names of the stages with this status.
    pub(crate) fn with(&self, status: &str) -> Vec<&str> {
        self.stages
            .iter()
            .filter(|(_, s)| s.0 == status)
            .map(|(n, _)| n.as_str())
            .collect()
    }
    pub(crate) fn ok(&self) -> &Self {
        assert_eq!(
            self.code(),
            0,
            "stdout:\n{}\nstderr:\n{}",
            self.stdout(),
            self.stderr()
        );
        self
    }
}

const CHAIN: &str = r#"
[pipeline]
name = "chain"

[stages.gen]
kind = "demo_numbers"
count = 30

[stages.a]
kind = "demo_sum"
inputs = { numbers = "gen.numbers" }

[stages.b]
kind = "demo_sum"
power = 2.0
inputs = { numbers = "data/nums.txt" }

[stages.c]
kind = "demo_concat"
separator = "|"
inputs = { a = "a.sum", b = "b.sum" }
"#;

fn chain_project() -> Project {
    let p = Project::new();
    p.write("chain.toml", CHAIN);
    p.write("data/nums.txt", "1\n2\n3\n");
    p
}

#[test]
fn reruns_only_what_changed() {
    let p = chain_project();
    let r = p.run("chain.toml", &[]);
    r.ok();
    assert_eq!(r.with("ran"), ["a", "b", "c", "gen"]);
    assert_eq!(r.reason("gen"), "new stage");
    // Outputs are materialised; c = a.sum | b.sum with b = 1 + 4 + 9.
    let c = std::fs::read_to_string(p.path("out/chain/c/text.txt")).unwrap();
    assert!(c.ends_with("|14\n"), "{c}");

    let r = p.run("chain.toml", &[]);
    r.ok();
    assert_eq!(r.with("cached").len(), 4, "{:?}", r.stages);

    // A parameter: gen and its dependents rerun, b stays cached.
    let r = p.run("chain.toml", &["--set", "gen.seed=5"]);
    r.ok();
    assert_eq!(r.with("ran"), ["a", "c", "gen"]);
    assert_eq!(r.status("b"), "cached");
    assert_eq!(r.reason("gen"), "parameter seed changed from 1 to 5");
    assert!(
        r.reason("a")
            .contains("input numbers changed (gen.numbers)"),
        "{}",
        r.reason("a")
    );

    // An input file: b and c rerun.
    p.write("data/nums.txt", "1\n2\n4\n");
    let r = p.run("chain.toml", &["--set", "gen.seed=5"]);
    r.ok();
    assert_eq!(r.with("ran"), ["b", "c"]);
    assert!(
        r.reason("b")
            .contains("input numbers changed (data/nums.txt)"),
        "{}",
        r.reason("b")
    );
    let c = std::fs::read_to_string(p.path("out/chain/c/text.txt")).unwrap();
    assert!(c.ends_with("|21\n"), "{c}");

    // Going back to the first parameters is a pure cache hit for gen and a.
    let r = p.run("chain.toml", &[]);
    r.ok();
    assert_eq!(r.status("gen"), "cached");
    assert_eq!(r.status("a"), "cached");
}

#[test]
fn early_cutoff_keeps_dependents_cached() {
    let p = Project::new();
    let pipe = |tag: &str| {
        format!(
            r#"
[stages.up]
kind = "command"
cmd = ["sh", "-c", "printf '3\n4\n' > nums.txt  # {tag}"]
outs = ["nums.txt"]

[stages.down]
kind = "demo_sum"
inputs = {{ numbers = "up.nums.txt" }}
"#
        )
    };
    p.write("p.toml", &pipe("first"));
    p.run("p.toml", &[]).ok();
    p.write("p.toml", &pipe("second"));
    let r = p.run("p.toml", &[]);
    r.ok();
    assert_eq!(r.status("up"), "ran");
    assert!(
        r.reason("up").contains("parameter cmd changed"),
        "{}",
        r.reason("up")
    );
    assert_eq!(r.status("down"), "cached");
    assert!(
        r.reason("down").contains("early cutoff"),
        "{}",
        r.reason("down")
    );
}

#[test]
fn status_explains_why() {
    let p = chain_project();
    let s = p.fure(&["status", "chain.toml"]);
    let text = String::from_utf8_lossy(&s.stdout);
    assert!(text.contains("new stage"), "{text}");
    p.run("chain.toml", &[]).ok();
    let s = p.fure(&["status", "chain.toml"]);
    let text = String::from_utf8_lossy(&s.stdout);
    assert!(text.contains("4 cached, 0 will run"), "{text}");
    p.write("data/nums.txt", "5\n");
    let s = p.fure(&[
        "status",
        "chain.toml",
        "--set",
        "a.power=3",
        "--set",
        "gen.count=31",
    ]);
    let text = String::from_utf8_lossy(&s.stdout);
    assert!(
        text.contains("parameter count changed from 30 to 31"),
        "{text}"
    );
    assert!(
        text.contains("parameter power changed from 1.0 to 3.0"),
        "{text}"
    );
    assert!(text.contains("input from `gen`, which will run"), "{text}");
    assert!(
        text.contains("input numbers changed (data/nums.txt)"),
        "{text}"
    );
    // status runs nothing.
    let r = p.run("chain.toml", &["--dry-run"]);
    assert_eq!(r.with("will_run"), ["b", "c"]);
}

#[test]
fn bad_pipelines_are_located_and_nothing_runs() {
    let p = Project::new();
    let run = |file: &str| {
        let out = p.fure(&["run", data(file).to_str().unwrap()]);
        (
            out.status.code(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    let (code, err) = run("bad_toml.toml");
    assert_eq!(code, Some(2));
    assert!(
        err.contains("bad_toml.toml:6:9: error: invalid TOML"),
        "{err}"
    );

    let (code, err) = run("cycle.toml");
    assert_eq!(code, Some(2));
    assert!(err.contains("dependency cycle: a -> b -> a"), "{err}");
    assert!(
        err.contains("cycle.toml:10:16: error: dependency cycle"),
        "{err}"
    );

    let (code, err) = run("mistakes.toml");
    assert_eq!(code, Some(2));
    for want in [
        "mistakes.toml:6:1: error: stage `gen`: parameter `count`: expected integer, found string",
        "mistakes.toml:7:1: error: stage `gen`: unknown parameter `colour`",
        "mistakes.toml:10:8: error: stage `sum`: unknown kind `demo_summ`",
        "has no input port `c`",
        "missing input `a`",
        "mistakes.toml:18:22: error: stage `cat` (kind `demo_concat`) has no output `txt` (expected one of: `text`)",
    ] {
        assert!(err.contains(want), "missing `{want}` in:\n{err}");
    }
    assert!(!p.path("out").exists(), "nothing may run");

    // A bad --set is a usage error too.
    let out = p.fure(&[
        "run",
        data("base.toml").to_str().unwrap(),
        "--set",
        "nope.x=1",
    ]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("no stage `nope`"));
}

#[test]
fn extends_overrides_and_moving_the_project_keeps_hits() {
    let p = Project::new();
    for f in ["base.toml", "ablation.toml"] {
        std::fs::copy(data(f), p.path(f)).unwrap();
    }
    p.run("base.toml", &[]).ok();
    let r = p.run("ablation.toml", &[]);
    r.ok();
    assert_eq!(r.json["pipeline"], "ablation");
    assert_eq!(r.status("gen"), "cached");
    assert_eq!(r.status("sum"), "cached");
    assert_eq!(r.status("squares"), "ran");
    assert!(p.path("out/ablation/squares/metrics.json").exists());

    // Another directory, same cache: every stage hits.
    let q = Project::new();
    for f in ["base.toml", "ablation.toml"] {
        std::fs::copy(data(f), q.path(f)).unwrap();
    }
    let mut c = q.cmd(&["run", "base.toml", "--plain"]);
    c.env("FURE_CACHE", p.path("cache"));
    let out = c.output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("0 ran, 3 cached"), "{text}");
}

#[test]
fn command_stages_run_fail_and_cache_nothing_on_failure() {
    let p = Project::new();
    p.write("in.txt", "7\n8\n");
    p.write(
        "cmd.toml",
        r#"
[stages.gen]
kind = "demo_numbers"
count = 3

[stages.both]
kind = "command"
cmd = ["sh", "-c", "cat {deps.file} {deps.gen} > all.txt && mkdir -p parts && cp {deps.file} parts/x.txt"]
deps = { file = "in.txt", gen = "gen.numbers" }
outs = ["all.txt", "parts/"]

[stages.count]
kind = "command"
cmd = ["sh", "-c", "wc -l < {deps.0} | tr -d ' ' > n.txt"]
deps = ["both.all.txt"]
outs = ["n.txt"]
"#,
    );
    let r = p.run("cmd.toml", &[]);
    r.ok();
    assert_eq!(
        std::fs::read_to_string(p.path("out/cmd/count/n.txt")).unwrap(),
        "5\n"
    );
    assert_eq!(
        std::fs::read_to_string(p.path("out/cmd/both/parts/x.txt")).unwrap(),
        "7\n8\n"
    );
    assert_eq!(p.run("cmd.toml", &[]).with("cached").len(), 3);

    p.write(
        "fail.toml",
        r#"
[stages.boom]
kind = "command"
cmd = ["sh", "-c", "echo partial > out.txt; echo 'something went wrong' >&2; exit 3"]
outs = ["out.txt"]

[stages.lazy]
kind = "command"
cmd = ["true"]
outs = ["never.txt"]
"#,
    );
    let r = p.run("fail.toml", &["--keep-going"]);
    assert_eq!(r.code(), 1);
    assert_eq!(r.status("boom"), "failed");
    assert_eq!(r.status("lazy"), "failed");
    let err = r.stderr();
    assert!(err.contains("exited with status 3"), "{err}");
    assert!(err.contains("something went wrong"), "{err}");
    assert!(
        err.contains("did not create its declared output `never.txt`"),
        "{err}"
    );
    // Nothing was cached: they run again.
    let r = p.run("fail.toml", &["--keep-going"]);
    assert_eq!(r.status("boom"), "failed");
    let s = p.fure(&["status", "fail.toml"]);
    assert!(String::from_utf8_lossy(&s.stdout).contains("0 cached, 2 will run"));
}

#[test]
fn a_failing_stage_names_its_inputs_as_the_pipeline_does() {
    // A stage reads its upstream inputs from a staging directory inside the cache that is
    // removed once it fails: its message names them by the output they came from instead.
    let p = Project::new();
    p.write(
        "names.toml",
        r#"
[stages.make]
kind = "command"
cmd = ["sh", "-c", "echo 7 > a.txt"]
outs = ["a.txt"]

[stages.check]
kind = "command"
cmd = ["sh", "-c", "echo \"unexpected value in {deps.a}\" >&2; exit 2"]
deps = { a = "make.a.txt" }
outs = ["n.txt"]
"#,
    );
    let r = p.run("names.toml", &[]);
    assert_eq!(r.code(), 1);
    assert_eq!(r.status("check"), "failed");
    let err = r.stderr();
    assert!(err.contains("unexpected value in make.a.txt"), "{err}");
    assert!(
        !err.contains("cache/tmp") && !err.contains("/in/a/"),
        "a staging path in the message: {err}"
    );
}

#[test]
fn a_panicking_stage_is_a_failure_without_backtrace() {
    let p = Project::new();
    p.write(
        "panic.toml",
        "[stages.p]\nkind = \"demo_sleep\"\nseconds = 0.0\nfail = \"panic\"\n[stages.after]\nkind = \"demo_sleep\"\nseconds = 0.0\ninputs = { after = \"p.done\" }\n",
    );
    let r = p.run("panic.toml", &[]);
    assert_eq!(r.code(), 1);
    assert_eq!(r.status("p"), "failed");
    assert_eq!(r.status("after"), "skipped");
    let err = r.stderr();
    assert!(err.contains("panicked: panicking on request"), "{err}");
    assert!(!err.contains("RUST_BACKTRACE"), "{err}");
}

#[test]
fn kill_9_mid_stage_then_rerun_and_verify_clean() {
    let p = Project::new();
    p.write(
        "slow.toml",
        "[stages.quick]\nkind = \"demo_numbers\"\ncount = 5\n\
         [stages.slow]\nkind = \"demo_sleep\"\nseconds = 2.0\nsteps = 4\nlabel = \"slept\"\ninputs = { after = \"quick.numbers\" }\n",
    );
    let mut child = p
        .cmd(&["run", "slow.toml", "--plain"])
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    // Wait until the slow stage is running, then kill -9.
    let stdout = child.stdout.take().unwrap();
    let mut lines = BufReader::new(stdout).lines();
    let t = Instant::now();
    loop {
        let line = lines.next().expect("fure printed nothing").unwrap();
        if line.starts_with("run     slow") {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(30));
    }
    std::thread::sleep(Duration::from_millis(300));
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();
    // A staging directory is left; no entry for `slow`.
    let r = p.run("slow.toml", &[]);
    r.ok();
    assert_eq!(r.status("quick"), "cached");
    assert_eq!(r.status("slow"), "ran");
    assert_eq!(
        std::fs::read_to_string(p.path("out/slow/slow/done.txt")).unwrap(),
        "slept\n"
    );
    let v = p.fure(&["verify"]);
    let text = String::from_utf8_lossy(&v.stdout);
    assert_eq!(v.status.code(), Some(0), "{text}");
    assert!(
        text.contains(
            "0 corrupted objects, 0 entries dropped, 0 invalid manifests, 0 stray paths; clean"
        ),
        "{text}"
    );
    // gc removes the dead run's leftovers and keeps the entries.
    let g = p.fure(&["gc"]);
    assert!(String::from_utf8_lossy(&g.stdout).contains("kept 2 entries"));
    assert_eq!(std::fs::read_dir(p.path("cache/tmp")).unwrap().count(), 0);
}

#[test]
fn a_corrupted_object_is_detected_and_recomputed() {
    let p = chain_project();
    let r = p.run("chain.toml", &[]);
    r.ok();
    let hash = r.json["stages"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["name"] == "a")
        .unwrap()["outputs"]["sum"]["blake3"]
        .as_str()
        .unwrap()
        .to_string();
    let obj = p.path("cache/objects").join(&hash[..2]).join(&hash[2..]);
    let good = std::fs::read(&obj).unwrap();
    let mut bad = good.clone();
    bad[0] ^= 1;
    std::fs::remove_file(&obj).unwrap(); // (objects are read-only; out/ links keep the old inode)
    std::fs::write(&obj, &bad).unwrap();
    let r = p.run("chain.toml", &[]);
    r.ok();
    assert_eq!(r.status("a"), "ran");
    assert!(r.reason("a").contains("corrupted"), "{}", r.reason("a"));
    assert!(
        r.stdout().contains("warning: a: cached entry"),
        "{}",
        r.stdout()
    );
    // Same bytes as before, so c stays cached (early cutoff), and the object is whole again.
    assert_eq!(r.status("c"), "cached");
    assert_eq!(std::fs::read(&obj).unwrap(), good);
    let v = p.fure(&["verify"]);
    assert_eq!(v.status.code(), Some(0));

    // verify finds and drops a corruption that no run has seen.
    let hash_b = r.json["stages"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["name"] == "b")
        .unwrap()["outputs"]["sum"]["blake3"]
        .as_str()
        .unwrap()
        .to_string();
    let obj_b = p
        .path("cache/objects")
        .join(&hash_b[..2])
        .join(&hash_b[2..]);
    std::fs::remove_file(&obj_b).unwrap();
    std::fs::write(&obj_b, b"garbage").unwrap();
    let v = p.fure(&["verify"]);
    let text = String::from_utf8_lossy(&v.stdout);
    assert_eq!(v.status.code(), Some(1), "{text}");
    assert!(
        text.contains("1 corrupted objects, 1 entries dropped"),
        "{text}"
    );
    let r = p.run("chain.toml", &[]);
    assert_eq!(r.status("b"), "ran");
    assert!(
        r.reason("b").contains("no cache entry"),
        "{}",
        r.reason("b")
    );
}

#[test]
fn two_concurrent_runs_share_one_cache() {
    let p = Project::new();
    let mut text = String::new();
    for i in 0..6 {
        text.push_str(&format!(
            "[stages.s{i}]\nkind = \"command\"\ncmd = [\"sh\", \"-c\", \"sleep 0.2; echo {i} > o.txt\"]\nouts = [\"o.txt\"]\n"
        ));
    }
    text.push_str("[stages.all]\nkind = \"command\"\ncmd = [\"sh\", \"-c\", \"cat {deps.0} {deps.5} > all.txt\"]\ndeps = [\"s0.o.txt\", \"s1.o.txt\", \"s2.o.txt\", \"s3.o.txt\", \"s4.o.txt\", \"s5.o.txt\"]\nouts = [\"all.txt\"]\n");
    p.write("par.toml", &text);
    let spawn = |report: &str| {
        p.cmd(&[
            "run", "par.toml", "--plain", "--jobs", "2", "--report", report,
        ])
        .stdout(Stdio::null())
        .spawn()
        .unwrap()
    };
    let mut a = spawn("ra.json");
    let mut b = spawn("rb.json");
    assert!(a.wait().unwrap().success());
    assert!(b.wait().unwrap().success());
    let ran = |f: &str| {
        let j: serde_json::Value =
            serde_json::from_slice(&std::fs::read(p.path(f)).unwrap()).unwrap();
        j["stages"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|s| s["status"] == "ran")
            .count()
    };
    // Every stage computed exactly once between the two runs.
    assert_eq!(ran("ra.json") + ran("rb.json"), 7);
    assert_eq!(
        std::fs::read_to_string(p.path("out/par/all/all.txt")).unwrap(),
        "0\n5\n"
    );
    let v = p.fure(&["verify"]);
    assert_eq!(
        v.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&v.stdout)
    );
}

#[test]
fn sweep_shares_upstream_entries_and_writes_a_table() {
    let p = Project::new();
    std::fs::copy(data("base.toml"), p.path("base.toml")).unwrap();
    let out = p.fure(&["sweep", "base.toml", "--grid", "squares.power=1,2,3"]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert_eq!(
        out.status.code(),
        Some(0),
        "{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // Variant 0 computes gen and sum; its `squares` (power 1) has `sum`'s key, so it is a hit
    // (computed by the concurrent stage or found after it). Later variants compute only `squares`.
    assert!(
        text.contains("variant 0 (squares.power=1): 2 ran, 1 cached"),
        "{text}"
    );
    assert!(
        text.contains("variant 1 (squares.power=2): 1 ran, 2 cached"),
        "{text}"
    );
    assert!(
        text.contains("variant 2 (squares.power=3): 1 ran, 2 cached"),
        "{text}"
    );
    let csv = std::fs::read_to_string(p.path("out/base/sweep.csv")).unwrap();
    let rows: Vec<&str> = csv.lines().collect();
    assert_eq!(rows.len(), 4, "{csv}");
    assert!(
        rows[0].contains("squares.power") && rows[0].contains("squares.mean"),
        "{csv}"
    );
    assert!(p.path("out/base/sweep.md").exists());
    // Metrics differ between variants.
    let mean_col = rows[0]
        .split(',')
        .position(|h| h == "squares.mean")
        .unwrap();
    let means: Vec<&str> = rows[1..]
        .iter()
        .map(|r| r.split(',').nth(mean_col).unwrap())
        .collect();
    assert_ne!(means[0], means[1]);
}

#[test]
fn dag_stages_until_and_gc() {
    let p = chain_project();
    let d = p.fure(&["dag", "chain.toml", "--format", "dot"]);
    let dot = String::from_utf8_lossy(&d.stdout);
    assert!(dot.contains("\"gen\" -> \"a\""), "{dot}");
    let m = p.fure(&["dag", "chain.toml", "--format", "mermaid"]);
    assert!(String::from_utf8_lossy(&m.stdout).starts_with("flowchart LR"));
    let s = p.fure(&["stages", "command"]);
    assert!(String::from_utf8_lossy(&s.stdout).contains("outs: array of strings (required)"));

    let r = p.run("chain.toml", &["--until", "a"]);
    r.ok();
    assert_eq!(r.with("ran"), ["a", "gen"]);
    p.run("chain.toml", &[]).ok();
    // A different parameter creates more entries; gc --keep keeps only the current ones.
    p.run("chain.toml", &["--set", "gen.seed=9"]).ok();
    let g = p.fure(&["gc", "--keep", "chain.toml"]);
    let text = String::from_utf8_lossy(&g.stdout);
    assert!(text.contains("kept 4 entries "), "{text}");
    assert!(text.contains("removed 3 entries"), "{text}");
    // out/ still links the seed-9 run's outputs: gc says their bytes stay on disk.
    assert!(text.contains("stay on disk"), "{text}");
    let r = p.run("chain.toml", &[]);
    assert_eq!(r.with("cached").len(), 4);
    // With no outputs linking them, every removed byte is freed.
    std::fs::remove_dir_all(p.path("out")).unwrap();
    let g = p.fure(&["gc", "--max-size", "0"]);
    let text = String::from_utf8_lossy(&g.stdout);
    assert!(text.contains("kept 0 entries"), "{text}");
    assert!(!text.contains("stay on disk"), "{text}");
}
