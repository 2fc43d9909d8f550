//! What a run prints: one line per stage event, with progress bars on a terminal.
//!
//! Plain mode (stdout is not a terminal, or `--plain`) prints stable lines
//! that scripts may parse:
//!
//! ```text
//! cached  NAME  key 1a2b3c4d5e6f  (reason)
//! run     NAME  (reason)
//! note    NAME  text                 (what a stage chose to report)
//! done    NAME  1.23s
//! failed  NAME  error text
//! skipped NAME  (reason)
//! ```
//!
//! Terminal mode shows the same lines above live progress bars (indicatif),
//! fed by stages through [`fure_stage_api::Progress`].

use std::io::IsTerminal;
use std::sync::Mutex;

use fure_stage_api::Progress;
use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};

/// Output style.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UiMode {
    /// Progress bars (stdout is a terminal).
    Tty,
    /// Plain lines.
    Plain,
    /// Nothing but failures (library use, benchmarks).
    Quiet,
}

impl UiMode {
    /// Terminal mode when stdout is a terminal, plain lines otherwise.
    pub fn detect() -> UiMode {
        if std::io::stdout().is_terminal() {
            UiMode::Tty
        } else {
            UiMode::Plain
        }
    }
}

/// Prints run events.
pub struct Ui {
    mode: UiMode,
    multi: Option<MultiProgress>,
    lock: Mutex<()>,
}

impl Ui {
    pub fn new(mode: UiMode) -> Ui {
        let multi = (mode == UiMode::Tty)
            .then(|| MultiProgress::with_draw_target(ProgressDrawTarget::stdout()));
        Ui {
            mode,
            multi,
            lock: Mutex::new(()),
        }
    }

    /// Prints a line (above the bars in terminal mode).
    pub fn line(&self, text: &str) {
        if self.mode == UiMode::Quiet {
            return;
        }
        let _g = self.lock.lock().unwrap_or_else(|e| e.into_inner());
        match &self.multi {
            Some(m) => {
                let _ = m.println(text);
            }
            None => println!("{text}"),
        }
    }

    /// Prints a failure line (always, also in quiet mode, on stderr there).
    pub fn error_line(&self, text: &str) {
        if self.mode == UiMode::Quiet {
            eprintln!("{text}");
        } else {
            self.line(text);
        }
    }

    pub fn cached(&self, name: &str, key: &str, reason: &str) {
        let k = crate::cache::short(key);
        if reason.is_empty() {
            self.line(&format!("cached  {name}  key {k}"));
        } else {
            self.line(&format!("cached  {name}  key {k}  ({reason})"));
        }
    }

    /// A stage starts; the returned progress sink feeds its bar.
    pub fn started(&self, name: &str, reason: &str) -> StageProgress {
        self.line(&format!("run     {name}  ({reason})"));
        let bar = self.multi.as_ref().map(|m| {
            let b = m.add(ProgressBar::new_spinner());
            b.set_style(
                ProgressStyle::with_template("{spinner} {prefix} {msg} [{elapsed}]")
                    .unwrap_or_else(|_| ProgressStyle::default_spinner()),
            );
            b.set_prefix(name.to_string());
            b.enable_steady_tick(std::time::Duration::from_millis(120));
            b
        });
        StageProgress {
            name: name.to_string(),
            bar,
            ui_mode: self.mode,
            notes: Default::default(),
        }
    }

    pub fn done(&self, name: &str, seconds: f64, progress: StageProgress) {
        if let Some(b) = progress.bar {
            b.finish_and_clear();
        }
        self.line(&format!("done    {name}  {seconds:.2}s"));
    }

    pub fn failed(&self, name: &str, error: &str, progress: Option<StageProgress>) {
        if let Some(b) = progress.and_then(|p| p.bar) {
            b.finish_and_clear();
        }
        self.error_line(&format!("failed  {name}  {error}"));
    }

    pub fn skipped(&self, name: &str, reason: &str) {
        self.line(&format!("skipped {name}  ({reason})"));
    }

    pub fn will_run(&self, name: &str, reason: &str) {
        self.line(&format!("will run {name}  ({reason})"));
    }
}

/// The progress sink handed to one running stage.
pub struct StageProgress {
    name: String,
    bar: Option<ProgressBar>,
    ui_mode: UiMode,
    /// Every note, in order, for the cache entry and the run report.
    notes: std::sync::Mutex<Vec<String>>,
}

impl StageProgress {
    /// The notes the stage wrote so far, in order.
    pub fn notes(&self) -> Vec<String> {
        self.notes.lock().map(|n| n.clone()).unwrap_or_default()
    }
}

impl Progress for StageProgress {
    fn set_total(&self, total: u64) {
        if let Some(b) = &self.bar {
            b.set_length(total);
            b.set_style(
                ProgressStyle::with_template(
                    "{prefix} [{bar:30}] {pos}/{len} {msg} [{elapsed}<{eta}]",
                )
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> "),
            );
        }
    }
    fn advance(&self, delta: u64) {
        if let Some(b) = &self.bar {
            b.inc(delta);
        }
    }
    fn message(&self, text: &str) {
        if let Some(b) = &self.bar {
            b.set_message(text.to_string());
        }
    }
    fn note(&self, text: &str) {
        if let Ok(mut n) = self.notes.lock() {
            n.push(text.to_string());
        }
        let line = format!("note    {}  {text}", self.name);
        match (&self.bar, self.ui_mode) {
            (Some(b), _) => b.println(line),
            (None, UiMode::Plain) => println!("{line}"),
            _ => {}
        }
    }
    fn interrupted(&self) -> bool {
        crate::signals::received().is_some()
    }
}
