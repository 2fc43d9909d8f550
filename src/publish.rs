//! `[publish]`: copies aggregate outputs of a sweep out of `out/`, to where a
//! project keeps its generated documents (`docs/results.md`).
//!
//! ```toml
//! [publish]
//! "report.results" = "../docs/results.md"   # AGGREGATE.PORT = destination
//! "report.charts"  = "../docs/benchmark"    # a directory port: its files
//! "report.headline" = "../README.md#benchmark-headline"   # a section of a file
//! ```
//!
//! A destination `FILE#SECTION` replaces only the lines between
//! `<!-- fure:begin SECTION -->` and `<!-- fure:end SECTION -->` in an existing
//! hand-written FILE (the README quotes the suite's headline table this way,
//! so the table is generated while the prose around it is not). The markers
//! are checked before anything runs: a missing or repeated marker is an error
//! that names the file and the marker, not a surprise after a two-hour suite.
//!
//! Destinations are relative to the file that declares them. Aggregate
//! outputs are cached and must be deterministic, so they cannot say when, where
//! and from which revision they were made; the published copy can. A text
//! file (`.md`, `.txt`, `.csv`, `.json` is left as is) whose line is exactly
//! [`PROVENANCE_MARK`] gets that line replaced by the provenance: date (UTC),
//! machine, git revision (and whether the tree was dirty) and the exact
//! command. Every destination is written to a temporary name beside it and
//! renamed, so a reader never sees half a document; any failure is an error
//! (the sweep exits 1). `fure sweep` publishes only the sweep as declared: one
//! changed by `--grid`, `--each` or `--set` leaves the documents alone, and so
//! does one with a failed variant unless `--publish-failed` asks for it (a
//! partial report must not silently replace a complete one).

use std::path::{Path, PathBuf};

use crate::exec::RunReport;
use crate::pipeline::Pipeline;

/// The line a published Markdown file carries where the provenance goes.
pub const PROVENANCE_MARK: &str = "<!-- fure:provenance -->";

/// Why publishing failed.
#[derive(Debug, thiserror::Error)]
pub enum PublishError {
    #[error("{loc}: publish `{key}`: no aggregate stage `{aggregate}` (aggregates: {have})")]
    NoAggregate {
        loc: String,
        key: String,
        aggregate: String,
        have: String,
    },
    #[error("publish `{key}`: aggregate `{aggregate}` has no output `{port}` (outputs: {have}); it may have failed")]
    NoOutput {
        key: String,
        aggregate: String,
        port: String,
        have: String,
    },
    #[error(
        "{loc}: publish `{key}`: {path}: expected exactly one line `<!-- fure:begin {section} -->` \
         followed by one line `<!-- fure:end {section} -->` ({found})"
    )]
    Markers {
        loc: String,
        key: String,
        path: PathBuf,
        section: String,
        found: String,
    },
    #[error("publish `{key}`: {path}: {source}")]
    Io {
        key: String,
        path: PathBuf,
        source: std::io::Error,
    },
}

/// Who, where and when: the lines that replace [`PROVENANCE_MARK`].
pub fn provenance(command: &str, repo_dir: &Path) -> String {
    let o = Origin::here(repo_dir, command);
    format!(
        "Generated {} by `{}` at revision {}{} on {}, fure {}.",
        o.date,
        o.command,
        o.revision,
        if o.dirty {
            " (uncommitted changes)"
        } else {
            ""
        },
        o.machine,
        env!("CARGO_PKG_VERSION"),
    )
}

/// Where, when and by which command something was made: the git revision of the repository
/// holding the pipeline (and whether its tree had uncommitted changes), the date, the machine.
#[derive(Debug, Clone, PartialEq)]
pub struct Origin {
    pub revision: String,
    pub dirty: bool,
    pub date: String,
    pub machine: String,
    pub command: String,
}

impl Origin {
    /// This process: the git revision of `repo_dir`, now, this machine, `command`.
    pub fn here(repo_dir: &Path, command: &str) -> Origin {
        let m = crate::bench::machine();
        let (revision, dirty) = crate::bench::git_revision(repo_dir);
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_secs())
            .unwrap_or(0);
        Origin {
            revision,
            dirty,
            date: utc_timestamp(now),
            machine: format!(
                "{} ({} cores, {:.0} GiB, {})",
                m.cpu_model,
                m.cores,
                m.memory_bytes as f64 / (1u64 << 30) as f64,
                m.os
            ),
            command: command.to_string(),
        }
    }
}

/// `YYYY-MM-DD HH:MM UTC` of a Unix time (civil-from-days, proleptic Gregorian).
pub fn utc_timestamp(secs: u64) -> String {
    let days = (secs / 86_400) as i64;
    let rem = secs % 86_400;
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02} {:02}:{:02} UTC",
        rem / 3600,
        (rem % 3600) / 60
    )
}

/// Checks every `[publish]` key names an aggregate and every `FILE#SECTION`
/// destination has its markers (before anything runs).
pub fn check(pipeline: &Pipeline) -> Result<(), PublishError> {
    for (key, (dest, loc)) in &pipeline.publish {
        if let Some((file, section)) = section_of(dest) {
            let text = std::fs::read_to_string(&file).map_err(|source| PublishError::Io {
                key: key.clone(),
                path: file.clone(),
                source,
            })?;
            splice(&text, &section, "")
                .map_err(|found| markers_error(key, loc, &file, &section, found))?;
        }
        let aggregate = key.split_once('.').map(|(a, _)| a).unwrap_or(key);
        if !pipeline.aggregates.iter().any(|a| a.name == aggregate) {
            return Err(PublishError::NoAggregate {
                loc: loc.to_string(),
                key: key.clone(),
                aggregate: aggregate.to_string(),
                have: pipeline
                    .aggregates
                    .iter()
                    .map(|a| a.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", "),
            });
        }
    }
    Ok(())
}

/// Copies each `[publish]` output of the aggregates' run report to its
/// destination; returns the destinations written.
pub fn publish(
    pipeline: &Pipeline,
    report: &RunReport,
    provenance: &str,
) -> Result<Vec<PathBuf>, PublishError> {
    let mut written = Vec::new();
    for (key, (dest, _)) in &pipeline.publish {
        let (aggregate, port) = key.split_once('.').unwrap_or((key, ""));
        let stage = report.stages.iter().find(|s| s.name == aggregate);
        let output = stage.and_then(|s| s.outputs.get(port));
        let Some(output) = output else {
            return Err(PublishError::NoOutput {
                key: key.clone(),
                aggregate: aggregate.into(),
                port: port.into(),
                have: stage
                    .map(|s| s.outputs.keys().cloned().collect::<Vec<_>>().join(", "))
                    .unwrap_or_default(),
            });
        };
        let io = |path: &Path, source| PublishError::Io {
            key: key.clone(),
            path: path.to_path_buf(),
            source,
        };
        let src = PathBuf::from(&output.path);
        let meta = std::fs::symlink_metadata(&src).map_err(|e| io(&src, e))?;
        if let Some((file, section)) = section_of(dest) {
            if !meta.is_file() {
                let e = std::io::Error::new(
                    std::io::ErrorKind::InvalidInput,
                    "a section destination takes a file output",
                );
                return Err(io(&src, e));
            }
            let part = std::fs::read_to_string(&src).map_err(|e| io(&src, e))?;
            let part = stamp(&part, provenance);
            let text = std::fs::read_to_string(&file).map_err(|e| io(&file, e))?;
            let loc = &pipeline.publish[key].1;
            let spliced = splice(&text, &section, &part)
                .map_err(|found| markers_error(key, loc, &file, &section, found))?;
            write_atomically(&file, spliced.as_bytes()).map_err(|e| io(&file, e))?;
            written.push(file);
        } else if meta.is_dir() {
            std::fs::create_dir_all(dest).map_err(|e| io(dest, e))?;
            let mut names: Vec<_> = std::fs::read_dir(&src)
                .map_err(|e| io(&src, e))?
                .filter_map(Result::ok)
                .filter(|e| e.file_type().map(|t| t.is_file()).unwrap_or(false))
                .map(|e| e.file_name())
                .collect();
            names.sort();
            for n in names {
                let (from, to) = (src.join(&n), dest.join(&n));
                copy_stamped(&from, &to, provenance).map_err(|e| io(&to, e))?;
                written.push(to);
            }
        } else if meta.is_file() {
            if let Some(parent) = dest.parent() {
                std::fs::create_dir_all(parent).map_err(|e| io(parent, e))?;
            }
            copy_stamped(&src, dest, provenance).map_err(|e| io(dest, e))?;
            written.push(dest.clone());
        } else {
            return Err(io(
                &src,
                std::io::Error::new(
                    std::io::ErrorKind::InvalidInput,
                    "not a regular file or directory",
                ),
            ));
        }
    }
    Ok(written)
}

/// `FILE#SECTION` -> (FILE, SECTION); `None` for a plain destination.
fn section_of(dest: &Path) -> Option<(PathBuf, String)> {
    let name = dest.file_name()?.to_str()?;
    let (file, section) = name.split_once('#')?;
    Some((dest.with_file_name(file), section.to_string()))
}

/// The marker lines of a section.
fn markers(section: &str) -> (String, String) {
    (
        format!("<!-- fure:begin {section} -->"),
        format!("<!-- fure:end {section} -->"),
    )
}

fn markers_error(
    key: &str,
    loc: &impl std::fmt::Display,
    file: &Path,
    section: &str,
    found: String,
) -> PublishError {
    PublishError::Markers {
        loc: loc.to_string(),
        key: key.to_string(),
        path: file.to_path_buf(),
        section: section.to_string(),
        found,
    }
}

/// `text` with the lines between the section's markers replaced by `part`
/// (which ends with a newline unless empty); `Err` says what was found instead.
fn splice(text: &str, section: &str, part: &str) -> Result<String, String> {
    let (begin, end) = markers(section);
    let lines: Vec<&str> = text.split('\n').collect();
    let at = |m: &str| -> Vec<usize> {
        lines
            .iter()
            .enumerate()
            .filter(|(_, l)| l.trim_end() == m)
            .map(|(i, _)| i)
            .collect()
    };
    let (b, e) = (at(&begin), at(&end));
    match (b.as_slice(), e.as_slice()) {
        ([b], [e]) if b < e => {
            let mut out = lines[..=*b].join("\n");
            out.push('\n');
            out.push_str(part);
            if !part.is_empty() && !part.ends_with('\n') {
                out.push('\n');
            }
            out.push_str(&lines[*e..].join("\n"));
            Ok(out)
        }
        ([b], [e]) => Err(format!(
            "the end marker is on line {}, before the begin marker on line {}",
            e + 1,
            b + 1
        )),
        _ => Err(format!("{} begin and {} end markers", b.len(), e.len())),
    }
}

/// `text` with every line that is exactly [`PROVENANCE_MARK`] replaced by the provenance.
fn stamp(text: &str, provenance: &str) -> String {
    text.split('\n')
        .map(|l| {
            if l.trim_end() == PROVENANCE_MARK {
                provenance
            } else {
                l
            }
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// Copies `from` to `to` through a temporary name, stamping Markdown files.
fn copy_stamped(from: &Path, to: &Path, provenance: &str) -> std::io::Result<()> {
    let mut bytes = std::fs::read(from)?;
    if to.extension().is_some_and(|e| e == "md") {
        if let Ok(text) = std::str::from_utf8(&bytes) {
            bytes = stamp(text, provenance).into_bytes();
        }
    }
    write_atomically(to, &bytes)
}

/// Writes `to` through a temporary name beside it, so a reader never sees half a file.
fn write_atomically(to: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let tmp = to.with_file_name(format!(
        ".{}.fure-publish-{}",
        to.file_name()
            .map(|n| n.to_string_lossy())
            .unwrap_or_default(),
        std::process::id()
    ));
    let result = std::fs::write(&tmp, bytes).and_then(|()| std::fs::rename(&tmp, to));
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn utc_timestamps() {
        assert_eq!(utc_timestamp(0), "1970-01-01 00:00 UTC");
        assert_eq!(utc_timestamp(951_782_400), "2000-02-29 00:00 UTC");
        assert_eq!(utc_timestamp(1_795_443_180), "2026-11-23 14:13 UTC");
    }

    #[test]
    fn markdown_is_stamped_other_files_are_not() {
        let d = std::env::temp_dir().join(format!("fure-publish-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        let text = format!("# R\n{PROVENANCE_MARK}\n| a |\n");
        std::fs::write(d.join("a.md"), &text).unwrap();
        copy_stamped(&d.join("a.md"), &d.join("b.md"), "stamp").unwrap();
        assert_eq!(
            std::fs::read_to_string(d.join("b.md")).unwrap(),
            "# R\nstamp\n| a |\n"
        );
        copy_stamped(&d.join("a.md"), &d.join("b.txt"), "stamp").unwrap();
        assert_eq!(std::fs::read_to_string(d.join("b.txt")).unwrap(), text);
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn a_section_is_replaced_between_its_markers_only() {
        let readme = "# Title\n\n<!-- fure:begin h -->\nold\ntable\n<!-- fure:end h -->\n\nprose\n";
        assert_eq!(
            splice(readme, "h", "| new |\n").unwrap(),
            "# Title\n\n<!-- fure:begin h -->\n| new |\n<!-- fure:end h -->\n\nprose\n"
        );
        // Splicing twice gives the same file (no marker is lost or doubled).
        let once = splice(readme, "h", "x").unwrap();
        assert_eq!(splice(&once, "h", "x").unwrap(), once);
        assert!(splice(readme, "other", "x")
            .unwrap_err()
            .contains("0 begin and 0 end"));
        let swapped = "<!-- fure:end h -->\n<!-- fure:begin h -->\n";
        assert!(splice(swapped, "h", "x")
            .unwrap_err()
            .contains("before the begin"));
        let twice = format!("{readme}{readme}");
        assert!(splice(&twice, "h", "x")
            .unwrap_err()
            .contains("2 begin and 2 end"));
        assert_eq!(
            section_of(Path::new("/a/README.md#bench")),
            Some((PathBuf::from("/a/README.md"), "bench".to_string()))
        );
        assert_eq!(section_of(Path::new("/a/results.md")), None);
    }
}
