//! The cache and command outputs are untrusted (issue 16): outputs are
//! stored without following links, every path read from the cache is
//! validated, materialisation failures fail the run, placeholders have a
//! grammar, signals reach the children, non-regular inputs are refused.
//! Each test is a case that once went wrong silently.

use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::engine::{signal_and_wait, Project};

/// The manifest path of the entry a stage resolved to in the last report.
fn manifest_of(p: &Project, run: &crate::engine::Run, stage: &str) -> PathBuf {
    let key = run.json["stages"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["name"] == stage)
        .unwrap_or_else(|| panic!("no stage {stage}"))["key"]
        .as_str()
        .unwrap()
        .to_string();
    p.path("cache/entries").join(format!("{key}.json"))
}

fn read_manifest(path: &Path) -> fure::cache::Manifest {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

/// Rewrites a manifest, resealed: only path and hash validation can catch it.
fn tamper(path: &Path, edit: impl FnOnce(&mut fure::cache::Manifest)) {
    let mut m = read_manifest(path);
    edit(&mut m);
    let m = m.seal();
    std::fs::write(path, serde_json::to_vec_pretty(&m).unwrap()).unwrap();
}

fn mode(p: &Path) -> u32 {
    std::fs::metadata(p).unwrap().mode() & 0o777
}

/// No symbolic link anywhere under `root`.
fn assert_no_links(root: &Path) {
    for e in walk(root) {
        let md = std::fs::symlink_metadata(&e).unwrap();
        assert!(
            !md.file_type().is_symlink(),
            "link in the cache: {}",
            e.display()
        );
    }
}

fn walk(root: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    if let Ok(rd) = std::fs::read_dir(root) {
        for e in rd.flatten() {
            let p = e.path();
            if e.file_type().unwrap().is_dir() {
                out.extend(walk(&p));
            }
            out.push(p);
        }
    }
    out
}

#[test]
fn links_in_command_outputs_are_refused_and_their_targets_untouched() {
    let p = Project::new();
    p.write("outside/a.txt", "keep me\n");
    p.write("outside/sub/b.txt", "me too\n");
    let outside = p.path("outside");
    let o = outside.display();
    p.write(
        "links.toml",
        &format!(
            r#"
[stages.dir_is_link]
kind = "command"
cmd = ["sh", "-c", "rmdir d && ln -s {o} d"]
outs = ["d/"]

[stages.link_inside]
kind = "command"
cmd = ["sh", "-c", "echo x > d/x.txt && ln -s {o}/sub d/sub"]
outs = ["d/"]

[stages.file_is_link]
kind = "command"
cmd = ["ln", "-s", "{o}/a.txt", "f.txt"]
outs = ["f.txt"]
"#
        ),
    );
    let r = p.run("links.toml", &["--keep-going"]);
    assert_eq!(r.code(), 1, "{}", r.stderr());
    for s in ["dir_is_link", "link_inside", "file_is_link"] {
        assert_eq!(r.status(s), "failed", "{s}");
    }
    let err = r.stderr();
    assert!(err.contains("symbolic link"), "{err}");
    // The targets are where they were, unchanged and still writable.
    assert_eq!(p.read("outside/a.txt"), "keep me\n");
    assert_eq!(p.read("outside/sub/b.txt"), "me too\n");
    assert_eq!(mode(&outside.join("a.txt")) & 0o200, 0o200);
    assert_no_links(&p.path("cache"));
    assert_eq!(walk(&p.path("cache/entries")).len(), 0);
}

#[test]
fn a_hard_linked_output_is_copied_never_made_read_only() {
    let p = Project::new();
    p.write("outside/b.txt", "shared inode\n");
    let b = p.path("outside/b.txt");
    p.write(
        "hard.toml",
        &format!(
            "[stages.hard]\nkind = \"command\"\ncmd = [\"ln\", \"{}\", \"h.txt\"]\nouts = [\"h.txt\"]\n",
            b.display()
        ),
    );
    let r = p.run("hard.toml", &[]);
    r.ok();
    assert_eq!(mode(&b), 0o644, "the outside file was chmod-ed");
    assert_eq!(std::fs::metadata(&b).unwrap().nlink(), 1);
    assert_eq!(p.read("out/hard/hard/h.txt"), "shared inode\n");
    // Changing the outside file does not change the cached object.
    std::fs::write(&b, "changed\n").unwrap();
    let v = p.fure(&["verify"]);
    assert_eq!(
        v.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&v.stdout)
    );
    assert_eq!(p.read("out/hard/hard/h.txt"), "shared inode\n");
}

const TWO: &str = r#"
[stages.f]
kind = "command"
cmd = ["sh", "-c", "echo file > o.txt"]
outs = ["o.txt"]

[stages.d]
kind = "command"
cmd = ["sh", "-c", "mkdir -p d/s && echo one > d/x.txt && echo two > d/s/y.txt"]
outs = ["d/"]

[stages.g]
kind = "command"
cmd = ["sh", "-c", "echo gggg > g.txt"]
outs = ["g.txt"]
"#;

#[test]
fn paths_and_hashes_read_from_a_manifest_are_validated() {
    let p = Project::new();
    p.write("two.toml", TWO);
    let first = p.run("two.toml", &[]);
    first.ok();
    let mf = manifest_of(&p, &first, "f");
    let md = manifest_of(&p, &first, "d");
    let g_manifest = read_manifest(&manifest_of(&p, &first, "g"));
    // The pool size the stage ran with is recorded (its seconds depend on it).
    assert!(g_manifest.threads >= 1, "{g_manifest:?}");
    let g_hash = g_manifest.outputs["g.txt"].blake3.clone();
    std::fs::create_dir_all(p.path("victim")).unwrap();
    p.write("victim/other.txt", "survives\n");
    let victim = p.path("victim").display().to_string();
    type Edit = Box<dyn Fn(&mut fure::cache::Manifest)>;
    let cases: Vec<(&str, &Path, Edit, &str)> = vec![
        (
            "f",
            &mf,
            Box::new(|m| m.outputs.get_mut("o.txt").unwrap().file_name = "../../escape.txt".into()),
            "not a plain name",
        ),
        (
            "f",
            &mf,
            Box::new({
                let v = victim.clone();
                move |m| m.outputs.get_mut("o.txt").unwrap().file_name = format!("{v}/o.txt")
            }),
            "not a plain name",
        ),
        (
            "d",
            &md,
            Box::new({
                let v = victim.clone();
                move |m| m.outputs.get_mut("d").unwrap().file_name = v.clone()
            }),
            "not a plain name",
        ),
        (
            "d",
            &md,
            Box::new(|m| {
                let o = m.outputs.get_mut("d").unwrap();
                o.files[0].path = "../../../escape.txt".into();
                o.files.sort_by(|a, b| a.path.cmp(&b.path));
                o.blake3 = fure::key::dir_hash(&o.files);
            }),
            "not a relative path",
        ),
        (
            "f",
            &mf,
            Box::new(|m| {
                m.outputs.get_mut("o.txt").unwrap().blake3 = "../../../../etc/hostname".into()
            }),
            "not a blake3 digest",
        ),
    ];
    for (stage, path, edit, why) in &cases {
        tamper(path, edit);
        let r = p.run("two.toml", &[]);
        r.ok();
        assert_eq!(r.status(stage), "ran", "{why}");
        assert!(
            r.reason(stage).contains("cached entry damaged") && r.reason(stage).contains(why),
            "{}",
            r.reason(stage)
        );
        assert!(!p.path("escape.txt").exists() && !p.path("out/escape.txt").exists());
        assert!(!p.path("victim/o.txt").exists());
        assert_eq!(p.read("victim/other.txt"), "survives\n");
        assert_eq!(p.read("out/two/f/o.txt"), "file\n");
        assert_eq!(p.read("out/two/d/d/s/y.txt"), "two\n");
        // verify reports the same damage and drops the entry.
        tamper(path, edit);
        let v = p.fure(&["verify"]);
        let text = String::from_utf8_lossy(&v.stdout);
        assert_eq!(v.status.code(), Some(1), "{text}");
        assert!(
            text.contains("invalid manifest") && text.contains(why),
            "{text}"
        );
        assert!(!path.exists());
        let v = p.fure(&["verify"]);
        assert_eq!(
            v.status.code(),
            Some(0),
            "{}",
            String::from_utf8_lossy(&v.stdout)
        );
        p.run("two.toml", &[]).ok();
    }

    // A manifest naming another valid object (not resealed): detected by the seal.
    let mut m = read_manifest(&mf);
    let o = m.outputs.get_mut("o.txt").unwrap();
    o.blake3 = g_hash.clone();
    o.bytes = 5;
    std::fs::write(&mf, serde_json::to_vec_pretty(&m).unwrap()).unwrap();
    let r = p.run("two.toml", &[]);
    r.ok();
    assert_eq!(r.status("f"), "ran");
    assert!(r.reason("f").contains("seal"), "{}", r.reason("f"));
    assert_eq!(p.read("out/two/f/o.txt"), "file\n");
    std::fs::write(&mf, serde_json::to_vec_pretty(&m).unwrap()).unwrap();
    let v = p.fure(&["verify"]);
    let text = String::from_utf8_lossy(&v.stdout);
    assert_eq!(v.status.code(), Some(1), "{text}");
    assert!(text.contains("seal"), "{text}");
}

#[test]
fn links_under_the_cache_are_never_followed() {
    let p = Project::new();
    p.write("two.toml", TWO);
    let r = p.run("two.toml", &[]);
    r.ok();
    // A symlinked key lock: the run refuses it instead of truncating the target.
    p.write("victim.txt", "precious\n");
    let mf = manifest_of(&p, &r, "f");
    let key = mf.file_stem().unwrap().to_string_lossy().into_owned();
    std::fs::remove_file(&mf).unwrap();
    let lock = p.path("cache/locks").join(format!("{key}.lock"));
    let _ = std::fs::remove_file(&lock);
    std::os::unix::fs::symlink(p.path("victim.txt"), &lock).unwrap();
    let r = p.run("two.toml", &[]);
    assert_eq!(r.code(), 1);
    assert_eq!(r.status("f"), "failed");
    assert!(r.stderr().contains("symbolic link"), "{}", r.stderr());
    assert_eq!(p.read("victim.txt"), "precious\n");

    // A symlinked shard directory: gc and verify remove the link, not the target's files.
    std::fs::create_dir_all(p.path("victim_dir")).unwrap();
    p.write("victim_dir/file", "precious\n");
    std::os::unix::fs::symlink(p.path("victim_dir"), p.path("cache/objects/zz")).unwrap();
    let v = p.fure(&["verify"]);
    let text = String::from_utf8_lossy(&v.stdout);
    assert_eq!(v.status.code(), Some(1), "{text}");
    assert!(text.contains("objects/zz: a symbolic link"), "{text}");
    assert!(
        text.contains(&format!("locks/{key}.lock: a symbolic link")),
        "{text}"
    );
    assert!(std::fs::symlink_metadata(&lock).is_err());
    std::os::unix::fs::symlink(p.path("victim_dir"), p.path("cache/objects/zz")).unwrap();
    let g = p.fure(&["gc"]);
    assert_eq!(g.status.code(), Some(0));
    assert_eq!(p.read("victim_dir/file"), "precious\n");
    assert!(std::fs::symlink_metadata(p.path("cache/objects/zz")).is_err());
    // A symlinked manifest is not read through.
    let r = p.run("two.toml", &[]);
    r.ok();
    let mg = manifest_of(&p, &r, "g");
    let real = p.path("g.json");
    std::fs::rename(&mg, &real).unwrap();
    std::os::unix::fs::symlink(&real, &mg).unwrap();
    let r = p.run("two.toml", &[]);
    r.ok();
    assert_eq!(r.status("g"), "ran");
    let v = p.fure(&["verify"]);
    assert_eq!(
        v.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&v.stdout)
    );
}

#[test]
fn a_materialisation_failure_fails_the_run_and_leaves_no_temporaries() {
    let p = Project::new();
    p.write("two.toml", TWO);
    // An unusable --out (a file).
    p.write("not_a_dir", "x");
    let r = p.run("two.toml", &["--out", "not_a_dir", "--keep-going"]);
    assert_eq!(r.code(), 1, "{}", r.stdout());
    assert_eq!(r.with("failed").len(), 3, "{:?}", r.stages);
    assert!(
        r.stderr().contains("cannot materialise outputs"),
        "{}",
        r.stderr()
    );
    // The entries were stored: the next run into a usable out/ hits.
    let r = p.run("two.toml", &[]);
    r.ok();
    assert_eq!(r.with("cached").len(), 3);

    // A full disk under out/ (a small tmpfs in a private mount namespace,
    // where the test may create one).
    p.write(
        "big.toml",
        "[stages.big]\nkind = \"command\"\ncmd = [\"sh\", \"-c\", \"head -c 300000 /dev/zero > big.bin\"]\nouts = [\"big.bin\"]\n",
    );
    let out = p.on_a_full_disk(
        "run big.toml --plain --out small",
        "find small -name '.fure-tmp-*' | sed 's/^/LEFT /' >&2;",
        "cache",
    );
    match out {
        Some(out) => {
            let err = String::from_utf8_lossy(&out.stderr);
            assert_eq!(out.status.code(), Some(1), "{err}");
            assert!(err.contains("cannot materialise outputs"), "{err}");
            assert!(err.contains("No space left"), "{err}");
            assert!(!err.contains("LEFT "), "a partial temporary is left: {err}");
        }
        None => eprintln!("skipped the full-disk case: no private tmpfs here"),
    }
    // (The tmpfs was private; no `.fure-tmp-*` is left in the real out/.)
    assert!(walk(&p.path("out"))
        .iter()
        .all(|f| !f.to_string_lossy().contains(".fure-tmp-")));
}

#[test]
fn concurrent_materialisations_keep_each_others_temporaries() {
    let p = Project::new();
    let pipe = |tag: &str| {
        format!(
            "[stages.s]\nkind = \"command\"\ncmd = [\"sh\", \"-c\", \"mkdir -p d && echo {tag} > d/x.txt && echo {tag} > o.txt\"]\nouts = [\"o.txt\", \"d/\"]\n"
        )
    };
    p.write("m.toml", &pipe("one"));
    p.run("m.toml", &[]).ok();
    // Another live process's temporaries (this test's pid) stay; a dead one's go.
    let me = std::process::id();
    let live = format!(".fure-tmp-{me}-0-o.txt");
    let live_in_dir = format!(".fure-tmp-{me}-1-x.txt");
    let dead = ".fure-tmp-999999999-0-o.txt";
    p.write(&format!("out/m/s/{live}"), "in flight");
    p.write(&format!("out/m/s/d/{live_in_dir}"), "in flight");
    p.write(&format!("out/m/s/{dead}"), "stale");
    p.write("m.toml", &pipe("two"));
    p.run("m.toml", &[]).ok();
    assert_eq!(p.read("out/m/s/o.txt"), "two\n");
    assert!(p.path(&format!("out/m/s/{live}")).exists());
    assert!(p.path(&format!("out/m/s/d/{live_in_dir}")).exists());
    assert!(!p.path(&format!("out/m/s/{dead}")).exists());

    // Two real runs into one out/, many rounds: no warnings, no failures.
    for round in 0..6 {
        p.write("m.toml", &pipe(&format!("r{round}")));
        let spawn = || {
            p.cmd(&["run", "m.toml", "--plain"])
                .stdout(Stdio::piped())
                .stderr(Stdio::piped())
                .spawn()
                .unwrap()
        };
        let (a, b) = (spawn(), spawn());
        for c in [a, b] {
            let out = c.wait_with_output().unwrap();
            let text = String::from_utf8_lossy(&out.stdout).into_owned()
                + &String::from_utf8_lossy(&out.stderr);
            assert_eq!(out.status.code(), Some(0), "{text}");
            assert!(!text.contains("warning"), "{text}");
        }
        assert_eq!(p.read("out/m/s/o.txt"), format!("r{round}\n"));
    }
}

fn wait_until(what: &str, limit: Duration, mut f: impl FnMut() -> bool) {
    let t = Instant::now();
    while !f() {
        assert!(t.elapsed() < limit, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn placeholders_are_found_inside_shell_groups_and_unknown_ones_are_located() {
    let p = Project::new();
    p.write("in.txt", "hello\n");
    p.write(
        "ph.toml",
        r#"
[stages.group]
kind = "command"
cmd = ["sh", "-c", "{ cat {deps.x}; echo end; } > b.txt; echo {{deps.x} '{\"k\": {\"v\": 1}}' ${HOME:+h} > e.txt"]
deps = { x = "in.txt" }
outs = ["b.txt", "e.txt"]
"#,
    );
    let r = p.run("ph.toml", &[]);
    r.ok();
    assert_eq!(p.read("out/ph/group/b.txt"), "hello\nend\n");
    assert_eq!(
        p.read("out/ph/group/e.txt"),
        "{deps.x} {\"k\": {\"v\": 1}} h\n"
    );

    for (text, want) in [
        (
            "cmd = [\"sh\", \"-c\", \"{ cat {deps.undeclared}; echo end; } > b.txt\"]",
            "bad.toml:4:1: error: stage `s` (kind `command`): parameter `cmd`: argument 2 (\"{ cat {deps.undeclared}; echo end; } > b.txt\"), column 7: placeholder names no declared dependency `undeclared`",
        ),
        (
            "cmd = [\"cat\", \"{dep.x}\"]",
            "column 1: unknown placeholder `{dep.x}`",
        ),
        (
            "cmd = [\"awk\", \"{print}\", \"{deps.x}\"]",
            "unknown placeholder `{print}` (expected {out}, {deps.NAME} or {outs.NAME}; write `{{` for a literal brace)",
        ),
        ("cmd = [\"cat\", \"{deps.x\"]", "has no closing `}`"),
    ] {
        p.write(
            "bad.toml",
            &format!("[stages.s]\nkind = \"command\"\ndeps = {{ x = \"in.txt\" }}\n{text}\nouts = [\"b.txt\"]\n"),
        );
        let out = p.fure(&["run", "bad.toml"]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{err}");
        assert!(err.contains(want), "missing `{want}` in:\n{err}");
        assert!(!p.path("out/bad").exists());
    }
}

/// Whether a process is alive (a zombie is not).
fn alive(pid: u32) -> bool {
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        Ok(s) => !s
            .rsplit_once(')')
            .is_some_and(|(_, rest)| rest.trim_start().starts_with('Z')),
        Err(_) => false,
    }
}

fn read_pids(p: &Project, files: &[&str]) -> Vec<u32> {
    files
        .iter()
        .map(|f| p.read(f).trim().parse().unwrap())
        .collect()
}

/// Two command stages that each leave a grandchild `sleep` behind the shell,
/// writing the shell's and the sleep's pid; fure is started and both are
/// waited for.
fn start_sleepers(p: &Project) -> (std::process::Child, Vec<u32>) {
    let d = p.path("").display().to_string();
    let mut text = String::new();
    for i in 0..2 {
        text.push_str(&format!(
            "[stages.s{i}]\nkind = \"command\"\ncmd = [\"sh\", \"-c\", \"sleep 60 & echo $! > {d}/sleep{i}.tmp; echo $$ > {d}/sh{i}.tmp; mv {d}/sleep{i}.tmp {d}/sleep{i}; mv {d}/sh{i}.tmp {d}/sh{i}; wait; echo done > o.txt\"]\nouts = [\"o.txt\"]\n"
        ));
    }
    p.write("sleepers.toml", &text);
    let child = p
        .cmd(&["run", "sleepers.toml", "--plain", "--jobs", "2"])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    wait_until("both commands", Duration::from_secs(30), || {
        ["sleep0", "sleep1", "sh0", "sh1"]
            .iter()
            .all(|f| p.path(f).exists())
    });
    let pids = read_pids(p, &["sleep0", "sleep1", "sh0", "sh1"]);
    assert!(pids.iter().all(|&q| alive(q)));
    (child, pids)
}

#[test]
fn signals_to_fure_stop_its_commands_and_clean_up() {
    for (sig, name, code) in [
        ("TERM", "SIGTERM", 143),
        ("INT", "SIGINT", 130),
        ("HUP", "SIGHUP", 129),
    ] {
        let p = Project::new();
        let (child, pids) = start_sleepers(&p);
        let (out, took) = signal_and_wait(child, sig);
        assert!(took < Duration::from_secs(20), "{name}: fure took {took:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(code), "{name}: {err}");
        assert!(err.contains(&format!("interrupted by {name}")), "{err}");
        wait_until("the commands to die", Duration::from_secs(5), || {
            pids.iter().all(|&q| !alive(q))
        });
        // Staging directories removed, nothing cached.
        assert_eq!(walk(&p.path("cache/tmp")).len(), 0, "{name}");
        assert_eq!(walk(&p.path("cache/entries")).len(), 0, "{name}");
    }
}

/// A command that traps the forwarded signal and exits 0 with what it has
/// (as a shell does that outlives its killed step) is interrupted all the
/// same: its outputs are not stored.
#[test]
fn a_command_exiting_0_after_a_signal_caches_nothing() {
    let p = Project::new();
    let started = p.path("started");
    p.write(
        "trap.toml",
        &format!(
            "[stages.partial]\nkind = \"command\"\ncmd = [\"sh\", \"-c\", \"trap 'echo partial > o.txt; exit 0' INT; touch {}; sleep 60 & wait; echo done > o.txt\"]\nouts = [\"o.txt\"]\n",
            started.display()
        ),
    );
    let child = p
        .cmd(&["run", "trap.toml", "--plain"])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    wait_until("the command", Duration::from_secs(30), || started.exists());
    let k = Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(k.success());
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(130), "{err}");
    assert!(
        err.contains("exited with status 0 after fure was interrupted by SIGINT")
            && err.contains("not stored"),
        "{err}"
    );
    assert_eq!(walk(&p.path("cache/entries")), Vec::<PathBuf>::new());
    assert_eq!(walk(&p.path("cache/tmp")).len(), 0);
    assert!(!p.path("out/trap/partial/o.txt").exists());
}

#[test]
fn commands_die_with_fure_on_sigkill() {
    let p = Project::new();
    let (mut child, pids) = start_sleepers(&p);
    child.kill().unwrap(); // SIGKILL: no handler runs.
    child.wait().unwrap();
    wait_until("the orphans to die", Duration::from_secs(5), || {
        pids.iter().all(|&q| !alive(q))
    });
}

#[test]
fn a_timeout_fails_the_stage_with_the_reason() {
    let p = Project::new();
    p.write(
        "t.toml",
        r#"
[stages.slow]
kind = "command"
cmd = ["sleep", "30"]
outs = ["o.txt"]
timeout = 0.5

[stages.stubborn]
kind = "command"
cmd = ["sh", "-c", "trap '' TERM; echo ignoring TERM >&2; sleep 30"]
outs = ["o.txt"]
timeout = 0.3

[stages.quick]
kind = "command"
cmd = ["sh", "-c", "echo ok > o.txt"]
outs = ["o.txt"]
timeout = 10
"#,
    );
    let t = Instant::now();
    let r = p.run("t.toml", &["--keep-going", "--jobs", "3"]);
    assert!(t.elapsed() < Duration::from_secs(15), "{:?}", t.elapsed());
    assert_eq!(r.code(), 1);
    assert_eq!(r.status("slow"), "failed");
    assert_eq!(r.status("stubborn"), "failed");
    assert_eq!(r.status("quick"), "ran");
    let err = r.stderr();
    assert!(err.contains("`sleep 30` timed out after 0.5 s"), "{err}");
    assert!(err.contains("timed out after 0.3 s"), "{err}");
    assert!(err.contains("ignoring TERM"), "{err}");
    // The limit is not part of the key.
    let text = std::fs::read_to_string(p.path("t.toml"))
        .unwrap()
        .replace("timeout = 10", "timeout = 20");
    p.write("t.toml", &text);
    let r = p.run("t.toml", &["--keep-going"]);
    assert_eq!(r.status("quick"), "cached");
}

/// Runs fure with a deadline; None if it had to be killed.
fn run_with_deadline(mut c: Command, limit: Duration) -> Option<std::process::Output> {
    let mut child = c
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let t = Instant::now();
    while t.elapsed() < limit {
        if child.try_wait().unwrap().is_some() {
            return Some(child.wait_with_output().unwrap());
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let _ = child.kill();
    let _ = child.wait();
    None
}

#[test]
fn fifos_and_devices_as_inputs_are_refused() {
    let p = Project::new();
    assert!(Command::new("mkfifo")
        .arg(p.path("fifo"))
        .status()
        .unwrap()
        .success());
    for (src, what) in [("fifo", "a FIFO"), ("/dev/zero", "a character device")] {
        p.write(
            "f.toml",
            &format!("[stages.s]\nkind = \"command\"\ncmd = [\"cp\", \"{{deps.x}}\", \"o.txt\"]\ndeps = {{ x = \"{src}\" }}\nouts = [\"o.txt\"]\n"),
        );
        let out = run_with_deadline(
            p.cmd(&["run", "f.toml", "--plain"]),
            Duration::from_secs(20),
        )
        .unwrap_or_else(|| panic!("fure hung on {src}"));
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{err}");
        assert!(
            err.contains(what) && err.contains("not a regular file"),
            "{err}"
        );
    }
}

#[test]
fn deep_extends_and_bad_pipeline_names_are_errors() {
    let p = Project::new();
    p.write("e0.toml", "[stages.gen]\nkind = \"demo_numbers\"\n");
    for i in 1..200 {
        p.write(
            &format!("e{i}.toml"),
            &format!("extends = \"e{}.toml\"\n", i - 1),
        );
    }
    let out = p.fure(&["run", "e199.toml"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("`extends` chain deeper than 32 files"),
        "{err}"
    );
    assert!(p.fure(&["run", "e20.toml"]).status.success());

    // `...toml` would name its pipeline `..` and materialise into ./<stage>.
    p.write("...toml", "[stages.gen]\nkind = \"demo_numbers\"\n");
    let out = p.fure(&["run", "...toml"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("pipeline name `..`"), "{err}");
    assert!(!p.path("gen").exists() && !p.path("out/gen").exists());
}

#[test]
fn a_read_only_cache_serves_hits_and_copies_only_once() {
    let p = Project::new();
    p.write("two.toml", TWO);
    p.run("two.toml", &[]).ok();
    std::fs::remove_dir_all(p.path("out")).unwrap();
    let fure = env!("CARGO_BIN_EXE_fure");
    // A read-only bind mount in a private mount namespace, where allowed.
    let script = format!(
        "mount --bind cache cache && mount -o remount,bind,ro cache || exit 99; \
         touch cache/probe 2>/dev/null && exit 98; \
         {fure} run two.toml --plain || exit 1; stat -c %i out/two/f/o.txt; \
         {fure} run two.toml --plain || exit 1; stat -c %i out/two/f/o.txt; \
         {fure} status two.toml"
    );
    let out = Command::new("unshare")
        .args(["-rm", "sh", "-c", &script])
        .current_dir(p.path(""))
        .env("FURE_CACHE", p.path("cache"))
        .output();
    let Ok(out) = out else {
        eprintln!("skipped: no unshare");
        return;
    };
    if matches!(out.status.code(), Some(99)) || out.stderr.starts_with(b"unshare") {
        eprintln!("skipped: no private read-only mount here");
        return;
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(0), "{text}\n{err}");
    assert_eq!(
        text.matches("0 ran, 3 cached, 0 failed").count(),
        2,
        "{text}\n{err}"
    );
    assert!(text.contains("two: 3 cached, 0 will run"), "{text}");
    let inodes: Vec<&str> = text
        .lines()
        .filter(|l| !l.is_empty() && l.bytes().all(|b| b.is_ascii_digit()))
        .collect();
    assert_eq!(inodes.len(), 2, "{text}");
    assert_eq!(inodes[0], inodes[1], "the copy was made again");
}

#[test]
fn stored_stderr_is_capped_to_its_tail() {
    let p = Project::new();
    let d = p.path("").display().to_string();
    // About 7 MB of stderr between two markers (computed, so that the command
    // line quoted in the error does not contain them); before failing, the command
    // looks for a file of more than 1 MB anywhere in the project (the cache
    // included): a stderr log kept whole would be one.
    p.write(
        "loud.toml",
        &format!(
            r#"
[stages.loud]
kind = "command"
cmd = ["sh", "-c", "echo FIRST-$((6*7)) >&2; seq 1 400000 | sed 's/^/noise line /' >&2; echo LAST-$((6*7)) >&2; find {d} -type f -size +1000k > {d}/big_files.tmp; mv {d}/big_files.tmp {d}/big_files; exit 3"]
outs = ["o.txt"]
"#
        ),
    );
    let r = p.run("loud.toml", &[]);
    assert_eq!(r.code(), 1, "{}", r.stdout());
    assert_eq!(r.status("loud"), "failed");
    assert_eq!(
        p.read("big_files"),
        "",
        "stderr was stored whole while the command ran"
    );
    let error = r.json["stages"][0]["error"].as_str().unwrap_or("");
    assert!(
        error.contains("exited with status 3") && error.contains("LAST-42"),
        "{error}"
    );
    assert!(!error.contains("FIRST-42"), "not only the tail");
    assert!(error.len() < 8 * 1024, "{} bytes of error", error.len());
    let err = r.stderr();
    assert!(err.contains("LAST-42") && !err.contains("FIRST-42"));
    assert!(err.len() < 16 * 1024, "{} bytes of stderr", err.len());
    // Nothing of it is left behind either.
    for f in walk(&p.path("")) {
        let len = std::fs::symlink_metadata(&f).unwrap().len();
        assert!(len < 1 << 20, "{}: {len} bytes", f.display());
    }
}

#[test]
fn identical_stages_of_one_run_wait_for_each_other_without_blaming_another_process() {
    let p = Project::new();
    let mut text = String::new();
    for s in ["a", "b"] {
        text.push_str(&format!(
            "[stages.{s}]\nkind = \"command\"\ncmd = [\"sh\", \"-c\", \"sleep 1; echo same > o.txt\"]\nouts = [\"o.txt\"]\n"
        ));
    }
    p.write("same.toml", &text);
    let r = p.run("same.toml", &["--jobs", "2"]);
    r.ok();
    let text = r.stdout() + &r.stderr();
    assert!(!text.contains("another fure process"), "{text}");
    assert!(
        text.contains("another stage of this run with the same key is computing it"),
        "{text}"
    );
    let mut statuses = vec![r.status("a"), r.status("b")];
    statuses.sort();
    assert_eq!(statuses, ["cached", "ran"], "{text}");
    assert_eq!(p.read("out/same/a/o.txt"), "same\n");
    assert_eq!(p.read("out/same/b/o.txt"), "same\n");
}

#[test]
fn a_command_failing_on_a_full_disk_names_the_cause() {
    let p = Project::new();
    p.write(
        "fill.toml",
        "[stages.fill]\nkind = \"command\"\ncmd = [\"sh\", \"-c\", \"head -c 300000 /dev/zero > big.bin\"]\nouts = [\"big.bin\"]\n",
    );
    // The whole cache (staging directories included) on the small disk: the command's write
    // fails, and so would a stderr log on that disk.
    let Some(out) = p.on_a_full_disk(
        "run fill.toml --plain",
        "find small/cache/tmp -mindepth 1 2>/dev/null | sed 's/^/LEFT /' >&2;",
        "small/cache",
    ) else {
        eprintln!("skipped: no private tmpfs here");
        return;
    };
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("exited with status 1"), "{err}");
    assert!(err.contains("No space left on device"), "{err}");
    assert!(!err.contains("LEFT "), "a staging directory is left: {err}");
}
