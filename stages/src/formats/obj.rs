//! Wavefront OBJ triangle meshes with vertex normals and per-vertex part labels.
//!
//! Part labels travel as OBJ groups: one `g <part name>` per part, the faces of that part after it.
//! A vertex's part is the group of the first face (in file order) that uses it. A file with no `g`
//! line but with `o` lines (Blender's default export) uses the objects as parts; a file with
//! neither is unlabelled (no part names, every `part` 0). Faces before the first group belong to a
//! part named `default` (the OBJ specification's default group). Vertices no face uses get part 0.
//!
//! Checked with Debian's Blender 3.4.1 (test `blender_imports_groups_when_available`, run when
//! `blender` is on the PATH): `wm.obj_import(import_vertex_groups=True)` keeps every vertex and
//! turns the groups into vertex groups named after the parts; the legacy `import_scene.obj` with
//! `use_split_groups=True` makes one object per part instead.
//!
//! Why our own parser and not `tobj`: `tobj` splits a file into one model per group, each with its
//! own renumbered vertex list, so a vertex shared by two parts would be duplicated and the global
//! vertex order lost; and its errors carry no line numbers. Ours keeps the file's vertex order
//! (a write/read round trip preserves vertex indices, which per-vertex scalar files rely on) and
//! reports `line:column` for every malformed entry.
//!
//! Reading accepts: `v x y z [w] [r g b]` (extra values ignored), `vn`, faces `f` with `v`, `v/vt`,
//! `v//vn` or `v/vt/vn` references, negative (relative) indices, and polygons (fan-triangulated
//! from their first vertex); `vt`, `l`, `p`, `s`, `usemtl`, `mtllib` and any other statements are
//! ignored. Normals: when every face reference names a normal and the normals are listed
//! one-to-one with the vertices (`f a//a ...`, what we write), they are taken as they are; otherwise
//! each vertex gets the normalised sum of the distinct normals its references name, and when faces
//! name no normals at all (or a vertex has none) area-weighted normals are computed from the
//! triangles ([`Mesh::recompute_normals`]).
//!
//! Writing: a `#` header line, `v` lines (Rust's shortest round-trip `{}` float formatting), `vn`
//! lines, then the faces as `f a//a b//b c//c`. With part names, every part gets a `g` line in
//! part order (an empty group for a part without faces, so names and their order survive) and a
//! face goes to the part most of its vertices have (ties: the part of its first vertex). Triangles
//! are therefore written grouped by part, keeping their order within a part. Per-vertex labels do
//! not always follow from face groups (a boundary vertex whose every face has a majority of another
//! part); the writer simulates the reader and, only when some vertex would read back differently,
//! appends the exact labels as run-length comment lines `# fure-vertex-parts <first> <count>
//! <part>` (0-based; other programs ignore comments, our reader applies them). So a mesh whose
//! triangles are already grouped by part reads back identical (`==`), and any mesh reads back with
//! identical positions, normals, labels and part names, with its triangles grouped by part.

use std::fmt::Write as _;
use std::path::Path;

use fure_stage_api::{StageContext, StageError};
use glam::Vec3;

use super::{check_finite, read_bytes, write_bytes, FormatError, Position};
use crate::data::mesh::Mesh;

const LABEL_COMMENT: &str = "# fure-vertex-parts";

/// Reads an OBJ file (see the module doc).
pub fn read_obj(path: impl AsRef<Path>) -> Result<Mesh, FormatError> {
    let path = path.as_ref();
    let bytes = read_bytes(path)?;
    let text = String::from_utf8_lossy(&bytes);
    parse(path, &text)
}

/// Reads a mesh input, naming the port on failure.
pub fn read_mesh(ctx: &StageContext<'_>, port: &str) -> Result<Mesh, StageError> {
    let path = ctx.input(port)?;
    let mesh = read_obj(path)?;
    if mesh.positions.is_empty() || mesh.triangles.is_empty() {
        return Err(StageError::input(
            port,
            path,
            "the mesh has no vertices or no triangles",
        ));
    }
    Ok(mesh)
}

/// Reads a mesh input that must carry one part label per vertex.
pub fn read_labelled_mesh(ctx: &StageContext<'_>, port: &str) -> Result<Mesh, StageError> {
    let mesh = read_mesh(ctx, port)?;
    if mesh.part.len() != mesh.positions.len() {
        return Err(StageError::input(
            port,
            ctx.input(port)?,
            "part labels do not match the vertices",
        ));
    }
    Ok(mesh)
}

/// A face corner: vertex index and optional normal index, both 0-based.
#[derive(Clone, Copy)]
struct Corner {
    v: usize,
    n: Option<usize>,
}

struct Face {
    corners: [Corner; 3],
    group: usize,
    line: usize,
}

/// What the statements of an OBJ file say, before parts are decided.
#[derive(Default)]
struct Statements {
    positions: Vec<Vec3>,
    normals: Vec<Vec3>,
    faces: Vec<Face>,
    // Group and object names in order of first appearance, and which is current.
    g_names: Vec<String>,
    o_names: Vec<String>,
    cur_g: Option<usize>,
    cur_o: Option<usize>,
    // Faces remember both their group and object; which one names parts is decided at the end.
    face_g: Vec<Option<usize>>,
    face_o: Vec<Option<usize>>,
    /// `# fure-vertex-parts` runs: first, count, part, line.
    label_runs: Vec<(usize, usize, usize, usize)>,
}

fn parse(path: &Path, text: &str) -> Result<Mesh, FormatError> {
    let mut st = Statements::default();
    for (li, raw_line) in text.lines().enumerate() {
        st.read_line(path, li + 1, raw_line.trim_end_matches('\r'))?;
    }
    let Statements {
        positions,
        normals,
        mut faces,
        g_names,
        o_names,
        face_g,
        face_o,
        label_runs,
        ..
    } = st;
    check_indices(path, &faces, positions.len(), normals.len())?;

    // Part names: groups if the file has any, else objects, else none.
    let (names, per_face) = if !g_names.is_empty() {
        (g_names, face_g)
    } else {
        (o_names, face_o)
    };
    let mut part_names = names;
    let labelled = !part_names.is_empty() || !label_runs.is_empty();
    if labelled && per_face.iter().any(Option::is_none) {
        // Faces before the first group statement: the OBJ default group.
        let idx = name_index(&mut part_names, "default");
        for (f, g) in faces.iter_mut().zip(&per_face) {
            f.group = g.unwrap_or(idx);
        }
    } else {
        for (f, g) in faces.iter_mut().zip(&per_face) {
            f.group = g.unwrap_or(0);
        }
    }

    let nv = positions.len();
    let part = if labelled {
        vertex_parts(path, &faces, nv, &part_names, &label_runs)?
    } else {
        vec![0u16; nv]
    };

    let triangles: Vec<[u32; 3]> = faces
        .iter()
        .map(|f| f.corners.map(|c| c.v as u32))
        .collect();
    if nv > u32::MAX as usize {
        return Err(FormatError::invalid(path, "more than 2^32 - 1 vertices"));
    }
    let mut mesh = Mesh {
        positions,
        normals: Vec::new(),
        triangles,
        part,
        part_names,
    };
    mesh.normals = vertex_normals(&mesh, &faces, &normals);
    Ok(mesh)
}

/// The index of `name` in `names`, appended when absent.
fn name_index(names: &mut Vec<String>, name: &str) -> usize {
    match names.iter().position(|n| n == name) {
        Some(i) => i,
        None => {
            names.push(name.to_string());
            names.len() - 1
        }
    }
}

impl Statements {
    /// Reads one line (without its line end).
    fn read_line(&mut self, path: &Path, line_no: usize, line: &str) -> Result<(), FormatError> {
        if let Some(rest) = line.strip_prefix(LABEL_COMMENT) {
            let nums: Vec<Option<usize>> =
                rest.split_whitespace().map(|t| t.parse().ok()).collect();
            return match nums.as_slice() {
                [Some(a), Some(b), Some(c)] => {
                    self.label_runs.push((*a, *b, *c, line_no));
                    Ok(())
                }
                _ => Err(FormatError::at(
                    path,
                    Position::Line(line_no),
                    "expected `# fure-vertex-parts <first> <count> <part>` with three non-negative integers",
                )),
            };
        }
        let content = match line.find('#') {
            Some(i) => &line[..i],
            None => line,
        };
        let mut tokens = Tokens::new(content);
        let Some((keyword, _)) = tokens.next() else {
            return Ok(());
        };
        let at = |column: usize| Position::LineColumn {
            line: line_no,
            column,
        };
        let mut float = |what: &str| -> Result<f32, FormatError> {
            match tokens.next() {
                Some((t, col)) => {
                    t.parse::<f32>()
                        .ok()
                        .filter(|v| v.is_finite())
                        .ok_or_else(|| {
                            FormatError::at(
                                path,
                                at(col),
                                format!("expected a finite number for {what}, found `{t}`"),
                            )
                        })
                }
                None => Err(FormatError::at(
                    path,
                    at(content.len() + 1),
                    format!("line ends early: expected {what}"),
                )),
            }
        };
        match keyword {
            "v" => {
                let p = Vec3::new(float("x")?, float("y")?, float("z")?);
                self.positions.push(p);
            }
            "vn" => {
                let n = Vec3::new(float("normal x")?, float("normal y")?, float("normal z")?);
                self.normals.push(n);
            }
            "g" | "o" => {
                let name = content.trim_start()[1..].trim();
                let name = if name.is_empty() { "default" } else { name };
                if keyword == "g" {
                    self.cur_g = Some(name_index(&mut self.g_names, name));
                } else {
                    self.cur_o = Some(name_index(&mut self.o_names, name));
                }
            }
            "f" => self.read_face(path, line_no, tokens)?,
            _ => {} // vt, vp, l, p, s, usemtl, mtllib, curves...: not ours.
        }
        Ok(())
    }

    /// An `f` statement's corners (after the keyword), fan-triangulated.
    fn read_face(
        &mut self,
        path: &Path,
        line_no: usize,
        tokens: Tokens<'_>,
    ) -> Result<(), FormatError> {
        let mut corners: Vec<Corner> = Vec::with_capacity(4);
        for (t, col) in tokens {
            corners.push(parse_corner(
                path,
                t,
                line_no,
                col,
                self.positions.len(),
                self.normals.len(),
            )?);
        }
        if corners.len() < 3 {
            return Err(FormatError::at(
                path,
                Position::Line(line_no),
                format!("a face needs at least 3 vertices, found {}", corners.len()),
            ));
        }
        for k in 1..corners.len() - 1 {
            self.faces.push(Face {
                corners: [corners[0], corners[k], corners[k + 1]],
                group: 0,
                line: line_no,
            });
            self.face_g.push(self.cur_g);
            self.face_o.push(self.cur_o);
        }
        Ok(())
    }
}

/// Validates the faces' indices (forward references are tolerated while
/// reading, checked here).
fn check_indices(path: &Path, faces: &[Face], nv: usize, nn: usize) -> Result<(), FormatError> {
    for f in faces {
        for c in f.corners {
            if c.v >= nv {
                return Err(FormatError::at(
                    path,
                    Position::Line(f.line),
                    format!(
                        "face uses vertex {} but the file has {} vertices",
                        c.v + 1,
                        nv
                    ),
                ));
            }
            if let Some(n) = c.n {
                if n >= nn {
                    return Err(FormatError::at(
                        path,
                        Position::Line(f.line),
                        format!("face uses normal {} but the file has {} normals", n + 1, nn),
                    ));
                }
            }
        }
    }
    Ok(())
}

/// Per-vertex parts of a labelled file: the group of the first face using
/// the vertex, then the `# fure-vertex-parts` runs.
fn vertex_parts(
    path: &Path,
    faces: &[Face],
    nv: usize,
    part_names: &[String],
    label_runs: &[(usize, usize, usize, usize)],
) -> Result<Vec<u16>, FormatError> {
    let mut part = vec![0u16; nv];
    if part_names.len() > u16::MAX as usize + 1 {
        return Err(FormatError::invalid(path, "more than 65536 groups"));
    }
    let mut seen = vec![false; nv];
    for f in faces {
        for c in f.corners {
            if !seen[c.v] {
                seen[c.v] = true;
                part[c.v] = f.group as u16;
            }
        }
    }
    for &(first, count, p, line) in label_runs {
        if first.checked_add(count).is_none_or(|e| e > nv) || p >= part_names.len().max(1) {
            return Err(FormatError::at(
                path,
                Position::Line(line),
                format!(
                    "label run {first}+{count} -> part {p} is out of range ({nv} vertices, {} parts): \
                     the `# fure-vertex-parts` lines fure wrote no longer match the file's \
                     vertices or groups (edited by hand?); delete those lines and the groups \
                     label the vertices",
                    part_names.len()
                ),
            ));
        }
        part[first..first + count].fill(p as u16);
    }
    Ok(part)
}

/// Per-vertex normals from the file's normals and the faces' references (see the module doc).
fn vertex_normals(mesh: &Mesh, faces: &[Face], normals: &[Vec3]) -> Vec<Vec3> {
    let nv = mesh.positions.len();
    let all_named = !faces.is_empty()
        && faces
            .iter()
            .all(|f| f.corners.iter().all(|c| c.n.is_some()));
    let aligned = all_named
        && normals.len() == nv
        && faces
            .iter()
            .all(|f| f.corners.iter().all(|c| c.n == Some(c.v)));
    if aligned {
        return normals.to_vec();
    }
    let mut computed = mesh.clone();
    computed.recompute_normals();
    let mut out = computed.normals;
    if faces
        .iter()
        .all(|f| f.corners.iter().all(|c| c.n.is_none()))
    {
        return out;
    }
    // Distinct normal ids per vertex, first one and a running sum of the distinct ones.
    let mut first: Vec<Option<usize>> = vec![None; nv];
    let mut sum = vec![Vec3::ZERO; nv];
    let mut mixed = vec![false; nv];
    let mut ids: Vec<Vec<usize>> = vec![Vec::new(); nv];
    for f in faces {
        for c in f.corners {
            if let Some(n) = c.n {
                if !ids[c.v].contains(&n) {
                    ids[c.v].push(n);
                    sum[c.v] += normals[n].normalize_or_zero();
                    match first[c.v] {
                        None => first[c.v] = Some(n),
                        Some(_) => mixed[c.v] = true,
                    }
                }
            }
        }
    }
    for i in 0..nv {
        match first[i] {
            Some(n) if !mixed[i] => out[i] = normals[n],
            Some(_) => {
                if let Some(s) = sum[i].try_normalize() {
                    out[i] = s;
                }
            }
            None => {}
        }
    }
    out
}

fn parse_corner(
    path: &Path,
    t: &str,
    line: usize,
    col: usize,
    nv: usize,
    nn: usize,
) -> Result<Corner, FormatError> {
    let bad = |what: &str| {
        FormatError::at(
            path,
            Position::LineColumn { line, column: col },
            format!(
                "expected a face vertex `v`, `v/vt`, `v//vn` or `v/vt/vn`, found `{t}` ({what})"
            ),
        )
    };
    let mut parts = t.split('/');
    let resolve = |s: &str, count: usize, what: &str| -> Result<usize, FormatError> {
        let i: i64 = s
            .parse()
            .map_err(|_| bad(&format!("{what} index is not an integer")))?;
        if i > 0 {
            Ok(i as usize - 1)
        } else if i < 0 && i.unsigned_abs() <= count as u64 {
            Ok((count as i64 + i) as usize)
        } else {
            Err(bad(&format!("{what} index {i} is out of range")))
        }
    };
    let v = resolve(parts.next().unwrap_or(""), nv, "vertex")?;
    if let Some(vt) = parts.next() {
        if !vt.is_empty() && vt.parse::<i64>().is_err() {
            return Err(bad("texture index is not an integer"));
        }
    }
    let n = match parts.next() {
        Some("") | None => None,
        Some(s) => Some(resolve(s, nn, "normal")?),
    };
    if parts.next().is_some() {
        return Err(bad("too many `/`"));
    }
    Ok(Corner { v, n })
}

/// Whitespace-separated tokens with their 1-based columns.
struct Tokens<'a> {
    s: &'a str,
    pos: usize,
}

impl<'a> Tokens<'a> {
    fn new(s: &'a str) -> Self {
        Tokens { s, pos: 0 }
    }
}

impl<'a> Iterator for Tokens<'a> {
    type Item = (&'a str, usize);
    fn next(&mut self) -> Option<(&'a str, usize)> {
        let b = self.s.as_bytes();
        while self.pos < b.len() && b[self.pos].is_ascii_whitespace() {
            self.pos += 1;
        }
        if self.pos >= b.len() {
            return None;
        }
        let start = self.pos;
        while self.pos < b.len() && !b[self.pos].is_ascii_whitespace() {
            self.pos += 1;
        }
        Some((&self.s[start..self.pos], start + 1))
    }
}

/// Writes an OBJ file (see the module doc).
pub fn write_obj(path: impl AsRef<Path>, mesh: &Mesh) -> Result<(), FormatError> {
    let path = path.as_ref();
    let text = encode(path, mesh)?;
    write_bytes(path, text.as_bytes())
}

/// The OBJ text of `mesh`: vertices, normals, faces grouped by part and, where the groups do not
/// imply the exact vertex labels, the label runs.
fn encode(path: &Path, mesh: &Mesh) -> Result<String, FormatError> {
    check_writable(path, mesh)?;
    let nv = mesh.positions.len();
    let has_normals = !mesh.normals.is_empty();
    let mut s = String::with_capacity(nv * 64 + mesh.triangles.len() * 32);
    let _ = writeln!(
        s,
        "# fure mesh: {nv} vertices, {} triangles, {} parts",
        mesh.triangles.len(),
        mesh.part_names.len()
    );
    for p in &mesh.positions {
        let _ = writeln!(s, "v {} {} {}", p.x, p.y, p.z);
    }
    for n in &mesh.normals {
        let _ = writeln!(s, "vn {} {} {}", n.x, n.y, n.z);
    }
    if mesh.part_names.is_empty() {
        for t in &mesh.triangles {
            write_face(&mut s, t, has_normals);
        }
        return Ok(s);
    }
    let inferred = write_groups(&mut s, mesh, has_normals);
    if inferred != mesh.part {
        write_label_runs(&mut s, &mesh.part);
    }
    Ok(s)
}

/// Refuses meshes an OBJ cannot faithfully hold: mismatched normals, out-of-range indices,
/// non-finite coordinates, and (when labelled) bad labels or part names.
fn check_writable(path: &Path, mesh: &Mesh) -> Result<(), FormatError> {
    let nv = mesh.positions.len();
    let has_normals = !mesh.normals.is_empty();
    if has_normals && mesh.normals.len() != nv {
        return Err(FormatError::invalid(
            path,
            format!("{} normals for {nv} vertices", mesh.normals.len()),
        ));
    }
    if let Some((t, tri)) = mesh
        .triangles
        .iter()
        .enumerate()
        .find(|(_, t)| t.iter().any(|&i| i as usize >= nv))
    {
        return Err(FormatError::invalid(
            path,
            format!("triangle {t} {tri:?} uses a vertex index >= {nv}"),
        ));
    }
    check_finite(
        path,
        "vertex coordinate",
        mesh.positions.iter().flat_map(|p| p.to_array()),
    )?;
    check_finite(
        path,
        "normal coordinate",
        mesh.normals.iter().flat_map(|p| p.to_array()),
    )?;
    if !mesh.part_names.is_empty() {
        check_labels(path, mesh)?;
    }
    Ok(())
}

/// Refuses part labels that are missing or beyond the names, and part names that cannot be OBJ
/// group names.
fn check_labels(path: &Path, mesh: &Mesh) -> Result<(), FormatError> {
    if let Some(problem) = mesh.part_label_problem() {
        return Err(FormatError::invalid(path, problem));
    }
    for (k, name) in mesh.part_names.iter().enumerate() {
        if name.is_empty()
            || name.trim() != name
            || name.contains(['\n', '\r', '#'])
            || mesh.part_names[..k].contains(name)
        {
            return Err(FormatError::invalid(
                path,
                format!(
                    "part name {name:?} cannot be an OBJ group name (must be non-empty, unique, \
                     without surrounding spaces, line breaks or `#`)"
                ),
            ));
        }
    }
    Ok(())
}

/// Writes the `f` line of triangle `t` (1-based indices, with `//n` normal indices if any).
fn write_face(s: &mut String, t: &[u32; 3], has_normals: bool) {
    let [a, b, c] = t.map(|i| i + 1);
    let _ = if has_normals {
        writeln!(s, "f {a}//{a} {b}//{b} {c}//{c}")
    } else {
        writeln!(s, "f {a} {b} {c}")
    };
}

/// Writes the faces in one `g <part>` group per part (a triangle goes to the part of its first
/// vertex, or of the other two when they agree) and returns the vertex labels a reader will infer
/// from them (the group of the first face using each vertex).
fn write_groups(s: &mut String, mesh: &Mesh, has_normals: bool) -> Vec<u16> {
    let nv = mesh.positions.len();
    let groups: Vec<usize> = mesh
        .triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| mesh.part[i as usize]);
            (if b == c && a != b { b } else { a }) as usize
        })
        .collect();
    let mut by_group: Vec<Vec<usize>> = vec![Vec::new(); mesh.part_names.len()];
    for (t, &g) in groups.iter().enumerate() {
        by_group[g].push(t);
    }
    let mut inferred = vec![0u16; nv];
    let mut seen = vec![false; nv];
    for (g, (name, tris)) in mesh.part_names.iter().zip(&by_group).enumerate() {
        let _ = writeln!(s, "g {name}");
        for &t in tris {
            let tri = &mesh.triangles[t];
            write_face(s, tri, has_normals);
            for &i in tri {
                if !seen[i as usize] {
                    seen[i as usize] = true;
                    inferred[i as usize] = g as u16;
                }
            }
        }
    }
    inferred
}

/// Spells out the exact vertex labels as runs: `<LABEL_COMMENT> <first> <count> <part>`.
fn write_label_runs(s: &mut String, part: &[u16]) {
    let nv = part.len();
    let mut i = 0;
    while i < nv {
        let p = part[i];
        let mut j = i + 1;
        while j < nv && part[j] == p {
            j += 1;
        }
        let _ = writeln!(s, "{LABEL_COMMENT} {i} {} {p}", j - i);
        i = j;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A unit cube split into two parts (bottom = "belly", top = "back"), triangles grouped.
    fn cube() -> Mesh {
        let positions: Vec<Vec3> = (0..8)
            .map(|i| {
                Vec3::new(
                    (i & 1) as f32,
                    ((i >> 1) & 1) as f32,
                    ((i >> 2) & 1) as f32 * 0.1 + 1e-7,
                )
            })
            .collect();
        let quads = [
            [0, 2, 3, 1], // z = 0 (bottom)
            [0, 1, 5, 4],
            [1, 3, 7, 5],
            [4, 5, 7, 6], // z = 1 (top)
            [2, 6, 7, 3],
            [0, 4, 6, 2],
        ];
        let mut triangles = Vec::new();
        for q in quads {
            triangles.push([q[0], q[1], q[2]]);
            triangles.push([q[0], q[2], q[3]]);
        }
        let part: Vec<u16> = (0..8).map(|i| if i < 4 { 0 } else { 1 }).collect();
        let mut m = Mesh {
            positions,
            normals: Vec::new(),
            triangles,
            part,
            part_names: vec!["belly".into(), "back".into()],
        };
        m.recompute_normals();
        // Group triangles by the writer's rule so that the round trip is `==`.
        let key = |t: &[u32; 3]| {
            let [a, b, c] = t.map(|i| m.part[i as usize]);
            if b == c && a != b {
                b
            } else {
                a
            }
        };
        let mut tris = m.triangles.clone();
        tris.sort_by_key(key);
        m.triangles = tris;
        m
    }

    #[test]
    fn round_trip_exact() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m/cube.obj");
        let m = cube();
        write_obj(&p, &m).unwrap();
        let back = read_obj(&p).unwrap();
        assert_eq!(back, m);
        let bytes = std::fs::read(&p).unwrap();
        write_obj(&p, &back).unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), bytes);
        // Unlabelled.
        let mut u = m.clone();
        u.part_names.clear();
        u.part.iter_mut().for_each(|p| *p = 0);
        write_obj(&p, &u).unwrap();
        assert!(!std::fs::read_to_string(&p).unwrap().contains("\ng "));
        assert_eq!(read_obj(&p).unwrap(), u);
    }

    #[test]
    fn labels_not_implied_by_groups_are_spelled_out() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("odd.obj");
        let mut m = cube();
        // Vertex 7 labelled "tail": no face using it has a majority of tail vertices.
        m.part[7] = 2;
        m.part_names.push("tail".into());
        // An empty fourth part keeps its name and place.
        m.part_names.push("whiskers".into());
        m.triangles.reverse();
        write_obj(&p, &m).unwrap();
        let text = std::fs::read_to_string(&p).unwrap();
        assert!(text.contains(LABEL_COMMENT), "{text}");
        assert!(text.contains("g tail\ng whiskers\n"), "{text}");
        let back = read_obj(&p).unwrap();
        assert_eq!(back.part, m.part);
        assert_eq!(back.part_names, m.part_names);
        assert_eq!(back.positions, m.positions);
        assert_eq!(back.normals, m.normals);
        let mut a = back.triangles.clone();
        let mut b = m.triangles.clone();
        a.sort();
        b.sort();
        assert_eq!(a, b);
        // Idempotent after the first write.
        let bytes = std::fs::read(&p).unwrap();
        write_obj(&p, &back).unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), bytes);
    }

    #[test]
    fn foreign_obj_with_quads_negative_indices_and_objects() {
        let text = "# Blender export\nmtllib x.mtl\no Body\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0 1.0 0.5 0.5 0.5\n\
                    vt 0 0\nvn 0 0 2\nusemtl skin\ns off\nf 1/1/1 2/1/1 3/1/1 4/1/1\no Ear\nv 0 0 1\nv 1 0 1\n\
                    f -2 -1 -3\nl 1 2\n";
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("f.obj");
        std::fs::write(&p, text).unwrap();
        let m = read_obj(&p).unwrap();
        assert_eq!(m.positions.len(), 6);
        assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3], [4, 5, 3]]);
        assert_eq!(m.part_names, vec!["Body".to_string(), "Ear".to_string()]);
        assert_eq!(m.part, vec![0, 0, 0, 0, 1, 1]);
        // Vertices 0..4 name the same (non-unit) normal: kept as given; 4, 5 get computed ones.
        assert_eq!(m.normals[0], Vec3::new(0.0, 0.0, 2.0));
        assert!((m.normals[4].length() - 1.0).abs() < 1e-5);
        // Groups take precedence over objects; faces before the first group are "default".
        let text2 = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\ng paw\nf 2 4 3\n";
        std::fs::write(&p, text2).unwrap();
        let m = read_obj(&p).unwrap();
        assert_eq!(m.part_names, vec!["paw".to_string(), "default".to_string()]);
        assert_eq!(m.part, vec![1, 1, 1, 0]);
        // Windows line endings and a polygon with a trailing comment.
        std::fs::write(
            &p,
            "g a\r\nv 0 0 0\r\nv 1 0 0\r\nv 0 1 0\r\nv 1 1 0\r\nf 1 2 4 3 # quad\r\n",
        )
        .unwrap();
        let m = read_obj(&p).unwrap();
        assert_eq!(m.triangles, vec![[0, 1, 3], [0, 3, 2]]);
        assert_eq!(m.part_names, vec!["a".to_string()]);
        // No groups at all: unlabelled, computed normals along +z.
        std::fs::write(&p, "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n").unwrap();
        let m = read_obj(&p).unwrap();
        assert!(m.part_names.is_empty());
        assert_eq!(m.normals[0], Vec3::Z);
    }

    #[test]
    fn malformed_lines_name_line_and_column() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("bad.obj");
        let cases: &[(&str, Position)] = &[
            (
                "v 0 0 0\nv 1 x 0\n",
                Position::LineColumn { line: 2, column: 5 },
            ),
            (
                "v 0 0 0\nv 1 0\n",
                Position::LineColumn { line: 2, column: 6 },
            ),
            ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", Position::Line(4)),
            ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", Position::Line(4)),
            (
                "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2/a 3\n",
                Position::LineColumn { line: 4, column: 5 },
            ),
            (
                "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -4\n",
                Position::LineColumn { line: 4, column: 7 },
            ),
            (
                "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1//2 2//1 3//1\nvn 0 0 1\n",
                Position::Line(4),
            ),
            ("v 0 0 0\n# fure-vertex-parts 0 5 0\n", Position::Line(2)),
            // The most negative index: an error, not an overflow (found by fuzz_obj_tokens).
            (
                "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -9223372036854775808\n",
                Position::LineColumn { line: 4, column: 7 },
            ),
        ];
        for (text, pos) in cases {
            std::fs::write(&p, text).unwrap();
            let e = read_obj(&p).unwrap_err();
            assert_eq!(e.position(), Some(pos), "{text:?}: {e}");
            assert!(e.to_string().contains("bad.obj"));
        }
        // A file cut mid-number still parses as far as it goes, and then fails on the face.
        write_obj(&p, &cube()).unwrap();
        let t = std::fs::read_to_string(&p).unwrap();
        let cut = t.find("\nf ").unwrap() + 8;
        std::fs::write(&p, &t[..cut]).unwrap();
        assert!(read_obj(&p).is_err());
    }

    /// Imports our OBJ into Blender (headless) when `blender` is on the PATH: the vertex count is
    /// kept and the groups become vertex groups named after the parts. Skipped without Blender or
    /// with FURE_SKIP_BLENDER=1.
    #[test]
    fn blender_imports_groups_when_available() {
        if std::env::var_os("FURE_SKIP_BLENDER").is_some() {
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        let m = cube();
        let obj = dir.path().join("m.obj");
        write_obj(&obj, &m).unwrap();
        let script = dir.path().join("check.py");
        std::fs::write(
            &script,
            format!(
                "import bpy\n\
                 for o in list(bpy.data.objects): bpy.data.objects.remove(o, do_unlink=True)\n\
                 bpy.ops.wm.obj_import(filepath={:?}, import_vertex_groups=True)\n\
                 o = bpy.context.selected_objects[0]\n\
                 print('FURE_RESULT', len(o.data.vertices), len(o.data.polygons), *[g.name for g in o.vertex_groups])\n",
                obj.to_str().unwrap()
            ),
        )
        .unwrap();
        let Ok(out) = std::process::Command::new("blender")
            .args(["-b", "--factory-startup", "--python"])
            .arg(&script)
            .output()
        else {
            eprintln!("blender not found: skipping the Blender import check");
            return;
        };
        let stdout = String::from_utf8_lossy(&out.stdout);
        let line = stdout
            .lines()
            .find(|l| l.starts_with("FURE_RESULT"))
            .unwrap_or_else(|| panic!("no result from Blender:\n{stdout}"));
        let words: Vec<&str> = line.split_whitespace().skip(1).collect();
        let expect_n = [m.positions.len().to_string(), m.triangles.len().to_string()];
        assert_eq!(&words[..2], &expect_n);
        assert_eq!(&words[2..], &["belly", "back"]);
    }

    #[test]
    fn unwritable_meshes_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("u.obj");
        let mut m = cube();
        m.part_names[1] = "belly".into();
        assert!(write_obj(&p, &m).is_err());
        let mut m = cube();
        m.triangles[0][1] = 99;
        assert!(write_obj(&p, &m).is_err());
        let mut m = cube();
        m.positions[0].x = f32::NAN;
        assert!(write_obj(&p, &m).is_err());
        assert!(!p.exists());
    }
}
