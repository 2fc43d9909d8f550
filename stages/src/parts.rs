//! `parts`: per-vertex body-part labels p(i) and the protected set B (method.md section 2).
//!
//! The paper labels M_outer with ALIGN-Parts plus a manual check. Here labels
//! come from a labelled source and are transferred by nearest vertex:
//!
//! - input `labels`: an OBJ with one group per part (the synthetic scene's skin
//!   mesh, or a user's mesh painted in any DCC tool). Every vertex of `mesh`
//!   takes the part of the nearest vertex of `labels` (Euclidean, through
//!   [`crate::geom::PointIndex`]; ties go to the lower index, so the result is
//!   deterministic). The labelled mesh may have any resolution and may lie
//!   inside the target (a skin under a furry envelope): nearest *vertex* is
//!   what the method specifies and it is robust to that offset as long as the
//!   fur is thinner than the distance between parts.
//! - input `vertex_labels`: a JSON list of part names, one per vertex of `mesh`
//!   (same order), applied directly; for meshes labelled elsewhere.
//!
//! Exactly one of them must be connected. The output keeps `mesh`'s
//! positions, triangles and vertex order and sets `part`/`part_names`; part
//! names keep the source's order (the labelled OBJ's group order, or first
//! appearance in the list), and parts no vertex received are kept too, so
//! names and indices stay stable across meshes labelled from the same source.
//!
//! **Protected set.** Non-fur parts (eyes, nose, paw pads, horns, hooves) get
//! no roots and no defurring displacement. The set is the union of the
//! `protected` parameter (matched case-insensitively against the part names;
//! the default covers the synthetic scene's `eyes`, `nose`, `pads` and common
//! user spellings) and, when the optional `scene` input is connected, every
//! part whose `fur` flag is false in `scene.json`. The output `protected` is a
//! JSON list of the protected names that exist in the labelled mesh (spelled
//! as in the mesh), which `defur`, `lengths` and `roots` read.
//!
//! `metrics.json` reports per-part vertex counts and the transfer distance
//! (mean / 95th percentile / max, also relative to the mesh diagonal) so a
//! badly aligned label source shows up.
//!
//! **Bad input.** The labelled `mesh` is M_outer for the stages after this
//! one, so it gets the same checks as an imported mesh in `outer_surface`
//! ([`crate::outer_surface::import_closed_mesh`]): holes and edges shared by
//! more than two triangles are errors, an inside-out mesh is flipped and the
//! fix is listed in `metrics.json` `warnings`. A mesh on which every vertex
//! ends up in a protected part has no fur to reconstruct: that is an error
//! here, at the first stage that can tell, naming the parts and the
//! `protected` parameter, rather than an empty root set three stages later.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use fure_stage_api::{ParamSpec, Params, PortSpec, Stage, StageContext, StageError};
use rayon::prelude::*;
use serde::Serialize;

use crate::geom::PointIndex;
use crate::mesh::Mesh;
use crate::scene::SceneInfo;

/// Default protected (non-fur) part names, matched case-insensitively.
pub const DEFAULT_PROTECTED: &[&str] = &[
    "eyes",
    "eye",
    "eye_l",
    "eye_r",
    "left_eye",
    "right_eye",
    "nose",
    "nose_tip",
    "pads",
    "paw_pads",
    "horns",
    "horn",
    "hooves",
    "hoof",
];

/// Result of a label transfer.
#[derive(Debug, Clone, Serialize)]
pub struct TransferReport {
    pub mean_distance: f32,
    pub p95_distance: f32,
    pub max_distance: f32,
}

/// Labels `mesh` from `source` by nearest source vertex; returns the distance statistics.
pub fn transfer_nearest(mesh: &mut Mesh, source: &Mesh) -> Result<TransferReport, StageError> {
    if source.positions.is_empty() {
        return Err(StageError::failed("the labelled mesh has no vertices"));
    }
    if source.part_names.is_empty() {
        return Err(StageError::failed(
            "the labelled mesh has no part groups: expected an OBJ with one `g <part>` group per part",
        ));
    }
    let index = PointIndex::new(&source.positions)?;
    let found: Vec<(u16, f32)> = mesh
        .positions
        .par_iter()
        .map(|p| {
            let (j, _) = index.nearest(*p);
            (
                source.part.get(j).copied().unwrap_or(0),
                p.distance(source.positions[j]),
            )
        })
        .collect();
    mesh.part = found.iter().map(|f| f.0).collect();
    mesh.part_names = source.part_names.clone();
    let mut d: Vec<f32> = found.iter().map(|f| f.1).collect();
    d.sort_by(f32::total_cmp);
    let n = d.len().max(1);
    Ok(TransferReport {
        mean_distance: d.iter().sum::<f32>() / n as f32,
        p95_distance: d
            .get(((n as f32 * 0.95) as usize).min(n - 1))
            .copied()
            .unwrap_or(0.0),
        max_distance: d.last().copied().unwrap_or(0.0),
    })
}

/// Applies a per-vertex list of part names; names are numbered by first appearance.
pub fn apply_vertex_labels(
    mesh: &mut Mesh,
    labels: &[String],
    path: &Path,
) -> Result<(), StageError> {
    if labels.len() != mesh.positions.len() {
        return Err(StageError::input(
            "vertex_labels",
            path,
            format!(
                "{} labels for a mesh of {} vertices: expected one part name per vertex",
                labels.len(),
                mesh.positions.len()
            ),
        ));
    }
    let mut names: Vec<String> = Vec::new();
    let mut ids: BTreeMap<&str, u16> = BTreeMap::new();
    let mut part = Vec::with_capacity(labels.len());
    for (i, l) in labels.iter().enumerate() {
        if l.trim().is_empty() {
            return Err(StageError::input(
                "vertex_labels",
                path,
                format!("entry {i} is an empty part name"),
            ));
        }
        let id = match ids.get(l.as_str()) {
            Some(id) => *id,
            None => {
                if names.len() >= u16::MAX as usize {
                    return Err(StageError::input(
                        "vertex_labels",
                        path,
                        "more than 65535 distinct parts",
                    ));
                }
                let id = names.len() as u16;
                names.push(l.clone());
                ids.insert(l.as_str(), id);
                id
            }
        };
        part.push(id);
    }
    mesh.part = part;
    mesh.part_names = names;
    Ok(())
}

/// The protected names present in `part_names` (mesh spelling, mesh order).
pub fn protected_in(
    part_names: &[String],
    wanted: &[String],
    scene: Option<&SceneInfo>,
) -> Vec<String> {
    let mut set: BTreeSet<String> = wanted.iter().map(|s| s.to_lowercase()).collect();
    if let Some(sc) = scene {
        for (name, info) in &sc.parts {
            if !info.fur {
                set.insert(name.to_lowercase());
            }
        }
    }
    part_names
        .iter()
        .filter(|n| set.contains(&n.to_lowercase()))
        .cloned()
        .collect()
}

/// The `parts` stage.
pub struct PartsStage;

#[derive(Serialize)]
struct Metrics {
    source: &'static str,
    vertices: usize,
    parts: BTreeMap<String, usize>,
    protected: Vec<String>,
    protected_vertices: usize,
    #[serde(skip_serializing_if = "Option::is_none")]
    transfer: Option<TransferReport>,
    #[serde(skip_serializing_if = "Option::is_none")]
    transfer_mean_frac: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    transfer_p95_frac: Option<f32>,
    /// What was repaired in the input mesh (inside-out flipped, ...).
    warnings: Vec<String>,
}

impl Stage for PartsStage {
    fn kind(&self) -> &'static str {
        "parts"
    }
    fn version(&self) -> u32 {
        2
    }
    fn doc(&self) -> &'static str {
        "Per-vertex part labels for a mesh (e.g. M_outer), transferred by nearest vertex from a labelled \
         OBJ (one group per part, e.g. the synthetic skin) or given as a per-vertex JSON list of names; \
         plus the protected (non-fur) part set from the `protected` names and the scene's non-fur parts."
    }
    fn params(&self) -> Vec<ParamSpec> {
        vec![ParamSpec::str_list(
            "protected",
            DEFAULT_PROTECTED,
            "non-fur part names (case-insensitive; names absent from the mesh are ignored)",
        )]
    }
    fn inputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![
            PortSpec::file("mesh", "obj", "the mesh to label (e.g. M_outer)"),
            PortSpec::file(
                "labels",
                "obj",
                "labelled mesh, one OBJ group per part (e.g. the synthetic skin)",
            )
            .optional(),
            PortSpec::file(
                "vertex_labels",
                "json",
                "JSON list of part names, one per vertex of `mesh`",
            )
            .optional(),
            PortSpec::file(
                "scene",
                "json",
                "scene.json: parts with fur = false join the protected set",
            )
            .optional(),
        ]
    }
    fn outputs(&self, _: &Params) -> Vec<PortSpec> {
        vec![
            PortSpec::file("mesh", "obj", "the mesh with part groups"),
            PortSpec::file(
                "protected",
                "json",
                "JSON list of the protected part names present in the mesh",
            ),
            PortSpec::file(
                "metrics",
                "json",
                "per-part vertex counts, protected set, transfer distances",
            ),
        ]
    }
    fn run(&self, ctx: &StageContext<'_>) -> Result<(), StageError> {
        let mesh_path = ctx.input("mesh")?;
        let mut mesh = crate::formats::obj::read_obj(mesh_path).map_err(|e| e.for_input("mesh"))?;
        if mesh.positions.is_empty() {
            return Err(StageError::input(
                "mesh",
                mesh_path,
                "the mesh has no vertices",
            ));
        }
        let import = crate::outer_surface::import_closed_mesh(&mut mesh)
            .map_err(|e| StageError::input("mesh", mesh_path, e))?;
        for w in &import.warnings {
            ctx.progress.note(&format!("mesh: {w}"));
        }
        let (source, transfer) = match (ctx.input_opt("labels"), ctx.input_opt("vertex_labels")) {
            (Some(_), Some(_)) => {
                return Err(StageError::failed("connect either `labels` (OBJ) or `vertex_labels` (JSON), not both"))
            }
            (None, None) => {
                return Err(StageError::failed(
                    "connect `labels` (an OBJ with one group per part) or `vertex_labels` (JSON list of names)",
                ))
            }
            (Some(path), None) => {
                let src = crate::formats::obj::read_obj(path).map_err(|e| e.for_input("labels"))?;
                let rep = transfer_nearest(&mut mesh, &src).map_err(|e| StageError::input("labels", path, e))?;
                ("nearest_vertex", Some(rep))
            }
            (None, Some(path)) => {
                let labels: Vec<String> = crate::formats::json::read_json(path)?;
                apply_vertex_labels(&mut mesh, &labels, path)?;
                ("vertex_labels", None)
            }
        };
        let scene: Option<SceneInfo> = match ctx.input_opt("scene") {
            Some(p) => Some(crate::formats::json::read_json(p)?),
            None => None,
        };
        let wanted = ctx.params.str_list("protected")?;
        let protected = protected_in(&mesh.part_names, &wanted, scene.as_ref());
        let mut counts: BTreeMap<String, usize> =
            mesh.part_names.iter().map(|n| (n.clone(), 0)).collect();
        for &p in &mesh.part {
            if let Some(n) = mesh.part_names.get(p as usize) {
                *counts.entry(n.clone()).or_insert(0) += 1;
            }
        }
        let protected_vertices: usize = protected
            .iter()
            .map(|n| counts.get(n).copied().unwrap_or(0))
            .sum();
        if protected_vertices >= mesh.positions.len() {
            let labelled: Vec<&str> = counts
                .iter()
                .filter(|(_, c)| **c > 0)
                .map(|(n, _)| n.as_str())
                .collect();
            let (port, path) = match (ctx.input_opt("labels"), ctx.input_opt("vertex_labels")) {
                (Some(p), _) => ("labels", p),
                (_, Some(p)) => ("vertex_labels", p),
                _ => ("mesh", mesh_path),
            };
            return Err(StageError::input(
                port,
                path,
                format!(
                    "the mesh has no fur parts: every vertex is in a protected part ({}), so there is no fur to reconstruct; expected at least one part that is not in the `protected` parameter (nor `fur = false` in scene.json)",
                    labelled.join(", ")
                ),
            ));
        }
        let unknown: Vec<&String> = wanted
            .iter()
            .filter(|w| !mesh.part_names.iter().any(|n| n.eq_ignore_ascii_case(w)))
            .collect();
        ctx.progress.note(&format!(
            "parts: {} ({} protected: {}){}",
            mesh.part_names.len(),
            protected.len(),
            protected.join(", "),
            if unknown.len() == wanted.len() && !wanted.is_empty() {
                " - none of the `protected` names is a part of this mesh"
            } else {
                ""
            }
        ));
        let diag = mesh.diagonal().max(1e-12);
        let metrics = Metrics {
            source,
            vertices: mesh.positions.len(),
            parts: counts,
            protected: protected.clone(),
            protected_vertices,
            transfer_mean_frac: transfer.as_ref().map(|t| t.mean_distance / diag),
            transfer_p95_frac: transfer.as_ref().map(|t| t.p95_distance / diag),
            transfer,
            warnings: import.warnings,
        };
        if mesh.normals.len() != mesh.positions.len() {
            mesh.recompute_normals();
        }
        fure_stage_api::ensure_finite(
            "labelled mesh positions and normals",
            mesh.positions
                .iter()
                .chain(&mesh.normals)
                .flat_map(|p| p.to_array()),
        )?;
        crate::formats::obj::write_obj(ctx.output("mesh")?, &mesh)?;
        crate::formats::json::write_json(ctx.output("protected")?, &protected)?;
        crate::formats::json::write_json(ctx.output("metrics")?, &metrics)?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    /// A grid of points on the unit square split into left/right parts at x = 0.5.
    fn labelled_grid(n: usize) -> Mesh {
        let mut m = Mesh {
            part_names: vec!["left".into(), "right".into(), "eyes".into()],
            ..Default::default()
        };
        for j in 0..n {
            for i in 0..n {
                // Slightly off-lattice: exact lattices trip the k-d tree behind PointIndex.
                let wobble = 1e-4 * (((i * 7 + j * 13) % 11) as f32 - 5.0);
                let p = Vec3::new(
                    i as f32 / (n - 1) as f32 + wobble,
                    j as f32 / (n - 1) as f32 - wobble,
                    wobble * 0.5 + 1e-4 * ((i * 3 + j) % 5) as f32,
                );
                m.positions.push(p);
                m.part.push(if p.x < 0.5 { 0 } else { 1 });
            }
        }
        // A small "eye" region in the corner.
        for (i, p) in m.positions.iter().enumerate() {
            if p.x > 0.85 && p.y > 0.85 {
                m.part[i] = 2;
            }
        }
        m
    }

    #[test]
    fn nearest_vertex_transfer_follows_the_source_regions() {
        let src = labelled_grid(21);
        // Target: a finer, offset (e.g. fur-inflated) set of points.
        let mut tgt = Mesh::default();
        for j in 0..33 {
            for i in 0..33 {
                tgt.positions
                    .push(Vec3::new(i as f32 / 32.0, j as f32 / 32.0, 0.03));
            }
        }
        let rep = transfer_nearest(&mut tgt, &src).unwrap();
        assert_eq!(tgt.part_names, src.part_names);
        let mut wrong = 0;
        for (p, &l) in tgt.positions.iter().zip(&tgt.part) {
            let want = if p.x > 0.85 + 0.025 && p.y > 0.85 + 0.025 {
                2
            } else if p.x < 0.5 - 0.025 {
                0
            } else if p.x > 0.5 + 0.025 && !(p.x > 0.85 - 0.025 && p.y > 0.85 - 0.025) {
                1
            } else {
                l // within half a source spacing of a boundary: either is right
            };
            if l != want {
                wrong += 1;
            }
        }
        assert_eq!(wrong, 0);
        assert!(
            rep.max_distance < 0.05 && rep.mean_distance >= 0.03 - 1e-6,
            "{rep:?}"
        );
    }

    #[test]
    fn unlabelled_source_is_an_error() {
        let mut src = labelled_grid(5);
        src.part_names.clear();
        let mut tgt = labelled_grid(5);
        let err = transfer_nearest(&mut tgt, &src).unwrap_err().to_string();
        assert!(err.contains("no part groups"), "{err}");
    }

    #[test]
    fn vertex_label_lists_are_checked_and_applied() {
        let mut m = labelled_grid(3);
        let labels: Vec<String> = ["a", "b", "a", "c", "b", "a", "a", "a", "c"]
            .map(String::from)
            .to_vec();
        apply_vertex_labels(&mut m, &labels, Path::new("labels.json")).unwrap();
        assert_eq!(m.part_names, vec!["a", "b", "c"]);
        assert_eq!(m.part, vec![0, 1, 0, 2, 1, 0, 0, 0, 2]);
        let err = apply_vertex_labels(&mut m, &labels[..4], Path::new("labels.json"))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("labels.json") && err.contains("4 labels") && err.contains("9 vertices"),
            "{err}"
        );
    }

    #[test]
    fn protected_set_merges_names_and_scene_flags() {
        let names: Vec<String> = ["torso", "Eyes", "pads", "tail", "horns"]
            .map(String::from)
            .to_vec();
        let got = protected_in(&names, &["eyes".to_string(), "nose".to_string()], None);
        assert_eq!(got, vec!["Eyes"]);
        let scene: SceneInfo = serde_json::from_value(serde_json::json!({
            "s_cm": 50.0,
            "eyes": [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]],
            "parts": {
                "torso": {"fur": true},
                "pads": {"fur": false},
                "tail": {"fur": true}
            }
        }))
        .unwrap();
        let got = protected_in(&names, &["EYES".to_string()], Some(&scene));
        assert_eq!(got, vec!["Eyes", "pads"]);
        let defaults: Vec<String> = DEFAULT_PROTECTED.iter().map(|s| s.to_string()).collect();
        assert_eq!(
            protected_in(&names, &defaults, None),
            vec!["Eyes", "pads", "horns"]
        );
    }
}
