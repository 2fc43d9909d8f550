//! Parameter values, specifications and typed access.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::StageError;

/// A parameter value, mirroring TOML's data model (dates excluded).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Value {
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
    List(Vec<Value>),
    Table(BTreeMap<String, Value>),
}

impl Value {
    pub fn type_name(&self) -> &'static str {
        match self {
            Value::Bool(_) => "boolean",
            Value::Int(_) => "integer",
            Value::Float(_) => "float",
            Value::Str(_) => "string",
            Value::List(_) => "array",
            Value::Table(_) => "table",
        }
    }
    /// Numeric value; integers widen to floats.
    pub fn as_f64(&self) -> Option<f64> {
        match self {
            Value::Int(i) => Some(*i as f64),
            Value::Float(f) => Some(*f),
            _ => None,
        }
    }
    pub fn as_i64(&self) -> Option<i64> {
        match self {
            Value::Int(i) => Some(*i),
            _ => None,
        }
    }
    pub fn as_str(&self) -> Option<&str> {
        match self {
            Value::Str(s) => Some(s),
            _ => None,
        }
    }
    pub fn as_bool(&self) -> Option<bool> {
        match self {
            Value::Bool(b) => Some(*b),
            _ => None,
        }
    }
    pub fn as_table(&self) -> Option<&BTreeMap<String, Value>> {
        match self {
            Value::Table(t) => Some(t),
            _ => None,
        }
    }
    pub fn as_list(&self) -> Option<&[Value]> {
        match self {
            Value::List(l) => Some(l),
            _ => None,
        }
    }
}

/// The declared type of a parameter.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ParamType {
    Bool,
    Int,
    /// Floats; integers are accepted and widened.
    Float,
    Str,
    /// An array of numbers.
    FloatList,
    /// An array of strings.
    StrList,
    /// A free-form table, checked by the stage's `validate` (e.g. per-part overrides).
    Table,
}

impl ParamType {
    pub fn name(self) -> &'static str {
        match self {
            ParamType::Bool => "boolean",
            ParamType::Int => "integer",
            ParamType::Float => "number",
            ParamType::Str => "string",
            ParamType::FloatList => "array of numbers",
            ParamType::StrList => "array of strings",
            ParamType::Table => "table",
        }
    }
    /// Whether `value` fits this type.
    pub fn accepts(self, value: &Value) -> bool {
        match (self, value) {
            (ParamType::Bool, Value::Bool(_)) => true,
            (ParamType::Int, Value::Int(_)) => true,
            (ParamType::Float, Value::Int(_) | Value::Float(_)) => true,
            (ParamType::Str, Value::Str(_)) => true,
            (ParamType::FloatList, Value::List(l)) => l.iter().all(|v| v.as_f64().is_some()),
            (ParamType::StrList, Value::List(l)) => l.iter().all(|v| v.as_str().is_some()),
            (ParamType::Table, Value::Table(_)) => true,
            _ => false,
        }
    }
}

/// A declared parameter: name, type, default, allowed range and a line of doc.
#[derive(Debug, Clone)]
pub struct ParamSpec {
    pub name: &'static str,
    pub ty: ParamType,
    /// `None` means the pipeline must set it.
    pub default: Option<Value>,
    /// Inclusive numeric bounds, checked by the engine (also for each element of a FloatList).
    pub min: Option<f64>,
    pub max: Option<f64>,
    /// The lower bound excludes `min` itself (set by [`ParamSpec::positive`]: values must be > min).
    pub min_exclusive: bool,
    /// Allowed strings for `Str` parameters (empty: any).
    pub choices: &'static [&'static str],
    /// May be left unset even though there is no default.
    pub optional: bool,
    /// Left out of the stage key while it holds its default (set by
    /// [`ParamSpec::omit_default_from_key`]).
    pub omit_default_from_key: bool,
    pub doc: &'static str,
}

impl ParamSpec {
    fn new(name: &'static str, ty: ParamType, default: Option<Value>, doc: &'static str) -> Self {
        ParamSpec {
            name,
            ty,
            default,
            min: None,
            max: None,
            min_exclusive: false,
            choices: &[],
            optional: false,
            omit_default_from_key: false,
            doc,
        }
    }
    pub fn float(name: &'static str, default: f64, doc: &'static str) -> Self {
        Self::new(name, ParamType::Float, Some(Value::Float(default)), doc)
    }
    pub fn int(name: &'static str, default: i64, doc: &'static str) -> Self {
        Self::new(name, ParamType::Int, Some(Value::Int(default)), doc)
    }
    pub fn bool(name: &'static str, default: bool, doc: &'static str) -> Self {
        Self::new(name, ParamType::Bool, Some(Value::Bool(default)), doc)
    }
    pub fn string(name: &'static str, default: &str, doc: &'static str) -> Self {
        Self::new(
            name,
            ParamType::Str,
            Some(Value::Str(default.to_string())),
            doc,
        )
    }
    pub fn float_list(name: &'static str, default: &[f64], doc: &'static str) -> Self {
        let v = Value::List(default.iter().map(|x| Value::Float(*x)).collect());
        Self::new(name, ParamType::FloatList, Some(v), doc)
    }
    pub fn str_list(name: &'static str, default: &[&str], doc: &'static str) -> Self {
        let v = Value::List(default.iter().map(|x| Value::Str(x.to_string())).collect());
        Self::new(name, ParamType::StrList, Some(v), doc)
    }
    /// A table parameter, empty by default.
    pub fn table(name: &'static str, doc: &'static str) -> Self {
        Self::new(
            name,
            ParamType::Table,
            Some(Value::Table(BTreeMap::new())),
            doc,
        )
    }
    /// A parameter the pipeline must set.
    pub fn required(mut self) -> Self {
        self.default = None;
        self
    }
    /// A parameter that may be left unset: no default, not required; `Params::get` gives `None`.
    pub fn optional(name: &'static str, ty: ParamType, doc: &'static str) -> Self {
        let mut s = Self::new(name, ty, None, doc);
        s.optional = true;
        s
    }
    pub fn min(mut self, min: f64) -> Self {
        self.min = Some(min);
        self.min_exclusive = false;
        self
    }
    /// Values must be strictly greater than zero (a length, a scale, a standard deviation).
    pub fn positive(mut self) -> Self {
        self.min = Some(0.0);
        self.min_exclusive = true;
        self
    }
    /// Whether `x` satisfies the bounds; the message says which bound it breaks.
    pub fn check_bounds(&self, x: f64) -> Result<(), String> {
        if x.is_nan() {
            return Err("expected a number, found NaN".to_string());
        }
        if let Some(m) = self.min {
            if self.min_exclusive && x <= m {
                return Err(format!(
                    "{x} is not allowed: expected a number greater than {m}"
                ));
            }
            if x < m {
                return Err(format!("{x} is below the minimum {m}"));
            }
        }
        if let Some(m) = self.max {
            if x > m {
                return Err(format!("{x} is above the maximum {m}"));
            }
        }
        Ok(())
    }
    pub fn max(mut self, max: f64) -> Self {
        self.max = Some(max);
        self
    }
    pub fn range(self, min: f64, max: f64) -> Self {
        self.min(min).max(max)
    }
    pub fn choices(mut self, choices: &'static [&'static str]) -> Self {
        self.choices = choices;
        self
    }
    /// Leaves the parameter out of the stage key while it holds its default, so that adding
    /// it to a stage keeps every existing key, and with them the cache entries and sweeps
    /// made before it existed. Only for an option whose default reproduces, bit for bit,
    /// what the stage did before the option was added (an extra loss at weight 0, a step
    /// that is off): the stage's version is then left as it was. Any other value enters the
    /// key as every parameter does.
    pub fn omit_default_from_key(mut self) -> Self {
        self.omit_default_from_key = true;
        self
    }
}

/// Parameters of one stage instance: defaults filled in, types checked by the engine.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Params(pub BTreeMap<String, Value>);

impl Params {
    pub fn get(&self, name: &str) -> Option<&Value> {
        self.0.get(name)
    }
    fn need(&self, name: &str) -> Result<&Value, StageError> {
        self.0
            .get(name)
            .ok_or_else(|| StageError::param(name, "is not set"))
    }
    fn wrong(name: &str, expected: &str, v: &Value) -> StageError {
        StageError::param(
            name,
            format!("expected {expected}, found {}", v.type_name()),
        )
    }
    pub fn f64(&self, name: &str) -> Result<f64, StageError> {
        let v = self.need(name)?;
        let x = v.as_f64().ok_or_else(|| Self::wrong(name, "a number", v))?;
        if x.is_finite() {
            Ok(x)
        } else {
            Err(StageError::param(
                name,
                format!("expected a finite number, found {x}"),
            ))
        }
    }
    pub fn f32(&self, name: &str) -> Result<f32, StageError> {
        self.f64(name).map(|x| x as f32)
    }
    pub fn f64_opt(&self, name: &str) -> Result<Option<f64>, StageError> {
        match self.0.get(name) {
            None => Ok(None),
            Some(_) => self.f64(name).map(Some),
        }
    }
    pub fn i64(&self, name: &str) -> Result<i64, StageError> {
        let v = self.need(name)?;
        v.as_i64().ok_or_else(|| Self::wrong(name, "an integer", v))
    }
    pub fn usize(&self, name: &str) -> Result<usize, StageError> {
        let x = self.i64(name)?;
        usize::try_from(x).map_err(|_| {
            StageError::param(name, format!("expected a non-negative integer, found {x}"))
        })
    }
    pub fn u64(&self, name: &str) -> Result<u64, StageError> {
        self.usize(name).map(|x| x as u64)
    }
    pub fn bool(&self, name: &str) -> Result<bool, StageError> {
        let v = self.need(name)?;
        v.as_bool().ok_or_else(|| Self::wrong(name, "a boolean", v))
    }
    pub fn str(&self, name: &str) -> Result<&str, StageError> {
        let v = self.need(name)?;
        v.as_str().ok_or_else(|| Self::wrong(name, "a string", v))
    }
    pub fn f64_list(&self, name: &str) -> Result<Vec<f64>, StageError> {
        let v = self.need(name)?;
        let l = v
            .as_list()
            .ok_or_else(|| Self::wrong(name, "an array of numbers", v))?;
        l.iter()
            .map(|x| {
                x.as_f64()
                    .filter(|f| f.is_finite())
                    .ok_or_else(|| StageError::param(name, "expected an array of finite numbers"))
            })
            .collect()
    }
    pub fn str_list(&self, name: &str) -> Result<Vec<String>, StageError> {
        let v = self.need(name)?;
        let l = v
            .as_list()
            .ok_or_else(|| Self::wrong(name, "an array of strings", v))?;
        l.iter()
            .map(|x| {
                x.as_str()
                    .map(str::to_string)
                    .ok_or_else(|| StageError::param(name, "expected an array of strings"))
            })
            .collect()
    }
    /// A table parameter (empty when unset).
    pub fn table(&self, name: &str) -> Result<BTreeMap<String, Value>, StageError> {
        match self.0.get(name) {
            None => Ok(BTreeMap::new()),
            Some(Value::Table(t)) => Ok(t.clone()),
            Some(v) => Err(Self::wrong(name, "a table", v)),
        }
    }
}
