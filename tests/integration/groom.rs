//! The groom out (`export_groom`, issue 19): `tiger.toml` at its smallest writes `blender.py` and
//! `groom.usda` from the learned strands and M_root; Debian's Blender (3.4.1) runs the script
//! headless and the hair curves it builds are counted and compared with the strand PLY: curves,
//! points, per-curve part and colour, radius, positions in metres and Blender's Z-up frame, the
//! mesh's vertex groups, the surface attachment and the conversion to a particle system (the
//! Alembic route). Without a `blender` on the PATH (or with FURE_SKIP_BLENDER set) that part is
//! skipped with a note; the USD layer is checked with Pixar's reader when the Python named by
//! FURE_USD_PYTHON (default `python3`) can import `pxr`, and by its text otherwise.

use std::path::Path;
use std::process::Command;

use serde_json::Value as Json;

use crate::engine::Project;
use crate::method::tiny_pipeline;

/// Reads the root mesh, the strands and s_cm of a tiny tiger run.
fn inputs(
    out: &Path,
) -> (
    fure_stages::data::mesh::Mesh,
    fure_stages::data::strands::Strands,
    f32,
) {
    let mesh = fure_stages::formats::obj::read_obj(out.join("defur/root_mesh.obj")).unwrap();
    let strands =
        fure_stages::formats::ply::read_ply_strands(out.join("codec/strands_ply.ply")).unwrap();
    let lengths: Json =
        serde_json::from_slice(&std::fs::read(out.join("lengths/lengths.json")).unwrap()).unwrap();
    let s_cm = lengths["s_cm"].as_f64().unwrap() as f32;
    (mesh, strands, s_cm)
}

/// `curveVertexCounts` of the USD layer, read from its text.
fn usda_counts(text: &str) -> Vec<u32> {
    let line = text
        .lines()
        .find_map(|l| l.trim().strip_prefix("int[] curveVertexCounts = ["))
        .expect("no curveVertexCounts");
    line.trim_end_matches(']')
        .split(", ")
        .map(|x| x.parse().unwrap())
        .collect()
}

const USD_CHECK: &str = r#"
import json, sys
from pxr import Usd, UsdGeom
st = Usd.Stage.Open(sys.argv[1])
c = UsdGeom.BasisCurves(st.GetPrimAtPath("/fure/hair"))
m = UsdGeom.Mesh(st.GetPrimAtPath("/fure/root_mesh"))
pv = UsdGeom.PrimvarsAPI(c.GetPrim())
print("FURE_USD " + json.dumps({
    "up": UsdGeom.GetStageUpAxis(st),
    "meters_per_unit": UsdGeom.GetStageMetersPerUnit(st),
    "counts": list(c.GetCurveVertexCountsAttr().Get()),
    "points": len(c.GetPointsAttr().Get()),
    "widths": len(c.GetWidthsAttr().Get()),
    "part": pv.GetPrimvar("part").GetInterpolation(),
    "color": len(pv.GetPrimvar("displayColor").Get()),
    "mesh_points": len(m.GetPointsAttr().Get()),
}))
"#;

/// Runs a `blender` command: its output, or `None` with a note naming `what` is skipped when
/// FURE_SKIP_BLENDER is set or no `blender` is on the PATH.
pub(crate) fn blender(mut cmd: Command, what: &str) -> Option<std::process::Output> {
    if std::env::var_os("FURE_SKIP_BLENDER").is_some() {
        eprintln!("FURE_SKIP_BLENDER set: skipping {what}");
        return None;
    }
    match cmd.output() {
        Ok(o) => Some(o),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            eprintln!("blender not found on the PATH: skipping {what}");
            None
        }
        Err(e) => panic!("blender: {e}"),
    }
}

/// What the Blender check prints after `blender.py` ran (one JSON line).
const BLENDER_CHECK: &str = r#"
import bpy, json
hair, mesh = bpy.data.objects["fure_hair"], bpy.data.objects["fure_mesh"]
c = hair.data
n = len(c.curves)
part = [0] * n
c.attributes["part"].data.foreach_get("value", part)
color = [0.0] * (4 * n)
c.attributes["color"].data.foreach_get("color", color)
radius = [0.0] * len(c.points)
c.attributes["radius"].data.foreach_get("value", radius)
pos = [0.0] * (3 * len(c.points))
c.attributes["position"].data.foreach_get("vector", pos)
def mean_z(group):
    g = mesh.vertex_groups[group].index
    zs = [v.co.z for v in mesh.data.vertices if any(e.group == g for e in v.groups)]
    return sum(zs) / len(zs)
print("FURE_CHECK " + json.dumps({
    "type": hair.type,
    "curves": n,
    "points": len(c.points),
    "attributes": {a.name: [a.domain, a.data_type] for a in c.attributes},
    "part": part,
    "color": color,
    "radius": radius,
    "positions": pos,
    "part_names": json.loads(hair["fure_part_names"]),
    "surface": c.surface.name if c.surface else None,
    "parent": hair.parent.name if hair.parent else None,
    "vertex_groups": [g.name for g in mesh.vertex_groups],
    "vertices": len(mesh.data.vertices),
    "faces": len(mesh.data.polygons),
    "particles": [len(p.particles) for p in mesh.particle_systems],
    "materials": [m.name for m in c.materials],
    "paws_z": mean_z("paws"),
    "head_z": mean_z("head"),
}))
"#;

fn f(v: &Json) -> f32 {
    v.as_f64().unwrap() as f32
}

#[test]
fn tiger_groom_opens_in_blender_as_hair_curves_on_the_root_mesh() {
    let p = Project::new();
    p.write("tiny.toml", &tiny_pipeline());
    let r = p.run("tiny.toml", &["--until", "groom"]);
    r.ok();
    assert_eq!(r.status("groom"), "ran", "{:?}", r.stages);
    let out = p.path("out/tiny");
    let (mesh, strands, s_cm) = inputs(&out);
    let n = strands.len();
    assert!(n > 100, "{n} strands");
    let sizes: Vec<u32> = strands.starts.windows(2).map(|w| w[1] - w[0]).collect();

    // The USD layer: one curve per strand, in metres, Y up like the synthetic scene.
    let usda_path = out.join("groom/groom.usda");
    let usda = std::fs::read_to_string(&usda_path).unwrap();
    assert_eq!(usda_counts(&usda), sizes);
    assert!(usda.contains("metersPerUnit = 1\n") && usda.contains("upAxis = \"Y\""));
    let python = std::env::var("FURE_USD_PYTHON").unwrap_or_else(|_| "python3".into());
    match Command::new(&python)
        .args(["-c", USD_CHECK])
        .arg(&usda_path)
        .output()
    {
        Ok(o) if o.status.success() => {
            let text = String::from_utf8_lossy(&o.stdout);
            let line = text
                .lines()
                .find_map(|l| l.strip_prefix("FURE_USD "))
                .unwrap_or_else(|| panic!("no USD result:\n{text}"));
            let u: Json = serde_json::from_str(line).unwrap();
            assert_eq!(u["up"], "Y");
            assert_eq!(u["meters_per_unit"], 1.0);
            assert_eq!(u["counts"], serde_json::json!(sizes));
            assert_eq!(u["points"], strands.points.len());
            assert_eq!(u["widths"], strands.points.len());
            assert_eq!(u["part"], "uniform");
            assert_eq!(u["color"], n);
            assert_eq!(u["mesh_points"], mesh.positions.len());
        }
        _ => {
            eprintln!("`{python}` cannot import pxr (usd-core): USD layer checked by its text only")
        }
    }

    // Blender.
    let script = out.join("groom/blender.py");
    let started = std::time::Instant::now();
    let mut cmd = Command::new("blender");
    cmd.args(["-b", "--factory-startup", "--python"])
        .arg(&script)
        .args([
            "--python-expr",
            BLENDER_CHECK,
            "--",
            "--particles",
            "--save",
        ])
        .arg(p.path("groom.blend"));
    let Some(run) = blender(cmd, "the Blender import of the groom") else {
        return;
    };
    let stdout = String::from_utf8_lossy(&run.stdout);
    let line = stdout
        .lines()
        .find_map(|l| l.strip_prefix("FURE_CHECK "))
        .unwrap_or_else(|| {
            panic!(
                "no result from Blender ({}):\n{stdout}\n{}",
                run.status,
                String::from_utf8_lossy(&run.stderr)
            )
        });
    eprintln!(
        "Blender built and checked {n} hair curves in {:.1} s",
        started.elapsed().as_secs_f32()
    );
    let b: Json = serde_json::from_str(line).unwrap();
    assert_eq!(b["type"], "CURVES");
    assert_eq!(b["curves"], n);
    assert_eq!(b["points"], strands.points.len());
    for (name, domain, ty) in [
        ("part", "CURVE", "INT"),
        ("color", "CURVE", "FLOAT_COLOR"),
        ("radius", "POINT", "FLOAT"),
        ("surface_uv_coordinate", "CURVE", "FLOAT2"),
    ] {
        assert_eq!(
            b["attributes"][name],
            serde_json::json!([domain, ty]),
            "{name}: {}",
            b["attributes"]
        );
    }
    assert_eq!(b["part_names"], serde_json::json!(strands.part_names));
    let part: Vec<u16> = b["part"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_u64().unwrap() as u16)
        .collect();
    assert_eq!(part, strands.part, "per-curve parts differ");
    let color = b["color"].as_array().unwrap();
    let radius = b["radius"].as_array().unwrap();
    let pos = b["positions"].as_array().unwrap();
    let m = s_cm / 100.0;
    let mut worst_move = 0.0f32;
    for s in 0..n {
        for k in 0..3 {
            assert!((f(&color[4 * s + k]) - strands.color[s][k]).abs() < 1e-6);
        }
        for i in strands.starts[s] as usize..strands.starts[s + 1] as usize {
            assert!(
                (f(&radius[i]) - 0.5 * strands.width[s] * m).abs() <= 1e-6 * m,
                "radius of point {i}"
            );
            // Metres, Y up turned to Blender's Z up: (x, y, z) -> (x, -z, y).
            let q = strands.points[i] * m;
            let want = [q.x, -q.z, q.y];
            let d2: f32 = (0..3).map(|k| (f(&pos[3 * i + k]) - want[k]).powi(2)).sum();
            worst_move = worst_move.max(d2.sqrt());
        }
    }
    // Attaching moves a strand by its root's distance to the surface: roots lie on M_root.
    assert!(worst_move < 1e-3, "a point moved by {worst_move} m");
    assert_eq!(b["surface"], "fure_mesh");
    assert_eq!(b["parent"], "fure_mesh");
    assert_eq!(b["vertex_groups"], serde_json::json!(mesh.part_names));
    assert_eq!(b["vertices"], mesh.positions.len());
    assert_eq!(b["faces"], mesh.triangles.len());
    assert_eq!(b["particles"], serde_json::json!([n]));
    assert_eq!(b["materials"], serde_json::json!(["fure_hair_fur"]));
    // The animal stands on Blender's floor: paws below the head.
    assert!(
        f(&b["paws_z"]) < f(&b["head_z"]),
        "{} {}",
        b["paws_z"],
        b["head_z"]
    );
    assert!(p.path("groom.blend").is_file(), "--save wrote no .blend");
}
