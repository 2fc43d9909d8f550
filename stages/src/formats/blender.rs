//! A groom as a Blender Python script: running it builds hair curves on the root mesh.
//!
//! Why a script: Debian's Blender 3.4.1 is built without USD and without Alembic, has no reader for
//! `.hair`, and imports the strand PLY as loose edges without its attributes. Its Python API, on the
//! other hand, builds everything a groom needs. So the groom for Blender is one self-contained
//! `.py` file (no sidecar: a stage writes only its output ports) holding the data and the code:
//!
//! - The data are little-endian arrays, base64 encoded, in implicitly concatenated string literals
//!   of at most [`LINE`] characters: mesh positions (`f32 x 3`), triangles (`u32 x 3`), the mesh's
//!   per-vertex part (`u16`), points per strand (`u32`), strand points (`f32 x 3`, root first),
//!   per-strand part (`u16`), width (`f32`) and linear RGB colour (`f32 x 3`). A JSON header
//!   (`GROOM`) names the parts and gives the counts and the units. The script decodes them with
//!   the standard `array` and `base64` modules (Debian's Blender runs the system Python, which has
//!   no numpy).
//! - Blender 3.4 has no Python call that sizes a hair `Curves` datablock, so the script makes a
//!   legacy curve with one poly spline per strand, converts it with
//!   `bpy.ops.object.convert(target='CURVES')`, checks the curve offsets against the strand sizes
//!   (the conversion keeps the spline order; the script fails loudly if it did not), then sets the
//!   `position` and `radius` (half the strand width) point attributes and the per-curve `part`
//!   (`INT`) and `color` (`FLOAT_COLOR`, linear RGBA) attributes with `foreach_set`.
//! - The root mesh becomes a mesh object (`from_pydata`) with one vertex group per part (the OBJ
//!   groups of fure's meshes) and a `part` point attribute. It gets a UV map (Smart UV Project)
//!   when it has none, the curves get it as their surface (`Curves.surface`, `surface_uv_map`),
//!   are parented to it and are attached with `bpy.ops.curves.snap_curves_to_surface(
//!   attach_mode='NEAREST')`, which writes `surface_uv_coordinate` (needed by sculpt mode's brushes
//!   and the Deform Curves on Surface node) and moves each strand by the distance of its root to
//!   the surface, a float rounding's worth here as the roots were sampled on that mesh.
//! - A material reads the `color` attribute into a Principled BSDF's base colour.
//!
//! Command-line options after `--`: `--save FILE.blend`, `--particles` (also convert the curves
//! to a hair particle system on the mesh, Blender's route to an Alembic groom) and `--no-attach`.
//!
//! Coordinates are written as given: the caller (stage `export_groom`) has already turned them
//! into Blender's frame (Z up) and units. Output is a pure function of the data.

use std::fmt::Write as _;
use std::path::Path;

use glam::Vec3;

use super::{check_finite, write_bytes, FormatError};
use crate::data::mesh::Mesh;
use crate::data::strands::Strands;

/// Longest line of base64 data in the script.
pub const LINE: usize = 1000;

/// What the script says about the data besides the arrays.
#[derive(Debug, Clone, PartialEq)]
pub struct GroomInfo {
    /// Name of the Blender objects (`<name>_mesh`, `<name>_hair`) and of their collection.
    pub name: String,
    /// Length unit of the coordinates, in words ("metres", "scene units").
    pub units: String,
    /// One line on where the data come from and how they were transformed.
    pub note: String,
}

/// Writes the Blender script (see the module doc).
pub fn write_blender_groom(
    path: impl AsRef<Path>,
    strands: &Strands,
    mesh: &Mesh,
    info: &GroomInfo,
) -> Result<(), FormatError> {
    let path = path.as_ref();
    let text = encode(path, strands, mesh, info)?;
    write_bytes(path, text.as_bytes())
}

/// Checks what both groom writers need: a consistent strand set with part labels inside its part
/// names, a mesh with valid triangles and labels, finite numbers.
pub(crate) fn check_groom(path: &Path, strands: &Strands, mesh: &Mesh) -> Result<(), FormatError> {
    let n = strands.len();
    if strands.starts.first().copied().unwrap_or(0) != 0
        || strands.starts.windows(2).any(|w| w[0] > w[1])
        || strands.starts.last().copied().unwrap_or(0) as usize != strands.points.len()
        || strands.width.len() != n
        || strands.color.len() != n
        || strands.part.len() != n
    {
        return Err(FormatError::invalid(
            path,
            "inconsistent strand set (starts / part / width / colour arrays do not match the points)",
        ));
    }
    if let Some(s) = (0..n).find(|&s| strands.starts[s] == strands.starts[s + 1]) {
        return Err(FormatError::invalid(
            path,
            format!("strand {s} has no points"),
        ));
    }
    let names = strands.part_names.len().max(1);
    if let Some(s) = strands.part.iter().position(|&p| p as usize >= names) {
        return Err(FormatError::invalid(
            path,
            format!(
                "strand {s} has part {} but there are {} part names",
                strands.part[s],
                strands.part_names.len()
            ),
        ));
    }
    let nv = mesh.positions.len();
    if let Some((t, tri)) = mesh
        .triangles
        .iter()
        .enumerate()
        .find(|(_, t)| t.iter().any(|&i| i as usize >= nv))
    {
        return Err(FormatError::invalid(
            path,
            format!("mesh triangle {t} {tri:?} uses a vertex index >= {nv}"),
        ));
    }
    if !mesh.part_names.is_empty() {
        if let Some(problem) = mesh.part_label_problem() {
            return Err(FormatError::invalid(path, format!("mesh {problem}")));
        }
    }
    check_finite(
        path,
        "strand point coordinate",
        strands.points.iter().flat_map(|p| p.to_array()),
    )?;
    check_finite(path, "strand width", strands.width.iter().copied())?;
    check_finite(
        path,
        "strand colour",
        strands.color.iter().flatten().copied(),
    )?;
    check_finite(
        path,
        "mesh vertex coordinate",
        mesh.positions.iter().flat_map(|p| p.to_array()),
    )?;
    Ok(())
}

/// The part names of a strand set ("part0" for unlabelled strands).
pub(crate) fn strand_part_names(strands: &Strands) -> Vec<String> {
    if strands.part_names.is_empty() {
        vec!["part0".to_string()]
    } else {
        strands.part_names.clone()
    }
}

fn encode(
    path: &Path,
    strands: &Strands,
    mesh: &Mesh,
    info: &GroomInfo,
) -> Result<String, FormatError> {
    check_groom(path, strands, mesh)?;
    let n = strands.len();
    let sizes: Vec<u32> = strands.starts.windows(2).map(|w| w[1] - w[0]).collect();
    let mesh_part: Vec<u16> = if mesh.part_names.is_empty() {
        vec![0; mesh.positions.len()]
    } else {
        mesh.part.clone()
    };
    let header = serde_json::json!({
        "format": "fure groom for Blender 1",
        "name": info.name,
        "units": info.units,
        "note": info.note,
        "strands": n,
        "points": strands.points.len(),
        "vertices": mesh.positions.len(),
        "triangles": mesh.triangles.len(),
        "part_names": strand_part_names(strands),
        "mesh_part_names": mesh.part_names,
    });
    // A JSON string literal is a valid Python string literal.
    let header = serde_json::to_string(&header.to_string()).expect("a string serialises");

    let mut s = String::new();
    s.push_str(PREAMBLE);
    let _ = writeln!(s, "GROOM = json.loads({header})\n");
    let arrays: [(&str, Vec<u8>); 8] = [
        ("MESH_POSITIONS", vec3_bytes(&mesh.positions)),
        (
            "MESH_TRIANGLES",
            mesh.triangles
                .iter()
                .flatten()
                .flat_map(|i| i.to_le_bytes())
                .collect(),
        ),
        (
            "MESH_PART",
            mesh_part.iter().flat_map(|i| i.to_le_bytes()).collect(),
        ),
        (
            "STRAND_SIZES",
            sizes.iter().flat_map(|i| i.to_le_bytes()).collect(),
        ),
        ("STRAND_POINTS", vec3_bytes(&strands.points)),
        (
            "STRAND_PART",
            strands.part.iter().flat_map(|i| i.to_le_bytes()).collect(),
        ),
        (
            "STRAND_WIDTH",
            strands.width.iter().flat_map(|i| i.to_le_bytes()).collect(),
        ),
        (
            "STRAND_COLOR",
            strands
                .color
                .iter()
                .flatten()
                .flat_map(|i| i.to_le_bytes())
                .collect(),
        ),
    ];
    for (name, bytes) in arrays {
        let b64 = base64(&bytes);
        let _ = writeln!(s, "{name} = (");
        if b64.is_empty() {
            s.push_str("    \"\"\n");
        }
        for chunk in b64.as_bytes().chunks(LINE) {
            let _ = writeln!(
                s,
                "    \"{}\"",
                std::str::from_utf8(chunk).expect("base64 is ASCII")
            );
        }
        s.push_str(")\n\n");
    }
    s.push_str(CODE);
    Ok(s)
}

fn vec3_bytes(v: &[Vec3]) -> Vec<u8> {
    v.iter()
        .flat_map(|p| p.to_array())
        .flat_map(|x| x.to_le_bytes())
        .collect()
}

/// Standard base64 (RFC 4648, with padding).
fn base64(bytes: &[u8]) -> String {
    const T: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for c in bytes.chunks(3) {
        let b = [c[0], *c.get(1).unwrap_or(&0), *c.get(2).unwrap_or(&0)];
        let v = (b[0] as u32) << 16 | (b[1] as u32) << 8 | b[2] as u32;
        for k in 0..4 {
            if k <= c.len() {
                out.push(T[(v >> (18 - 6 * k) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

const PREAMBLE: &str = r#"# fure groom for Blender: hair curves (one per strand) on the root mesh.
# Written by fure's `export_groom` stage; checked with Blender 3.4.1 (docs/groom.md).
#
#   blender --python groom.py                          opens Blender with the groom
#   blender -b --python groom.py -- --save groom.blend  writes a .blend without a window
#   in Blender: Scripting workspace > Text > Open > groom.py > Run Script
#
# Options after `--`: --save FILE.blend; --particles (also convert the curves to a hair particle
# system on the mesh, for Alembic export); --no-attach (skip the UV map and surface attachment).
# Adds a collection with `<name>_mesh` (vertex group and `part` attribute per part) and
# `<name>_hair` (hair curves: `radius` per point; `part`, `color` per curve) to the current scene.

import array
import base64
import json
import os
import sys

import bpy

"#;

const CODE: &str = r#"def _array(typecode, chunks):
    a = array.array(typecode)
    a.frombytes(base64.b64decode(chunks))
    if sys.byteorder == "big":
        a.byteswap()
    return a


def _check_itemsizes():
    for code, size in (("f", 4), ("I", 4), ("H", 2), ("i", 4)):
        if array.array(code).itemsize != size:
            raise RuntimeError(f"array typecode {code!r} is not {size} bytes on this machine")


def _activate(obj):
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj


def _build_mesh(name, collection):
    pos = _array("f", MESH_POSITIONS)
    tri = _array("I", MESH_TRIANGLES)
    part = _array("H", MESH_PART)
    verts = list(zip(pos[0::3], pos[1::3], pos[2::3]))
    faces = list(zip(tri[0::3], tri[1::3], tri[2::3]))
    me = bpy.data.meshes.new(name)
    me.from_pydata(verts, [], faces)
    me.update()
    obj = bpy.data.objects.new(name, me)
    collection.objects.link(obj)
    if GROOM["mesh_part_names"]:
        attr = me.attributes.new("part", "INT", "POINT")
        attr.data.foreach_set("value", array.array("i", part))
        for k, part_name in enumerate(GROOM["mesh_part_names"]):
            group = obj.vertex_groups.new(name=part_name)
            group.add([i for i, p in enumerate(part) if p == k], 1.0, "REPLACE")
    return obj


def _material(name):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nodes = mat.node_tree.nodes
    bsdf = next((n for n in nodes if n.type == "BSDF_PRINCIPLED"), None)
    if bsdf is not None:
        attr = nodes.new("ShaderNodeAttribute")
        attr.attribute_name = "color"
        mat.node_tree.links.new(attr.outputs["Color"], bsdf.inputs["Base Color"])
    return mat


def _build_hair(name, collection):
    sizes = _array("I", STRAND_SIZES)
    points = _array("f", STRAND_POINTS)
    n, p = GROOM["strands"], GROOM["points"]
    if len(sizes) != n or len(points) != 3 * p:
        raise RuntimeError("groom data do not match their header")
    # Blender 3.4 cannot size a Curves datablock from Python: build poly splines, convert.
    cu = bpy.data.curves.new(name, "CURVE")
    cu.dimensions = "3D"
    for size in sizes:
        spline = cu.splines.new("POLY")
        spline.points.add(size - 1)
    obj = bpy.data.objects.new(name, cu)
    collection.objects.link(obj)
    _activate(obj)
    bpy.ops.object.convert(target="CURVES")
    obj = bpy.context.view_layer.objects.active
    curves = obj.data
    if obj.type != "CURVES" or len(curves.curves) != n or len(curves.points) != p:
        raise RuntimeError(
            f"conversion to hair curves gave {obj.type} with {len(curves.curves)} curves and "
            f"{len(curves.points)} points, expected {n} and {p}"
        )
    offsets = array.array("i", [0]) * (n + 1)
    curves.curve_offset_data.foreach_get("value", offsets)
    start = 0
    for s, size in enumerate(sizes):
        if offsets[s] != start:
            raise RuntimeError(f"curve {s} starts at point {offsets[s]}, expected {start}")
        start += size
    obj.name = name
    curves.name = name
    attrs = curves.attributes
    attrs["position"].data.foreach_set("vector", points)
    width = _array("f", STRAND_WIDTH)
    radius = array.array("f", (0.5 * w for w, size in zip(width, sizes) for _ in range(size)))
    (attrs.get("radius") or attrs.new("radius", "FLOAT", "POINT")).data.foreach_set(
        "value", radius
    )
    part = attrs.new("part", "INT", "CURVE")
    part.data.foreach_set("value", array.array("i", _array("H", STRAND_PART)))
    rgb = _array("f", STRAND_COLOR)
    rgba = array.array("f", (v for i in range(n) for v in (rgb[3 * i], rgb[3 * i + 1], rgb[3 * i + 2], 1.0)))
    attrs.new("color", "FLOAT_COLOR", "CURVE").data.foreach_set("color", rgba)
    obj["fure_part_names"] = json.dumps(GROOM["part_names"])
    curves.materials.append(_material(name + "_fur"))
    return obj


def _attach(hair, mesh_obj):
    curves = hair.data
    curves.surface = mesh_obj
    hair.parent = mesh_obj
    me = mesh_obj.data
    if not me.polygons:
        print("fure groom: the mesh has no faces, curves not attached")
        return
    if not me.uv_layers:
        _activate(mesh_obj)
        bpy.ops.object.mode_set(mode="EDIT")
        bpy.ops.mesh.select_all(action="SELECT")
        bpy.ops.uv.smart_project()
        bpy.ops.object.mode_set(mode="OBJECT")
    curves.surface_uv_map = me.uv_layers.active.name
    _activate(hair)
    bpy.ops.curves.snap_curves_to_surface(attach_mode="NEAREST")


def build(attach=True, particles=False):
    """Adds the groom to the current scene; returns (mesh object, hair object)."""
    _check_itemsizes()
    if bpy.context.object is not None and bpy.context.object.mode != "OBJECT":
        bpy.ops.object.mode_set(mode="OBJECT")
    name = GROOM["name"]
    collection = bpy.data.collections.new(name)
    bpy.context.scene.collection.children.link(collection)
    mesh_obj = _build_mesh(name + "_mesh", collection)
    hair = _build_hair(name + "_hair", collection)
    if attach or particles:
        _attach(hair, mesh_obj)
    if particles:
        _activate(hair)
        bpy.ops.curves.convert_to_particle_system()
    _activate(hair)
    print(
        f"fure groom: {len(hair.data.curves)} hair curves, {len(hair.data.points)} points "
        f"on {mesh_obj.name} ({GROOM['units']})"
    )
    return mesh_obj, hair


def _main(argv):
    args = argv[argv.index("--") + 1:] if "--" in argv else []
    save = None
    if "--save" in args:
        i = args.index("--save")
        if i + 1 >= len(args):
            raise SystemExit("fure groom: --save needs a FILE.blend")
        save = os.path.abspath(args[i + 1])
    build(attach="--no-attach" not in args, particles="--particles" in args)
    if save:
        bpy.ops.wm.save_as_mainfile(filepath=save)


if __name__ == "__main__":
    _main(sys.argv)
"#;

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    pub(crate) fn sample_mesh() -> Mesh {
        let mut m = Mesh {
            positions: vec![
                Vec3::new(0.0, 0.0, 0.0),
                Vec3::new(1.0, 0.0, 0.0),
                Vec3::new(0.0, 1.0, 0.0),
                Vec3::new(0.0, 0.0, 1.0),
            ],
            triangles: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
            part: vec![0, 0, 1, 1],
            part_names: vec!["torso".into(), "head".into()],
            ..Default::default()
        };
        m.recompute_normals();
        m
    }

    pub(crate) fn sample_strands() -> Strands {
        let mut s = Strands::new();
        s.part_names = vec!["torso".into(), "head".into()];
        s.push(
            &[Vec3::new(0.2, 0.2, 0.2), Vec3::new(0.5, 0.5, 0.5)],
            0,
            0.01,
            [0.8, 0.4, 0.1],
        );
        s.push(
            &[
                Vec3::new(0.1, 0.1, 0.0),
                Vec3::new(0.1, 0.1, -0.2),
                Vec3::new(0.15, 0.1, -0.4),
            ],
            1,
            0.02,
            [0.1, 0.1, 0.1],
        );
        s
    }

    fn info() -> GroomInfo {
        GroomInfo {
            name: "fure".into(),
            units: "metres".into(),
            note: "test \"quoted\" note\nwith a line break".into(),
        }
    }

    #[test]
    fn base64_matches_rfc4648_vectors() {
        for (plain, enc) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(plain.as_bytes()), enc, "{plain:?}");
        }
    }

    #[test]
    fn script_holds_the_data_and_is_deterministic() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a.py"), dir.path().join("b.py"));
        write_blender_groom(&a, &sample_strands(), &sample_mesh(), &info()).unwrap();
        write_blender_groom(&b, &sample_strands(), &sample_mesh(), &info()).unwrap();
        let text = std::fs::read_to_string(&a).unwrap();
        assert_eq!(text, std::fs::read_to_string(&b).unwrap());
        assert!(text.contains("STRAND_POINTS = ("), "{text}");
        assert!(text.contains(r#"\"strands\":2"#), "{text}");
        // The sizes array: [2, 3] as u32 little endian.
        assert!(text.contains(&base64(&[2, 0, 0, 0, 3, 0, 0, 0])));
        assert!(
            text.lines().all(|l| l.len() <= LINE + 8),
            "a line is too long"
        );
        // The system Python parses it (Blender runs the same language); skipped without python3.
        if let Ok(out) = std::process::Command::new("python3")
            .args(["-c", "import ast, sys; ast.parse(open(sys.argv[1]).read())"])
            .arg(&a)
            .output()
        {
            assert!(
                out.status.success(),
                "{}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
    }

    #[test]
    fn bad_data_are_refused_naming_the_problem() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("g.py");
        let mut s = sample_strands();
        s.part[1] = 7;
        let e = write_blender_groom(&p, &s, &sample_mesh(), &info()).unwrap_err();
        assert!(e.to_string().contains("strand 1 has part 7"), "{e}");
        let mut s = sample_strands();
        s.points[0].x = f32::NAN;
        let e = write_blender_groom(&p, &s, &sample_mesh(), &info()).unwrap_err();
        assert!(e.to_string().contains("non-finite"), "{e}");
        let mut m = sample_mesh();
        m.triangles[0][0] = 9;
        let e = write_blender_groom(&p, &sample_strands(), &m, &info()).unwrap_err();
        assert!(e.to_string().contains("triangle 0"), "{e}");
        assert!(!p.exists());
    }
}
