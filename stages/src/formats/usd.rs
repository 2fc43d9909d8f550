//! A groom as a USD text layer (`.usda`): the strands as `BasisCurves`, the root mesh as `Mesh`.
//!
//! ```text
//! #usda 1.0
//! ( defaultPrim = "fure"  metersPerUnit = 1  upAxis = "Y" )   (metersPerUnit only when known)
//! def Xform "fure" (kind = "component")
//!     def Mesh "root_mesh"        points, faceVertexCounts (all 3), faceVertexIndices, normals
//!                                 (vertex), primvars:part (int, vertex), fure:partNames
//!     def BasisCurves "hair"      type "linear", wrap "nonperiodic", curveVertexCounts, points
//!                                 (root first), widths (vertex: the strand width repeated),
//!                                 primvars:displayColor (color3f, uniform: one per curve, linear),
//!                                 primvars:part (int, uniform), fure:partNames
//! ```
//!
//! Part labels are integers indexing `fure:partNames` (a custom `string[]` attribute), on the
//! curves per curve and on the mesh per vertex, exactly as in the PLY and OBJ files. Widths are
//! per vertex rather than per curve (`uniform`) because that is the interpolation every curve
//! consumer reads. The layer is a pure function of the data; floats use Rust's shortest
//! round-trip formatting. Not every DCC reads it: Debian's Blender 3.4 is built without USD (the
//! Blender script of [`super::blender`] is the groom for it); the structure is checked against
//! Pixar's `usd-core` reader where that is installed (docs/groom.md).

use std::fmt::Write as _;
use std::path::Path;

use glam::Vec3;

use super::blender::{check_groom, strand_part_names};
use super::{write_bytes, FormatError};
use crate::data::mesh::Mesh;
use crate::data::strands::Strands;

/// The stage metadata of the layer.
#[derive(Debug, Clone, PartialEq)]
pub struct UsdInfo {
    /// `"Y"` or `"Z"`.
    pub up_axis: char,
    /// Metres per coordinate unit, when the metric scale is known.
    pub meters_per_unit: Option<f64>,
    /// Free text for the layer's `doc`.
    pub doc: String,
}

/// Writes the `.usda` layer (see the module doc).
pub fn write_usda_groom(
    path: impl AsRef<Path>,
    strands: &Strands,
    mesh: &Mesh,
    info: &UsdInfo,
) -> Result<(), FormatError> {
    let path = path.as_ref();
    if !matches!(info.up_axis, 'Y' | 'Z') {
        return Err(FormatError::invalid(
            path,
            format!("up axis {:?}: expected Y or Z", info.up_axis),
        ));
    }
    if let Some(m) = info.meters_per_unit {
        if !(m > 0.0) || !m.is_finite() {
            return Err(FormatError::invalid(
                path,
                format!("metersPerUnit {m}: expected a positive number"),
            ));
        }
    }
    check_groom(path, strands, mesh)?;
    let text = encode(strands, mesh, info);
    write_bytes(path, text.as_bytes())
}

fn quoted(s: &str) -> String {
    serde_json::to_string(s).expect("a string serialises")
}

fn list<T>(s: &mut String, items: impl IntoIterator<Item = T>, f: impl Fn(&mut String, T)) {
    s.push('[');
    for (i, x) in items.into_iter().enumerate() {
        if i > 0 {
            s.push_str(", ");
        }
        f(s, x);
    }
    s.push(']');
}

fn vec3s(s: &mut String, v: &[Vec3]) {
    list(s, v, |s, p| {
        let _ = write!(s, "({}, {}, {})", p.x, p.y, p.z);
    });
}

fn names(s: &mut String, v: &[String]) {
    list(s, v, |s, n| s.push_str(&quoted(n)));
}

fn encode(strands: &Strands, mesh: &Mesh, info: &UsdInfo) -> String {
    let mut s = String::new();
    s.push_str("#usda 1.0\n(\n    defaultPrim = \"fure\"\n");
    let _ = writeln!(s, "    doc = {}", quoted(&info.doc));
    if let Some(m) = info.meters_per_unit {
        let _ = writeln!(s, "    metersPerUnit = {m}");
    }
    let _ = writeln!(s, "    upAxis = \"{}\"\n)\n", info.up_axis);
    s.push_str("def Xform \"fure\" (\n    kind = \"component\"\n)\n{\n");

    // The root mesh.
    s.push_str("    def Mesh \"root_mesh\"\n    {\n");
    s.push_str("        int[] faceVertexCounts = ");
    list(&mut s, &mesh.triangles, |s, _| s.push('3'));
    s.push_str("\n        int[] faceVertexIndices = ");
    list(&mut s, mesh.triangles.iter().flatten(), |s, i| {
        let _ = write!(s, "{i}");
    });
    s.push_str("\n        point3f[] points = ");
    vec3s(&mut s, &mesh.positions);
    if mesh.normals.len() == mesh.positions.len() && !mesh.normals.is_empty() {
        s.push_str("\n        normal3f[] normals = ");
        vec3s(&mut s, &mesh.normals);
        s.push_str(" (\n            interpolation = \"vertex\"\n        )");
    }
    if !mesh.part_names.is_empty() {
        s.push_str("\n        int[] primvars:part = ");
        list(&mut s, &mesh.part, |s, p| {
            let _ = write!(s, "{p}");
        });
        s.push_str(" (\n            interpolation = \"vertex\"\n        )");
        s.push_str("\n        string[] fure:partNames = ");
        names(&mut s, &mesh.part_names);
    }
    s.push_str("\n        uniform token subdivisionScheme = \"none\"\n    }\n\n");

    // The strands.
    let n = strands.len();
    s.push_str("    def BasisCurves \"hair\"\n    {\n");
    s.push_str("        uniform token type = \"linear\"\n");
    s.push_str("        uniform token wrap = \"nonperiodic\"\n");
    s.push_str("        int[] curveVertexCounts = ");
    list(&mut s, strands.starts.windows(2), |s, w| {
        let _ = write!(s, "{}", w[1] - w[0]);
    });
    s.push_str("\n        point3f[] points = ");
    vec3s(&mut s, &strands.points);
    s.push_str("\n        float[] widths = ");
    list(
        &mut s,
        (0..n).flat_map(|c| {
            let k = (strands.starts[c + 1] - strands.starts[c]) as usize;
            std::iter::repeat_n(strands.width[c], k)
        }),
        |s, w| {
            let _ = write!(s, "{w}");
        },
    );
    s.push_str(" (\n            interpolation = \"vertex\"\n        )");
    s.push_str("\n        color3f[] primvars:displayColor = ");
    list(&mut s, &strands.color, |s, c| {
        let _ = write!(s, "({}, {}, {})", c[0], c[1], c[2]);
    });
    s.push_str(" (\n            interpolation = \"uniform\"\n        )");
    s.push_str("\n        int[] primvars:part = ");
    list(&mut s, &strands.part, |s, p| {
        let _ = write!(s, "{p}");
    });
    s.push_str(" (\n            interpolation = \"uniform\"\n        )");
    s.push_str("\n        string[] fure:partNames = ");
    names(&mut s, &strand_part_names(strands));
    s.push_str("\n    }\n}\n");
    s
}

#[cfg(test)]
mod tests {
    use super::super::blender::tests::{sample_mesh, sample_strands};
    use super::*;

    fn info() -> UsdInfo {
        UsdInfo {
            up_axis: 'Y',
            meters_per_unit: Some(1.0),
            doc: "fure groom \"test\"".into(),
        }
    }

    #[test]
    fn layer_has_the_prims_counts_and_primvars() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("g.usda");
        write_usda_groom(&p, &sample_strands(), &sample_mesh(), &info()).unwrap();
        let t = std::fs::read_to_string(&p).unwrap();
        assert!(t.starts_with("#usda 1.0\n"), "{t}");
        for needle in [
            "metersPerUnit = 1\n",
            "upAxis = \"Y\"",
            "def BasisCurves \"hair\"",
            "int[] curveVertexCounts = [2, 3]",
            "float[] widths = [0.01, 0.01, 0.02, 0.02, 0.02]",
            "color3f[] primvars:displayColor = [(0.8, 0.4, 0.1), (0.1, 0.1, 0.1)]",
            "int[] primvars:part = [0, 1] (",
            "string[] fure:partNames = [\"torso\", \"head\"]",
            "int[] faceVertexCounts = [3, 3, 3, 3]",
            "int[] primvars:part = [0, 0, 1, 1] (",
            "doc = \"fure groom \\\"test\\\"\"",
        ] {
            assert!(t.contains(needle), "missing {needle:?} in\n{t}");
        }
        // Deterministic.
        let q = dir.path().join("h.usda");
        write_usda_groom(&q, &sample_strands(), &sample_mesh(), &info()).unwrap();
        assert_eq!(t, std::fs::read_to_string(&q).unwrap());
    }

    #[test]
    fn unknown_scale_and_bad_axis() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("g.usda");
        let mut i = info();
        i.meters_per_unit = None;
        write_usda_groom(&p, &sample_strands(), &sample_mesh(), &i).unwrap();
        assert!(!std::fs::read_to_string(&p)
            .unwrap()
            .contains("metersPerUnit"));
        i.up_axis = 'X';
        let e = write_usda_groom(&p, &sample_strands(), &sample_mesh(), &i).unwrap_err();
        assert!(e.to_string().contains("expected Y or Z"), "{e}");
    }
}
