//! Stage `export_groom`: the strands and the root mesh as a groom for the tools artists use.
//!
//! Two files, one per family of tools:
//!
//! - `blender.py` ([`formats::blender`]): a self-contained Blender script that builds a hair
//!   `Curves` object (one curve per strand, `radius` per point, `part` and linear `color` per
//!   curve) attached to the root mesh (vertex group per part), checked headless with Debian's
//!   Blender 3.4.1 by `tests/integration/groom.rs`. It is the Blender route because that build has
//!   neither USD nor Alembic.
//! - `groom.usda` ([`formats::usd`]): a USD layer with the strands as `BasisCurves` (widths,
//!   per-curve `displayColor` and `part`) and the root mesh as `Mesh`, for USD-reading tools.
//!
//! Units and frame. With the `lengths` input (stage `lengths`, whose `s_cm` is centimetres per
//! scene unit) both files are in metres: coordinates and widths are multiplied by `s_cm / 100`, the
//! USD layer says `metersPerUnit = 1`. Without it they stay in scene units and the USD layer has no
//! `metersPerUnit` (its reader's default, centimetres, would then be a guess). The `up` parameter
//! names the capture's up axis: the USD layer keeps the axes and records it as `upAxis`; the
//! Blender script is turned into Blender's Z-up frame (for `up = "y"`: `(x, y, z) -> (x, -z, y)`,
//! the rotation Blender's own Y-up importers apply), so the animal stands on Blender's floor.
//! The synthetic scenes are Y-up; a capture's frame is whatever its cameras were given in
//! (Blender renders and NeRF-synthetic `transforms.json` are Z-up).
//!
//! The strands come from the PLY strand file, which carries the part labels (`.hair` has none).

use std::path::Path;

use fure_stage_api::{ParamSpec, Params, PortSpec, Stage, StageContext, StageError};
use glam::Vec3;
use serde::Deserialize;

use crate::data::mesh::Mesh;
use crate::data::strands::Strands;
use crate::formats;
use crate::formats::blender::GroomInfo;
use crate::formats::usd::UsdInfo;

fure_stage_api::stage_params! {
    /// The `export_groom` stage's parameters.
    pub struct ExportGroomParams {
        /// the capture's up axis (synthetic scenes: y; Blender / NeRF-synthetic captures: z)
        up: String = string("y").choices(UP),
        /// name of the Blender collection and objects (<name>_mesh, <name>_hair)
        name: String = string("fure"),
    }
}

/// The `export_groom` stage.
pub struct ExportGroomStage;

const UP: &[&str] = &["y", "z"];

/// The part of the `lengths` output this stage reads.
#[derive(Debug, Deserialize)]
struct MetricScale {
    s_cm: f32,
}

/// Errors of the export beyond file formats.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum GroomError {
    #[error("`s_cm` is {0}: expected a positive number of centimetres per scene unit")]
    BadScale(f32),
    #[error("the strand set is empty: nothing to export")]
    NoStrands,
    #[error("the root mesh has no triangles: the hair needs a surface")]
    NoTriangles,
}

/// Maps a scene-frame point to Blender's Z-up frame.
fn to_blender(p: Vec3, up: &str) -> Vec3 {
    if up == "y" {
        Vec3::new(p.x, -p.z, p.y)
    } else {
        p
    }
}

/// `strands` and `mesh` with every point mapped by `f` and widths scaled by `scale`.
fn transformed(
    strands: &Strands,
    mesh: &Mesh,
    scale: f32,
    f: impl Fn(Vec3) -> Vec3,
) -> (Strands, Mesh) {
    let mut s = strands.clone();
    for p in &mut s.points {
        *p = f(*p * scale);
    }
    for w in &mut s.width {
        *w *= scale;
    }
    let mut m = mesh.clone();
    for p in &mut m.positions {
        *p = f(*p * scale);
    }
    for n in &mut m.normals {
        *n = f(*n);
    }
    (s, m)
}

impl Stage for ExportGroomStage {
    fn kind(&self) -> &'static str {
        "export_groom"
    }
    fn version(&self) -> u32 {
        1
    }
    fn doc(&self) -> &'static str {
        "The strands (PLY, with part labels) and the root mesh as a groom: `blender.py`, a Blender \
         script that builds hair curves (radius, part, colour) attached to the mesh (vertex group \
         per part), and `groom.usda`, USD BasisCurves + Mesh with widths and per-curve part and \
         colour; in metres when the `lengths` output gives s_cm (docs/groom.md)."
    }
    fn params(&self) -> Vec<ParamSpec> {
        ExportGroomParams::specs()
    }
    fn inputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![
            PortSpec::file(
                "strands",
                "ply",
                "strands as PLY polylines with part labels (e.g. codec.strands_ply)",
            ),
            PortSpec::file(
                "mesh",
                "obj",
                "the root mesh M_root with part groups (e.g. defur.root_mesh)",
            ),
            PortSpec::file(
                "lengths",
                "json",
                "the `lengths` stage output: its s_cm puts the groom in metres",
            )
            .optional(),
        ]
    }
    fn outputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![
            PortSpec::file(
                "blender",
                "py",
                "Blender script: hair curves on the root mesh (run with `blender --python`)",
            ),
            PortSpec::file(
                "groom",
                "usda",
                "USD layer: BasisCurves (widths, displayColor, part) and the root Mesh",
            ),
        ]
    }
    fn validate(&self, params: &Params) -> Result<(), StageError> {
        let name = ExportGroomParams::from_params(params)?.name;
        if name.is_empty() || name.len() > 48 || name.contains(['\n', '\r']) {
            return Err(StageError::param(
                "name",
                format!("{name:?}: expected 1 to 48 characters on one line"),
            ));
        }
        Ok(())
    }
    fn run(&self, ctx: &StageContext<'_>) -> Result<(), StageError> {
        let ExportGroomParams { up, name } = ExportGroomParams::from_params(ctx.params)?;
        let strands_path = ctx.input("strands")?;
        let strands =
            formats::ply::read_ply_strands(strands_path).map_err(|e| e.for_input("strands"))?;
        if strands.is_empty() {
            return Err(StageError::input(
                "strands",
                strands_path,
                GroomError::NoStrands,
            ));
        }
        let mesh_path = ctx.input("mesh")?;
        let mesh = formats::obj::read_obj(mesh_path).map_err(|e| e.for_input("mesh"))?;
        if mesh.triangles.is_empty() {
            return Err(StageError::input(
                "mesh",
                mesh_path,
                GroomError::NoTriangles,
            ));
        }
        let s_cm = match ctx.input_opt("lengths") {
            Some(path) => {
                let m: MetricScale =
                    formats::json::read_json(path).map_err(|e| e.for_input("lengths"))?;
                if !(m.s_cm > 0.0) || !m.s_cm.is_finite() {
                    return Err(StageError::input(
                        "lengths",
                        path,
                        GroomError::BadScale(m.s_cm),
                    ));
                }
                Some(m.s_cm)
            }
            None => None,
        };
        let (scale, units, unit_note) = match s_cm {
            Some(s) => (
                s / 100.0,
                "metres",
                format!("metres (s_cm = {s} cm per scene unit)"),
            ),
            None => (
                1.0,
                "scene units",
                "scene units (no metric scale given)".to_string(),
            ),
        };
        ctx.progress.note(&format!(
            "{} strands, {} points; mesh {} vertices; {unit_note}; up = {up}",
            strands.len(),
            strands.points.len(),
            mesh.positions.len()
        ));

        let (bs, bm) = transformed(&strands, &mesh, scale, |v| to_blender(v, &up));
        let info = GroomInfo {
            name,
            units: units.to_string(),
            note: format!(
                "{unit_note}; the capture's {} axis turned to Blender's Z up",
                up.to_uppercase()
            ),
        };
        write_blender_file(ctx.output("blender")?, &bs, &bm, &info)?;

        let (us, um) = transformed(&strands, &mesh, scale, |v| v);
        let usd = UsdInfo {
            up_axis: if up == "y" { 'Y' } else { 'Z' },
            meters_per_unit: s_cm.map(|_| 1.0),
            doc: format!("fure groom: strands as BasisCurves on the root mesh; {unit_note}"),
        };
        formats::usd::write_usda_groom(ctx.output("groom")?, &us, &um, &usd)?;
        Ok(())
    }
}

fn write_blender_file(
    path: &Path,
    strands: &Strands,
    mesh: &Mesh,
    info: &GroomInfo,
) -> Result<(), StageError> {
    formats::blender::write_blender_groom(path, strands, mesh, info).map_err(StageError::from)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::blender::tests::{sample_mesh, sample_strands};
    use fure_stage_api::{NoProgress, Value};
    use std::collections::BTreeMap;

    fn run(dir: &Path, lengths: Option<&str>, up: &str) -> Result<(), StageError> {
        let input = dir.join("in");
        formats::ply::write_ply_strands(input.join("s.ply"), &sample_strands()).unwrap();
        formats::obj::write_obj(input.join("m.obj"), &sample_mesh()).unwrap();
        let mut inputs = BTreeMap::from([
            ("strands".to_string(), input.join("s.ply")),
            ("mesh".to_string(), input.join("m.obj")),
        ]);
        if let Some(text) = lengths {
            std::fs::write(input.join("l.json"), text).unwrap();
            inputs.insert("lengths".into(), input.join("l.json"));
        }
        let params = Params(BTreeMap::from([
            ("up".to_string(), Value::Str(up.into())),
            ("name".to_string(), Value::Str("fure".into())),
        ]));
        let ctx = StageContext {
            name: "groom",
            params: &params,
            inputs,
            outputs: BTreeMap::from([
                ("blender".to_string(), dir.join("out/blender.py")),
                ("groom".to_string(), dir.join("out/groom.usda")),
            ]),
            progress: &NoProgress,
        };
        ExportGroomStage.run(&ctx)
    }

    #[test]
    fn metres_from_s_cm_and_the_blender_frame() {
        let dir = tempfile::tempdir().unwrap();
        run(dir.path(), Some(r#"{"s_cm": 50.0, "variant": "v2"}"#), "y").unwrap();
        let usd = std::fs::read_to_string(dir.path().join("out/groom.usda")).unwrap();
        assert!(usd.contains("metersPerUnit = 1\n"), "{usd}");
        assert!(usd.contains("upAxis = \"Y\""), "{usd}");
        // Root of strand 0 at (0.2, 0.2, 0.2) scene units, half a metre per unit; width 0.01 -> 0.005.
        assert!(usd.contains("point3f[] points = [(0.1, 0.1, 0.1), (0.25, 0.25, 0.25)"));
        assert!(
            usd.contains("float[] widths = [0.005, 0.005, 0.01"),
            "{usd}"
        );
        let py = std::fs::read_to_string(dir.path().join("out/blender.py")).unwrap();
        assert!(py.contains(r#"\"units\":\"metres\""#), "{py}");
        assert_eq!(
            to_blender(Vec3::new(1.0, 2.0, 3.0), "y"),
            Vec3::new(1.0, -3.0, 2.0)
        );
        assert_eq!(
            to_blender(Vec3::new(1.0, 2.0, 3.0), "z"),
            Vec3::new(1.0, 2.0, 3.0)
        );
    }

    #[test]
    fn scene_units_without_lengths_and_bad_scales_refused() {
        let dir = tempfile::tempdir().unwrap();
        run(dir.path(), None, "z").unwrap();
        let usd = std::fs::read_to_string(dir.path().join("out/groom.usda")).unwrap();
        assert!(!usd.contains("metersPerUnit"), "{usd}");
        assert!(usd.contains("upAxis = \"Z\""), "{usd}");
        let e = run(dir.path(), Some(r#"{"s_cm": -1}"#), "z").unwrap_err();
        assert!(e.to_string().contains("expected a positive number"), "{e}");
        assert!(e.to_string().contains("l.json"), "{e}");
        let e = run(dir.path(), Some(r#"{"scale": 1}"#), "z").unwrap_err();
        assert!(e.to_string().contains("s_cm"), "{e}");
    }
}
