//! `--executor slurm` on a real Slurm: a single-node cluster on localhost
//! (munged with a generated key, slurmctld and slurmd from a generated
//! slurm.conf on free ports, all in a temporary directory), started by the
//! test itself. Where it cannot start (Slurm or munge not installed, no
//! permission, ...) the test prints why and passes.
//!
//! What it checks, against local runs of the same pipelines on another
//! cache: a run and a one-at-a-time sweep (with a failing and a degraded
//! variant, and an aggregate) give the same keys, the same outputs byte for
//! byte and the same sweep record (costs aside: they are measured seconds);
//! a second Slurm run submits nothing; a failing stage reports the job's
//! state, exit code and log tail; SIGINT cancels the jobs in flight.

use std::io::{BufRead, BufReader};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use super::engine::{data, Project};

/// A running single-node cluster; stopped (daemons killed) on drop.
struct Cluster {
    dir: tempfile::TempDir,
    conf: PathBuf,
    daemons: Vec<Child>,
}

fn which(program: &str) -> Option<PathBuf> {
    std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .chain([PathBuf::from("/usr/sbin"), PathBuf::from("/sbin")])
            .map(|d| d.join(program))
            .find(|p| p.is_file())
    })
}

fn free_port() -> Result<u16, String> {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .map_err(|e| format!("no free port: {e}"))
}

fn tail(path: &Path) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(8)..].join("\n")
}

fn user_name() -> String {
    Command::new("id")
        .arg("-un")
        .output()
        .ok()
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
        .filter(|s| !s.is_empty())
        .unwrap_or_else(|| "root".into())
}

impl Cluster {
    /// Starts munged, slurmctld and slurmd; Err says why it cannot.
    fn start() -> Result<Cluster, String> {
        let mut missing = Vec::new();
        let mut bins = std::collections::BTreeMap::new();
        for b in [
            "slurmctld",
            "slurmd",
            "sbatch",
            "squeue",
            "scontrol",
            "scancel",
            "sinfo",
        ] {
            match which(b) {
                Some(p) => {
                    bins.insert(b, p);
                }
                None => missing.push(b),
            }
        }
        if !missing.is_empty() {
            return Err(format!(
                "{} not found (apt-get install slurm-wlm munge)",
                missing.join(", ")
            ));
        }
        let dir = tempfile::Builder::new()
            .prefix("fure-slurm-")
            .tempdir()
            .map_err(|e| e.to_string())?;
        let d = dir.path().to_path_buf();
        for sub in ["state", "spool", "log", "munge"] {
            std::fs::create_dir_all(d.join(sub)).map_err(|e| e.to_string())?;
        }
        let mut daemons = Vec::new();
        let log = |name: &str| -> Result<Stdio, String> {
            std::fs::File::create(d.join("log").join(name))
                .map(Stdio::from)
                .map_err(|e| e.to_string())
        };
        // munge with a generated key; without munged, auth/none.
        let auth = match which("munged") {
            Some(munged) => {
                use std::os::unix::fs::PermissionsExt;
                let key: Vec<u8> = (0..1024u32)
                    .map(|i| (i.wrapping_mul(2654435761) >> 13) as u8 ^ std::process::id() as u8)
                    .collect();
                let kf = d.join("munge/munge.key");
                std::fs::write(&kf, key).map_err(|e| e.to_string())?;
                std::fs::set_permissions(&kf, std::fs::Permissions::from_mode(0o400))
                    .map_err(|e| e.to_string())?;
                std::fs::set_permissions(d.join("munge"), std::fs::Permissions::from_mode(0o700))
                    .map_err(|e| e.to_string())?;
                let sock = d.join("munge/sock");
                let child = Command::new(munged)
                    .args(["--foreground", "--force"])
                    .arg(format!("--key-file={}", kf.display()))
                    .arg(format!("--socket={}", sock.display()))
                    .arg(format!("--pid-file={}", d.join("munge/pid").display()))
                    .arg(format!("--log-file={}", d.join("log/munged.log").display()))
                    .arg(format!("--seed-file={}", d.join("munge/seed").display()))
                    .stdout(log("munged.out")?)
                    .stderr(log("munged.err")?)
                    .spawn()
                    .map_err(|e| format!("munged: {e}"))?;
                daemons.push(child);
                let t0 = Instant::now();
                while !sock.exists() {
                    if t0.elapsed() > Duration::from_secs(10) {
                        let c = Cluster {
                            dir,
                            conf: PathBuf::new(),
                            daemons,
                        };
                        return Err(format!(
                            "munged did not start: {}",
                            tail(&c.dir.path().join("log/munged.err"))
                        ));
                    }
                    std::thread::sleep(Duration::from_millis(50));
                }
                format!(
                    "AuthType=auth/munge\nCredType=cred/munge\nAuthInfo=socket={}\n",
                    sock.display()
                )
            }
            None => "AuthType=auth/none\nCredType=cred/none\n".to_string(),
        };
        let host = Command::new("hostname")
            .arg("-s")
            .output()
            .ok()
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
            .filter(|s| !s.is_empty())
            .unwrap_or_else(|| "localhost".into());
        let cpus = std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1);
        let user = user_name();
        let (p1, p2) = (free_port()?, free_port()?);
        let conf = d.join("slurm.conf");
        let text = format!(
            "ClusterName=furetest\n\
             SlurmctldHost={host}(127.0.0.1)\n\
             SlurmUser={user}\nSlurmdUser={user}\n\
             SlurmctldPort={p1}\nSlurmdPort={p2}\n\
             {auth}\
             StateSaveLocation={d}/state\nSlurmdSpoolDir={d}/spool\n\
             SlurmctldPidFile={d}/slurmctld.pid\nSlurmdPidFile={d}/slurmd.pid\n\
             SlurmctldLogFile={d}/log/slurmctld.log\nSlurmdLogFile={d}/log/slurmd.log\n\
             ProctrackType=proctrack/linuxproc\nTaskPlugin=task/none\n\
             SelectType=select/cons_tres\nSelectTypeParameters=CR_Core\n\
             SchedulerType=sched/builtin\nSchedulerParameters=sched_interval=1\n\
             JobAcctGatherType=jobacct_gather/none\n\
             AccountingStorageType=accounting_storage/none\nJobCompType=jobcomp/none\n\
             MpiDefault=none\nReturnToService=2\nMinJobAge=600\nKillWait=2\n\
             InactiveLimit=0\nWaittime=0\n\
             NodeName={host} NodeAddr=127.0.0.1 CPUs={cpus} RealMemory=500 State=UNKNOWN\n\
             PartitionName=test Nodes={host} Default=YES MaxTime=INFINITE State=UP OverSubscribe=YES\n",
            d = d.display()
        );
        std::fs::write(&conf, text).map_err(|e| e.to_string())?;
        for (daemon, args) in [
            ("slurmctld", vec!["-D", "-i"]),
            ("slurmd", vec!["-D", "-N", host.as_str()]),
        ] {
            let child = Command::new(&bins[daemon])
                .args(&args)
                .arg("-f")
                .arg(&conf)
                .env("SLURM_CONF", &conf)
                .stdout(log(&format!("{daemon}.out"))?)
                .stderr(log(&format!("{daemon}.err"))?)
                .spawn()
                .map_err(|e| format!("{daemon}: {e}"))?;
            daemons.push(child);
        }
        let mut c = Cluster { dir, conf, daemons };
        // Up when the node is idle.
        let t0 = Instant::now();
        loop {
            let out = c.command("sinfo").args(["-h", "-o", "%t"]).output();
            if let Ok(o) = &out {
                if String::from_utf8_lossy(&o.stdout).trim() == "idle" {
                    return Ok(c);
                }
            }
            for ch in &mut c.daemons {
                if let Ok(Some(st)) = ch.try_wait() {
                    let d = c.dir.path();
                    return Err(format!(
                        "a daemon exited ({st}): slurmctld: {} | slurmd: {}",
                        tail(&d.join("log/slurmctld.log")) + &tail(&d.join("log/slurmctld.err")),
                        tail(&d.join("log/slurmd.log")) + &tail(&d.join("log/slurmd.err")),
                    ));
                }
            }
            if t0.elapsed() > Duration::from_secs(30) {
                let d = c.dir.path();
                return Err(format!(
                    "the node did not become idle in 30 s ({:?}): {}",
                    out.map(|o| String::from_utf8_lossy(&o.stdout).into_owned()),
                    tail(&d.join("log/slurmd.log"))
                ));
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    /// A Slurm client command of this cluster.
    fn command(&self, program: &str) -> Command {
        let mut c = Command::new(program);
        c.env("SLURM_CONF", &self.conf);
        c
    }

    /// `fure ARGS` in a project, with this cluster.
    fn fure(&self, p: &Project, args: &[&str]) -> std::process::Output {
        p.cmd(args)
            .env("SLURM_CONF", &self.conf)
            .env_remove("FURE_EXECUTOR")
            .output()
            .expect("run fure")
    }

    /// State of a job as `squeue` shows it (COMPLETING while its
    /// processes are being ended, where `scontrol` already says CANCELLED).
    fn queue_state(&self, id: &str) -> String {
        let o = self
            .command("squeue")
            .args(["-h", "-t", "all", "-j", id, "-o", "%T"])
            .output()
            .expect("squeue");
        String::from_utf8_lossy(&o.stdout).trim().to_string()
    }

    /// State of a job (`scontrol show job`).
    fn job_state(&self, id: &str) -> String {
        let o = self
            .command("scontrol")
            .args(["show", "job", "-o", id])
            .output()
            .expect("scontrol");
        String::from_utf8_lossy(&o.stdout)
            .split_whitespace()
            .find_map(|f| f.strip_prefix("JobState="))
            .unwrap_or("")
            .to_string()
    }
}

impl Drop for Cluster {
    fn drop(&mut self) {
        // slurmd, slurmctld, then munged.
        for c in self.daemons.iter_mut().rev() {
            // SAFETY: signalling our own child.
            unsafe { libc::kill(c.id() as i32, libc::SIGTERM) };
            let t0 = Instant::now();
            while matches!(c.try_wait(), Ok(None)) && t0.elapsed() < Duration::from_secs(5) {
                std::thread::sleep(Duration::from_millis(50));
            }
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// Every file under `dir` (relative path -> bytes).
fn tree(dir: &Path) -> std::collections::BTreeMap<String, Vec<u8>> {
    fn walk(root: &Path, d: &Path, out: &mut std::collections::BTreeMap<String, Vec<u8>>) {
        let Ok(rd) = std::fs::read_dir(d) else { return };
        for e in rd.flatten() {
            let p = e.path();
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                let rel = p.strip_prefix(root).unwrap().display().to_string();
                out.insert(rel, std::fs::read(&p).unwrap());
            }
        }
    }
    let mut out = std::collections::BTreeMap::new();
    walk(dir, dir, &mut out);
    out
}

/// stage -> key of every pipeline in a cache's index (variants included).
fn index_keys(cache: &Path) -> std::collections::BTreeMap<String, String> {
    let mut keys = std::collections::BTreeMap::new();
    for e in std::fs::read_dir(cache.join("index")).unwrap().flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let j: serde_json::Value =
            serde_json::from_slice(&std::fs::read(e.path()).unwrap()).unwrap();
        for (stage, entry) in j.as_object().unwrap() {
            keys.insert(
                format!("{name}/{stage}"),
                entry["key"].as_str().unwrap().to_string(),
            );
        }
    }
    keys
}

/// The sweep record without its measured costs.
fn record_without_costs(path: &Path) -> serde_json::Value {
    let mut j: serde_json::Value = serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap();
    for v in j["variants"].as_array_mut().unwrap() {
        v.as_object_mut().unwrap().remove("costs");
    }
    j
}

fn all(o: &std::process::Output) -> String {
    format!(
        "status {}\nstdout:\n{}\nstderr:\n{}",
        o.status,
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

const CHAIN: &str = r#"
[pipeline]
name = "chain"

[stages.gen]
kind = "demo_numbers"
count = 300

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

[stages.lines]
kind = "command"
cmd = ["sh", "-c", "wc -l < {deps.t} > lines.txt; mkdir parts; echo x > parts/x.txt"]
deps = { t = "c.text" }
outs = ["lines.txt", "parts/"]

[executor]
time = "5"
[executor.kinds.command]
cpus = 1
sbatch = ["--comment=fure-test"]
"#;

const FAIL: &str = r#"
[stages.ok]
kind = "command"
cmd = ["sh", "-c", "echo fine > ok.txt"]
outs = ["ok.txt"]

[stages.bad]
kind = "command"
cmd = ["sh", "-c", "echo 'boom: the stage failed' >&2; exit 3"]
deps = { x = "ok.ok.txt" }
outs = ["never.txt"]
"#;

/// A slow stage that exits 0 with its output when it is signalled, as a
/// shell does whose step Slurm killed first (`sleep 120; echo late`: Slurm
/// signals a job's processes one at a time, children first) or a program
/// that traps SIGTERM and saves what it has. `STARTED` is replaced by a file
/// it touches once the trap is set.
const SLOW: &str = r#"
[stages.slow]
kind = "command"
cmd = ["sh", "-c", "trap 'echo partial > late.txt; exit 0' TERM INT; touch STARTED; sleep 120 & wait; echo late > late.txt"]
outs = ["late.txt"]
"#;

/// What `cache/entries` holds, for a failure message: each name, and
/// whether it is a complete entry (a manifest: its stage and outputs).
fn describe_entries(dir: &Path) -> Vec<String> {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    rd.flatten()
        .map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            let manifest = std::fs::read(e.path())
                .ok()
                .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
                .filter(|j| j["seal"].is_string() && j["outputs"].is_object());
            match manifest {
                Some(j) => format!(
                    "{name}: complete entry of stage {} (pipeline {}), outputs {}",
                    j["stage"], j["pipeline"], j["outputs"]
                ),
                None => format!(
                    "{name}: no complete entry ({} bytes)",
                    e.metadata().map(|m| m.len()).unwrap_or(0)
                ),
            }
        })
        .collect()
}

/// The user configuration every Slurm call of the test uses: poll often.
fn project(cluster_conf: &str) -> Project {
    let p = Project::new();
    p.write("executor.toml", cluster_conf);
    p
}

#[test]
fn runs_and_sweeps_on_slurm_match_local_ones() {
    let t_all = Instant::now();
    let cluster = match Cluster::start() {
        Ok(c) => c,
        Err(why) => {
            eprintln!("slurm tests skipped: Slurm cannot start here: {why}");
            return;
        }
    };
    eprintln!("slurm: cluster up in {:.1}s", t_all.elapsed().as_secs_f64());
    let user_conf = "[executor]\npoll_seconds = 0.2\n";
    let slurm = ["--executor", "slurm", "--executor-config", "executor.toml"];

    // --- A run: same keys and outputs as locally; then all cached. ---
    let local = project(user_conf);
    let remote = project(user_conf);
    for p in [&local, &remote] {
        p.write("chain.toml", CHAIN);
        p.write("data/nums.txt", "1\n2\n3\n");
    }
    let t = Instant::now();
    let o = cluster.fure(&local, &["run", "chain.toml", "--plain"]);
    assert!(o.status.success(), "{}", all(&o));
    let t_local = t.elapsed();
    let t = Instant::now();
    let mut args = vec!["run", "chain.toml", "--plain"];
    args.extend(slurm);
    let o = cluster.fure(&remote, &args);
    let t_remote = t.elapsed();
    assert!(o.status.success(), "{}", all(&o));
    let text = String::from_utf8_lossy(&o.stdout).into_owned();
    for stage in ["gen", "a", "b", "c", "lines"] {
        assert!(
            text.contains(&format!("slurm   chain/{stage}  submitted as job")),
            "{stage}: {text}"
        );
    }
    assert!(text.contains("5 ran, 0 cached, 0 failed"), "{text}");
    eprintln!(
        "slurm: run of 5 stages: local {:.2}s, slurm {:.2}s",
        t_local.as_secs_f64(),
        t_remote.as_secs_f64()
    );
    assert_eq!(
        index_keys(&local.path("cache")),
        index_keys(&remote.path("cache"))
    );
    assert_eq!(tree(&local.path("out")), tree(&remote.path("out")));
    assert_eq!(
        tree(&local.path("cache/objects")),
        tree(&remote.path("cache/objects"))
    );
    // Job files of succeeded jobs are gone.
    let left: Vec<_> = std::fs::read_dir(remote.path("cache/slurm"))
        .map(|rd| rd.flatten().map(|e| e.path()).collect())
        .unwrap_or_default();
    assert!(left.is_empty(), "{left:?}");
    let o = cluster.fure(&remote, &args);
    assert!(o.status.success(), "{}", all(&o));
    let text = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(text.contains("0 ran, 5 cached"), "{text}");
    assert!(!text.contains("submitted"), "{text}");

    // --- A sweep: 10 variants, a failing and a degraded one, an aggregate. ---
    let local = project(user_conf);
    let remote = project(user_conf);
    for p in [&local, &remote] {
        std::fs::copy(data("sweep_each.toml"), p.path("sw.toml")).unwrap();
    }
    let t = Instant::now();
    let o = cluster.fure(&local, &["sweep", "sw.toml", "--jobs", "1"]);
    assert!(o.status.success(), "{}", all(&o));
    let t_local = t.elapsed();
    let mut args = vec!["sweep", "sw.toml"];
    args.extend(slurm);
    let t = Instant::now();
    let o = cluster.fure(&remote, &args);
    let t_remote = t.elapsed();
    assert!(o.status.success(), "{}", all(&o));
    let text = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        text.contains("2 of 10 variants failed, 2 degraded"),
        "{text}"
    );
    assert!(text.contains("aggregate summary: ran"), "{text}");
    let jobs = text.matches("submitted as job").count();
    eprintln!(
        "slurm: sweep of 10 variants: local {:.2}s, slurm {:.2}s ({jobs} jobs)",
        t_local.as_secs_f64(),
        t_remote.as_secs_f64()
    );
    // Every key once: shared upstream stages were not submitted twice.
    let keys = index_keys(&remote.path("cache"));
    let mut distinct: Vec<&String> = keys
        .iter()
        .filter(|(k, _)| k.starts_with("sw@"))
        .map(|(_, v)| v)
        .collect();
    distinct.sort();
    distinct.dedup();
    // Failed stages are not in the index: + 2 failures, + the aggregate.
    assert_eq!(jobs, distinct.len() + 2 + 1, "{text}");
    // Same keys for every variant's stages; the aggregate's key depends on
    // the record, whose costs are measured seconds.
    let no_agg = |m: std::collections::BTreeMap<String, String>| {
        m.into_iter()
            .filter(|(k, _)| k.starts_with("sw@"))
            .collect::<std::collections::BTreeMap<_, _>>()
    };
    assert_eq!(no_agg(index_keys(&local.path("cache"))), no_agg(keys));
    assert_eq!(
        record_without_costs(&local.path("out/sw/sweep.json")),
        record_without_costs(&remote.path("out/sw/sweep.json"))
    );
    let strip_agg = |m: std::collections::BTreeMap<String, Vec<u8>>| {
        m.into_iter()
            .filter(|(k, _)| k.starts_with("sw@"))
            .collect::<std::collections::BTreeMap<_, _>>()
    };
    assert_eq!(
        strip_agg(tree(&local.path("out"))),
        strip_agg(tree(&remote.path("out")))
    );
    // The failed jobs' logs are kept, the others' removed.
    let logs: Vec<String> = std::fs::read_dir(remote.path("cache/slurm"))
        .unwrap()
        .flatten()
        .flat_map(|d| std::fs::read_dir(d.path()).unwrap().flatten())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".log"))
        .collect();
    assert_eq!(logs.len(), 2, "{logs:?}");

    // --- A failing stage: the job's state, exit code and log tail. ---
    let p = project(user_conf);
    p.write("fail.toml", FAIL);
    let mut args = vec!["run", "fail.toml", "--plain"];
    args.extend(slurm);
    let o = cluster.fure(&p, &args);
    assert_eq!(o.status.code(), Some(1), "{}", all(&o));
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(
        err.contains("error: stage `bad` (command) failed: `sh -c")
            && err.contains("exited with status 3"),
        "{err}"
    );
    assert!(
        err.contains("FAILED (NonZeroExitCode), exit code 1:0"),
        "{err}"
    );
    assert!(err.contains("boom: the stage failed"), "{err}");
    assert!(err.contains(".log:"), "{err}");

    // --- SIGINT: the job in flight is cancelled, nothing is cached, even
    // though its command exits 0 with an output once signalled. ---
    let p = project(user_conf);
    let started = p.path("started");
    p.write(
        "slow.toml",
        &SLOW.replace("STARTED", &started.display().to_string()),
    );
    let mut args = vec!["run", "slow.toml", "--plain"];
    args.extend(slurm);
    let mut child = p
        .cmd(&args)
        .env("SLURM_CONF", &cluster.conf)
        .env_remove("FURE_EXECUTOR")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
    let mut job = None;
    let t0 = Instant::now();
    for line in lines.by_ref() {
        let line = line.unwrap();
        if let Some(rest) = line.split("job ").nth(1) {
            if line.contains("running on") {
                job = rest.split_whitespace().next().map(str::to_string);
                break;
            }
        }
        assert!(t0.elapsed() < Duration::from_secs(60), "no job started");
    }
    let job = job.expect("the slow stage's job runs");
    while !started.exists() {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "the command did not start"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    // SAFETY: signalling our own child.
    unsafe { libc::kill(child.id() as i32, libc::SIGINT) };
    let rest: Vec<String> = lines.map_while(Result::ok).collect();
    let st = child.wait().unwrap();
    assert_eq!(st.code(), Some(130), "{rest:?}");
    assert!(
        rest.iter()
            .any(|l| l.contains(&format!("cancelling jobs {job}"))),
        "{rest:?}"
    );
    // Until its processes are gone (squeue: no longer COMPLETING).
    let t0 = Instant::now();
    while cluster.job_state(&job) != "CANCELLED" || cluster.queue_state(&job) != "CANCELLED" {
        assert!(
            t0.elapsed() < Duration::from_secs(20),
            "job {job}: {} ({})",
            cluster.job_state(&job),
            cluster.queue_state(&job)
        );
        std::thread::sleep(Duration::from_millis(200));
    }
    let left = describe_entries(&p.path("cache/entries"));
    let logs: Vec<String> = std::fs::read_dir(p.path("cache/slurm"))
        .into_iter()
        .flatten()
        .flatten()
        .flat_map(|d| std::fs::read_dir(d.path()).into_iter().flatten().flatten())
        .filter(|e| e.file_name().to_string_lossy().ends_with(".log"))
        .map(|e| std::fs::read_to_string(e.path()).unwrap_or_default())
        .collect();
    assert!(
        left.is_empty(),
        "cache/entries after the cancelled job: {left:#?}\njob logs: {logs:#?}\n{rest:#?}"
    );
    eprintln!("slurm: whole test {:.1}s", t_all.elapsed().as_secs_f64());
}
