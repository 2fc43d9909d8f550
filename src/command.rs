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
//!   directory, so `outs` are written by relative name. The environment also
//!   holds `FURE_OUT`.
//! - Placeholders in `cmd` (each argument is scanned on its own):
//!   `{deps.NAME}` is the absolute path of a dependency, `{outs.NAME}` of an
//!   output, `{out}` the output directory; they are recognised anywhere in an
//!   argument, inside shell groups and quotes included. `{{` is a literal `{`
//!   (so `{{deps.x}` is the text `{deps.x}`). A `{` right after `$` is the
//!   shell's (`${VAR}`). Any other `{` followed by a name (letters, digits,
//!   `_`, `-`, `.`) and `}`, such as `{dep.x}` or awk's `{print}`, is an
//!   error at load time, as is a `{deps.`/`{outs.` without its `}` or naming
//!   nothing declared; write `{{print}` for the literal text. Every other
//!   brace is literal (`{ a; b; }`, `{a,b}`, JSON).
//! - The command runs in its own process group, with `PR_SET_PDEATHSIG`, and a
//!   watchdog process (forked, async-signal-safe code only) that kills the
//!   whole group when the command ends, when its `timeout` expires (SIGTERM,
//!   SIGKILL 2 s later) or when fure dies in any way (the watchdog's pipe
//!   closes). So no process of a stage outlives it, and SIGINT/SIGTERM/SIGHUP
//!   sent to fure are forwarded to the group (`signals`).
//! - stdout is discarded; stderr is kept in memory, its last 64 KiB only. A
//!   non-zero exit, death by signal, a timeout or a missing declared output
//!   fails the stage with the tail of stderr, and the engine caches nothing.
//! - `timeout` (seconds) does not enter the key: a result is the same
//!   whatever the limit it was computed under.
//! - Peak memory is the child's maximum resident set size from `wait4`.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::Read;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};

use fure_stage_api::{ParamSpec, Params, PortSpec, Stage, StageContext, StageError};

/// The `command` stage kind.
pub struct CommandStage;

pub const KIND: &str = "command";

/// How many bytes of stderr a failure message shows.
const STDERR_TAIL: usize = 2000;

/// How many bytes of stderr are kept while a command runs (the rest is dropped).
const STDERR_KEEP: usize = 64 * 1024;

/// Grace between SIGTERM and SIGKILL when a timeout expires.
const TIMEOUT_GRACE_MS: i64 = 2000;

/// The parameter that bounds a command's run time (not part of the key).
pub const TIMEOUT_PARAM: &str = "timeout";

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
         substituted as {outs.NAME}; {out} is the output directory; `{{` is a literal brace. \
         Fails with the tail of stderr when the program fails, times out or does not write \
         its outputs."
    }
    fn params(&self) -> Vec<ParamSpec> {
        vec![
            ParamSpec::str_list(
                "cmd",
                &[],
                "argv of the program; {deps.NAME}, {outs.NAME} and {out} are substituted, {{ is a literal {",
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
            ParamSpec::optional(
                TIMEOUT_PARAM,
                fure_stage_api::ParamType::Float,
                "seconds the program may run before it is killed (a failure); not part of the key",
            )
            .positive(),
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
        for (k, arg) in cmd.iter().enumerate() {
            let bad = |col: usize, m: String| {
                StageError::param("cmd", format!("argument {k} ({arg:?}), column {col}: {m}"))
            };
            for piece in parse_arg(arg).map_err(|(col, m)| bad(col, m))? {
                let (ok, what, name, col) = match piece {
                    Piece::Dep(n, col) => (deps.iter().any(|d| d == n), "dependency", n, col),
                    Piece::Output(n, col) => (
                        outs.iter().any(|o| o.strip_suffix('/').unwrap_or(o) == n),
                        "output",
                        n,
                        col,
                    ),
                    _ => continue,
                };
                if !ok {
                    return Err(bad(
                        col,
                        format!("placeholder names no declared {what} `{name}`"),
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

/// One piece of a `cmd` argument.
#[derive(Debug, PartialEq)]
enum Piece<'a> {
    Text(&'a str),
    /// `{out}`
    OutDir,
    /// `{deps.NAME}` (name, 1-based column of the `{`)
    Dep(&'a str, usize),
    /// `{outs.NAME}`
    Output(&'a str, usize),
}

/// Splits an argument into text and placeholders (grammar in the module
/// doc). Err is (1-based character column, message).
fn parse_arg(arg: &str) -> Result<Vec<Piece<'_>>, (usize, String)> {
    let col = |i: usize| arg[..i].chars().count() + 1;
    let b = arg.as_bytes();
    let mut out = Vec::new();
    let mut start = 0;
    let mut i = 0;
    while i < b.len() {
        if b[i] != b'{' {
            i += 1;
            continue;
        }
        if b.get(i + 1) == Some(&b'{') {
            // `{{`: one literal brace.
            out.push(Piece::Text(&arg[start..i + 1]));
            i += 2;
            start = i;
            continue;
        }
        if i > 0 && b[i - 1] == b'$' {
            i += 1;
            continue;
        }
        let rest = &arg[i + 1..];
        let reserved = ["deps.", "outs."].iter().find(|p| rest.starts_with(**p));
        if reserved.is_some() || rest.starts_with("out}") {
            let Some(j) = rest.find('}') else {
                return Err((
                    col(i),
                    format!("placeholder `{{{rest}` has no closing `}}`"),
                ));
            };
            let inner = &rest[..j];
            if i > start {
                out.push(Piece::Text(&arg[start..i]));
            }
            out.push(match inner.split_once('.') {
                None => Piece::OutDir,
                Some(("deps", n)) => Piece::Dep(n, col(i)),
                Some((_, n)) => Piece::Output(n, col(i)),
            });
            i += j + 2;
            start = i;
            continue;
        }
        let name_len = rest
            .bytes()
            .take_while(|c| c.is_ascii_alphanumeric() || matches!(c, b'_' | b'-' | b'.'))
            .count();
        if name_len > 0 && rest.as_bytes().get(name_len) == Some(&b'}') {
            return Err((
                col(i),
                format!(
                    "unknown placeholder `{{{}}}` (expected {{out}}, {{deps.NAME}} or \
                     {{outs.NAME}}; write `{{{{` for a literal brace)",
                    &rest[..name_len]
                ),
            ));
        }
        i += 1;
    }
    if start < b.len() {
        out.push(Piece::Text(&arg[start..]));
    }
    Ok(out)
}

/// Substitutes the placeholders of a (validated) argument.
fn substitute(
    arg: &str,
    deps: &BTreeMap<String, PathBuf>,
    outs: &BTreeMap<String, PathBuf>,
    out_dir: &Path,
) -> Result<String, StageError> {
    let pieces = parse_arg(arg)
        .map_err(|(c, m)| StageError::param("cmd", format!("{arg:?}, column {c}: {m}")))?;
    let mut s = String::with_capacity(arg.len());
    for p in pieces {
        let path = match p {
            Piece::Text(t) => {
                s.push_str(t);
                continue;
            }
            Piece::OutDir => Some(out_dir),
            Piece::Dep(n, _) => deps.get(n).map(PathBuf::as_path),
            Piece::Output(n, _) => outs.get(n).map(PathBuf::as_path),
        };
        let path = path.ok_or_else(|| {
            StageError::param(
                "cmd",
                format!("{arg:?}: a placeholder names nothing declared"),
            )
        })?;
        s.push_str(&path.display().to_string());
    }
    Ok(s)
}

/// Runs the command of `ctx`; returns the child's peak RSS in bytes.
pub fn run_command(ctx: &StageContext<'_>) -> Result<u64, StageError> {
    let cmd = ctx.params.str_list("cmd")?;
    let env = ctx.params.table("env")?;
    let timeout = ctx.params.f64_opt(TIMEOUT_PARAM)?;
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
        .collect::<Result<_, _>>()?;
    let (err_r, err_w) =
        pipe().map_err(|e| StageError::failed(format!("cannot make a pipe: {e}")))?;
    let mut command = std::process::Command::new(&argv[0]);
    command
        .args(&argv[1..])
        .current_dir(&out_dir)
        .env("FURE_OUT", &out_dir)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::from(err_w))
        // Its own group: forwarded signals and the watchdog reach all of it.
        .process_group(0);
    for (k, v) in &env {
        if let Some(s) = v.as_str() {
            command.env(k, s);
        }
    }
    let parent = std::process::id() as libc::pid_t;
    // SAFETY: only async-signal-safe calls between fork and exec.
    unsafe {
        command.pre_exec(move || {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL as libc::c_ulong) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            // fure died before the prctl: do not run orphaned.
            if libc::getppid() != parent {
                return Err(std::io::Error::from_raw_os_error(libc::ESRCH));
            }
            Ok(())
        });
    }
    ctx.progress.message(&format!("running {}", argv[0]));
    let child = command
        .spawn()
        .map_err(|e| StageError::failed(format!("cannot start `{}`: {e}", argv[0])))?;
    // The parent's copy of the write end must go, or the reader never sees EOF.
    drop(command);
    let pid = child.id() as libc::pid_t;
    let _forward = crate::signals::register(pid);
    let tail = StderrTail::start(err_r);
    let watchdog = Watchdog::start(pid, timeout);
    let (status, peak, timed_out) = wait_child(child, watchdog)?;
    let tail = tail.finish();
    let with_tail = |msg: String| {
        StageError::failed(if tail.is_empty() {
            msg
        } else {
            format!("{msg}; stderr tail:\n{tail}")
        })
    };
    if timed_out {
        return Err(with_tail(format!(
            "`{}` timed out after {} s (timeout) and was killed",
            argv.join(" "),
            timeout.unwrap_or(0.0)
        )));
    }
    if let Some(msg) = status {
        return Err(with_tail(format!("`{}` {msg}", argv.join(" "))));
    }
    // Its group got the signal (or it ended as the signal came): a command
    // that traps it and exits 0, or a shell whose killed step it outlives
    // (`sleep 60; echo done`), leaves outputs that must not be stored.
    if let Some(sig) = crate::signals::received() {
        return Err(with_tail(format!(
            "`{}` exited with status 0 after fure was interrupted by {}; its outputs may be \
             partial and are not stored",
            argv.join(" "),
            crate::signals::name(sig)
        )));
    }
    for (port, path) in &ctx.outputs {
        if std::fs::symlink_metadata(path).is_err() {
            return Err(with_tail(format!(
                "`{}` exited successfully but did not create its declared output `{port}`",
                argv.join(" ")
            )));
        }
    }
    Ok(peak)
}

/// A pipe with both ends close-on-exec (the child gets a dup of the write end).
fn pipe() -> std::io::Result<(std::os::fd::OwnedFd, std::os::fd::OwnedFd)> {
    use std::os::fd::FromRawFd;
    let mut fds = [0 as libc::c_int; 2];
    // SAFETY: fds is a valid two-element array.
    if unsafe { libc::pipe2(fds.as_mut_ptr(), libc::O_CLOEXEC) } != 0 {
        return Err(std::io::Error::last_os_error());
    }
    // SAFETY: both descriptors are fresh and owned by nobody else.
    Ok(unsafe {
        (
            std::os::fd::OwnedFd::from_raw_fd(fds[0]),
            std::os::fd::OwnedFd::from_raw_fd(fds[1]),
        )
    })
}

/// Reads a command's stderr on a thread, keeping only the last
/// [`STDERR_KEEP`] bytes (a chatty or runaway command cannot fill memory or
/// disk, and the tail survives a full disk).
struct StderrTail {
    done: std::sync::mpsc::Receiver<Vec<u8>>,
}

impl StderrTail {
    fn start(fd: std::os::fd::OwnedFd) -> StderrTail {
        let (tx, rx) = std::sync::mpsc::channel();
        let _ = std::thread::Builder::new()
            .name("fure-stderr".into())
            .spawn(move || {
                let mut f = File::from(fd);
                let mut keep: Vec<u8> = Vec::new();
                let mut buf = vec![0u8; 16 * 1024];
                loop {
                    match f.read(&mut buf) {
                        Ok(0) => break,
                        Ok(n) => {
                            keep.extend_from_slice(&buf[..n]);
                            if keep.len() > 2 * STDERR_KEEP {
                                keep.drain(..keep.len() - STDERR_KEEP);
                            }
                        }
                        Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                        Err(_) => break,
                    }
                }
                let _ = tx.send(keep);
            });
        StderrTail { done: rx }
    }

    /// The last [`STDERR_TAIL`] bytes, trimmed. Waits a moment for EOF: a
    /// process that left the group may hold the pipe open forever.
    fn finish(self) -> String {
        let keep = self
            .done
            .recv_timeout(std::time::Duration::from_secs(2))
            .unwrap_or_default();
        let mut start = keep.len().saturating_sub(STDERR_TAIL);
        // Start at a character boundary (continuation bytes are 10xxxxxx).
        while start < keep.len() && start > 0 && (keep[start] & 0xc0) == 0x80 {
            start += 1;
        }
        String::from_utf8_lossy(&keep[start..])
            .trim_end()
            .to_string()
    }
}

/// A forked process that kills a command's process group when its pipe
/// closes (the command ended and fure closed it, or fure died) or when the
/// timeout expires. It exits 0, or 2 after a timeout.
struct Watchdog {
    pid: libc::pid_t,
    /// Closing it tells the watchdog to kill the group and exit.
    pipe: Option<std::os::fd::OwnedFd>,
}

impl Watchdog {
    fn start(pgid: libc::pid_t, timeout: Option<f64>) -> Option<Watchdog> {
        use std::os::fd::AsRawFd;
        let (r, w) = pipe().ok()?;
        let rfd = r.as_raw_fd();
        let limit_ms: i64 = timeout.map(|t| (t * 1000.0).ceil() as i64).unwrap_or(-1);
        // SAFETY: the child runs only async-signal-safe calls (sigaction via
        // signal, close_range, clock_gettime, poll, read, kill, _exit) and
        // never returns into Rust code.
        let pid = unsafe { libc::fork() };
        if pid < 0 {
            return None;
        }
        if pid == 0 {
            unsafe { watchdog_main(rfd, pgid, limit_ms) }
        }
        drop(r);
        Some(Watchdog { pid, pipe: Some(w) })
    }

    /// Tells the watchdog the command is over; whether it had timed out.
    fn finish(mut self) -> bool {
        self.pipe.take();
        let mut status: libc::c_int = 0;
        loop {
            // SAFETY: waiting for our own child.
            let r = unsafe { libc::waitpid(self.pid, &mut status, 0) };
            if r == self.pid {
                return libc::WIFEXITED(status) && libc::WEXITSTATUS(status) == 2;
            }
            if std::io::Error::last_os_error().kind() != std::io::ErrorKind::Interrupted {
                return false;
            }
        }
    }
}

/// Milliseconds on the monotonic clock (async-signal-safe).
unsafe fn now_ms() -> i64 {
    let mut ts: libc::timespec = std::mem::zeroed();
    libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts);
    ts.tv_sec as i64 * 1000 + ts.tv_nsec as i64 / 1_000_000
}

/// Waits until `rfd` is closed by every writer or `until_ms` (monotonic;
/// negative: forever) passes. True if the pipe closed.
unsafe fn wait_closed(rfd: libc::c_int, until_ms: i64) -> bool {
    loop {
        let wait = if until_ms < 0 {
            -1
        } else {
            (until_ms - now_ms()).clamp(0, i32::MAX as i64) as libc::c_int
        };
        let mut p = libc::pollfd {
            fd: rfd,
            events: libc::POLLIN,
            revents: 0,
        };
        let r = libc::poll(&mut p, 1, wait);
        if r == 0 {
            return false;
        }
        if r < 0 {
            if *libc::__errno_location() == libc::EINTR {
                continue;
            }
            return true;
        }
        let mut b = [0u8; 1];
        let n = libc::read(rfd, b.as_mut_ptr().cast(), 1);
        if n == 0 || (n < 0 && *libc::__errno_location() != libc::EINTR) {
            return true;
        }
    }
}

/// The watchdog's body (a forked child of a multi-threaded process: only
/// async-signal-safe calls, no allocation).
unsafe fn watchdog_main(rfd: libc::c_int, pgid: libc::pid_t, limit_ms: i64) -> ! {
    // Signals for fure are not for its watchdog (fure forwards them).
    for sig in [libc::SIGINT, libc::SIGTERM, libc::SIGHUP, libc::SIGQUIT] {
        libc::signal(sig, libc::SIG_IGN);
    }
    // Hold no other descriptor: neither another watchdog's pipe nor a lock.
    let r = rfd as libc::c_uint;
    for (lo, hi) in [(3, r.saturating_sub(1)), (r + 1, libc::c_uint::MAX)] {
        if lo <= hi && libc::syscall(libc::SYS_close_range, lo, hi, 0) != 0 {
            for fd in lo..=hi.min(65535) {
                libc::close(fd as libc::c_int);
            }
        }
    }
    let deadline = if limit_ms < 0 {
        -1
    } else {
        now_ms() + limit_ms
    };
    if wait_closed(rfd, deadline) {
        libc::kill(-pgid, libc::SIGKILL);
        libc::_exit(0);
    }
    libc::kill(-pgid, libc::SIGTERM);
    wait_closed(rfd, now_ms() + TIMEOUT_GRACE_MS);
    libc::kill(-pgid, libc::SIGKILL);
    libc::_exit(2)
}

/// Waits for the child (`waitid` without reaping, so its pid and group id
/// stay reserved while the watchdog kills what is left of the group), then
/// reaps it with `wait4` for its peak RSS. Returns a failure description
/// (None for exit status 0), the peak RSS in bytes, and whether it timed out.
fn wait_child(
    child: std::process::Child,
    watchdog: Option<Watchdog>,
) -> Result<(Option<String>, u64, bool), StageError> {
    let pid = child.id() as libc::pid_t;
    loop {
        // SAFETY: siginfo is plain old data; waiting on our own child.
        let mut info: libc::siginfo_t = unsafe { std::mem::zeroed() };
        let r = unsafe {
            libc::waitid(
                libc::P_PID,
                pid as libc::id_t,
                &mut info,
                libc::WEXITED | libc::WNOWAIT,
            )
        };
        if r == 0 {
            break;
        }
        let err = std::io::Error::last_os_error();
        if err.kind() != std::io::ErrorKind::Interrupted {
            return Err(StageError::failed(format!(
                "waiting for the command: {err}"
            )));
        }
    }
    let timed_out = watchdog.map(Watchdog::finish).unwrap_or(false);
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
        let sig = libc::WTERMSIG(status);
        Some(match crate::signals::received() {
            Some(s) if s == sig => format!(
                "was stopped by {} (forwarded: fure was interrupted)",
                crate::signals::name(sig)
            ),
            _ => format!("was killed by signal {sig} ({})", crate::signals::name(sig)),
        })
    } else {
        Some("ended abnormally".to_string())
    };
    Ok((msg, peak, timed_out))
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
        )
        .unwrap();
        assert_eq!(s, "cat /x/a.txt > /o/o.txt; echo ${HOME} /o");
        // Inside a shell group, with an escaped brace and JSON around.
        let s = substitute(
            "{ cat {deps.a}; echo end; } > b.txt; echo {{deps.a} '{\"k\": {\"v\": 1}}' {a,b}",
            &deps,
            &outs,
            Path::new("/o"),
        )
        .unwrap();
        assert_eq!(
            s,
            "{ cat /x/a.txt; echo end; } > b.txt; echo {deps.a} '{\"k\": {\"v\": 1}}' {a,b}"
        );
        for (arg, col, what) in [
            ("x {x}", 3, "unknown placeholder `{x}`"),
            ("awk '{print}'", 6, "unknown placeholder `{print}`"),
            ("{ cat {deps.a ;", 7, "has no closing"),
            ("{dep.a}", 1, "unknown placeholder `{dep.a}`"),
        ] {
            let (c, m) = parse_arg(arg).unwrap_err();
            assert_eq!(c, col, "{arg}");
            assert!(m.contains(what), "{arg}: {m}");
        }
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
        // In a shell group the placeholder is still seen (and checked).
        let e = mk(
            &["sh", "-c", "{ cat {deps.undeclared}; echo end; } > b.txt"],
            &["b.txt"],
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("argument 2") && e.contains("column 7"), "{e}");
        assert!(e.contains("no declared dependency `undeclared`"), "{e}");
        assert!(mk(
            &["sh", "-c", "{ echo; } > a.txt; echo {{print}"],
            &["a.txt"]
        )
        .is_ok());
        assert!(mk(&["echo", "{outs.b.txt}"], &["a.txt"]).is_err());
        assert!(mk(&["echo", "{outs.a.txt}{out}"], &["a.txt"]).is_ok());
        assert!(mk(&[], &["a.txt"]).is_err());
    }
}
