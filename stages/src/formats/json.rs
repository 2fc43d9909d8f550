//! JSON documents for any serde type.
//!
//! Written pretty (two-space indent) with a trailing newline. Output is deterministic as long as
//! the type is (use `BTreeMap`, never `HashMap`, in serialised types). Non-finite floats, which JSON
//! cannot represent (serde_json would silently write `null`), are refused by [`write_json`].
//! Parse errors carry serde_json's line and column.

use std::path::Path;

use serde::de::DeserializeOwned;
use serde::Serialize;

use super::{read_bytes, write_bytes, FormatError, Position};

/// `#[serde(skip_serializing_if = "crate::formats::json::is_zero")]`: leaves a
/// report field out at 0, so adding an optional setting's report keeps the
/// bytes of every report written without it.
pub fn is_zero(x: &f32) -> bool {
    *x == 0.0
}

/// Reads a JSON file into `T`.
pub fn read_json<T: DeserializeOwned>(path: impl AsRef<Path>) -> Result<T, FormatError> {
    let path = path.as_ref();
    let bytes = read_bytes(path)?;
    from_slice(path, &bytes)
}

/// Parses JSON bytes that came from `path` (used for messages only).
pub(crate) fn from_slice<T: DeserializeOwned>(path: &Path, bytes: &[u8]) -> Result<T, FormatError> {
    serde_json::from_slice(bytes).map_err(|e| json_error(path, e))
}

/// Maps a serde_json error to a positioned [`FormatError`].
pub(crate) fn json_error(path: &Path, e: serde_json::Error) -> FormatError {
    if e.is_io() {
        return FormatError::io(path, std::io::Error::other(e.to_string()));
    }
    let (line, column) = (e.line(), e.column());
    // serde_json appends " at line L column C" to its message; the position is ours to print.
    let msg = e.to_string();
    let msg = match msg.rfind(" at line ") {
        Some(i) => msg[..i].to_string(),
        None => msg,
    };
    if line == 0 {
        FormatError::invalid(path, msg)
    } else {
        FormatError::at(path, Position::LineColumn { line, column }, msg)
    }
}

/// Serialises `value` to pretty JSON bytes with a trailing newline.
pub(crate) fn to_pretty_bytes<T: Serialize + ?Sized>(
    path: &Path,
    value: &T,
) -> Result<Vec<u8>, FormatError> {
    // serde_json writes NaN and infinities as `null`, which would read back as an error or a
    // silently different value; a cheap probe serializer finds them first.
    let mut probe = FiniteProbe { bad: None };
    value
        .serialize(&mut probe)
        .map_err(|e| FormatError::invalid(path, e))?;
    if let Some(what) = probe.bad {
        return Err(FormatError::invalid(
            path,
            format!("refusing to write a non-finite number ({what}): JSON cannot represent it"),
        ));
    }
    let mut bytes = serde_json::to_vec_pretty(value).map_err(|e| FormatError::invalid(path, e))?;
    bytes.push(b'\n');
    Ok(bytes)
}

/// Writes `value` as pretty JSON with a trailing newline, creating parent directories.
pub fn write_json<T: Serialize + ?Sized>(
    path: impl AsRef<Path>,
    value: &T,
) -> Result<(), FormatError> {
    let path = path.as_ref();
    let bytes = to_pretty_bytes(path, value)?;
    write_bytes(path, &bytes)
}

/// A serializer that only looks for NaN and infinities (cheap: it never builds output).
struct FiniteProbe {
    bad: Option<String>,
}

#[derive(Debug)]
struct ProbeError(String);
impl std::fmt::Display for ProbeError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}
impl std::error::Error for ProbeError {}
impl serde::ser::Error for ProbeError {
    fn custom<M: std::fmt::Display>(msg: M) -> Self {
        ProbeError(msg.to_string())
    }
}

impl FiniteProbe {
    fn float(&mut self, v: f64) {
        if !v.is_finite() && self.bad.is_none() {
            self.bad = Some(v.to_string());
        }
    }
}

macro_rules! probe_ok {
    ($($name:ident : $t:ty),*) => {
        $(fn $name(self, _v: $t) -> Result<(), ProbeError> { Ok(()) })*
    };
}

impl serde::Serializer for &mut FiniteProbe {
    type Ok = ();
    type Error = ProbeError;
    type SerializeSeq = Self;
    type SerializeTuple = Self;
    type SerializeTupleStruct = Self;
    type SerializeTupleVariant = Self;
    type SerializeMap = Self;
    type SerializeStruct = Self;
    type SerializeStructVariant = Self;

    probe_ok!(serialize_bool: bool, serialize_i8: i8, serialize_i16: i16, serialize_i32: i32,
        serialize_i64: i64, serialize_u8: u8, serialize_u16: u16, serialize_u32: u32,
        serialize_u64: u64, serialize_char: char, serialize_str: &str, serialize_bytes: &[u8]);

    fn serialize_f32(self, v: f32) -> Result<(), ProbeError> {
        self.float(v as f64);
        Ok(())
    }
    fn serialize_f64(self, v: f64) -> Result<(), ProbeError> {
        self.float(v);
        Ok(())
    }
    fn serialize_none(self) -> Result<(), ProbeError> {
        Ok(())
    }
    fn serialize_some<T: ?Sized + Serialize>(self, value: &T) -> Result<(), ProbeError> {
        value.serialize(self)
    }
    fn serialize_unit(self) -> Result<(), ProbeError> {
        Ok(())
    }
    fn serialize_unit_struct(self, _: &'static str) -> Result<(), ProbeError> {
        Ok(())
    }
    fn serialize_unit_variant(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
    ) -> Result<(), ProbeError> {
        Ok(())
    }
    fn serialize_newtype_struct<T: ?Sized + Serialize>(
        self,
        _: &'static str,
        value: &T,
    ) -> Result<(), ProbeError> {
        value.serialize(self)
    }
    fn serialize_newtype_variant<T: ?Sized + Serialize>(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
        value: &T,
    ) -> Result<(), ProbeError> {
        value.serialize(self)
    }
    fn serialize_seq(self, _: Option<usize>) -> Result<Self, ProbeError> {
        Ok(self)
    }
    fn serialize_tuple(self, _: usize) -> Result<Self, ProbeError> {
        Ok(self)
    }
    fn serialize_tuple_struct(self, _: &'static str, _: usize) -> Result<Self, ProbeError> {
        Ok(self)
    }
    fn serialize_tuple_variant(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
        _: usize,
    ) -> Result<Self, ProbeError> {
        Ok(self)
    }
    fn serialize_map(self, _: Option<usize>) -> Result<Self, ProbeError> {
        Ok(self)
    }
    fn serialize_struct(self, _: &'static str, _: usize) -> Result<Self, ProbeError> {
        Ok(self)
    }
    fn serialize_struct_variant(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
        _: usize,
    ) -> Result<Self, ProbeError> {
        Ok(self)
    }
}

macro_rules! probe_compound {
    ($trait:ident, $method:ident $(, $key:ident)?) => {
        impl serde::ser::$trait for &mut FiniteProbe {
            type Ok = ();
            type Error = ProbeError;
            fn $method<T: ?Sized + Serialize>(&mut self, $($key: &'static str,)? value: &T) -> Result<(), ProbeError> {
                $(let _ = $key;)?
                value.serialize(&mut **self)
            }
            fn end(self) -> Result<(), ProbeError> {
                Ok(())
            }
        }
    };
}
probe_compound!(SerializeSeq, serialize_element);
probe_compound!(SerializeTuple, serialize_element);
probe_compound!(SerializeTupleStruct, serialize_field);
probe_compound!(SerializeTupleVariant, serialize_field);
probe_compound!(SerializeStruct, serialize_field, key);
probe_compound!(SerializeStructVariant, serialize_field, key);

impl serde::ser::SerializeMap for &mut FiniteProbe {
    type Ok = ();
    type Error = ProbeError;
    fn serialize_key<T: ?Sized + Serialize>(&mut self, key: &T) -> Result<(), ProbeError> {
        key.serialize(&mut **self)
    }
    fn serialize_value<T: ?Sized + Serialize>(&mut self, value: &T) -> Result<(), ProbeError> {
        value.serialize(&mut **self)
    }
    fn end(self) -> Result<(), ProbeError> {
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::Deserialize;
    use std::collections::BTreeMap;

    #[derive(Debug, PartialEq, Serialize, Deserialize)]
    struct Doc {
        name: String,
        values: Vec<f32>,
        map: BTreeMap<String, f64>,
        opt: Option<f32>,
    }

    fn doc() -> Doc {
        let mut map = BTreeMap::new();
        map.insert("b".to_string(), 0.1);
        map.insert("a".to_string(), -3.5e-12);
        Doc {
            name: "x \"quoted\"".into(),
            values: vec![0.1, 1.0 / 3.0, f32::MIN_POSITIVE, f32::MAX, -0.0],
            map,
            opt: None,
        }
    }

    #[test]
    fn round_trip_is_exact_and_deterministic() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("sub/dir/doc.json");
        write_json(&p, &doc()).unwrap();
        let back: Doc = read_json(&p).unwrap();
        assert_eq!(back, doc());
        let first = std::fs::read(&p).unwrap();
        assert_eq!(*first.last().unwrap(), b'\n');
        write_json(&p, &back).unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), first);
    }

    #[test]
    fn f32_values_round_trip_bit_exactly() {
        // serde_json parses through f64; check that the shortest f32 text survives that for a
        // spread of bit patterns (all exponents, random mantissas).
        let mut x = 0x9E37_79B9u32;
        let mut values = Vec::new();
        while values.len() < 100_000 {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            let v = f32::from_bits(x);
            if v.is_finite() {
                values.push(v);
            }
        }
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("f.json");
        write_json(&p, &values).unwrap();
        let back: Vec<f32> = read_json(&p).unwrap();
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&back), bits(&values));
    }

    #[test]
    fn non_finite_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("bad.json");
        let mut d = doc();
        d.opt = Some(f32::NAN);
        let e = write_json(&p, &d).unwrap_err();
        assert!(e.to_string().contains("non-finite"), "{e}");
        assert!(!p.exists());
    }

    #[test]
    fn syntax_error_names_line_and_column() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("broken.json");
        std::fs::write(&p, "{\n  \"name\": \"x\",\n  \"values\": [1, 2,, 3]\n}\n").unwrap();
        let e = read_json::<Doc>(&p).unwrap_err();
        let s = e.to_string();
        assert!(s.contains("broken.json"), "{s}");
        assert_eq!(
            e.position(),
            Some(&Position::LineColumn {
                line: 3,
                column: 19
            }),
            "{s}"
        );
    }

    #[test]
    fn truncated_file_is_an_error_with_position() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("t.json");
        write_json(&p, &doc()).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        std::fs::write(&p, &bytes[..bytes.len() / 2]).unwrap();
        let e = read_json::<Doc>(&p).unwrap_err();
        assert!(matches!(e, FormatError::Malformed { .. }), "{e}");
        assert!(e.to_string().contains("EOF"), "{e}");
    }

    #[test]
    fn missing_file_is_io_error_naming_it() {
        let e = read_json::<Doc>("/nonexistent/fure/x.json").unwrap_err();
        assert!(matches!(e, FormatError::Io { .. }));
        assert!(e.to_string().contains("/nonexistent/fure/x.json"));
        let s: fure_stage_api::StageError = e.into();
        assert!(s.to_string().contains("x.json"));
    }
}
