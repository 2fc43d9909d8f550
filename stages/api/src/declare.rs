//! Parameters declared once: [`stage_params!`](crate::stage_params) turns one list of fields into the stage's
//! [`ParamSpec`](crate::ParamSpec) list (what the engine checks and `fure stages` prints) and a typed settings
//! struct read from [`Params`], so a parameter's name, type, default, bounds and doc are written
//! in one place and the stage reads fields, not strings. [`param_enum!`](crate::param_enum) declares an enum whose
//! values are a string parameter's choices.
//!
//! A field is `name: Type = constructor(args).chain(args)...`: the constructor and the chained
//! calls are [`ParamSpec`](crate::ParamSpec)'s (`float`, `int`, `bool`, `string`, `str_list`, `float_list`, `table`,
//! `optional`, then `positive`, `range`, `choices`, ...) with the name and the doc left out: the
//! name is the field's, the doc its `///` comment. The type says how the value is read
//! ([`FromParam`]).

use std::collections::BTreeMap;

use crate::{Params, StageError, Value};

/// Reading one parameter's value as a Rust type (the engine has already checked its type,
/// bounds and choices against the [`ParamSpec`](crate::ParamSpec)).
pub trait FromParam: Sized {
    fn from_param(p: &Params, name: &str) -> Result<Self, StageError>;
}

impl FromParam for f64 {
    fn from_param(p: &Params, name: &str) -> Result<Self, StageError> {
        p.f64(name)
    }
}

impl FromParam for f32 {
    fn from_param(p: &Params, name: &str) -> Result<Self, StageError> {
        p.f32(name)
    }
}

impl FromParam for i64 {
    fn from_param(p: &Params, name: &str) -> Result<Self, StageError> {
        p.i64(name)
    }
}

impl FromParam for usize {
    fn from_param(p: &Params, name: &str) -> Result<Self, StageError> {
        p.usize(name)
    }
}

impl FromParam for u64 {
    fn from_param(p: &Params, name: &str) -> Result<Self, StageError> {
        p.u64(name)
    }
}

impl FromParam for u32 {
    fn from_param(p: &Params, name: &str) -> Result<Self, StageError> {
        let x = p.u64(name)?;
        u32::try_from(x)
            .map_err(|_| StageError::param(name, format!("{x} does not fit in 32 bits")))
    }
}

impl FromParam for bool {
    fn from_param(p: &Params, name: &str) -> Result<Self, StageError> {
        p.bool(name)
    }
}

impl FromParam for String {
    fn from_param(p: &Params, name: &str) -> Result<Self, StageError> {
        p.str(name).map(str::to_string)
    }
}

impl FromParam for Vec<String> {
    fn from_param(p: &Params, name: &str) -> Result<Self, StageError> {
        p.str_list(name)
    }
}

impl FromParam for Vec<f64> {
    fn from_param(p: &Params, name: &str) -> Result<Self, StageError> {
        p.f64_list(name)
    }
}

impl FromParam for BTreeMap<String, Value> {
    fn from_param(p: &Params, name: &str) -> Result<Self, StageError> {
        p.table(name)
    }
}

/// A table of non-negative numbers (per-part multipliers, thicknesses, lengths): every value
/// must be a finite number >= 0.
impl FromParam for BTreeMap<String, f32> {
    fn from_param(p: &Params, name: &str) -> Result<Self, StageError> {
        let mut out = BTreeMap::new();
        for (k, v) in p.table(name)? {
            let x = v.as_f64().ok_or_else(|| {
                StageError::param(
                    name,
                    format!("`{k}`: expected a number, found {}", v.type_name()),
                )
            })?;
            if !(x.is_finite() && x >= 0.0) {
                return Err(StageError::param(
                    name,
                    format!("`{k}`: expected a non-negative number, found {x}"),
                ));
            }
            out.insert(k, x as f32);
        }
        Ok(out)
    }
}

/// An unset optional parameter is `None`; a set one is read as `T`.
impl<T: FromParam> FromParam for Option<T> {
    fn from_param(p: &Params, name: &str) -> Result<Self, StageError> {
        match p.get(name) {
            None => Ok(None),
            Some(_) => T::from_param(p, name).map(Some),
        }
    }
}

/// Checks every set value against its spec's bounds and choices, as the engine does before a
/// stage runs, so a struct read by `from_params` holds declared values whoever calls it (a
/// stage's own `validate`, a test, a library user).
pub fn check_declared(specs: &[crate::ParamSpec], p: &Params) -> Result<(), StageError> {
    for spec in specs {
        let Some(v) = p.get(spec.name) else {
            continue;
        };
        let numbers: Vec<f64> = match v {
            Value::List(l) => l.iter().filter_map(Value::as_f64).collect(),
            other => other.as_f64().into_iter().collect(),
        };
        for x in numbers {
            spec.check_bounds(x)
                .map_err(|e| StageError::param(spec.name, e))?;
        }
        if let Some(text) = v.as_str() {
            if !spec.choices.is_empty() && !spec.choices.contains(&text) {
                return Err(StageError::param(
                    spec.name,
                    format!("`{text}`: expected one of {}", spec.choices.join(", ")),
                ));
            }
        }
    }
    Ok(())
}

/// Declares a stage's parameters once: a struct with one public field per parameter, its
/// `specs()` (the [`ParamSpec`](crate::ParamSpec) list, in field order) and `from_params`
/// (the typed values). See the [module doc](crate::declare).
///
/// ```
/// use fure_stage_api::{stage_params, Params, ParamType};
/// stage_params! {
///     /// Parameters of a toy stage.
///     pub struct ToyParams {
///         /// how many
///         count: usize = int(3).range(1.0, 10.0),
///         /// an explicit scale, or unset
///         scale: Option<f32> = optional(ParamType::Float).positive(),
///     }
/// }
/// let specs = ToyParams::specs();
/// assert_eq!((specs[0].name, specs[0].doc), ("count", "how many"));
/// let p = Params(std::iter::once(("count".to_string(), fure_stage_api::Value::Int(4))).collect());
/// let t = ToyParams::from_params(&p).unwrap();
/// assert_eq!((t.count, t.scale), (4, None));
/// ```
#[macro_export]
macro_rules! stage_params {
    (
        $(#[$meta:meta])*
        $vis:vis struct $name:ident {
            $(
                $(#[doc = $doc:expr])+
                $field:ident : $ty:ty = $ctor:ident ( $($arg:expr),* $(,)? )
                    $( . $chain:ident ( $($carg:expr),* $(,)? ) )*
            ),* $(,)?
        }
    ) => {
        $(#[$meta])*
        #[derive(Debug, Clone)]
        $vis struct $name {
            $( $(#[doc = $doc])+ pub $field: $ty, )*
        }

        impl $name {
            /// The parameters' specs, in declaration order.
            pub fn specs() -> ::std::vec::Vec<$crate::ParamSpec> {
                ::std::vec![
                    $(
                        $crate::ParamSpec::$ctor(
                            stringify!($field),
                            $($arg,)*
                            concat!($($doc),+).trim(),
                        ) $( . $chain ( $($carg),* ) )*
                    ),*
                ]
            }

            /// The declared defaults (unset optional parameters are `None`): the values a
            /// pipeline gets when it sets nothing. Fails only for a parameter declared without
            /// a default.
            pub fn defaults() -> ::std::result::Result<Self, $crate::StageError> {
                let p = $crate::Params(
                    Self::specs()
                        .into_iter()
                        .filter_map(|s| s.default.map(|d| (s.name.to_string(), d)))
                        .collect(),
                );
                Self::from_params(&p)
            }

            /// The typed values, each checked against its declared bounds and choices.
            pub fn from_params(p: &$crate::Params) -> ::std::result::Result<Self, $crate::StageError> {
                $crate::declare::check_declared(&Self::specs(), p)?;
                Ok($name {
                    $( $field: <$ty as $crate::FromParam>::from_param(p, stringify!($field))?, )*
                })
            }
        }
    };
}

/// Declares an enum whose values are a string parameter's choices: `NAMES` (for
/// [`ParamSpec::choices`](crate::ParamSpec::choices)), `name()`, and [`FromParam`].
///
/// ```
/// use fure_stage_api::param_enum;
/// param_enum! {
///     /// How to read a width.
///     pub enum Reading { Outer = "outer", Inner = "inner" }
/// }
/// assert_eq!(Reading::NAMES, &["outer", "inner"]);
/// assert_eq!(Reading::Inner.name(), "inner");
/// ```
#[macro_export]
macro_rules! param_enum {
    (
        $(#[$meta:meta])*
        $vis:vis enum $name:ident {
            $( $(#[$vmeta:meta])* $variant:ident = $text:literal ),+ $(,)?
        }
    ) => {
        $(#[$meta])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq)]
        $vis enum $name {
            $( $(#[$vmeta])* $variant ),+
        }

        impl $name {
            /// The parameter's allowed strings, one per variant.
            pub const NAMES: &'static [&'static str] = &[$($text),+];

            /// The parameter string of this variant.
            pub fn name(self) -> &'static str {
                match self {
                    $( $name::$variant => $text ),+
                }
            }
        }

        impl $crate::FromParam for $name {
            fn from_param(p: &$crate::Params, name: &str) -> ::std::result::Result<Self, $crate::StageError> {
                match p.str(name)? {
                    $( $text => Ok($name::$variant), )+
                    other => Err($crate::StageError::param(
                        name,
                        format!("unknown value `{other}`: expected one of {}", Self::NAMES.join(", ")),
                    )),
                }
            }
        }
    };
}

#[cfg(test)]
mod tests {
    use crate::{ParamType, Params, Value};

    crate::param_enum! {
        /// A choice.
        enum Mode { Fast = "fast", Exact = "exact" }
    }

    crate::stage_params! {
        /// Every kind of field.
        struct All {
            /// a count
            /// over two lines
            n: usize = int(3).range(1.0, 9.0),
            /// a rate
            rate: f32 = float(0.5).positive(),
            /// a mode
            mode: Mode = string("fast").choices(Mode::NAMES),
            /// maybe a scale
            scale: Option<f64> = optional(ParamType::Float),
            /// names
            names: Vec<String> = str_list(&["a"]),
        }
    }

    fn params(pairs: &[(&str, Value)]) -> Params {
        Params(
            pairs
                .iter()
                .map(|(k, v)| (k.to_string(), v.clone()))
                .collect(),
        )
    }

    #[test]
    fn specs_carry_name_default_bounds_choices_and_the_doc() {
        let s = All::specs();
        let names: Vec<&str> = s.iter().map(|p| p.name).collect();
        assert_eq!(names, ["n", "rate", "mode", "scale", "names"]);
        assert_eq!(s[0].doc, "a count over two lines");
        assert_eq!((s[0].min, s[0].max), (Some(1.0), Some(9.0)));
        assert!(s[1].min_exclusive);
        assert_eq!(s[2].choices, &["fast", "exact"]);
        assert!(s[3].optional && s[3].default.is_none());
        assert_eq!(s[4].ty, ParamType::StrList);
    }

    #[test]
    fn values_are_read_typed_and_a_bad_choice_names_the_parameter() {
        let ok = params(&[
            ("n", Value::Int(4)),
            ("rate", Value::Float(0.25)),
            ("mode", Value::Str("exact".into())),
            ("names", Value::List(vec![Value::Str("b".into())])),
        ]);
        let d = All::defaults().unwrap();
        assert_eq!((d.n, d.rate, d.mode, d.scale), (3, 0.5, Mode::Fast, None));
        assert_eq!(d.names, ["a"]);
        let a = All::from_params(&ok).unwrap();
        assert_eq!((a.n, a.rate, a.mode, a.scale), (4, 0.25, Mode::Exact, None));
        assert_eq!(a.mode.name(), "exact");
        assert_eq!(a.names, ["b"]);
        let mut bad = ok.clone();
        bad.0.insert("mode".into(), Value::Str("slow".into()));
        let e = All::from_params(&bad).unwrap_err().to_string();
        assert!(
            e.contains("mode") && e.contains("slow") && e.contains("fast, exact"),
            "{e}"
        );
        let mut out_of_bounds = ok.clone();
        out_of_bounds.0.insert("n".into(), Value::Int(12));
        let e = All::from_params(&out_of_bounds).unwrap_err().to_string();
        assert!(e.contains('n') && e.contains("12"), "{e}");
        let mut missing = ok;
        missing.0.remove("rate");
        assert!(All::from_params(&missing)
            .unwrap_err()
            .to_string()
            .contains("rate"));
    }
}
