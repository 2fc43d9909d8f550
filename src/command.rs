//! The built-in `command` stage kind: wrap any external program.
//!
//! ```toml
//! [stages.neus]
//! kind = "command"
//! cmd  = ["sh", "-c", "my-neus2 --images {deps.views} --out mesh.obj"]
//! deps = { views = "data/views" }          # or a list: deps = ["a.out", "x.txt"] -> {deps.0}, {deps.1}
//! outs = ["mesh.obj", "renders/"]          # files (or `dir/`) the command must create
//! ```
//!
//! Design:
//! - `deps` entries are sources exactly like `inputs` values (an upstream
//!   output `STAGE.PORT` or a file/directory path); the planner turns them into
//!   input ports (named by the table key, or `0`, `1`, ... for a list) and
//!   leaves in the `deps` parameter only the port names, so the key holds the
//!   argv as written and the *contents* of the deps, never their paths.
//! - Each `outs` entry is an output port whose name is the entry itself
//!   (`neus.mesh.obj` refers to it downstream); a trailing `/` declares a
//!   directory. Entries are plain names: no `/` inside, no `..`.
//! - The command runs with its working directory set to the (empty) output
//!   directory, so `outs` are written by relative name. In `cmd`, `{deps.NAME}`
//!   becomes the absolute path of a dependency, `{outs.NAME}` the absolute path
//!   of an output and `{out}` the output directory; other braces are left alone
//!   (shell `${VAR}` keeps working). The environment also holds `FURE_OUT`.
//! - stdout and stderr go to files; a non-zero exit, death by signal or a
//!   missing declared output fails the stage with the tail of stderr, and the
//!   engine caches nothing.
//! - Peak memory is the child's maximum resident set size from `wait4`.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use fure_stage_api::{ParamSpec, Params, PortSpec, Stage, StageContext, StageError};

/// The `command` stage kind.
pub struct CommandStage;

pub const KIND: &str = "command";

/// How many bytes of stderr a failure message shows.
const STDERR_TAIL: u64 = 2000;

impl Stage for CommandStage {
    fn kind(&self) -> &'static str {
        KIND
    }
    fn version(&self) -> u32 {
        1
    }
    fn doc(&self) -> &'static str {
        "Runs an external program (argv `cmd`) in its output directory. `deps` (a list or a \
         table of upstream outputs `STAGE.PORT` or file paths) become inputs, substituted into \
         `cmd` as {deps.NAME}; `outs` lists the files (or `dir/`) the program must create, \
         substituted as {outs.NAME}; {out} is the output directory. Fails with the tail of \
         stderr when the program fails or does not write its outputs."
    }
    fn params(&self) -> Vec<ParamSpec> {
        vec![
            ParamSpec::str_list(
                "cmd",
                &[],
                "argv of the program; {deps.NAME}, {outs.NAME} and {out} are substituted",
            )
            .required(),
            ParamSpec::str_list(
                "deps",
                &[],
                "inputs: a list or table of `STAGE.PORT` or paths",
            ),
            ParamSpec::str_list(
                "outs",
                &[],
                "files (or `dir/`) the program must create in its working directory",
            )
            .required(),
            ParamSpec::table("env", "extra environment variables (string values)"),
        ]
    }
    fn inputs(&self, params: &Params) -> Vec<PortSpec> {
        let names = params.str_list("deps").unwrap_or_default();
        names
            .iter()
            .map(|n| {
                // A dependency may be a file or a directory; the planner accepts either.
                PortSpec::file(n, "", "a dependency of the command")
            })
            .collect()
    }
    fn outputs(&self, params: &Params) -> Vec<PortSpec> {
        let outs = params.str_list("outs").unwrap_or_default();
        outs.iter()
            .map(|o| match o.strip_suffix('/') {
                Some(d) => PortSpec::dir(d, "a directory the command creates"),
                None => PortSpec::file(o, "", "a file the command creates"),
            })
            .collect()
    }
    fn validate(&self, params: &Params) -> Result<(), StageError> {
        let cmd = params.str_list("cmd")?;
        if cmd.is_empty() {
            return Err(StageError::param(
                "cmd",
                "must name a program (a non-empty argv list)",
            ));
        }
        let outs = params.str_list("outs")?;
        if outs.is_empty() {
            return Err(StageError::param("outs", "must list at least one output"));
        }
        let mut seen = std::collections::BTreeSet::new();
        for o in &outs {
            let n = o.strip_suffix('/').unwrap_or(o);
            if n.is_empty() || n == "." || n == ".." || n.contains('/') || n.contains('\\') {
                return Err(StageError::param(
                    "outs",
                    format!("`{o}`: expected a plain file name (or `dir/`), without `/` inside"),
                ));
            }
            if !seen.insert(n.to_string()) {
                return Err(StageError::param("outs", format!("`{o}` is listed twice")));
            }
        }
        let deps = params.str_list("deps")?;
        for (k, v) in params.table("env")? {
            if v.as_str().is_none() {
                return Err(StageError::param(
                    "env",
                    format!("`{k}`: expected a string value"),
                ));
            }
        }
        // Every placeholder must name a declared dependency or output.
        for arg in &cmd {
            for ph in placeholders(arg) {
                let ok = match ph.split_once('.') {
                    Some(("deps", n)) => deps.iter().any(|d| d == n),
                    Some(("outs", n)) => outs.iter().any(|o| o.strip_suffix('/').unwrap_or(o) == n),
                    _ => true,
                };
                if !ok {
                    return Err(StageError::param(
                        "cmd",
                        format!("placeholder `{{{ph}}}` names no declared dependency or output"),
                    ));
                }
            }
        }
        Ok(())
    }
    fn run(&self, ctx: &StageContext<'_>) -> Result<(), StageError> {
        run_command(ctx).map(|_| ())
    }
}

/// The `{deps.X}` / `{outs.X}` / `{out}` placeholders of one argument.
fn placeholders(arg: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut rest = arg;
    while let Some(i) = rest.find('{') {
        let after = &rest[i + 1..];
        match after.find('}') {
            Some(j) => {
                let inner = &after[..j];
                if inner == "out" || inner.starts_with("deps.") || inner.starts_with("outs.") {
                    out.push(inner.to_string());
                }
                rest = &after[j + 1..];
            }
            None => break,
        }
    }
    out
}

fn substitute(
    arg: &str,
    deps: &BTreeMap<String, PathBuf>,
    outs: &BTreeMap<String, PathBuf>,
    out_dir: &Path,
) -> String {
    let mut s = String::with_capacity(arg.len());
    let mut rest = arg;
    while let Some(i) = rest.find('{') {
        s.push_str(&rest[..i]);
        let after = &rest[i + 1..];
        let Some(j) = after.find('}') else {
            s.push_str(&rest[i..]);
            return s;
        };
        let inner = &after[..j];
        let rep = if inner == "out" {
            Some(out_dir.display().to_string())
        } else if let Some(n) = inner.strip_prefix("deps.") {
            deps.get(n).map(|p| p.display().to_string())
        } else if let Some(n) = inner.strip_prefix("outs.") {
            outs.get(n).map(|p| p.display().to_string())
        } else {
            None
        };
        match rep {
            Some(r) => s.push_str(&r),
            None => {
                s.push('{');
                s.push_str(inner);
                s.push('}');
            }
        }
        rest = &after[j + 1..];
    }
    s.push_str(rest);
    s
}

/// Runs the command of `ctx`; returns the child's peak RSS in bytes.
pub fn run_command(ctx: &StageContext<'_>) -> Result<u64, StageError> {
    let cmd = ctx.params.str_list("cmd")?;
    let env = ctx.params.table("env")?;
    let first = ctx
        .outputs
        .values()
        .next()
        .ok_or_else(|| StageError::param("outs", "must list at least one output"))?;
    let out_dir = first
        .parent()
        .ok_or_else(|| StageError::failed("output path has no parent"))?
        .to_path_buf();
    let outs: BTreeMap<String, PathBuf> = ctx.outputs.clone();
    let argv: Vec<String> = cmd
        .iter()
        .map(|a| substitute(a, &ctx.inputs, &outs, &out_dir))
        .collect();
    // Logs live next to (not inside) the output directory, so they are not outputs.
    let log_dir = out_dir.parent().unwrap_or(&out_dir).to_path_buf();
    let stdout_path = log_dir.join("stdout.log");
    let stderr_path = log_dir.join("stderr.log");
    let stdout = File::create(&stdout_path).map_err(|e| StageError::io(&stdout_path, e))?;
    let stderr = File::create(&stderr_path).map_err(|e| StageError::io(&stderr_path, e))?;
    let mut command = std::process::Command::new(&argv[0]);
    command
        .args(&argv[1..])
        .current_dir(&out_dir)
        .env("FURE_OUT", &out_dir)
        .stdin(std::process::Stdio::null())
        .stdout(stdout)
        .stderr(stderr);
    for (k, v) in &env {
        if let Some(s) = v.as_str() {
            command.env(k, s);
        }
    }
    ctx.progress.message(&format!("running {}", argv[0]));
    let child = command
        .spawn()
        .map_err(|e| StageError::failed(format!("cannot start `{}`: {e}", argv[0])))?;
    let (status, peak) = wait_child(child)?;
    if let Some(msg) = status {
        let tail = tail_of(&stderr_path);
        return Err(StageError::failed(format!(
            "`{}` {msg}{}",
            argv.join(" "),
            if tail.is_empty() {
                String::new()
            } else {
                format!("; stderr tail:\n{tail}")
            }
        )));
    }
    for (port, path) in &ctx.outputs {
        if !path.exists() {
            let tail = tail_of(&stderr_path);
            return Err(StageError::failed(format!(
                "`{}` exited successfully but did not create its declared output `{port}`{}",
                argv.join(" "),
                if tail.is_empty() {
                    String::new()
                } else {
                    format!("; stderr tail:\n{tail}")
                }
            )));
        }
    }
    Ok(peak)
}

/// Waits for the child with `wait4` to get its peak RSS. Returns a failure
/// description (None for exit status 0) and the peak RSS in bytes.
fn wait_child(child: std::process::Child) -> Result<(Option<String>, u64), StageError> {
    let pid = child.id() as libc::pid_t;
    let mut status: libc::c_int = 0;
    // SAFETY: rusage is plain old data; wait4 fills it.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    loop {
        // SAFETY: waiting on our own child with valid out-pointers.
        let r = unsafe { libc::wait4(pid, &mut status, 0, &mut usage) };
        if r == pid {
            break;
        }
        let err = std::io::Error::last_os_error();
        if err.kind() == std::io::ErrorKind::Interrupted {
            continue;
        }
        return Err(StageError::failed(format!(
            "waiting for the command: {err}"
        )));
    }
    // The child is reaped; dropping the handle neither waits nor kills.
    drop(child);
    let peak = (usage.ru_maxrss.max(0) as u64) * 1024;
    let msg = if libc::WIFEXITED(status) {
        match libc::WEXITSTATUS(status) {
            0 => None,
            c => Some(format!("exited with status {c}")),
        }
    } else if libc::WIFSIGNALED(status) {
        Some(format!("was killed by signal {}", libc::WTERMSIG(status)))
    } else {
        Some("ended abnormally".to_string())
    };
    Ok((msg, peak))
}

fn tail_of(path: &Path) -> String {
    let Ok(mut f) = File::open(path) else {
        return String::new();
    };
    let len = f.metadata().map(|m| m.len()).unwrap_or(0);
    let start = len.saturating_sub(STDERR_TAIL);
    if f.seek(SeekFrom::Start(start)).is_err() {
        return String::new();
    }
    let mut buf = Vec::new();
    let _ = f.read_to_end(&mut buf);
    String::from_utf8_lossy(&buf).trim_end().to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn substitutes_known_placeholders_only() {
        let mut deps = BTreeMap::new();
        deps.insert("a".to_string(), PathBuf::from("/x/a.txt"));
        let mut outs = BTreeMap::new();
        outs.insert("o.txt".to_string(), PathBuf::from("/o/o.txt"));
        let s = substitute(
            "cat {deps.a} > {outs.o.txt}; echo ${HOME} {out}",
            &deps,
            &outs,
            Path::new("/o"),
        );
        assert_eq!(s, "cat /x/a.txt > /o/o.txt; echo ${HOME} /o");
        assert_eq!(
            placeholders("{deps.a}{x}{outs.b}"),
            vec!["deps.a", "outs.b"]
        );
    }

    #[test]
    fn validate_rejects_bad_outs_and_placeholders() {
        let mk = |cmd: &[&str], outs: &[&str]| {
            let mut p = Params::default();
            let l = |v: &[&str]| {
                fure_stage_api::Value::List(
                    v.iter()
                        .map(|s| fure_stage_api::Value::Str(s.to_string()))
                        .collect(),
                )
            };
            p.0.insert("cmd".into(), l(cmd));
            p.0.insert("outs".into(), l(outs));
            p.0.insert("deps".into(), l(&[]));
            CommandStage.validate(&p)
        };
        assert!(mk(&["true"], &["a.txt"]).is_ok());
        assert!(mk(&["true"], &["../a.txt"]).is_err());
        assert!(mk(&["true"], &[]).is_err());
        assert!(mk(&["cat", "{deps.zz}"], &["a.txt"]).is_err());
        assert!(mk(&[], &["a.txt"]).is_err());
    }
}
