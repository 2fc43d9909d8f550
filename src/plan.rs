//! Planning: from a parsed [`Pipeline`] to a checked, ordered DAG of stages.
//!
//! Planning resolves every stage kind, checks every parameter against the
//! kind's [`ParamSpec`]s (unknown names, types, bounds, choices, required
//! ones), fills defaults, runs the kind's own `validate`, resolves every input
//! (an upstream output or an existing file or directory), checks ports on both
//! ends, builds the dependency graph with petgraph and orders it. It collects
//! all problems before failing, each with the file, line and column of the
//! culprit, so a user fixes a pipeline in one round. Nothing runs on a
//! pipeline that does not plan.
//!
//! Choices:
//! - Integers given to `Float` (and `FloatList`) parameters are widened to
//!   floats before keying, so `x = 1` and `x = 1.0` share a cache entry.
//! - The order is topological with ties broken by declaration order (Kahn's
//!   algorithm over a min-heap), so listings and logs are stable and readable.
//! - The `command` kind's `deps` parameter holds sources: the planner turns
//!   them into input connections and keeps only the port names in the
//!   parameter (see [`crate::command`]).

use std::cmp::Reverse;
use std::collections::{BTreeMap, BTreeSet, BinaryHeap};
use std::path::PathBuf;
use std::sync::Arc;

use fure_stage_api::{ParamSpec, ParamType, Params, PortKind, PortSpec, Stage, Value};
use petgraph::graph::{DiGraph, NodeIndex};

use crate::command;
use crate::pipeline::{
    InputDecl, Loc, ParamDecl, Pipeline, PipelineError, PipelineErrors, StageDecl,
};

/// The stage kinds an engine knows: the caller's plus the built-in `command`.
#[derive(Clone)]
pub struct Registry {
    kinds: BTreeMap<&'static str, Arc<dyn Stage>>,
}

impl Registry {
    /// Builds a registry; kinds must be unique and must not be `command`.
    pub fn new(stages: Vec<Box<dyn Stage>>) -> Result<Registry, String> {
        let mut kinds: BTreeMap<&'static str, Arc<dyn Stage>> = BTreeMap::new();
        kinds.insert(command::KIND, Arc::new(command::CommandStage));
        for s in stages {
            let k = s.kind();
            if kinds.contains_key(k) {
                return Err(format!("stage kind `{k}` is registered twice"));
            }
            kinds.insert(k, Arc::from(s));
        }
        Ok(Registry { kinds })
    }
    pub fn get(&self, kind: &str) -> Option<&Arc<dyn Stage>> {
        self.kinds.get(kind)
    }
    pub fn iter(&self) -> impl Iterator<Item = &Arc<dyn Stage>> {
        self.kinds.values()
    }
    fn names(&self) -> String {
        self.kinds.keys().copied().collect::<Vec<_>>().join(", ")
    }
}

/// Where an input comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Source {
    /// Output `port` of the stage at index `stage` of [`Plan::stages`].
    Upstream { stage: usize, port: String },
    /// A file or directory: absolute path and the text as written.
    Path { path: PathBuf, written: String },
}

/// One connected input port.
#[derive(Debug, Clone)]
pub struct Input {
    pub port: String,
    pub spec: PortSpec,
    pub source: Source,
    pub loc: Loc,
}

/// One stage, ready to key and run.
#[derive(Clone)]
pub struct PlannedStage {
    pub name: String,
    pub kind: String,
    pub version: u32,
    pub stage: Arc<dyn Stage>,
    pub params: Params,
    /// Connected inputs, sorted by port.
    pub inputs: Vec<Input>,
    pub outputs: Vec<PortSpec>,
    /// Indices of the stages this one reads from (sorted, unique).
    pub upstream: Vec<usize>,
    pub loc: Loc,
}

/// A checked pipeline in topological order.
#[derive(Clone)]
pub struct Plan {
    pub name: String,
    pub description: String,
    pub file: PathBuf,
    pub stages: Vec<PlannedStage>,
}

impl std::fmt::Debug for Plan {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Plan")
            .field("name", &self.name)
            .field(
                "stages",
                &self
                    .stages
                    .iter()
                    .map(|s| (&s.name, &s.kind))
                    .collect::<Vec<_>>(),
            )
            .finish()
    }
}

impl Plan {
    pub fn index_of(&self, name: &str) -> Option<usize> {
        self.stages.iter().position(|s| s.name == name)
    }
    /// How an input source is shown (`stage.port` or the path as written).
    pub fn source_label(&self, s: &Source) -> String {
        match s {
            Source::Upstream { stage, port } => format!("{}.{}", self.stages[*stage].name, port),
            Source::Path { written, .. } => written.clone(),
        }
    }
    /// Keeps only `target` and the stages it depends on.
    pub fn until(&self, target: &str) -> Result<Plan, PipelineError> {
        let t = self.index_of(target).ok_or_else(|| {
            PipelineError::bare(format!(
                "--until: no stage `{target}` (stages: {})",
                self.stages
                    .iter()
                    .map(|s| s.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            ))
        })?;
        let mut keep = BTreeSet::new();
        let mut todo = vec![t];
        while let Some(i) = todo.pop() {
            if keep.insert(i) {
                todo.extend(self.stages[i].upstream.iter().copied());
            }
        }
        let remap: BTreeMap<usize, usize> = keep.iter().enumerate().map(|(n, o)| (*o, n)).collect();
        let stages = keep
            .iter()
            .map(|&i| {
                let mut s = self.stages[i].clone();
                s.upstream = s.upstream.iter().map(|u| remap[u]).collect();
                for inp in &mut s.inputs {
                    if let Source::Upstream { stage, .. } = &mut inp.source {
                        *stage = remap[stage];
                    }
                }
                s
            })
            .collect();
        Ok(Plan {
            name: self.name.clone(),
            description: self.description.clone(),
            file: self.file.clone(),
            stages,
        })
    }
}

struct Partial<'a> {
    decl: &'a StageDecl,
    stage: Arc<dyn Stage>,
    params: Params,
    inputs_decl: BTreeMap<String, InputDecl>,
    input_specs: Vec<PortSpec>,
    outputs: Vec<PortSpec>,
}

/// Plans `pipeline` against `registry`, reporting every problem found.
pub fn plan(pipeline: &Pipeline, registry: &Registry) -> Result<Plan, PipelineErrors> {
    let mut errors = Vec::new();
    let mut partials: Vec<Option<Partial<'_>>> = Vec::new();
    if pipeline.stages.is_empty() {
        errors.push(PipelineError::at(
            &Loc::origin(&pipeline.file.display().to_string()),
            "the pipeline has no stages (expected `[stages.NAME]` tables)",
        ));
    }
    for decl in &pipeline.stages {
        partials.push(check_stage(decl, registry, &mut errors));
    }
    let resolved = resolve_inputs(pipeline, &partials, &mut errors);
    if !errors.is_empty() {
        return Err(PipelineErrors(errors));
    }
    let (graph, nodes) = dependency_graph(&resolved);
    if petgraph::algo::toposort(&graph, None).is_err() {
        return Err(cycle_error(&graph, pipeline, &resolved).into());
    }
    let order = declaration_ordered_toposort(&graph, &nodes);
    let partials: Vec<Partial<'_>> = partials
        .into_iter()
        .map(|p| p.expect("checked"))
        .collect::<Vec<_>>();
    Ok(Plan {
        name: pipeline.name.clone(),
        description: pipeline.description.clone(),
        file: pipeline.file.clone(),
        stages: planned_stages(partials, resolved, &order),
    })
}

/// The second pass: every stage's inputs resolved against the outputs now
/// known, per stage in declaration order.
fn resolve_inputs(
    pipeline: &Pipeline,
    partials: &[Option<Partial<'_>>],
    errors: &mut Vec<PipelineError>,
) -> Vec<Vec<Input>> {
    let names: BTreeMap<&str, usize> = pipeline
        .stages
        .iter()
        .enumerate()
        .map(|(i, s)| (s.name.as_str(), i))
        .collect();
    let mut resolved: Vec<Vec<Input>> = vec![Vec::new(); pipeline.stages.len()];
    for (i, p) in partials.iter().enumerate() {
        let Some(p) = p else { continue };
        resolved[i] = resolve_stage_inputs(p, &names, partials, pipeline, errors);
    }
    resolved
}

/// One stage's inputs: each declared one checked against the kind's ports
/// and resolved to its source, then every required port checked connected.
fn resolve_stage_inputs(
    p: &Partial<'_>,
    names: &BTreeMap<&str, usize>,
    partials: &[Option<Partial<'_>>],
    pipeline: &Pipeline,
    errors: &mut Vec<PipelineError>,
) -> Vec<Input> {
    let mut inputs = Vec::new();
    let mut connected = BTreeSet::new();
    for (port, inp) in &p.inputs_decl {
        let Some(spec) = p.input_specs.iter().find(|s| &s.name == port) else {
            errors.push(PipelineError::at(
                &inp.loc,
                format!(
                    "stage `{}` (kind `{}`) has no input port `{port}` (expected one of: {})",
                    p.decl.name,
                    p.stage.kind(),
                    list_ports(&p.input_specs)
                ),
            ));
            continue;
        };
        connected.insert(port.clone());
        match resolve_source(inp, names, partials, pipeline) {
            Err(e) => errors.push(e),
            Ok(source) => {
                if let Err(e) = check_port_kinds(p, spec, &source, inp, partials) {
                    errors.push(e);
                    continue;
                }
                inputs.push(Input {
                    port: port.clone(),
                    spec: spec.clone(),
                    source,
                    loc: inp.loc.clone(),
                });
            }
        }
    }
    for spec in &p.input_specs {
        if spec.required && !connected.contains(&spec.name) {
            errors.push(PipelineError::at(
                &p.decl.loc,
                format!(
                    "stage `{}` (kind `{}`): missing input `{}` ({}); connect it with `inputs = {{ {} = \"STAGE.PORT\" }}` or a file path",
                    p.decl.name,
                    p.stage.kind(),
                    spec.name,
                    spec.doc,
                    spec.name
                ),
            ));
        }
    }
    inputs
}

/// The DAG: node `i` is declared stage `i`, with an edge from each stage to
/// every stage reading one of its outputs.
fn dependency_graph(resolved: &[Vec<Input>]) -> (DiGraph<usize, ()>, Vec<NodeIndex>) {
    let mut graph: DiGraph<usize, ()> = DiGraph::new();
    let nodes: Vec<NodeIndex> = (0..resolved.len()).map(|i| graph.add_node(i)).collect();
    for (i, ins) in resolved.iter().enumerate() {
        for inp in ins {
            if let Source::Upstream { stage, .. } = inp.source {
                graph.update_edge(nodes[stage], nodes[i], ());
            }
        }
    }
    (graph, nodes)
}

/// Kahn's algorithm over an acyclic `graph`, ties broken by declaration order
/// (so listings and logs are stable): the declared indices in run order.
fn declaration_ordered_toposort(graph: &DiGraph<usize, ()>, nodes: &[NodeIndex]) -> Vec<usize> {
    let n = nodes.len();
    let mut indeg: Vec<usize> = (0..n)
        .map(|i| {
            graph
                .neighbors_directed(nodes[i], petgraph::Incoming)
                .count()
        })
        .collect();
    let mut heap: BinaryHeap<Reverse<usize>> =
        (0..n).filter(|&i| indeg[i] == 0).map(Reverse).collect();
    let mut order = Vec::with_capacity(n);
    while let Some(Reverse(i)) = heap.pop() {
        order.push(i);
        let mut next: Vec<usize> = graph
            .neighbors_directed(nodes[i], petgraph::Outgoing)
            .map(|nx| graph[nx])
            .collect();
        next.sort_unstable();
        for j in next {
            indeg[j] -= 1;
            if indeg[j] == 0 {
                heap.push(Reverse(j));
            }
        }
    }
    order
}

/// The checked stages in run `order`, their upstream references renumbered
/// from declared indices to positions in that order.
fn planned_stages(
    partials: Vec<Partial<'_>>,
    mut resolved: Vec<Vec<Input>>,
    order: &[usize],
) -> Vec<PlannedStage> {
    let n = order.len();
    let pos: Vec<usize> = {
        let mut pos = vec![0; n];
        for (k, &i) in order.iter().enumerate() {
            pos[i] = k;
        }
        pos
    };
    let mut stages = Vec::with_capacity(n);
    let mut taken: Vec<Option<Partial<'_>>> = partials.into_iter().map(Some).collect();
    for &i in order {
        let p = taken[i].take().expect("each stage once");
        let mut inputs = std::mem::take(&mut resolved[i]);
        for inp in &mut inputs {
            if let Source::Upstream { stage, .. } = &mut inp.source {
                *stage = pos[*stage];
            }
        }
        inputs.sort_by(|a, b| a.port.cmp(&b.port));
        let mut upstream: Vec<usize> = inputs
            .iter()
            .filter_map(|inp| match inp.source {
                Source::Upstream { stage, .. } => Some(stage),
                _ => None,
            })
            .collect();
        upstream.sort_unstable();
        upstream.dedup();
        stages.push(PlannedStage {
            name: p.decl.name.clone(),
            kind: p.stage.kind().to_string(),
            version: p.stage.version(),
            stage: p.stage.clone(),
            params: p.params,
            inputs,
            outputs: p.outputs,
            upstream,
            loc: p.decl.loc.clone(),
        });
    }
    stages
}

fn list_ports(specs: &[PortSpec]) -> String {
    if specs.is_empty() {
        "none".to_string()
    } else {
        specs
            .iter()
            .map(|s| format!("`{}`", s.name))
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// First pass over one stage: its kind, parameters (checked, defaults
/// filled, the kind's own `validate`) and ports; `None` once it has an error.
fn check_stage<'a>(
    decl: &'a StageDecl,
    registry: &Registry,
    errors: &mut Vec<PipelineError>,
) -> Option<Partial<'a>> {
    let (kind, stage) = resolve_kind(decl, registry, errors)?;
    let specs = stage.params();
    let before = errors.len();
    let mut inputs_decl = decl.inputs.clone();
    let mut params = check_declared_params(decl, kind, &specs, &mut inputs_decl, errors);
    fill_defaults(decl, kind, &specs, &mut params, errors);
    if errors.len() > before {
        return None;
    }
    let params = Params(params);
    if let Err(e) = stage.validate(&params) {
        errors.push(validate_error(decl, kind, e));
        return None;
    }
    let input_specs = stage.inputs(&params);
    let outputs = stage.outputs(&params);
    Some(Partial {
        decl,
        stage: stage.clone(),
        params,
        inputs_decl,
        input_specs,
        outputs,
    })
}

/// The stage's `kind`, which must be written and registered.
fn resolve_kind<'a, 'r>(
    decl: &'a StageDecl,
    registry: &'r Registry,
    errors: &mut Vec<PipelineError>,
) -> Option<(&'a str, &'r Arc<dyn Stage>)> {
    let Some((kind, kloc)) = &decl.kind else {
        errors.push(PipelineError::at(
            &decl.loc,
            format!(
                "stage `{}` has no `kind` (expected one of: {})",
                decl.name,
                registry.names()
            ),
        ));
        return None;
    };
    let Some(stage) = registry.get(kind) else {
        errors.push(PipelineError::at(
            kloc,
            format!(
                "stage `{}`: unknown kind `{kind}` (expected one of: {})",
                decl.name,
                registry.names()
            ),
        ));
        return None;
    };
    Some((kind, stage))
}

/// The parameters as written, each checked against its spec; a command
/// stage's `deps` become inputs (added to `inputs_decl`), its parameter
/// keeping only the port names.
fn check_declared_params(
    decl: &StageDecl,
    kind: &str,
    specs: &[ParamSpec],
    inputs_decl: &mut BTreeMap<String, InputDecl>,
    errors: &mut Vec<PipelineError>,
) -> BTreeMap<String, Value> {
    let mut params = BTreeMap::new();
    for (name, p) in &decl.params {
        if kind == command::KIND && name == "deps" {
            match command_deps(&p.value) {
                Ok(list) => {
                    params.insert(name.clone(), bind_command_deps(p, list, inputs_decl));
                }
                Err(m) => errors.push(PipelineError::at(
                    &p.loc,
                    format!("stage `{}`: `deps`: {m}", decl.name),
                )),
            }
            continue;
        }
        let Some(spec) = specs.iter().find(|s| s.name == name) else {
            let known: Vec<&str> = specs.iter().map(|s| s.name).collect();
            errors.push(PipelineError::at(
                &p.loc,
                format!(
                    "stage `{}`: unknown parameter `{name}` for kind `{kind}` (expected one of: {}; or `kind`, `inputs`)",
                    decl.name,
                    if known.is_empty() { "none".to_string() } else { known.join(", ") }
                ),
            ));
            continue;
        };
        match check_value(spec, &p.value) {
            Ok(v) => {
                params.insert(name.clone(), v);
            }
            Err(m) => errors.push(PipelineError::at(
                &p.loc,
                format!("stage `{}`: parameter `{name}`: {m}", decl.name),
            )),
        }
    }
    params
}

/// Turns a command stage's `deps` (port, source) pairs into input
/// declarations located at the `deps` value; returns the port-name list the
/// parameter keeps.
fn bind_command_deps(
    deps: &ParamDecl,
    list: Vec<(String, String)>,
    inputs_decl: &mut BTreeMap<String, InputDecl>,
) -> Value {
    let mut ports = Vec::new();
    for (port, text) in list {
        ports.push(Value::Str(port.clone()));
        inputs_decl.insert(
            port,
            InputDecl {
                text,
                loc: deps.loc.clone(),
                base: deps.base.clone(),
            },
        );
    }
    Value::List(ports)
}

/// Every parameter not written takes its default; a required one without a
/// default is an error.
fn fill_defaults(
    decl: &StageDecl,
    kind: &str,
    specs: &[ParamSpec],
    params: &mut BTreeMap<String, Value>,
    errors: &mut Vec<PipelineError>,
) {
    for spec in specs {
        if params.contains_key(spec.name) {
            continue;
        }
        match &spec.default {
            Some(d) => {
                let v = check_value(spec, d).unwrap_or_else(|_| d.clone());
                params.insert(spec.name.to_string(), v);
            }
            None if spec.optional => {}
            None => errors.push(PipelineError::at(
                &decl.loc,
                format!(
                    "stage `{}` (kind `{kind}`): missing required parameter `{}` ({}: {})",
                    decl.name,
                    spec.name,
                    spec.ty.name(),
                    spec.doc
                ),
            )),
        }
    }
}

/// The kind's own `validate` refusal, located at the parameter it names
/// (else at the stage).
fn validate_error(decl: &StageDecl, kind: &str, e: fure_stage_api::StageError) -> PipelineError {
    let loc = match &e {
        fure_stage_api::StageError::Param { name, .. } => decl
            .params
            .get(name)
            .map(|p| p.loc.clone())
            .unwrap_or_else(|| decl.loc.clone()),
        _ => decl.loc.clone(),
    };
    PipelineError::at(&loc, format!("stage `{}` (kind `{kind}`): {e}", decl.name))
}

/// The `deps` of a command stage: a list (ports `0`, `1`, ...) or a table.
fn command_deps(v: &Value) -> Result<Vec<(String, String)>, String> {
    match v {
        Value::List(l) => l
            .iter()
            .enumerate()
            .map(|(i, x)| {
                x.as_str()
                    .map(|s| (i.to_string(), s.to_string()))
                    .ok_or_else(|| {
                        format!("element {i}: expected a string (`STAGE.PORT` or a path)")
                    })
            })
            .collect(),
        Value::Table(t) => t
            .iter()
            .map(|(k, x)| {
                x.as_str()
                    .map(|s| (k.clone(), s.to_string()))
                    .ok_or_else(|| format!("`{k}`: expected a string (`STAGE.PORT` or a path)"))
            })
            .collect(),
        other => Err(format!(
            "expected an array or a table of strings, found {}",
            other.type_name()
        )),
    }
}

/// Type, bounds and choices of one value; widens integers for float types.
pub fn check_value(spec: &fure_stage_api::ParamSpec, v: &Value) -> Result<Value, String> {
    if !spec.ty.accepts(v) {
        return Err(format!(
            "expected {}, found {} ({})",
            spec.ty.name(),
            v.type_name(),
            show(v)
        ));
    }
    let bounds = |x: f64| spec.check_bounds(x);
    // No parameter accepts NaN or infinities, wherever they sit (a table's
    // per-part overrides included): TOML can write `nan` and `inf`.
    if let Some(at) = non_finite_at(v, String::new()) {
        return Err(format!(
            "{}expected finite numbers only, found {} (TOML `nan`/`inf` are not accepted)",
            if at.is_empty() {
                String::new()
            } else {
                format!("`{at}`: ")
            },
            show(&first_non_finite(v))
        ));
    }
    Ok(match (spec.ty, v) {
        (ParamType::Float, _) => {
            let x = v.as_f64().unwrap_or(f64::NAN);
            if !x.is_finite() {
                return Err(format!("expected a finite number, found {x}"));
            }
            bounds(x)?;
            Value::Float(x)
        }
        (ParamType::Int, Value::Int(i)) => {
            bounds(*i as f64)?;
            v.clone()
        }
        (ParamType::FloatList, Value::List(l)) => {
            let mut out = Vec::with_capacity(l.len());
            for (i, e) in l.iter().enumerate() {
                let x = e.as_f64().unwrap_or(f64::NAN);
                if !x.is_finite() {
                    return Err(format!("element {i}: expected a finite number"));
                }
                bounds(x).map_err(|m| format!("element {i}: {m}"))?;
                out.push(Value::Float(x));
            }
            Value::List(out)
        }
        (ParamType::Str, Value::Str(s)) => {
            if !spec.choices.is_empty() && !spec.choices.contains(&s.as_str()) {
                return Err(format!("`{s}` is not one of: {}", spec.choices.join(", ")));
            }
            v.clone()
        }
        _ => v.clone(),
    })
}

/// Where the first NaN or infinite float sits inside `v` (`""` for `v` itself,
/// `a.b[2]` inside tables and arrays), or `None` when every float is finite.
fn non_finite_at(v: &Value, at: String) -> Option<String> {
    match v {
        Value::Float(f) if !f.is_finite() => Some(at),
        Value::List(l) => l
            .iter()
            .enumerate()
            .find_map(|(i, x)| non_finite_at(x, format!("{at}[{i}]"))),
        Value::Table(t) => t.iter().find_map(|(k, x)| {
            non_finite_at(
                x,
                if at.is_empty() {
                    k.clone()
                } else {
                    format!("{at}.{k}")
                },
            )
        }),
        _ => None,
    }
}

/// The first non-finite float inside `v` (for the message), `v` itself otherwise.
fn first_non_finite(v: &Value) -> Value {
    match v {
        Value::List(l) => l
            .iter()
            .find(|x| non_finite_at(x, String::new()).is_some())
            .map(first_non_finite)
            .unwrap_or_else(|| v.clone()),
        Value::Table(t) => t
            .values()
            .find(|x| non_finite_at(x, String::new()).is_some())
            .map(first_non_finite)
            .unwrap_or_else(|| v.clone()),
        _ => v.clone(),
    }
}

/// A value as TOML-ish text, for messages.
pub fn show(v: &Value) -> String {
    match v {
        Value::Bool(b) => b.to_string(),
        Value::Int(i) => i.to_string(),
        Value::Float(f) => {
            if f.fract() == 0.0 && f.abs() < 1e15 {
                format!("{f:.1}")
            } else {
                f.to_string()
            }
        }
        Value::Str(s) => format!("{s:?}"),
        Value::List(l) => format!("[{}]", l.iter().map(show).collect::<Vec<_>>().join(", ")),
        Value::Table(t) => format!(
            "{{ {} }}",
            t.iter()
                .map(|(k, v)| format!("{k} = {}", show(v)))
                .collect::<Vec<_>>()
                .join(", ")
        ),
    }
}

fn resolve_source(
    inp: &InputDecl,
    names: &BTreeMap<&str, usize>,
    partials: &[Option<Partial<'_>>],
    pipeline: &Pipeline,
) -> Result<Source, PipelineError> {
    let text = inp.text.as_str();
    if !text.contains('/') {
        if let Some((stage, port)) = text.split_once('.') {
            if let Some(&i) = names.get(stage) {
                let Some(p) = &partials[i] else {
                    // That stage has its own error already; do not pile on.
                    return Ok(Source::Upstream {
                        stage: i,
                        port: port.to_string(),
                    });
                };
                if !p.outputs.iter().any(|o| o.name == port) {
                    return Err(PipelineError::at(
                        &inp.loc,
                        format!(
                            "stage `{stage}` (kind `{}`) has no output `{port}` (expected one of: {})",
                            p.stage.kind(),
                            list_ports(&p.outputs)
                        ),
                    ));
                }
                return Ok(Source::Upstream {
                    stage: i,
                    port: port.to_string(),
                });
            }
        }
    }
    let path = inp.base.join(text);
    if path.exists() {
        return Ok(Source::Path {
            path,
            written: text.to_string(),
        });
    }
    let stages: Vec<&str> = pipeline.stages.iter().map(|s| s.name.as_str()).collect();
    Err(PipelineError::at(
        &inp.loc,
        format!(
            "input `{text}` is neither an output of a stage (STAGE.PORT with STAGE one of: {}) nor an existing file (looked for {})",
            stages.join(", "),
            path.display()
        ),
    ))
}

fn check_port_kinds(
    p: &Partial<'_>,
    spec: &PortSpec,
    source: &Source,
    inp: &InputDecl,
    partials: &[Option<Partial<'_>>],
) -> Result<(), PipelineError> {
    if p.stage.kind() == command::KIND {
        return Ok(()); // command deps accept files and directories alike
    }
    let want_dir = spec.kind == PortKind::Dir;
    let have_dir = match source {
        Source::Path { path, .. } => path.is_dir(),
        Source::Upstream { stage, port } => match &partials[*stage] {
            Some(up) => up
                .outputs
                .iter()
                .find(|o| &o.name == port)
                .map(|o| o.kind == PortKind::Dir)
                .unwrap_or(want_dir),
            None => want_dir,
        },
    };
    if want_dir != have_dir {
        let what = |d: bool| if d { "a directory" } else { "a file" };
        return Err(PipelineError::at(
            &inp.loc,
            format!(
                "input `{}` of stage `{}` expects {}, but `{}` is {}",
                spec.name,
                p.decl.name,
                what(want_dir),
                inp.text,
                what(have_dir)
            ),
        ));
    }
    Ok(())
}

fn cycle_error(
    graph: &DiGraph<usize, ()>,
    pipeline: &Pipeline,
    resolved: &[Vec<Input>],
) -> PipelineError {
    let sccs = petgraph::algo::tarjan_scc(graph);
    let cyc = sccs
        .into_iter()
        .find(|c| c.len() > 1 || graph.contains_edge(c[0], c[0]))
        .unwrap_or_default();
    let mut members: Vec<usize> = cyc.iter().map(|n| graph[*n]).collect();
    members.sort_unstable();
    let set: BTreeSet<usize> = members.iter().copied().collect();
    // Walk the cycle from its first member for a readable path.
    let mut path = Vec::new();
    let mut loc = None;
    if let Some(&start) = members.first() {
        let mut cur = start;
        loop {
            path.push(pipeline.stages[cur].name.clone());
            // The next member that reads from `cur`.
            let next = (0..resolved.len())
                .filter(|j| set.contains(j))
                .find_map(|j| {
                    resolved[j].iter().find_map(|inp| match inp.source {
                        Source::Upstream { stage, .. } if stage == cur => {
                            Some((j, inp.loc.clone()))
                        }
                        _ => None,
                    })
                });
            match next {
                Some((j, l)) => {
                    if loc.is_none() {
                        loc = Some(l);
                    }
                    if j == start || path.len() > members.len() {
                        path.push(pipeline.stages[j].name.clone());
                        break;
                    }
                    cur = j;
                }
                None => break,
            }
        }
    }
    let message = format!(
        "dependency cycle: {} (a stage cannot depend on its own outputs)",
        path.join(" -> ")
    );
    match loc {
        Some(l) => PipelineError::at(&l, message),
        None => PipelineError::bare(message),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use fure_stage_api::{ParamSpec, StageContext, StageError};
    use std::path::Path;

    struct K;
    impl Stage for K {
        fn kind(&self) -> &'static str {
            "k"
        }
        fn version(&self) -> u32 {
            1
        }
        fn doc(&self) -> &'static str {
            "test"
        }
        fn params(&self) -> Vec<ParamSpec> {
            vec![
                ParamSpec::float("x", 1.0, "x").range(0.0, 10.0),
                ParamSpec::string("mode", "a", "m").choices(&["a", "b"]),
                ParamSpec::float("sigma", 1.0, "s").positive(),
                ParamSpec::int("n", 1, "n").min(1.0),
                ParamSpec::float_list("l", &[1.0], "l"),
                ParamSpec::table("parts", "per-part overrides"),
            ]
        }
        fn inputs(&self, _: &Params) -> Vec<PortSpec> {
            vec![PortSpec::file("src", "txt", "source").optional()]
        }
        fn outputs(&self, _: &Params) -> Vec<PortSpec> {
            vec![PortSpec::file("out", "txt", "out")]
        }
        fn run(&self, _: &StageContext<'_>) -> Result<(), StageError> {
            Ok(())
        }
    }

    fn plan_str(text: &str) -> Result<Plan, PipelineErrors> {
        let reg = Registry::new(vec![Box::new(K)]).unwrap();
        let p = Pipeline::parse_str(text, "p.toml", Path::new("/nonexistent")).unwrap();
        plan(&p, &reg)
    }

    #[test]
    fn orders_topologically_and_fills_defaults() {
        let p = plan_str(
            "[stages.b]\nkind=\"k\"\ninputs={src=\"a.out\"}\n[stages.a]\nkind=\"k\"\nx=2\n",
        )
        .unwrap();
        let names: Vec<&str> = p.stages.iter().map(|s| s.name.as_str()).collect();
        assert_eq!(names, ["a", "b"]);
        assert_eq!(p.stages[0].params.get("x"), Some(&Value::Float(2.0)));
        assert_eq!(p.stages[1].params.get("x"), Some(&Value::Float(1.0)));
        assert_eq!(p.stages[1].upstream, vec![0]);
    }

    #[test]
    fn reports_every_problem_with_locations() {
        let e = plan_str(
            "[stages.a]\nkind=\"k\"\nx=\"big\"\nzz=1\nmode=\"c\"\n[stages.b]\nkind=\"nope\"\n[stages.c]\nkind=\"k\"\ninputs={src=\"d.missing\", bad=\"a.out\"}\n[stages.d]\nkind=\"k\"\n",
        )
        .unwrap_err();
        let s = e.to_string();
        assert!(
            s.contains(
                "p.toml:3:1: error: stage `a`: parameter `x`: expected number, found string"
            ),
            "{s}"
        );
        assert!(
            s.contains("p.toml:4:1: error: stage `a`: unknown parameter `zz`"),
            "{s}"
        );
        assert!(s.contains("`c` is not one of: a, b"), "{s}");
        assert!(
            s.contains("p.toml:7:6: error: stage `b`: unknown kind `nope`"),
            "{s}"
        );
        assert!(s.contains("has no output `missing`"), "{s}");
        assert!(s.contains("has no input port `bad`"), "{s}");
    }

    #[test]
    fn non_finite_zero_and_negative_values_are_located() {
        let e = plan_str(
            "[stages.a]\nkind=\"k\"\nx=nan\nsigma=0\nn=-3\nl=[1.0, inf]\n\
             [stages.a.parts.torso]\nlength_cm=-nan\n[stages.b]\nkind=\"k\"\nsigma=-inf\nx=+inf\n",
        )
        .unwrap_err();
        let s = e.to_string();
        for want in [
            "p.toml:3:1: error: stage `a`: parameter `x`: expected finite numbers only, found NaN",
            "p.toml:4:1: error: stage `a`: parameter `sigma`: 0 is not allowed: expected a number greater than 0",
            "p.toml:5:1: error: stage `a`: parameter `n`: -3 is below the minimum 1",
            "p.toml:6:1: error: stage `a`: parameter `l`: `[1]`: expected finite numbers only, found inf",
            "parameter `parts`: `torso.length_cm`: expected finite numbers only, found NaN",
            "p.toml:11:1: error: stage `b`: parameter `sigma`: expected finite numbers only, found -inf",
            "p.toml:12:1: error: stage `b`: parameter `x`: expected finite numbers only, found inf",
        ] {
            assert!(s.contains(want), "missing `{want}` in:\n{s}");
        }
        // Within bounds and finite: accepted.
        plan_str(
            "[stages.a]\nkind=\"k\"\nsigma=1e-9\nn=1\n[stages.a.parts.torso]\nlength_cm=2.0\n",
        )
        .unwrap();
    }

    #[test]
    fn detects_cycles() {
        let e = plan_str("[stages.a]\nkind=\"k\"\ninputs={src=\"b.out\"}\n[stages.b]\nkind=\"k\"\ninputs={src=\"a.out\"}\n")
            .unwrap_err();
        let s = e.to_string();
        assert!(s.contains("dependency cycle: a -> b -> a"), "{s}");
        assert!(s.starts_with("p.toml:"), "{s}");
    }

    #[test]
    fn until_keeps_ancestors_only() {
        let p = plan_str(
            "[stages.a]\nkind=\"k\"\n[stages.b]\nkind=\"k\"\ninputs={src=\"a.out\"}\n[stages.c]\nkind=\"k\"\n",
        )
        .unwrap();
        let u = p.until("b").unwrap();
        assert_eq!(u.stages.len(), 2);
        assert_eq!(u.stages[1].upstream, vec![0]);
        assert!(p.until("zz").is_err());
    }
}
