//! Pipeline files: TOML parsing with source locations, `extends`, `[sweep]`
//! and `--set` overrides.
//!
//! A pipeline file is
//!
//! ```toml
//! extends = "base.toml"          # optional, relative to this file
//! [pipeline]
//! name = "tiger"                 # optional, defaults to the file stem
//! description = "..."            # optional
//! [stages.NAME]
//! kind = "..."                   # required unless inherited
//! inputs = { port = "OTHER.port", other = "data/file.png" }
//! param = 1.5                    # every other key is a parameter
//! [sweep]                       # crossed axes (cartesian product)
//! "NAME.param" = [1.0, 2.0]
//! [sweep.each]                  # axes varied one at a time (see `crate::sweep`)
//! "NAME.other" = [0.0, 0.1, 0.2]
//! [aggregate.report]            # stages run by `fure sweep` on the sweep record
//! kind = "..."                  # kind and parameters only: no `inputs`
//! [publish]                     # aggregate outputs copied out of out/ (`crate::publish`)
//! "report.results" = "../docs/results.md"
//! ```
//!
//! Parsing is purely syntactic: it keeps every value with the file, line and
//! column it came from (so that [`crate::plan`] can point at the culprit), and
//! it does not yet know which stage kinds exist. Input strings are resolved by
//! the planner because only it knows the full set of stage names after
//! `extends` and overrides: `A.B` is a reference to output `B` of stage `A`
//! when a stage `A` exists, otherwise it is a file path relative to the
//! directory of the file that wrote it.
//!
//! `extends` merges field by field: the child's `kind` replaces the parent's,
//! its parameters and inputs replace the parent's one by one, its `[sweep]`
//! and `[sweep.each]` entries replace the parent's by key (a key moves to the
//! child's kind of axis; a replaced `each` key keeps its position, new ones
//! come after the parent's), its `[aggregate.NAME]` tables merge like stages,
//! its `[publish]` entries replace the parent's by key, and the pipeline name is the child's
//! (its `[pipeline] name`, or its file stem), so an ablation writes its outputs
//! next to, not over, the original's.

use std::collections::BTreeMap;
use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use fure_stage_api::Value;
use toml_edit::{ImDocument, Item, TableLike};

/// Where something was written: a file, line and column (1-based), or a
/// command-line option.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Loc {
    pub file: Arc<str>,
    pub line: usize,
    pub col: usize,
}

impl Loc {
    /// A location outside any file (e.g. `--set`).
    pub fn origin(what: &str) -> Loc {
        Loc {
            file: Arc::from(what),
            line: 0,
            col: 0,
        }
    }
}

impl fmt::Display for Loc {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.line == 0 {
            write!(f, "{}", self.file)
        } else {
            write!(f, "{}:{}:{}", self.file, self.line, self.col)
        }
    }
}

/// One problem with a pipeline, located where possible.
#[derive(Debug, Clone)]
pub struct PipelineError {
    pub loc: Option<Loc>,
    pub message: String,
}

impl PipelineError {
    pub fn at(loc: &Loc, message: impl Into<String>) -> Self {
        PipelineError {
            loc: Some(loc.clone()),
            message: message.into(),
        }
    }
    pub fn bare(message: impl Into<String>) -> Self {
        PipelineError {
            loc: None,
            message: message.into(),
        }
    }
}

impl fmt::Display for PipelineError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.loc {
            Some(l) => write!(f, "{l}: error: {}", self.message),
            None => write!(f, "error: {}", self.message),
        }
    }
}

/// All the problems found in a pipeline (nothing runs while there is one).
#[derive(Debug, Clone)]
pub struct PipelineErrors(pub Vec<PipelineError>);

impl fmt::Display for PipelineErrors {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, e) in self.0.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            write!(f, "{e}")?;
        }
        Ok(())
    }
}

impl std::error::Error for PipelineErrors {}

impl From<PipelineError> for PipelineErrors {
    fn from(e: PipelineError) -> Self {
        PipelineErrors(vec![e])
    }
}

/// A parameter value as written, with where and relative to what directory.
#[derive(Debug, Clone)]
pub struct ParamDecl {
    pub value: Value,
    pub loc: Loc,
    /// Directory relative paths in this value are resolved against.
    pub base: Arc<PathBuf>,
}

/// An input connection as written (`"STAGE.PORT"` or a path).
#[derive(Debug, Clone)]
pub struct InputDecl {
    pub text: String,
    pub loc: Loc,
    pub base: Arc<PathBuf>,
}

/// One `[stages.NAME]` table after `extends` merging.
#[derive(Debug, Clone)]
pub struct StageDecl {
    pub name: String,
    pub loc: Loc,
    pub kind: Option<(String, Loc)>,
    pub params: BTreeMap<String, ParamDecl>,
    pub inputs: BTreeMap<String, InputDecl>,
}

/// A parsed pipeline, `extends` resolved, overrides not yet checked.
#[derive(Debug, Clone)]
pub struct Pipeline {
    pub name: String,
    pub description: String,
    /// The file given on the command line.
    pub file: PathBuf,
    /// Stages in declaration order (parents' stages first).
    pub stages: Vec<StageDecl>,
    /// `"STAGE.PARAM"` -> values to sweep over, crossed (`[sweep]`).
    pub sweep: BTreeMap<String, (Vec<Value>, Loc)>,
    /// `"STAGE.PARAM"` -> values varied one at a time (`[sweep.each]`), in
    /// declaration order (parents' keys first).
    pub sweep_each: Vec<(String, Vec<Value>, Loc)>,
    /// `[aggregate.NAME]` stages, run by `fure sweep` on the sweep record
    /// (`kind` and parameters only; their one input is bound by the engine).
    pub aggregates: Vec<StageDecl>,
    /// `[publish]`: `"AGGREGATE.PORT"` -> destination (resolved against the
    /// declaring file's directory), copied there by `fure sweep` (`crate::publish`).
    pub publish: BTreeMap<String, (PathBuf, Loc)>,
    /// `[executor]`: where stages run when not locally (`crate::slurm`),
    /// checked at load time; a child's keys override its parent's (tables
    /// merged). Never part of a key.
    pub executor: Option<(Value, Loc)>,
}

impl Pipeline {
    /// Reads `path` and everything it extends.
    pub fn load(path: &Path) -> Result<Pipeline, PipelineErrors> {
        let mut stack = Vec::new();
        let p = load_rec(path, &mut stack)?;
        // The name is a directory under out/ and a file under cache/index/:
        // a stem such as `..` (from `...toml`) must not become one.
        if !valid_name(&p.name) {
            return Err(PipelineError::bare(format!(
                "{}: the pipeline name `{}` (from the file name) is not a valid name \
                 (letters, digits, `_`, `-`); set `[pipeline] name`",
                path.display(),
                p.name
            ))
            .into());
        }
        Ok(p)
    }

    /// Parses pipeline text (for tests and generated pipelines); relative paths
    /// resolve against `base_dir`, `extends` is not allowed.
    pub fn parse_str(
        text: &str,
        file_label: &str,
        base_dir: &Path,
    ) -> Result<Pipeline, PipelineErrors> {
        let raw = parse_file(text, file_label, base_dir)?;
        if let Some((_, loc)) = &raw.extends {
            return Err(PipelineError::at(loc, "`extends` is not allowed here").into());
        }
        let stem = Path::new(file_label)
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "pipeline".into());
        Ok(Pipeline {
            name: raw.name.map(|(n, _)| n).unwrap_or(stem),
            description: raw.description.unwrap_or_default(),
            file: PathBuf::from(file_label),
            stages: raw.stages,
            sweep: raw.sweep,
            sweep_each: raw.sweep_each,
            aggregates: raw.aggregates,
            publish: raw.publish,
            executor: raw.executor,
        })
    }

    pub fn stage(&self, name: &str) -> Option<&StageDecl> {
        self.stages.iter().find(|s| s.name == name)
    }

    /// Applies `STAGE.PARAM=VALUE` (VALUE parsed as TOML, else taken as a string).
    pub fn apply_set(&mut self, spec: &str, origin: &str) -> Result<(), PipelineError> {
        let (target, value) = spec.split_once('=').ok_or_else(|| {
            PipelineError::at(
                &Loc::origin(origin),
                format!("`{spec}`: expected STAGE.PARAM=VALUE"),
            )
        })?;
        let value = parse_cli_value(value.trim());
        self.set_param(
            target.trim(),
            value,
            &Loc::origin(&format!("{origin} {spec}")),
        )
    }

    /// Sets a parameter `STAGE.PARAM` (the stage must exist).
    pub fn set_param(
        &mut self,
        target: &str,
        value: Value,
        loc: &Loc,
    ) -> Result<(), PipelineError> {
        let (stage, param) = target
            .split_once('.')
            .ok_or_else(|| PipelineError::at(loc, format!("`{target}`: expected STAGE.PARAM")))?;
        let names: Vec<String> = self.stages.iter().map(|s| s.name.clone()).collect();
        let decl = self
            .stages
            .iter_mut()
            .find(|s| s.name == stage)
            .ok_or_else(|| {
                PipelineError::at(
                    loc,
                    format!("no stage `{stage}` (stages: {})", names.join(", ")),
                )
            })?;
        if param == "kind" || param == "inputs" {
            return Err(PipelineError::at(
                loc,
                format!("`{param}` cannot be overridden from the command line"),
            ));
        }
        let base = Arc::new(std::env::current_dir().unwrap_or_default());
        decl.params.insert(
            param.to_string(),
            ParamDecl {
                value,
                loc: loc.clone(),
                base,
            },
        );
        Ok(())
    }
}

/// Parses a command-line value as TOML (`1.5`, `true`, `[1,2]`, `"s"`), falling
/// back to a bare string.
pub fn parse_cli_value(text: &str) -> Value {
    let doc = format!("v = {text}");
    if let Ok(d) = ImDocument::parse(doc.as_str()) {
        if let Some(item) = d.as_table().get("v") {
            let dummy = Loc::origin("");
            if let Ok(v) = item_to_value(item, &dummy, &LineIndex::new("")) {
                return v;
            }
        }
    }
    Value::Str(text.to_string())
}

/// Parses a comma-separated list of command-line values (`--grid S.P=1,2,3`).
pub fn parse_cli_list(text: &str) -> Vec<Value> {
    let t = text.trim();
    if t.starts_with('[') {
        if let Value::List(l) = parse_cli_value(t) {
            return l;
        }
    }
    t.split(',').map(|s| parse_cli_value(s.trim())).collect()
}

struct RawFile {
    name: Option<(String, Loc)>,
    description: Option<String>,
    extends: Option<(String, Loc)>,
    stages: Vec<StageDecl>,
    sweep: BTreeMap<String, (Vec<Value>, Loc)>,
    sweep_each: Vec<(String, Vec<Value>, Loc)>,
    aggregates: Vec<StageDecl>,
    publish: BTreeMap<String, (PathBuf, Loc)>,
    executor: Option<(Value, Loc)>,
}

/// How many files an `extends` chain may hold (deeper is a mistake, and the
/// loader recurses).
pub const MAX_EXTENDS_DEPTH: usize = 32;

fn load_rec(path: &Path, stack: &mut Vec<PathBuf>) -> Result<Pipeline, PipelineErrors> {
    let label = path.display().to_string();
    let canon = path
        .canonicalize()
        .map_err(|e| PipelineError::bare(format!("cannot read pipeline `{label}`: {e}")))?;
    if stack.contains(&canon) {
        let chain: Vec<String> = stack.iter().map(|p| p.display().to_string()).collect();
        return Err(PipelineError::bare(format!(
            "`extends` cycle: {} -> {}",
            chain.join(" -> "),
            canon.display()
        ))
        .into());
    }
    let text = std::fs::read_to_string(path)
        .map_err(|e| PipelineError::bare(format!("cannot read pipeline `{label}`: {e}")))?;
    let base = canon.parent().map(Path::to_path_buf).unwrap_or_default();
    let raw = parse_file(&text, &label, &base)?;
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "pipeline".into());
    let mut pipeline = match &raw.extends {
        None => Pipeline {
            name: String::new(),
            description: String::new(),
            file: path.to_path_buf(),
            stages: Vec::new(),
            sweep: BTreeMap::new(),
            sweep_each: Vec::new(),
            aggregates: Vec::new(),
            publish: BTreeMap::new(),
            executor: None,
        },
        Some((parent, loc)) => {
            let parent_path = base.join(parent);
            if !parent_path.is_file() {
                return Err(PipelineError::at(
                    loc,
                    format!(
                        "`extends`: no pipeline file `{parent}` (looked for {})",
                        parent_path.display()
                    ),
                )
                .into());
            }
            if stack.len() >= MAX_EXTENDS_DEPTH {
                return Err(PipelineError::at(
                    loc,
                    format!(
                        "`extends` chain deeper than {MAX_EXTENDS_DEPTH} files (from {})",
                        stack
                            .first()
                            .map(|p| p.display().to_string())
                            .unwrap_or_default()
                    ),
                )
                .into());
            }
            stack.push(canon.clone());
            let p = load_rec(&parent_path, stack)?;
            stack.pop();
            p
        }
    };
    pipeline.file = path.to_path_buf();
    pipeline.name = raw.name.map(|(n, _)| n).unwrap_or(stem);
    if let Some(d) = raw.description {
        pipeline.description = d;
    }
    // Name -> position, so that merging n stages is not n^2 comparisons.
    let mut index: std::collections::HashMap<String, usize> = pipeline
        .stages
        .iter()
        .enumerate()
        .map(|(i, s)| (s.name.clone(), i))
        .collect();
    for child in raw.stages {
        match index.get(&child.name).map(|&i| &mut pipeline.stages[i]) {
            None => {
                index.insert(child.name.clone(), pipeline.stages.len());
                pipeline.stages.push(child)
            }
            Some(parent) => {
                if child.kind.is_some() {
                    parent.kind = child.kind;
                }
                parent.params.extend(child.params);
                parent.inputs.extend(child.inputs);
            }
        }
    }
    merge_sweep(&mut pipeline, raw.sweep, raw.sweep_each);
    pipeline.publish.extend(raw.publish);
    pipeline.executor = match (pipeline.executor.take(), raw.executor) {
        (Some((parent, _)), Some((child, loc))) => Some((merge_tables(parent, child), loc)),
        (parent, child) => child.or(parent),
    };
    for child in raw.aggregates {
        match pipeline
            .aggregates
            .iter_mut()
            .find(|s| s.name == child.name)
        {
            None => pipeline.aggregates.push(child),
            Some(parent) => {
                if child.kind.is_some() {
                    parent.kind = child.kind;
                }
                parent.params.extend(child.params);
            }
        }
    }
    Ok(pipeline)
}

/// `child` over `parent`: tables merged key by key, anything else replaced.
fn merge_tables(parent: Value, child: Value) -> Value {
    match (parent, child) {
        (Value::Table(mut p), Value::Table(c)) => {
            for (k, v) in c {
                let merged = match p.remove(&k) {
                    Some(old) => merge_tables(old, v),
                    None => v,
                };
                p.insert(k, merged);
            }
            Value::Table(p)
        }
        (_, c) => c,
    }
}

/// Byte offset -> (line, column) conversion for one file.
struct LineIndex {
    starts: Vec<usize>,
    text: String,
}

impl LineIndex {
    fn new(text: &str) -> Self {
        let mut starts = vec![0];
        for (i, b) in text.bytes().enumerate() {
            if b == b'\n' {
                starts.push(i + 1);
            }
        }
        LineIndex {
            starts,
            text: text.to_string(),
        }
    }
    fn line_col(&self, offset: usize) -> (usize, usize) {
        let line = match self.starts.binary_search(&offset) {
            Ok(i) => i,
            Err(i) => i - 1,
        };
        let start = self.starts[line];
        let end = offset.min(self.text.len());
        let col = self
            .text
            .get(start..end)
            .map(|s| s.chars().count())
            .unwrap_or(0)
            + 1;
        (line + 1, col)
    }
}

struct Ctx<'a> {
    file: Arc<str>,
    lines: &'a LineIndex,
    base: Arc<PathBuf>,
}

impl Ctx<'_> {
    fn loc(&self, span: Option<std::ops::Range<usize>>) -> Loc {
        let (line, col) = span.map(|s| self.lines.line_col(s.start)).unwrap_or((1, 1));
        Loc {
            file: self.file.clone(),
            line,
            col,
        }
    }
    fn key_loc(&self, t: &dyn TableLike, key: &str) -> Loc {
        let span = t
            .get_key_value(key)
            .and_then(|(k, item)| k.span().or_else(|| item.span()));
        self.loc(span)
    }
    fn item_loc(&self, item: &Item) -> Loc {
        self.loc(item.span())
    }
}

/// Parses one pipeline file's text into its sections, collecting every
/// problem rather than stopping at the first.
fn parse_file(text: &str, label: &str, base: &Path) -> Result<RawFile, PipelineErrors> {
    let lines = LineIndex::new(text);
    let file: Arc<str> = Arc::from(label);
    let doc = parse_toml(text, &file, &lines)?;
    let cx = Ctx {
        file: file.clone(),
        lines: &lines,
        base: Arc::new(base.to_path_buf()),
    };
    let root = doc.as_table();
    let mut errors = Vec::new();
    let mut out = RawFile {
        name: None,
        description: None,
        extends: None,
        stages: Vec::new(),
        sweep: BTreeMap::new(),
        sweep_each: Vec::new(),
        aggregates: Vec::new(),
        publish: BTreeMap::new(),
        executor: None,
    };
    for (key, item) in root.iter() {
        let loc = cx.key_loc(root, key);
        match key {
            "extends" => match item.as_str() {
                Some(s) => out.extends = Some((s.to_string(), cx.item_loc(item))),
                None => errors.push(PipelineError::at(
                    &loc,
                    "`extends` must be a string (a pipeline file path)",
                )),
            },
            "pipeline" => match item.as_table_like() {
                None => errors.push(PipelineError::at(&loc, "`pipeline` must be a table")),
                Some(t) => parse_pipeline_table(&cx, t, &mut out, &mut errors),
            },
            "stages" => match item.as_table_like() {
                None => errors.push(PipelineError::at(&loc, "`stages` must be a table of tables")),
                Some(t) => {
                    for (name, st) in t.iter() {
                        match parse_stage(&cx, t, name, st) {
                            Ok(s) => out.stages.push(s),
                            Err(mut e) => errors.append(&mut e),
                        }
                    }
                }
            },
            "sweep" => match item.as_table_like() {
                None => errors.push(PipelineError::at(&loc, "`sweep` must be a table")),
                Some(t) => parse_sweep_table(&cx, t, &mut out, &mut errors),
            },
            "aggregate" => match item.as_table_like() {
                None => errors.push(PipelineError::at(&loc, "`aggregate` must be a table of tables")),
                Some(t) => parse_aggregate_table(&cx, t, &mut out, &mut errors),
            },
            "publish" => match item.as_table_like() {
                None => errors.push(PipelineError::at(
                    &loc,
                    "`publish` must be a table of \"AGGREGATE.PORT\" = \"destination path\"",
                )),
                Some(t) => parse_publish_table(&cx, t, &mut out, &mut errors),
            },
            "executor" => parse_executor_table(&cx, item, &loc, &mut out, &mut errors),
            other => errors.push(PipelineError::at(
                &loc,
                format!(
                    "unknown field `{other}` (expected `extends`, `[pipeline]`, `[stages.NAME]`, `[sweep]`, `[aggregate.NAME]`, `[publish]` or `[executor]`)"
                ),
            )),
        }
    }
    if errors.is_empty() {
        Ok(out)
    } else {
        Err(PipelineErrors(errors))
    }
}

/// The TOML document itself; a syntax error is located in `file`.
fn parse_toml<'t>(
    text: &'t str,
    file: &Arc<str>,
    lines: &LineIndex,
) -> Result<ImDocument<&'t str>, PipelineError> {
    ImDocument::parse(text).map_err(|e| {
        let (line, col) = e.span().map(|s| lines.line_col(s.start)).unwrap_or((1, 1));
        let msg = e.message().trim().to_string();
        PipelineError::at(
            &Loc {
                file: file.clone(),
                line,
                col,
            },
            format!("invalid TOML: {msg}"),
        )
    })
}

/// `[pipeline]`: the optional `name` and `description`.
fn parse_pipeline_table(
    cx: &Ctx<'_>,
    t: &dyn TableLike,
    out: &mut RawFile,
    errors: &mut Vec<PipelineError>,
) {
    for (k, v) in t.iter() {
        let kloc = cx.key_loc(t, k);
        match (k, v.as_str()) {
            ("name", Some(s)) => {
                if valid_name(s) {
                    out.name = Some((s.to_string(), kloc))
                } else {
                    errors.push(PipelineError::at(
                        &cx.item_loc(v),
                        format!("pipeline name `{s}`: expected letters, digits, `_` or `-`"),
                    ))
                }
            }
            ("description", Some(s)) => out.description = Some(s.to_string()),
            ("name" | "description", None) => errors.push(PipelineError::at(
                &kloc,
                format!("`pipeline.{k}` must be a string"),
            )),
            _ => errors.push(PipelineError::at(
                &kloc,
                format!("unknown field `pipeline.{k}` (expected `name` or `description`)"),
            )),
        }
    }
}

/// `[sweep]`: crossed axes, and its `[sweep.each]` subtable where it appears.
fn parse_sweep_table(
    cx: &Ctx<'_>,
    t: &dyn TableLike,
    out: &mut RawFile,
    errors: &mut Vec<PipelineError>,
) {
    for (k, v) in t.iter() {
        let kloc = cx.key_loc(t, k);
        if k == "each" {
            if let Some(each) = v.as_table_like() {
                parse_sweep_each_table(cx, each, out, errors);
            } else {
                errors.push(PipelineError::at(
                    &kloc,
                    "`sweep.each` must be a table of \"STAGE.PARAM\" = [values]",
                ));
            }
            continue;
        }
        if let Some(l) = sweep_axis(cx, "sweep", k, v, &kloc, errors) {
            if out.sweep_each.iter().any(|(e, _, _)| e == k) {
                errors.push(PipelineError::at(
                    &kloc,
                    format!("sweep key `{k}` is both crossed (`[sweep]`) and varied one at a time (`[sweep.each]`); keep one"),
                ));
            } else {
                out.sweep.insert(k.to_string(), (l, kloc));
            }
        }
    }
}

/// `[sweep.each]`: axes varied one at a time, in declaration order.
fn parse_sweep_each_table(
    cx: &Ctx<'_>,
    each: &dyn TableLike,
    out: &mut RawFile,
    errors: &mut Vec<PipelineError>,
) {
    for (k, v) in each.iter() {
        let kloc = cx.key_loc(each, k);
        if let Some(l) = sweep_axis(cx, "sweep.each", k, v, &kloc, errors) {
            if out.sweep.contains_key(k) {
                errors.push(PipelineError::at(
                    &kloc,
                    format!("sweep key `{k}` is both crossed (`[sweep]`) and varied one at a time (`[sweep.each]`); keep one"),
                ));
            } else {
                out.sweep_each.push((k.to_string(), l, kloc));
            }
        }
    }
}

/// `[aggregate.NAME]` tables: stages without `inputs` (the engine binds their
/// one input to the sweep record).
fn parse_aggregate_table(
    cx: &Ctx<'_>,
    t: &dyn TableLike,
    out: &mut RawFile,
    errors: &mut Vec<PipelineError>,
) {
    for (name, st) in t.iter() {
        match parse_stage(cx, t, name, st) {
            Ok(s) => {
                // The one input is bound by the engine (see `crate::sweep`).
                if let Some(inp) = s.inputs.values().next() {
                    errors.push(PipelineError::at(
                        &inp.loc,
                        format!("aggregate `{name}`: no `inputs` expected (its one input port is bound to the sweep record by the engine)"),
                    ));
                } else {
                    out.aggregates.push(s);
                }
            }
            Err(e) => errors.extend(e.into_iter().map(|mut e| {
                e.message = e.message.replace("`stages.", "`aggregate.");
                e
            })),
        }
    }
}

/// `[publish]`: `"AGGREGATE.PORT" = "destination path"`, the destination
/// resolved against this file's directory.
fn parse_publish_table(
    cx: &Ctx<'_>,
    t: &dyn TableLike,
    out: &mut RawFile,
    errors: &mut Vec<PipelineError>,
) {
    for (k, v) in t.iter() {
        let kloc = cx.key_loc(t, k);
        match (k.split_once('.'), v.as_str()) {
            (Some((a, port)), Some(dest))
                if !a.is_empty() && !port.is_empty() && !dest.is_empty() =>
            {
                out.publish
                    .insert(k.to_string(), (cx.base.join(dest), kloc));
            }
            (None, _) | (Some(_), Some(_)) => errors.push(PipelineError::at(
                &kloc,
                format!("publish key `{k}`: expected \"AGGREGATE.PORT\" = \"destination path\""),
            )),
            (Some(_), None) => errors.push(PipelineError::at(
                &cx.item_loc(v),
                format!("publish `{k}`: expected a destination path (a string)"),
            )),
        }
    }
}

/// `[executor]`: kept as a value, but checked now so that a bad one is a
/// located load error.
fn parse_executor_table(
    cx: &Ctx<'_>,
    item: &Item,
    loc: &Loc,
    out: &mut RawFile,
    errors: &mut Vec<PipelineError>,
) {
    match item_to_value(item, loc, cx.lines) {
        Ok(v @ Value::Table(_)) => {
            match crate::slurm::ExecutorConfig::from_value(&v, &loc.to_string()) {
                Ok(_) => out.executor = Some((v, loc.clone())),
                Err(crate::slurm::SlurmError::Config { message, .. }) => {
                    errors.push(PipelineError::at(loc, format!("[executor]: {message}")))
                }
                Err(e) => errors.push(PipelineError::at(loc, e.to_string())),
            }
        }
        Ok(_) => errors.push(PipelineError::at(loc, "`executor` must be a table")),
        Err(e) => errors.push(e),
    }
}

/// One sweep axis `"STAGE.PARAM" = [values]` (of `[sweep]` or `[sweep.each]`).
fn sweep_axis(
    cx: &Ctx<'_>,
    table: &str,
    k: &str,
    v: &Item,
    kloc: &Loc,
    errors: &mut Vec<PipelineError>,
) -> Option<Vec<Value>> {
    // A key links one or more comma-separated targets (`crate::sweep::linked_targets`).
    if k.split(',').any(|t| t.trim().split_once('.').is_none()) {
        errors.push(PipelineError::at(
            kloc,
            format!(
                "{table} key `{k}`: expected \"STAGE.PARAM\" or linked \"STAGE.PARAM,STAGE.PARAM\""
            ),
        ));
        return None;
    }
    match item_to_value(v, kloc, cx.lines) {
        Ok(Value::List(l)) if !l.is_empty() => Some(l),
        Ok(_) => {
            errors.push(PipelineError::at(
                &cx.item_loc(v),
                format!("{table} `{k}`: expected a non-empty array of values"),
            ));
            None
        }
        Err(e) => {
            errors.push(e);
            None
        }
    }
}

/// `extends` merging of the sweep axes: a child's key replaces the parent's
/// values and takes the child's kind of axis (crossed or one at a time); a
/// replaced `[sweep.each]` key keeps its position, new ones are appended.
fn merge_sweep(
    pipeline: &mut Pipeline,
    crossed: BTreeMap<String, (Vec<Value>, Loc)>,
    each: Vec<(String, Vec<Value>, Loc)>,
) {
    for (k, v) in crossed {
        pipeline.sweep_each.retain(|(e, _, _)| e != &k);
        pipeline.sweep.insert(k, v);
    }
    for (k, v, l) in each {
        pipeline.sweep.remove(&k);
        match pipeline.sweep_each.iter_mut().find(|(e, _, _)| e == &k) {
            Some(slot) => *slot = (k, v, l),
            None => pipeline.sweep_each.push((k, v, l)),
        }
    }
}

/// Names of stages and pipelines: they become directory names and DAG labels.
pub fn valid_name(s: &str) -> bool {
    !s.is_empty()
        && s.len() <= 128
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
}

fn parse_stage(
    cx: &Ctx<'_>,
    parent: &dyn TableLike,
    name: &str,
    item: &Item,
) -> Result<StageDecl, Vec<PipelineError>> {
    let loc = cx.key_loc(parent, name);
    let mut errors = Vec::new();
    if !valid_name(name) {
        errors.push(PipelineError::at(
            &loc,
            format!("stage name `{name}`: expected letters, digits, `_` or `-` (no dots)"),
        ));
    }
    let t = match item.as_table_like() {
        Some(t) => t,
        None => {
            errors.push(PipelineError::at(
                &loc,
                format!("`stages.{name}` must be a table"),
            ));
            return Err(errors);
        }
    };
    let mut decl = StageDecl {
        name: name.to_string(),
        loc: loc.clone(),
        kind: None,
        params: BTreeMap::new(),
        inputs: BTreeMap::new(),
    };
    for (k, v) in t.iter() {
        let kloc = cx.key_loc(t, k);
        match k {
            "kind" => match v.as_str() {
                Some(s) => decl.kind = Some((s.to_string(), cx.item_loc(v))),
                None => errors.push(PipelineError::at(
                    &kloc,
                    format!("`stages.{name}.kind` must be a string (a stage kind, see `fure stages`)"),
                )),
            },
            "inputs" => match v.as_table_like() {
                None => errors.push(PipelineError::at(
                    &kloc,
                    format!("`stages.{name}.inputs` must be a table of PORT = \"STAGE.PORT\" or \"path\""),
                )),
                Some(it) => {
                    for (port, src) in it.iter() {
                        let ploc = cx.key_loc(it, port);
                        match src.as_str() {
                            Some(s) => {
                                decl.inputs.insert(
                                    port.to_string(),
                                    InputDecl {
                                        text: s.to_string(),
                                        loc: cx.item_loc(src),
                                        base: cx.base.clone(),
                                    },
                                );
                            }
                            None => errors.push(PipelineError::at(
                                &ploc,
                                format!("input `{port}` of stage `{name}`: expected a string \"STAGE.PORT\" or a file path"),
                            )),
                        }
                    }
                }
            },
            param => match item_to_value(v, &kloc, cx.lines) {
                Ok(value) => {
                    decl.params.insert(
                        param.to_string(),
                        ParamDecl {
                            value,
                            loc: kloc,
                            base: cx.base.clone(),
                        },
                    );
                }
                Err(e) => errors.push(e),
            },
        }
    }
    if errors.is_empty() {
        Ok(decl)
    } else {
        Err(errors)
    }
}

fn item_to_value(item: &Item, loc: &Loc, lines: &LineIndex) -> Result<Value, PipelineError> {
    match item {
        Item::None => Err(PipelineError::at(loc, "missing value")),
        Item::Value(v) => toml_value(v, loc, lines),
        Item::Table(t) => table_to_value(t, loc, lines),
        Item::ArrayOfTables(a) => {
            let mut out = Vec::new();
            for t in a.iter() {
                out.push(table_to_value(t, loc, lines)?);
            }
            Ok(Value::List(out))
        }
    }
}

fn table_to_value(t: &dyn TableLike, loc: &Loc, lines: &LineIndex) -> Result<Value, PipelineError> {
    let mut m = BTreeMap::new();
    for (k, v) in t.iter() {
        m.insert(k.to_string(), item_to_value(v, loc, lines)?);
    }
    Ok(Value::Table(m))
}

fn toml_value(v: &toml_edit::Value, loc: &Loc, lines: &LineIndex) -> Result<Value, PipelineError> {
    use toml_edit::Value as T;
    Ok(match v {
        T::String(s) => Value::Str(s.value().clone()),
        T::Integer(i) => Value::Int(*i.value()),
        T::Float(f) => Value::Float(*f.value()),
        T::Boolean(b) => Value::Bool(*b.value()),
        T::Datetime(_) => {
            let l = v
                .span()
                .map(|s| {
                    let (line, col) = lines.line_col(s.start);
                    Loc {
                        file: loc.file.clone(),
                        line,
                        col,
                    }
                })
                .unwrap_or_else(|| loc.clone());
            return Err(PipelineError::at(
                &l,
                "dates are not supported as parameter values",
            ));
        }
        T::Array(a) => {
            let mut out = Vec::with_capacity(a.len());
            for x in a.iter() {
                out.push(toml_value(x, loc, lines)?);
            }
            Value::List(out)
        }
        T::InlineTable(t) => table_to_value(t, loc, lines)?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Pipeline, PipelineErrors> {
        Pipeline::parse_str(text, "t.toml", Path::new("/tmp"))
    }

    #[test]
    fn parses_stages_params_inputs_and_sweep() {
        let p = parse(
            "[pipeline]\nname = \"demo\"\n[stages.a]\nkind = \"k\"\nx = 1.5\nl = [1, 2]\n\
             [stages.b]\nkind = \"k2\"\ninputs = { src = \"a.out\" }\n[sweep]\n\"a.x\" = [1.0, 2.0]\n",
        )
        .unwrap();
        assert_eq!(p.name, "demo");
        assert_eq!(p.stages.len(), 2);
        let a = p.stage("a").unwrap();
        assert_eq!(a.params["x"].value, Value::Float(1.5));
        assert_eq!(a.params["x"].loc.line, 5);
        assert_eq!(p.stage("b").unwrap().inputs["src"].text, "a.out");
        assert_eq!(p.sweep["a.x"].0.len(), 2);
    }

    #[test]
    fn unknown_top_level_field_is_located() {
        let e = parse("[pipeline]\nname = \"x\"\n\n[stagez.a]\nkind = \"k\"\n").unwrap_err();
        let s = e.to_string();
        assert!(s.contains("t.toml:4:2"), "{s}");
        assert!(s.contains("unknown field `stagez`"), "{s}");
    }

    #[test]
    fn invalid_toml_is_located() {
        let e = parse("[stages.a]\nkind = \"k\"\nx = = 2\n").unwrap_err();
        let s = e.to_string();
        assert!(s.starts_with("t.toml:3:"), "{s}");
        assert!(s.contains("invalid TOML"), "{s}");
    }

    #[test]
    fn cli_values_parse_as_toml_or_strings() {
        assert_eq!(parse_cli_value("2"), Value::Int(2));
        assert_eq!(parse_cli_value("2.5"), Value::Float(2.5));
        assert_eq!(parse_cli_value("true"), Value::Bool(true));
        assert_eq!(parse_cli_value("hello"), Value::Str("hello".into()));
        assert_eq!(parse_cli_list("1,2,3").len(), 3);
        assert_eq!(parse_cli_list("[1, 2]").len(), 2);
    }

    #[test]
    fn set_param_needs_existing_stage() {
        let mut p = parse("[stages.a]\nkind = \"k\"\n").unwrap();
        assert!(p.apply_set("a.x=3", "--set").is_ok());
        assert_eq!(p.stage("a").unwrap().params["x"].value, Value::Int(3));
        let e = p.apply_set("zz.x=3", "--set").unwrap_err();
        assert!(e.to_string().contains("no stage `zz`"));
    }
}
