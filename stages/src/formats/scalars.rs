//! Per-vertex scalar arrays (shell widths, lengths, densities...).
//!
//! Format: a JSON document `{"values": [v0, v1, ...]}` (one number per vertex, in vertex order),
//! written pretty with a trailing newline. JSON rather than a binary blob because these arrays are
//! small (one float per mesh vertex), users inspect and hand-edit them (an imported Frosting width
//! map, say), and the shortest-round-trip float printing keeps the round trip exact. For reading, a
//! bare JSON array `[v0, v1, ...]` is accepted too. Values must be finite: JSON has no NaN, and a
//! NaN width would poison every stage downstream.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::json::{from_slice, to_pretty_bytes};
use super::{check_finite, read_bytes, write_bytes, FormatError};

#[derive(Serialize)]
struct ScalarsOut<'a> {
    values: &'a [f32],
}

#[derive(Deserialize)]
#[serde(untagged)]
enum ScalarsIn {
    Object { values: Vec<f32> },
    Bare(Vec<f32>),
}

/// Reads a per-vertex scalar array.
pub fn read_scalars(path: impl AsRef<Path>) -> Result<Vec<f32>, FormatError> {
    let path = path.as_ref();
    let bytes = read_bytes(path)?;
    // Parse to a Value first so that syntax errors keep their line/column (untagged enums lose it).
    let value: serde_json::Value = from_slice(path, &bytes)?;
    let parsed: ScalarsIn = serde_json::from_value(value).map_err(|_| {
        FormatError::invalid(
            path,
            "expected {\"values\": [numbers...]} or a bare array of numbers",
        )
    })?;
    let values = match parsed {
        ScalarsIn::Object { values } | ScalarsIn::Bare(values) => values,
    };
    for (i, v) in values.iter().enumerate() {
        if !v.is_finite() {
            return Err(FormatError::at(
                path,
                super::Position::Field(format!("values[{i}]")),
                format!("expected a finite number, got {v} (out of f32 range?)"),
            ));
        }
    }
    Ok(values)
}

/// Writes a per-vertex scalar array as `{"values": [...]}`.
pub fn write_scalars(path: impl AsRef<Path>, values: &[f32]) -> Result<(), FormatError> {
    let path = path.as_ref();
    check_finite(path, "values", values.iter().copied())?;
    let bytes = to_pretty_bytes(path, &ScalarsOut { values })?;
    write_bytes(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_exact() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("w.json");
        let v: Vec<f32> = (0..1000)
            .map(|i| ((i as f32) * 0.731).sin() * 1e-3)
            .collect();
        write_scalars(&p, &v).unwrap();
        assert_eq!(read_scalars(&p).unwrap(), v);
        write_scalars(&p, &[]).unwrap();
        assert!(read_scalars(&p).unwrap().is_empty());
    }

    #[test]
    fn bare_array_accepted() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("w.json");
        std::fs::write(&p, "[1, 2.5, -3e-2]").unwrap();
        assert_eq!(read_scalars(&p).unwrap(), vec![1.0, 2.5, -0.03]);
    }

    #[test]
    fn bad_inputs_give_errors() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("w.json");
        assert!(write_scalars(&p, &[1.0, f32::INFINITY]).is_err());
        std::fs::write(&p, "{\"values\": [1, \"x\"]}").unwrap();
        let e = read_scalars(&p).unwrap_err();
        assert!(e.to_string().contains("w.json"), "{e}");
        std::fs::write(&p, "{\"values\": [1, 2").unwrap();
        let e = read_scalars(&p).unwrap_err();
        assert!(e.position().is_some(), "{e}");
        std::fs::write(&p, "{\"values\": [1, 1e300]}").unwrap();
        let e = read_scalars(&p).unwrap_err();
        assert!(e.to_string().contains("values[1]"), "{e}");
    }
}
